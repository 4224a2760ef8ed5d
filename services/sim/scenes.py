"""Seeded families of L-corner scenes for tests and the estimator benchmark.

Each family varies one thing the estimators are judged on, drawn broadly (the
project is evaluated on scenes it never sees, so nothing here is tuned to a
preset); ``mixed`` varies everything at once:

=============  =================================================================
family         what is drawn (everything else is the paper's Test 1/2 setting)
=============  =================================================================
``paper``      the paper's L (1.57 m, 1.06 m), 184 or 220 steps over −10…110°;
               range jitter 1–3 mm, cycle slips 0–3 %, amplitude noise 0–2 %
``distance``   each wall independently at 0.6–2.6 m
``tilted``     each plane tilted up to ±6° about two axes (a: x, z; b: x, y)
``partial``    sweeps that start late or stop early: start in [−10°, 15°],
               stop in [70°, 110°], always containing the corner (±5°)
``steps``      90–400 steps over −10…110°
``beam``       capsule radius 6–12 mm
``corner``     corner gain 1.0–2.5
``noise``      range jitter 1–6 mm, cycle slips 0–5 %, amplitude noise 1–5 %
               (energy noise ≈ 2–10 %)
``mixed``      all of the above at once
=============  =================================================================

Every draw is a valid configuration (:func:`check_config` is empty): the
waveform window holds the longest echo (the corner's, at the edge distance)
with its whole envelope, the servo reaches the sweep, the panels cover every
beam of the sweep, and the sweep contains the corner.

The energy model: a real rig is calibrated once, with its own capsules and
receiver, by the paper's six face-on shots (0.9–1.8 m).  The benchmark does the
same for every draw — ``calibrate_simulator(cfg)`` of the draw's acoustics and
receiver (see :func:`calibrated_energy_model`, cached) — rather than pass the
default simulator's ``E0(d)``, which is wrong for another receiver or
amplitude noise.  (Face-on shots see the on-axis gain ``D(0) = 1``, so in
this simulator the capsule radius and the corner gain leave ``E0`` unchanged;
the calibration still runs per rig, as a user's would.)  Walls outside
0.9–1.8 m then rely on the model's extrapolation, as on a real robot.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import zlib
from dataclasses import dataclass
from typing import Any

import numpy as np

from lelsonar.energy_model import EnergyModel
from lelsonar.errors import ConfigError
from lelsonar.geometry import boresight
from lelsonar.sim.acoustics import Acoustics, Receiver
from lelsonar.sim.calibrate import PAPER_CALIBRATION_DISTANCES, calibrate_simulator
from lelsonar.sim.config import SimConfig
from lelsonar.sim.scan import SimulatedScan, echo_table, simulate_scan
from lelsonar.sim.scene import Scene

#: Scene families, in the order the benchmark reports them.
FAMILIES: tuple[str, ...] = ("paper", "distance", "tilted", "partial", "steps", "beam", "corner", "noise", "mixed")

#: The sweep must contain the corner with this much room on each side, rad.
CORNER_MARGIN = math.radians(5.0)

_DEG = math.pi / 180.0
#: Receiver envelope span (rise times) the window must hold after the last arrival.
_ENVELOPE_SPAN = 8.0


@dataclass(frozen=True)
class SceneParams:
    """The drawn parameters of one scene (SI units, angles in rad).

    Parameters
    ----------
    distance_a, distance_b : float
        Offsets of plane a (``y = d_a`` untilted) and plane b (``z = d_b``), m.
    tilt_a_x, tilt_a_z, tilt_b_x, tilt_b_y : float
        Tilts of :meth:`Scene.l_corner`, rad.
    gamma_start, gamma_stop : float
        Commanded sweep, rad.
    steps : int
    capsule_radius : float
        m.
    corner_gain : float
    tof_jitter : float
        Range noise (standard deviation), m.
    cycle_slip_probability : float
    amplitude_noise : float
        Relative per-shot, per-capsule echo amplitude noise (``Receiver.amplitude_noise``).
    """

    distance_a: float = 1.57
    distance_b: float = 1.06
    tilt_a_x: float = 0.0
    tilt_a_z: float = 0.0
    tilt_b_x: float = 0.0
    tilt_b_y: float = 0.0
    gamma_start: float = -10.0 * _DEG
    gamma_stop: float = 110.0 * _DEG
    steps: int = 184
    capsule_radius: float = 0.007
    corner_gain: float = 1.5
    tof_jitter: float = 0.002
    cycle_slip_probability: float = 0.02
    amplitude_noise: float = 0.0

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if not (isinstance(v, (int, float, np.integer, np.floating)) and math.isfinite(v)):
                raise ConfigError(f"SceneParams.{f.name} must be a finite number, got {v!r}")
        if not (0.2 <= self.distance_a <= 10 and 0.2 <= self.distance_b <= 10):
            raise ConfigError("SceneParams: distances must be in [0.2, 10] m")
        if not self.gamma_start < self.gamma_stop:
            raise ConfigError("SceneParams: gamma_start must be below gamma_stop")
        if not (isinstance(self.steps, (int, np.integer)) and 2 <= self.steps <= 4096):
            raise ConfigError(f"SceneParams.steps must be an int in [2, 4096], got {self.steps!r}")
        object.__setattr__(self, "steps", int(self.steps))

    def describe(self) -> str:
        """One line: distances, tilts, sweep, beam, corner gain and noise."""
        tilts = (self.tilt_a_x, self.tilt_a_z, self.tilt_b_x, self.tilt_b_y)
        tilt = (
            "untilted"
            if not any(tilts)
            else "tilts a(x {:+.1f}°, z {:+.1f}°) b(x {:+.1f}°, y {:+.1f}°)".format(*(math.degrees(t) for t in tilts))
        )
        return (
            f"d_a {self.distance_a:.2f} m, d_b {self.distance_b:.2f} m, {tilt}, "
            f"sweep {math.degrees(self.gamma_start):+.1f}…{math.degrees(self.gamma_stop):+.1f}° "
            f"in {self.steps} steps, capsule {1e3 * self.capsule_radius:.1f} mm, "
            f"corner gain {self.corner_gain:.2f}, jitter {1e3 * self.tof_jitter:.1f} mm, "
            f"slips {100 * self.cycle_slip_probability:.1f} %, amplitude noise {100 * self.amplitude_noise:.1f} %"
        )


@dataclass(frozen=True, eq=False)
class SceneDraw:
    """One scene of a family: what was drawn and the configuration built from it.

    Attributes
    ----------
    family : str
    seed : int
        Seed of the draw (see :func:`draw_scene`); also the natural seed of the scan.
    params : SceneParams
    config : SimConfig
    """

    family: str
    seed: int
    params: SceneParams
    config: SimConfig

    def __post_init__(self) -> None:
        if self.family not in FAMILIES:
            raise ConfigError(f"unknown scene family {self.family!r}; choose one of {', '.join(FAMILIES)}")
        if not isinstance(self.params, SceneParams) or not isinstance(self.config, SimConfig):
            raise ConfigError("SceneDraw needs SceneParams and a SimConfig")

    @property
    def description(self) -> str:
        """``family #seed: <params>``."""
        return f"{self.family} #{self.seed}: {self.params.describe()}"


