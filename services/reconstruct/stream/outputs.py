"""Where the live service's estimates go: the finals (made here or in a final pool), the newest estimate per
scanner, the observer, and the re-opening of a scan finalised without steps that came later.

:class:`ServiceOutputs` declares the state :class:`~lelsonar.reconstruct.stream.service.ReconstructionService`
keeps for this (placed by its constructor) and the methods that close, finalise and publish; the service decides
when (its input, its tick).
"""

from __future__ import annotations

import itertools
import logging
from collections.abc import Callable
from typing import Protocol

from lelsonar import codec
from lelsonar.reconstruct.estimate import wire
from lelsonar.reconstruct.estimate.incremental import IncrementalPlane
from lelsonar.reconstruct.estimate.record import RecordOptions, reconstruct_scan
from lelsonar.reconstruct.estimate.results import FailureReason, FitFailure, PlaneResult, ScanReconstruction
from lelsonar.reconstruct.stream.assembly import ScanAssembly, StepView
from lelsonar.reconstruct.stream.config import ReconstructConfig, ServiceStats
from lelsonar.reconstruct.stream.final_jobs import FinalJob, accounting_event, close_final, final_message
from lelsonar.reconstruct.stream.final_pool import FinalPool
from lelsonar.reconstruct.stream.final_worker import Done
from lelsonar.reconstruct.stream.finals import estimate_final, received
from lelsonar.reconstruct.stream.ingest import Ingest, ScanKey
from lelsonar.reconstruct.stream.log_requests import LogRequests
from lelsonar.reconstruct.stream.partial import Partial
from lelsonar.reconstruct.stream.provisionals import ProvisionalSchedule
from lelsonar.reconstruct.stream.recovery import RecoveryPolicy, RecoveryRequest
from lelsonar.reconstruct.stream.scan_input import scan_input

__all__ = ["MAX_REVISIONS", "Observer", "ServiceOutputs"]

_log = logging.getLogger(__name__)

#: Times a scan may be re-finalised after a FINAL_TIMEOUT or INCOMPLETE verdict (late steps from its log).
MAX_REVISIONS = 3


class Observer(Protocol):
    """Receives what the service sees and decides (e.g. the Rerun logger).

    ``estimate`` gets the message, and for a terminal one each method's reconstruction with its planes
    as published (:meth:`~lelsonar.reconstruct.estimate.record.ScanEstimate.as_published`; None for a
    provisional one, whose planes and points are the ``partial``'s).
    """

    def scan_started(self, scan: ScanAssembly) -> None: ...

    def step(self, scan: ScanAssembly, view: StepView, energy: float, expected: float, ratio: float) -> None: ...

    def estimate(
        self,
        scan: ScanAssembly,
        message: codec.Reconstruction,
        results: dict[str, ScanReconstruction] | None,
        partial: Partial,
    ) -> None: ...

    def event(self, level: str, text: str, time_ns: int | None = None) -> None: ...


