"""Loads the kernels a final uses in the final pool's fork server: imported there, and only there.

A fresh process loads each compiled kernel from the disk cache on its first call, which costs far more
than the final itself.  The fork server imports this module before it forks any worker
(:data:`~lelsonar.reconstruct.stream.finals.PRELOAD`), and importing it estimates one small simulated
scan the way a final does: every worker is forked with the kernels loaded.  A failure here only costs
the workers that loading (logged); it never stops the server.
"""

from __future__ import annotations

import logging

from lelsonar.reconstruct.estimate.record import ScanInput, reconstruct_scan
from lelsonar.reconstruct.stream.config import ReconstructConfig
from lelsonar.signal.energy import echo_amplitude, waveform_energy
from lelsonar.sim import default_energy_model, preset, simulate_scan

_log = logging.getLogger(__name__)


def load_kernels() -> None:
    """One final estimate (the default method of record and its compared methods) of a simulated scan."""
    scan = simulate_scan(preset("paper-test1"), seed=0)
    energy = waveform_energy(scan.waveforms, scan.sample_rate)
    amplitude = echo_amplitude(scan.waveforms, scan.sample_rate, scan.t0, scan.tof)
    given = ScanInput.of_scan(
        scan.gamma_measured, scan.distance, energy, scan.geometry, default_energy_model(), echo_amplitude=amplitude
    )
    reconstruct_scan(given, ReconstructConfig().record_options())


try:
    load_kernels()
except Exception:  # noqa: BLE001 - the workers then load the kernels themselves: slower, never wrong
    _log.exception("the final pool's fork server could not load the kernels ahead")
