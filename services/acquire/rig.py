"""A real scanner's rig file: everything ``--device serial`` needs, and nothing from the simulator.

``examples/rig.toml`` documents every key.  Tables::

    [array]         capsule_x (m, along the rotation axis), radial_offset (m)
    [servo]         port, id, baudrate, zero_raw, gamma_min_deg, gamma_max_deg, moving_speed, latency_timer_ms
    [sensor_board]  port, sample_rate (Hz), window_samples, full_scale_v, link ("usb-fs" or "uart"), baudrate
    [air]           temperature_c or sound_speed (m/s)
    [energy_model]  phi = [phi0, phi1, phi2], d_min, d_max (m): E0(d) = 1/(phi0 d² + phi1 d + phi2)
    [schedule]      gamma_start_deg, gamma_stop_deg, steps
    [mount]         kind ("fan" or "paper"), height (m), odometry_max_age (s): the array on the robot; with it,
                    each scan carries the pose the robot's odometry publishes on <prefix>/<scanner>/odom

:func:`load_rig` reads and type-checks them; :func:`require_for_serial` names
every missing key at once.  :func:`write_energy_model` rewrites only the
``[energy_model]`` table of a file (``lelsonar calibrate --device serial``).
"""

from __future__ import annotations

import math
import re
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from lelsonar.acquire.devices.link import LINK_KINDS, Link
from lelsonar.acquire.devices.motor import MotorConfig
from lelsonar.acquire.devices.sensor_board import SensorBoardConfig
from lelsonar.acquire.scanner import ScannerInfo
from lelsonar.energy_model import EnergyModel
from lelsonar.errors import ConfigError
from lelsonar.geometry import ArrayGeometry

if TYPE_CHECKING:  # the config reads rig files: it imports this module
    from lelsonar.acquire.config import AcquireConfig

#: Every table and key of a rig file with its type (float also accepts an int).
RIG_KEYS: dict[str, dict[str, type]] = {
    "array": {"capsule_x": list, "radial_offset": float},
    "servo": {
        "port": str,
        "id": int,
        "baudrate": int,
        "zero_raw": int,
        "gamma_min_deg": float,
        "gamma_max_deg": float,
        "moving_speed": int,
        "latency_timer_ms": float,
    },
    "sensor_board": {
        "port": str,
        "sample_rate": float,
        "window_samples": int,
        "full_scale_v": float,
        "link": str,
        "baudrate": int,
    },
    "air": {"temperature_c": float, "sound_speed": float},
    "energy_model": {"phi": list, "d_min": float, "d_max": float},
    "schedule": {"gamma_start_deg": float, "gamma_stop_deg": float, "steps": int},
    "mount": {"kind": str, "height": float, "odometry_max_age": float},
}

#: What ``--device serial`` cannot run without (flags may supply the ports, the schedule and φ).
REQUIRED_FOR_SERIAL = (
    "array.capsule_x",
    "array.radial_offset",
    "servo.port",
    "servo.zero_raw",
    "servo.gamma_min_deg",
    "servo.gamma_max_deg",
    "sensor_board.port",
    "sensor_board.sample_rate",
    "sensor_board.window_samples",
    "air.temperature_c or air.sound_speed",
    "energy_model.phi",
    "energy_model.d_min",
    "energy_model.d_max",
    "schedule.gamma_start_deg",
    "schedule.gamma_stop_deg",
    "schedule.steps",
)


