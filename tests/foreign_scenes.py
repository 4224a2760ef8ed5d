"""A *foreign* writer of the lelsonar contract, for tests: its own physics, waveforms and conventions.

The project is judged on scans from an independent simulator that writes our
protobuf messages but shares none of our code.  This module plays that
simulator.  It reuses only the scene geometry (:class:`Scene.l_corner`, for
the panels and their edge: the ground truth) and builds everything else
itself, from the paper's physics (§3) and the design notes (§8), with
choices deliberately unlike :mod:`lelsonar.sim`:

* a **Gaussian** two-way beam (not a piston's ``D²``), 1/(2d) spreading and
  1.3 dB/m absorption;
* a 40 kHz tone burst under a **Hann** envelope (not the sim's rise/decay),
  so the comparator's threshold crossing walks with the echo's amplitude;
* the transmitter's ring-down and the neighbours' **cross-talk** at the start
  of the window, a **DC offset**, **coloured** (AR(1)) noise, a per-capsule
  **gain mismatch**, **clipping** at the converter's full scale;
* a **spurious late echo** from a floor below the array (diffuse, along the
  beam), which is in the waveform but never the first echo;
* the range is the board's: the first threshold crossing of the rectified
  waveform after blanking, ``distance = c·tof/2``.

:class:`Conventions` holds how the writer fills the messages (capsule ids,
where the radial offset goes, how "no echo" is written, which of range and
time of flight it fills, γ units and wrapping, …): each is something the
contract allows, or a proto3 default a writer may leave unset.

:func:`write_scan` records a scan with the project's :class:`McapRecorder`;
:func:`judge` scores ``reconstruct --source --json`` output against the truth
as ``lelsonar bench estimators --stress`` does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from lelsonar.sim.scene import Scene
from lelsonar.v1 import scan_pb2

_DEG = math.pi / 180.0
FREQUENCY = 40_000.0  # Hz, the capsules' carrier (paper §3)


def sound_speed(temperature: float) -> float:
    """c(T) = 331.3·√(1 + T/273.15) m/s, T in °C (design notes §8)."""
    return 331.3 * math.sqrt(1.0 + temperature / 273.15)


@dataclass(frozen=True)
class ForeignRig:
    """The foreign simulator's sensor and scene (SI units, angles in rad)."""

    distance_a: float = 1.57
    distance_b: float = 1.06
    roll: float = 0.0  # the whole L about x
    capsule_x: tuple[float, ...] = (-0.12, -0.04, 0.04, 0.12)
    radial_offset: float = 0.03
    gamma_start: float = -10.0 * _DEG
    gamma_stop: float = 110.0 * _DEG
    steps: int = 184
    reverse: bool = False
    temperature: float = 20.0  # °C
    sample_rate: float = 250_000.0
    window: float = 0.0  # s recorded after t0; 0: to the corner's range and 0.5 m beyond
    t0: float = 0.0  # s, first sample after firing
    beam_sigma: float = 11.0 * _DEG  # Gaussian two-way beam: exp(−ψ²/(2σ²))
    beam_limit: float = 30.0 * _DEG  # no echo beyond this off-axis angle
    burst: float = 0.3e-3  # s, Hann envelope length
    echo_scale: float = 1.2  # V at 1 m face-on (before gain)
    corner_gain: float = 1.3
    absorption: float = 1.3  # dB/m
    gains: tuple[float, ...] = (1.0, 0.72, 1.3, 0.88)
    ringdown: float = 2.5  # V at t = 0, the transmitter's own ring
    ringdown_time: float = 0.25e-3  # s
    crosstalk: float = 0.4  # V, neighbours' bursts at t ≈ 0
    dc: float = 0.06  # V
    noise: float = 0.004  # V, std of the AR(1) noise
    noise_corr: float = 0.9  # AR(1) coefficient per sample (coloured)
    full_scale: float = 1.0  # V, the converter clips here
    floor_depth: float = 0.45  # m below the axis (z = −depth); 0: no floor
    floor_scale: float = 0.25  # diffuse backscatter relative to a mirror echo
    threshold: float = 0.025  # V over the DC, the comparator
    blanking: float = 0.0  # s; 0: the board's own, where its ring-down is under a third of the threshold
    range_jitter: float = 0.0015  # m, std of the board's timing noise as range
    seed: int = 0

    @property
    def blanking_time(self) -> float:
        """s: ``blanking``, or the earliest time the ring-down is under a third of the threshold (≥ 1 ms)."""
        if self.blanking > 0:
            return self.blanking
        ring = self.ringdown_time * math.log(max(3 * self.ringdown / self.threshold, 1.0))
        return max(1.0e-3, ring, 0.05e-3 + self.burst + 0.1e-3)

    @property
    def c(self) -> float:
        return sound_speed(self.temperature)

    def scene(self) -> Scene:
        """The L (ground truth), its panels long enough for every beam of the sweep."""
        lo, hi = min(self.gamma_start, self.gamma_stop), max(self.gamma_start, self.gamma_stop)
        far_a = min(max(0.0, -lo + self.roll) + 35 * _DEG, 75 * _DEG)
        far_b = min(max(0.0, hi - self.roll - math.pi / 2) + 35 * _DEG, 75 * _DEG)
        return Scene.l_corner(
            self.distance_a,
            self.distance_b,
            tilt_a_x=self.roll,
            tilt_b_x=self.roll,
            width=6.0,
            height_a=self.distance_b + self.distance_a * math.tan(far_a) + 0.3,
            height_b=self.distance_a + self.distance_b * math.tan(far_b) + 0.3,
        )

    def commanded(self) -> np.ndarray:
        g = np.linspace(self.gamma_start, self.gamma_stop, self.steps)
        return g[::-1].copy() if self.reverse else g


