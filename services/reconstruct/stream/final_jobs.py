"""A scan's final on its way: what its message needs beside the estimate, fixed when the scan is closed.

The service closes a scan and hands its input to the estimation (on its own thread, or in a
:class:`~lelsonar.reconstruct.stream.final_pool.FinalPool`); :func:`final_message` then builds the terminal
message from the estimate and the :class:`FinalJob`, whenever and wherever the estimate was made: the same
message either way.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lelsonar import codec
from lelsonar.reconstruct.estimate import wire
from lelsonar.reconstruct.estimate.quality import DEGRADED
from lelsonar.reconstruct.estimate.record import ScanEstimate, with_findings
from lelsonar.reconstruct.stream.assembly import ScanAssembly
from lelsonar.reconstruct.stream.partial import Partial
from lelsonar.reconstruct.stream.reasons import conflict_reason, partial_sweep_reason, ranges_text
from lelsonar.reconstruct.stream.scan_input import ClosedScan
from lelsonar.v1.reconstruction_pb2 import ScanAccounting
from lelsonar.v1.scan_pb2 import SCAN_STATUS_ABORTED

__all__ = ["FinalJob", "close_final", "final_message", "accounting_event"]


@dataclass(frozen=True, eq=False)
class FinalJob:
    """What a final's message needs beside its estimate."""

    scan: ScanAssembly  # (for the observer: the ingest has let the closed scan go)
    partial: Partial
    status: str
    missing: np.ndarray
    accounting: ScanAccounting
    #: What the stream knows of the scan beyond its data (a sweep stopped early, copies that conflicted).
    findings: tuple[tuple[str, str], ...]
    revision: int
    #: Its place among the service's estimates, taken when the scan was closed: an estimate of the scanner's
    #: next scan published while this one was being made stays the scanner's latest.
    rank: int


def close_final(
    scan: ScanAssembly,
    p: Partial,
    status: str,
    *,
    live: bool,
    revision: int,
    rank: int,
) -> tuple[FinalJob, ClosedScan]:
    """The final's job and the closed scan its estimate reads (through
    :func:`~lelsonar.reconstruct.stream.scan_input.scan_input`, where the estimate is made), for a scan being
    closed.

    ``status`` is the verdict asked for; it becomes "incomplete" with steps missing and "aborted" for a
    sweep stopped early (never FINAL).  ``live``: the acquirer's log could settle conflicting copies.
    """
    missing = scan.missing_steps()
    if status == "final" and len(missing):
        status = "incomplete"  # never FINAL with steps missing
    end = scan.end
    aborted = end is not None and end.status == SCAN_STATUS_ABORTED
    if aborted and status in ("final", "incomplete"):
        status = "aborted"  # a sweep stopped early is never FINAL (its missing_steps still listed)
    acc = wire.accounting_message(
        published=int(end.samples_sent) if end is not None else 0,
        received_live=scan.n_received - scan.n_recovered,
        recovered=scan.n_recovered,
        duplicates=scan.duplicates,
        rejected=dict(scan.rejected),
        missing=len(missing),
        conflicts=scan.conflicts,
    )
    findings: tuple[tuple[str, str], ...] = ()
    if end is not None and aborted:
        findings += ((DEGRADED, partial_sweep_reason(end, int(scan.start.steps))),)
    if scan.conflicts:
        findings += ((DEGRADED, conflict_reason(scan, live)),)
    return FinalJob(scan, p, status, missing, acc, findings, revision, rank), ClosedScan(scan)


def final_message(job: FinalJob, estimate: ScanEstimate) -> tuple[codec.Reconstruction, ScanEstimate]:
    """The terminal message of ``job`` and its estimate with the stream's findings on every plane."""
    est = with_findings(estimate, job.findings)
    scan = job.scan
    msg = wire.estimate_message(
        est,
        scan.start.scanner_id,
        scan.start.scan_id,
        status=job.status,
        missing_steps=job.missing,
        accounting=job.accounting,
    )
    if scan.end is not None and job.status == "aborted":
        msg.aborted_reason = scan.end.reason or "aborted"
    msg.revision = job.revision
    return msg, est


def accounting_event(job: FinalJob, live: bool) -> str:
    """The accounting line of a final, with its missing steps and, for an incomplete scan, what to do."""
    missing = job.missing
    hint = ""
    if missing.size and job.status == "incomplete":
        hint = (
            "; the acquirer's log did not supply them (is acquire serving it? raise acquire "
            "--serve-log-for or reconstruct --recovery-attempts)"
            if live
            else "; nothing could recover them here (a replay, or live with --recovery-attempts 0)"
        )
    return f"scan {job.scan.key} accounting: {wire.accounting_text(job.accounting)}" + (
        f"; missing steps {ranges_text(missing)}{hint}" if missing.size else ""
    )
