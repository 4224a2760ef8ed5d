"""``lelsonar bench estimators --stress all``: scans *outside* the bench families, run through the real CLI path.

The project is judged on scenes from an independent simulator, recorded in
our schema and replayed with ``lelsonar reconstruct --source X.mcap --json``.
This sweep draws scenes and rigs the seeded families of
:mod:`lelsonar.sim.scenes` never produce, alone and in combination:

=============  =================================================================
family         what is drawn
=============  =================================================================
``distance``   each wall at 0.3–3 m, independently (unequal)
``opening``    corner opening 70–110° (one wall rolled against the other)
``tilt``       the whole L rolled ±20°, each wall skewed ±12° (edge off x)
``roll``       the whole L rolled ±45° (a robot far from square to the corner)
``sweep``      narrow (corner ±12–30°) and asymmetric sweeps, half reversed
               (γ from high to low: ``ScanStart.direction`` DECREASING)
``steps``      60–400 steps, uniform, jittered or two densities
``array``      2–8 capsules, pitch 3–15 cm, uneven (±40 % of the pitch),
               radial offset 0–10 cm
``rate``       sample rate 100 kHz–1 MHz, INT16 or float32 waveforms, late t0
``noise``      range jitter 1–8 mm, slips 0–8 %, amplitude noise 0–10 %,
               receiver noise 2–12 mV
``corner``     corner (double-bounce) gain 0–3
``missing``    10–35 % of readings without an echo, scattered or in runs
``calib``      the announced ``E0(d)`` off by a factor 0.5–2 (another rig's)
``nocorner``   a sweep that sees only one wall (the corner is outside it)
``wire``       what the schema allows and our writer never does: capsules
               listed in another order (in ``ScanStart`` and every
               ``Sample``), samples written out of step order, reversed
``mixed``      all of the above at once (reversed half the time)
``extreme``    mixed, wider: walls 0.25–4 m, opening 60–120° with double
               bounces at any opening (a simulator without the 90° ±10°
               retro-reflection limit), ``E0`` off by 0.1–10, reversed half
               the time
``comparator`` a board whose comparator times the echo's threshold crossing
               (``Receiver.timing = "crossing"``: later on weaker echoes):
               threshold 0.02–0.15 V, envelope rise
               0.08–0.4 ms, echo gain 1–6 V·m, walls 0.6–2.5 m, the L rolled
               ±15°, half the sweeps narrow or asymmetric
=============  =================================================================

Each scan is simulated by the project's simulator physics
(:func:`lelsonar.sim.scan.echo_table` and the comparator, noise and
waveform stages of :func:`simulate_scan`), but on any schedule (order and
spacing), recorded by the acquisition scan loop and
:class:`lelsonar.log.recording.McapRecorder` exactly as ``lelsonar acquire``
writes it, and reconstructed by ``lelsonar reconstruct --source FILE --json``
(the CLI's ``main``, in process, stdout captured).

Every wall of the scene is judged against its ground truth (the scene's
panel) and the oracle (LS on the true mirror echoes, as
:mod:`lelsonar.tools.bench_families`):

* **accurate**: not a failure (patch error ≤ 2 cm or ≤ 3× the oracle's);
* **flagged**: a failure whose quality is not ``good`` (degraded/unreliable,
  with ``quality_reasons``), or no plane with a non-zero exit code;
* **claims good** (the bug): a failure whose quality is ``good``; also a
  ``good`` plane of a wall that was never observed (fewer than 3 mirror echoes);
* **crash**: the command raised, printed no JSON line, or exited with an
  undocumented code (documented: 0, 1 = no final or a method produced no
  plane, 2 = typed error).

Every plane's reported standard errors are judged too (principle 1: an honest
σ), for the method of record ``corner`` and the compared ``ls``
(``--compare ls``: the cross-check only degrades the compared planes, the
record's are unchanged): **z** = error / standard error for the normal (angle
/ ``normal_stderr``) and the offset (``(h − h_true)/offset_stderr``), as
:mod:`lelsonar.tools.bench_families` — median |z| ≈ 0.8 / 0.7 and ~0.3 %
beyond 3 when calibrated.  The z table gives, per family, the median |z| and
the share beyond 3 over the planes that claim ``good`` and over all planes of
observed walls.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import io
import json
import math
import os
import tempfile
import threading
import traceback
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lelsonar.cli.executor import add_ray_argument, config_from_args, map_values
from lelsonar.tools.bench_families import (
    frac_above,
    is_failure,
    json_default,
    ls_plane,
    percentile,
    plane_errors,
    z_score,
)

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
        _amplitude_noise,
        _first_echo,
        _time_of_flight,
        _waveforms,
        echo_table,
    )

    cfg = build_config(case)
    rng = np.random.default_rng([case.seed, zlib.crc32(b"scan-" + case.family.encode())])
    commanded = _schedule(case, rng)
    servo = cfg.servo
    goal = servo.to_raw(commanded)
    gamma_true = servo.to_gamma(goal) + rng.standard_normal(commanded.shape) * servo.position_error
    raw = np.clip(servo.to_raw(gamma_true), 0, 1023)
    measured = servo.to_gamma(raw)
    echoes = _amplitude_noise(cfg, echo_table(cfg, gamma_true), rng)
    _range, source, _index, delay = _first_echo(cfg, echoes)
    tof = _time_of_flight(cfg, _range, rng, delay)
    waveforms = _waveforms(cfg, echoes, rng)
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
            field = message.capsules if isinstance(message, codec.ScanStart) else message.sensors
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
            ScanReplay(scan),
            scan.commanded,
            ScanIdentity("stress", 1),
            energy_model(scan),
            ScanOutput(out, None),
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


# ---------------------------------------------------------------------------- judging
def judge(scan: StressScan, code: int | None, lines: list[dict[str, Any]], error: str) -> list[dict[str, Any]]:
    """One row per wall: errors against the truth and the oracle, quality, verdict (see the module docstring)."""
    from lelsonar.sim.scan import EchoSource

    cfg = scan.config
    pc = cfg.geometry.capsule_positions(scan.gamma_measured)
    distance = cfg.sound_speed * scan.tof / 2.0
    rows = []
    crashed = code not in DOCUMENTED_EXIT or not lines
    # Consumers pick the plane of record by method name (a fallback plane carries that name too).
    all_planes = [p for msg in lines for p in msg.get("planes", [])]
    planes = [p for p in all_planes if p.get("method", RECORD) == RECORD]
    compared = [p for p in all_planes if p.get("method") == COMPARED]
    for label, src, panel in (
        ("a", EchoSource.PLANE_A, cfg.scene.panels[0]),
        ("b", EchoSource.PLANE_B, cfg.scene.panels[1]),
    ):
        n_true, h_true = np.asarray(panel.normal), panel.offset
        m = (scan.echo_source == src) & np.isfinite(distance)
        patch = pc[m] + (h_true - pc[m] @ n_true)[:, None] * n_true
        oracle = float("nan")
        if m.sum() >= 3:
            n_o, h_o, _, _ = ls_plane(pc[m] + distance[m][:, None] * n_true)
            oracle = plane_errors(n_o, h_o, n_true, h_true, patch)[2]
        row: dict[str, Any] = {
            "family": scan.case.family,
            "seed": scan.case.seed,
            "label": label,
            "reverse": scan.case.reverse,
            "n_mirror": int(m.sum()),
            "oracle_patch_cm": oracle,
            "exit": code,
        }
        fit = next((p for p in planes if p.get("label") == label), None)
        if crashed:
            row.update(verdict="crash", error=error.strip().splitlines()[-1:] if error else ["no JSON line"])
        elif fit is None:
            # No plane is an honest answer only with the documented non-zero exit.
            row.update(verdict="flagged" if code != 0 else "claims_good", quality=None)
        else:
            n = np.array([fit["normal"].get(k, 0.0) for k in ("x", "y", "z")])
            h = float(fit.get("offset", 0.0))
            quality = fit.get("quality")
            row.update(quality=quality, reasons=fit.get("quality_reasons", []))
            if m.sum() >= 3:
                ang, off, pe = plane_errors(n, h, n_true, h_true, patch)
                row.update(angle_deg=ang, offset_cm=off, patch_cm=pe, **_z_fields(fit, ang, off))
                wrong = is_failure(pe, oracle)
            else:  # never observed: any plane is a guess
                wrong = True
            row["verdict"] = "accurate" if not wrong else ("claims_good" if quality == "good" else "flagged")
        other = next((p for p in compared if p.get("label") == label), None)
        if not crashed and other is not None and m.sum() >= 3:
            n = np.array([other["normal"].get(k, 0.0) for k in ("x", "y", "z")])
            ang, off, pe = plane_errors(n, float(other.get("offset", 0.0)), n_true, h_true, patch)
            row.update(
                {f"{COMPARED}_{k}": v for k, v in _z_fields(other, ang, off).items()},
                **{f"{COMPARED}_quality": other.get("quality"), f"{COMPARED}_patch_cm": pe},
            )
        rows.append(row)
    return rows


def _z_fields(plane: dict[str, Any], angle_deg: float, offset_cm: float) -> dict[str, float]:
    """A JSON plane's standard errors (°, cm) and z-scores of its angle (°) and offset (cm) errors."""
    se_n = float(plane.get("normal_stderr", float("nan")))
    se_h = float(plane.get("offset_stderr", float("nan")))
    return {
        "normal_stderr_deg": math.degrees(se_n),
        "offset_stderr_cm": 100.0 * se_h,
        "z_angle": z_score(math.radians(angle_deg), se_n),
        "z_offset": z_score(offset_cm / 100.0, se_h),
    }