@dataclass(frozen=True)
class Conventions:
    """How the foreign writer fills the contract's fields.

    Each default is what our own writer does; every other value is allowed by
    the schema (or is a proto3 default a writer may leave unset).
    """

    capsule_id_base: int = 0  # ids start here
    radial_offset_in: str = "both"  # "both", "field" (capsule y = 0) or "position" (field left 0)
    no_echo: str = "zero"  # "zero", "nan" or "negative" for tof and distance without an echo
    fill: str = "both"  # "both", "tof" (distance left 0) or "distance" (tof left 0)
    echo_valid: bool = True  # False: the flag is never set (proto3 default) although ranges are
    gamma: str = "measured"  # "measured", "commanded" (measured left 0)
    gamma_wrap: bool = False  # γ in [0, 2π) instead of (−π, π]
    encoding: str = "int16"  # "int16" or "float32"
    energy_model: bool = True
    start_sample_rate: bool = True  # False: ScanStart.sample_rate left 0
    start_sound_speed: bool = True  # False: ScanStart.sound_speed left 0
    acquisition_time: bool = True  # False: Sample.acquisition_time_ns left 0
    rotation_axis: tuple[float, float, float] = (1.0, 0.0, 0.0)
    gamma_unit: str = "rad"  # "rad" or "deg" (against the contract)
    step_base: int = 0  # steps numbered from here
    ids_reversed: bool = False  # capsule id k−1−j for the j-th capsule along +x
    tof_scale: float = 1.0  # 0.5: one-way time of flight (against the contract)
    distance_scale: float = 1.0  # 2: round-trip path as "distance" (against the contract)
    stated_sound_speed: float = 0.0  # m/s stated in the ScanStart (0: the rig's own)
    waveforms: bool = True  # False: no samples recorded (sample_count 0), ranges only
    int16_scale: bool = True  # False: Waveform.scale left unset (0) on int16 data
    t0: bool = True  # False: Waveform.t0 left unset (0) whatever the window's start


@dataclass
class ForeignScan:
    """The simulated scan in step order, with its truth."""

    rig: ForeignRig
    scene: Scene
    gamma: np.ndarray  # (n,) true = measured γ, rad
    commanded: np.ndarray  # (n,)
    tof: np.ndarray  # (n, k) s, NaN: no echo
    waveforms: np.ndarray  # (n, k, samples) V, after clipping
    source: np.ndarray  # (n, k) 0 none, 1 wall a, 2 wall b, 3 corner: what set the range
    energy_model: tuple[float, float, float, float, float] | None = None
    extra: dict = field(default_factory=dict)
    #: (n, k) where the board fired on the noise (``source`` 0 with a range): the first echo after its crossing
    #: that reaches the threshold (the one the board would have reported had the noise not crossed first), as
    #: its source (0: none) and range (m, NaN: none).  0 and NaN elsewhere.
    hidden_source: np.ndarray | None = None
    hidden_range: np.ndarray | None = None

    @property
    def distance(self) -> np.ndarray:
        return self.rig.c * self.tof / 2.0