@dataclass(frozen=True)
class Rig:
    """The rig tables of a TOML file, as read (``None`` = not given).  Angles in the file are degrees."""

    path: Path | None
    values: dict[str, dict[str, Any]]

    def get(self, dotted: str, default: Any = None) -> Any:
        table, key = dotted.split(".", 1)
        return self.values.get(table, {}).get(key, default)

    def missing(self, overrides: dict[str, Any] | None = None) -> list[str]:
        """The keys of :data:`REQUIRED_FOR_SERIAL` that neither the file nor ``overrides`` (dotted keys) give."""
        given = {f"{t}.{k}" for t, kv in self.values.items() for k in kv} | {
            k for k, v in (overrides or {}).items() if v is not None
        }
        out = []
        for need in REQUIRED_FOR_SERIAL:
            options = need.split(" or ")
            if not any(o in given for o in options):
                out.append(need)
        return out

    # --- derived values ----------------------------------------------------------------
    def sound_speed_and_temperature(self) -> tuple[float, float]:
        """(c m/s, T K): from ``sound_speed``, or ``c = 331.3·√(1 + T_C/273.15)`` from ``temperature_c``.

        With only a sound speed, the temperature is the one that gives it.
        """
        c, t_c = self.get("air.sound_speed"), self.get("air.temperature_c")
        if c is None and t_c is None:
            raise ConfigError(_where(self.path, "[air] needs temperature_c or sound_speed"))
        if c is None:
            c = 331.3 * math.sqrt(1.0 + t_c / 273.15)
        elif t_c is None:
            t_c = ((c / 331.3) ** 2 - 1.0) * 273.15
        return float(c), float(t_c) + 273.15


def rig_links(rig: Rig | None) -> tuple[Link, Link]:
    """(AX-12 bus, sensor board link) of a rig file, or the defaults without one.

    The servo's bus is a UART at ``[servo] baudrate`` (1 Mbps, the factory setting); the
    board's link is ``[sensor_board] link``: ``usb-fs`` (the default, a USB CDC board) or
    ``uart`` at ``[sensor_board] baudrate``.  The emulated backend paces its emulators with
    them and the physical bound charges every byte at their rates.
    """
    g = (rig or Rig(None, {})).get
    motor = Link.uart(int(g("servo.baudrate", 1_000_000)))
    board = Link.named(str(g("sensor_board.link", "usb-fs")), int(g("sensor_board.baudrate", 1_000_000)))
    return motor, board


def _where(path: Path | None, text: str) -> str:
    return f"{path}: {text}" if path else text


def load_rig(path: Path | str) -> Rig:
    """The rig tables of ``path`` (other tables, e.g. ``[acquire]`` or ``[zenoh]``, are left to their commands).

    Raises
    ------
    ConfigError
        Missing file, invalid TOML, an unknown key in a rig table, a value of the wrong type or range.
    """
    path = Path(path)
    try:
        with open(path, "rb") as f:
            doc = tomllib.load(f)
    except FileNotFoundError:
        raise ConfigError(f"config file {path} does not exist") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path} is not valid TOML: {exc}") from None
    values: dict[str, dict[str, Any]] = {}
    for table, keys in RIG_KEYS.items():
        given = doc.get(table, {})
        if not isinstance(given, dict):
            raise ConfigError(f"{path}: [{table}] must be a table")
        for key, value in given.items():
            kind = keys.get(key)
            if kind is None:
                raise ConfigError(f"{path}: unknown key {key!r} in [{table}]; known: {', '.join(keys)}")
            if isinstance(value, bool) or not (isinstance(value, kind) or (kind is float and isinstance(value, int))):
                raise ConfigError(f"{path}: [{table}].{key} must be of type {kind.__name__}, got {value!r}")
        values[table] = dict(given)
    rig = Rig(path, values)
    _validate(rig)
    return rig


