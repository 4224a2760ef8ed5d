"""The simulator proper: echoes → times of flight → waveforms, vectorised over steps and capsules.

One physics for a whole scan (:func:`simulate_scan`) and for one shot
(:func:`simulate_step`, used by the sensor-board emulator).

Echo model:

* **Mirror echo** of panel ``p``: the sound leaves and returns along the panel
  normal.  Range = perpendicular distance ``s`` from the capsule; present when
  the foot of the perpendicular lies on the rectangle and the normal is inside
  the main lobe.  Amplitude ``ρ·D(ψ)²·10^(−α·2s/20)/(2s)``, ψ = angle between
  boresight and normal.
* **Corner** (double bounce) of an edge: the dihedral turns the source by
  twice its opening about the edge, so the path is ``2ρ·sin(opening)`` (= 2ρ
  at 90°), ρ = distance from the capsule to the edge line; it leaves and
  returns along the perpendicular to the edge.  Present when that foot is on
  the edge segment, the capsule is in front of both panels and the direction
  is in the main lobe.  Amplitude as a wall at that range, times
  ``Acoustics.corner_gain`` and both reflectivities.
* **Diffuse** backscatter from the first panel the boresight ray meets, at
  the range along the beam; Lambert ``cos`` of the incidence, random phase.

Occlusion between panels is not modelled (a concave L never occludes its own
mirror paths).  The four capsules are treated independently (no cross-talk).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum

import numpy as np
from scipy.special import ndtri

from lelsonar.geometry import ArrayGeometry, beam_points, boresight
from lelsonar.signal.directivity import piston_directivity
from lelsonar.signal.energy import total_energy, waveform_energy
from lelsonar.sim.acoustics import absorption_factor, comparator_delay, echo_envelope
from lelsonar.sim.config import Rig, SimConfig

#: The receiver envelope is cut after this many rise times (its value is then < 10⁻⁴).
_ENVELOPE_SPAN = 8.0


class EchoSource(IntEnum):
    """Which echo set a capsule's time of flight (ground truth, never on the wire)."""

    NONE = 0
    #: Mirror echo of panel 0 (plane a of the L, ``y = 1.57 m``).
    PLANE_A = 1
    #: Mirror echo of panel 1 (plane b of the L, ``z = 1.06 m``).
    PLANE_B = 2
    #: Double bounce of a corner (see ``echo_index`` for which).
    CORNER = 3
    #: Diffuse backscatter along the beam (see ``echo_index`` for the panel).
    DIFFUSE = 4
    #: Mirror echo of panel 2 or later, or of any surface of a world (see ``echo_index``).
    PLANE_OTHER = 5
    #: Triple bounce of a wall + wall + floor (or ceiling) corner of a world.
    TRIHEDRAL = 6
    #: Diffraction by a convex or free edge of a world.
    EDGE = 7


def _plane_source(index: int) -> EchoSource:
    return (EchoSource.PLANE_A, EchoSource.PLANE_B)[index] if index < 2 else EchoSource.PLANE_OTHER


@dataclass(frozen=True, eq=False)
class TruePlane:
    """A panel of the scene as ground truth.

    Attributes
    ----------
    label : str
        'a', 'b', ...
    normal : (3,) array
        Unit normal pointing away from the origin.
    offset : float
        ``normal·p = offset`` for every point of the plane, m.
    corners : (4, 3) array
        The panel's corners, m.
    """

    label: str
    normal: np.ndarray
    offset: float
    corners: np.ndarray


@dataclass(frozen=True, eq=False)
class EchoTable:
    """Every echo each capsule receives at each step; slot axis last.

    Slots are: one mirror echo per panel, one double bounce per corner, one
    diffuse echo.  An absent echo has ``range`` NaN and ``amplitude`` 0.

    Attributes
    ----------
    range : (n, m, K) array
        One-way range of the echo (half its path), m.
    amplitude : (n, m, K) array
        Echo amplitude at the receiver before ``Receiver.echo_gain``, 1/m.
    source : (n, m, K) int8 array
        :class:`EchoSource` of each slot.
    index : (n, m, K) int16 array
        Panel index (mirror, diffuse) or corner index (corner).
    """

    range: np.ndarray
    amplitude: np.ndarray
    source: np.ndarray
    index: np.ndarray


