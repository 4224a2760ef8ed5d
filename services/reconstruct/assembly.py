"""One scan, assembled from its messages in whatever order they arrive (no I/O).

Samples are placed by step index, so arrival order does not matter; a second
copy of a step is dropped.  Per step the assembly keeps what the math needs —
measured γ, ranges, the energy of each capsule (eq. 10), the first echo's
peak — and the latest step's waveforms, for display.

A sample's waveforms are worked on once, as it is placed, while their
samples are in the cache: a ``Sample`` may carry the energies its writer
computed (``sensor_energy``, as the acquisition service does); they are
checked against the waveforms in float32
(:func:`~lelsonar.reconstruct.energy.waveform_energy_agrees`, one dot product
a step) instead of integrated again in float64.  Where they disagree, or are
not plausible, the energies are recomputed, counted
(:attr:`ScanAssembly.energy_mismatches`) and warned about; without them
(another writer) they are computed.  Either way the arrays hold eq. (10) of
the waveforms: the writer's value, which the check holds to within float32
rounding of it (the acquisition service's is
:func:`~lelsonar.reconstruct.energy.waveform_energy` itself, bit for bit), or
that function's.  The first echo's
peak window is cut out of each waveform (on every :data:`RISE_STRIDE`-th step
also the window just before it, and the DC level is taken, for
:meth:`ScanAssembly.writer_problems`); the peaks, and R (§4), are worked out
for many steps at once (:meth:`ScanAssembly.settle`) when first read, when
the ScanEnd comes, or every :attr:`ScanAssembly.SETTLE_EVERY` steps.  The
acquisition service's samples (capsules in the ScanStart's order, float32
waveforms of one length on one clock) take one pass; anything else another
writer may send (its own capsule order and ids, int16 data, a clock per
capsule) the general path, to the same values.

The per-step arrays grow with the highest step that actually arrived (doubling,
capped at ``ScanStart.steps``): a ScanStart claiming many steps costs nothing
until its samples come.  The assembly knows which steps it lacks
(:meth:`ScanAssembly.missing_steps`) and where each step came from (the live
stream or the acquirer's log), for the per-scan accounting.
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from lelsonar import codec
from lelsonar.errors import ConfigError, InvalidMessageError
from lelsonar.geometry import ArrayGeometry, beam_points
from lelsonar.reconstruct.energy import (
    ECHO_PEAK_WINDOW,
    PRE_ECHO_WINDOW,
    EnergyModel,
    echo_window_starts,
    echo_window_width,
    energy_ratio,
    total_energy,
    waveform_energy,
    waveform_energy_agrees,
    window_peak,
)
from lelsonar.reconstruct.echo_timing import (RangeWalk, TimingWindows, range_walk, typical_edges, walk_finding,
                                              walk_free_ranges)
from lelsonar.reconstruct.quality import DEGRADED, GOOD, UNRELIABLE
from lelsonar.v1 import scan_pb2

_log = logging.getLogger(__name__)

_FLOAT32 = scan_pb2.WAVEFORM_ENCODING_FLOAT32_LE


#: How far two statements of one length may differ (m): the radial offset in ScanStart.radial_offset and in
#: the capsules' array-frame positions.  A millimetre is far below the range noise and far above rounding.
_SAME_LENGTH = 1e-3


def geometry_from_start(start: codec.ScanStart) -> ArrayGeometry:
    """The array geometry a ``ScanStart`` describes (capsules on x at the radial offset).

    The radial offset is stated twice: ``radial_offset`` and the capsules' array-frame positions ``(x, r, 0)``.
    A writer may fill only one (proto3 leaves the other 0); both filled, they must agree.  An unset
    boresight (0, 0, 0) is the contract's +y, an unset rotation axis its x.

    Raises
    ------
    InvalidMessageError
        An array this build cannot describe (not a line along x facing +y, a rotation axis other than +x), or
        radial offsets that contradict each other; the message names the field to fix.
    """
    axis = start.rotation_axis
    if (axis.x, axis.y, axis.z) != (0.0, 0.0, 0.0):
        norm = math.sqrt(axis.x**2 + axis.y**2 + axis.z**2)
        if not (axis.x > 0 and math.hypot(axis.y, axis.z) <= 1e-3 * norm):
            raise InvalidMessageError(
                f"ScanStart.rotation_axis is ({axis.x:g}, {axis.y:g}, {axis.z:g}); this build supports rotation "
                "about +x only (γ right-handed about +x, beam along +y at γ = 0): state γ about +x")
    ordered = sorted(start.capsules, key=lambda c: c.capsule_id)
    for c in ordered:
        b = c.boresight
        unset = (b.x, b.y, b.z) == (0.0, 0.0, 0.0)
        if abs(c.position.z) > 1e-9 or not (unset or (abs(b.x) + abs(b.z) <= 1e-9 and abs(b.y - 1.0) <= 1e-9)):
            raise InvalidMessageError(
                f"capsule {c.capsule_id} is not on the x axis line facing +y; this build supports only linear arrays")
    radial = {round(c.position.y, 9) for c in ordered}
    if len(radial) > 1 and max(radial) - min(radial) > _SAME_LENGTH:
        raise InvalidMessageError(f"the capsules sit at different radial offsets {sorted(radial)} m (position.y); "
                                  "this build supports one line of capsules")
    from_positions = float(np.mean([c.position.y for c in ordered]))
    offset = start.radial_offset
    if offset == 0.0:
        offset = from_positions
    elif from_positions != 0.0 and abs(from_positions - offset) > _SAME_LENGTH:
        raise InvalidMessageError(
            f"ScanStart.radial_offset {offset} m contradicts the capsules' position.y {from_positions} m: the "
            "positions are in the array frame, so y is the radial offset; state the same value in both")
    return ArrayGeometry(capsule_x=tuple(c.position.x for c in ordered), radial_offset=offset)


#: Fewest readings a scan-wide check of the ranges against the waveforms or the speed of sound rests on.
RANGE_CHECK_MIN = 16
#: Largest median |distance / (c·tof/2) − 1| that is not a convention problem: 1 % is 3 K of air temperature,
#: or 1.5 cm at 1.5 m.
RANGE_TOF_TOLERANCE = 0.01
#: Smallest median ratio of an echo's peak (:data:`~lelsonar.reconstruct.energy.ECHO_PEAK_WINDOW` after the
#: time of flight) to the peak just before it (``PRE_ECHO_WINDOW``) for the ranges to match the waveforms.
#: A comparator fires on an echo's rising edge, over a threshold well above the noise: the echo's peak is
#: several times what precedes it.  A time of flight off by a factor (one-way, or a range taken for the round
#: trip) puts both windows on noise or inside one echo: a ratio near 1.
MIN_ECHO_RISE = 1.5
#: The ranges are checked (against the waveforms, against the time of flight) on every this-many-th step by
#: index: each check is a median over the scan, and a quarter of a 184-step scan's readings is 184 of them.
RISE_STRIDE = 4


#: Largest disagreement between ``ScanStart.sound_speed`` and c(air_temperature) that is still one air: 2 % is
#: 6 K, beyond what humidity (< 0.5 %) or a measured c explains.
SOUND_SPEED_TOLERANCE = 0.02


def air_sound_speed(start: codec.ScanStart) -> float | None:
    """c(T) = 331.3·√(T/273.15) m/s of ``ScanStart.air_temperature`` (K; design notes §8), None if unset."""
    t = start.air_temperature
    return 331.3 * math.sqrt(t / 273.15) if 200.0 < t < 350.0 else None


def speed_of_sound(start: codec.ScanStart) -> float | None:
    """The scan's speed of sound, m/s: ``ScanStart.sound_speed``, or from ``air_temperature`` (K) where the
    writer left it unset (0); None when neither is known."""
    if start.sound_speed > 0:
        return float(start.sound_speed)
    return air_sound_speed(start)


#: E0 for a ScanStart without a usable energy model: spherical spreading alone, E0 ∝ 1/d² (eq. 12 with
#: φ1 = φ2 = 0).  R is then uncalibrated but still relative, which is all the critical step and the energy
#: split use; the default method does not use R at all.
UNCALIBRATED_E0 = EnergyModel(1.0, 0.0, 0.0, d_min=0.01, d_max=100.0)


def energy_model_from_start(start: codec.ScanStart) -> tuple[EnergyModel, str | None]:
    """The scan's E0 (eq. 12), and why it is :data:`UNCALIBRATED_E0` instead (None if it is not).

    A scan is not thrown away for its calibration: the planes do not depend on it.
    """
    e = start.energy_model
    try:
        return EnergyModel(e.phi0, e.phi1, e.phi2, d_min=e.valid_min_range, d_max=e.valid_max_range), None
    except ConfigError as exc:
        return UNCALIBRATED_E0, f"its energy model is unusable ({exc}); E0 taken as 1/d², uncalibrated"


@dataclass
class StepView:
    """The latest step as it arrived, for display."""

    step: int
    time_ns: int
    gamma: float
    distance: np.ndarray     # (k,) m, NaN = no echo
    waveforms: np.ndarray    # (k, n) V
    sample_rate: float
    t0: float


@dataclass
class ScanAssembly:
    """Everything known about one (scanner, scan).

    ``sensor_energy``, ``echo_amplitude``, ``pre_echo_peak``, ``step_energy``,
    ``expected_energy`` and ``ratio`` are properties that first :meth:`settle` the steps placed
    since they were last read (write nothing into them).
    """

    start: codec.ScanStart
    geometry: ArrayGeometry = field(init=False)
    energy_model: EnergyModel = field(init=False)
    energy_model_problem: str | None = field(init=False)   # why E0 is the uncalibrated one, if it is
    gamma: np.ndarray = field(init=False)            # (steps,) rad, NaN until received
    gamma_commanded: np.ndarray = field(init=False)  # (steps,) rad, NaN until received
    sound_speed: float | None = field(init=False)    # m/s, None: neither stated nor a temperature to derive it
    #: Readings marked echo_valid = false that carry a range anyway (a writer that never sets the flag).
    unflagged_ranges: int = 0
    distance: np.ndarray = field(init=False)         # (steps, k) m, NaN = no echo / not received
    dc_level: np.ndarray = field(init=False)         # (steps, k) V, |mean| of each waveform (a receiver's offset)
    #: (steps, k) distance / (c·tof/2) where the reading gave both (NaN elsewhere): 1 when they agree.
    range_tof_ratio: np.ndarray = field(init=False)
    time_ns: np.ndarray = field(init=False)          # (steps,)
    received: np.ndarray = field(init=False)         # (steps,) bool
    recovered_mask: np.ndarray = field(init=False)   # (steps,) bool: the step came from the acquirer's log
    end: codec.ScanEnd | None = None
    duplicates: int = 0
    #: Messages of this scan that were refused, by reason (the wire's ScanAccounting.rejected).
    rejected: Counter = field(default_factory=Counter)
    #: Steps whose carried ``Sample.sensor_energy`` disagreed with their waveforms (or was not plausible:
    #: not one finite, non-negative value per capsule); their energies were recomputed.
    energy_mismatches: int = 0

    #: Rows allocated at first; the arrays double as higher steps arrive, up to ScanStart.steps.
    INITIAL_ROWS = 256
    #: Steps placed but not yet settled that make :meth:`add` settle them (what is held for it is small: the
    #: echo windows, 4 × 80 float32 samples a step, and as many again on every RISE_STRIDE-th step).
    SETTLE_EVERY = 256

    def __post_init__(self) -> None:
        self.geometry = geometry_from_start(self.start)
        # Capsules are matched by the ids the ScanStart gave them (0..k-1 from our writer, any unique ids from
        # another); row i of the arrays is the i-th id in ascending order, as the geometry's capsule i.
        self._capsule_ids = sorted(c.capsule_id for c in self.start.capsules)
        self.sound_speed = speed_of_sound(self.start)
        self.energy_model, self.energy_model_problem = energy_model_from_start(self.start)
        # Steps placed since the last settle(), and the windows of their first echoes, by width:
        # (float32 bytes of each window, its flat index in echo_amplitude).
        self._unsettled: list[int] = []
        self._windows: dict[int, tuple[list[bytes], list[int]]] = {}
        self._pre_windows: dict[int, tuple[list[bytes], list[int]]] = {}  # the same, just before (sampled steps)
        self._widths: dict[tuple[float, tuple[float, float]], int] = {}  # window width by (sample rate, window)
        # Each reading's window around its time of flight, re-timed only when the scan's ranges are tested
        # (range_walk): those of the RISE_STRIDE-th steps first, the rest only if the test finds a walk.
        self._timing = (TimingWindows(), TimingWindows())  # (checked steps, the others)
        # The latest step placed: (step, time_ns, gamma, (k, n) float32 bytes, shape), made a StepView when read.
        self._latest: StepView | tuple | None = None
        self._allocate(min(self.start.steps, self.INITIAL_ROWS))

    def _allocate(self, n: int) -> None:
        """Hold ``n`` rows, keeping what is there (rows of steps not received stay empty)."""
        k = self.geometry.n_capsules

        def grown(name: str, tail: tuple[int, ...], fill, dtype=float) -> np.ndarray:
            new = np.full((n, *tail), fill, dtype=dtype)
            old = self.__dict__.get(name)
            if isinstance(old, np.ndarray):
                new[:len(old)] = old
            return new

        self.gamma = grown("gamma", (), np.nan)
        self.gamma_commanded = grown("gamma_commanded", (), np.nan)
        self.distance = grown("distance", (k,), np.nan)
        self._sensor_energy = grown("_sensor_energy", (k,), 0.0)      # (steps, k) V²·s, eq. 10
        self._echo_amplitude = grown("_echo_amplitude", (k,), np.nan)  # (steps, k) V, first echo's peak; NaN: none
        self._pre_echo_peak = grown("_pre_echo_peak", (k,), np.nan)    # (steps, k) V, peak just before it; NaN: none
        self.dc_level = grown("dc_level", (k,), np.nan)
        # (steps, k, 3) each echo re-timed from its waveform (echo_timing.echo_onsets): onset − tof (s), peak (V), edge (s)
        self._echo_timing = grown("_echo_timing", (k, 3), np.nan)
        self.range_tof_ratio = grown("range_tof_ratio", (k,), np.nan)
        self._step_energy = grown("_step_energy", (), 0.0)            # (steps,) E^γ, eq. 11
        self._expected_energy = grown("_expected_energy", (), 0.0)    # (steps,) E0(d_m), eq. 12
        self._ratio = grown("_ratio", (), 0.0)                        # (steps,) R = E^γ / E0(d_m); 0 without a range
        self.time_ns = grown("time_ns", (), 0, np.int64)
        self.received = grown("received", (), False, bool)
        self.recovered_mask = grown("recovered_mask", (), False, bool)

    # --- what comes from the waveforms, settled when read ----------------------------------------
    @property
    def sensor_energy(self) -> np.ndarray:
        """(steps, k) V²·s, eq. (10) of each capsule's waveform; 0 for steps not received."""
        self.settle()
        return self._sensor_energy

    @property
    def echo_amplitude(self) -> np.ndarray:
        """(steps, k) V, peak of the first echo alone (:func:`~lelsonar.reconstruct.energy.echo_amplitude`);
        NaN: none."""
        self.settle()
        return self._echo_amplitude

    @property
    def pre_echo_peak(self) -> np.ndarray:
        """(steps, k) V, peak just before the first echo (``PRE_ECHO_WINDOW``), on every :data:`RISE_STRIDE`-th
        step; NaN: none, or not a checked step."""
        self.settle()
        return self._pre_echo_peak

    @property
    def step_energy(self) -> np.ndarray:
        """(steps,) E^γ, eq. (11)."""
        self.settle()
        return self._step_energy

    @property
    def expected_energy(self) -> np.ndarray:
        """(steps,) E0(d_m), eq. (12); 0 without a valid range."""
        self.settle()
        return self._expected_energy

    @property
    def ratio(self) -> np.ndarray:
        """(steps,) R = E^γ / E0(d_m) (§4); 0 without a valid range."""
        self.settle()
        return self._ratio

    @property
    def latest(self) -> StepView | None:
        """The latest step placed, for display (its waveforms unpacked when first read)."""
        view = self._latest
        if view is None or isinstance(view, StepView):
            return view
        step, time_ns, gamma, joined, (n, rate, t0) = view
        waveforms = np.frombuffer(joined, dtype="<f4").reshape(self.geometry.n_capsules, n)
        self._latest = view = StepView(step, time_ns, gamma, self.distance[step].copy(), waveforms, rate, t0)
        return view

    @property
    def key(self) -> tuple[str, int]:
        return (self.start.scanner_id, self.start.scan_id)

    @property
    def n_received(self) -> int:
        return int(np.count_nonzero(self.received))

    @property
    def n_recovered(self) -> int:
        return int(np.count_nonzero(self.recovered_mask))

    @property
    def expected_steps(self) -> int:
        """Steps this scan should have: ``ScanEnd.samples_sent`` once known (the scan loop sends steps
        0..samples_sent-1), else the whole schedule of the ScanStart."""
        if self.end is not None:
            return min(int(self.end.samples_sent), int(self.start.steps))
        return int(self.start.steps)

    def missing_steps(self, upto: int | None = None) -> np.ndarray:
        """Steps below ``upto`` (default :attr:`expected_steps`) that have not arrived, ascending."""
        n = self.expected_steps if upto is None else min(int(upto), int(self.start.steps))
        have = np.zeros(n, dtype=bool)
        m = min(n, len(self.received))
        have[:m] = self.received[:m]
        return np.flatnonzero(~have)

    @property
    def highest_step(self) -> int:
        """The highest step received, -1 before any."""
        steps = np.flatnonzero(self.received)
        return int(steps[-1]) if len(steps) else -1

    @property
    def complete(self) -> bool:
        """The ScanEnd came and every step it counts has arrived."""
        return self.end is not None and len(self.missing_steps()) == 0

    def add(self, sample: codec.Sample, origin: str = "live", samples: bytes | None = None) -> bool:
        """Place a sample (``origin`` "live" or "recovered"); return False for a duplicate step.

        ``samples``: the float32 samples of its waveforms joined in the order of its sensors, as
        :func:`~lelsonar.codec.decode_sample` returns them (else they are copied out of the message).

        Raises
        ------
        InvalidMessageError
            A step outside the schedule, capsules the ScanStart did not list, or waveforms of different lengths.
        """
        step = sample.step
        if step >= self.start.steps:
            raise InvalidMessageError(f"step {step} is outside the schedule of {self.start.steps} steps")
        if step >= len(self.received):
            self._allocate(min(int(self.start.steps), max(2 * len(self.received), step + 1)))
        if self.received[step]:
            self.duplicates += 1
            return False
        k = self.geometry.n_capsules
        sensors = sample.sensors
        if not sensors:
            raise InvalidMessageError(f"sample {step} carries no sensor readings")
        first = sensors[0].waveform
        n, rate, t0 = first.sample_count, first.sample_rate, first.t0
        # The fast path, for what the acquisition service sends: the capsules in the ScanStart's order, float32
        # waveforms of one length on one clock, the samples joined once.  Anything else (another writer's
        # order, int16 data, a clock per capsule) takes the general path, with the same results.
        ids = self._capsule_ids
        data = []
        fast = len(sensors) == k
        if fast:
            for s, capsule in zip(sensors, ids):
                w = s.waveform
                if (s.capsule_id != capsule or w.sample_count != n or w.encoding != _FLOAT32
                        or w.sample_rate != rate or w.t0 != t0):
                    fast = False
                    break
                if samples is None:
                    data.append(w.data)
        carried = sample.sensor_energy
        carried = list(carried) if len(carried) else None
        if fast:
            joined = samples if samples is not None and len(samples) == 4 * k * n else b"".join(
                data or [s.waveform.data for s in sensors])
            clocks = None
        else:
            sensors, carried = self._in_capsule_order(sample, carried)
            first = sensors[0].waveform  # the lowest id's clock: the one the display shows
            rate, t0 = first.sample_rate, first.t0
            joined = _waveforms([s.waveform for s in sensors], n).astype("<f4", copy=False).tobytes()
            clocks = [(s.waveform.sample_rate, s.waveform.t0) for s in sensors]
            if all(c == (rate, t0) for c in clocks):
                clocks = None  # one clock after all
        # The scan-wide checks of the ranges (writer_problems) are medians over tens of readings: every
        # RISE_STRIDE-th step (by index) gives them plenty, at a quarter of the cost.
        sampled = step % RISE_STRIDE == 0
        ranges, tof, agree = self._ranges(step, sensors, sampled)
        # The (k, n) float32 samples, worked on while they are in the cache (holding them for later would
        # cost more: fresh memory for each step, and a cold cache for the next step's decoding).
        waveforms = np.frombuffer(joined, dtype="<f4").reshape(k, n)
        if clocks is None:
            agrees = carried is not None and waveform_energy_agrees(waveforms, rate, carried)
        else:  # each capsule on its own clock (the contract allows it): each waveform at its own rate
            agrees = carried is not None and len(carried) == k and all(
                waveform_energy_agrees(waveforms[i:i + 1], r, carried[i:i + 1]) for i, (r, _) in enumerate(clocks))
        if agrees:
            self._sensor_energy[step] = carried  # the writer's, checked against the samples
        else:
            self._sensor_energy[step] = (waveform_energy(waveforms, rate) if clocks is None else
                                         [waveform_energy(wv, r) for wv, (r, _) in zip(waveforms, clocks)])
            if carried is not None:
                self._energy_mismatch(step)
        # The first echoes' peak windows (and, on a sampled step, the windows just before them, and each
        # waveform's DC level), cut out of the samples now and reduced with the other steps' later.
        self._cut(self._windows, step, joined, n, rate, t0, clocks, tof, ECHO_PEAK_WINDOW)
        self._timing[not sampled].cut(step, joined, n, rate, t0, clocks, tof)
        if sampled:
            self.range_tof_ratio[step] = agree
            if n > 0:
                self._cut(self._pre_windows, step, joined, n, rate, t0, clocks, tof, PRE_ECHO_WINDOW)
                self.dc_level[step] = np.abs(waveforms.mean(axis=-1, dtype=np.float64))
        self.gamma[step] = sample.gamma_measured
        self.gamma_commanded[step] = sample.gamma_commanded
        self.distance[step] = ranges
        self.time_ns[step] = sample.acquisition_time_ns
        self.received[step] = True
        self.recovered_mask[step] = origin == "recovered"
        self._latest = (step, sample.acquisition_time_ns, sample.gamma_measured, joined, (n, rate, t0))
        self._unsettled.append(step)
        if len(self._unsettled) >= self.SETTLE_EVERY:
            self.settle()
        return True

    def _energy_mismatch(self, step: int) -> None:
        self.energy_mismatches += 1
        if self.energy_mismatches == 1:  # once a scan; the rest are counted
            _log.warning("scan %s: the sensor_energy carried by step %d disagrees with its waveforms (or is not "
                         "one finite, non-negative value per capsule); recomputed from the waveforms; further "
                         "such steps of this scan are counted in energy_mismatches", self.key, step)

    def _in_capsule_order(self, sample: codec.Sample, carried: list[float] | None) -> tuple[list, list | None]:
        """The sensors of a sample in the order of the ScanStart's capsule ids, and the carried energies in
        the same order; checked (the capsules the ScanStart listed, waveforms of one length)."""
        sensors = list(sample.sensors)
        ids = [s.capsule_id for s in sensors]
        if ids != self._capsule_ids:
            if sorted(ids) != self._capsule_ids:
                raise InvalidMessageError(f"sample {sample.step} carries capsules {ids}; the scan has capsules "
                                          f"{self._capsule_ids}")
            order = sorted(range(len(ids)), key=ids.__getitem__)
            sensors = [sensors[i] for i in order]
            if carried is not None and len(carried) == len(order):  # carried in the order of the sensors
                carried = [carried[i] for i in order]
        counts = {s.waveform.sample_count for s in sensors}
        if len(counts) > 1:
            raise InvalidMessageError(f"sample {sample.step} has waveforms of different lengths {sorted(counts)}")
        return sensors, carried

    def _ranges(self, step: int, sensors, sampled: bool) -> tuple[list, list, list | None]:
        """Each reading's range and round trip (NaN: no echo), in the order of ``sensors``, and on a
        ``sampled`` step each one's distance / (c·tof/2) where it gave both (NaN elsewhere).

        A writer may fill only one of the range and the round trip (the codec made sure one is > 0); the other
        follows from the scan's speed of sound.  A reading without an echo that carries a range anyway is
        counted (:attr:`unflagged_ranges`), its range not read.
        """
        k = len(sensors)
        ranges = [math.nan] * k
        tof = [math.nan] * k
        agree = [math.nan] * k if sampled else None
        c = self.sound_speed
        for i, s in enumerate(sensors):
            if s.echo_valid:
                d, t = s.distance, s.time_of_flight
                if not (d > 0 and t > 0):
                    if c is None:
                        raise InvalidMessageError(
                            f"sample {step} capsule {s.capsule_id} gives only its {'distance' if d > 0 else 'time of flight'}"
                            " and the ScanStart states neither sound_speed nor air_temperature to convert it: "
                            "fill both fields of the reading, or ScanStart.sound_speed")
                    d, t = (d, 2.0 * d / c) if d > 0 else (0.5 * c * t, t)
                elif sampled and c is not None:
                    agree[i] = d / (0.5 * c * t)
                ranges[i], tof[i] = d, t
            elif s.distance > 0:  # NaN compares false: only a positive range counts
                self.unflagged_ranges += 1
        return ranges, tof, agree

    def _cut(self, store: dict, step: int, joined: bytes, n: int, rate: float, t0: float, clocks: list | None,
             tof: list[float], window: tuple[float, float]) -> None:
        """Cut each waveform's ``window`` after its round trip out of the (k, n) float32 ``joined`` into
        ``store`` (by width: the windows' bytes and their flat index in a (steps, k) array), for
        :meth:`settle` to reduce (:func:`~lelsonar.reconstruct.energy.echo_amplitude`'s windows).

        ``clocks``: each capsule's (sample rate, t0), or None when all share ``rate`` and ``t0``.
        """
        k = len(tof)
        if clocks is None:
            key = (rate, window)
            width = self._widths.get(key)
            if width is None:
                width = self._widths[key] = echo_window_width(rate, window)
            starts = echo_window_starts(n, rate, t0, tof, window)
            widths = [width] * k
        else:
            starts = [echo_window_starts(n, r, t, [tt], window)[0] for (r, t), tt in zip(clocks, tof)]
            widths = [echo_window_width(r, window) for r, _ in clocks]
        for i, (a, width) in enumerate(zip(starts, widths)):
            if a >= 0:
                size = 4 * width
                at = 4 * (i * n + a)
                chunk = joined[at:at + min(size, 4 * (n - a))]
                if len(chunk) < size:  # off the end: zeros, which leave the largest |w| as it is
                    chunk += bytes(size - len(chunk))
                chunks, where = store.get(width) or store.setdefault(width, ([], []))
                chunks.append(chunk)
                where.append(step * k + i)

    def settle(self) -> None:
        """Work out, for the steps placed since the last call and all at once, the first echoes' peaks and the
        peaks just before them (from the windows cut out by :meth:`add`), E^γ (eq. 11), E0(d_m) (eq. 12) and
        R (§4)."""
        for store, peaks in ((self._windows, self._echo_amplitude), (self._pre_windows, self._pre_echo_peak)):
            if store:
                flat = peaks.reshape(-1)
                for width, (chunks, where) in store.items():
                    flat[where] = window_peak(np.frombuffer(b"".join(chunks), dtype="<f4").reshape(-1, width))
                store.clear()
        if not self._unsettled:
            return
        steps = np.array(self._unsettled)
        self._unsettled = []
        self._step_energy[steps] = step_energy = total_energy(self._sensor_energy[steps])
        expected = self._expected_energy[steps]
        self._ratio[steps] = energy_ratio(step_energy, self.distance[steps], self.energy_model, expected=expected)
        self._expected_energy[steps] = expected

    @property
    def gamma_unmeasured(self) -> bool:
        """Every received step's ``gamma_measured`` is exactly 0 (proto3's unset) while the commanded angles
        move: the writer never filled the measured angle, and :meth:`arrays` uses the commanded one."""
        steps = np.flatnonzero(self.received)
        return (len(steps) > 1 and not np.any(self.gamma[steps])
                and bool(np.ptp(self.gamma_commanded[steps]) > 0))

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(steps, gamma, distance, ratio)`` of the received steps, in step order.

        γ is the measured angle, or the commanded one where no step's measured angle was filled
        (:attr:`gamma_unmeasured`): with every γ at 0 all beams would point one way.
        """
        steps = np.flatnonzero(self.received)
        gamma = self.gamma_commanded if self.gamma_unmeasured else self.gamma
        return steps, gamma[steps], self.distance[steps], self.ratio[steps]

    def range_walk(self) -> tuple[RangeWalk, np.ndarray, np.ndarray, np.ndarray]:
        """Whether the writer's ranges walk with the echoes' amplitude (:func:`~lelsonar.reconstruct.echo_timing.
        range_walk`, on the echoes of a typical shape), and each received step's offsets (writer's range −
        re-timed, m; NaN: not timed), peaks (V; NaN: no echo found) and whether its shape is typical
        (:func:`~lelsonar.reconstruct.echo_timing.typical_edges`)."""
        self.settle()
        steps = np.flatnonzero(self.received)

        def test(rows: np.ndarray, halves: bool) -> tuple[RangeWalk, np.ndarray, np.ndarray, np.ndarray]:
            onset, peak, edge = np.moveaxis(self._echo_timing[rows], -1, 0)
            typical = typical_edges(edge)
            offset = -0.5 * (self.sound_speed or math.nan) * onset
            shown = typical | np.isnan(onset)  # clipped echoes count as found but untimed
            walk = range_walk(np.where(typical, offset, np.nan), np.where(shown, peak, np.nan), halves=halves)
            return walk, offset, peak, typical

        # A screen on the checked steps (a quarter of the echoes: the re-timing, ~40 µs a step, is spared on
        # the others where nothing walks), then the test on every step where the screen found a walk.
        self._timing[0].reduce(self._echo_timing)
        found = test(steps[steps % RISE_STRIDE == 0], False)
        if not found[0].detected:
            return found[0], *(np.full(self.distance[steps].shape, np.nan),) * 2, np.zeros(self.distance[steps].shape, bool)
        self._timing[1].reduce(self._echo_timing)
        return test(steps, True)

    def walk_free(self, distance: np.ndarray) -> np.ndarray:
        """:meth:`arrays`' ``distance`` re-timed from the waveforms where the writer's ranges walk with the
        echoes' amplitude (:func:`~lelsonar.reconstruct.echo_timing.walk_free_ranges`), else as it is."""
        walk, offset, peak, _ = self.range_walk()
        return walk_free_ranges(distance, offset, peak, walk)

    def writer_problems(self) -> list[tuple[str | None, str]]:
        """What the scan's writer left unset or stated otherwise than the contract, each with its fix.

        Returns ``(level, text)`` pairs: ``level`` is the verdict the problem imposes on every plane of the
        scan (``"degraded"``, ``"unreliable"``), ``"good"`` for what every plane names without its verdict
        lowered (ranges re-timed, :meth:`walk_free`), or None where the estimate does not suffer (a fallback
        was taken) or there is no plane to judge.
        """
        out: list[tuple[str | None, str]] = []
        got = self.received
        if self.gamma_unmeasured:
            out.append((None, "no Sample filled gamma_measured (all 0): the commanded angles were used instead; "
                              "fill gamma_measured with the motor's measured angle"))
        if self.unflagged_ranges and not np.isfinite(self.distance[got]).any():
            out.append((None, f"no reading is marked echo_valid, yet {self.unflagged_ranges} carry a distance: set "
                              "echo_valid = true on readings with an echo (the contract reads no range from the "
                              "others)"))
        _, gamma, _, _ = self.arrays()
        if gamma.size and (float(np.ptp(gamma)) > 2.0 * math.pi or float(np.max(np.abs(gamma))) > 2.0 * math.pi):
            # The AX-12 turns through 300°: a sweep over a turn, or an angle beyond one, is not in radians.
            out.append((UNRELIABLE, f"γ spans {np.min(gamma):.1f} to {np.max(gamma):.1f} rad, beyond a turn: the "
                                    "angles are not in rad (degrees?); the contract's gamma_measured is in rad"))
        # Both peaks above the waveform's DC level (max |w| of a carrier burst or of noise over an offset is
        # |offset| + its own peak): a receiver's offset would otherwise pull the rise towards 1.
        dc = self.dc_level[got]
        with np.errstate(divide="ignore", invalid="ignore"):
            rise = (self.echo_amplitude[got] - dc) / (self.pre_echo_peak[got] - dc)
        rise = rise[np.isfinite(rise)]
        if rise.size >= RANGE_CHECK_MIN and float(np.median(rise)) < MIN_ECHO_RISE:
            out.append((UNRELIABLE, f"the waveforms show no echo starting at the readings' time of flight (median rise "
                                    f"×{np.median(rise):.2f} over the {1e3 * -PRE_ECHO_WINDOW[0]:.1f} ms before): "
                                    "the ranges do not match the waveforms (distance is one way, time_of_flight "
                                    "the round trip from firing, waveform.t0 the first sample's time)"))
        walk = self.range_walk()[0]
        if walk.detected:  # re-timed (walk_free): named on every plane, the verdict left to the fit
            out.append((GOOD, walk_finding(walk)))
        c_air = air_sound_speed(self.start)
        if self.start.sound_speed > 0 and c_air is not None and \
                abs(self.start.sound_speed / c_air - 1.0) > SOUND_SPEED_TOLERANCE:
            out.append((DEGRADED, f"ScanStart.sound_speed {self.start.sound_speed:.1f} m/s is not the speed of sound "
                                  f"at its air_temperature {self.start.air_temperature:.1f} K ({c_air:.1f} m/s): the "
                                  "range scale is uncertain"))
        ratio = self.range_tof_ratio[got]
        ratio = ratio[np.isfinite(ratio)]
        if ratio.size >= RANGE_CHECK_MIN:
            off = float(np.median(ratio)) - 1.0
            if abs(off) > RANGE_TOF_TOLERANCE:
                # The planes rest on the distance; which of the two fields is right the scan cannot tell (the
                # waveforms place the time of flight, not the speed of sound).  A few % is a scale error of
                # centimetres: degraded; beyond, one field is in another convention (a one-way time, a
                # round-trip path): unreliable.
                out.append((UNRELIABLE if abs(off) > 5 * RANGE_TOF_TOLERANCE else DEGRADED,
                            f"the readings' distance is {100 * off:+.0f} % off c·time_of_flight/2 at the stated "
                            f"speed of sound {self.sound_speed:.1f} m/s: the range scale is uncertain (distance is "
                            "one way, time_of_flight the round trip, sound_speed the air's)"))
        return out

    def raw_points(self, step: int) -> np.ndarray:
        """Eq. (9) points of one received step, (k, 3); NaN rows where no echo."""
        return beam_points(self.geometry, self.gamma[step:step + 1], self.distance[step:step + 1])[0]


def _waveforms(waves: list, n: int) -> np.ndarray:
    """(k, n) float32 V of ``k`` validated ``Waveform``s of ``n`` samples each, in order."""
    if all(w.encoding == _FLOAT32 for w in waves):
        return np.frombuffer(b"".join([w.data for w in waves]), dtype="<f4").reshape(len(waves), n)
    return np.stack([codec.unpack_waveform(w, validated=True) for w in waves])
