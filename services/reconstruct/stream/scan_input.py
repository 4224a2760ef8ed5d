"""A scan being assembled, as the reconstruction of record reads it
(:class:`~lelsonar.reconstruct.estimate.record.ScanInput`).

This is where the writer's ranges are repaired for a final, and where what only the whole scan shows
about its writer is collected; the estimate itself is
:func:`~lelsonar.reconstruct.estimate.record.reconstruct_scan`'s.

A closed scan travels to a final worker as a :class:`ClosedScan` (its state without what placing samples
needs), and the worker makes its input there: the range repair is part of the final's cost, off the
stream's thread like the rest of it.
"""

from __future__ import annotations

import numpy as np

from lelsonar.errors import InternalError
from lelsonar.reconstruct.estimate.record import ScanInput
from lelsonar.reconstruct.stream.assembly import ScanAssembly
from lelsonar.reconstruct.stream.scan_state import ScanState
from lelsonar.reconstruct.stream.writer_checks import WriterChecks

__all__ = ["ClosedScan", "scan_input"]

#: What a closed scan's checks read (:class:`ScanState`'s declared state) but the blocks the arrays are planes
#: of, which only placing a sample writes through.
_STATE = tuple(name for name in ScanState.__annotations__ if name not in ("_per_capsule", "_per_step", "_rows"))


class ClosedScan(WriterChecks):
    """A closed scan as its final reads it: the arrays, kept waveform windows and caches of a
    :class:`~lelsonar.reconstruct.stream.assembly.ScanAssembly`, without its sample buffers and the latest
    step's payload (a small, picklable object for a final worker).

    The arrays are the assembly's own, not copies: a closed scan is placed no more samples (a step that comes
    late re-opens it as a new assembly).  Its checks (the range repair, the writer checks) give what the
    assembly's would, bit for bit: the same methods on the same arrays.
    """

    def __init__(self, scan: ScanAssembly) -> None:
        for name in _STATE:
            setattr(self, name, getattr(scan, name))

    def __getstate__(self) -> dict:
        return {name: getattr(self, name) for name in _STATE}

    def __setstate__(self, state: dict) -> None:
        for name, value in state.items():
            setattr(self, name, value)


def scan_input(scan: ScanAssembly | ClosedScan, *, provisional: bool = False) -> ScanInput:
    """The received steps of ``scan`` (being assembled, or a :class:`ClosedScan`) as a :class:`ScanInput`.

    A final's ranges are repaired: re-timed where the writer's ranges walk with the echoes' amplitude
    (:meth:`ScanAssembly.walk_free`), and where the board fired on noise, those readings' ranges and
    peaks are the echo's after them where one was found (:meth:`ScanAssembly.noise_triggers_recovered`);
    then the board's own readings (its noise triggers left out) go with them for the recovered echoes'
    check, and the writer's problems (:meth:`ScanAssembly.writer_problems`) for the verdict.

    A provisional input is the ranges as received with the stream's ``R`` (what the provisional variant
    reads; O(steps), no waveform pass), of a scan being assembled.
    """
    steps, gamma, distance, ratio = scan.arrays()
    n_schedule = int(scan.start.steps)
    if provisional:
        if not isinstance(scan, ScanAssembly):
            raise InternalError("a provisional input is made of a scan being assembled, not a closed one")
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
