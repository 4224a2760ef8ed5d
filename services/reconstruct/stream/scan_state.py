"""The arrays one scan's samples fill, and what they say read as they stand (no I/O, nothing placed here).

:class:`ScanState` declares the state :class:`~lelsonar.reconstruct.stream.assembly.ScanAssembly` keeps
(placed by it, read by the checks built on this class: the noise triggers, the range repair, the writer
checks) and the accessors that only read it: which steps arrived, the (steps, γ, distance, R) of record, a
step's points.
"""

from __future__ import annotations

from collections import Counter

import numpy as np

from lelsonar import codec
from lelsonar.geometry import ArrayGeometry, beam_points
from lelsonar.signal.echo_timing import RangeWalk
from lelsonar.signal.energy import EnergyModel


class ScanState:
    """The state of one (scanner, scan) and its read-only accessors.

    The public arrays are documented on :class:`~lelsonar.reconstruct.stream.scan_arrays.ScanArrays`, which
    allocates them (:class:`~lelsonar.reconstruct.stream.assembly.ScanAssembly` fills them); the private ones
    are the kept waveform windows and the caches of the scan-wide checks.
    """

    start: codec.ScanStart
    end: codec.ScanEnd | None
    geometry: ArrayGeometry
    energy_model: EnergyModel
    sound_speed: float | None
    unflagged_ranges: int
    rejected: Counter
    gamma: np.ndarray
    gamma_commanded: np.ndarray
    distance: np.ndarray
    sensor_energy: np.ndarray
    echo_amplitude: np.ndarray
    pre_echo_peak: np.ndarray
    dc_level: np.ndarray
    range_tof_ratio: np.ndarray
    ratio: np.ndarray
    time_ns: np.ndarray
    received: np.ndarray
    recovered_mask: np.ndarray
    # The blocks the arrays above are planes and rows of, and what the kernel writes a step into.
    _per_capsule: np.ndarray
    _per_step: np.ndarray
    _rows: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]
    # The kept windows (:mod:`~lelsonar.reconstruct.stream.step_features`) and the checks' caches.
    _timing_rate: float
    _timing_at: np.ndarray
    _timing_windows: np.ndarray
    _candidate_at: np.ndarray
    _candidate_start: np.ndarray
    _candidate_windows: np.ndarray
    _echo_timing: np.ndarray
    _timed: np.ndarray
    _walk_tested: tuple[int, tuple[RangeWalk, np.ndarray, np.ndarray, np.ndarray]] | None
    _noise_tested: tuple[int, tuple[np.ndarray, float]] | None
    _recovered: tuple[int, tuple[np.ndarray, np.ndarray]] | None
    _recovery_sigma: float

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

    def raw_points(self, step: int) -> np.ndarray:
        """Eq. (9) points of one received step, (k, 3); NaN rows where no echo."""
        return beam_points(self.geometry, self.gamma[step : step + 1], self.distance[step : step + 1])[0]
