"""The stress sweep's cases: drawn outside the bench families, simulated, recorded in our schema and replayed
through ``lelsonar reconstruct --source X.mcap --json``.

The families and the verdicts: :mod:`lelsonar.tools.bench_stress`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import math
import threading
import traceback
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

FAMILIES: tuple[str, ...] = (
    "distance",
    "opening",
    "tilt",
    "roll",
    "sweep",
    "steps",
    "array",
    "rate",
    "noise",
    "corner",
    "missing",
    "calib",
    "nocorner",
    "wire",
    "mixed",
    "extreme",
    "comparator",
)
#: Verdicts of one wall, in table order.
VERDICTS = ("accurate", "flagged", "claims_good", "crash")
_DEG = math.pi / 180.0
#: The method of record (its planes carry the verdicts) and the compared one, whose σ is judged too.
RECORD, COMPARED = "corner", "ls"
#: Exit codes ``reconstruct --source`` documents: 0 ok, 1 no final / a plane missing, 2 typed error.
DOCUMENTED_EXIT = (0, 1, 2)


@dataclass(frozen=True)
class StressCase:
    """One drawn scene, rig and schedule (SI units, angles in rad).

    ``opening`` is the interior angle of the corner; ``roll`` turns the whole L
    about x; ``skew_a``/``skew_b`` turn plane a about z and plane b about y.
    ``spacing`` is ``uniform``, ``jitter`` (each step moved up to ±40 % of a
    step) or ``dense`` (the middle third of the sweep twice as dense).
    ``missing`` is the share of readings dropped (``missing_runs``: in runs of
    3–10 steps of one capsule instead of scattered).  ``e0_scale`` multiplies
    the announced ``E0(d)``.
    """

    family: str
    seed: int
    distance_a: float = 1.57
    distance_b: float = 1.06
    opening: float = 90.0 * _DEG
    roll: float = 0.0
    skew_a: float = 0.0
    skew_b: float = 0.0
    gamma_start: float = -10.0 * _DEG
    gamma_stop: float = 110.0 * _DEG
    reverse: bool = False
    steps: int = 184
    spacing: str = "uniform"
    capsules: int = 4
    pitch: float = 0.08
    uneven: float = 0.0
    radial_offset: float = 0.03
    sample_rate: float = 200_000.0
    int16: bool = False
    window_start: float = 0.0
    tof_jitter: float = 0.002
    cycle_slip_probability: float = 0.02
    amplitude_noise: float = 0.0
    noise_std: float = 0.002
    corner_gain: float = 1.5
    corner_max_error: float = 10.0 * _DEG
    missing: float = 0.0
    missing_runs: bool = False
    e0_scale: float = 1.0
    permute_capsules: bool = False
    shuffle_samples: bool = False
    timing: str = "onset"
    threshold: float = 0.05
    envelope_time: float = 0.15e-3
    echo_gain: float = 2.5

    def describe(self) -> str:
        """One line of what differs from the paper's setting."""
        base = StressCase(self.family, self.seed)
        parts = []
        for f in dataclasses.fields(self):
            if f.name in ("family", "seed"):
                continue
            v, b = getattr(self, f.name), getattr(base, f.name)
            if v != b:
                if f.name in ("opening", "roll", "skew_a", "skew_b", "gamma_start", "gamma_stop", "corner_max_error"):
                    parts.append(f"{f.name} {math.degrees(v):.1f}°")
                elif isinstance(v, float):
                    parts.append(f"{f.name} {v:.4g}")
                else:
                    parts.append(f"{f.name} {v}")
        return f"{self.family} #{self.seed}: " + (", ".join(parts) or "paper setting")


# ---------------------------------------------------------------------------- drawing
def _critical(case_kw: dict[str, Any]) -> float:
    return _scene(StressCase("mixed", 0, **case_kw), 3.0, 3.0).critical_angle()


