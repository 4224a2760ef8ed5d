"""One scan, assembled from its messages in whatever order they arrive (no I/O).

Samples are placed by step index, so arrival order does not matter; a second
copy of a step is dropped.  Per step the assembly keeps what the math needs —
measured γ, ranges, the energy of each capsule (eq. 10), the first echo's
peak — and the latest step's waveforms, for display.

A sample's readings and waveforms are worked on once, as it is placed, in one
compiled pass while its samples are in the cache (:func:`_place_step`).  A
sample for a scan whose layout is known arrives parsed but not validated
(:func:`~lelsonar.codec.parse`): the pass reads its readings and waveforms
straight from its payload (:func:`_read_sample`, bit for bit what the parsed
fields hold) and makes the contract's checks of them (its samples finite
among them), leaving anything it does not clear to
:func:`~lelsonar.codec.validate_body`, which names the culprit.  A ``Sample``
may carry the energies
its writer computed (``sensor_energy``, as the acquisition service does); they
are checked against the waveforms in float32
(:func:`~lelsonar.signal.energy.energy_agrees`, one dot product a
waveform) instead of integrated again in float64.  Where they disagree, or are
not plausible, the energies are recomputed, counted
(:attr:`ScanAssembly.energy_mismatches`) and warned about; without them
(another writer) they are computed.  Either way the arrays hold eq. (10) of
the waveforms: the writer's value, which the check holds to within float32
rounding of it (the acquisition service's is
:func:`~lelsonar.signal.energy.waveform_energy` itself, bit for bit), or
that function's.  The same pass takes each reading's range, the first echo's
peak (:func:`~lelsonar.signal.energy.echo_amplitude`'s window) and, on
every :data:`RISE_STRIDE`-th step, the peak just before it and the DC level,
for :meth:`ScanAssembly.writer_problems`, each waveform around its time of
flight (and around the first echo after it, where the reading may be the
noise a board fired on: :func:`_candidate_echo`), and the step's E^γ, E0(d_m) and R (§4,
eq. 11–12; :func:`_settle_step`).  The
acquisition service's samples (capsules in the ScanStart's order, float32
waveforms of one length on one clock) go straight to the pass; anything else
another writer may send (its own capsule order and ids, int16 data, a clock
per capsule) is put in capsule order first (the general path), to the same
values.

The per-step arrays grow with the highest step that actually arrived (doubling,
capped at ``ScanStart.steps``): a ScanStart claiming many steps costs nothing
until its samples come.  The assembly knows which steps it lacks
(:meth:`ScanAssembly.missing_steps`) and where each step came from (the live
stream or the acquirer's log), for the per-scan accounting.
"""

from __future__ import annotations

import functools
import logging
import math
import struct
from collections import Counter, OrderedDict
from dataclasses import dataclass, field

import numpy as np

from lelsonar import codec
from lelsonar.codec import MAX_RANGE_M
from lelsonar.errors import ConfigError, InvalidMessageError, LelsonarError
from lelsonar.geometry import ArrayGeometry, beam_points
from lelsonar.reconstruct.estimate.corner.model import _pairwise_block  # NumPy's add.reduce, to the bit
from lelsonar.reconstruct.estimate.quality import DEGRADED, GOOD, UNRELIABLE
from lelsonar.signal.compiled import kernel
from lelsonar.signal.echo_timing import (
    _FLOOR_TIME,
    MIN_TIMED,
    TIMING_WINDOW,
    RangeWalk,
    echo_onsets,
    range_walk,
    typical_edges,
    walk_finding,
    walk_free_ranges,
)
from lelsonar.signal.energy import (
    ECHO_PEAK_WINDOW,
    PRE_ECHO_WINDOW,
    EnergyModel,
    echo_amplitude,
    echo_window_start,
    echoes_over_noise,
    energy_agrees,
    noise_level,
    ranges_backed,
    step_median_range,
    waveform_energy,
    window_samples,
)
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
                "about +x only (γ right-handed about +x, beam along +y at γ = 0): state γ about +x"
            )
    ordered = sorted(start.capsules, key=lambda c: c.capsule_id)
    for c in ordered:
        b = c.boresight
        unset = (b.x, b.y, b.z) == (0.0, 0.0, 0.0)
        if abs(c.position.z) > 1e-9 or not (unset or (abs(b.x) + abs(b.z) <= 1e-9 and abs(b.y - 1.0) <= 1e-9)):
            raise InvalidMessageError(
                f"capsule {c.capsule_id} is not on the x axis line facing +y; this build supports only linear arrays"
            )
    radial = {round(c.position.y, 9) for c in ordered}
    if len(radial) > 1 and max(radial) - min(radial) > _SAME_LENGTH:
        raise InvalidMessageError(
            f"the capsules sit at different radial offsets {sorted(radial)} m (position.y); "
            "this build supports one line of capsules"
        )
    from_positions = float(np.mean([c.position.y for c in ordered]))
    offset = start.radial_offset
    if offset == 0.0:
        offset = from_positions
    elif from_positions != 0.0 and abs(from_positions - offset) > _SAME_LENGTH:
        raise InvalidMessageError(
            f"ScanStart.radial_offset {offset} m contradicts the capsules' position.y {from_positions} m: the "
            "positions are in the array frame, so y is the radial offset; state the same value in both"
        )
    return ArrayGeometry(capsule_x=tuple(c.position.x for c in ordered), radial_offset=offset)


#: Fewest readings a scan-wide check of the ranges against the waveforms or the speed of sound rests on.
RANGE_CHECK_MIN = 16
#: Largest median |distance / (c·tof/2) − 1| that is not a convention problem: 1 % is 3 K of air temperature,
#: or 1.5 cm at 1.5 m.
RANGE_TOF_TOLERANCE = 0.01
#: Smallest median ratio of an echo's peak (:data:`~lelsonar.signal.energy.ECHO_PEAK_WINDOW` after the
#: time of flight) to the peak just before it (``PRE_ECHO_WINDOW``) for the ranges to match the waveforms.
#: A comparator fires on an echo's rising edge, over a threshold well above the noise: the echo's peak is
#: several times what precedes it.  A time of flight off by a factor (one-way, or a range taken for the round
#: trip) puts both windows on noise or inside one echo: a ratio near 1.
MIN_ECHO_RISE = 1.5
#: The ranges are checked (against the waveforms, against the time of flight) on every this-many-th step by
#: index: each check is a median over the scan, and a quarter of a 184-step scan's readings is 184 of them.
RISE_STRIDE = 4
#: Smallest step-to-step change of the noise triggers' ranges over their spread (:meth:`ScanAssembly.
#: noise_independence`) for most readings marking no echo to be a board firing on the noise rather than ranges
#: in another convention: halfway between independent draws' ~1 and a surface's ~0.
NOISE_INDEPENDENT = 0.5


#: The (steps, k) arrays of a scan, in the order of their block (see ScanAssembly._allocate): range (m; NaN: no
#: echo or not received), eq. (10) energy (V²·s; 0), first echo's peak (V; NaN: none), the peak just before it
#: (V; NaN: none or not a sampled step), |mean| of the waveform (V), distance / (c·tof/2) (NaN: not both); where
#: each reading's timing window starts (``_timing_at``: its time of flight after the window's first sample, s)
#: and, for a reading that may be the noise a board fired on, its candidate echo's (``_candidate_at``: the echo's
#: first crossing after its window's first sample, s; ``_candidate_start``: that sample's time after firing, s).
_PER_CAPSULE = (
    "distance",
    "sensor_energy",
    "echo_amplitude",
    "pre_echo_peak",
    "dc_level",
    "range_tof_ratio",
    "_timing_at",
    "_candidate_at",
    "_candidate_start",
)
#: The (steps,) float arrays: γ measured and commanded (rad; NaN until received), E^γ (eq. 11), E0(d_m)
#: (eq. 12), R = E^γ / E0(d_m) (0 without a range).
_PER_STEP = ("gamma", "gamma_commanded", "step_energy", "expected_energy", "ratio")


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
    return _energy_model(e.phi0, e.phi1, e.phi2, e.valid_min_range, e.valid_max_range)


@functools.lru_cache(maxsize=64)
def _energy_model(phi0: float, phi1: float, phi2: float, d_min: float, d_max: float) -> tuple[EnergyModel, str | None]:
    # Cached: a scanner states the same model in every ScanStart, and checking it costs ~20 µs a scan.
    try:
        return EnergyModel(phi0, phi1, phi2, d_min=d_min, d_max=d_max), None
    except ConfigError as exc:
        return UNCALIBRATED_E0, f"its energy model is unusable ({exc}); E0 taken as 1/d², uncalibrated"


#: Geometries of recent ScanStarts by what describes them (a scanner states the same array in every ScanStart,
#: and reading and checking it costs ~30 µs a scan); bounded.
_GEOMETRIES: OrderedDict[tuple, ArrayGeometry] = OrderedDict()


def _scan_geometry(start: codec.ScanStart) -> ArrayGeometry:
    """:func:`geometry_from_start`, of the same description once."""
    key = (
        start.rotation_axis.SerializeToString(),
        tuple([c.SerializeToString() for c in start.capsules]),
        start.radial_offset,
    )
    geometry = _GEOMETRIES.get(key)
    if geometry is None:
        geometry = _GEOMETRIES[key] = geometry_from_start(start)
        if len(_GEOMETRIES) > 64:
            _GEOMETRIES.popitem(last=False)
    return geometry


@dataclass
class StepView:
    """The latest step as it arrived, for display."""

    step: int
    time_ns: int
    gamma: float
    distance: np.ndarray  # (k,) m, NaN = no echo
    waveforms: np.ndarray  # (k, n) V
    sample_rate: float
    t0: float