def stress_scan(family: str, seed: int, keep_dir: str | None = None) -> list[dict[str, Any]]:
    """Draw, simulate, record, reconstruct through the CLI and judge one case; rows per wall."""
    from lelsonar.errors import ConfigError, PayloadTooLargeError

    try:
        case = draw_case(family, seed)
        scan = simulate(case)
    except (ValueError, ConfigError) as exc:  # an impossible scene is the sweep's problem, not the estimator's
        return [{"family": family, "seed": seed, "label": "-", "verdict": "skipped", "error": str(exc)}]
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(keep_dir or tmp) / f"{family}-{seed}.mcap"
        path.parent.mkdir(parents=True, exist_ok=True)
        try:
            record(scan, path)
        except PayloadTooLargeError as exc:  # the recorder refuses it (e.g. a window over the codec's limit)
            return [{"family": family, "seed": seed, "label": "-", "verdict": "skipped", "error": str(exc)}]
        code, lines, error = run_cli(path)
        rows = judge(scan, code, lines, error)
        if keep_dir and not any(r["verdict"] in ("claims_good", "crash") for r in rows):
            path.unlink()
    for r in rows:
        r["case"] = case.describe()
    return rows


def tally(rows: list[dict[str, Any]]) -> dict[str, dict[str, int]]:
    """Per family (and ``all``): planes and the count of each verdict."""
    out: dict[str, dict[str, int]] = {}
    for r in rows:
        if r["verdict"] == "skipped":
            continue
        for key in (r["family"], "all"):
            t = out.setdefault(key, {"planes": 0, "unseen": 0, **{v: 0 for v in VERDICTS}})
            t["planes"] += 1
            t["unseen"] += int(r.get("n_mirror", 0) < 3)
            t[r["verdict"]] += 1
    return out