def _draw_sweep(rng: np.random.Generator, crit: float) -> dict[str, Any]:
    """Narrow or asymmetric sweeps around ``crit`` (rad), inside the servo's reach."""
    if rng.random() < 0.5:  # narrow: the corner ±12–30°
        lo, hi = crit - rng.uniform(12, 30) * _DEG, crit + rng.uniform(12, 30) * _DEG
    else:  # asymmetric: one side short, the other long
        short, long_ = rng.uniform(8, 20) * _DEG, rng.uniform(45, 80) * _DEG
        lo, hi = (crit - short, crit + long_) if rng.random() < 0.5 else (crit - long_, crit + short)
    return {"gamma_start": max(lo, -40 * _DEG), "gamma_stop": min(hi, 140 * _DEG), "reverse": bool(rng.random() < 0.5)}


def draw_case(family: str, seed: int) -> StressCase:
    """Case ``seed`` of ``family`` (see the module table); the same pair gives the same case."""
    if family not in FAMILIES:
        raise ValueError(f"unknown stress family {family!r}; choose from {', '.join(FAMILIES)}")
    rng = np.random.default_rng([int(seed), zlib.crc32(b"stress-" + family.encode())])
    every = family in ("mixed", "extreme")
    wide = family == "extreme"
    kw: dict[str, Any] = {}
    if family in ("distance", "mixed", "extreme"):
        lo, hi = (0.25, 4.0) if wide else (0.3, 3.0)
        kw.update(distance_a=rng.uniform(lo, hi), distance_b=rng.uniform(lo, hi))
    if family in ("opening", "mixed", "extreme"):
        kw.update(opening=rng.uniform(60, 120) * _DEG if wide else rng.uniform(70, 110) * _DEG)
    if wide:
        kw.update(corner_max_error=44.0 * _DEG)
    if family in ("tilt", "mixed", "extreme"):
        kw.update(
            roll=rng.uniform(-20, 20) * _DEG, skew_a=rng.uniform(-12, 12) * _DEG, skew_b=rng.uniform(-12, 12) * _DEG
        )
    if family == "roll":
        kw.update(roll=rng.uniform(-45, 45) * _DEG)
    if family in ("steps", "mixed", "extreme"):
        kw.update(steps=int(rng.integers(60, 401)), spacing=str(rng.choice(["uniform", "jitter", "dense"])))
    if family in ("array", "mixed", "extreme"):
        kw.update(
            capsules=int(rng.integers(2, 9)),
            pitch=rng.uniform(0.03, 0.15),
            uneven=rng.uniform(0, 0.4),
            radial_offset=rng.uniform(0, 0.1),
        )
    if family in ("rate", "mixed", "extreme"):
        kw.update(
            sample_rate=float(rng.choice([100e3, 125e3, 250e3, 400e3, 1e6])),
            int16=bool(rng.random() < 0.5),
            window_start=float(rng.choice([0.0, 0.5e-3, 1.0e-3])),
        )
    if family in ("noise", "mixed", "extreme"):
        kw.update(
            tof_jitter=rng.uniform(0.001, 0.008),
            cycle_slip_probability=rng.uniform(0, 0.08),
            amplitude_noise=rng.uniform(0, 0.10),
            noise_std=rng.uniform(0.002, 0.012),
        )
    if family in ("corner", "mixed", "extreme"):
        kw.update(corner_gain=rng.uniform(0.0, 3.0))
    if family in ("missing", "mixed", "extreme"):
        kw.update(
            missing=rng.uniform(0.10, 0.35) if not every else rng.uniform(0, 0.2), missing_runs=bool(rng.random() < 0.5)
        )
    if family in ("calib", "mixed", "extreme"):
        lo, hi = (0.1, 10.0) if wide else (0.5, 2.0)
        kw.update(e0_scale=float(np.exp(rng.uniform(math.log(lo), math.log(hi)))))
    if family == "comparator":
        kw.update(
            timing="crossing",
            threshold=float(np.exp(rng.uniform(math.log(0.02), math.log(0.15)))),
            envelope_time=rng.uniform(0.08e-3, 0.4e-3),
            echo_gain=float(np.exp(rng.uniform(0.0, math.log(6.0)))),
            distance_a=rng.uniform(0.6, 2.5),
            distance_b=rng.uniform(0.6, 2.5),
            roll=rng.uniform(-15, 15) * _DEG,
        )
    if family == "wire":
        kw.update(
            capsules=int(rng.integers(2, 9)),
            permute_capsules=True,
            shuffle_samples=bool(rng.random() < 0.5),
            reverse=bool(rng.random() < 0.5),
        )
    crit = _critical(kw)
    if family == "sweep" or ((every or family == "comparator") and rng.random() < 0.5):
        kw.update(_draw_sweep(rng, crit))
        if every:
            kw.update(reverse=bool(rng.random() < 0.5))
    elif family == "nocorner":
        if rng.random() < 0.5:  # only wall a
            kw.update(gamma_start=crit - rng.uniform(70, 90) * _DEG, gamma_stop=crit - rng.uniform(15, 25) * _DEG)
        else:
            kw.update(gamma_start=crit + rng.uniform(15, 25) * _DEG, gamma_stop=crit + rng.uniform(70, 90) * _DEG)
        kw.update(reverse=bool(rng.random() < 0.5))
    else:
        kw.update(gamma_start=min(-10 * _DEG, crit - 60 * _DEG), gamma_stop=max(110 * _DEG, crit + 60 * _DEG))
        if every:
            kw.update(reverse=bool(rng.random() < 0.5))
    return StressCase(family, int(seed), **kw)