def _positions(rig: ForeignRig, gamma: np.ndarray) -> np.ndarray:
    """Capsule positions in the world, (n, k, 3): the array frame (x, r, 0) turned by γ about x."""
    x = np.asarray(rig.capsule_x)
    c, s = np.cos(gamma)[:, None], np.sin(gamma)[:, None]
    r = rig.radial_offset
    return np.stack([np.broadcast_to(x, (gamma.size, x.size)), r * c + 0 * x, r * s + 0 * x], axis=-1)


def _echoes(rig: ForeignRig, scene: Scene, gamma: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, int]]:
    """Every echo as (range m, amplitude V, source) arrays of shape (n, k); amplitude 0 where absent."""
    pos = _positions(rig, gamma)
    beam = np.stack([np.zeros_like(gamma), np.cos(gamma), np.sin(gamma)], axis=-1)  # (n, 3)
    spread = lambda path: 10.0 ** (-rig.absorption * path / 20.0) / path  # noqa: E731  one-way path pair, m
    lobe = lambda psi: np.exp(-(psi**2) / (2 * rig.beam_sigma**2)) * (psi < rig.beam_limit)  # noqa: E731
    out = []
    for src, panel in enumerate(scene.panels, start=1):
        n = np.asarray(panel.normal)
        s = panel.offset - pos @ n
        psi = np.arccos(np.clip(beam @ n, -1, 1))[:, None] + 0 * s
        foot = pos + s[..., None] * n
        ok = (s > 0) & panel.contains(foot)
        amp = np.where(ok, rig.echo_scale * panel.reflectivity * lobe(psi) * spread(2 * s) * 2.0, 0.0)
        out.append((np.where(ok, s, np.nan), amp, src))
    for edge in scene.edges:
        rel = pos - edge.point
        t = rel @ edge.direction
        to_edge = edge.point + t[..., None] * edge.direction - pos
        rho = np.linalg.norm(to_edge, axis=-1)
        psi = np.arccos(np.clip(np.einsum("nkc,nc->nk", to_edge, beam) / rho, -1, 1))
        ok = abs(edge.opening - math.pi / 2) < 8 * _DEG
        amp = np.where(ok, rig.corner_gain * rig.echo_scale * 0.9 * lobe(psi) * spread(2 * rho) * 2.0, 0.0)
        out.append((rho, amp, 3))
    if rig.floor_depth > 0:
        # Diffuse backscatter from a floor z = −depth, along the beam: only beams pointing down reach it.
        down = -np.sin(gamma)[:, None] + 0 * pos[..., 0]
        along = np.where(down > 0.05, (rig.floor_depth + pos[..., 2]) / np.maximum(down, 0.05), np.nan)
        amp = np.where(
            np.isfinite(along), rig.floor_scale * rig.echo_scale * spread(2 * np.nan_to_num(along, nan=1.0)) * 2.0, 0.0
        )
        out.append((along, amp, 4))
    return out


def _hann_burst(u: np.ndarray, length: float) -> np.ndarray:
    """The tone burst at time ``u`` since its arrival: sin(2πfu) under a Hann window of ``length`` s."""
    inside = (u >= 0) & (u <= length)
    return np.where(inside, np.sin(np.pi * np.clip(u, 0, length) / length) ** 2, 0.0) * np.sin(
        2 * np.pi * FREQUENCY * u
    )