def z_summary(rows: list[dict[str, Any]], prefix: str = "") -> dict[str, dict[str, float]]:
    """Per family (and ``all``): the z-scores of one method's planes (``prefix`` ``""`` record, ``"ls_"`` compared).

    For ``good`` (planes claiming good) and ``all`` (every plane of an observed wall): ``n``, median |z| and
    the share of |z| > 3, of the normal (``zn``) and the offset (``zh``).
    """

    def num(r: dict[str, Any], key: str) -> float:
        v = r.get(prefix + key)
        return float(v) if v is not None else float("nan")

    out: dict[str, dict[str, float]] = {}
    for fam in {r["family"] for r in rows} | {"all"}:
        fr = [r for r in rows if (fam == "all" or r["family"] == fam) and math.isfinite(num(r, "z_angle"))]
        stats: dict[str, float] = {}
        for which, sel in (("good", [r for r in fr if r.get(prefix + "quality") == "good"]), ("all", fr)):
            zn = np.abs([num(r, "z_angle") for r in sel], dtype=float)
            zh = np.abs([num(r, "z_offset") for r in sel], dtype=float)
            stats.update(
                {
                    f"{which}_n": len(sel),
                    f"{which}_zn_med": percentile(zn, 50),
                    f"{which}_zn_gt3": frac_above(zn, 3.0),
                    f"{which}_zh_med": percentile(zh, 50),
                    f"{which}_zh_gt3": frac_above(zh, 3.0),
                }
            )
        out[fam] = stats
    return out


def _z_cell(s: dict[str, float], which: str, z: str) -> str:
    med, gt3 = s.get(f"{which}_{z}_med", float("nan")), s.get(f"{which}_{z}_gt3", float("nan"))
    if not math.isfinite(med):
        return "–"
    return f"{med:.2f}, {100 * gt3:.0f} %"


