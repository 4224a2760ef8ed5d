"""One scan, assembled from its messages in whatever order they arrive (no I/O).

Samples are placed by step index, so arrival order does not matter; a second
copy of a step is dropped.  Per step the assembly keeps what the math needs —
measured γ, ranges, the energy of each capsule (eq. 10) — and the waveforms of
the latest step only, for display.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lelsonar import codec
from lelsonar.errors import InvalidMessageError
from lelsonar.geometry import ArrayGeometry, beam_points
from lelsonar.reconstruct.energy import EnergyModel, echo_amplitude, median_range, total_energy, waveform_energy


def geometry_from_start(start: codec.ScanStart) -> ArrayGeometry:
    """The array geometry a ``ScanStart`` describes (capsules on x at the radial offset)."""
    ordered = sorted(start.capsules, key=lambda c: c.capsule_id)
    for c in ordered:
        if abs(c.position.z) > 1e-9 or abs(c.boresight.y - 1.0) > 1e-9:
            raise InvalidMessageError(
                f"capsule {c.capsule_id} is not on the x axis line facing +y; this build supports only linear arrays")
    return ArrayGeometry(capsule_x=tuple(c.position.x for c in ordered), radial_offset=start.radial_offset)


def energy_model_from_start(start: codec.ScanStart) -> EnergyModel:
    e = start.energy_model
    return EnergyModel(e.phi0, e.phi1, e.phi2, d_min=e.valid_min_range, d_max=e.valid_max_range)


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
    gamma: np.ndarray = field(init=False)            # (steps,) rad, NaN until received
    distance: np.ndarray = field(init=False)         # (steps, k) m, NaN = no echo / not received
    sensor_energy: np.ndarray = field(init=False)    # (steps, k) V²·s
    echo_amplitude: np.ndarray = field(init=False)   # (steps, k) V, peak of the first echo alone, NaN: none
    step_energy: np.ndarray = field(init=False)      # (steps,) E^γ, eq. 11
    expected_energy: np.ndarray = field(init=False)  # (steps,) E0(d_m), eq. 12
    ratio: np.ndarray = field(init=False)            # (steps,) R = E^γ / E0(d_m); 0 without a valid range
    time_ns: np.ndarray = field(init=False)          # (steps,)
    received: np.ndarray = field(init=False)         # (steps,) bool
    end: codec.ScanEnd | None = None
    duplicates: int = 0
    latest: StepView | None = None

    def __post_init__(self) -> None:
        self.geometry = geometry_from_start(self.start)
        self.energy_model = energy_model_from_start(self.start)
        n, k = self.start.steps, self.geometry.n_capsules
        self.gamma = np.full(n, np.nan)
        self.distance = np.full((n, k), np.nan)
        self.sensor_energy = np.zeros((n, k))
        self.echo_amplitude = np.full((n, k), np.nan)
        self.step_energy = np.zeros(n)
        self.expected_energy = np.zeros(n)
        self.ratio = np.zeros(n)
        self.time_ns = np.zeros(n, dtype=np.int64)
        self.received = np.zeros(n, dtype=bool)

    @property
    def key(self) -> tuple[str, int]:
        return (self.start.scanner_id, self.start.scan_id)

    @property
    def n_received(self) -> int:
        return int(np.count_nonzero(self.received))

    @property
    def complete(self) -> bool:
        """All the samples that the ScanEnd announced have arrived."""
        return self.end is not None and self.n_received >= self.end.samples_sent

    def add(self, sample: codec.Sample) -> bool:
        """Place a sample; return False for a duplicate step.

        Raises
        ------
        InvalidMessageError
            A step outside the schedule, or capsules the ScanStart did not list.
        """
        step = sample.step
        if step >= self.start.steps:
            raise InvalidMessageError(f"step {step} is outside the schedule of {self.start.steps} steps")
        if self.received[step]:
            self.duplicates += 1
            return False
        k = self.geometry.n_capsules
        ids = [s.capsule_id for s in sample.sensors]
        if sorted(ids) != list(range(k)):
            raise InvalidMessageError(f"sample {step} carries capsules {ids}; the scan has capsules 0..{k - 1}")
        distance = np.full(k, np.nan)
        tof = np.full(k, np.nan)
        waves = [None] * k
        for s in sample.sensors:
            if s.echo_valid:
                distance[s.capsule_id] = s.distance
                tof[s.capsule_id] = s.time_of_flight
            waves[s.capsule_id] = codec.unpack_waveform(s.waveform, validated=True)  # ingest decoded it
        lengths = {w.size for w in waves}
        if len(lengths) != 1:
            raise InvalidMessageError(f"sample {step} has waveforms of different lengths {sorted(lengths)}")
        rate = sample.sensors[0].waveform.sample_rate
        waveforms = np.stack(waves)
        self.gamma[step] = sample.gamma_measured
        self.distance[step] = distance
        self.sensor_energy[step] = waveform_energy(waveforms, rate)
        self.echo_amplitude[step] = echo_amplitude(waveforms, rate, sample.sensors[0].waveform.t0, tof)
        # R of this step, once, as energy_ratio() computes it for a whole scan (§4).
        self.step_energy[step] = total_energy(self.sensor_energy[step])
        d_m = median_range(distance[None, :])[0]
        if np.isfinite(d_m):
            self.expected_energy[step] = float(self.energy_model.expected_energy(d_m))
            self.ratio[step] = self.step_energy[step] / self.expected_energy[step]
        self.time_ns[step] = sample.acquisition_time_ns
        self.received[step] = True
        self.latest = StepView(step, sample.acquisition_time_ns, sample.gamma_measured, distance, waveforms, rate,
                               sample.sensors[0].waveform.t0)
        return True

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(steps, gamma, distance, ratio)`` of the received steps, in step order."""
        steps = np.flatnonzero(self.received)
        return steps, self.gamma[steps], self.distance[steps], self.ratio[steps]

    def raw_points(self, step: int) -> np.ndarray:
        """Eq. (9) points of one received step, (k, 3); NaN rows where no echo."""
        return beam_points(self.geometry, self.gamma[step:step + 1], self.distance[step:step + 1])[0]