@dataclass(frozen=True, eq=False)
class ScanTruth:
    """Ground truth kept next to a simulated scan (not on the wire).

    Attributes
    ----------
    echo_source : (n, m) int8 array
        :class:`EchoSource` that set each time of flight.
    echo_index : (n, m) int16 array
        Panel or corner index of that echo, −1 for none.
    echo_range : (n, m) array
        Noise-free range of that echo, m (NaN for none).
    gamma_true : (n,) array
        Where the array really was, rad.
    planes : tuple of TruePlane
        Every panel of the scene, in order.
    critical_angle : float
        γ at which the beams point at the (first) corner edge, rad.
    critical_step : int
        The step whose measured γ is closest to ``critical_angle`` (−1 if the
        scene has no corner).
    """

    echo_source: np.ndarray
    echo_index: np.ndarray
    echo_range: np.ndarray
    gamma_true: np.ndarray
    planes: tuple[TruePlane, ...]
    critical_angle: float
    critical_step: int


@dataclass(frozen=True, eq=False)
class SimulatedScan:
    """A whole simulated scan, shaped like what the acquisition service records.

    Attributes
    ----------
    gamma_commanded : (n,) array, rad
    gamma_measured : (n,) array, rad — AX-12 read-back (0.293° grid)
    gamma_raw : (n,) int array — the same in AX-12 units
    tof : (n, m) array, s — NaN = no echo
    distance : (n, m) array, m — ``c·tof/2``, NaN = no echo
    waveforms : (n, m, n_samples) float32 array, V
    sample_rate : float, Hz
    t0 : float, s — time of the first waveform sample after firing
    sound_speed : float, m/s
    temperature : float, K
    geometry : ArrayGeometry
    truth : ScanTruth
    config : SimConfig
    """

    gamma_commanded: np.ndarray
    gamma_measured: np.ndarray
    gamma_raw: np.ndarray
    tof: np.ndarray
    distance: np.ndarray
    waveforms: np.ndarray
    sample_rate: float
    t0: float
    sound_speed: float
    temperature: float
    geometry: ArrayGeometry
    truth: ScanTruth
    config: SimConfig

    @property
    def n_steps(self) -> int:
        return int(self.gamma_measured.shape[0])

    def points(self) -> np.ndarray:
        """Raw data points along the beams, eq. (9): shape (n, m, 3), NaN where no echo."""
        return beam_points(self.geometry, self.gamma_measured, self.distance)

    def step_energy(self) -> np.ndarray:
        """Total waveform energy ``E^γ`` of each step, eq. (10)–(11), V²·s."""
        return total_energy(waveform_energy(self.waveforms, self.sample_rate))


@dataclass(frozen=True, eq=False)
class SimulatedStep:
    """One shot of all capsules (what the sensor board returns), plus its ground truth.

    Attributes
    ----------
    tof : (m,) array, s (NaN = no echo)
    distance : (m,) array, m
    waveforms : (m, n_samples) float32 array, V
    echo_source : (m,) int8 array of :class:`EchoSource`
    echo_index : (m,) int16 array
    echo_range : (m,) array, m
    """

    tof: np.ndarray
    distance: np.ndarray
    waveforms: np.ndarray
    echo_source: np.ndarray
    echo_index: np.ndarray
    echo_range: np.ndarray