# ---------------------------------------------------------------------------- drawing
def _u(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(rng.uniform(lo, hi))


def _paper_steps(rng: np.random.Generator) -> int:
    return int(rng.choice((184, 220)))


def _distances(rng: np.random.Generator) -> dict[str, float]:
    return {"distance_a": _u(rng, 0.6, 2.6), "distance_b": _u(rng, 0.6, 2.6)}


def _tilts(rng: np.random.Generator) -> dict[str, float]:
    return {name: _u(rng, -6.0, 6.0) * _DEG for name in ("tilt_a_x", "tilt_a_z", "tilt_b_x", "tilt_b_y")}


def _sweep(rng: np.random.Generator, critical: float) -> dict[str, float]:
    """A partial sweep containing ``critical`` (rad) with :data:`CORNER_MARGIN` on both sides."""
    for _ in range(1000):
        start, stop = _u(rng, -10.0, 15.0) * _DEG, _u(rng, 70.0, 110.0) * _DEG
        if start + CORNER_MARGIN <= critical <= stop - CORNER_MARGIN:
            return {"gamma_start": start, "gamma_stop": stop}
    raise ConfigError(f"no partial sweep contains a corner at {math.degrees(critical):.1f}°")


def _critical(params: dict[str, float]) -> float:
    keys = ("distance_a", "distance_b", "tilt_a_x", "tilt_a_z", "tilt_b_x", "tilt_b_y")
    base = SceneParams()
    args = {k: params.get(k, getattr(base, k)) for k in keys}
    return Scene.l_corner(**args).critical_angle()


def _noise(rng: np.random.Generator) -> dict[str, float]:
    return {
        "tof_jitter": _u(rng, 0.001, 0.006),
        "cycle_slip_probability": _u(rng, 0.0, 0.05),
        "amplitude_noise": _u(rng, 0.01, 0.05),
    }


def draw_params(family: str, rng: np.random.Generator) -> SceneParams:
    """Draw the parameters of one scene of ``family`` (see the module table).

    Parameters
    ----------
    family : str
        One of :data:`FAMILIES`.
    rng : numpy.random.Generator
        The only source of randomness: the same state gives the same draw.

    Raises
    ------
    ConfigError
        For an unknown family.
    """
    p: dict[str, Any] = {}  # SceneParams fields, drawn per family
    if family == "paper":
        p.update(
            steps=_paper_steps(rng),
            tof_jitter=_u(rng, 0.001, 0.003),
            cycle_slip_probability=_u(rng, 0.0, 0.03),
            amplitude_noise=_u(rng, 0.0, 0.02),
        )
    elif family == "distance":
        p.update(steps=_paper_steps(rng), **_distances(rng))
    elif family == "tilted":
        p.update(steps=_paper_steps(rng), **_tilts(rng))
    elif family == "partial":
        p.update(steps=_paper_steps(rng), **_sweep(rng, _critical(p)))
    elif family == "steps":
        p.update(steps=int(rng.integers(90, 401)))
    elif family == "beam":
        p.update(steps=_paper_steps(rng), capsule_radius=_u(rng, 0.006, 0.012))
    elif family == "corner":
        p.update(steps=_paper_steps(rng), corner_gain=_u(rng, 1.0, 2.5))
    elif family == "noise":
        p.update(steps=_paper_steps(rng), **_noise(rng))
    elif family == "mixed":
        p.update(_distances(rng))
        p.update(_tilts(rng))
        p.update(_sweep(rng, _critical(p)))
        p.update(
            steps=int(rng.integers(90, 401)),
            capsule_radius=_u(rng, 0.006, 0.012),
            corner_gain=_u(rng, 1.0, 2.5),
            **_noise(rng),
        )
    else:
        raise ConfigError(f"unknown scene family {family!r}; choose one of {', '.join(FAMILIES)}")
    return SceneParams(**p)


def build_config(params: SceneParams) -> SimConfig:
    """The :class:`SimConfig` of drawn parameters, with panels and window sized to the scene.

    Panel heights cover every boresight of the sweep (a margin of 5° and
    10 cm beyond the extreme rays, grown until :func:`check_config` agrees);
    the window holds the longest echo and its envelope.

    Raises
    ------
    ConfigError
        If no valid configuration exists (e.g. the sweep misses the corner).
    """
    p = params
    base = SimConfig()
    far_a = max(0.0, -p.gamma_start) + 5 * _DEG
    far_b = max(0.0, p.gamma_stop - math.pi / 2) + 5 * _DEG
    height_a = max(1.7, p.distance_b + p.distance_a * math.tan(far_a) + 0.1)
    height_b = max(2.2, p.distance_a + p.distance_b * math.tan(far_b) + 0.1)
    acoustics = dataclasses.replace(base.acoustics, capsule_radius=p.capsule_radius, corner_gain=p.corner_gain)
    receiver = dataclasses.replace(
        base.receiver,
        tof_jitter=p.tof_jitter,
        cycle_slip_probability=p.cycle_slip_probability,
        amplitude_noise=p.amplitude_noise,
    )
    problems: list[str] = []
    for _ in range(6):
        scene = Scene.l_corner(
            p.distance_a,
            p.distance_b,
            tilt_a_x=p.tilt_a_x,
            tilt_a_z=p.tilt_a_z,
            tilt_b_x=p.tilt_b_x,
            tilt_b_y=p.tilt_b_y,
            height_a=height_a,
            height_b=height_b,
        )
        cfg = SimConfig(
            scene=scene,
            gamma_start=p.gamma_start,
            gamma_stop=p.gamma_stop,
            steps=p.steps,
            acoustics=acoustics,
            receiver=receiver,
        )
        cfg = dataclasses.replace(cfg, window_samples=max(base.window_samples, required_window_samples(cfg)))
        problems = check_config(cfg)
        if not problems:
            return cfg
        height_a += 0.5
        height_b += 0.5
    raise ConfigError(f"no valid configuration for {p.describe()}: {'; '.join(problems)}")


def sample_scene(family: str, rng: np.random.Generator) -> SimConfig:
    """A valid :class:`SimConfig` of ``family``, drawn from ``rng`` (see :func:`draw_params`)."""
    return build_config(draw_params(family, rng))


def scene_rng(family: str, seed: int) -> np.random.Generator:
    """The generator of scene ``seed`` of ``family``: independent streams per family and seed."""
    if not (isinstance(seed, (int, np.integer)) and seed >= 0):
        raise ConfigError(f"a scene seed must be an int >= 0, got {seed!r}")
    return np.random.default_rng([int(seed), zlib.crc32(family.encode())])


def draw_scene(family: str, seed: int) -> SceneDraw:
    """Scene ``seed`` of ``family``: the same pair always gives the same configuration."""
    params = draw_params(family, scene_rng(family, seed))
    return SceneDraw(family=family, seed=int(seed), params=params, config=build_config(params))


def parse_families(names: list[str] | tuple[str, ...]) -> tuple[str, ...]:
    """``["all"]`` → :data:`FAMILIES`; otherwise the names, checked (order kept, duplicates dropped)."""
    out: list[str] = []
    for name in names:
        for n in FAMILIES if name == "all" else (name,):
            if n not in FAMILIES:
                raise ConfigError(f"unknown scene family {n!r}; choose from all, {', '.join(FAMILIES)}")
            if n not in out:
                out.append(n)
    return tuple(out)


# ---------------------------------------------------------------------------- validity
def longest_echo_range(cfg: SimConfig, margin: float = 2.0 * _DEG) -> float:
    """Largest one-way range of any echo (mirror, corner, diffuse) over the sweep, m.

    Evaluated at the commanded angles and at ``± margin`` around them (the
    servo rounds and settles).  0 if there is no echo at all.
    """
    gamma = cfg.gamma_commanded()
    table = echo_table(cfg, np.concatenate([gamma - margin, gamma, gamma + margin]))
    r = table.range[np.isfinite(table.range)]
    return float(r.max()) if r.size else 0.0


def required_window_samples(cfg: SimConfig) -> int:
    """Samples a window needs to hold the longest echo and its whole envelope (+1 cm), rounded up to 100."""
    r = longest_echo_range(cfg) + 0.01
    t = 2.0 * r / cfg.sound_speed + _ENVELOPE_SPAN * cfg.receiver.envelope_time - cfg.window_start
    return int(math.ceil(t * cfg.sample_rate / 100.0) * 100)


def check_config(cfg: SimConfig) -> list[str]:
    """What makes ``cfg`` unfit for a benchmark scene; empty if it is fine.

    Checks: the scene has one corner; the sweep contains it with
    :data:`CORNER_MARGIN` on both sides; the window holds the longest echo
    and its envelope; every capsule's boresight at every commanded angle meets
    a panel (the panels cover the beams).  The servo range is checked by
    :class:`SimConfig` itself.
    """
    problems = []
    crit = cfg.scene.critical_angle()
    if not math.isfinite(crit):
        return ["the scene has no corner"]
    if not cfg.gamma_start + CORNER_MARGIN <= crit <= cfg.gamma_stop - CORNER_MARGIN:
        problems.append(
            f"the sweep {math.degrees(cfg.gamma_start):.1f}…{math.degrees(cfg.gamma_stop):.1f}° "
            f"does not contain the corner at {math.degrees(crit):.1f}° with 5° to spare"
        )
    need = required_window_samples(cfg)
    if cfg.window_samples < need:
        problems.append(f"window of {cfg.window_samples} samples is shorter than the {need} the longest echo needs")
    gamma = cfg.gamma_commanded()
    pos = cfg.geometry.capsule_positions(gamma)  # (n, m, 3)
    bore = boresight(gamma)  # (n, 3)
    covered = np.zeros(pos.shape[:2], dtype=bool)
    for panel in cfg.scene.panels:
        normal = np.asarray(panel.normal)
        s = panel.offset - pos @ normal
        cos_i = bore @ normal
        with np.errstate(divide="ignore", invalid="ignore"):
            along = np.where(cos_i[:, None] > 1e-6, s / cos_i[:, None], np.nan)
        hit = pos + np.nan_to_num(along)[..., None] * bore[:, None, :]
        covered |= (s > 0) & np.isfinite(along) & (along > 0) & panel.contains(hit)
    if not covered.all():
        bad = np.flatnonzero(~covered.all(axis=1))
        problems.append(
            f"{bad.size} steps have a beam that meets no panel (first at γ = {math.degrees(gamma[bad[0]]):.1f}°)"
        )
    return problems


# ---------------------------------------------------------------------------- energy model
#: Calibration distances of the ``wide`` choice: the families' whole span of wall distances, m.
WIDE_CALIBRATION_DISTANCES: tuple[float, ...] = (0.6, 0.9, 1.2, 1.5, 1.8, 2.1, 2.4, 2.7)


@functools.lru_cache(maxsize=64)
def _calibrated(
    acoustics: Acoustics,
    receiver: Receiver,
    window_samples: int,
    sample_rate: float,
    temperature: float,
    radial_offset: float,
    reflectivity: float,
    distances: tuple[float, ...],
):
    cfg = SimConfig(
        acoustics=acoustics,
        receiver=receiver,
        window_samples=window_samples,
        sample_rate=sample_rate,
        temperature=temperature,
    )
    cfg = dataclasses.replace(
        cfg,
        geometry=dataclasses.replace(cfg.geometry, radial_offset=radial_offset),
        scene=Scene.wall(1.0, reflectivity=reflectivity),
    )
    return calibrate_simulator(cfg, seed=0, distances=distances).model


def calibrated_energy_model(cfg: SimConfig, distances: tuple[float, ...] | None = None):
    """``E0(d)`` a user of this rig would have: the paper's six-shot calibration of ``cfg``'s rig.

    ``distances`` default to the paper's six (0.9–1.8 m, what ``lelsonar
    calibrate`` does); :data:`WIDE_CALIBRATION_DISTANCES` spans the families'
    walls.  The model clips ranges to the calibrated interval.

    The rig is everything but the scene: acoustics (capsule radius, corner
    gain), receiver (noise), window, sample rate, air and radial offset; the
    wall has the reflectivity of plane a.  Seeded (seed 0) and cached per rig,
    since a real rig is calibrated once.

    Returns
    -------
    lelsonar.signal.energy.EnergyModel
    """
    return _calibrated(
        cfg.acoustics,
        cfg.receiver,
        int(cfg.window_samples),
        float(cfg.sample_rate),
        float(cfg.temperature),
        float(cfg.geometry.radial_offset),
        float(cfg.scene.panels[0].reflectivity),
        tuple(distances or _paper_distances()),
    )


def _paper_distances() -> tuple[float, ...]:
    return PAPER_CALIBRATION_DISTANCES


@dataclass(frozen=True, eq=False)
class FamilyScan:
    """A family scene, its simulated scan and the energy model of its rig (for tests and benchmarks).

    Attributes
    ----------
    draw : SceneDraw
    scan : SimulatedScan
        ``simulate_scan(draw.config, seed)``: ground truth in ``scan.truth``.
    energy_model : EnergyModel
        :func:`calibrated_energy_model` of the rig.
    """

    draw: SceneDraw
    scan: SimulatedScan
    energy_model: EnergyModel


def simulate_family_scene(
    family: str, seed: int, *, wide_calibration: bool = False, with_waveforms: bool = True
) -> FamilyScan:
    """Scene ``seed`` of ``family``, simulated with the same seed, and its rig's calibrated ``E0(d)``.

    Exactly what ``lelsonar bench estimators --families`` reconstructs and what
    ``lelsonar simulate --family F --seed N --mcap OUT`` records.
    """
    draw = draw_scene(family, seed)
    scan = simulate_scan(draw.config, seed=seed, with_waveforms=with_waveforms)
    model = calibrated_energy_model(draw.config, WIDE_CALIBRATION_DISTANCES if wide_calibration else None)
    return FamilyScan(draw=draw, scan=scan, energy_model=model)
