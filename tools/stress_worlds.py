"""Seeded worlds *outside* the world families: the shapes, clutter, rigs and air the families never draw.

The families of :mod:`lelsonar.sim.worlds` are rectangles, notched rectangles, a corridor, a maze of square
cells and boxes in a room: every corner 90°, every wall the full room height.  The project is judged on an
independent simulator's world files, which include surfaces it did not model.  Each class below perturbs
one thing at a time (``mixed``: several at once) and every draw goes through :func:`parse_world`, so each
is a world file a user could write (:func:`world_toml` writes it out).

================  ==============================================================
class             what is drawn
================  ==============================================================
``oblique``       a quadrilateral room, no corner near 90° (each 60–120°)
``acute``         a triangular room, one corner 25–60°
``obtuse``        a convex pentagon to heptagon (corners 108–140°)
``thin``          a rectangle with 1–3 free-standing or jutting thin walls (convex ends)
``boxes_turned``  2–4 boxes at any yaw, 0.3–1 m
``boxes_tiny``    2–6 posts and small boxes, 4–20 cm
``boxes_large``   1–2 boxes 1–2.5 m
``touching``      1–3 boxes flush against a wall (the box's face 0–2 cm from it)
``clutter``       6–12 boxes of any size and yaw
``narrow``        a room 0.9–1.4 m wide and 3–8 m long
``wide``          a room 6–12 m across (walls past the waveform window)
``heights``       scanner 0.1–1.4 m; a low wall under it, a shelf (wall off the floor) and a short box
``acoustics``     temperature −10–40 °C, absorption 0–4 dB/m, corner, edge and triple-bounce gains,
                  diffuse share, floor and ceiling reflectivity, no ceiling half the time
``reflect``       each wall and box its own reflectivity 0.1–1
``strong_edges``  2–4 boxes at any yaw whose edges diffract 0.5–1× a mirror (a corner's gain 0.5–2.5):
                  a lone edge or corner then echoes as a wall does
``odometry``      translation and rotation noise 0–10 %, heading noise and drift up to 3°/m
``beam``          a rectangle with a box, the capsules' echo beam 20–60° wide (−6 dB full angle), level
``tilt``          a rectangle with a box, the mount tilted −10…+10° about the robot's lateral axis
``rig``           steps 60–600, a partial sweep, radial offset 0–10 cm, max range 2–8 m
``mixed``         a polygon room with boxes and thin walls, the rig, air and odometry drawn too
================  ==============================================================

Every world is turned by a random angle and shifted.  ``mount = "paper"`` turns each pose to face a
wall whose foot of the perpendicular it sees (off square by up to ±12°), its sweep reaching the floor
and the ceiling, as the families do.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Callable
from typing import Any

import numpy as np
from shapely.geometry import LineString, Point, Polygon
from shapely.ops import unary_union

from lelsonar.errors import ConfigError
from lelsonar.sim.world import MOUNTS, World, parse_world

#: Perturbation classes, in the order the bench reports them.
STRESS_CLASSES: tuple[str, ...] = (
    "oblique",
    "acute",
    "obtuse",
    "thin",
    "boxes_turned",
    "boxes_tiny",
    "boxes_large",
    "touching",
    "clutter",
    "narrow",
    "wide",
    "heights",
    "acoustics",
    "reflect",
    "strong_edges",
    "odometry",
    "beam",
    "tilt",
    "rig",
    "mixed",
)
#: A drawn pose is at least this far from every wall and box, m.
POSE_CLEARANCE = 0.3
#: Paper mount: the most a pose's heading is off square to the wall it faces, rad; the farthest wall, m.
PAPER_YAW, PAPER_REACH = math.radians(12.0), 3.0

Seg = tuple[tuple[float, float], tuple[float, float]]


class _Draft:
    """A world being drawn, in its own frame (turned and shifted at the end)."""

    def __init__(self, rng: np.random.Generator, outline: list[tuple[float, float]]) -> None:
        self.rng = rng
        self.outline = outline
        self.room = Polygon(outline)
        self.walls: list[dict[str, Any]] = [
            {"from": list(outline[i]), "to": list(outline[(i + 1) % len(outline)])} for i in range(len(outline))
        ]
        self.boxes: list[dict[str, Any]] = []
        self.ceiling: float | None = float(rng.uniform(2.3, 3.0))
        self.room_extra: dict[str, Any] = {}
        self.scanner: dict[str, Any] = {"height": float(rng.uniform(0.2, 0.5))}
        self.acoustics: dict[str, Any] = {}
        self.odometry: dict[str, Any] = {}
        self.n_poses = int(rng.integers(2, 5))

    # ------------------------------------------------------------------ occupancy
    def obstacles(self):
        shapes = [LineString([w["from"], w["to"]]) for w in self.walls[len(self.outline) :]]
        shapes += [_footprint(b) for b in self.boxes]
        return unary_union(shapes) if shapes else None

    def free(self, p: tuple[float, float], clearance: float) -> bool:
        pt = Point(p)
        if not self.room.contains(pt) or self.room.exterior.distance(pt) < clearance:
            return False
        obs = self.obstacles()
        return obs is None or obs.distance(pt) >= clearance

    def add_box(self, center, size, yaw: float, *, gap: float = 0.15, against_wall: bool = False) -> bool:
        box = {"center": [float(center[0]), float(center[1])], "size": [float(s) for s in size], "yaw": yaw}
        fp = _footprint(box)
        inner = self.room.buffer(1e-3 if against_wall else -gap)
        if not inner.contains(fp):
            return False
        obs = self.obstacles()
        if obs is not None and obs.distance(fp) < gap:
            return False
        self.boxes.append(box)
        return True

    def random_box(self, lo: float, hi: float, height: tuple[float, float] = (0.3, 1.2), tries: int = 200) -> bool:
        minx, miny, maxx, maxy = self.room.bounds
        for _ in range(tries):
            size = (self.rng.uniform(lo, hi), self.rng.uniform(lo, hi), self.rng.uniform(*height))
            c = (self.rng.uniform(minx, maxx), self.rng.uniform(miny, maxy))
            if self.add_box(c, size, float(self.rng.uniform(-180.0, 180.0))):
                return True
        return False

    def thin_wall(self, tries: int = 200) -> bool:
        """A free-standing wall inside the room, or one jutting from a room wall (one free end)."""
        minx, miny, maxx, maxy = self.room.bounds
        for _ in range(tries):
            length = self.rng.uniform(0.6, 2.0)
            if self.rng.random() < 0.5:
                a = np.array([self.rng.uniform(minx, maxx), self.rng.uniform(miny, maxy)])
                ang = self.rng.uniform(-math.pi, math.pi)
                b = a + length * np.array([math.cos(ang), math.sin(ang)])
                seg = LineString([a, b])
                if not self.room.buffer(-0.5).contains(seg):
                    continue
            else:
                k = int(self.rng.integers(len(self.outline)))
                p, q = np.array(self.outline[k], float), np.array(self.outline[(k + 1) % len(self.outline)], float)
                t = self.rng.uniform(0.25, 0.75)
                a = p + t * (q - p)
                d = (q - p) / np.linalg.norm(q - p)
                inward = np.array([-d[1], d[0]])
                if not self.room.contains(Point(a + 0.05 * inward)):
                    inward = -inward
                ang = self.rng.uniform(-0.7, 0.7)
                c, s = math.cos(ang), math.sin(ang)
                b = a + length * np.array([c * inward[0] - s * inward[1], s * inward[0] + c * inward[1]])
                if not self.room.buffer(-0.3).contains(Point(b)):
                    continue
                seg = LineString([a, b])
            obs = self.obstacles()
            if obs is not None and obs.distance(seg) < 0.5:
                continue
            self.walls.append({"from": [float(a[0]), float(a[1])], "to": [float(b[0]), float(b[1])]})
            return True
        return False

    def poses(self) -> list[tuple[float, float, float]]:
        minx, miny, maxx, maxy = self.room.bounds
        out: list[tuple[float, float, float]] = []
        for _ in range(4000):
            p = (float(self.rng.uniform(minx, maxx)), float(self.rng.uniform(miny, maxy)))
            if self.free(p, POSE_CLEARANCE + self.scanner.get("radial_offset", 0.03)):
                out.append((p[0], p[1], float(self.rng.uniform(-math.pi, math.pi))))
                if len(out) == self.n_poses:
                    break
        if not out:
            raise ConfigError("could not place a pose in a drawn stress world (a bug in its class's bounds)")
        return out


def _footprint(box: dict[str, Any]) -> Polygon:
    c, s = math.cos(math.radians(box["yaw"])), math.sin(math.radians(box["yaw"]))
    hx, hy = box["size"][0] / 2, box["size"][1] / 2
    cx, cy = box["center"]
    return Polygon([(cx + c * u - s * v, cy + s * u + c * v) for u, v in ((-hx, -hy), (hx, -hy), (hx, hy), (-hx, hy))])


def _rect(rng: np.random.Generator, w: tuple[float, float] = (3.0, 6.0), d: tuple[float, float] = (2.5, 5.0)):
    a, b = float(rng.uniform(*w)), float(rng.uniform(*d))
    return [(0.0, 0.0), (a, 0.0), (a, b), (0.0, b)]


def _convex(rng: np.random.Generator, n: int, radius: tuple[float, float], jitter: float):
    """A convex polygon: n vertices on an ellipse, each moved in angle by up to ``jitter`` of a slot."""
    rx, ry = float(rng.uniform(*radius)), float(rng.uniform(*radius))
    ang = np.sort(2 * np.pi * (np.arange(n) + rng.uniform(-jitter, jitter, n)) / n)
    return [(float(rx * math.cos(t)), float(ry * math.sin(t))) for t in ang]


def _corners_deg(outline) -> list[float]:
    pts = np.asarray(outline, float)
    out = []
    for i in range(len(pts)):
        a, b, c = pts[i - 1], pts[i], pts[(i + 1) % len(pts)]
        u, v = a - b, c - b
        out.append(math.degrees(math.acos(np.clip(u @ v / (np.linalg.norm(u) * np.linalg.norm(v)), -1, 1))))
    return out


def _oblique(rng):
    for _ in range(500):
        w, d = rng.uniform(3.0, 6.0), rng.uniform(2.5, 5.0)
        pts = [(0.0, 0.0), (w, 0.0), (w, d), (0.0, d)]
        pts = [(x + float(rng.uniform(-0.9, 0.9)), y + float(rng.uniform(-0.9, 0.9))) for x, y in pts]
        ang = _corners_deg(pts)
        if Polygon(pts).is_valid and all(60 <= a <= 120 and abs(a - 90) > 8 for a in ang):
            return _Draft(rng, pts)
    raise ConfigError("oblique: no quadrilateral drawn")


def _acute(rng):
    for _ in range(500):
        a = math.radians(rng.uniform(25.0, 60.0))
        b = math.radians(rng.uniform(40.0, 180.0 - math.degrees(a) - 40.0))
        base = float(rng.uniform(4.0, 7.0))
        # Third vertex from the base's two angles.
        c = math.pi - a - b
        side = base * math.sin(b) / math.sin(c)
        pts = [(0.0, 0.0), (base, 0.0), (side * math.cos(a), side * math.sin(a))]
        if Polygon(pts).buffer(-0.6).area > 1.0:
            return _Draft(rng, pts)
    raise ConfigError("acute: no triangle drawn")


def _obtuse(rng):
    n = int(rng.integers(5, 8))
    return _Draft(rng, _convex(rng, n, (2.0, 3.5), 0.15))


def _thin(rng):
    dr = _Draft(rng, _rect(rng, (3.5, 6.5), (3.0, 5.5)))
    for _ in range(int(rng.integers(1, 4))):
        dr.thin_wall()
    return dr


def _boxes(lo, hi, count, height=(0.3, 1.2)):
    def draw(rng):
        dr = _Draft(rng, _rect(rng, (3.5, 6.5), (3.0, 5.5)))
        for _ in range(int(rng.integers(*count))):
            dr.random_box(lo, hi, height)
        return dr

    return draw


def _touching(rng):
    dr = _Draft(rng, _rect(rng, (3.5, 6.5), (3.0, 5.5)))
    for _ in range(int(rng.integers(1, 4))):
        for _ in range(200):
            k = int(rng.integers(4))
            p, q = np.array(dr.outline[k]), np.array(dr.outline[(k + 1) % 4])
            d = (q - p) / np.linalg.norm(q - p)
            inward = np.array([-d[1], d[0]])
            size = (float(rng.uniform(0.3, 1.2)), float(rng.uniform(0.2, 0.8)), float(rng.uniform(0.3, 1.2)))
            gap = float(rng.uniform(0.0, 0.02))
            c = p + rng.uniform(0.15, 0.85) * (q - p) + inward * (size[1] / 2 + gap)
            if dr.add_box(c, size, math.degrees(math.atan2(d[1], d[0])), against_wall=True):
                break
    return dr


def _narrow(rng):
    return _Draft(rng, _rect(rng, (3.0, 8.0), (0.9, 1.4)))


def _wide(rng):
    dr = _Draft(rng, _rect(rng, (6.0, 12.0), (6.0, 12.0)))
    dr.scanner["max_range"] = float(rng.uniform(3.0, 6.0))
    return dr


def _heights(rng):
    dr = _Draft(rng, _rect(rng, (3.5, 6.0), (3.0, 5.0)))
    dr.ceiling = float(rng.uniform(2.4, 3.0))
    dr.scanner["height"] = float(rng.uniform(0.1, 1.4))
    h = dr.scanner["height"]
    if dr.thin_wall():  # a low wall, its top under the scanner
        dr.walls[-1]["height"] = float(rng.uniform(0.05, max(0.06, h - 0.1)))
    if dr.thin_wall():  # a shelf: a wall off the floor
        bottom = float(rng.uniform(0.05, 1.2))
        dr.walls[-1] |= {"bottom": bottom, "height": float(rng.uniform(0.1, 0.6))}
    dr.random_box(0.3, 0.8, (0.05, max(0.06, h - 0.05)))
    return dr


def _acoustics(rng):
    dr = _Draft(rng, _rect(rng))
    if rng.random() < 0.5:
        dr.ceiling = None
    else:
        dr.room_extra["ceiling_reflectivity"] = float(rng.uniform(0.2, 1.0))
    dr.room_extra["floor_reflectivity"] = float(rng.uniform(0.2, 1.0))
    dr.acoustics = {
        "temperature_c": float(rng.uniform(-10.0, 40.0)),
        "absorption_db_per_m": float(rng.uniform(0.0, 4.0)),
        "corner_gain": float(rng.uniform(0.0, 2.5)),
        "diffuse_coefficient": float(rng.uniform(0.0, 0.4)),
        "edge_gain": float(rng.uniform(0.0, 0.8)),
        "trihedral_gain": float(rng.uniform(0.0, 2.5)),
    }
    dr.random_box(0.3, 0.9)
    return dr


def _reflect(rng):
    dr = _Draft(rng, _rect(rng))
    dr.random_box(0.3, 0.9)
    dr.random_box(0.3, 0.9)
    for item in dr.walls + dr.boxes:
        item["reflectivity"] = float(rng.uniform(0.1, 1.0))
    return dr


def _strong_edges(rng):
    dr = _boxes(0.3, 1.0, (2, 5))(rng)
    dr.acoustics = {"edge_gain": float(rng.uniform(0.5, 1.0)), "corner_gain": float(rng.uniform(0.5, 2.5))}
    return dr


def _odometry(rng):
    dr = _Draft(rng, _rect(rng))
    dr.n_poses = int(rng.integers(3, 6))
    dr.odometry = {
        "translation_noise": float(rng.uniform(0.0, 0.1)),
        "rotation_noise": float(rng.uniform(0.0, 0.1)),
        "heading_noise": float(rng.uniform(0.0, 3.0)),
        "heading_drift": float(rng.uniform(-3.0, 3.0)),
    }
    return dr


def _beam(rng):
    dr = _Draft(rng, _rect(rng))
    dr.random_box(0.3, 0.9)
    dr.scanner["beam_width"] = float(rng.uniform(20.0, 60.0))
    return dr


def _tilt(rng):
    dr = _Draft(rng, _rect(rng))
    dr.random_box(0.3, 0.9)
    dr.scanner["tilt"] = float(rng.uniform(-10.0, 10.0))
    return dr


def _rig(rng):
    dr = _Draft(rng, _rect(rng))
    dr.random_box(0.3, 0.9)
    lo, hi = -149.0, 149.0
    if rng.random() < 0.5:
        lo = float(rng.uniform(-149.0, -30.0))
        hi = float(rng.uniform(lo + 60.0, 149.0))
    dr.scanner |= {
        "steps": int(rng.integers(60, 601)),
        "sweep": [lo, hi],
        "radial_offset": float(rng.uniform(0.0, 0.1)),
        "max_range": float(rng.uniform(2.0, 8.0)),
    }
    return dr


def _mixed(rng):
    kind = rng.random()
    dr = _oblique(rng) if kind < 0.4 else _obtuse(rng) if kind < 0.7 else _acute(rng)
    for _ in range(int(rng.integers(0, 3))):
        dr.thin_wall()
    for _ in range(int(rng.integers(0, 5))):
        dr.random_box(0.1, 1.2)
    for key, val in _acoustics(np.random.default_rng(rng.integers(2**32))).acoustics.items():
        if rng.random() < 0.5:
            dr.acoustics[key] = val
    dr.scanner["radial_offset"] = float(rng.uniform(0.0, 0.08))
    dr.scanner["steps"] = int(rng.integers(120, 500))
    dr.odometry = {"translation_noise": float(rng.uniform(0.0, 0.06)), "rotation_noise": float(rng.uniform(0, 0.06))}
    return dr


_DRAW: dict[str, Callable[[np.random.Generator], _Draft]] = {
    "oblique": _oblique,
    "acute": _acute,
    "obtuse": _obtuse,
    "thin": _thin,
    "boxes_turned": _boxes(0.3, 1.0, (2, 5)),
    "boxes_tiny": _boxes(0.04, 0.2, (2, 7), (0.1, 1.2)),
    "boxes_large": _boxes(1.0, 2.5, (1, 3)),
    "touching": _touching,
    "clutter": _boxes(0.1, 1.0, (6, 13)),
    "narrow": _narrow,
    "wide": _wide,
    "heights": _heights,
    "acoustics": _acoustics,
    "reflect": _reflect,
    "strong_edges": _strong_edges,
    "odometry": _odometry,
    "beam": _beam,
    "tilt": _tilt,
    "rig": _rig,
    "mixed": _mixed,
}


def _face_walls(rng, poses, walls: list[Seg], reach: float) -> list[tuple[float, float, float]]:
    """Each pose turned to face a wall whose foot of the perpendicular it sees, off square by up to PAPER_YAW."""
    segs = [LineString([a, b]) for a, b in walls]
    out = []
    for x, y, h in poses:
        feet = []
        for k, (a, b) in enumerate(walls):
            a_, b_ = np.asarray(a, float), np.asarray(b, float)
            d = b_ - a_
            t = float((np.array([x, y]) - a_) @ d / (d @ d))
            foot = a_ + t * d
            dist = float(np.hypot(*(foot - (x, y))))
            margin = 0.3 / float(np.sqrt(d @ d))
            ray = LineString([(x, y), foot - 0.01 * (foot - (x, y)) / max(dist, 1e-9)])
            blocked = any(ray.crosses(s) or ray.intersects(s) for j, s in enumerate(segs) if j != k)
            if margin < t < 1 - margin and dist <= reach and not blocked:
                feet.append(math.atan2(foot[1] - y, foot[0] - x))
        if feet:
            toward = feet[int(rng.integers(len(feet)))]
            h = math.remainder(toward + float(rng.uniform(-PAPER_YAW, PAPER_YAW)), 2 * math.pi)
        out.append((x, y, h))
    return out


def stress_rng(cls: str, seed: int) -> np.random.Generator:
    """Independent streams per class and seed."""
    return np.random.default_rng([int(seed), zlib.crc32(b"stress-world:" + cls.encode())])


def stress_world_data(cls: str, seed: int, mount: str = "fan") -> dict[str, Any]:
    """The world file's content (a dict as TOML parses it) of world ``seed`` of class ``cls``."""
    if cls not in _DRAW:
        raise ConfigError(f"unknown stress class {cls!r}; choose from {', '.join(STRESS_CLASSES)}")
    if mount not in MOUNTS:
        raise ConfigError(f"unknown scanner mount {mount!r}; choose from {', '.join(MOUNTS)}")
    rng = stress_rng(cls, seed)
    dr = _DRAW[cls](rng)
    poses = dr.poses()
    scanner = dict(dr.scanner) | {"mount": mount}
    if mount == "paper":
        prng = np.random.default_rng([int(seed), zlib.crc32(b"stress-mount:paper:" + cls.encode())])
        walls = [(tuple(w["from"]), tuple(w["to"])) for w in dr.walls if w.get("bottom", 0.0) == 0.0]
        poses = _face_walls(prng, poses, walls, min(PAPER_REACH, scanner.get("max_range", 4.0) - 0.5))
        lo = float(prng.uniform(-149.5, -125.0))
        hi = float(prng.uniform(125.0, 149.5))
        scanner.pop("sweep", None)
        scanner |= {"sweep": [lo, hi], "steps": int(scanner.get("steps", round((hi - lo) / (120.0 / 184))))}
        if dr.ceiling is not None:
            scanner["height"] = min(scanner["height"], dr.ceiling - 0.15)
        scanner["height"] = max(scanner["height"], 0.15)
    turn = float(rng.uniform(-math.pi, math.pi))
    shift = rng.uniform(-3.0, 3.0, size=2)
    c, s = math.cos(turn), math.sin(turn)

    def move(p) -> list[float]:
        return [float(c * p[0] - s * p[1] + shift[0]), float(s * p[0] + c * p[1] + shift[1])]

    room: dict[str, Any] = {"floor": 0.0} | dr.room_extra
    if dr.ceiling is not None:
        room["ceiling"] = dr.ceiling
    data: dict[str, Any] = {
        "world": {"name": f"stress-{cls}-{seed}"},
        "room": room,
        "wall": [w | {"from": move(w["from"]), "to": move(w["to"])} for w in dr.walls],
        "box": [
            b | {"center": move(b["center"]), "yaw": math.remainder(b["yaw"] + math.degrees(turn), 360.0)}
            for b in dr.boxes
        ],
        "scanner": scanner,
        "pose": [
            {"x": q[0], "y": q[1], "heading": math.degrees(math.remainder(h + turn, 2 * math.pi))}
            for (x, y, h) in poses
            for q in [move((x, y))]
        ],
        "odometry": {"seed": int(seed)} | dr.odometry,
    }
    if dr.acoustics:
        data["acoustics"] = dr.acoustics
    if not data["box"]:
        del data["box"]
    return data


def draw_stress_world(cls: str, seed: int, mount: str = "fan") -> World:
    """World ``seed`` of stress class ``cls``: the same triple always gives the same world."""
    return parse_world(stress_world_data(cls, seed, mount), f"stress-{cls}-{seed}-{mount}")


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"no TOML for {type(v).__name__}")


def world_toml(data: dict[str, Any]) -> str:
    """A world file's text from its content (tables of numbers, strings and lists; arrays of tables)."""
    lines: list[str] = []
    for name, value in data.items():
        blocks = value if isinstance(value, list) else [value]
        for block in blocks:
            lines.append(f"[[{name}]]" if isinstance(value, list) else f"[{name}]")
            lines += [f"{k} = {_toml_value(v)}" for k, v in block.items()]
            lines.append("")
    return "\n".join(lines)
