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
peak window is cut out of each waveform; the peaks, and R (§4), are worked
out for many steps at once (:meth:`ScanAssembly.settle`) when first read, when
the ScanEnd comes, or every :attr:`ScanAssembly.SETTLE_EVERY` steps.

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
    EnergyModel,
    echo_window_starts,
    echo_window_width,
    energy_ratio,
    total_energy,
    waveform_energy,
    waveform_energy_agrees,
    window_peak,
)
from lelsonar.v1 import scan_pb2

_log = logging.getLogger(__name__)

_FLOAT32 = scan_pb2.WAVEFORM_ENCODING_FLOAT32_LE


def geometry_from_start(start: codec.ScanStart) -> ArrayGeometry:
    """The array geometry a ``ScanStart`` describes (capsules on x at the radial offset)."""
    ordered = sorted(start.capsules, key=lambda c: c.capsule_id)
    for c in ordered:
        if abs(c.position.z) > 1e-9 or abs(c.boresight.y - 1.0) > 1e-9:
            raise InvalidMessageError(
                f"capsule {c.capsule_id} is not on the x axis line facing +y; this build supports only linear arrays")
    return ArrayGeometry(capsule_x=tuple(c.position.x for c in ordered), radial_offset=start.radial_offset)


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

    ``sensor_energy``, ``echo_amplitude``, ``step_energy``, ``expected_energy``
    and ``ratio`` are properties that first :meth:`settle` the steps placed
    since they were last read (write nothing into them).
    """

    start: codec.ScanStart
    geometry: ArrayGeometry = field(init=False)
    energy_model: EnergyModel = field(init=False)
    energy_model_problem: str | None = field(init=False)   # why E0 is the uncalibrated one, if it is
    gamma: np.ndarray = field(init=False)            # (steps,) rad, NaN until received
    distance: np.ndarray = field(init=False)         # (steps, k) m, NaN = no echo / not received
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
    #: echo windows, 4 × 80 float32 samples a step).
    SETTLE_EVERY = 256

    def __post_init__(self) -> None:
        self.geometry = geometry_from_start(self.start)
        self._capsule_ids = list(range(self.geometry.n_capsules))
        self.energy_model, self.energy_model_problem = energy_model_from_start(self.start)
        # Steps placed since the last settle(), and the windows of their first echoes, by width:
        # (float32 bytes of each window, its flat index in echo_amplitude).
        self._unsettled: list[int] = []
        self._windows: dict[int, tuple[list[bytes], list[int]]] = {}
        self._shape: tuple[int, float, float] | None = None   # the latest (samples, rate, t0), and its window width
        self._width = 0
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
        self.distance = grown("distance", (k,), np.nan)
        self._sensor_energy = grown("_sensor_energy", (k,), 0.0)      # (steps, k) V²·s, eq. 10
        self._echo_amplitude = grown("_echo_amplitude", (k,), np.nan)  # (steps, k) V, first echo's peak; NaN: none
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
        # One pass over the readings, for what the acquisition service sends (capsules in order, float32
        # waveforms of one length): each echo's range and round trip, and the samples.
        ranges = [math.nan] * k
        tof = [math.nan] * k
        data = []
        i = 0
        for s in sensors:
            w = s.waveform
            if s.capsule_id != i or w.sample_count != n or w.encoding != _FLOAT32:
                break
            if samples is None:
                data.append(w.data)
            if s.echo_valid:
                ranges[i] = d = s.distance
                # The round trip, where the echo sits in the waveform; a recorder that leaves it
                # unset still gave the range, and the speed of sound is in the ScanStart.
                t = s.time_of_flight
                tof[i] = t if t > 0 else 2.0 * d / self.start.sound_speed
            i += 1
        carried = sample.sensor_energy
        carried = list(carried) if len(carried) else None
        if i == k and len(sensors) == k:
            joined = samples if samples is not None and len(samples) == 4 * k * n else b"".join(
                data or [s.waveform.data for s in sensors])
        else:  # anything else: the same, the general way
            sensors, ranges, tof, carried = self._readings(sample, carried)
            joined = _waveforms([s.waveform for s in sensors], n).astype("<f4", copy=False).tobytes()
        # The (k, n) float32 samples, worked on while they are in the cache (holding them for later would
        # cost more: fresh memory for each step, and a cold cache for the next step's decoding).
        waveforms = np.frombuffer(joined, dtype="<f4").reshape(k, n)
        if carried is not None and waveform_energy_agrees(waveforms, rate, carried):
            self._sensor_energy[step] = carried  # the writer's, checked against the samples
        else:
            self._sensor_energy[step] = waveform_energy(waveforms, rate)
            if carried is not None:
                self._energy_mismatch(step)
        # The first echoes' peak windows, cut out of the samples now and reduced with the other steps' later.
        shape = (n, rate, t0)
        if shape != self._shape:
            self._shape, self._width = shape, echo_window_width(rate)
        width = self._width
        size = 4 * width
        chunks = where = None
        for i, a in enumerate(echo_window_starts(n, rate, t0, tof)):
            if a >= 0:
                at = 4 * (i * n + a)
                window = joined[at:at + min(size, 4 * (n - a))]
                if len(window) < size:  # off the end: zeros, which leave the largest |w| as it is
                    window += bytes(size - len(window))
                if chunks is None:
                    chunks, where = self._windows.setdefault(width, ([], []))
                chunks.append(window)
                where.append(step * k + i)
        self.gamma[step] = sample.gamma_measured
        self.distance[step] = ranges
        self.time_ns[step] = sample.acquisition_time_ns
        self.received[step] = True
        self.recovered_mask[step] = origin == "recovered"
        self._latest = (step, sample.acquisition_time_ns, sample.gamma_measured, joined, shape)
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

    def _readings(self, sample: codec.Sample, carried: list[float] | None) -> tuple[list, list, list, list | None]:
        """The sensors of a sample in capsule order, their ranges and round trips (NaN: no echo), and the
        carried energies in the same order; checked."""
        k = self.geometry.n_capsules
        sensors = list(sample.sensors)
        ids = [s.capsule_id for s in sensors]
        if ids != self._capsule_ids:
            if sorted(ids) != self._capsule_ids:
                raise InvalidMessageError(f"sample {sample.step} carries capsules {ids}; the scan has capsules "
                                          f"0..{k - 1}")
            order = sorted(range(k), key=ids.__getitem__)
            sensors = [sensors[i] for i in order]
            if carried is not None and len(carried) == k:  # carried in the order of the sensors
                carried = [carried[i] for i in order]
        counts = {s.waveform.sample_count for s in sensors}
        if len(counts) > 1:
            raise InvalidMessageError(f"sample {sample.step} has waveforms of different lengths {sorted(counts)}")
        ranges = [math.nan] * k
        tof = [math.nan] * k
        for i, s in enumerate(sensors):
            if s.echo_valid:
                ranges[i] = d = s.distance
                t = s.time_of_flight
                tof[i] = t if t > 0 else 2.0 * d / self.start.sound_speed
        return sensors, ranges, tof, carried

    def settle(self) -> None:
        """Work out, for the steps placed since the last call and all at once, the first echoes' peaks (from the
        windows cut out by :meth:`add`), E^γ (eq. 11), E0(d_m) (eq. 12) and R (§4)."""
        if self._windows:
            flat = self._echo_amplitude.reshape(-1)
            for width, (chunks, where) in self._windows.items():
                flat[where] = window_peak(np.frombuffer(b"".join(chunks), dtype="<f4").reshape(-1, width))
            self._windows = {}
        if not self._unsettled:
            return
        steps = np.array(self._unsettled)
        self._unsettled = []
        self._step_energy[steps] = step_energy = total_energy(self._sensor_energy[steps])
        expected = self._expected_energy[steps]
        self._ratio[steps] = energy_ratio(step_energy, self.distance[steps], self.energy_model, expected=expected)
        self._expected_energy[steps] = expected

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(steps, gamma, distance, ratio)`` of the received steps, in step order."""
        steps = np.flatnonzero(self.received)
        return steps, self.gamma[steps], self.distance[steps], self.ratio[steps]

    def raw_points(self, step: int) -> np.ndarray:
        """Eq. (9) points of one received step, (k, 3); NaN rows where no echo."""
        return beam_points(self.geometry, self.gamma[step:step + 1], self.distance[step:step + 1])[0]


def _waveforms(waves: list, n: int) -> np.ndarray:
    """(k, n) float32 V of ``k`` validated ``Waveform``s of ``n`` samples each, in order."""
    if all(w.encoding == _FLOAT32 for w in waves):
        return np.frombuffer(b"".join([w.data for w in waves]), dtype="<f4").reshape(len(waves), n)
    return np.stack([codec.unpack_waveform(w, validated=True) for w in waves])
