"""A world the simulated scanner moves through: walls, boxes, floor and ceiling, and the poses it scans from.

Read from a TOML world file (``docs/worlds.md``) into frozen dataclasses by
:func:`load_world` / :func:`parse_world`; every error is one line naming the
key and the fix.  World frame: x and y on the floor, z up, metres; headings
and yaws counter-clockwise from +x, degrees in the file and radians here.

``world = load_world("examples/worlds/maze.toml")`` then ``world.poses``, ``world.walls`` …
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from lelsonar.errors import ConfigError
from lelsonar.geometry import CAPSULE_PITCH_M

#: Mounts of the scanner on the robot (``[scanner] mount``).
MOUNTS = ("fan", "paper")
#: Default wall height without a ceiling, m.
DEFAULT_WALL_HEIGHT = 2.5
#: Farthest a wall endpoint may be from the origin, m (a sanity bound, not a physical one).
MAX_EXTENT = 1000.0
#: Most walls, boxes and poses one world may hold (bounded tables keyed by file data).
MAX_WALLS, MAX_BOXES, MAX_POSES = 2000, 500, 10_000
#: The AX-12 turns 300°; its raw position 1023 is 149.7° from the centre.
AX12_HALF_RANGE_DEG = 149.7

_TABLES = {"world", "room", "wall", "box", "scanner", "pose", "odometry", "acoustics"}


@dataclass(frozen=True)
class Room:
    """Horizontal planes: the floor (always) and an optional ceiling (heights in m, reflectivities in (0, 1])."""

    floor: float = 0.0
    ceiling: float | None = None
    floor_reflectivity: float = 0.95
    ceiling_reflectivity: float = 0.95


@dataclass(frozen=True)
class Wall:
    """A vertical wall between two floor points, both sides reflecting.

    Attributes
    ----------
    start, end : (x, y)
        Floor points, m (the file's ``from`` and ``to``).
    height : float
        m, from ``bottom`` up.
    bottom : float
        m above the floor (0: standing on it; > 0: a lintel or a shelf).
    reflectivity : float
        Amplitude reflection coefficient in (0, 1].
    name : str
    """

    start: tuple[float, float]
    end: tuple[float, float]
    height: float
    bottom: float = 0.0
    reflectivity: float = 0.95
    name: str = ""

    @property
    def length(self) -> float:
        return math.dist(self.start, self.end)


@dataclass(frozen=True)
class Box:
    """A box standing on the floor; its four sides and its top reflect.

    Attributes
    ----------
    center : (x, y)
        Floor position of its centre, m.
    size : (sx, sy, sz)
        Extent along its own x (after ``yaw``), y, and its height, m.
    yaw : float
        rad, counter-clockwise from +x.
    reflectivity : float
    name : str
    """

    center: tuple[float, float]
    size: tuple[float, float, float]
    yaw: float = 0.0
    reflectivity: float = 0.95
    name: str = ""

    def footprint(self) -> tuple[tuple[float, float], ...]:
        """The four floor corners, counter-clockwise."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        hx, hy = self.size[0] / 2, self.size[1] / 2
        out = []
        for u, v in ((-hx, -hy), (hx, -hy), (hx, hy), (-hx, hy)):
            out.append((self.center[0] + c * u - s * v, self.center[1] + s * u + c * v))
        return tuple(out)


@dataclass(frozen=True)
class ScannerMount:
    """How the scanner sits on the robot and what one sweep is.

    Attributes
    ----------
    mount : {"fan", "paper"}
        ``fan``: rotation axis vertical, a horizontal fan; the capsules stack
        vertically, γ = 0 looks ahead and γ grows counter-clockwise seen from
        above.  ``paper``: rotation axis horizontal (to the robot's right), a
        vertical fan; γ = 0 looks ahead and γ = 90° straight up.
    height : float
        Rotation axis (centre of the capsule stack) above the floor, m.
    sweep_start, sweep_stop : float
        One sweep, rad; at most the AX-12's 300°.
    steps : int
        Shots per sweep.
    radial_offset : float
        Capsule faces from the rotation axis, m.
    max_range : float
        Farthest echo the waveform window holds, m.
    tilt : float
        rad: the mount turned about the robot's lateral axis, the γ = 0 beam raised above ahead by this much
        (negative: looking down); 0 for a level mount.
    beam_width : float or None
        rad: the capsules' echo beam, the full angle at which a mirror's echo falls to half its face-on
        amplitude (:func:`lelsonar.sim.acoustics.capsule_radius_for_beam_width`); None for the simulator's
        capsule.
    """

    mount: str = "fan"
    height: float = 0.3
    sweep_start: float = math.radians(-AX12_HALF_RANGE_DEG)
    sweep_stop: float = math.radians(AX12_HALF_RANGE_DEG)
    steps: int = 300
    radial_offset: float = 0.03
    max_range: float = 4.0
    tilt: float = 0.0
    beam_width: float | None = None


@dataclass(frozen=True)
class Pose2:
    """Where the robot stops and scans: floor position (m) and heading (rad, counter-clockwise from +x)."""

    x: float
    y: float
    heading: float


@dataclass(frozen=True)
class Odometry:
    """The robot's odometry between poses, for the pose each scan announces.

    Attributes
    ----------
    translation_noise : float
        Standard deviation of the distance travelled, as a fraction of it.
    rotation_noise : float
        Standard deviation of each turn, rad per rad turned.
    heading_drift : float
        Systematic heading error, rad per metre travelled (a wheel slightly larger than the other).
    heading_noise : float
        Random heading error, rad per √m travelled.
    seed : int
        Seeds the draws; the same seed gives the same odometry.
    """

    translation_noise: float = 0.02
    rotation_noise: float = 0.02
    heading_drift: float = 0.0
    heading_noise: float = 0.01
    seed: int = 0


@dataclass(frozen=True)
class WorldAcoustics:
    """Air and surface acoustics of a world (the simulator's defaults unless set).

    Attributes
    ----------
    temperature : float
        K (the file's ``temperature_c`` in °C).
    absorption_db_per_m, corner_gain, diffuse_coefficient : float, optional
        Override :class:`lelsonar.sim.acoustics.Acoustics`.
    edge_gain : float
        Amplitude of a convex edge's diffraction echo relative to a mirror echo at the same range.
    trihedral_gain : float, optional
        Amplitude of a wall + wall + floor (or ceiling) triple bounce relative to
        a mirror at that range; default the corner gain.
    """

    temperature: float = 293.15
    absorption_db_per_m: float | None = None
    corner_gain: float | None = None
    diffuse_coefficient: float | None = None
    edge_gain: float = 0.2
    trihedral_gain: float | None = None


@dataclass(frozen=True)
class World:
    """Everything a world file describes."""

    name: str
    room: Room
    walls: tuple[Wall, ...]
    boxes: tuple[Box, ...] = ()
    scanner: ScannerMount = field(default_factory=ScannerMount)
    poses: tuple[Pose2, ...] = ()
    odometry: Odometry = field(default_factory=Odometry)
    acoustics: WorldAcoustics = field(default_factory=WorldAcoustics)
    source: str = ""

    @property
    def wall_top(self) -> float:
        """Default wall height above the floor, m: up to the ceiling, else :data:`DEFAULT_WALL_HEIGHT`."""
        return (self.room.ceiling - self.room.floor) if self.room.ceiling is not None else DEFAULT_WALL_HEIGHT

    def bounds(self) -> tuple[float, float, float, float]:
        """(x_min, y_min, x_max, y_max) of every wall, box and pose, m."""
        xs: list[float] = []
        ys: list[float] = []
        for w in self.walls:
            xs += [w.start[0], w.end[0]]
            ys += [w.start[1], w.end[1]]
        for b in self.boxes:
            for x, y in b.footprint():
                xs.append(x)
                ys.append(y)
        for p in self.poses:
            xs.append(p.x)
            ys.append(p.y)
        return min(xs), min(ys), max(xs), max(ys)


# ---------------------------------------------------------------------------- parsing
class _Table:
    """One TOML table with its name for messages; tracks which keys were read."""

    def __init__(self, where: str, name: str, values: object) -> None:
        if not isinstance(values, dict):
            raise ConfigError(f"{where}: {name} must be a table; write [{name.strip('[]')}] with key = value lines")
        self.where, self.name, self.values = where, name, values

    def _bad(self, key: str, what: str, got: object, example: str) -> ConfigError:
        return ConfigError(f"{self.where}: {self.name} {key!r} must be {what}, got {got!r}; write {example}")

    def number(
        self, key: str, default: float | None, *, lo: float = -math.inf, hi: float = math.inf, example: str = ""
    ) -> float:
        v = self.values.get(key, default)
        ex = example or f"{key} = 1.0"
        if v is None:
            raise ConfigError(f"{self.where}: {self.name} needs {key!r}; write {ex}")
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise self._bad(key, "a finite number", v, ex)
        if not lo <= v <= hi:
            raise self._bad(key, f"in [{lo:g}, {hi:g}]", v, ex)
        return float(v)

    def optional_number(self, key: str, *, lo: float = -math.inf, hi: float = math.inf) -> float | None:
        return self.number(key, None, lo=lo, hi=hi) if key in self.values else None

    def integer(self, key: str, default: int, *, lo: int, hi: int) -> int:
        v = self.values.get(key, default)
        if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
            raise self._bad(key, f"an integer in [{lo}, {hi}]", v, f"{key} = {default}")
        return int(v)

    def string(self, key: str, default: str, *, choices: tuple[str, ...] | None = None) -> str:
        v = self.values.get(key, default)
        if not isinstance(v, str) or len(v) > 200:
            raise self._bad(key, "a string of at most 200 characters", v, f'{key} = "{default}"')
        if choices is not None and v not in choices:
            raise self._bad(key, f"one of {', '.join(choices)}", v, f'{key} = "{choices[0]}"')
        return v

    def pair(self, key: str, *, required: bool = True, n: int = 2, example: str = "") -> tuple[float, ...] | None:
        ex = example or f"{key} = [{', '.join(['1.0'] * n)}]"
        if key not in self.values:
            if required:
                raise ConfigError(f"{self.where}: {self.name} needs {key!r}; write {ex}")
            return None
        v = self.values[key]
        if (
            not isinstance(v, list)
            or len(v) != n
            or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v)
        ):
            raise self._bad(key, f"{n} finite numbers", v, ex)
        if any(abs(x) > MAX_EXTENT for x in v):
            raise self._bad(key, f"within ±{MAX_EXTENT:g} m", v, ex)
        return tuple(float(x) for x in v)

    def check_keys(self, known: tuple[str, ...]) -> None:
        for key in self.values:
            if key not in known:
                raise ConfigError(
                    f"{self.where}: unknown key {key!r} in {self.name}; known keys: {', '.join(known)} "
                    "(see docs/worlds.md)"
                )