def simulate(rig: ForeignRig) -> ForeignScan:
    """The foreign simulator: echoes, waveforms, the board's comparator (seeded by ``rig.seed``)."""
    rng = np.random.default_rng([rig.seed, 0xF0])
    scene = rig.scene()
    commanded = rig.commanded()
    gamma = commanded + rng.normal(0.0, 0.05 * _DEG, commanded.shape)
    n, k = gamma.size, len(rig.capsule_x)
    window = rig.window or 2.0 * (math.hypot(rig.distance_a, rig.distance_b) + 0.5) / rig.c
    m = int(round(window * rig.sample_rate))
    t = rig.t0 + np.arange(m) / rig.sample_rate
    gains = np.asarray((rig.gains * k)[:k])
    w = np.zeros((n, k, m))
    echoes = _echoes(rig, scene, gamma)
    for rng_m, amp, _src in echoes:
        tau = 2.0 * rng_m / rig.c
        ok = amp > 0
        for i, j in zip(*np.nonzero(ok)):
            lo = np.searchsorted(t, tau[i, j])
            hi = np.searchsorted(t, tau[i, j] + rig.burst)
            w[i, j, lo:hi] += gains[j] * amp[i, j] * _hann_burst(t[lo:hi] - tau[i, j], rig.burst)
    # Transmitter ring-down and cross-talk from the neighbours firing at the same time.
    w += rig.ringdown * np.exp(-t / rig.ringdown_time) * np.sin(2 * np.pi * FREQUENCY * t)
    w += rig.crosstalk * _hann_burst(t - 0.05e-3, rig.burst)
    # Coloured noise: AR(1), stationary std rig.noise.
    e = rng.normal(0.0, rig.noise * math.sqrt(1 - rig.noise_corr**2), (n, k, m))
    noise = np.empty_like(e)
    noise[..., 0] = rng.normal(0.0, rig.noise, (n, k))
    for q in range(1, m):
        noise[..., q] = rig.noise_corr * noise[..., q - 1] + e[..., q]
    w += noise + rig.dc
    w = np.clip(w, -rig.full_scale, rig.full_scale)
    # The board's comparator: first sample after blanking whose |w − DC| crosses the threshold.
    over = (np.abs(w - rig.dc) >= rig.threshold) & (t >= rig.blanking_time)
    first = np.where(over.any(axis=-1), over.argmax(axis=-1), -1)
    crossing = np.where(first >= 0, t[np.maximum(first, 0)], np.nan)
    # Which echo set the range: the nearest of the echoes arriving before the crossing.
    source = np.zeros((n, k), dtype=int)
    best = np.full((n, k), np.inf)
    for rng_m, amp, src in echoes:
        arrive = 2 * rng_m / rig.c
        hit = (amp > 0) & (arrive <= crossing + 1e-9) & (np.abs(arrive - crossing) < np.abs(best - crossing))
        best = np.where(hit, arrive, best)
        source = np.where(hit, src, source)
    tof = crossing + rng.normal(0.0, 2 * rig.range_jitter / rig.c, crossing.shape)
    # Behind a noise trigger: the first echo after the crossing strong enough for the comparator.
    noisy = (source == 0) & np.isfinite(crossing)
    hidden_source, hidden_range = np.zeros((n, k), dtype=int), np.full((n, k), np.nan)
    for rng_m, amp, src in echoes:
        arrive = 2 * rng_m / rig.c
        hit = (
            noisy
            & (gains * amp >= rig.threshold)
            & (arrive > crossing)
            & ~(np.nan_to_num(hidden_range, nan=np.inf) <= rng_m)
        )
        hidden_source = np.where(hit, src, hidden_source)
        hidden_range = np.where(hit, rng_m, hidden_range)
    return ForeignScan(
        rig,
        scene,
        gamma,
        commanded,
        tof,
        w.astype(np.float32),
        source,
        hidden_source=hidden_source,
        hidden_range=hidden_range,
    )


def energy_model(rig: ForeignRig) -> tuple[float, float, float, float, float]:
    """The foreign rig's own E0(d) calibration (eq. 12–14): face-on shots at six distances, no floor."""
    from lelsonar.signal.energy import fit_energy_model, waveform_energy

    ds = np.linspace(0.9, 1.8, 6)
    energies = []
    for d in ds:
        one = replace(
            rig, distance_a=d, distance_b=3.0, gamma_start=0.0, gamma_stop=0.0, steps=1, floor_depth=0.0, reverse=False
        )
        scan = simulate(one)
        energies.append(float(waveform_energy(scan.waveforms[0], rig.sample_rate).sum()))
    m = fit_energy_model(ds, np.array(energies))
    return (m.phi0, m.phi1, m.phi2, m.d_min, m.d_max)


def _set(v, xyz) -> None:
    v.x, v.y, v.z = (float(a) for a in xyz)


