"""A whole scan's input to the reconstruction from its waveforms, as the reconstruction service computes it.

A simulated scan (or any scan held as arrays with its waveforms) gives its angles and ranges; the service
computes each waveform's energy (eq. 10) and the first echo's own amplitude from each ``Sample``, and so does
:func:`scan_input_of_waveforms`, so that a scan reconstructed offline is reconstructed as the service would.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from lelsonar.geometry import ArrayGeometry
from lelsonar.reconstruct.estimate.record import ScanInput
from lelsonar.signal.energy import EnergyModel, echo_amplitude, waveform_energy


class WaveformScan(Protocol):
    """What :func:`scan_input_of_waveforms` reads of a scan (a ``SimulatedScan`` or a ``WorldScan``)."""

    @property
    def gamma_measured(self) -> np.ndarray: ...  # (n,) rad

    @property
    def distance(self) -> np.ndarray: ...  # (n, k) m, NaN = no echo

    @property
    def waveforms(self) -> np.ndarray: ...  # (n, k, samples) V

    @property
    def sample_rate(self) -> float: ...  # Hz

    @property
    def t0(self) -> float: ...  # s, the time of each waveform's first sample

    @property
    def tof(self) -> np.ndarray: ...  # (n, k) s, NaN = no echo

    @property
    def geometry(self) -> ArrayGeometry: ...


def scan_input_of_waveforms(scan: WaveformScan, energy_model: EnergyModel) -> ScanInput:
    """The scan's :class:`~lelsonar.reconstruct.estimate.record.ScanInput`: its angles and ranges, each
    waveform's energy (eq. 10) and the first echoes' own amplitudes
    (:func:`~lelsonar.signal.energy.echo_amplitude`), under ``energy_model`` (eq. 12)."""
    energy = waveform_energy(scan.waveforms, scan.sample_rate)
    amplitude = echo_amplitude(scan.waveforms, scan.sample_rate, scan.t0, scan.tof)
    return ScanInput.of_scan(
        scan.gamma_measured, scan.distance, energy, scan.geometry, energy_model, echo_amplitude=amplitude
    )