def _validate(rig: Rig) -> None:
    p = rig.path
    xs = rig.get("array.capsule_x")
    if xs is not None and not (1 <= len(xs) <= 16 and all(isinstance(x, (int, float)) for x in xs)):
        raise ConfigError(_where(p, "[array].capsule_x must list 1 to 16 positions in m"))
    phi = rig.get("energy_model.phi")
    if phi is not None and not (len(phi) == 3 and all(isinstance(x, (int, float)) for x in phi)):
        raise ConfigError(_where(p, "[energy_model].phi must be three numbers [phi0, phi1, phi2]"))
    lo, hi = rig.get("servo.gamma_min_deg"), rig.get("servo.gamma_max_deg")
    if lo is not None and hi is not None and not -150.0 <= lo < hi <= 150.0:
        raise ConfigError(_where(p, f"[servo] needs -150 <= gamma_min_deg < gamma_max_deg <= 150, got {lo}, {hi}"))
    zero = rig.get("servo.zero_raw")
    if zero is not None and not 0 <= zero <= 1023:
        raise ConfigError(_where(p, f"[servo].zero_raw must be in 0..1023 (AX-12 units), got {zero}"))
    link = rig.get("sensor_board.link")
    if link is not None and link not in LINK_KINDS:
        raise ConfigError(_where(p, f"[sensor_board].link must be one of {', '.join(LINK_KINDS)}, got {link!r}"))
    for table in ("servo", "sensor_board"):
        baud = rig.get(f"{table}.baudrate")
        if baud is not None and baud <= 0:
            raise ConfigError(_where(p, f"[{table}].baudrate must be positive, got {baud}"))
    kind, height = rig.get("mount.kind"), rig.get("mount.height")
    if kind is not None and kind not in ("fan", "paper"):
        raise ConfigError(_where(p, f'[mount].kind must be "fan" or "paper", got {kind!r}'))
    if height is not None and not 0.0 <= height <= 10.0:
        raise ConfigError(_where(p, f"[mount].height must be in [0, 10] m above the floor, got {height}"))
    age = rig.get("mount.odometry_max_age")
    if age is not None and not 0.0 < age <= 60.0:
        raise ConfigError(_where(p, f"[mount].odometry_max_age must be in (0, 60] s, got {age}"))
    t_c, c = rig.get("air.temperature_c"), rig.get("air.sound_speed")
    if t_c is not None and not -40.0 <= t_c <= 60.0:
        raise ConfigError(_where(p, f"[air].temperature_c must be in [-40, 60] °C, got {t_c}"))
    if c is not None and not 300.0 <= c <= 370.0:
        raise ConfigError(_where(p, f"[air].sound_speed must be in [300, 370] m/s, got {c}"))


def require_for_serial(rig: Rig | None, overrides: dict[str, Any] | None = None) -> None:
    """Raise one :class:`ConfigError` naming every missing rig key (``overrides``: dotted keys set by flags)."""
    missing = (rig or Rig(None, {})).missing(overrides)
    if missing:
        where = f"the rig file {rig.path}" if rig and rig.path else "a rig file (--config rig.toml)"
        raise ConfigError(
            f"--device serial takes the rig from {where}, never from a simulator preset; missing: "
            f"{', '.join(missing)} (see examples/rig.toml)"
        )


# --- writing φ back ------------------------------------------------------------------------
_TABLE = re.compile(r"^\s*\[([^\[\]]+)\]\s*(#.*)?$")


def write_energy_model(
    path: Path | str, phi: tuple[float, float, float], d_min: float, d_max: float, note: str = ""
) -> None:
    """Replace the ``[energy_model]`` table of ``path`` (append it if absent); every other line stays."""
    path = Path(path)
    lines = path.read_text().splitlines(keepends=True) if path.exists() else []
    body = ["[energy_model]\n"]
    if note:
        body.append(f"# {note}\n")
    body += [
        f"phi = [{phi[0]!r}, {phi[1]!r}, {phi[2]!r}]  # 1/(V²·s·m²), 1/(V²·s·m), 1/(V²·s)\n",
        f"d_min = {d_min!r}  # m: the model is valid from here ...\n",
        f"d_max = {d_max!r}  # m: ... to here (the calibrated interval)\n",
    ]
    start = next(
        (i for i, line in enumerate(lines) if (m := _TABLE.match(line)) and m.group(1).strip() == "energy_model"), None
    )
    if start is None:
        if lines and not lines[-1].endswith("\n"):
            lines[-1] += "\n"
        out = lines + (["\n"] if lines else []) + body
    else:
        end = next((i for i in range(start + 1, len(lines)) if _TABLE.match(lines[i])), len(lines))
        # Keep the blank lines and comments that lead into the next table.
        while end - 1 > start and (not lines[end - 1].strip() or lines[end - 1].lstrip().startswith("#")):
            end -= 1
        out = lines[:start] + body + lines[end:]
    text = "".join(out)
    tomllib.loads(text)  # never write a file that no longer parses
    path.write_text(text)


# --- what --device serial drives ---------------------------------------------------------
@dataclass(frozen=True)
class SerialSetup:
    """Everything ``--device serial`` drives, from the rig file and the flags that override it."""

    info: ScannerInfo
    motor: MotorConfig
    board: SensorBoardConfig
    gamma_start: float  # rad
    gamma_stop: float  # rad
    steps: int
    energy_model: EnergyModel