# ---------------------------------------------------------------------------- simulation
def _scene(case: StressCase, height_a: float, height_b: float):
    from lelsonar.geometry import rotation_x
    from lelsonar.sim.scene import Scene

    half = (case.opening - math.pi / 2) / 2  # opening = 90° + tilt_a_x − tilt_b_x
    if max(abs(case.roll + half), abs(case.roll - half)) <= math.radians(30):
        return Scene.l_corner(
            case.distance_a,
            case.distance_b,
            tilt_a_x=case.roll + half,
            tilt_b_x=case.roll - half,
            tilt_a_z=case.skew_a,
            tilt_b_y=case.skew_b,
            width=4.0,
            height_a=height_a,
            height_b=height_b,
        )
    # Beyond l_corner's ±30° tilts: the unrolled L turned as a whole about the rotation axis (offsets kept).
    base = Scene.l_corner(
        case.distance_a,
        case.distance_b,
        tilt_a_x=half,
        tilt_b_x=-half,
        tilt_a_z=case.skew_a,
        tilt_b_y=case.skew_b,
        width=4.0,
        height_a=height_a,
        height_b=height_b,
    )
    turn = rotation_x(case.roll)
    panels = tuple(
        dataclasses.replace(
            p, center=turn @ np.array(p.center), normal=turn @ np.array(p.normal), u_axis=turn @ np.array(p.u_axis)
        )
        for p in base.panels
    )
    return Scene(panels=panels, corners=base.corners)


def _schedule(case: StressCase, rng: np.random.Generator) -> np.ndarray:
    """Commanded γ per step, in the order of the scan (reversed: high to low)."""
    n = case.steps
    if case.spacing == "dense":
        # Warp [0, 1] so the middle third of the sweep gets half the steps (twice the density).
        g = np.interp(np.linspace(0, 1, n), [0, 0.25, 0.75, 1.0], [0, 1 / 3, 2 / 3, 1.0])
    else:
        g = np.linspace(0, 1, n)
        if case.spacing == "jitter" and n > 2:
            g[1:-1] += rng.uniform(-0.4, 0.4, n - 2) / (n - 1)
    gamma = case.gamma_start + g * (case.gamma_stop - case.gamma_start)
    return gamma[::-1].copy() if case.reverse else gamma


