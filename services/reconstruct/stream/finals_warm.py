"""Loads the kernels a final uses in the final pool's fork server: imported there, and only there.

A fresh process loads each compiled kernel from the disk cache on its first call, which costs far more
than the final itself.  The fork server imports this module before it forks any worker
(:data:`~lelsonar.reconstruct.stream.final_worker.PRELOAD`), and importing it estimates one small simulated
scan the way a final does, and runs the range repair's kernels on its waveforms' windows: every worker
is forked with the kernels loaded.  A failure here only costs
the workers that loading (logged); it never stops the server.
"""

from __future__ import annotations

import logging

import numpy as np

from lelsonar.reconstruct.estimate.record import reconstruct_scan
from lelsonar.reconstruct.estimate.waveform_input import scan_input_of_waveforms
from lelsonar.reconstruct.stream.config import ReconstructConfig
from lelsonar.signal.echo_timing import FLOOR_TIME, TIMING_WINDOW, echo_onsets, range_walk, typical_edges
from lelsonar.signal.energy import echo_amplitude, echoes_over_noise, noise_level
from lelsonar.sim import default_energy_model, preset, simulate_scan

_log = logging.getLogger(__name__)


def load_kernels() -> None:
    """One final estimate (the default method of record and its compared methods) of a simulated scan."""
    scan = simulate_scan(preset("paper-test1"), seed=0)
    reconstruct_scan(scan_input_of_waveforms(scan, default_energy_model()), ReconstructConfig().record_options())
    # The range repair (a final's first step, :mod:`~lelsonar.reconstruct.stream.range_repair`): its kernels on
    # each reading's float32 window around its time of flight, as the assembly keeps them.
    rate = float(scan.sample_rate)
    width = max(int(round((TIMING_WINDOW[1] - TIMING_WINDOW[0]) * rate)), 1)
    rows, capsules = np.nonzero(np.isfinite(scan.tof))
    first = np.round((scan.tof[rows, capsules] + TIMING_WINDOW[0] - scan.t0) * rate).astype(np.int64)
    inside = (first >= 0) & (first + width <= scan.waveforms.shape[-1])
    rows, capsules, first = rows[inside], capsules[inside], first[inside]
    windows = np.stack([scan.waveforms[r, c, a : a + width] for r, c, a in zip(rows, capsules, first)])
    at = scan.tof[rows, capsules] - (scan.t0 + first / rate)
    onset, peak, edge = echo_onsets(windows, rate, at)
    typical = typical_edges(edge)
    # The repair reads the edges as a (steps, capsules) view of its (steps, capsules, 3) timings: a strided array.
    typical_edges(np.moveaxis(np.stack([onset, peak, edge], axis=-1)[:, None], -1, 0)[2])
    range_walk(np.where(typical, -0.5 * 343.0 * onset, np.nan), peak, halves=True)
    _, _, sigma = echoes_over_noise(windows, rate, at, 2.0 * at, FLOOR_TIME)
    echo_onsets(windows, rate, at, level=noise_level(sigma, 2.0 * at, rate))
    echo_amplitude(windows, rate, 0.0, at)


try:
    load_kernels()
except Exception:  # noqa: BLE001 - the workers then load the kernels themselves: slower, never wrong
    _log.exception("the final pool's fork server could not load the kernels ahead")