def _array_of_tables(where: str, data: dict, name: str, limit: int) -> list[_Table]:
    items = data.get(name, [])
    if isinstance(items, dict):
        raise ConfigError(f"{where}: {name} must be an array of tables; write [[{name}]], not [{name}]")
    if not isinstance(items, list):
        raise ConfigError(f"{where}: {name} must be an array of tables; write [[{name}]] blocks")
    if len(items) > limit:
        raise ConfigError(f"{where}: {len(items)} [[{name}]] entries; at most {limit} are supported, split the world")
    return [_Table(where, f"[[{name}]] #{i + 1}", item) for i, item in enumerate(items)]


def parse_world(data: dict, where: str = "world") -> World:
    """A :class:`World` from the parsed TOML ``data``; ``where`` names the file in messages.

    Raises
    ------
    ConfigError
        One line naming the key and how to fix it.
    """
    for key in data:
        if key not in _TABLES:
            raise ConfigError(
                f"{where}: unknown table {key!r}; known: {', '.join(sorted(_TABLES))} (see docs/worlds.md)"
            )
    meta = _Table(where, "[world]", data.get("world", {}))
    meta.check_keys(("name",))
    name = meta.string("name", Path(where).stem)

    rt = _Table(where, "[room]", data.get("room", {}))
    rt.check_keys(("floor", "ceiling", "floor_reflectivity", "ceiling_reflectivity"))
    floor = rt.number("floor", 0.0, lo=-100.0, hi=100.0, example="floor = 0.0")
    ceiling = rt.optional_number("ceiling", lo=-100.0, hi=200.0)
    if ceiling is not None and ceiling <= floor + 0.5:
        raise ConfigError(f"{where}: [room] 'ceiling' must be at least 0.5 m above the floor; write ceiling = 2.6")
    room = Room(
        floor=floor,
        ceiling=ceiling,
        floor_reflectivity=rt.number("floor_reflectivity", 0.95, lo=0.01, hi=1.0),
        ceiling_reflectivity=rt.number("ceiling_reflectivity", 0.95, lo=0.01, hi=1.0),
    )
    top = (ceiling - floor) if ceiling is not None else DEFAULT_WALL_HEIGHT

    walls: list[Wall] = []
    for t in _array_of_tables(where, data, "wall", MAX_WALLS):
        t.check_keys(("from", "to", "height", "bottom", "reflectivity", "name"))
        a = t.pair("from", example="from = [0.0, 0.0]")
        b = t.pair("to", example="to = [4.0, 0.0]")
        assert a is not None and b is not None
        if math.dist(a, b) < 0.01:
            raise ConfigError(f"{where}: {t.name} is shorter than 1 cm; move 'to' away from 'from'")
        bottom = t.number("bottom", 0.0, lo=0.0, hi=100.0)
        height = t.number("height", top - bottom, lo=0.01, hi=100.0, example="height = 2.6")
        if ceiling is not None and floor + bottom + height > ceiling + 1e-9:
            raise ConfigError(
                f"{where}: {t.name} reaches {floor + bottom + height:g} m, above the ceiling at {ceiling:g} m; "
                "lower 'height'"
            )
        walls.append(
            Wall(
                start=(a[0], a[1]),
                end=(b[0], b[1]),
                height=height,
                bottom=bottom,
                reflectivity=t.number("reflectivity", 0.95, lo=0.01, hi=1.0),
                name=t.string("name", f"wall{len(walls) + 1}"),
            )
        )

    boxes: list[Box] = []
    for t in _array_of_tables(where, data, "box", MAX_BOXES):
        t.check_keys(("center", "size", "yaw", "reflectivity", "name"))
        c = t.pair("center", example="center = [2.0, 1.5]")
        s = t.pair("size", n=3, example="size = [0.6, 0.4, 0.8]")
        assert c is not None and s is not None
        if min(s) < 0.01:
            raise ConfigError(
                f"{where}: {t.name} 'size' must be at least 1 cm on every side; write size = [0.6, 0.4, 0.8]"
            )
        if ceiling is not None and floor + s[2] > ceiling:
            raise ConfigError(f"{where}: {t.name} is taller than the room; lower size[2]")
        boxes.append(
            Box(
                center=(c[0], c[1]),
                size=(s[0], s[1], s[2]),
                yaw=math.radians(t.number("yaw", 0.0, lo=-360.0, hi=360.0, example="yaw = 20.0")),
                reflectivity=t.number("reflectivity", 0.95, lo=0.01, hi=1.0),
                name=t.string("name", f"box{len(boxes) + 1}"),
            )
        )

    scanner = _parse_scanner(where, data.get("scanner", {}), room)

    poses: list[Pose2] = []
    for t in _array_of_tables(where, data, "pose", MAX_POSES):
        t.check_keys(("x", "y", "heading"))
        poses.append(
            Pose2(
                x=t.number("x", None, lo=-MAX_EXTENT, hi=MAX_EXTENT, example="x = 1.0"),
                y=t.number("y", None, lo=-MAX_EXTENT, hi=MAX_EXTENT, example="y = 1.0"),
                heading=math.radians(t.number("heading", 0.0, lo=-360.0, hi=360.0, example="heading = 90.0")),
            )
        )
    if not walls and not boxes:
        raise ConfigError(f"{where}: the world has no [[wall]] and no [[box]]; add at least one surface")
    if not poses:
        raise ConfigError(f"{where}: the world has no [[pose]]; add one with x, y and heading")

    ot = _Table(where, "[odometry]", data.get("odometry", {}))
    ot.check_keys(("translation_noise", "rotation_noise", "heading_drift", "heading_noise", "seed"))
    odometry = Odometry(
        translation_noise=ot.number("translation_noise", 0.02, lo=0.0, hi=1.0),
        rotation_noise=ot.number("rotation_noise", 0.02, lo=0.0, hi=1.0),
        heading_drift=math.radians(ot.number("heading_drift", 0.0, lo=-90.0, hi=90.0)),
        heading_noise=math.radians(ot.number("heading_noise", math.degrees(0.01), lo=0.0, hi=90.0)),
        seed=ot.integer("seed", 0, lo=0, hi=2**63 - 1),
    )

    at = _Table(where, "[acoustics]", data.get("acoustics", {}))
    at.check_keys(
        ("temperature_c", "absorption_db_per_m", "corner_gain", "diffuse_coefficient", "edge_gain", "trihedral_gain")
    )
    acoustics = WorldAcoustics(
        temperature=at.number("temperature_c", 20.0, lo=-50.0, hi=60.0) + 273.15,
        absorption_db_per_m=at.optional_number("absorption_db_per_m", lo=0.0, hi=20.0),
        corner_gain=at.optional_number("corner_gain", lo=0.0, hi=10.0),
        diffuse_coefficient=at.optional_number("diffuse_coefficient", lo=0.0, hi=1.0),
        edge_gain=at.number("edge_gain", 0.2, lo=0.0, hi=1.0),
        trihedral_gain=at.optional_number("trihedral_gain", lo=0.0, hi=10.0),
    )
    world = World(
        name=name,
        room=room,
        walls=tuple(walls),
        boxes=tuple(boxes),
        scanner=scanner,
        poses=tuple(poses),
        odometry=odometry,
        acoustics=acoustics,
        source=where,
    )
    _check_poses(world)
    return world