def build_config(case: StressCase):
    """The :class:`SimConfig` of a case: panels wide enough for every beam, window long enough for every echo."""
    from lelsonar.geometry import ArrayGeometry
    from lelsonar.sim.acoustics import Acoustics, Receiver
    from lelsonar.sim.config import SimConfig
    from lelsonar.sim.scenes import check_config, required_window_samples

    x = (np.arange(case.capsules) - (case.capsules - 1) / 2) * case.pitch
    if case.uneven > 0:  # uneven spacing, still in order along +x (the schema's capsule order)
        x = x + np.random.default_rng([case.seed, 7]).uniform(-0.5, 0.5, x.size) * case.uneven * case.pitch
    geometry = ArrayGeometry(capsule_x=tuple(float(v) for v in x), radial_offset=case.radial_offset)
    acoustics = Acoustics(corner_gain=case.corner_gain, corner_max_error=case.corner_max_error)
    receiver = Receiver(
        tof_jitter=case.tof_jitter,
        cycle_slip_probability=case.cycle_slip_probability,
        amplitude_noise=case.amplitude_noise,
        noise_std=case.noise_std,
        timing=case.timing,
        threshold=case.threshold,
        envelope_time=case.envelope_time,
        echo_gain=case.echo_gain,
    )
    far_a = max(0.0, -case.gamma_start) + 10 * _DEG
    far_b = max(0.0, case.gamma_stop - math.pi / 2) + 10 * _DEG
    height_a = case.distance_b + case.distance_a * math.tan(min(far_a, 75 * _DEG)) + 0.3
    height_b = case.distance_a + case.distance_b * math.tan(min(far_b, 75 * _DEG)) + 0.3
    problems: list[str] = []
    for _ in range(8):
        scene = _scene(case, height_a, height_b)
        cfg = SimConfig(
            scene=scene,
            geometry=geometry,
            gamma_start=min(case.gamma_start, case.gamma_stop),
            gamma_stop=max(case.gamma_start, case.gamma_stop),
            steps=case.steps,
            sample_rate=case.sample_rate,
            window_start=case.window_start,
            acoustics=acoustics,
            receiver=receiver,
        )
        cfg = dataclasses.replace(cfg, window_samples=max(int(0.0175 * case.sample_rate), required_window_samples(cfg)))
        problems = [p for p in check_config(cfg) if "corner" not in p or case.family not in ("nocorner", "sweep")]
        problems = [p for p in problems if "does not contain the corner" not in p]
        if not problems:
            return cfg
        height_a += 0.5
        height_b += 0.5
    raise ValueError(f"no valid configuration for {case.describe()}: {'; '.join(problems)}")


@dataclass(frozen=True, eq=False)
class StressScan:
    """A simulated scan on the case's schedule, in scan order, with its ground truth."""

    case: StressCase
    config: Any
    commanded: np.ndarray
    gamma_measured: np.ndarray
    gamma_raw: np.ndarray
    tof: np.ndarray
    waveforms: np.ndarray
    echo_source: np.ndarray  # EchoSource per step and capsule (NONE where dropped)

    @property
    def t0(self) -> float:
        """s; start of every waveform (what :class:`~lelsonar.acquire.simulated.ScanReplay` replays)."""
        return float(self.config.window_start)


def simulate(case: StressCase) -> StressScan:
    """Simulate ``case`` with the simulator's physics on its own schedule (seeded by the case)."""
    from lelsonar.sim.scan import (
        EchoSource,
        apply_amplitude_noise,
        comparator_time_of_flight,
        digitised_waveforms,
        echo_table,
        first_echo,
    )

    cfg = build_config(case)
    rng = np.random.default_rng([case.seed, zlib.crc32(b"scan-" + case.family.encode())])
    commanded = _schedule(case, rng)
    servo = cfg.servo
    goal = servo.to_raw(commanded)
    gamma_true = servo.to_gamma(goal) + rng.standard_normal(commanded.shape) * servo.position_error
    raw = np.clip(servo.to_raw(gamma_true), 0, 1023)
    measured = servo.to_gamma(raw)
    echoes = apply_amplitude_noise(cfg, echo_table(cfg, gamma_true), rng)
    _range, source, _index, delay = first_echo(cfg, echoes)
    tof = comparator_time_of_flight(cfg, _range, rng, delay)
    waveforms = digitised_waveforms(cfg, echoes, rng)
    if case.missing > 0:
        n, m = tof.shape
        drop = np.zeros((n, m), dtype=bool)
        if case.missing_runs:
            while drop.mean() < case.missing:
                k, j, length = rng.integers(n), rng.integers(m), rng.integers(3, 11)
                drop[k : k + length, j] = True
        else:
            drop = rng.random((n, m)) < case.missing
        tof = np.where(drop, np.nan, tof)
        source = np.where(drop, EchoSource.NONE, source)
    return StressScan(case, cfg, commanded, measured, raw, tof, waveforms, source)


