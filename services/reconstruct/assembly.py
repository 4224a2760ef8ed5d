"""One scan, assembled from its messages in whatever order they arrive (no I/O).

Samples are placed by step index, so arrival order does not matter; a second
copy of a step is dropped.  Per step the assembly keeps what the math needs —
measured γ, ranges, the energy of each capsule (eq. 10) — and the waveforms of
the latest step only, for display.

The per-step arrays grow with the highest step that actually arrived (doubling,
capped at ``ScanStart.steps``): a ScanStart claiming many steps costs nothing
until its samples come.  The assembly knows which steps it lacks
(:meth:`ScanAssembly.missing_steps`) and where each step came from (the live
stream or the acquirer's log), for the per-scan accounting.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from lelsonar import codec
from lelsonar.errors import ConfigError, InvalidMessageError
from lelsonar.geometry import ArrayGeometry, beam_points
from lelsonar.reconstruct.energy import EnergyModel, echo_amplitude, waveform_energy
from lelsonar.v1 import scan_pb2


_FLOAT32 = scan_pb2.WAVEFORM_ENCODING_FLOAT32_LE


def _median_of_valid(distance: list[float]) -> float:
    """:func:`~lelsonar.reconstruct.energy.median_range` of one step, without numpy's per-call overhead:
    the same arithmetic on the same numbers (the mean of the two middle valid ranges), so the same bits."""
    valid = sorted(x for x in distance if x == x)
    c = len(valid)
    if not c:
        return math.nan
    return 0.5 * (valid[(c - 1) // 2] + valid[c // 2])


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
    """Everything known about one (scanner, scan)."""

    start: codec.ScanStart
    geometry: ArrayGeometry = field(init=False)
    energy_model: EnergyModel = field(init=False)
    energy_model_problem: str | None = field(init=False)   # why E0 is the uncalibrated one, if it is
    gamma: np.ndarray = field(init=False)            # (steps,) rad, NaN until received
    distance: np.ndarray = field(init=False)         # (steps, k) m, NaN = no echo / not received
    sensor_energy: np.ndarray = field(init=False)    # (steps, k) V²·s
    echo_amplitude: np.ndarray = field(init=False)   # (steps, k) V, peak of the first echo alone, NaN: none
    step_energy: np.ndarray = field(init=False)      # (steps,) E^γ, eq. 11
    expected_energy: np.ndarray = field(init=False)  # (steps,) E0(d_m), eq. 12
    ratio: np.ndarray = field(init=False)            # (steps,) R = E^γ / E0(d_m); 0 without a valid range
    time_ns: np.ndarray = field(init=False)          # (steps,)
    received: np.ndarray = field(init=False)         # (steps,) bool
    recovered_mask: np.ndarray = field(init=False)   # (steps,) bool: the step came from the acquirer's log
    end: codec.ScanEnd | None = None
    duplicates: int = 0
    #: Messages of this scan that were refused, by reason (the wire's ScanAccounting.rejected).
    rejected: Counter = field(default_factory=Counter)
    latest: StepView | None = None

    #: Rows allocated at first; the arrays double as higher steps arrive, up to ScanStart.steps.
    INITIAL_ROWS = 256

    def __post_init__(self) -> None:
        self.geometry = geometry_from_start(self.start)
        self._capsule_ids = list(range(self.geometry.n_capsules))
        self.energy_model, self.energy_model_problem = energy_model_from_start(self.start)
        self._allocate(min(self.start.steps, self.INITIAL_ROWS))

    def _allocate(self, n: int) -> None:
        """Hold ``n`` rows, keeping what is there (rows of steps not received stay empty)."""
        k = self.geometry.n_capsules

        def grown(name: str, tail: tuple[int, ...], fill, dtype=float) -> np.ndarray:
            new = np.full((n, *tail), fill, dtype=dtype)
            old = getattr(self, name, None)
            if isinstance(old, np.ndarray):
                new[:len(old)] = old
            return new

        self.gamma = grown("gamma", (), np.nan)
        self.distance = grown("distance", (k,), np.nan)
        self.sensor_energy = grown("sensor_energy", (k,), 0.0)
        self.echo_amplitude = grown("echo_amplitude", (k,), np.nan)
        self.step_energy = grown("step_energy", (), 0.0)
        self.expected_energy = grown("expected_energy", (), 0.0)
        self.ratio = grown("ratio", (), 0.0)
        self.time_ns = grown("time_ns", (), 0, np.int64)
        self.received = grown("received", (), False, bool)
        self.recovered_mask = grown("recovered_mask", (), False, bool)

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

    def add(self, sample: codec.Sample, origin: str = "live") -> bool:
        """Place a sample (``origin`` "live" or "recovered"); return False for a duplicate step.

        Raises
        ------
        InvalidMessageError
            A step outside the schedule, or capsules the ScanStart did not list.
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
        if [s.capsule_id for s in sensors] != self._capsule_ids:
            ids = [s.capsule_id for s in sensors]
            if sorted(ids) != self._capsule_ids:
                raise InvalidMessageError(f"sample {step} carries capsules {ids}; the scan has capsules 0..{k - 1}")
            sensors = sorted(sensors, key=lambda s: s.capsule_id)
        # One pass over the readings: the waveforms, and each echo's range and round trip.
        waves = []
        ranges = [math.nan] * k
        tof = [math.nan] * k
        for i, s in enumerate(sensors):
            waves.append(s.waveform)
            if s.echo_valid:
                ranges[i] = d = s.distance
                # The round trip, where the echo sits in the waveform; a recorder that leaves it
                # unset still gave the range, and the speed of sound is in the ScanStart.
                t = s.time_of_flight
                tof[i] = t if t > 0 else 2.0 * d / self.start.sound_speed
        first = waves[0]
        n, rate, t0 = first.sample_count, first.sample_rate, first.t0
        if any(w.sample_count != n for w in waves):
            raise InvalidMessageError(f"sample {step} has waveforms of different lengths "
                                      f"{sorted({w.sample_count for w in waves})}")
        # One (k, n) float32 array of the waveforms (ingest decoded and validated them); for float32 data a
        # read-only view of the joined bytes: one copy in all.
        if all(w.encoding == _FLOAT32 for w in waves):
            waveforms = np.frombuffer(b"".join([w.data for w in waves]), dtype="<f4").reshape(k, n)
        else:
            waveforms = np.stack([codec.unpack_waveform(w, validated=True) for w in waves])
        distance = np.array(ranges)
        energy = waveform_energy(waveforms, rate)
        self.gamma[step] = sample.gamma_measured
        self.distance[step] = distance
        self.sensor_energy[step] = energy
        self.echo_amplitude[step] = echo_amplitude(waveforms, rate, t0, tof)
        # R of this step, once, as energy_ratio() computes it for a whole scan (§4).
        self.step_energy[step] = total = float(energy.sum())
        d_m = _median_of_valid(ranges)
        if d_m == d_m:  # not NaN
            self.expected_energy[step] = expected = float(self.energy_model.expected_energy(d_m))
            self.ratio[step] = total / expected
        self.time_ns[step] = sample.acquisition_time_ns
        self.received[step] = True
        self.recovered_mask[step] = origin == "recovered"
        self.latest = StepView(step, sample.acquisition_time_ns, sample.gamma_measured, distance, waveforms, rate, t0)
        return True

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(steps, gamma, distance, ratio)`` of the received steps, in step order."""
        steps = np.flatnonzero(self.received)
        return steps, self.gamma[steps], self.distance[steps], self.ratio[steps]

    def raw_points(self, step: int) -> np.ndarray:
        """Eq. (9) points of one received step, (k, 3); NaN rows where no echo."""
        return beam_points(self.geometry, self.gamma[step:step + 1], self.distance[step:step + 1])[0]