def _parse_scanner(where: str, values: object, room: Room) -> ScannerMount:
    t = _Table(where, "[scanner]", values)
    t.check_keys(("mount", "height", "sweep", "steps", "radial_offset", "max_range", "tilt", "beam_width"))
    mount = t.string("mount", "fan", choices=MOUNTS)
    default_sweep = (-AX12_HALF_RANGE_DEG, AX12_HALF_RANGE_DEG) if mount == "fan" else (-10.0, 110.0)
    sweep = t.pair("sweep", required=False, example="sweep = [-149.0, 149.0]") or default_sweep
    if not -AX12_HALF_RANGE_DEG <= sweep[0] < sweep[1] <= AX12_HALF_RANGE_DEG:
        raise ConfigError(
            f"{where}: [scanner] 'sweep' must rise within ±{AX12_HALF_RANGE_DEG}° (the AX-12 turns 300°), "
            f"got {list(sweep)}; a full turn is two poses at two headings"
        )
    steps = t.integer("steps", 300 if mount == "fan" else 184, lo=2, hi=4096)
    height = t.number("height", 0.3, lo=0.0, hi=100.0, example="height = 0.3")
    radial_offset = t.number("radial_offset", 0.03, lo=0.0, hi=0.4)
    tilt = math.radians(t.number("tilt", 0.0, lo=-45.0, hi=45.0, example="tilt = -10.0"))
    beam_width = (
        math.radians(t.number("beam_width", None, lo=6.0, hi=170.0, example="beam_width = 40.0"))
        if "beam_width" in t.values
        else None
    )
    # The fan stacks the capsules along the vertical axis (a tilt leans the stack and lifts the faces); the
    # paper's mount swings them around it.
    if mount == "fan":
        reach = 1.5 * CAPSULE_PITCH_M * math.cos(tilt) + radial_offset * abs(math.sin(tilt))
    else:
        reach = 0.1
    if height - reach <= 0.0 or (room.ceiling is not None and room.floor + height + reach >= room.ceiling):
        raise ConfigError(
            f"{where}: [scanner] 'height' {height:g} m puts capsules outside the room "
            f"(they reach ±{reach:g} m); write height = 0.3"
        )
    return ScannerMount(
        mount=mount,
        height=height,
        sweep_start=math.radians(sweep[0]),
        sweep_stop=math.radians(sweep[1]),
        steps=steps,
        radial_offset=radial_offset,
        max_range=t.number("max_range", 4.0, lo=0.2, hi=20.0, example="max_range = 4.0"),
        tilt=tilt,
        beam_width=beam_width,
    )