@dataclass
class ScanAssembly:
    """Everything known about one (scanner, scan)."""

    start: codec.ScanStart
    geometry: ArrayGeometry = field(init=False)
    energy_model: EnergyModel = field(init=False)
    energy_model_problem: str | None = field(init=False)  # why E0 is the uncalibrated one, if it is
    gamma: np.ndarray = field(init=False)  # (steps,) rad, NaN until received
    gamma_commanded: np.ndarray = field(init=False)  # (steps,) rad, NaN until received
    sound_speed: float | None = field(init=False)  # m/s, None: neither stated nor a temperature to derive it
    #: Readings marked echo_valid = false that carry a range anyway (a writer that never sets the flag).
    unflagged_ranges: int = 0
    distance: np.ndarray = field(init=False)  # (steps, k) m, NaN = no echo / not received
    sensor_energy: np.ndarray = field(init=False)  # (steps, k) V²·s, eq. (10) of each waveform; 0: not received
    #: (steps, k) V, peak of the first echo alone (:func:`~lelsonar.signal.energy.echo_amplitude`); NaN: none.
    echo_amplitude: np.ndarray = field(init=False)
    #: (steps, k) V, peak just before the first echo (``PRE_ECHO_WINDOW``), on every :data:`RISE_STRIDE`-th
    #: step; NaN: none, or not a checked step.
    pre_echo_peak: np.ndarray = field(init=False)
    step_energy: np.ndarray = field(init=False)  # (steps,) E^γ, eq. (11)
    expected_energy: np.ndarray = field(init=False)  # (steps,) E0(d_m), eq. (12); 0 without a valid range
    ratio: np.ndarray = field(init=False)  # (steps,) R = E^γ / E0(d_m) (§4); 0 without a valid range
    dc_level: np.ndarray = field(init=False)  # (steps, k) V, |mean| of each waveform (a receiver's offset)
    #: (steps, k) distance / (c·tof/2) where the reading gave both (NaN elsewhere): 1 when they agree.
    range_tof_ratio: np.ndarray = field(init=False)
    time_ns: np.ndarray = field(init=False)  # (steps,)
    received: np.ndarray = field(init=False)  # (steps,) bool
    recovered_mask: np.ndarray = field(init=False)  # (steps,) bool: the step came from the acquirer's log
    end: codec.ScanEnd | None = None
    duplicates: int = 0
    #: Copies of a held step whose content differed from the held one (a forgery, a replayed step of another
    #: run, a broken writer): counted apart from identical resends, and settled by the acquirer's log.
    conflicts: int = 0
    #: Steps with a conflicting copy that no copy from the acquirer's log has settled yet.
    unsettled: set = field(default_factory=set)
    #: Held steps the acquirer's log replaced (its copy differed from the one held).
    replaced: int = 0
    #: Messages of this scan that were refused, by reason (the wire's ScanAccounting.rejected).
    rejected: Counter = field(default_factory=Counter)
    #: Steps whose carried ``Sample.sensor_energy`` disagreed with their waveforms (or was not plausible:
    #: not one finite, non-negative value per capsule); their energies were recomputed.
    energy_mismatches: int = 0

    #: Rows allocated at first; the arrays double as higher steps arrive, up to ScanStart.steps.
    INITIAL_ROWS = 256

    def __post_init__(self) -> None:
        self.geometry = _scan_geometry(self.start)
        self._k = self.geometry.n_capsules
        self._steps = int(self.start.steps)
        # Capsules are matched by the ids the ScanStart gave them (0..k-1 from our writer, any unique ids from
        # another); row i of the arrays is the i-th id in ascending order, as the geometry's capsule i.
        self._capsule_ids = sorted(c.capsule_id for c in self.start.capsules)
        self._ids = np.array(self._capsule_ids, dtype=np.int64)
        self.sound_speed = speed_of_sound(self.start)
        e = self.start.energy_model
        self.energy_model, self.energy_model_problem = _energy_model(
            e.phi0, e.phi1, e.phi2, e.valid_min_range, e.valid_max_range
        )
        # The kernel's constants of the scan (_place_step's ``scan``): the speed of sound (NaN for none: the
        # ranges then need both fields), the timing windows' rate (NaN until the first waveforms), E0's model.
        model = self.energy_model
        self._scan = np.array(
            [
                math.nan if self.sound_speed is None else float(self.sound_speed),
                math.nan,
                model.phi0,
                model.phi1,
                model.phi2,
                model.d_min,
                model.d_max,
            ]
        )
        # The fast path's layout (the readings' capsule ids, lengths and clocks), once a sample has shown it, and
        # the kernel's buffer of numbers (_place_step's ``values``): the layout's clocks, then each sample's
        # readings and energies, packed straight from the decoded lists (cheaper than a new array a sample).
        self._layout: list | None = None
        self._buffer = bytearray(8 * (6 * self._k + 5))
        self._values = np.frombuffer(self._buffer, dtype=np.float64)
        self._pack_readings = struct.Struct(f"<{5 + 3 * self._k}d")
        self._pack_readings_energies = struct.Struct(f"<{5 + 4 * self._k}d")
        # Where _place_wire copies a sample's waveforms ((k, n) float32 V, n the layout's).
        self._waves = np.zeros((self._k, 0), np.float32)
        # Each reading's waveform around its time of flight (echo_timing.TIMING_WINDOW), kept to re-time the
        # echoes if the scan's ranges walk with their amplitude (range_walk): (steps, k, width) float32 at the
        # rate of the first sample's first capsule (width 0 until then; a capsule on another clock is not kept).
        self._timing_rate = math.nan
        self._timing_windows = np.zeros((0, self._k, 0), np.float32)
        # A reading that may be the noise a board fired on (:func:`_candidate_echo`): its waveform around the
        # first echo after its time of flight, the same width (the echo recovered at the final if the reading
        # proves to be noise, :meth:`recovered_echoes`).
        self._candidate_windows = np.zeros((0, self._k, 0), np.float32)
        # (steps, k, 3) each echo re-timed (echo_timing.echo_onsets): onset − tof (s), peak (V), edge (s); and
        # which steps have been (re-timing is done only when the ranges are tested, RISE_STRIDE-th steps first).
        self._echo_timing = np.zeros((0, self._k, 3))
        self._timed = np.zeros(0, bool)
        self._walk_tested: tuple[int, tuple] | None = None  # (steps received, range_walk()) when last asked
        self._noise_tested: tuple[int, tuple] | None = None  # (steps received, noise_triggers()) when last asked
        self._recovered: tuple[int, tuple] | None = None  # (steps received, recovered_echoes()) when last asked
        self._recovery_sigma = math.nan  # V, the noise σ over the recovered echoes' windows
        # The latest step placed: (step, (k, n) float32 bytes, n, sample rate, t0), made a StepView when read.
        self._latest: StepView | tuple | None = None
        self._allocate(min(self.start.steps, self.INITIAL_ROWS))

    def _allocate(self, n: int) -> None:
        """Hold ``n`` rows, keeping what is there (rows of steps not received stay empty).

        The (steps, k) arrays are the planes of one block, and the (steps,) float arrays the rows of another:
        two allocations instead of eleven, and one array each for the kernel to write a step into.
        """
        k = self._k
        per_capsule = np.full((len(_PER_CAPSULE), n, k), np.nan)
        per_capsule[_PER_CAPSULE.index("sensor_energy")] = 0.0
        per_step = np.full((len(_PER_STEP), n), np.nan)
        per_step[_PER_STEP.index("step_energy") :] = 0.0
        time_ns, received, recovered = np.zeros(n, np.int64), np.zeros(n, bool), np.zeros(n, bool)
        if hasattr(self, "_per_capsule"):
            had = self._per_capsule.shape[1]
            per_capsule[:, :had] = self._per_capsule
            per_step[:, :had] = self._per_step
            time_ns[:had], received[:had], recovered[:had] = self.time_ns, self.received, self.recovered_mask
        self._per_capsule, self._per_step = per_capsule, per_step
        for name, plane in zip(_PER_CAPSULE, per_capsule):
            setattr(self, name, plane)
        for name, row in zip(_PER_STEP, per_step):
            setattr(self, name, row)
        self.time_ns, self.received, self.recovered_mask = time_ns, received, recovered
        self._rows = (per_capsule, per_step, time_ns, received, recovered)  # what the kernel writes a step into
        self._grow_timing(n, self._timing_windows.shape[2])

    def _grow_timing(self, n: int, width: int) -> None:
        """Hold ``n`` rows of timing windows ``width`` samples wide, keeping what is there."""
        windows = np.zeros((n, self._k, width), np.float32)
        # (The candidates' only once one was found, :meth:`_keep_candidates`.)
        kept = self._candidate_windows.shape[2] if width == self._timing_windows.shape[2] else 0
        candidates = np.zeros((n, self._k, kept), np.float32)
        timing, timed = np.full((n, self._k, 3), np.nan), np.zeros(n, bool)
        had = len(self._timed)
        if width == self._timing_windows.shape[2]:
            windows[:had] = self._timing_windows
            candidates[:had] = self._candidate_windows
        timing[:had], timed[:had] = self._echo_timing, self._timed
        self._timing_windows, self._echo_timing, self._timed = windows, timing, timed
        self._candidate_windows = candidates

    @property
    def latest(self) -> StepView | None:
        """The latest step placed, for display (its waveforms unpacked when first read)."""
        view = self._latest
        if view is None or isinstance(view, StepView):
            return view
        step, held, n, rate, t0 = view
        # (k, n) float32, or the Sample itself where its waveforms were read from its payload (on the fast path's
        # layout: its sensors in the order of the capsules)
        waveforms = held if isinstance(held, np.ndarray) else _waveforms([s.waveform for s in held.sensors], n)
        self._latest = view = StepView(
            step, int(self.time_ns[step]), float(self.gamma[step]), self.distance[step].copy(), waveforms, rate, t0
        )
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

    def add(
        self,
        sample: codec.Sample,
        origin: str = "live",
        *,
        limits: codec.DecodeLimits | None = None,
        payload: bytes | None = None,
    ) -> bool | None:
        """Place a sample (``origin`` "live" or "recovered"); return False for a duplicate step.

        ``limits``: the sample's body has not been validated (:func:`~lelsonar.codec.parse` only); its checks
        under ``limits`` are made here, on the acquisition service's layout in the pass that places it
        (:func:`_place_step`).  Anything that pass does not clear — a layout other than the one last placed,
        a refused check, a duplicate or a step outside the schedule — returns None with nothing written: the
        caller then validates the sample (:func:`~lelsonar.codec.validate_body`, which names the culprit) and
        adds it again without ``limits``, so that the decoding refuses before the scan does.  ``payload``
        (with ``limits``): the bytes the sample was parsed from, its readings and waveforms then read straight
        from them (:func:`_place_wire`; the message's own fields where they are not plainly encoded).

        Raises
        ------
        InvalidMessageError
            A step outside the schedule, capsules the ScanStart did not list, waveforms of different lengths,
            or a range that needs a speed of sound the scan does not state.
        """
        step = sample.step
        received = self.received
        if step >= self._steps or (step < len(received) and received[step]):
            if limits is not None:
                return None
            if step >= self._steps:
                raise InvalidMessageError(f"step {step} is outside the schedule of {self._steps} steps")
            self.duplicates += 1
            self._compare_copy(sample, step, origin)
            return False
        k = self._k
        known = self._layout
        if limits is not None:
            # Only on the layout of a sample validated before (the same ids, encodings, lengths and clocks: the
            # contract's checks of them passed) but for its checks against ``limits``, made here.
            if known is None or not (
                step < limits.max_steps and k <= limits.max_sensors and known[1] <= limits.max_waveform_samples
            ):
                return None
            if step >= len(received):
                self._allocate(min(self._steps, max(2 * len(received), step + 1)))
            if payload is not None:
                status = _place_wire(
                    payload,
                    self._ids,
                    self._values,
                    self._waves,
                    self._scan,
                    step,
                    sample.acquisition_time_ns,
                    origin == "recovered",
                    *self._rows,
                    self._timing_windows,
                    self._candidate_windows,
                )
                if status != _UNREAD:
                    return self._placed(status, sample, step, self._waves, known, None, True, sample)
        ranges, layout, data = codec.sample_readings(sample.sensors)
        # The fast path, for what the acquisition service sends: the capsules in the ScanStart's order, float32
        # waveforms of one length on one clock (the layout of the previous such sample, or checked here).
        # Anything else (another writer's order, int16 data, a clock per capsule) takes the general path, to
        # the same values.
        fast = layout == known
        if limits is not None and not fast:
            return None
        if step >= len(received):
            self._allocate(min(self._steps, max(2 * len(received), step + 1)))
        if not layout:
            raise InvalidMessageError(f"sample {step} carries no sensor readings")
        n = layout[1]
        carried = sample.sensor_energy[:]  # a list: cheaper to slice out than to unpack the field (~1 µs)
        m = len(carried)
        gamma = sample.gamma_measured
        motor = sample.motor
        if fast or self._one_layout(layout):
            # The readings into the kernel's buffer, after the clocks (the layout's, written there once).
            if m == k:
                self._pack_readings_energies.pack_into(
                    self._buffer,
                    16 * k,
                    gamma,
                    sample.gamma_commanded,
                    motor.load,
                    motor.voltage,
                    motor.temperature,
                    *ranges,
                    *carried,
                )
            else:  # not one a waveform: not the waveforms' energies (recomputed and counted below)
                self._pack_readings.pack_into(
                    self._buffer,
                    16 * k,
                    gamma,
                    sample.gamma_commanded,
                    motor.load,
                    motor.voltage,
                    motor.temperature,
                    *ranges,
                )
            values, joined, one_clock = self._values, b"".join(data), True
        else:
            sensors, carried_list = self._in_capsule_order(sample, carried if m else None)
            ranges, layout, data = codec.sample_readings(sensors)
            joined = np.ascontiguousarray(_waveforms([s.waveform for s in sensors], n), dtype="<f4").tobytes()
            clocks = [v for i in range(k) for v in layout[6 * i + 2 : 6 * i + 4]]  # (rate, t0) of each
            one_clock = clocks == [layout[2], layout[3]] * k
            carried_list = carried_list if m == k else []
            values = np.array(
                [
                    *clocks,
                    gamma,
                    sample.gamma_commanded,
                    motor.load,
                    motor.voltage,
                    motor.temperature,
                    *ranges,
                    *carried_list,
                ],
                dtype=np.float64,
            )
        waveforms = np.frombuffer(joined, dtype=np.float32).reshape(k, n)
        if not self._timing_windows.shape[2] and n and values[0] > 0 and math.isfinite(values[0]):
            # The first sample with waveforms sets the windows' rate.
            self._timing_rate = self._scan[1] = float(values[0])
            self._grow_timing(
                len(self.received), max(int(round((TIMING_WINDOW[1] - TIMING_WINDOW[0]) * self._timing_rate)), 1)
            )
        status = _place_step(
            waveforms,
            values,
            self._scan,
            k if m == k else 0,
            step,
            limits is None,
            sample.acquisition_time_ns,
            origin == "recovered",
            *self._rows,
            self._timing_windows,
            self._candidate_windows,
        )
        return self._placed(status, sample, step, waveforms, layout, ranges, one_clock, waveforms)

    def _compare_copy(self, sample: codec.Sample, step: int, origin: str) -> None:
        """A second copy of a held step: identical, or a conflict; a copy from the acquirer's log settles it.

        The copy is placed in a scratch scan and compared on what the estimate reads (time, angle, ranges,
        energies): only duplicates pay for it.
        """
        probe = ScanAssembly(self.start)
        try:
            probe.add(sample, origin)
            differs = probe.time_ns[step] != self.time_ns[step] or not all(
                np.allclose(getattr(probe, name)[step], getattr(self, name)[step], rtol=1e-9, atol=0, equal_nan=True)
                for name in ("gamma", "gamma_commanded", "distance", "sensor_energy", "echo_amplitude")
            )
        except LelsonarError:
            differs = True
        if origin == "recovered":  # the log is the truth: its copy stays
            if differs:
                self.received[step] = False
                self._timed[step] = False
                self._walk_tested = self._noise_tested = self._recovered = None
                self.add(sample, origin)
                self.replaced += 1
            self.unsettled.discard(step)
        elif differs:
            self.conflicts += 1
            self.unsettled.add(step)

    def _placed(
        self,
        status: int,
        sample: codec.Sample,
        step: int,
        waveforms: np.ndarray,
        layout: list,
        ranges: list | None,
        one_clock: bool,
        latest,
    ) -> bool | None:
        """What a step's placement (:func:`_place_step`'s ``status``) leaves to do, rarely anything: a refusal,
        energies to recompute, ranges without an echo to count; the step is then the latest (``latest``: its
        waveforms, or the sample to read them from).  ``layout``, ``ranges``: the sample's in the order of the
        capsules (``ranges`` read here if None: then the fast path's)."""
        if status > 0 and status & _CANDIDATES:
            status &= ~_CANDIDATES
            self._keep_candidates(step, waveforms, layout)
        if status != _AGREED:
            if status == _UNCHECKED:
                return None
            if status == _NO_SOUND_SPEED:
                if ranges is None:
                    ranges = codec.sample_readings(sample.sensors)[0]
                self._no_sound_speed(step, ranges, layout)
            if not status & _AGREED:
                self.sensor_energy[step] = (
                    waveform_energy(waveforms, layout[2])
                    if one_clock
                    else [waveform_energy(wv, r) for wv, r in zip(waveforms, layout[2::6])]
                )
                _settle_step(self._per_capsule, self._per_step, step, self._scan)  # of these energies
                if len(sample.sensor_energy):
                    self._energy_mismatch(step)
            self.unflagged_ranges += status >> 1
        self._latest = (step, latest, waveforms.shape[1], layout[2], layout[3])  # (the lowest id's clock)
        return True

    def _keep_candidates(self, step: int, waveforms: np.ndarray, layout: list) -> None:
        """Allocate the candidate echoes' windows (the first step with one: a clean scan never holds them) and
        copy step ``step``'s from its ``waveforms`` ((k, n) float32 in capsule order, each on its ``layout``'s
        clock), where the pass found them (``_candidate_start``)."""
        width = self._timing_windows.shape[2]
        self._candidate_windows = np.zeros((len(self.received), self._k, width), np.float32)
        for i in np.flatnonzero(np.isfinite(self._candidate_at[step])):
            c0 = int(round((self._candidate_start[step, i] - layout[6 * i + 3]) * self._timing_rate))
            self._candidate_windows[step, i] = waveforms[i, c0 : c0 + width]

    def _one_layout(self, layout: list) -> bool:
        """Whether a validated sample's layout is the fast path's (the ScanStart's capsule ids in order, float32
        waveforms of one length on one clock); if it is, it is the one to expect next, and its clocks are
        written into the kernel's buffer."""
        k = self._k
        _, n, rate, t0 = layout[:4]
        if not (
            len(layout) == 6 * k
            and layout[::6] == self._capsule_ids
            and layout[1::6] == [n] * k
            and layout[2::6] == [rate] * k
            and layout[3::6] == [t0] * k
            and layout[4::6] == [_FLOAT32] * k
            and layout[5::6] == [4 * n] * k
        ):
            return False
        self._values[: 2 * k] = [rate, t0] * k
        self._layout = layout
        if self._waves.shape[1] != n:
            self._waves = np.empty((k, n), np.float32)
        return True

    def _no_sound_speed(self, step: int, ranges: list, layout: list) -> None:
        for i in range(0, len(ranges) // 3):
            valid, d, t = ranges[3 * i : 3 * i + 3]
            if valid and not (d > 0 and t > 0):
                raise InvalidMessageError(
                    f"sample {step} capsule {layout[6 * i]} gives only its {'distance' if d > 0 else 'time of flight'}"
                    " and the ScanStart states neither sound_speed nor air_temperature to convert it: "
                    "fill both fields of the reading, or ScanStart.sound_speed"
                )

    def _energy_mismatch(self, step: int) -> None:
        self.energy_mismatches += 1
        if self.energy_mismatches == 1:  # once a scan; the rest are counted
            _log.warning(
                "scan %s: the sensor_energy carried by step %d disagrees with its waveforms (or is not "
                "one finite, non-negative value per capsule); recomputed from the waveforms; further "
                "such steps of this scan are counted in energy_mismatches",
                self.key,
                step,
            )

    def _in_capsule_order(self, sample: codec.Sample, carried: list[float] | None) -> tuple[list, list | None]:
        """The sensors of a sample in the order of the ScanStart's capsule ids, and the carried energies in
        the same order; checked (the capsules the ScanStart listed, waveforms of one length)."""
        sensors = list(sample.sensors)
        ids = [s.capsule_id for s in sensors]
        if ids != self._capsule_ids:
            if sorted(ids) != self._capsule_ids:
                raise InvalidMessageError(
                    f"sample {sample.step} carries capsules {ids}; the scan has capsules {self._capsule_ids}"
                )
            order = sorted(range(len(ids)), key=ids.__getitem__)
            sensors = [sensors[i] for i in order]
            if carried is not None and len(carried) == len(order):  # carried in the order of the sensors
                carried = [carried[i] for i in order]
        counts = {s.waveform.sample_count for s in sensors}
        if len(counts) > 1:
            raise InvalidMessageError(f"sample {sample.step} has waveforms of different lengths {sorted(counts)}")
        return sensors, carried

    @property
    def gamma_unmeasured(self) -> bool:
        """Every received step's ``gamma_measured`` is exactly 0 (proto3's unset) while the commanded angles
        move: the writer never filled the measured angle, and :meth:`arrays` uses the commanded one."""
        steps = np.flatnonzero(self.received)
        return len(steps) > 1 and not np.any(self.gamma[steps]) and bool(np.ptp(self.gamma_commanded[steps]) > 0)

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(steps, gamma, distance, ratio)`` of the received steps, in step order.

        γ is the measured angle, or the commanded one where no step's measured angle was filled
        (:attr:`gamma_unmeasured`): with every γ at 0 all beams would point one way.
        """
        steps = np.flatnonzero(self.received)
        gamma = self.gamma_commanded if self.gamma_unmeasured else self.gamma
        return steps, gamma[steps], self.distance[steps], self.ratio[steps]

    def range_walk(self) -> tuple[RangeWalk, np.ndarray, np.ndarray, np.ndarray]:
        """Whether the writer's ranges walk with the echoes' amplitude (:func:`~lelsonar.signal.echo_timing.
        range_walk`, on the echoes of a typical shape), and each received step's offsets (writer's range −
        re-timed, m; NaN: not timed), peaks (V; NaN: no echo found) and whether its shape is typical
        (:func:`~lelsonar.signal.echo_timing.typical_edges`)."""
        steps = np.flatnonzero(self.received)
        if self._walk_tested is not None and self._walk_tested[0] == len(steps):
            return self._walk_tested[1]  # steps only add up: the same count is the same steps

        def test(rows: np.ndarray, halves: bool) -> tuple[RangeWalk, np.ndarray, np.ndarray, np.ndarray]:
            onset, peak, edge = np.moveaxis(self._echo_timing[rows], -1, 0)
            typical = typical_edges(edge)
            offset = -0.5 * (self.sound_speed or math.nan) * onset
            shown = typical | np.isnan(onset)  # clipped echoes count as found but untimed
            walk = range_walk(np.where(typical, offset, np.nan), np.where(shown, peak, np.nan), halves=halves)
            return walk, offset, peak, typical

        # A screen on the checked steps (a quarter of the echoes: the re-timing, ~40 µs a step, is spared on
        # the others where nothing walks), then the test on every step where the screen found a walk.
        checked = steps[steps % RISE_STRIDE == 0]
        self._time_echoes(checked)
        found = test(checked, False)
        if not found[0].detected:
            found = (
                found[0],
                *(np.full(self.distance[steps].shape, np.nan),) * 2,
                np.zeros(self.distance[steps].shape, bool),
            )
        else:
            self._time_echoes(steps)
            found = test(steps, True)
        self._walk_tested = (len(steps), found)  # the final's ranges and its planes' reasons ask it in turn
        return found

    def _time_echoes(self, steps: np.ndarray) -> None:
        """Re-time (:func:`~lelsonar.signal.echo_timing.echo_onsets`) the kept windows of ``steps`` not
        timed yet."""
        todo = steps[~self._timed[steps]]
        at = self._timing_at[todo]
        kept = np.isfinite(at)
        if kept.any():
            timing = np.full((*at.shape, 3), np.nan)
            timing[kept] = np.stack(echo_onsets(self._timing_windows[todo][kept], self._timing_rate, at[kept]), axis=-1)
            self._echo_timing[todo] = timing
        self._timed[todo] = True

    def walk_free(self, distance: np.ndarray) -> np.ndarray:
        """:meth:`arrays`' ``distance`` re-timed from the waveforms where the writer's ranges walk with the
        echoes' amplitude (:func:`~lelsonar.signal.echo_timing.walk_free_ranges`), else as it is."""
        walk, offset, peak, _ = self.range_walk()
        return walk_free_ranges(distance, offset, peak, walk)

    def echo_rise(self) -> tuple[float, float]:
        """The median over the checked readings of the first echo's peak over the peak just before it (both
        above the waveform's DC level): over all of them, and over those with an echo over the noise
        (:meth:`noise_triggers`); NaN with fewer than :data:`RANGE_CHECK_MIN` readings.  Under
        :data:`MIN_ECHO_RISE` the ranges do not match the waveforms (:meth:`ranges_match_waveforms`)."""
        got = self.received
        # Both peaks above the waveform's DC level (max |w| of a carrier burst or of noise over an offset is
        # |offset| + its own peak): a receiver's offset would otherwise pull the rise towards 1.
        dc = self.dc_level[got]
        with np.errstate(divide="ignore", invalid="ignore"):
            rise = (self.echo_amplitude[got] - dc) / (self.pre_echo_peak[got] - dc)
        checked = np.isfinite(rise)
        echoes = checked & ~self.noise_triggers()[0]
        return tuple(
            float(np.median(rise[m])) if np.count_nonzero(m) >= RANGE_CHECK_MIN else math.nan for m in (checked, echoes)
        )

    def ranges_match_waveforms(self) -> bool:
        """Whether the readings' times of flight fall where their waveforms' echoes begin (:meth:`echo_rise`).

        Those readings with an echo over the noise decide: a board whose comparator fires on the noise before
        some echoes leaves the others' ranges right (those are re-timed from the echo after them or left out, :meth:`noise_triggers_recovered`),
        while ranges in another convention than the waveforms (a one-way time, a window's start left unset)
        put next to none of them at an echo's onset.  Too few of them to tell, the scan's readings as a whole
        decide (none to check: they match).
        """
        whole, echoes = self.echo_rise()
        return echoes >= MIN_ECHO_RISE if math.isfinite(echoes) else not whole < MIN_ECHO_RISE

    def noise_triggers(self) -> tuple[np.ndarray, float]:
        """Which readings of the received steps (:meth:`arrays`' rows) show no echo over the noise at their time
        of flight (:func:`~lelsonar.signal.energy.echoes_over_noise`: a board whose comparator fired on
        the noise) nor have a neighbour's echo near their range (:func:`~lelsonar.signal.energy.
        ranges_backed`: a weak echo), and the noise σ (V; NaN: not known).  None where a reading's window was not kept (no
        waveform, or on another clock), nor with fewer than :data:`RANGE_CHECK_MIN` windows."""
        steps = np.flatnonzero(self.received)
        if self._noise_tested is not None and self._noise_tested[0] == len(steps):
            return self._noise_tested[1]  # steps only add up: the same count is the same steps
        at = self._timing_at[steps]
        kept = np.isfinite(at) & np.isfinite(self.distance[steps])
        noise = np.zeros(at.shape, bool)
        sigma = math.nan
        if np.count_nonzero(kept) >= RANGE_CHECK_MIN and self.sound_speed:
            distance = self.distance[steps]
            listened = 2.0 * distance[kept] / self.sound_speed
            echo = np.isfinite(distance)  # a reading without its window is not tested: taken as an echo
            echo[kept], _, sigma = echoes_over_noise(
                self._timing_windows[steps][kept], self._timing_rate, at[kept], listened, _FLOOR_TIME
            )
            # A weak echo beside a neighbour's stays: within the range one echo window spans.
            reach = 0.5 * self.sound_speed * (ECHO_PEAK_WINDOW[1] - ECHO_PEAK_WINDOW[0])
            noise = kept & ~echo & ~ranges_backed(distance, echo, reach)
        self._noise_tested = (len(steps), (noise, sigma))
        return noise, sigma

    def recovered_echoes(self) -> tuple[np.ndarray, np.ndarray]:
        """The ranges (m) and peaks (V, :func:`~lelsonar.signal.energy.echo_amplitude`'s) of the first echo
        after each reading the board fired on noise (:meth:`noise_triggers`; :meth:`arrays`' rows, NaN where
        none), from its waveform (design notes §8).

        At ingest each reading that may be noise kept its waveform around the first echo after its time of
        flight (:func:`_candidate_echo`).  That echo is recovered if it stands over the scan's noise as an
        echo at a board's time of flight must (:func:`~lelsonar.signal.energy.echoes_over_noise`, the
        scan's DC level and σ, over the samples listened to until it), and is timed where a board would time
        it: by constant fraction (:func:`~lelsonar.signal.echo_timing.echo_onsets`, a time that does not
        walk with its strength), with the board's zero where the scan's echoes show it (their ranges less
        their constant-fraction times over the strongest quarter, :attr:`~lelsonar.signal.echo_timing.
        RangeWalk.reference`, as :meth:`walk_free` keeps it), else at the strongest recovered echoes' crossing
        of the noise's level (:func:`~lelsonar.signal.energy.noise_level`) — a comparator set within a
        few σ of the noise, as this board's, fires near there on a strong echo.  An echo clipped at its peak
        (no fraction of it its own) is strong: timed at that crossing.  One not found or too weak to time
        stays out."""
        steps = np.flatnonzero(self.received)
        if self._recovered is not None and self._recovered[0] == len(steps):
            return self._recovered[1]
        noise, _ = self.noise_triggers()
        distance, peak = np.full(noise.shape, np.nan), np.full(noise.shape, np.nan)
        at, start = self._candidate_at[steps], self._candidate_start[steps]
        rows = noise & np.isfinite(at)
        if np.count_nonzero(rows) >= RANGE_CHECK_MIN and self.sound_speed:
            rate = self._timing_rate
            windows = self._candidate_windows[steps][rows]
            at, start = at[rows], start[rows]
            # The noise over these windows' own floors: the time-of-flight windows' may lie in the transmitter's
            # ring-down, where a board that fires on the noise as soon as its blanking ends puts them.
            echo, _, sigma = echoes_over_noise(windows, rate, at, start + at, _FLOOR_TIME)
            self._recovery_sigma = sigma
            onset, envelope, _ = echo_onsets(windows, rate, at)
            # Where each echo's envelope rises through the noise's level (clipped echoes too: strong ones).
            crossing = echo_onsets(windows, rate, at, level=noise_level(sigma, start + at, rate))[0]
            timed = echo & np.isfinite(onset) & np.isfinite(crossing)
            level_zero = 0.0
            if timed.any():
                # The strongest quarter's crossing of the noise's level, as a board set near it times them.
                strong = timed & (envelope >= np.percentile(envelope[timed], 75.0))
                level_zero = float(np.median(crossing[strong] - onset[strong]))
            # An echo clipped at its peak (no fraction of it to time) is strong: its crossing, less that zero.
            cf = np.where(timed, onset, np.where(echo & np.isfinite(crossing), crossing - level_zero, np.nan))
            walk = self.range_walk()[0] if self.ranges_match_waveforms() else None
            if walk is not None and walk.n >= MIN_TIMED:
                # The scan's echoes give the board's own zero: its ranges less their constant-fraction ones over
                # the strongest quarter (RangeWalk.reference), as the re-timed ranges keep it (walk_free_ranges).
                distance[rows] = 0.5 * self.sound_speed * (start + at + cf) + walk.reference
            else:
                distance[rows] = 0.5 * self.sound_speed * (start + at + cf + level_zero)
            amplitude = echo_amplitude(windows, rate, 0.0, at)
            peak[rows] = np.where(np.isfinite(cf), amplitude, np.nan)
        self._recovered = (len(steps), (distance, peak))
        return distance, peak

    def noise_triggers_recovered(self, distance: np.ndarray, amplitude: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`arrays`' ``distance`` and the echoes' peaks (``amplitude``) with the readings that mark no echo
        (:meth:`noise_triggers`) replaced by the echo after them (:meth:`recovered_echoes`; NaN where none), if
        the scan's ranges otherwise match its waveforms (:meth:`ranges_match_waveforms`) or most readings are
        noise (:meth:`noise_share`) whose ranges change from step to step as the noise's crossings do
        (:meth:`noise_independence`: a board firing on the noise, not ranges in another convention than the
        waveforms); unchanged otherwise (nothing the readings mark can be told from noise: the scan is
        unreliable as a whole, :meth:`writer_problems`)."""
        noise, _ = self.noise_triggers()
        if not noise.any() or not (
            self.ranges_match_waveforms() or self.noise_share() > 0.5 and self.noise_independence() > NOISE_INDEPENDENT
        ):
            return distance, amplitude
        found, peak = self.recovered_echoes()
        return np.where(noise, found, distance), np.where(noise, peak, amplitude)

    def noise_independence(self) -> float:
        """How the ranges of the readings that mark no echo (:meth:`noise_triggers`) change from step to step: the
        median |difference| between a capsule's consecutive such readings over their spread (1.4826·MAD); NaN
        with fewer than :data:`RANGE_CHECK_MIN` differences.

        The noise's crossings are drawn anew at each reading (anywhere in the time the board listened, or all
        just after its blanking): about 1, as for independent draws.  A surface's ranges in another convention
        than the waveforms' times (a one-way time, a window's start left unset) change smoothly with the beam:
        next to 0.
        """
        noise, _ = self.noise_triggers()
        d = np.where(noise, self.distance[np.flatnonzero(self.received)], np.nan)
        jumps = np.abs(np.diff(d, axis=0))
        jumps = jumps[np.isfinite(jumps)]
        if jumps.size < RANGE_CHECK_MIN:
            return math.nan
        ranges = d[np.isfinite(d)]
        spread = 1.4826 * float(np.median(np.abs(ranges - np.median(ranges))))
        step = float(np.median(jumps))
        return step / spread if spread > 0 else (math.inf if step > 0 else 0.0)

    def noise_share(self) -> float:
        """The share of the received readings with a range that mark no echo (:meth:`noise_triggers`)."""
        readings = int(np.count_nonzero(np.isfinite(self.distance[self.received])))
        return np.count_nonzero(self.noise_triggers()[0]) / max(readings, 1)

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
            out.append(
                (
                    None,
                    "no Sample filled gamma_measured (all 0): the commanded angles were used instead; "
                    "fill gamma_measured with the motor's measured angle",
                )
            )
        if self.unflagged_ranges and not np.isfinite(self.distance[got]).any():
            out.append(
                (
                    None,
                    f"no reading is marked echo_valid, yet {self.unflagged_ranges} carry a distance: set "
                    "echo_valid = true on readings with an echo (the contract reads no range from the "
                    "others)",
                )
            )
        _, gamma, _, _ = self.arrays()
        if gamma.size and (float(np.ptp(gamma)) > 2.0 * math.pi or float(np.max(np.abs(gamma))) > 2.0 * math.pi):
            # The AX-12 turns through 300°: a sweep over a turn, or an angle beyond one, is not in radians.
            out.append(
                (
                    UNRELIABLE,
                    f"γ spans {np.min(gamma):.1f} to {np.max(gamma):.1f} rad, beyond a turn: the "
                    "angles are not in rad (degrees?); the contract's gamma_measured is in rad",
                )
            )
        noise, sigma = self.noise_triggers()
        readings = int(np.count_nonzero(np.isfinite(self.distance[got])))
        share = self.noise_share()
        found = np.count_nonzero(np.isfinite(self.recovered_echoes()[0])) if noise.any() else 0
        recovered = (
            f"; {found} of them re-timed from the first echo over the noise after it in their waveforms "
            "(constant-fraction times), the others left out"
            if found
            else "; left out"
        )
        independence = self.noise_independence() if share > 0.5 else math.nan
        if not self.ranges_match_waveforms() and independence > NOISE_INDEPENDENT:
            # (σ over the echoes' windows: the time-of-flight windows may lie in the transmitter's ring-down.)
            out.append(
                (
                    DEGRADED,
                    f"{100 * share:.0f} % of the readings show no echo over the noise (σ "
                    f"{1e3 * self._recovery_sigma:.1f} mV) at their time of flight, and their ranges "
                    "change from step to step as independent draws do (median step "
                    f"{independence:.2f}× their spread), not as a surface's: the board's comparator "
                    f"fires on the noise (a threshold within a few σ of it){recovered}; their zero is "
                    "the strongest echoes' crossing of the noise's level, not the board's",
                )
            )
        elif not self.ranges_match_waveforms():
            whole, echoes = self.echo_rise()
            rise = echoes if math.isfinite(echoes) else whole
            # Most readings marking noise is a board whose comparator fires on it, or ranges in another
            # convention than the waveforms (their echoes elsewhere): the windows alone cannot tell which.
            noisy = (
                f"{100 * share:.0f} % of the readings show no echo over the noise (σ {1e3 * sigma:.1f} mV) at "
                f"their time of flight{recovered}: the board's comparator fires on the noise (a threshold "
                "within a few σ of it), or "
                if share > 0.5
                else ""
            )
            out.append(
                (
                    UNRELIABLE,
                    f"the waveforms show no echo starting at the readings' time of flight (median rise "
                    f"×{rise:.2f} over the {1e3 * -PRE_ECHO_WINDOW[0]:.1f} ms before): {noisy}the "
                    "ranges do not match the waveforms (distance is one way, time_of_flight the "
                    "round trip from firing, waveform.t0 the first sample's time)",
                )
            )
        elif (
            noise.any()
        ):  # re-timed or left out (noise_triggers_recovered): named on every plane, the verdict left to the fit
            out.append(
                (
                    GOOD,
                    f"{np.count_nonzero(noise)} of the {readings} readings ({100 * share:.1f} %) show no "
                    f"echo over the noise (σ {1e3 * sigma:.1f} mV) at their time of flight: the board's "
                    f"comparator fired on noise{recovered}",
                )
            )
        walk = self.range_walk()[0]
        if walk.detected:  # re-timed (walk_free): named on every plane, the verdict left to the fit
            out.append((GOOD, walk_finding(walk)))
        c_air = air_sound_speed(self.start)
        if (
            self.start.sound_speed > 0
            and c_air is not None
            and abs(self.start.sound_speed / c_air - 1.0) > SOUND_SPEED_TOLERANCE
        ):
            out.append(
                (
                    DEGRADED,
                    f"ScanStart.sound_speed {self.start.sound_speed:.1f} m/s is not the speed of sound "
                    f"at its air_temperature {self.start.air_temperature:.1f} K ({c_air:.1f} m/s): the "
                    "range scale is uncertain",
                )
            )
        ratio = self.range_tof_ratio[got]
        ratio = ratio[np.isfinite(ratio)]
        if ratio.size >= RANGE_CHECK_MIN:
            off = float(np.median(ratio)) - 1.0
            if abs(off) > RANGE_TOF_TOLERANCE:
                # The planes rest on the distance; which of the two fields is right the scan cannot tell (the
                # waveforms place the time of flight, not the speed of sound).  A few % is a scale error of
                # centimetres: degraded; beyond, one field is in another convention (a one-way time, a
                # round-trip path): unreliable.
                out.append(
                    (
                        UNRELIABLE if abs(off) > 5 * RANGE_TOF_TOLERANCE else DEGRADED,
                        f"the readings' distance is {100 * off:+.0f} % off c·time_of_flight/2 at the stated "
                        f"speed of sound {self.sound_speed:.1f} m/s: the range scale is uncertain (distance is "
                        "one way, time_of_flight the round trip, sound_speed the air's)",
                    )
                )
        return out

    def raw_points(self, step: int) -> np.ndarray:
        """Eq. (9) points of one received step, (k, 3); NaN rows where no echo."""
        return beam_points(self.geometry, self.gamma[step : step + 1], self.distance[step : step + 1])[0]


# --- a Sample read from its payload ---------------------------------------------------------------------------
# The fields :func:`_read_sample` reads, by their numbers in lelsonar/v1/scan.proto: literals, so that the
# compiled code (cached by this file's contents) never holds numbers other than these, and checked against the
# generated descriptors on import.
_SAMPLE_GAMMA_COMMANDED, _SAMPLE_GAMMA_MEASURED, _SAMPLE_MOTOR, _SAMPLE_SENSORS, _SAMPLE_ENERGY = 6, 7, 8, 9, 10
_MOTOR_LOAD, _MOTOR_VOLTAGE, _MOTOR_TEMPERATURE = 2, 3, 4
_READING_CAPSULE, _READING_VALID, _READING_TOF, _READING_DISTANCE, _READING_WAVEFORM = 1, 2, 3, 4, 5
_WAVE_ENCODING, _WAVE_DATA, _WAVE_RATE, _WAVE_T0, _WAVE_COUNT = 1, 2, 4, 5, 6
for _message, _fields in (
    (
        codec.Sample,
        {
            "gamma_commanded": _SAMPLE_GAMMA_COMMANDED,
            "gamma_measured": _SAMPLE_GAMMA_MEASURED,
            "motor": _SAMPLE_MOTOR,
            "sensors": _SAMPLE_SENSORS,
            "sensor_energy": _SAMPLE_ENERGY,
        },
    ),
    (scan_pb2.MotorStatus, {"load": _MOTOR_LOAD, "voltage": _MOTOR_VOLTAGE, "temperature": _MOTOR_TEMPERATURE}),
    (
        scan_pb2.SensorReading,
        {
            "capsule_id": _READING_CAPSULE,
            "echo_valid": _READING_VALID,
            "time_of_flight": _READING_TOF,
            "distance": _READING_DISTANCE,
            "waveform": _READING_WAVEFORM,
        },
    ),
    (
        codec.Waveform,
        {
            "encoding": _WAVE_ENCODING,
            "data": _WAVE_DATA,
            "sample_rate": _WAVE_RATE,
            "t0": _WAVE_T0,
            "sample_count": _WAVE_COUNT,
        },
    ),
):
    if {name: _message.DESCRIPTOR.fields_by_name[name].number for name in _fields} != _fields:
        raise ConfigError(
            f"lelsonar.v1.{_message.DESCRIPTOR.name}'s field numbers are not the ones "
            "assembly._read_sample reads: a schema that breaks the wire format"
        )
del _message, _fields
_VARINT, _FIXED64, _LENGTH, _FIXED32 = 0, 1, 2, 5
_ONE = 0x3FF0000000000000  # 1.0's bits


@kernel
def _wire_varint(buf, i, end):
    """The base-128 varint at ``buf[i:end]``, and the index after it (-1: none there)."""
    value = np.uint64(0)
    shift = np.uint64(0)
    while i < end and shift < 64:
        b = np.uint64(buf[i])
        i += 1
        value |= (b & np.uint64(0x7F)) << shift
        if b < 0x80:
            return value, i
        shift += np.uint64(7)
    return value, -1


@kernel
def _wire_fixed64(buf, i):
    """The little-endian 64 bits at ``buf[i:i + 8]`` (a double's, bit for bit)."""
    value = np.uint64(0)
    for j in range(8):
        value |= np.uint64(buf[i + j]) << np.uint64(8 * j)
    return value


@kernel
def _wire_length(buf, i, end):
    """The bounds (start, end) of the length-delimited field whose length is at ``buf[i:end]``; (-1, -1): none."""
    size, i = _wire_varint(buf, i, end)
    if i < 0 or size > end - i:
        return -1, -1
    return i, i + np.int64(size)


@kernel
def _wire_skip(buf, i, end, wire_type):
    """The index after a field of ``wire_type`` whose value starts at ``buf[i]`` (-1: a group, or malformed)."""
    if wire_type == _VARINT:
        return _wire_varint(buf, i, end)[1]
    if wire_type == _FIXED64:
        return i + 8 if i + 8 <= end else -1
    if wire_type == _LENGTH:
        return _wire_length(buf, i, end)[1]
    if wire_type == _FIXED32:
        return i + 4 if i + 4 <= end else -1
    return -1


@kernel
def _read_reading(buf, i, end, capsule_id, bits, at, clock, row):
    """One ``SensorReading`` (``buf[i:end]``) of :func:`_read_sample`: its ``echo_valid, distance,
    time_of_flight`` into ``bits[at:at + 3]`` (1.0 or 0.0, and the doubles' bits) and its waveform's samples into
    ``row``; False (``row`` and ``bits`` then partly written) unless the reading is plainly encoded and on the
    fast path's layout: ``capsule_id``, a float32 waveform of ``row.size`` samples on the clock whose bits are
    ``bits[clock:clock + 2]`` (rate, t0)."""
    n = row.size
    bits[at] = 0
    bits[at + 1] = 0
    bits[at + 2] = 0
    valid = capsule = np.uint64(0)
    seen = 0
    a = b = -1
    while i < end:
        tag, i = _wire_varint(buf, i, end)
        if i < 0:
            return False
        field, wire_type = np.int64(tag >> np.uint64(3)), np.int64(tag & np.uint64(7))
        if field == _READING_CAPSULE or field == _READING_VALID:
            if wire_type != _VARINT or seen & (1 << field):
                return False
            v, i = _wire_varint(buf, i, end)
            if i < 0:
                return False
            if field == _READING_CAPSULE:
                capsule = v
            else:
                valid = v
        elif field == _READING_TOF or field == _READING_DISTANCE:
            if wire_type != _FIXED64 or seen & (1 << field) or i + 8 > end:
                return False
            bits[at + 2 if field == _READING_TOF else at + 1] = _wire_fixed64(buf, i)
            i += 8
        elif field == _READING_WAVEFORM:
            if wire_type != _LENGTH or seen & (1 << field):
                return False
            a, b = _wire_length(buf, i, end)
            if a < 0:
                return False
            i = b
        else:  # a field this build does not know: skipped, as the parser keeps it aside
            i = _wire_skip(buf, i, end, wire_type)
            if i < 0:
                return False
            continue
        seen |= 1 << field
    if capsule != capsule_id or a < 0:
        return False
    if valid != 0:  # (a bool is any varint but 0)
        bits[at] = _ONE
    encoding = count = rate = t0 = np.uint64(0)
    d0 = d1 = -1
    seen = 0
    i = a
    while i < b:
        tag, i = _wire_varint(buf, i, b)
        if i < 0:
            return False
        field, wire_type = np.int64(tag >> np.uint64(3)), np.int64(tag & np.uint64(7))
        if field == _WAVE_ENCODING or field == _WAVE_COUNT:
            if wire_type != _VARINT or seen & (1 << field):
                return False
            v, i = _wire_varint(buf, i, b)
            if i < 0:
                return False
            if field == _WAVE_ENCODING:
                encoding = v
            else:
                count = v
        elif field == _WAVE_RATE or field == _WAVE_T0:
            if wire_type != _FIXED64 or seen & (1 << field) or i + 8 > b:
                return False
            if field == _WAVE_RATE:
                rate = _wire_fixed64(buf, i)
            else:
                t0 = _wire_fixed64(buf, i)
            i += 8
        elif field == _WAVE_DATA:
            if wire_type != _LENGTH or seen & (1 << field):
                return False
            d0, d1 = _wire_length(buf, i, b)
            if d0 < 0:
                return False
            i = d1
        else:
            i = _wire_skip(buf, i, b, wire_type)
            if i < 0:
                return False
            continue
        seen |= 1 << field
    # The layout's clock to the bit (stricter than ==, which the fast path's clocks, finite, need no more of).
    if not (encoding == _FLOAT32 and count == n and d1 - d0 == 4 * n and rate == bits[clock] and t0 == bits[clock + 1]):
        return False
    # A loop over the bytes: one vectorised copy (a slice assignment checks for overlap and copies twice).
    src, dst = buf[d0:d1], row.view(np.uint8)
    for j in range(d1 - d0):
        dst[j] = src[j]
    return True


@kernel
def _read_sample(payload, ids, values, waveforms):
    """What a ``Sample``'s payload holds that :func:`_place_step` reads, straight from the protobuf wire format:
    γ measured and commanded, the motor's load, voltage and temperature and each reading's ``echo_valid,
    distance, time_of_flight`` into ``values`` (where :func:`_place_step` reads them; a field absent is 0, as
    the parser gives it), the first k carried energies after them, and each waveform's samples into
    ``waveforms`` — bit for bit what the parsed message's fields hold.

    Only a payload plainly encoded (each field read here once, with its own wire type, no groups) on the fast
    path's layout (the k readings in the order of the capsule ``ids``, float32 waveforms of
    ``waveforms.shape[1]`` samples each on the clocks in ``values[:2k]``, to the bit) is read; anything else,
    however valid, is left to the parsed message (-1; ``values`` and ``waveforms`` then partly written).

    Returns
    -------
    int
        How many energies the sample carries (≥ 0), or -1: not read.
    """
    buf = np.frombuffer(payload, dtype=np.uint8)
    bits = values.view(np.uint64)
    k = ids.size
    head, readings, energies = 2 * k, 2 * k + 5, 5 * k + 5
    for j in range(head, head + 5):
        bits[j] = 0
    sensors = carried = seen = 0
    i, end = 0, buf.size
    while i < end:
        tag, i = _wire_varint(buf, i, end)
        if i < 0:
            return -1
        field, wire_type = np.int64(tag >> np.uint64(3)), np.int64(tag & np.uint64(7))
        if field == _SAMPLE_SENSORS:
            if wire_type != _LENGTH or sensors == k:
                return -1
            a, b = _wire_length(buf, i, end)
            if a < 0 or not _read_reading(
                buf, a, b, np.uint64(ids[sensors]), bits, readings + 3 * sensors, 2 * sensors, waveforms[sensors]
            ):
                return -1
            sensors += 1
            i = b
        elif field == _SAMPLE_ENERGY:  # a repeated double: packed runs, or one at a time
            if wire_type == _FIXED64:
                a, b = i, i + 8
            elif wire_type == _LENGTH:
                a, b = _wire_length(buf, i, end)
            else:
                return -1
            if a < 0 or b > end or (b - a) % 8:
                return -1
            for j in range(a, b, 8):
                if carried < k:
                    bits[energies + carried] = _wire_fixed64(buf, j)
                carried += 1
            i = b
        elif field == _SAMPLE_GAMMA_MEASURED or field == _SAMPLE_GAMMA_COMMANDED:
            if wire_type != _FIXED64 or seen & (1 << field) or i + 8 > end:
                return -1
            bits[head if field == _SAMPLE_GAMMA_MEASURED else head + 1] = _wire_fixed64(buf, i)
            i += 8
            seen |= 1 << field
        elif field == _SAMPLE_MOTOR:
            if wire_type != _LENGTH or seen & (1 << field):
                return -1
            a, b = _wire_length(buf, i, end)
            if a < 0:
                return -1
            read = 0
            while a < b:
                tag, a = _wire_varint(buf, a, b)
                if a < 0:
                    return -1
                f, w = np.int64(tag >> np.uint64(3)), np.int64(tag & np.uint64(7))
                if f == _MOTOR_LOAD or f == _MOTOR_VOLTAGE or f == _MOTOR_TEMPERATURE:
                    if w != _FIXED64 or read & (1 << f) or a + 8 > b:
                        return -1
                    bits[head + 2 + (0 if f == _MOTOR_LOAD else 1 if f == _MOTOR_VOLTAGE else 2)] = _wire_fixed64(
                        buf, a
                    )
                    a += 8
                    read |= 1 << f
                else:
                    a = _wire_skip(buf, a, b, w)
                    if a < 0:
                        return -1
            i = b
            seen |= 1 << field
        else:  # the header (read by the parser), or a field this build does not know
            i = _wire_skip(buf, i, end, wire_type)
            if i < 0:
                return -1
    return carried if sensors == k else -1


@kernel
def _place_wire(
    payload,
    ids,
    values,
    waveforms,
    scan,
    step,
    time_ns,
    recovered,
    per_capsule,
    per_step,
    acquired_ns,
    received,
    recovered_mask,
    timing_windows,
    candidate_windows,
):
    """:func:`_place_step` of a sample not validated, read from its ``payload`` (:func:`_read_sample`, into
    ``values`` and ``waveforms``); ``_UNREAD`` if it could not be read that way (nothing placed)."""
    carried = _read_sample(payload, ids, values, waveforms)
    if carried < 0:
        return _UNREAD
    k = ids.size
    return _place_step(
        waveforms,
        values,
        scan,
        k if carried == k else 0,
        step,
        False,
        time_ns,
        recovered,
        per_capsule,
        per_step,
        acquired_ns,
        received,
        recovered_mask,
        timing_windows,
        candidate_windows,
    )


# --- the per-sample kernel ------------------------------------------------------------------------------------
#: :func:`_place_step`'s refusals (nothing written): a sample not validated that its screen does not clear (a
#: check of the contract, or a NaN or infinite sum of squares: NaN or infinite samples, or squares that
#: overflowed float32), a range without a speed of sound.
_UNCHECKED, _NO_SOUND_SPEED = -1, -2
#: :func:`_place_wire`'s: a payload not read (not plainly encoded, or not the fast path's layout), nothing written.
_UNREAD = -3
#: In its result otherwise: the carried energies agree and were written; the rest counts unflagged ranges.
_AGREED = 1
#: ... plus this where a reading's candidate echo was found before the scan kept any (their windows not allocated
#: yet: :meth:`ScanAssembly._keep_candidates` copies this step's); the unflagged ranges count below it.
_CANDIDATES = 1 << 24


@kernel
def _place_step(
    waveforms,
    values,
    scan,
    m,
    step,
    checked,
    time_ns,
    recovered,
    per_capsule,
    per_step,
    acquired_ns,
    received,
    recovered_mask,
    timing_windows,
    candidate_windows,
):
    """Everything one step's readings and waveforms give, in one pass while they are in the cache: unless the
    sample was validated, the checks of the contract on its readings (:func:`lelsonar.codec.validate_body`'s
    screen: γ and the motor's readings finite, each valid echo's range finite, positive and below
    ``codec.MAX_RANGE_M``); each waveform's samples checked finite, its carried eq. (10) energy checked (:func:`energy_agrees`, float32 sum
    of squares), each reading's range and round trip (one from the other at the speed of sound where only one
    is given), the first echo's peak (:func:`~lelsonar.signal.energy.echo_amplitude`'s window), and on
    every :data:`RISE_STRIDE`-th step the peak just before it, the DC level and distance / (c·tof/2); written
    into row ``step`` of the scan's arrays, with γ, the time and the step's origin; each waveform around its
    time of flight (:data:`~lelsonar.signal.echo_timing.TIMING_WINDOW`), to re-time the echo if need be,
    and where the reading may be the noise a board fired on, the same around its first echo after
    (:func:`_candidate_echo`); and, where the carried energies were written, the step's E^γ, E0(d_m) and R (:func:`_settle_step`,
    eq. 11–12).

    Parameters
    ----------
    waveforms : (k, n) float32 array
        The k waveforms (V), in the order of the scan's capsules (k: the scan's, ``per_capsule.shape[2]``).
    values : (≥ 6·k + 5,) float64 array
        Each waveform's sample rate (Hz) and t0 (s); γ measured and commanded (rad); the motor's load,
        voltage and temperature; each reading's ``echo_valid, distance, time_of_flight`` (same order); the
        ``m`` carried energies (V²·s), m = k or 0 (none to check).
    scan : (7,) float64 array
        The scan's speed of sound (m/s; NaN: none stated), the timing windows' rate (Hz), and its energy
        model φ0, φ1, φ2, d_min, d_max (eq. 12).
    checked : bool
        The sample was validated (:func:`lelsonar.codec.validate_body`): its samples are finite, so a
        non-finite sum of squares is an overflow (the energies then disagree); otherwise that, or a reading
        the screen does not clear, is ``_UNCHECKED`` (for the caller to validate it, naming the culprit).
    time_ns, recovered : int, bool
        The sample's acquisition time and origin (the acquirer's log).
    per_capsule, per_step : (7, steps, k), (5, steps) float64 arrays
        The scan's blocks (:data:`_PER_CAPSULE`, :data:`_PER_STEP`).
    acquired_ns, received, recovered_mask : (steps,) arrays
        The scan's ``time_ns``, ``received``, ``recovered_mask``.
    timing_windows : (steps, k, width) float32 array
        Where each waveform's window around its time of flight goes, if its rate is the windows' (``scan[1]``)
        and the window lies inside it (its start's offset from the time of flight into ``_timing_at``).
    candidate_windows : (steps, k, width) float32 array
        Where a waveform's window around its candidate echo goes (:func:`_candidate_echo`; the echo's crossing
        after the window's start into ``_candidate_at``, the start's time into ``_candidate_start``).

    Returns
    -------
    int
        A refusal (< 0, nothing written), else ``_AGREED`` if the carried energies were each waveform's and
        written (not written otherwise, nor E^γ, E0 and R), plus twice the readings without an echo that carry
        a range anyway, plus ``_CANDIDATES`` if a candidate echo's window was found but not kept
        (``candidate_windows`` not allocated yet).
    """
    k, n = waveforms.shape
    clocks, readings, energies = values[: 2 * k], values[2 * k + 5 : 5 * k + 5], values[5 * k + 5 : 5 * k + 5 + m]
    if not checked:
        # codec._validate_sample's screen (a sum is finite only if each term is), refusing nothing it clears.
        if not math.isfinite(
            values[2 * k] + values[2 * k + 1] + values[2 * k + 2] + values[2 * k + 3] + values[2 * k + 4]
        ):
            return _UNCHECKED
        for i in range(k):
            d, t = readings[3 * i + 1], readings[3 * i + 2]
            if readings[3 * i] != 0.0 and not (math.isfinite(t + d) and 0.0 < d < MAX_RANGE_M and t > 0.0):
                return _UNCHECKED
    agreed = m == k
    for i in range(k):
        squares = np.dot(waveforms[i], waveforms[i])  # float32, as energy_agrees' bound assumes
        if not math.isfinite(squares):  # NaN or infinite samples (or float32 overflow)
            if not checked:
                return _UNCHECKED
            agreed = False
        elif agreed:
            agreed = energy_agrees(energies[i], float(squares), n, clocks[2 * i])
    c, timing_rate = scan[0], scan[1]
    for i in range(k):
        if readings[3 * i] != 0.0 and not (readings[3 * i + 1] > 0.0 and readings[3 * i + 2] > 0.0) and not c == c:
            return _NO_SOUND_SPEED
    distance, sensor_energy, echo_amplitude = per_capsule[0], per_capsule[1], per_capsule[2]
    pre_echo_peak, dc_level, range_tof_ratio, timing_at = per_capsule[3], per_capsule[4], per_capsule[5], per_capsule[6]
    candidate_at, candidate_start = per_capsule[7], per_capsule[8]
    width = timing_windows.shape[2]
    sampled = step % RISE_STRIDE == 0
    unflagged = 0
    unkept = False
    for i in range(k):
        d, t = readings[3 * i + 1], readings[3 * i + 2]
        rate, t0 = clocks[2 * i], clocks[2 * i + 1]
        ratio = np.nan
        if readings[3 * i] != 0.0:  # echo_valid
            if not (d > 0.0 and t > 0.0):
                if d > 0.0:
                    t = 2.0 * d / c
                else:
                    d = 0.5 * c * t
            elif c == c:
                ratio = d / (0.5 * c * t)
        else:
            if d > 0.0:  # NaN compares false: only a positive range counts
                unflagged += 1
            d = t = np.nan
        distance[step, i] = d
        if agreed:
            sensor_energy[step, i] = energies[i]
        row = waveforms[i]
        echo_amplitude[step, i] = _window_peak(row, rate, t0, t, ECHO_PEAK_WINDOW[0], ECHO_PEAK_WINDOW[1])
        if width > 0 and rate == timing_rate and t > 0.0:  # NaN compares false: no echo, nothing to time
            a = int(round((t + TIMING_WINDOW[0] - t0) * rate))
            if a >= 0 and a + width <= n:
                timing_windows[step, i, :] = row[a : a + width]
                timing_at[step, i] = t - (t0 + a / rate)
                b = _candidate_echo(row, a, width, rate)
                if b >= 0:
                    c0 = (
                        b + a - width // 2
                    )  # the crossing in the middle of its window, as the time of flight in its own
                    if c0 + width <= n:
                        if candidate_windows.shape[2] == width:
                            candidate_windows[step, i, :] = row[c0 : c0 + width]
                        else:
                            unkept = True
                        candidate_at[step, i] = (b + a - c0) / rate
                        candidate_start[step, i] = t0 + c0 / rate
        if sampled:
            range_tof_ratio[step, i] = ratio
            if n > 0:
                pre_echo_peak[step, i] = _window_peak(row, rate, t0, t, PRE_ECHO_WINDOW[0], PRE_ECHO_WINDOW[1])
    if sampled and n > 0:
        _dc_levels(waveforms, dc_level[step])
    per_step[0, step], per_step[1, step] = values[2 * k], values[2 * k + 1]  # γ measured, commanded
    if agreed:
        _settle_step(per_capsule, per_step, step, scan)
    acquired_ns[step] = time_ns
    received[step] = True
    recovered_mask[step] = recovered
    return (_AGREED if agreed else 0) + 2 * unflagged + (_CANDIDATES if unkept else 0)


#: A reading whose first :data:`~lelsonar.signal.energy.ECHO_PEAK_WINDOW` after its time of flight rises
#: (half its peak to peak) less than this over the same time before may be the noise a board's comparator fired
#: on: its first echo after is looked for (:func:`_candidate_echo`).  The noise's crossing of a threshold within a
#: few σ of it stands ~1–2× over the noise before it (the largest of ~100 samples against the first crossing in
#: the ~1,000 the board listened to); an echo rises by its own signal-to-noise ratio.  Loose: which readings are
#: noise is decided at the final, over the scan's noise (:meth:`ScanAssembly.noise_triggers`).
CANDIDATE_RISE = 4.0
#: The candidate echo is where ``|w − DC|`` first reaches this many times the noise spike's own peak (the
#: largest ``|w − DC|`` over the spike's window): twice the level the noise reached once in the time the board
#: listened stands over it in the time after (Gaussian tails: z → 2z is a false alarm ~e^(−3z²/2) as likely),
#: while an echo a board would report stands well over its threshold.  An echo under that level is passed over
#: for the next one (a board with a higher threshold would report that one too); the final checks the echo
#: found stands over the scan's noise (:func:`~lelsonar.signal.energy.echoes_over_noise`).
CANDIDATE_LEVEL = 2.0


@kernel
def _candidate_echo(row, a, width, rate):
    """The sample of ``row`` where the first echo after a time of flight that may be the noise a board fired on
    begins (:data:`CANDIDATE_RISE`, :data:`CANDIDATE_LEVEL`), as an offset from the timing window's first sample
    ``a`` (the window ``width`` samples wide, the time of flight in its middle); -1: not such a reading, or no
    echo after it.

    The DC level is the mean of the waveform from the window on (after the transmitter's ring-down, which the
    board's blanking leaves behind; an echo's carrier averages out).
    """
    n = row.size
    mid = a + width // 2
    span = window_samples(rate, ECHO_PEAK_WINDOW[0], ECHO_PEAK_WINDOW[1])
    if mid - span < a or mid + span > n:
        return -1
    lo_b = hi_b = row[mid - span]
    for j in range(mid - span, mid):
        lo_b, hi_b = min(lo_b, row[j]), max(hi_b, row[j])
    lo_a = hi_a = row[mid]
    for j in range(mid, mid + span):
        lo_a, hi_a = min(lo_a, row[j]), max(hi_a, row[j])
    if hi_a - lo_a >= CANDIDATE_RISE * (hi_b - lo_b):
        return -1  # an echo rises at the time of flight
    total = 0.0
    for j in range(a, n):
        total += row[j]
    dc = total / (n - a)
    spike = max(abs(hi_a - dc), abs(lo_a - dc))
    level = CANDIDATE_LEVEL * spike
    for j in range(mid + span, n):
        if abs(row[j] - dc) >= level:
            return j - a
    return -1


@kernel
def _settle_step(per_capsule, per_step, step, scan):
    """Row ``step``'s E^γ (eq. 11), E0(d_m) (eq. 12, where the step has a range) and R = E^γ / E0(d_m) (§4; 0
    without a range), from its ranges and eq. (10) energies, bit for bit what
    :func:`~lelsonar.signal.energy.total_energy`, :func:`~lelsonar.signal.energy.median_range` and
    :func:`~lelsonar.signal.energy.energy_ratio` give (E0 as ``EnergyModel.expected_energy`` of the
    model in ``scan[2:7]``: φ0, φ1, φ2, d_min, d_max)."""
    step_energy = 0.0 + _pairwise_block(per_capsule[1, step], 0, per_capsule.shape[2])  # as add.reduce
    per_step[2, step] = step_energy
    d_m = step_median_range(per_capsule[0, step])
    if math.isfinite(d_m):
        d = min(max(d_m, scan[5]), scan[6])  # np.clip to the calibrated interval
        e0 = 1.0 / (scan[2] * d * d + scan[3] * d + scan[4])
        per_step[3, step] = e0
        per_step[4, step] = step_energy / e0
    else:
        per_step[4, step] = 0.0


@kernel
def _window_peak(row, rate, t0, round_trip, lo, hi):
    """The largest |w| of ``row`` over the window (``lo``, ``hi``) s after ``round_trip``
    (:func:`~lelsonar.signal.energy.echo_amplitude` of one waveform: exact, in float32); NaN: none."""
    n = row.size
    a = echo_window_start(n, rate, t0, round_trip, lo)
    if a < 0:
        return np.nan
    peak = abs(row[a])
    for j in range(a + 1, min(a + window_samples(rate, lo, hi), n)):
        v = abs(row[j])
        if v > peak:
            peak = v
    return float(peak)


@kernel
def _dc_levels(waveforms, out):
    """|mean| of each float32 waveform (row), V, into ``out``, bit for bit what ``np.mean(..., axis=-1,
    dtype=np.float64)`` gives: that sums the samples in float64 in order (through its cast, not pairwise).

    In-order float64 additions cannot run side by side without changing the rounding, so they are done
    exactly instead where they can be: scaled by 2^s so that each sample is an integer and all of them
    together stay below 2^52, the samples add up in int64 (side by side), and every partial sum of the
    in-order float64 additions was exact too — the same number.  A waveform whose samples do not all fit
    (a dynamic range beyond ~2^40 at ``n`` samples) is summed in order.
    """
    k, n = waveforms.shape
    if n == 0:
        return
    bits = 0
    while (1 << bits) < n:
        bits += 1
    for i in range(k):
        row = waveforms[i]
        s = 52 - bits - ((_largest_bits(row) >> 23) - 126)  # |sample| < 2^(exponent + 1): n of them < 2^52 after 2^s
        total, inexact = _scaled_sum(row, 2.0**s)
        out[i] = _dc_level_in_order(row) if inexact else abs(float(total) * 2.0**-s / n)


@kernel
def _largest_bits(row):
    """The largest |sample|'s float32 bit pattern (an int: its exponent in bits 23–30)."""
    patterns = row.view(np.int32)
    top = np.int32(0)
    for j in range(patterns.size):
        top = max(top, patterns[j] & np.int32(0x7FFFFFFF))
    return top


@kernel
def _scaled_sum(row, scale):
    """Σ row·scale in int64, and whether any term was not an integer."""
    total = np.int64(0)
    inexact = np.int64(0)
    for j in range(row.size):
        y = np.float64(row[j]) * scale
        whole = np.int64(y)
        total += whole
        inexact |= np.int64(np.float64(whole) != y)
    return total, inexact != 0


@kernel
def _dc_level_in_order(row):
    """|mean| of a float32 waveform summed in float64 in order (:func:`_dc_levels` where it cannot be exact)."""
    total = 0.0
    for v in row:
        total += float(v)
    return abs(total / row.size)


def _waveforms(waves: list, n: int) -> np.ndarray:
    """(k, n) float32 V of ``k`` validated ``Waveform``s of ``n`` samples each, in order."""
    if all(w.encoding == _FLOAT32 for w in waves):
        return np.frombuffer(b"".join([w.data for w in waves]), dtype="<f4").reshape(len(waves), n)
    return np.stack([codec.unpack_waveform(w, validated=True) for w in waves])