class ServiceOutputs:
    """The finals, the latest estimates and the observer of a
    :class:`~lelsonar.reconstruct.stream.service.ReconstructionService` (which fills this state)."""

    config: ReconstructConfig
    ingest: Ingest
    stats: ServiceStats
    _publish: Callable[[codec.Reconstruction], None] | None
    _observer: Observer | None
    _requests: LogRequests
    _partials: dict[ScanKey, Partial]
    _options: RecordOptions
    #: The newest estimate per scanner (what a `get` on the planes key returns).
    latest: dict[str, codec.Reconstruction]
    _latest_rank: dict[str, int]  # the rank (order of making) of each scanner's latest
    _ranks: itertools.count
    #: Final estimates, per scan, in the order they were made (the newest keep_finals).
    finals: dict[ScanKey, codec.Reconstruction]
    #: Scans re-opened after a FINAL_TIMEOUT or INCOMPLETE verdict, and the revision their next final takes.
    _reopened: dict[ScanKey, int]
    #: Where finals are estimated: None here; a source lends its worker pool (:meth:`use_pool`).
    _pool: FinalPool | None
    _dispatched: dict[int, FinalJob]  # by the pool's ticket
    #: Provisional exact fits in the pool, by its ticket: their scan and plane.
    _fits_away: dict[int, tuple[ScanKey, IncrementalPlane]]
    _schedule: ProvisionalSchedule
    _late: set[ScanKey]  # closed scans whose final is on its way and that got steps meanwhile
    _completed: list[codec.Reconstruction]  # finals made since handle() or tick() last returned
    #: Scans closed complete whose final waits for a backlog to drain (its input reads the whole scan), with
    #: their rank, taken when they were closed.
    _closing: dict[ScanKey, tuple[int, ScanAssembly, Partial]]

    @property
    def recover(self) -> Callable[[RecoveryRequest], bool] | None:
        """Asks the acquirer's log for what a scan lacks; returns False when the request was refused."""
        return self._requests.recover

    @recover.setter
    def recover(self, recover: Callable[[RecoveryRequest], bool] | None) -> None:
        self._requests.recover = recover

    @property
    def recovery_policy(self) -> RecoveryPolicy:
        """When to ask again and when to give up (a live source lets it ask on while the log may answer)."""
        return self._requests.policy

    @recovery_policy.setter
    def recovery_policy(self, policy: RecoveryPolicy) -> None:
        self._requests.policy = policy

    # --- where finals are estimated -------------------------------------------------------
    def use_pool(self, pool: FinalPool | None, *, drain: bool = True) -> list[codec.Reconstruction]:
        """Estimate the finals in ``pool``'s workers from now on (None: on the caller's thread).

        The finals on their way in the pool used so far are waited for and returned (published, as every
        final is) with ``drain``; without it (the source is failing) they are dropped, logged and counted.
        """
        out = self.collect(wait=True) if drain else []
        if self._dispatched:
            dropped = sorted(job.scan.key for job in self._dispatched.values())
            self.stats.finals_dropped += len(dropped)
            self._event("ERROR", f"{len(dropped)} finals dropped unmade as their source stopped: scans {dropped}")
            self._dispatched.clear()
            self._late.clear()
        for key, inc in self._fits_away.values():  # (due again: made here, or in the next pool)
            inc.fit_lost()
            self._schedule.fits_later(key)
        self._fits_away.clear()
        if self._pool is not None and self._pool is not pool:
            self.stats.add_pool(self._pool.stats)
        self._pool = pool
        return out

    @property
    def finals_on_their_way(self) -> int:
        """Finals dispatched to the pool and not yet handed back."""
        return len(self._dispatched)

    def collect(self, *, wait: bool = False) -> list[codec.Reconstruction]:
        """The finals made since the last call, in the order their scans were closed; ``wait`` for those on
        their way in the pool.  (:meth:`handle`, :meth:`tick` and :meth:`finish` return them too.)"""
        if self._pool is not None and (self._dispatched or self._fits_away):
            for done in self._pool.drain() if wait else self._pool.ready():
                away = self._fits_away.pop(done.ticket, None)
                if away is not None:
                    self._fitted(*away, done)
                else:
                    self._complete(self._dispatched.pop(done.ticket), done)
        out, self._completed = self._completed, []
        return out

    def stats_dict(self) -> dict:
        """Everything counted so far, for the exit line and ``--json``."""
        return self.stats.as_dict(self.ingest, self._pool.stats if self._pool is not None else None)

    # --- re-opening ----------------------------------------------------------------------
    def _reopen(self, key: ScanKey) -> None:
        """Steps came for a scan finalised without them: ask the acquirer's log for the whole scan, to publish
        it again complete, with a higher revision (at most ``MAX_REVISIONS``)."""
        old = self.finals.get(key)
        if (
            old is None
            or self.recover is None
            or key in self._reopened
            or wire.status_name(old) not in ("final_timeout", "incomplete")
            or old.revision >= MAX_REVISIONS
        ):
            return
        self._reopened[key] = old.revision + 1
        while len(self._reopened) > self.config.max_scans:
            self._reopened.pop(next(iter(self._reopened)))
            self.stats.evicted["re-opened scan forgotten (max_scans)"] += 1
        self.ingest.closed.pop(key, None)
        steps = int(old.samples_used) + len(old.missing_steps)  # the schedule
        self._event(
            "WARNING",
            f"scan {key}: steps came after its {wire.status_name(old).replace('_', ' ')} verdict; asking the "
            f"acquirer's log for the whole scan, to publish revision {old.revision + 1}",
        )
        self._requests.request(RecoveryRequest(*key, steps=tuple(range(steps)), want_start=True, want_end=True))

    # --- finals and publishing ------------------------------------------------------------
    def _close(self, scan: ScanAssembly, p: Partial, busy: bool) -> None:
        """A complete scan's final: made now, or while a backlog waits (``busy``) once it drains: making its
        input reads the whole scan, and the samples come first.  Its rank is taken now."""
        if not busy:
            self._finalise(scan, p, "final")
            return
        # Closed now, as a final made now closes it: a straggler is rejected as late.
        self._partials.pop(scan.key, None)
        self.ingest.close(scan.key)
        self._closing[scan.key] = (next(self._ranks), scan, p)
        while len(self._closing) > self.config.max_scans:
            self._finalise(*next(iter(self._closing.values()))[1:], "final")  # bounded: the oldest is made now

    def _finalise(self, scan: ScanAssembly, p: Partial, status: str) -> None:
        """Close the scan and estimate its final: here, or in the pool (:meth:`collect` hands it back)."""
        rank = self._closing.pop(scan.key, (None,))[0]
        job, closed = close_final(
            scan,
            p,
            status,
            live=self.recover is not None,
            revision=self._reopened.pop(scan.key, 0),
            rank=next(self._ranks) if rank is None else rank,
        )
        # The scan is done: forget its state; a straggler is then rejected as late.
        self._partials.pop(scan.key, None)
        self.ingest.close(scan.key)
        if self._pool is None:
            self._complete(job, Done(0, reconstruct_scan(scan_input(closed), self._options)))
        else:
            # The whole final, its range repair included, in the pool; the points behind each plane travel
            # back only for an observer, which draws them.
            self._dispatched[self._pool.submit(estimate_final, closed, self._options, self._observer is not None)] = job

    def _fitted(self, key: ScanKey, inc: IncrementalPlane, done: Done) -> None:
        """A provisional exact fit came back from the pool: its plane's estimate from now on (dropped if its
        scan was closed meanwhile: the final does not use it)."""
        fit: PlaneResult
        if done.error is not None:
            self.stats.fit_errors += 1
            self._event(
                "ERROR",
                f"scan {key}: the provisional exact fit of plane {inc.label} failed in a worker "
                f"({type(done.error).__name__}: {done.error})\n{done.trace}",
            )
            fit = FitFailure(
                FailureReason.DEGENERATE_GEOMETRY,
                f"provisional: its exact fit failed ({type(done.error).__name__}: {done.error})",
                inc.label,
                inc.n,
            )
        else:
            self.stats.fits_from_pool += 1
            fit = done.value
        p = self._partials.get(key)
        if p is not None:
            p.fitted(inc, fit)

    def _complete(self, job: FinalJob, done: Done) -> None:
        """Publish a final whose estimate is made (or say why it could not be)."""
        scan, status = job.scan, job.status
        if done.error is not None:
            self.stats.final_errors += 1
            self._event(
                "ERROR",
                f"scan {scan.key}: its final estimate failed ({type(done.error).__name__}: {done.error}); "
                f"nothing published for it\n{done.trace}",
            )
            return
        msg, est = final_message(job, received(done.value))
        # What the writer left unset: a warning (and where no plane came, a failure of the estimate).
        for note in est.notes:
            self._event("WARNING", f"scan {scan.key}: {note}")
        self.finals[scan.key] = msg
        while len(self.finals) > self.config.keep_finals:
            self.finals.pop(next(iter(self.finals)))
            self.stats.evicted["final kept for lookup forgotten (keep_finals)"] += 1
        self.stats.add_final(job.accounting, status)
        summary = "; ".join(
            f"{pl.method} {pl.label}: n=({pl.normal.x:+.3f},{pl.normal.y:+.3f},{pl.normal.z:+.3f}) "
            f"h={pl.offset * 100:.1f} cm"
            for pl in msg.planes
            if pl.method == self.config.method
        )
        self._event(
            "INFO" if not msg.failures else "WARNING",
            f"scan {scan.key} {status.replace('_', ' ')}: {summary or 'no plane'}"
            + (f"; failures: {'; '.join(msg.failures)}" if msg.failures else ""),
        )
        self._event("INFO" if not job.missing.size else "WARNING", accounting_event(job, self.recover is not None))
        if self._observer:
            self._observer.estimate(scan, msg, est.as_published(), job.partial)
        self._emit(msg, job.rank)
        self._completed.append(msg)
        if scan.key in self._late:
            self._late.discard(scan.key)
            self._reopen(scan.key)  # steps came while it was being estimated

    def _emit(self, msg: codec.Reconstruction, rank: int | None = None) -> codec.Reconstruction:
        """Publish ``msg``; it becomes its scanner's latest unless one made after it (``rank``: when it was
        made, by default now) already is: a final made in the pool while the scanner's next scan went on."""
        rank = next(self._ranks) if rank is None else rank
        if rank >= self._latest_rank.get(msg.scanner_id, -1):
            self.latest.pop(msg.scanner_id, None)  # most recently updated last
            self.latest[msg.scanner_id] = msg
            self._latest_rank[msg.scanner_id] = rank
        while len(self.latest) > self.config.max_scanners:
            self._latest_rank.pop(gone := next(iter(self.latest)), None)
            self.latest.pop(gone)
            self.stats.evicted["latest estimate of a scanner forgotten (max_scanners)"] += 1
        self.stats.estimates += 1
        if self._publish is not None:
            self._publish(msg)
        return msg

    def _event(self, level: str, text: str, time_ns: int | None = None) -> None:
        getattr(_log, level.lower(), _log.info)(text)
        if self._observer:
            self._observer.event(level, text, time_ns)