def _segment_distance(p: tuple[float, float], a: tuple[float, float], b: tuple[float, float]) -> float:
    ax, ay = b[0] - a[0], b[1] - a[1]
    den = ax * ax + ay * ay
    t = 0.0 if den == 0 else max(0.0, min(1.0, ((p[0] - a[0]) * ax + (p[1] - a[1]) * ay) / den))
    return math.dist(p, (a[0] + t * ax, a[1] + t * ay))


def _check_poses(world: World) -> None:
    """Each pose leaves the scanner clear of every wall and outside every box."""
    clearance = world.scanner.radial_offset + 0.05
    for i, p in enumerate(world.poses):
        for w in world.walls:
            if _segment_distance((p.x, p.y), w.start, w.end) < clearance:
                raise ConfigError(
                    f"{world.source}: [[pose]] #{i + 1} at ({p.x:g}, {p.y:g}) is within {clearance:g} m of "
                    f"wall {w.name!r}; move the pose away from it"
                )
        for b in world.boxes:
            c, s = math.cos(-b.yaw), math.sin(-b.yaw)
            dx, dy = p.x - b.center[0], p.y - b.center[1]
            u, v = c * dx - s * dy, s * dx + c * dy
            if abs(u) < b.size[0] / 2 + clearance and abs(v) < b.size[1] / 2 + clearance:
                raise ConfigError(
                    f"{world.source}: [[pose]] #{i + 1} at ({p.x:g}, {p.y:g}) is inside or against box "
                    f"{b.name!r}; move the pose away from it"
                )


def load_world(path: Path | str) -> World:
    """Read a world file (TOML).

    Raises
    ------
    ConfigError
        The file is missing, not TOML, or a key is wrong (one line naming it and the fix).
    """
    path = Path(path)
    try:
        with open(path, "rb") as f:
            data = tomllib.load(f)
    except FileNotFoundError:
        raise ConfigError(f"world file {path} does not exist; give a .toml world (see examples/worlds/)") from None
    except IsADirectoryError:
        raise ConfigError(f"world file {path} is a directory; give a .toml world (see examples/worlds/)") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path} is not valid TOML: {exc}") from None
    return parse_world(data, str(path))
