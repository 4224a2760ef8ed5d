"""What a final is: the reconstruction of record of a closed scan, as a worker runs it and sends it back.

A final runs in a :class:`~lelsonar.reconstruct.stream.final_pool.FinalPool` worker, or in the caller where
no worker is there: :func:`estimate_final` is the job, :func:`received` restores its result on the caller's
side, and :func:`auto_workers` says how many workers the finals get by default.
"""

from __future__ import annotations

import os
from dataclasses import replace
from types import MappingProxyType

from lelsonar.reconstruct.estimate.record import RecordOptions, ScanEstimate, reconstruct_scan
from lelsonar.reconstruct.stream.scan_input import ClosedScan, scan_input

__all__ = ["auto_workers", "estimate_final", "received"]


def auto_workers(cpus: int | None = None) -> int:
    """Workers for finals by default: one per core beyond the caller's, at most two; none on one core.

    Live and in a replay the caller's thread stays busy with the samples, so the finals need cores of their
    own; two workers keep up with a reader that outruns one (a final costs about as much as reading its
    scan), and more would only wait for the reader.
    """
    n = cpus if cpus is not None else (os.cpu_count() or 1)
    return max(0, min(2, n - 1))


def estimate_final(scan: ClosedScan, options: RecordOptions, with_points: bool) -> ScanEstimate:
    """A closed scan's final estimate of record (:func:`reconstruct_scan` of its repaired ranges,
    :func:`~lelsonar.reconstruct.stream.scan_input.scan_input`), ready to be sent back from a worker.

    The whole final runs here, the range repair included: in a worker, none of it holds the stream.
    ``with_points``: keep each method's reconstruction (the points behind each plane, for a viewer);
    without it only what the message is built from comes back.  Pass the result through :func:`received`
    on the caller's side.
    """
    est = reconstruct_scan(scan_input(scan), options)
    # A mapping proxy does not pickle: a plain dict travels, received() makes it read-only again.
    return replace(est, results=dict(est.results) if with_points else {})


def received(estimate: ScanEstimate) -> ScanEstimate:
    """An estimate from :func:`estimate_final` as :func:`reconstruct_scan` returns one (read-only results)."""
    if isinstance(estimate.results, MappingProxyType):
        return estimate
    return replace(estimate, results=MappingProxyType(dict(estimate.results)))