def energy_model(scan: StressScan):
    """The ``E0(d)`` announced: the rig's own six-shot calibration, times the case's ``e0_scale``."""
    from lelsonar.energy_model import EnergyModel
    from lelsonar.sim.scenes import calibrated_energy_model

    m = calibrated_energy_model(scan.config)
    s = scan.case.e0_scale
    return EnergyModel(m.phi0 / s, m.phi1 / s, m.phi2 / s, m.d_min, m.d_max)


class _WireVariations:
    """Between the scan loop and the recorder: capsules listed in another order, samples written out of order.

    Both are within the schema (capsules are matched by ``capsule_id``, samples by ``step``); our own writer
    never produces them.
    """

    def __init__(self, recorder: Any, case: StressCase) -> None:
        self.recorder = recorder
        rng = np.random.default_rng([case.seed, 11])
        self.order = rng.permutation(case.capsules) if case.permute_capsules else None
        self.shuffle = rng if case.shuffle_samples else None
        self.held: list[Any] = []

    def write(self, message: Any) -> None:
        from lelsonar import codec

        if self.order is not None and isinstance(message, (codec.ScanStart, codec.Sample)):
            field: Any = message.capsules if isinstance(message, codec.ScanStart) else message.sensors
            items = [type(field[0])() for _ in range(len(field))]
            for item, i in zip(items, self.order):
                item.CopyFrom(field[int(i)])
            del field[:]
            field.extend(items)
        if self.shuffle is not None and isinstance(message, codec.Sample):
            self.held.append(message)
            return
        if self.shuffle is not None and isinstance(message, codec.ScanEnd):
            times = sorted(m.acquisition_time_ns for m in self.held)
            for t, k in zip(times, self.shuffle.permutation(len(self.held))):
                self.recorder.write(self.held[int(k)], log_time_ns=t)  # step order lost in the file too
        self.recorder.write(message)

    def log(self, level: str, text: str) -> None:
        self.recorder.log(level, text)


def record(scan: StressScan, path: Path) -> None:
    """Write ``scan`` as ``lelsonar acquire --device sim`` would (scan loop + recorder)."""
    from lelsonar.acquire.scan_loop import ScanIdentity, ScanOutput, run_scan
    from lelsonar.acquire.simulated import ScanReplay
    from lelsonar.log.recording import McapRecorder

    int16_scale = scan.config.receiver.adc_lsb if scan.case.int16 else None
    with McapRecorder(path, compression="zstd", metadata={"device": "sim", "stress": scan.case.describe()}) as rec:
        out = _WireVariations(rec, scan.case) if scan.case.permute_capsules or scan.case.shuffle_samples else rec
        run_scan(
            ScanReplay(scan),  # type: ignore[arg-type]  # a StressScan has every field ScanReplay reads
            scan.commanded,
            ScanIdentity("stress", 1),
            energy_model(scan),
            ScanOutput(out, None),  # type: ignore[arg-type]  # _WireVariations writes and logs as a recorder does
            threading.Event(),
            int16_scale=int16_scale,
        )


def run_cli(
    path: Path, method: str | None = None, compare: str = COMPARED
) -> tuple[int | None, list[dict[str, Any]], str]:
    """``lelsonar reconstruct --source PATH --json --compare COMPARE`` in process: exit code, JSON lines, error."""
    from lelsonar.cli.main import main

    argv = ["reconstruct", "--source", str(path), "--json", "--compare", compare]
    if method:
        argv += ["--method", method]
    out, err = io.StringIO(), io.StringIO()
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = main(argv)
    except BaseException as exc:  # noqa: BLE001 — any escape is the crash this sweep looks for
        return None, [], f"{type(exc).__name__}: {exc}\n{traceback.format_exc(limit=6)}"
    lines = [json.loads(line) for line in out.getvalue().splitlines() if line.startswith("{")]
    return code, lines, err.getvalue()[-2000:]
