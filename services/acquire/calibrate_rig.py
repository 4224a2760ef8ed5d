"""``lelsonar calibrate --device serial``: the paper's six face-on shots on a real rig, φ written back.

The servo turns the array face-on (γ = 0); for each of the six distances the
user places a flat wall parallel to the array, measures the distance from the
capsule faces to the wall, and types it.  The board fires, the summed waveform
energy ``E^{0°}(d)`` (eq. 10–11) is kept, and eq. (12) is fitted by eq. (13)–(14).
The board's own range (c·TOF/2) is shown next to the typed one, so a typo or a
wall that is not where it should be shows at once; a fit whose shots disagree
beyond :func:`range_tolerance` is refused unless forced.  φ and its valid range go
into the rig file's ``[energy_model]`` table; every other line of the file is kept.
"""

from __future__ import annotations

import datetime as _dt
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lelsonar.acquire.devices.dynamixel import DynamixelMotor
from lelsonar.acquire.devices.motor import MotorConfig
from lelsonar.acquire.devices.sensor_board import SensorBoardConfig, SerialSensorBoard
from lelsonar.acquire.rig import REQUIRED_FOR_SERIAL, Rig, load_rig, rig_links, write_energy_model
from lelsonar.errors import ConfigError
from lelsonar.signal.energy import EnergyModel, fit_energy_model, total_energy, waveform_energy

#: Keys the calibration needs from the rig file: a scan's, but φ (it measures it), the schedule and the array's
#: geometry (it shoots face-on at set distances).
REQUIRED_FOR_CALIBRATION = tuple(
    need for need in REQUIRED_FOR_SERIAL if need.partition(".")[0] not in ("energy_model", "schedule", "array")
)


#: The capsules' carrier, Hz: a comparator that slips one cycle moves the range by c / (2 f).
CARRIER_HZ = 40_000.0
#: A tape measure read to the centimetre, m.
TAPE_TOLERANCE = 0.01
#: The speed of sound's relative error when the rig file's temperature is off by about 6 °C.
SOUND_SPEED_TOLERANCE = 0.01


@dataclass(frozen=True)
class Shot:
    distance: float  # m, as typed
    energy: float  # V²·s, summed over the capsules
    board_range: float  # m, median c·TOF/2 of the capsules with an echo (NaN: none)
    tolerance: float = float("inf")  # m, how far board_range may be from distance (range_tolerance)

    @property
    def agrees(self) -> bool:
        """The board saw a wall where the typed distance says, within the noise model."""
        return bool(np.isfinite(self.board_range) and abs(self.board_range - self.distance) <= self.tolerance)


def range_tolerance(distance: float, sound_speed: float) -> float:
    """How far the board's range may lie from a typed distance on a good shot, m.

    The sum of the tape's reading (:data:`TAPE_TOLERANCE`), one slipped carrier cycle of the
    comparator (c / 2f), and the range error of a speed of sound off by :data:`SOUND_SPEED_TOLERANCE`.
    """
    return TAPE_TOLERANCE + sound_speed / (2.0 * CARRIER_HZ) + SOUND_SPEED_TOLERANCE * distance


def check_shots(shots: list[Shot]) -> None:
    """Refuse shots whose board range disagrees with the typed distance.

    Raises
    ------
    ConfigError
        Naming each such shot; the fit would calibrate E0 against the wrong distances.
    """
    bad = [(i, s) for i, s in enumerate(shots, 1) if not s.agrees]
    if not bad:
        return
    what = ", ".join(
        f"shot {i} typed {s.distance:.3f} m, board "
        + (f"{s.board_range:.3f} m (±{s.tolerance:.3f})" if np.isfinite(s.board_range) else "no echo")
        for i, s in bad
    )
    raise ConfigError(
        f"{len(bad)} of {len(shots)} shots disagree with their typed distance ({what}); the rig file is "
        "unchanged: check the wall and the tape and shoot again, or pass --force to write the fit anyway"
    )


def _require(rig: Rig, overrides: dict) -> None:
    given = {f"{t}.{k}" for t, kv in rig.values.items() for k in kv} | {k for k, v in overrides.items() if v}
    missing = [need for need in REQUIRED_FOR_CALIBRATION if not any(o in given for o in need.split(" or "))]
    if missing:
        raise ConfigError(
            f"calibrate --device serial takes the rig from {rig.path}; missing: {', '.join(missing)} "
            "(see examples/rig.toml)"
        )