def run_stress(args: argparse.Namespace) -> int:
    """Run the sweep; print the table and the bugs; exit 1 if any wall claims good while wrong or a scan crashed."""
    from rich.console import Console
    from rich.table import Table

    families = FAMILIES if "all" in args.stress else tuple(args.stress)
    for f in families:
        if f not in FAMILIES:
            raise SystemExit(f"unknown stress family {f!r}; choose from all, {', '.join(FAMILIES)}")
    jobs = [(f, s) for f in families for s in range(args.first_seed, args.first_seed + args.seeds)]
    rows: list[dict[str, Any]] = []
    items = [(f, s, args.keep) for f, s in jobs]
    for res in map_values(stress_scan, items, config_from_args(args, "jobs")):
        rows.extend(res)
    console = Console(width=max(Console().width, 160))
    table = Table(title=f"stress sweep: {args.seeds} seeds from {args.first_seed}, method corner")
    for col in ("family", "planes", "unseen", *VERDICTS):
        table.add_column(col, justify="right" if col != "family" else "left")
    counts = tally(rows)
    for fam in (*families, "all"):
        if fam in counts:
            t = counts[fam]
            table.add_row(fam, str(t["planes"]), str(t["unseen"]), *(str(t[v]) for v in VERDICTS))
    console.print(table)
    console.print(
        "planes: walls of the scenes; unseen: walls with fewer than 3 true mirror echoes (no plane, or a "
        "flagged one, is the right answer); accurate: patch error ≤ 2 cm or ≤ 3× the oracle's; flagged: "
        "a failure whose quality is not good, or no plane with a non-zero exit; claims_good: a failure "
        "(or a plane of an unseen wall) whose quality is good; crash: an exception, no JSON line or an "
        "undocumented exit code"
    )
    zs = {m: z_summary(rows, prefix) for m, prefix in ((RECORD, ""), (COMPARED, COMPARED + "_"))}
    zt = Table(title="honest σ: |z| = |error| / reported standard error (median, share > 3), normal and offset")
    for col in ("family", "method", "good", "|z_n| good", "|z_h| good", "all", "|z_n| all", "|z_h| all"):
        zt.add_column(col, justify="right" if col not in ("family", "method") else "left")
    for fam in (*families, "all"):
        for m in (RECORD, COMPARED):
            s = zs[m].get(fam)
            if s:
                zt.add_row(
                    fam,
                    m,
                    str(s["good_n"]),
                    _z_cell(s, "good", "zn"),
                    _z_cell(s, "good", "zh"),
                    str(s["all_n"]),
                    _z_cell(s, "all", "zn"),
                    _z_cell(s, "all", "zh"),
                )
        zt.add_section()
    console.print(zt)
    console.print(
        "calibrated: median |z| ≈ 0.8 (normal, a 2-D tilt) / 0.7 (offset) and ~0.3 % beyond 3; "
        f"{COMPARED}'s quality is after the cross-check against the method of record"
    )
    bad = [r for r in rows if r["verdict"] in ("claims_good", "crash")]
    for r in bad:
        console.print(
            f"[red]{r['verdict']}[/] {r['case']} plane {r['label']}: "
            f"patch {r.get('patch_cm', float('nan')):.2f} cm (oracle {r.get('oracle_patch_cm', float('nan')):.2f}), "
            f"mirror echoes {r.get('n_mirror')}, exit {r.get('exit')} {r.get('error', '')}",
            highlight=False,
        )
    skipped = [r for r in rows if r["verdict"] == "skipped"]
    if skipped:
        console.print(f"{len(skipped)} draws skipped (invalid configuration): {skipped[0]['error']}")
    if args.json:
        Path(args.json).write_text(
            json.dumps({"rows": rows, "tally": counts, "z": zs}, default=json_default, indent=None), encoding="utf-8"
        )
    return 1 if bad else 0


def add_stress_arguments(parser: argparse.ArgumentParser) -> None:
    """``--stress FAMILY…`` (with ``--seeds``, ``--first-seed``, ``--jobs``, ``--json`` shared)."""
    g = parser.add_argument_group("stress sweep (scenes outside the families, through reconstruct --source)")
    g.add_argument(
        "--stress", nargs="+", metavar="NAME", help=f"run the stress sweep: 'all' or names from {', '.join(FAMILIES)}"
    )
    g.add_argument(
        "--keep",
        metavar="DIR",
        help="with --stress: keep the recordings of scans with a bug (crash, claims good) in DIR",
    )


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="bench_stress", description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, default=10)
    p.add_argument("--first-seed", type=int, default=0)
    p.add_argument("--jobs", type=int, default=os.cpu_count() or 1)
    p.add_argument("--json")
    add_ray_argument(p)
    add_stress_arguments(p)
    args = p.parse_args(argv)
    if not args.stress:
        args.stress = ["all"]
    return run_stress(args)


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