def _capsule_id(conv: Conventions, j: int, k: int) -> int:
    return (k - 1 - j if conv.ids_reversed else j) + conv.capsule_id_base


def messages(
    scan: ForeignScan, conv: Conventions = Conventions(), *, scanner: str = "foreign", scan_id: int = 7
) -> list:
    """ScanStart, the Samples (in scan order) and ScanEnd as the foreign writer fills them."""
    rig = scan.rig
    k = len(rig.capsule_x)
    t_start = 1_700_000_000_000_000_000
    start = scan_pb2.ScanStart(
        schema_version=1,
        scanner_id=scanner,
        scan_id=scan_id,
        start_time_ns=t_start,
        software_version="foreign-sim 0.1",
        gamma_start=float(rig.commanded()[0]),
        gamma_stop=float(rig.commanded()[-1]),
        steps=rig.steps,
        direction=(scan_pb2.ROTATION_DIRECTION_DECREASING if rig.reverse else scan_pb2.ROTATION_DIRECTION_INCREASING),
        air_temperature=rig.temperature + 273.15,
        window_samples=scan.waveforms.shape[-1],
        device="foreign",
    )
    if conv.start_sample_rate:
        start.sample_rate = rig.sample_rate
    if conv.start_sound_speed:
        start.sound_speed = conv.stated_sound_speed or rig.c
    if conv.radial_offset_in in ("both", "field"):
        start.radial_offset = rig.radial_offset
    _set(start.rotation_axis, conv.rotation_axis)
    for j, x in enumerate(rig.capsule_x):
        cap = start.capsules.add(capsule_id=_capsule_id(conv, j, k))
        _set(cap.position, (x, rig.radial_offset if conv.radial_offset_in in ("both", "position") else 0.0, 0.0))
        _set(cap.boresight, (0.0, 1.0, 0.0))
    if conv.energy_model:
        phi0, phi1, phi2, lo, hi = scan.energy_model or energy_model(rig)
        em = start.energy_model
        em.phi0, em.phi1, em.phi2, em.valid_min_range, em.valid_max_range = phi0, phi1, phi2, lo, hi
        em.distance_unit, em.energy_unit = "m", "V^2 s"
    out: list = [start]
    lsb = rig.full_scale / 32767.0
    d = scan.distance
    for step in range(rig.steps):
        g = float(scan.gamma[step])
        if conv.gamma_wrap:
            g = g % (2 * math.pi)
        cmd = float(scan.commanded[step]) % (2 * math.pi) if conv.gamma_wrap else float(scan.commanded[step])
        if conv.gamma_unit == "deg":
            g, cmd = math.degrees(g), math.degrees(cmd)
        s = scan_pb2.Sample(
            schema_version=1, scanner_id=scanner, scan_id=scan_id, step=step + conv.step_base, gamma_commanded=cmd
        )
        if conv.gamma == "measured":
            s.gamma_measured = g
        if conv.acquisition_time:
            s.acquisition_time_ns = t_start + (step + 1) * 20_000_000
        for j in range(k):
            r = s.sensors.add(capsule_id=_capsule_id(conv, j, k))
            ok = bool(np.isfinite(scan.tof[step, j]))
            r.echo_valid = ok and conv.echo_valid
            if ok:
                if conv.fill in ("both", "tof"):
                    r.time_of_flight = float(scan.tof[step, j]) * conv.tof_scale
                if conv.fill in ("both", "distance"):
                    r.distance = float(d[step, j]) * conv.distance_scale
            elif conv.no_echo == "nan":
                r.time_of_flight = r.distance = math.nan
            elif conv.no_echo == "negative":
                r.time_of_flight = r.distance = -1.0
            wf = r.waveform
            wf.sample_rate, wf.t0, wf.sample_count = (
                rig.sample_rate,
                rig.t0 if conv.t0 else 0.0,
                scan.waveforms.shape[-1],
            )
            if not conv.waveforms:
                wf.encoding, wf.sample_count = scan_pb2.WAVEFORM_ENCODING_FLOAT32_LE, 0
                continue
            if conv.encoding == "int16":
                wf.encoding, wf.scale = scan_pb2.WAVEFORM_ENCODING_INT16_LE, lsb if conv.int16_scale else 0.0
                wf.data = np.clip(np.rint(scan.waveforms[step, j] / lsb), -32768, 32767).astype("<i2").tobytes()
            else:
                wf.encoding = scan_pb2.WAVEFORM_ENCODING_FLOAT32_LE
                wf.data = scan.waveforms[step, j].astype("<f4").tobytes()
        out.append(s)
    out.append(
        scan_pb2.ScanEnd(
            schema_version=1,
            scanner_id=scanner,
            scan_id=scan_id,
            end_time_ns=t_start + (rig.steps + 2) * 20_000_000,
            status=scan_pb2.SCAN_STATUS_COMPLETE,
            steps_planned=rig.steps,
            samples_sent=rig.steps,
            echoes_missing=int(np.count_nonzero(~np.isfinite(scan.tof))),
        )
    )
    # Samples in step order on the wire, ScanEnd last (a reversed sweep still counts its steps from 0).
    return out