# ---------------------------------------------------------------------------- echoes
def echo_table(cfg: SimConfig, gamma: np.ndarray) -> EchoTable:
    """Every echo of every capsule at the true array angles ``gamma`` (rad), noise-free.

    See the module docstring for the physics of each kind of echo.
    """
    gamma = np.atleast_1d(np.asarray(gamma, dtype=float))
    c = cfg.sound_speed
    ac = cfg.acoustics
    ka = ac.wavenumber(c) * ac.capsule_radius
    lobe = ac.main_lobe(c)
    alpha = ac.absorption_db_per_m
    pos = cfg.geometry.capsule_positions(gamma)  # (n, m, 3)
    bore = boresight(gamma)  # (n, 3)
    n, m = pos.shape[:2]
    panels, edges = cfg.scene.panels, cfg.scene.edges
    k_slots = len(panels) + len(edges) + 1
    rng_ = np.full((n, m, k_slots), np.nan)
    amp = np.zeros((n, m, k_slots))
    src = np.zeros((n, m, k_slots), dtype=np.int8)
    idx = np.full((n, m, k_slots), -1, dtype=np.int16)

    perpendicular = np.empty((len(panels), n, m))
    diffuse_range = np.full((n, m), np.inf)
    diffuse_amp = np.zeros((n, m))
    diffuse_index = np.full((n, m), -1, dtype=np.int16)
    for k, panel in enumerate(panels):
        normal = np.asarray(panel.normal)
        s = panel.offset - pos @ normal  # perpendicular distance, > 0 in front
        perpendicular[k] = s
        cos_psi = bore @ normal  # (n,): the same for every capsule (all share the boresight)
        psi = np.arccos(np.clip(cos_psi, -1.0, 1.0))[:, None]
        with np.errstate(divide="ignore", invalid="ignore"):
            foot = pos + s[..., None] * normal
            ok = (s > 0) & panel.contains(foot) & (psi < lobe)
            a = panel.reflectivity * piston_directivity(psi, ka) ** 2 * absorption_factor(2 * s, alpha) / (2 * s)
        rng_[..., k] = np.where(ok, s, np.nan)
        amp[..., k] = np.where(ok, a, 0.0)
        src[..., k] = _plane_source(k)
        idx[..., k] = k

        # Diffuse: where the boresight ray meets this panel, if it is the nearest so far.
        cos_i = np.broadcast_to(cos_psi[:, None], (n, m))
        with np.errstate(divide="ignore", invalid="ignore"):
            along = np.where(cos_i > 1e-6, s / cos_i, np.inf)
            hit = pos + np.where(np.isfinite(along), along, 0.0)[..., None] * bore[:, None, :]
            hit_ok = (s > 0) & np.isfinite(along) & panel.contains(hit) & (along < diffuse_range)
            a_d = (
                ac.diffuse_coefficient * panel.reflectivity * cos_i * absorption_factor(2 * along, alpha) / (2 * along)
            )
        diffuse_range = np.where(hit_ok, along, diffuse_range)
        diffuse_amp = np.where(hit_ok, a_d, diffuse_amp)
        diffuse_index = np.where(hit_ok, np.int16(k), diffuse_index)

    for q, edge in enumerate(edges):
        i, j = edge.panels
        t = (pos - edge.point) @ edge.direction
        to_edge = edge.point + t[..., None] * edge.direction - pos
        rho = np.linalg.norm(to_edge, axis=-1)
        with np.errstate(divide="ignore", invalid="ignore"):
            cos_psi = np.einsum("nmk,nk->nm", to_edge, bore) / rho
            psi = np.arccos(np.clip(cos_psi, -1.0, 1.0))
            r = rho * math.sin(edge.opening)
            ok = (
                (t >= edge.t_min)
                & (t <= edge.t_max)
                & (perpendicular[i] > 0)
                & (perpendicular[j] > 0)
                & (psi < lobe)
                & (rho > 0)
                & (abs(edge.opening - math.pi / 2) <= ac.corner_max_error)
            )
            a = (
                ac.corner_gain
                * panels[i].reflectivity
                * panels[j].reflectivity
                * piston_directivity(psi, ka) ** 2
                * absorption_factor(2 * r, alpha)
                / (2 * r)
            )
        slot = len(panels) + q
        rng_[..., slot] = np.where(ok, r, np.nan)
        amp[..., slot] = np.where(ok, a, 0.0)
        src[..., slot] = EchoSource.CORNER
        idx[..., slot] = q

    has_diffuse = np.isfinite(diffuse_range) & (ac.diffuse_coefficient > 0)
    rng_[..., -1] = np.where(has_diffuse, diffuse_range, np.nan)
    amp[..., -1] = np.where(has_diffuse, diffuse_amp, 0.0)
    src[..., -1] = EchoSource.DIFFUSE
    idx[..., -1] = np.where(has_diffuse, diffuse_index, -1)
    return EchoTable(range=rng_, amplitude=amp, source=src, index=idx)


