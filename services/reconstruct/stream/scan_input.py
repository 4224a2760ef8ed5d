"""A scan being assembled, as the reconstruction of record reads it
(:class:`~lelsonar.reconstruct.estimate.record.ScanInput`).

This is where the writer's ranges are repaired for a final, and where what only the whole scan shows
about its writer is collected; the estimate itself is
:func:`~lelsonar.reconstruct.estimate.record.reconstruct_scan`'s.
"""

from __future__ import annotations

import numpy as np

from lelsonar.reconstruct.estimate.record import ScanInput
from lelsonar.reconstruct.stream.assembly import ScanAssembly

__all__ = ["scan_input"]


def scan_input(scan: ScanAssembly, *, provisional: bool = False) -> ScanInput:
    """The received steps of ``scan`` as a :class:`ScanInput`.

    A final's ranges are repaired: re-timed where the writer's ranges walk with the echoes' amplitude
    (:meth:`ScanAssembly.walk_free`), and where the board fired on noise, those readings' ranges and
    peaks are the echo's after them where one was found (:meth:`ScanAssembly.noise_triggers_recovered`);
    then the board's own readings (its noise triggers left out) go with them for the recovered echoes'
    check, and the writer's problems (:meth:`ScanAssembly.writer_problems`) for the verdict.

    A provisional input is the ranges as received with the stream's ``R`` (what the provisional variant
    reads; O(steps), no waveform pass).
    """
    steps, gamma, distance, ratio = scan.arrays()
    n_schedule = int(scan.start.steps)
    if provisional:
        return ScanInput(
            scan.geometry,
            scan.energy_model,
            steps,
            gamma,
            distance,
            ratio=ratio,
            newest_ns=scan.newest_ns,
            n_schedule=n_schedule,
        )
    distance = scan.walk_free(distance)  # a writer whose ranges walk with the echoes' amplitude: re-timed
    board_distance, board_amplitude = distance, scan.echo_amplitude[steps]
    distance, amplitude = scan.noise_triggers_recovered(board_distance, board_amplitude)
    own = None
    if not np.array_equal(distance, board_distance, equal_nan=True):
        own = np.where(scan.noise_triggers()[0], np.nan, board_distance)
    return ScanInput(
        scan.geometry,
        scan.energy_model,
        steps,
        gamma,
        distance,
        sensor_energy=scan.sensor_energy[steps],
        echo_amplitude=amplitude,
        own_distance=own,
        own_amplitude=board_amplitude if own is not None else None,
        writer_problems=tuple(scan.writer_problems()),
        n_schedule=n_schedule,
    )