def calibrate_serial(
    rig_path: Path,
    distances: tuple[float, ...],
    ask: Callable[[str], str],
    say: Callable[[str], None],
    *,
    motor_port: str | None = None,
    sensor_port: str | None = None,
    write: bool = True,
    force: bool = False,
) -> tuple[list[Shot], EnergyModel]:
    """Guide the shots, fit φ and (unless ``write`` is False) write it into ``rig_path``.

    Parameters
    ----------
    rig_path : Path
        The rig file (read for the ports, the servo and the board; its ``[energy_model]`` is rewritten).
    distances : tuple of float
        Where to place the wall, m; the user types what was actually measured.
    ask : callable
        Shows a prompt and returns the typed line (``input`` at a terminal).
    say : callable
        Prints a line.
    force : bool
        Fit (and write) even when shots disagree with their typed distance (:func:`check_shots`).

    Raises
    ------
    ConfigError
        Missing rig keys, an unparsable distance, the user quit, too few usable shots, or shots that
        disagree with their distances (without ``force``).
    """
    rig = load_rig(rig_path)
    _require(rig, {"servo.port": motor_port, "sensor_board.port": sensor_port})
    g = rig.get
    c, _temperature = rig.sound_speed_and_temperature()
    motor_cfg = MotorConfig(
        port=motor_port or g("servo.port"),
        motor_id=int(g("servo.id", 1)),
        baudrate=int(g("servo.baudrate", 1_000_000)),
        gamma_min=np.radians(g("servo.gamma_min_deg")),
        gamma_max=np.radians(g("servo.gamma_max_deg")),
        zero_raw=int(g("servo.zero_raw")),
        moving_speed=int(g("servo.moving_speed", 0)),
        latency_timer_ms=float(g("servo.latency_timer_ms", 16.0)),
    )
    sample_rate = float(g("sensor_board.sample_rate"))
    board_cfg = SensorBoardConfig(
        port=sensor_port or g("sensor_board.port"),
        n_samples=int(g("sensor_board.window_samples")),
        fs_hz=int(round(sample_rate)),
        full_scale_v=float(g("sensor_board.full_scale_v", 1.65)),
        baudrate=int(g("sensor_board.baudrate", 1_000_000)),
        link=rig_links(rig)[1],
    )
    shots: list[Shot] = []
    with DynamixelMotor(motor_cfg) as motor, SerialSensorBoard(board_cfg) as board:
        pos = motor.move_to(0.0)
        say(f"array face-on: γ = {np.degrees(pos.gamma):.2f}° (raw {pos.raw}); c = {c:.1f} m/s")
        for i, nominal in enumerate(distances):
            line = ask(
                f"shot {i + 1}/{len(distances)}: place a flat wall face-on about {nominal:.2f} m from the "
                f"capsule faces, measure that distance and type it in m (Enter: {nominal:.2f}, q: quit): "
            )
            text = line.strip()
            if text.lower() in ("q", "quit"):
                raise ConfigError("calibration stopped; the rig file is unchanged")
            try:
                d = float(text) if text else float(nominal)
            except ValueError:
                raise ConfigError(f"shot {i + 1}: {text!r} is not a distance in m; the rig file is unchanged") from None
            if not 0.05 < d < 10.0:
                raise ConfigError(f"shot {i + 1}: {d} m is not a plausible wall distance")
            shot = board.fire(i)
            e = float(total_energy(waveform_energy(np.asarray(shot.waveforms, dtype=np.float64), shot.fs_hz)))
            tof = np.asarray(shot.tof_s, dtype=float)
            ranges = c * tof[np.isfinite(tof)] / 2.0
            board_range = float(np.median(ranges)) if ranges.size else float("nan")
            shots.append(Shot(d, e, board_range, range_tolerance(d, c)))
            check = f"board range {board_range:.3f} m" if np.isfinite(board_range) else "no echo"
            warn = "" if shots[-1].agrees else "  ← check the wall and the tape"
            say(f"  d = {d:.3f} m: E = {e:.4e} V²·s, {check}{warn}")
    if not force:
        check_shots(shots)
    distances_m = np.array([s.distance for s in shots])
    model = fit_energy_model(distances_m, np.array([s.energy for s in shots]))
    if write:
        note = (
            f"calibrated {_dt.datetime.now(_dt.UTC):%Y-%m-%d %H:%M} UTC by `lelsonar calibrate "
            f"--device serial` from {len(shots)} face-on shots at {', '.join(f'{x:.3f}' for x in distances_m)} m"
        )
        write_energy_model(rig_path, (model.phi0, model.phi1, model.phi2), model.d_min, model.d_max, note)
    return shots, model