def write_scan(path: Path, scan: ForeignScan, conv: Conventions = Conventions()) -> Path:
    """Record the foreign writer's messages with the project's recorder, in their order."""
    from lelsonar.log.recording import McapRecorder

    msgs = messages(scan, conv)
    with McapRecorder(path, metadata={"device": "foreign"}) as rec:
        for i, msg in enumerate(msgs):
            rec.write(msg, log_time_ns=1_700_000_000_000_000_000 + i * 1_000_000)
    return path


def run_cli(path: Path) -> tuple[int | None, list[dict], str]:
    """``lelsonar reconstruct --source PATH --json --compare ''`` in process (bench_stress's runner)."""
    from lelsonar.tools.bench_stress import run_cli as _run

    return _run(path, compare="")


def judge(scan: ForeignScan, planes: list[dict], *, hidden: bool = True) -> dict[str, dict]:
    """Per wall: patch error (cm) against the truth, the oracle's, quality, and the stress sweep's verdict.

    The oracle is LS on the mirror echoes of that wall at their reported ranges along the true normal (the
    stress sweep's definition); a failure is a patch error > 2 cm and > 3× the oracle's
    (:func:`lelsonar.tools.bench_families.is_failure`).  A wall's echo behind a reading the board fired on noise
    (:attr:`ForeignScan.hidden_source`) is in the waveform too: it counts among the wall's mirror echoes, at its
    true range with the board's timing noise (``hidden=False``: the board's readings only, as before).
    """
    from lelsonar.tools.bench_families import is_failure, ls_plane, plane_errors

    rig = scan.rig
    pos = _positions(rig, scan.gamma)
    d = scan.distance
    if hidden and scan.hidden_source is not None:
        behind = np.isfinite(scan.hidden_range)
        jitter = np.random.default_rng([rig.seed, 0xF1]).normal(0.0, rig.range_jitter, d.shape)
        d = np.where(behind, scan.hidden_range + jitter, d)
        source = np.where(behind, scan.hidden_source, scan.source)
    else:
        source = scan.source
    out = {}
    for src, (label, panel) in enumerate(zip("ab", scan.scene.panels), start=1):
        n_true, h_true = np.asarray(panel.normal), panel.offset
        m = (source == src) & np.isfinite(d)
        patch = pos[m] + (h_true - pos[m] @ n_true)[:, None] * n_true
        row: dict = {"n_mirror": int(m.sum())}
        oracle = math.nan
        if m.sum() >= 3:
            n_o, h_o, _, _ = ls_plane(pos[m] + d[m][:, None] * n_true)
            oracle = plane_errors(n_o, h_o, n_true, h_true, patch)[2]
        row["oracle_cm"] = oracle
        fit = next((p for p in planes if p.get("label") == label), None)
        if fit is None:
            row.update(verdict="missing", quality=None)
        else:
            n = np.array([fit["normal"].get(a, 0.0) for a in "xyz"])
            ang, off, pe = plane_errors(n, float(fit.get("offset", 0.0)), n_true, h_true, patch)
            wrong = is_failure(pe, oracle) if m.sum() >= 3 else True
            q = fit.get("quality")
            row.update(
                angle_deg=ang,
                offset_cm=off,
                patch_cm=pe,
                quality=q,
                reasons=fit.get("quality_reasons", []),
                verdict="accurate" if not wrong else ("claims_good" if q == "good" else "flagged"),
            )
        out[label] = row
    return out