def first_echo(cfg: Rig, echoes: EchoTable) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The comparator: the earliest echo whose peak is over the threshold, after blanking.

    Returns the noise-free range, source and index of that echo per capsule,
    and the comparator's delay after its arrival (s; 0 where ``Receiver.timing``
    is ``"onset"``, :func:`~lelsonar.sim.acoustics.comparator_delay`
    where it is ``"crossing"``).  A crossing past the end of the window is no
    echo.
    """
    c = cfg.sound_speed
    rec = cfg.receiver
    arrival = 2.0 * echoes.range / c
    peak = echoes.amplitude * rec.echo_gain
    if rec.timing == "crossing":
        with np.errstate(divide="ignore", invalid="ignore"):
            delay = np.where(peak > 0, comparator_delay(peak, rec.threshold, rec.envelope_time), 0.0)
    else:
        delay = np.zeros_like(peak)
    window_end = cfg.window_start + cfg.window_samples / cfg.sample_rate
    with np.errstate(invalid="ignore"):
        detected = (peak >= rec.threshold) & (arrival >= rec.blanking_time) & (arrival + delay <= window_end)
    candidate = np.where(detected, echoes.range, np.inf)
    first = np.argmin(candidate, axis=-1)[..., None]
    first_range = np.take_along_axis(candidate, first, axis=-1)[..., 0]
    found = np.isfinite(first_range)
    source = np.where(found, np.take_along_axis(echoes.source, first, axis=-1)[..., 0], EchoSource.NONE)
    index = np.where(found, np.take_along_axis(echoes.index, first, axis=-1)[..., 0], -1)
    first_delay = np.where(found, np.take_along_axis(delay, first, axis=-1)[..., 0], 0.0)
    return (np.where(found, first_range, np.nan), source.astype(np.int8), index.astype(np.int16), first_delay)


def apply_amplitude_noise(cfg: Rig, echoes: EchoTable, rng: np.random.Generator) -> EchoTable:
    """Scale every echo of a capsule's shot by one log-normal factor (``Receiver.amplitude_noise``).

    Draws nothing when the noise is 0, so the random stream (and every existing
    seed's bytes) is unchanged.  The factor is ``exp(σ·N − σ²/2)``: mean 1,
    relative standard deviation ≈ σ.
    """
    sigma = cfg.receiver.amplitude_noise
    if sigma <= 0:
        return echoes
    factor = np.exp(sigma * rng.standard_normal(echoes.amplitude.shape[:2]) - sigma * sigma / 2)
    return EchoTable(
        range=echoes.range, amplitude=echoes.amplitude * factor[..., None], source=echoes.source, index=echoes.index
    )


def comparator_time_of_flight(
    cfg: Rig, echo_range: np.ndarray, rng: np.random.Generator, delay: np.ndarray | float = 0.0
) -> np.ndarray:
    """The comparator's time: arrival plus its ``delay`` (:func:`first_echo`), Gaussian jitter and ±1-cycle
    slips (±λ/2 of range)."""
    c = cfg.sound_speed
    rec = cfg.receiver
    jitter = rng.standard_normal(echo_range.shape) * (2.0 * rec.tof_jitter / c)
    u = rng.random(echo_range.shape)
    p = rec.cycle_slip_probability
    slip = np.where(u < p / 2, -1.0, np.where(u < p, 1.0, 0.0))
    return 2.0 * echo_range / c + delay + jitter + slip / cfg.acoustics.frequency


# ---------------------------------------------------------------------------- waveforms
#: Standard normal quantiles at the midpoints of 2¹⁶ equal-probability bins.
_NORMAL_TABLE = ndtri((np.arange(2**16) + 0.5) / 2**16).astype(np.float32)


def _gaussian_noise(rng: np.random.Generator, shape: tuple[int, int], std: float) -> np.ndarray:
    """White Gaussian noise, float32, by inverse-CDF lookup of 16-bit uniforms.

    Cheaper than ``standard_normal`` over a scan's 2.6 M samples, where the
    noise is most of a scan's time.  The 16-bit
    quantisation of the probability cuts the tails at ±4.3σ; the ADC rounds far
    coarser than the table's steps.
    """
    count = shape[0] * shape[1]
    raw = rng.bit_generator.random_raw((count + 3) // 4)  # four 16-bit draws per 64-bit word
    noise = np.take(_NORMAL_TABLE * np.float32(std), raw.view(np.uint16)[:count])
    return noise.reshape(shape)


def digitised_waveforms(cfg: Rig, echoes: EchoTable, rng: np.random.Generator) -> np.ndarray:
    """Digitised echo signals, (n, m, window_samples) float32 volts.

    Each echo adds a 40 kHz burst under :func:`echo_envelope`, starting at its
    arrival ``2·range/c`` with its own amplitude; the transmit ring-down sits at
    t = 0; then white noise and the ADC (rounding to codes, clipping).
    """
    c = cfg.sound_speed
    rec = cfg.receiver
    fs, n_samples, t0 = cfg.sample_rate, int(cfg.window_samples), cfg.window_start
    f = cfg.acoustics.frequency
    n, m, k_slots = echoes.range.shape
    rows = n * m
    span = int(math.ceil(_ENVELOPE_SPAN * rec.envelope_time * fs)) + 1
    # Padding on both sides lets a burst start before or run past the window without clipping indices.
    buf = np.zeros((rows, n_samples + 2 * span), dtype=np.float32)
    diffuse_phase = rng.uniform(0.0, 2.0 * math.pi, size=rows)
    amp = echoes.amplitude.reshape(rows, k_slots)
    rng_ = echoes.range.reshape(rows, k_slots)
    src = echoes.source.reshape(rows, k_slots)
    offsets = np.arange(span)
    stride = buf.shape[1]
    flat = buf.reshape(-1)
    two_pi_f = np.float32(2.0 * math.pi * f)
    # One slot at a time: within a slot each channel has at most one echo, so the
    # fancy-indexed add never repeats an index (no np.add.at needed).
    for k in range(k_slots):
        sel = np.flatnonzero(amp[:, k] > 0)
        if sel.size == 0:
            continue
        tau = 2.0 * rng_[sel, k] / c
        first = np.ceil((tau - t0) * fs).astype(np.int64)
        keep = (first < n_samples) & (first > -span)
        sel, tau, first = sel[keep], tau[keep], first[keep]
        if sel.size == 0:
            continue
        # Time since arrival of every sample of the burst; float32 is exact enough
        # (u < 2 ms, phase error < 1e-4 rad) and cheaper for exp and sin.
        u = ((first / fs + t0 - tau)[:, None] + offsets / fs).astype(np.float32)
        phase = np.where(src[sel, k] == EchoSource.DIFFUSE, diffuse_phase[sel], 0.0).astype(np.float32)
        burst = echo_envelope(u, np.float32(rec.envelope_time))
        burst *= np.sin(two_pi_f * u + phase[:, None])
        burst *= (rec.echo_gain * amp[sel, k]).astype(np.float32)[:, None]
        flat[(sel * stride + first + span)[:, None] + offsets] += burst
    w = buf[:, span : span + n_samples]
    t = t0 + np.arange(n_samples) / fs
    ringdown = rec.ringdown_amplitude * np.exp(-t / rec.ringdown_time) * np.sin(2.0 * math.pi * f * t)
    w += ringdown.astype(np.float32)
    if rec.noise_std > 0:
        w += _gaussian_noise(rng, (rows, n_samples), rec.noise_std)
    # ADC: round to codes and clip to the converter's range, back to volts.
    lsb = np.float32(rec.adc_lsb)
    half = 2 ** (rec.adc_bits - 1)
    codes = np.multiply(w, np.float32(1.0) / lsb)
    np.rint(codes, out=codes)
    np.clip(codes, -half, half - 1, out=codes)
    codes *= lsb
    return codes.reshape(n, m, n_samples)


# ---------------------------------------------------------------------------- public
def true_planes(cfg: SimConfig) -> tuple[TruePlane, ...]:
    """The scene's panels as :class:`TruePlane` ground truth."""
    return tuple(
        TruePlane(label=p.label or str(i), normal=np.asarray(p.normal), offset=p.offset, corners=p.corners())
        for i, p in enumerate(cfg.scene.panels)
    )


def simulate_scan(
    cfg: SimConfig, seed: int | np.random.Generator | None = 0, *, with_waveforms: bool = True
) -> SimulatedScan:
    """Simulate a whole scan: servo, echoes, times of flight and waveforms.

    Parameters
    ----------
    cfg : SimConfig
    seed : int or numpy.random.Generator
        The same seed gives the same bytes.
    with_waveforms : bool
        False skips the waveforms (``waveforms`` then has 0 samples); the
        times of flight are the same as with them.

    Returns
    -------
    SimulatedScan
    """
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    commanded = cfg.gamma_commanded()
    goal = cfg.servo.to_raw(commanded)
    # Always draw, so the rest of the stream does not depend on position_error being 0.
    settle = rng.standard_normal(commanded.shape) * cfg.servo.position_error
    gamma_true = cfg.servo.to_gamma(goal) + settle
    raw = np.clip(cfg.servo.to_raw(gamma_true), 0, 1023)
    gamma_measured = cfg.servo.to_gamma(raw)

    echoes = apply_amplitude_noise(cfg, echo_table(cfg, gamma_true), rng)
    echo_range, source, index, delay = first_echo(cfg, echoes)
    tof = comparator_time_of_flight(cfg, echo_range, rng, delay)
    c = cfg.sound_speed
    distance = c * tof / 2.0
    if with_waveforms:
        waveforms = digitised_waveforms(cfg, echoes, rng)
    else:
        waveforms = np.zeros((*tof.shape, 0), dtype=np.float32)

    critical = cfg.scene.critical_angle()
    critical_step = int(np.argmin(np.abs(gamma_measured - critical))) if math.isfinite(critical) else -1
    truth = ScanTruth(
        echo_source=source,
        echo_index=index,
        echo_range=echo_range,
        gamma_true=gamma_true,
        planes=true_planes(cfg),
        critical_angle=critical,
        critical_step=critical_step,
    )
    return SimulatedScan(
        gamma_commanded=commanded,
        gamma_measured=gamma_measured,
        gamma_raw=raw,
        tof=tof,
        distance=distance,
        waveforms=waveforms,
        sample_rate=float(cfg.sample_rate),
        t0=float(cfg.window_start),
        sound_speed=c,
        temperature=float(cfg.temperature),
        geometry=cfg.geometry,
        truth=truth,
        config=cfg,
    )


def simulate_step(cfg: SimConfig, gamma_measured: float, rng: np.random.Generator) -> SimulatedStep:
    """One shot of every capsule with the array at ``gamma_measured`` (rad).

    The same physics as :func:`simulate_scan` (the angle is taken as where the
    array really is).  Draws from ``rng`` in the same order as a scan of one
    step, without the servo draw.
    """
    gamma = np.array([float(gamma_measured)])
    echoes = apply_amplitude_noise(cfg, echo_table(cfg, gamma), rng)
    echo_range, source, index, delay = first_echo(cfg, echoes)
    tof = comparator_time_of_flight(cfg, echo_range, rng, delay)
    waveforms = digitised_waveforms(cfg, echoes, rng)
    return SimulatedStep(
        tof=tof[0],
        distance=cfg.sound_speed * tof[0] / 2.0,
        waveforms=waveforms[0],
        echo_source=source[0],
        echo_index=index[0],
        echo_range=echo_range[0],
    )


def shots_from_echoes(
    cfg: Rig, echoes: EchoTable, rng: np.random.Generator, *, with_waveforms: bool = True
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The receiver on any table of echoes: amplitude noise, comparator, timing and waveforms.

    The chain :func:`simulate_scan` and :func:`simulate_step` run, in the same
    order and with the same draws, for echoes computed elsewhere (a world's,
    :mod:`lelsonar.sim.world_render`).

    Returns
    -------
    echo_range, source, index : (n, m) arrays
        Noise-free range (m), :class:`EchoSource` and element index of the echo that set each time of flight.
    tof : (n, m) array
        s, NaN where no echo crossed the threshold.
    waveforms : (n, m, window_samples) float32 array
        V; 0 samples when ``with_waveforms`` is False.
    """
    echoes = apply_amplitude_noise(cfg, echoes, rng)
    echo_range, source, index, delay = first_echo(cfg, echoes)
    tof = comparator_time_of_flight(cfg, echo_range, rng, delay)
    if with_waveforms:
        waveforms = digitised_waveforms(cfg, echoes, rng)
    else:
        waveforms = np.zeros((*tof.shape, 0), dtype=np.float32)
    return echo_range, source, index, tof, waveforms
