"""The arrays of one scan, held as its samples are placed, and its latest step for display (no I/O).

:class:`ScanArrays` declares and allocates what :class:`~lelsonar.reconstruct.stream.assembly.ScanAssembly`
knows of one (scanner, scan), placed there: per step the measured γ, ranges, the energy of each capsule
(eq. 10), the first echo's peak, the kept waveform windows, where each step came from (the live stream or the
acquirer's log), and the latest step's waveforms, for display.

The per-step arrays grow with the highest step that actually arrived (doubling, capped at
``ScanStart.steps``): a ScanStart claiming many steps costs nothing until its samples come.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import InitVar, dataclass, field
from typing import NamedTuple

import numpy as np

from lelsonar import codec
from lelsonar.geometry import ArrayGeometry
from lelsonar.reconstruct.stream.scan_start import energy_model_of, scan_geometry, speed_of_sound
from lelsonar.reconstruct.stream.step_features import PER_CAPSULE, PER_STEP
from lelsonar.reconstruct.stream.writer_checks import WriterChecks
from lelsonar.signal.energy import EnergyModel
from lelsonar.v1 import scan_pb2

_FLOAT32 = scan_pb2.WAVEFORM_ENCODING_FLOAT32_LE


_SENSOR_ENERGY, _STEP_ENERGY = PER_CAPSULE.index("sensor_energy"), PER_STEP.index("step_energy")
#: The windows of a scan that has none yet (no rows, no width): read only for their shape.
_NO_WINDOWS = np.zeros((0, 0, 0), np.float32)
_NO_WINDOWS.flags.writeable = False


class ScanDescription(NamedTuple):
    """What a ``ScanStart`` states of its scanner that a scan's arrays are made from (:attr:`ScanArrays.description`):
    the same for every ``ScanStart`` equal to it but for ``scan_id`` and ``start_time_ns``, which none of it reads
    (a scanner sends the same description scan after scan).  Read only, shared by the scans made from it."""

    geometry: ArrayGeometry
    capsule_ids: list  # the ScanStart's capsule ids, ascending: row i of the arrays is the i-th
    ids: np.ndarray  # the same, int64
    sound_speed: float | None
    energy_model: EnergyModel
    energy_model_problem: str | None


def describe(start: codec.ScanStart) -> ScanDescription:
    """The :class:`ScanDescription` of a validated ``ScanStart``."""
    geometry = scan_geometry(start)
    # Capsules are matched by the ids the ScanStart gave them (0..k-1 from our writer, any unique ids from
    # another); row i of the arrays is the i-th id in ascending order, as the geometry's capsule i.
    ids = sorted(c.capsule_id for c in start.capsules)
    e = start.energy_model
    model, problem = energy_model_of(e.phi0, e.phi1, e.phi2, e.valid_min_range, e.valid_max_range)
    return ScanDescription(geometry, ids, np.array(ids, dtype=np.int64), speed_of_sound(start), model, problem)


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
class ScanArrays(WriterChecks):
    """Everything known about one (scanner, scan): its arrays, allocated and grown, and its latest step."""

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

    #: What ``start`` states of its scanner, derived once for the scans of equal ScanStarts.
    description: ScanDescription = field(init=False, repr=False)
    #: The :attr:`description` of ``start`` if the caller has it (an equal ScanStart's scan's): not derived again.
    described: InitVar[ScanDescription | None] = None

    def __post_init__(self, described: ScanDescription | None = None) -> None:
        self.description = described = describe(self.start) if described is None else described
        self.geometry, self._capsule_ids, self._ids, self.sound_speed, self.energy_model, self.energy_model_problem = (
            described
        )
        self._k = self.geometry.n_capsules
        self._steps = int(self.start.steps)
        # Each reading's waveform around its time of flight (echo_timing.TIMING_WINDOW), kept to re-time the
        # echoes if the scan's ranges walk with their amplitude (range_walk): (steps, k, width) float32 at the
        # rate of the first sample's first capsule (width 0 until then; a capsule on another clock is not kept).
        self._timing_rate = math.nan
        # A reading that may be the noise a board fired on (:func:`candidate_echo`): its waveform around the
        # first echo after its time of flight, the same width (the echo recovered at the final if the reading
        # proves to be noise, :meth:`recovered_echoes`); both made by :meth:`_grow_timing`.
        self._timing_windows = self._candidate_windows = _NO_WINDOWS
        # (steps, k, 3) each echo re-timed (echo_timing.echo_onsets): onset − tof (s), peak (V), edge (s); and
        # which steps have been (re-timing is done only when the ranges are tested, RISE_STRIDE-th steps first):
        # made by :meth:`_allocate`.
        self._walk_tested: tuple[int, tuple] | None = None  # (steps received, range_walk()) when last asked
        self._noise_tested: tuple[int, tuple] | None = None  # (steps received, noise_triggers()) when last asked
        self._recovered: tuple[int, tuple] | None = None  # (steps received, recovered_echoes()) when last asked
        self._recovery_sigma = math.nan  # V, the noise σ over the recovered echoes' windows
        self._wire: tuple | None = None  # place_wire's arguments (ScanAssembly._wire_for), dropped as the arrays grow
        # The latest step placed: (step, its (k, n) float32 waveforms or the payload they lie in, its layout: each
        # reading's capsule id, samples, rate, t0…), made a StepView when read.
        self._latest: StepView | tuple | None = None
        self._allocate(min(self.start.steps, self.INITIAL_ROWS))

    def _allocate(self, n: int) -> None:
        """Hold ``n`` rows, keeping what is there (rows of steps not received stay empty).

        The (steps, k) arrays are the planes of one block, and the (steps,) float arrays the rows of another,
        one array each for the kernel to write a step into; those two and each echo's timing are views of one
        allocation, as are the flags (received, recovered, timed): a scan's arrays cost five allocations.
        """
        k = self._k
        planes, rows = len(PER_CAPSULE) * n * k, len(PER_STEP) * n
        floats = np.full(planes + rows + 3 * n * k, np.nan)
        per_capsule = floats[:planes].reshape(len(PER_CAPSULE), n, k)
        per_step = floats[planes : planes + rows].reshape(len(PER_STEP), n)
        timing = floats[planes + rows :].reshape(n, k, 3)
        per_capsule[_SENSOR_ENERGY] = 0.0
        per_step[_STEP_ENERGY:] = 0.0
        time_ns, flags = np.zeros(n, np.int64), np.zeros((3, n), bool)
        received, recovered, timed = flags
        if "_per_capsule" in self.__dict__:  # (grown: what is there kept)
            had = self._per_capsule.shape[1]
            per_capsule[:, :had] = self._per_capsule
            per_step[:, :had] = self._per_step
            timing[:had] = self._echo_timing
            time_ns[:had], received[:had], recovered[:had] = self.time_ns, self.received, self.recovered_mask
            timed[:had] = self._timed
        self._per_capsule, self._per_step = per_capsule, per_step
        for name, plane in zip(PER_CAPSULE, per_capsule):
            setattr(self, name, plane)
        for name, row in zip(PER_STEP, per_step):
            setattr(self, name, row)
        self.time_ns, self.received, self.recovered_mask = time_ns, received, recovered
        self._echo_timing, self._timed = timing, timed
        self._rows = (per_capsule, per_step, time_ns, received, recovered)  # what the kernel writes a step into
        self._grow_timing(n, self._timing_windows.shape[2])

    def _arrays(self) -> tuple[np.ndarray, ...]:
        """What :func:`~lelsonar.reconstruct.stream.step_features.place_step` writes a step into."""
        return (*self._rows, self._timing_windows, self._candidate_windows)

    def _grow_timing(self, n: int, width: int) -> None:
        """Hold ``n`` rows of timing windows ``width`` samples wide (and of candidate echoes' windows, if the scan
        keeps them), keeping what is there at the same width."""
        # Not cleared: a window is read only where its step's ``_timing_at`` is finite, which the pass writes with it
        # (clearing half a megabyte a scan costs more than all its reads of them).
        windows = np.empty((n, self._k, width), np.float32)
        same = width == self._timing_windows.shape[2]
        # (The candidates' only once one was found, :meth:`_keep_candidates`.)
        candidates = np.zeros((n, self._k, self._candidate_windows.shape[2] if same else 0), np.float32)
        if same and width:
            had = min(n, len(self._timing_windows))
            windows[:had] = self._timing_windows[:had]
            candidates[:had] = self._candidate_windows[:had]
        self._timing_windows, self._candidate_windows = windows, candidates
        self._wire = None  # (its arrays changed)

    @property
    def newest_ns(self) -> int:
        """The acquisition time of the latest step placed (else of the highest step received; 0: none), without
        unpacking its waveforms (:attr:`latest` does, for display)."""
        view = self._latest
        if view is not None:
            return int(self.time_ns[view.step if isinstance(view, StepView) else view[0]])
        steps = np.flatnonzero(self.received)
        return int(self.time_ns[steps[-1]]) if len(steps) else 0

    @property
    def latest(self) -> StepView | None:
        """The latest step placed, for display (its waveforms unpacked when first read)."""
        view = self._latest
        if view is None or isinstance(view, StepView):
            return view
        step, held, layout = view
        n, rate, t0 = layout[1:4]  # (the lowest id's clock)
        # (k, n) float32, or the payload its waveforms were read from (on the fast path's layout: its sensors in
        # the order of the capsules), parsed only for display
        if not isinstance(held, np.ndarray):
            held = stacked_waveforms([s.waveform for s in codec.parse(held, codec.Sample).sensors], n)
        waveforms = held
        self._latest = view = StepView(
            step, int(self.time_ns[step]), float(self.gamma[step]), self.distance[step].copy(), waveforms, rate, t0
        )
        return view


def stacked_waveforms(waves: list, n: int) -> np.ndarray:
    """(k, n) float32 V of ``k`` validated ``Waveform``s of ``n`` samples each, in order."""
    if all(w.encoding == _FLOAT32 for w in waves):
        return np.frombuffer(b"".join([w.data for w in waves]), dtype="<f4").reshape(len(waves), n)
    return np.stack([codec.unpack_waveform(w, validated=True) for w in waves])