def serial_setup(cfg: AcquireConfig) -> SerialSetup:
    """Build the serial scanner of an :class:`~lelsonar.acquire.config.AcquireConfig` from its rig.

    Flags that the config carries (ports, schedule, radial offset, φ) win over the file.
    """
    rig: Rig = cfg.rig or Rig(None, {})
    require_for_serial(rig, serial_overrides(cfg))
    g = rig.get
    geometry = ArrayGeometry(
        capsule_x=tuple(float(x) for x in g("array.capsule_x")),
        radial_offset=float(cfg.radial_offset if cfg.radial_offset is not None else g("array.radial_offset")),
    )
    c, temperature = rig.sound_speed_and_temperature()
    sample_rate = float(g("sensor_board.sample_rate"))
    window = int(g("sensor_board.window_samples"))
    info = ScannerInfo(
        device="serial",
        geometry=geometry,
        sample_rate=sample_rate,
        window_samples=window,
        air_temperature=temperature,
        sound_speed=c,
    )
    gamma_start = cfg.gamma_start if cfg.gamma_start is not None else math.radians(g("schedule.gamma_start_deg"))
    gamma_stop = cfg.gamma_stop if cfg.gamma_stop is not None else math.radians(g("schedule.gamma_stop_deg"))
    lo, hi = math.radians(g("servo.gamma_min_deg")), math.radians(g("servo.gamma_max_deg"))
    for name, v in (("gamma start", gamma_start), ("gamma stop", gamma_stop)):
        if not lo - 1e-9 <= v <= hi + 1e-9:
            raise ConfigError(
                f"the schedule's {name} {math.degrees(v):.1f}° is outside the servo's limits "
                f"[{math.degrees(lo):.1f}°, {math.degrees(hi):.1f}°] ([servo] gamma_min_deg/gamma_max_deg)"
            )
    motor = MotorConfig(
        port=cfg.motor_port or g("servo.port"),
        motor_id=int(g("servo.id", 1)),
        baudrate=int(g("servo.baudrate", 1_000_000)),
        gamma_min=lo,
        gamma_max=hi,
        zero_raw=int(g("servo.zero_raw")),
        moving_speed=int(g("servo.moving_speed", 0)),
        latency_timer_ms=float(g("servo.latency_timer_ms", 16.0)),
    )
    board = SensorBoardConfig(
        port=cfg.sensor_port or g("sensor_board.port"),
        n_samples=window,
        fs_hz=int(round(sample_rate)),
        full_scale_v=float(g("sensor_board.full_scale_v", 1.65)),
        baudrate=int(g("sensor_board.baudrate", 1_000_000)),
        link=rig_links(rig)[1],
    )
    d_min, d_max = g("energy_model.d_min", 0.9), g("energy_model.d_max", 1.8)
    if cfg.energy_model is not None:
        m = cfg.energy_model
        model = EnergyModel(m.phi0, m.phi1, m.phi2, float(d_min), float(d_max))
    else:
        phi0, phi1, phi2 = (float(x) for x in g("energy_model.phi"))  # three numbers: checked by load_rig
        model = EnergyModel(phi0, phi1, phi2, float(d_min), float(d_max))
    steps = cfg.steps if cfg.steps is not None else int(g("schedule.steps"))
    return SerialSetup(info, motor, board, float(gamma_start), float(gamma_stop), steps, model)


def serial_overrides(cfg: AcquireConfig) -> dict[str, Any]:
    """The rig keys that flags of ``cfg`` supply."""
    phi = cfg.energy_model
    return {
        "servo.port": cfg.motor_port,
        "sensor_board.port": cfg.sensor_port,
        "schedule.steps": cfg.steps,
        "schedule.gamma_start_deg": cfg.gamma_start,
        "schedule.gamma_stop_deg": cfg.gamma_stop,
        "array.radial_offset": cfg.radial_offset,
        "energy_model.phi": phi,
        "energy_model.d_min": phi,
        "energy_model.d_max": phi,
    }
