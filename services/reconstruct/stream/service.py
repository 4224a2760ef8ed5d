"""The live reconstruction: incremental estimates per scan, from any source.

Everything enters through :meth:`ReconstructionService.handle` as (type name,
payload bytes), whether it came from Zenoh or from an MCAP file, so live and
replayed data take the same path and give the same final estimate.

Every estimate is :func:`~lelsonar.reconstruct.estimate.record.reconstruct_scan`'s, the reconstruction of
record (paper §4–5); this module decides when a scan is estimated and with what status:

1. after each sample, E^γ, E0(d_m) and R are updated (the assembly);
2. every ``refit_every`` steps the provisional variant runs: it confirms the corner (R at its maximum
   well above the scan's typical R, enough steps after it), then re-estimates plane b in O(new
   samples), at most once per ``provisional_period`` of scan time (default 0.08 s: ≤ 12.5 provisional
   estimates a second per scan) — behind a short backlog (``handle(..., fits_wait=True)``) it runs at once
   and only its exact fits wait for the backlog; behind a long one (``busy=True``) it waits too
   (:mod:`~lelsonar.reconstruct.stream.provisionals`): the samples come first, a burst costs one refit, not
   one per sample, and the refits are caught up within ``provisional_budget`` when the backlog drains, each
   published at once in O(new samples) and the exact fits they need made after them; live, one due on a
   sample that waited past ``provisional_deadline`` is not published (stale); live with a final pool
   and ``fits_in_pool`` on, the exact fits run in its workers instead, and their plane keeps its estimate until
   the result is back (:meth:`ReconstructionService.collect` takes it);
3. at ``ScanEnd`` (once its samples are in) or after ``scan_timeout`` of silence, the final runs on the
   whole scan from scratch, with the method of record and the compared methods, and is published as
   terminal; a scan completed while a backlog waits is closed once it drains, within the same budget (its
   input reads the whole scan, and the samples come first).

Gaps and when a final may be published:

- the service knows which steps a scan lacks (step indices, ``ScanStart.steps``,
  ``ScanEnd.samples_sent``); with a ``recover`` hook (live) it asks the
  acquirer's log for them: at ``ScanEnd`` with steps missing, after
  ``recovery_after`` of silence without a ScanEnd (the rest and the ScanEnd),
  and at the first sample or the ScanEnd of a scan it never saw start (the
  ScanStart and the earlier steps — a reconstructor that starts late catches up);
- ``recovery_attempts`` requests without progress, from ``recovery_interval``
  apart and doubling, then on while the acquirer's log may still answer
  (:class:`~lelsonar.reconstruct.stream.recovery.RecoveryPolicy`; any new step
  starts the budget again);
- ``FINAL`` only when every step the ScanEnd counts is in; otherwise, once
  recovery is exhausted, ``INCOMPLETE`` with ``missing_steps``; a scan whose
  ScanEnd never came is ``FINAL_TIMEOUT``, also with its ``missing_steps``;
- every terminal estimate carries the scan's exact ``accounting``.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable
from dataclasses import replace

import numpy as np

from lelsonar import codec
from lelsonar.errors import InternalError
from lelsonar.reconstruct.estimate import wire
from lelsonar.reconstruct.estimate.incremental import IncrementalPlane, exact_fit
from lelsonar.reconstruct.estimate.record import provisional_method, reconstruct_scan
from lelsonar.reconstruct.stream.assembly import ScanAssembly
from lelsonar.reconstruct.stream.config import ReconstructConfig, ServiceStats
from lelsonar.reconstruct.stream.final_jobs import FinalJob
from lelsonar.reconstruct.stream.final_pool import FinalPool
from lelsonar.reconstruct.stream.ingest import Accepted, Ingest, Rejected, ScanKey
from lelsonar.reconstruct.stream.log_requests import LogRequests
from lelsonar.reconstruct.stream.outputs import MAX_REVISIONS, Observer, ServiceOutputs
from lelsonar.reconstruct.stream.partial import Partial, RecoveryState
from lelsonar.reconstruct.stream.provisionals import ProvisionalSchedule
from lelsonar.reconstruct.stream.reasons import ranges_text
from lelsonar.reconstruct.stream.recovery import RecoveryRequest
from lelsonar.reconstruct.stream.scan_input import scan_input

__all__ = ["MAX_REVISIONS", "Observer", "ReconstructionService"]


class ReconstructionService(ServiceOutputs):
    """Turns a stream of contract payloads into Reconstruction messages."""

    def __init__(
        self,
        config: ReconstructConfig = ReconstructConfig(),
        *,
        publish: Callable[[codec.Reconstruction], None] | None = None,
        observer: Observer | None = None,
        clock: Callable[[], float] = time.monotonic,
        recover: Callable[[RecoveryRequest], bool] | None = None,
    ) -> None:
        self.config = config
        self.ingest = Ingest(limits=config.limits, max_scans=config.max_scans, max_pending=config.max_pending)
        self._publish = publish
        self._observer = observer
        self._clock = clock
        self.stats = ServiceStats()
        self._requests = LogRequests(config, self.stats, self._event)
        self._requests.recover = recover
        self._partials: dict[ScanKey, Partial] = {}
        # Scans whose provisional refit waited for a backlog (tick() catches up on them).
        self._schedule = ProvisionalSchedule(config, self.stats, clock)
        #: How finals are reconstructed; provisional estimates are the cheaper variant of the same.
        self._options = config.record_options()
        self._provisional_options = replace(self._options, provisional=True)
        #: The method of the provisional refits (:func:`provisional_method`).
        self.provisional_method = provisional_method(config.method)
        #: The newest estimate per scanner (what a `get` on the planes key returns).
        self.latest: dict[str, codec.Reconstruction] = {}
        self._latest_rank: dict[str, int] = {}  # the rank (order of making) of each scanner's latest
        self._ranks = itertools.count()
        #: Final estimates, per scan, in the order they were made.
        self.finals: dict[ScanKey, codec.Reconstruction] = {}  # the newest keep_finals
        #: Scans re-opened after a FINAL_TIMEOUT or INCOMPLETE verdict, and the revision their next final takes.
        self._reopened: dict[ScanKey, int] = {}
        #: Where finals are estimated: None here; a source lends its worker pool (:meth:`use_pool`).
        self._pool: FinalPool | None = None
        self._dispatched: dict[int, FinalJob] = {}  # by the pool's ticket
        self._fits_away: dict[int, tuple[ScanKey, IncrementalPlane]] = {}  # provisional exact fits, by ticket
        self._late: set[ScanKey] = set()  # closed scans whose final is on its way and that got steps meanwhile
        self._completed: list[codec.Reconstruction] = []  # finals made since handle() or tick() last returned
        #: Scans closed complete whose final waits for a backlog to drain (its input reads the whole scan), with
        #: their rank, taken when they were closed.
        self._closing: dict[ScanKey, tuple[int, ScanAssembly, Partial]] = {}

    @property
    def wall_ns(self) -> Callable[[], int] | None:
        """The wall clock (ns) a live source gives, to tell a provisional estimate due on a sample that waited
        too long (``provisional_deadline``); None: no estimate is stale (a replay's times are the file's)."""
        return self._schedule.wall_ns

    @wall_ns.setter
    def wall_ns(self, clock: Callable[[], int] | None) -> None:
        self._schedule.wall_ns = clock

    # --- input ---------------------------------------------------------------------------
    def handle(
        self,
        type_name: str,
        payload: bytes,
        *,
        busy: bool = False,
        fits_wait: bool | None = None,
        origin: str = "live",
        key_scanner: str | None = None,
    ) -> list[codec.Reconstruction]:
        """Apply one payload; return the estimates it produced (also published).

        ``busy``: a backlog waits, so a provisional refit can wait for it; :meth:`catch_up` and
        :meth:`tick` catch up.
        ``fits_wait`` (default: ``busy``): payloads wait, so a refit runs now without its exact fits
        (milliseconds each), which wait for them: the source says a backlog is short this way, where the
        refit's update (a fraction of a millisecond) holds the samples behind it less than deferring it
        would hold its estimate; a scan completed meanwhile is closed once they are in, as under ``busy``.
        ``origin``: "live" (the stream) or "recovered" (the acquirer's log).
        ``key_scanner``: the scanner id of the key it came on; the payload must claim the same.
        """
        out: list[codec.Reconstruction] = []
        for event in self.ingest.accept(type_name, payload, origin=origin, key_scanner=key_scanner):
            if isinstance(event, Rejected):
                self._event("WARNING", f"rejected input ({event.error}): {event.detail}")
                continue
            out += self._on_accepted(event, busy, busy if fits_wait is None else fits_wait, live=origin == "live")
        now = self._clock()
        if self.ingest.late:
            late, self.ingest.late = self.ingest.late, []
            in_flight = {job.scan.key for job in self._dispatched.values()} | self._closing.keys()
            for key in late:
                if key in in_flight:
                    self._late.add(key)  # re-opened, if its verdict asks for it, once its final is made
                else:
                    self._reopen(key)
        fresh, self.ingest.newly_pending = self.ingest.newly_pending, []
        for key in fresh:
            if key in self.ingest.pending and key not in self._requests.pending_since:
                # A scan met in the middle (this reconstructor started late, or its ScanStart was lost):
                # ask the log for the ScanStart and the steps before.
                self._requests.pending_since[key] = (now, RecoveryState())
                self._requests.ask_for_start(key, now, self.ingest.pending.get(key, []))
        return out + self.collect()

    def tick(self, *, busy: bool = False) -> list[codec.Reconstruction]:
        """Catch up on deferred provisional estimates; ask the log for what scans lack; finalise
        scans that are complete, whose recovery is exhausted, or that went silent.

        ``busy``: a backlog waits, so silence means this service is behind, not that the
        scanner stopped: no silence-based request or timeout then; and an ended scan's
        recovery neither retries nor gives up (its replies may be waiting in the backlog).
        """
        now = self._clock()
        cfg = self.config
        out = self._catch_up(busy)
        for key, p in list(self._partials.items()):
            scan = self.ingest.scans.get(key)
            if scan is None:  # forgotten by the bounded scan table (counted in ingest.evicted)
                del self._partials[key]
                continue
            r = p.recovery
            self._requests.note_progress(r, scan.n_received)
            self._requests.settle(scan, p, now)
            if p.ended_at is not None:
                missing = scan.missing_steps()
                if not len(missing):
                    if not self._requests.settling(scan, p, now):  # (conflicting copies wait for the log's, bounded)
                        self._finalise(scan, p, "final")
                elif busy:
                    pass  # the replies to the last request may be in the backlog: no new attempt, no verdict yet
                elif self._requests.can_ask(r, now, key):
                    self._requests.ask(
                        r, RecoveryRequest(*key, steps=tuple(int(s) for s in missing)), now, scan.n_received
                    )
                elif self._requests.exhausted(r, now, key) and now - p.ended_at >= cfg.end_grace:
                    self._finalise(scan, p, "incomplete")
            elif not busy:
                silent = now - p.last_activity
                if silent >= cfg.recovery_after and self._requests.can_ask(r, now, key):
                    self._requests.ask(
                        r,
                        RecoveryRequest(*key, steps=tuple(int(s) for s in scan.missing_steps()), want_end=True),
                        now,
                        scan.n_received,
                    )
                elif silent >= cfg.scan_timeout and self._requests.exhausted(r, now, key):
                    self._event(
                        "WARNING",
                        f"scan {key} silent for {silent:.1f} s without a ScanEnd; finalising it as FINAL_TIMEOUT",
                    )
                    self.stats.timeouts += 1
                    self._finalise(scan, p, "final_timeout")
        for key, (since, r) in list(self._requests.pending_since.items()):
            if key not in self.ingest.pending:
                del self._requests.pending_since[key]  # its ScanStart came (or the bound dropped the samples, counted)
            elif self._requests.can_ask(r, now, key):
                self._requests.ask_for_start(key, now, self.ingest.pending.get(key, []))
            elif not busy and now - since >= cfg.scan_timeout and self._requests.exhausted(r, now, key):
                # Samples whose ScanStart never came are dropped, and counted, after the same timeout.
                del self._requests.pending_since[key]
                for rej in self.ingest.drop_pending(key):
                    self._event("WARNING", f"rejected input ({rej.error}): {rej.detail}")
        return out + self.collect()

    def catch_up(self) -> list[codec.Reconstruction]:
        """Only the provisional refits that waited for a backlog that has drained, within
        ``provisional_budget``: no walk over every open scan, which :meth:`tick` makes, so a source may call
        this after every payload and :meth:`tick` less often."""
        return self._catch_up(False) + self.collect()

    def _catch_up(self, busy: bool) -> list[codec.Reconstruction]:
        """Close the scans whose final waited for a backlog, then run the deferred provisional refits, oldest
        estimate first, for at most ``provisional_budget`` in all.

        Those left wait for the next call; under a backlog (``busy``) a refit deferred for over twice
        ``max_provisional_delay`` is shed and counted instead: its scan's next refit covers its samples
        (:class:`~lelsonar.reconstruct.stream.provisionals.ProvisionalSchedule`).  A final is never shed.
        """
        start = self._clock()
        for _, scan, p in list(self._closing.values()):
            if self._clock() - start >= self.config.provisional_budget or self._pool_full():
                break  # (a full pool would make the final here, on the samples' thread: it waits for room)
            self._finalise(scan, p, "final")
        return self._schedule.catch_up(
            self._partials, self.ingest.scans, busy, self._provisional, start, run_fits=self._due_fits
        )

    def _fits_elsewhere(self) -> bool:
        """Whether provisional exact fits run in the pool's workers (``fits_in_pool``: live, with a pool)."""
        pool = self._pool
        return self.config.fits_in_pool and pool is not None and pool.workers > 0 and self.wall_ns is not None

    def _send_fits(self, scan: ScanAssembly, p: Partial) -> None:
        """Hand the scan's exact fits due to the pool while it has room; those left wait for :meth:`catch_up`."""
        pool = self._pool
        if pool is not None and self._fits_elsewhere() and not self._pool_full():
            for inc, job in p.take_fits():
                self._fits_away[pool.submit(exact_fit, job)] = (scan.key, inc)
        if p.fits_wanted:
            self._schedule.fits_later(scan.key)

    def _due_fits(self, scan: ScanAssembly, p: Partial) -> list[codec.Reconstruction]:
        """The exact fits that waited for a backlog: to the pool (live, with one), else made here, with the
        estimate they give."""
        if self._fits_elsewhere():
            self._send_fits(scan, p)
            return []
        return self._provisional(scan, p)

    def _pool_full(self) -> bool:
        """Whether the pool's workers are all taken and its queue full (a final submitted now would run here)."""
        pool = self._pool
        return pool is not None and pool.workers > 0 and pool.unfinished >= pool.capacity

    @property
    def has_deferred(self) -> bool:
        """Whether a provisional refit or a final waits for :meth:`tick` (they waited for a backlog)."""
        return bool(self._schedule or self._closing)

    def finish(self) -> list[codec.Reconstruction]:
        """End of input (a replay reached the end of its file): finalise every open scan now, and wait for
        every final on its way."""
        for _, closed, waited in list(self._closing.values()):
            self._finalise(closed, waited, "final")  # (closed complete while a backlog waited)
        for key, p in list(self._partials.items()):
            scan = self.ingest.scans.get(key)
            if scan is not None:
                if scan.end is None:
                    status = "final_timeout"
                    self._event("WARNING", f"scan {key} has no ScanEnd; finalised as FINAL_TIMEOUT")
                    self.stats.timeouts += 1
                else:
                    status = "final" if scan.complete else "incomplete"
                self._finalise(scan, p, status)
        for key, held in self.ingest.pending.items():
            # No ScanStart, no array geometry or schedule: nothing can be estimated, and saying so is the result.
            self.stats.without_start += 1
            self._event(
                "ERROR",
                f"scan {key}: {len(held)} messages but never its ScanStart (which carries the "
                "array geometry and the schedule); not reconstructed",
            )
        return self.collect(wait=True)

    # --- recovery ------------------------------------------------------------------------
    def still_wanted(self, request: RecoveryRequest) -> bool:
        """Whether a request still matters (its scan has no verdict yet); safe from another thread."""
        return (request.scanner_id, request.scan_id) not in self.ingest.closed

    # --- the incremental estimate ---------------------------------------------------------
    def _on_accepted(self, event: Accepted, busy: bool, fits_wait: bool, *, live: bool) -> list[codec.Reconstruction]:
        scan = event.scan
        p = self._partials.get(scan.key)
        if p is None:  # not setdefault: a Partial built per sample to be thrown away costs more than the lookup
            p = self._partials[scan.key] = Partial(estimated_at=self._clock())
        p.last_activity = self._clock()
        if event.kind == "start":
            if self._observer:
                self._observer.scan_started(scan)
            self._event("INFO", f"scan {scan.key} started: {scan.start.steps} steps", scan.start.start_time_ns)
            if scan.energy_model_problem:
                self._event("WARNING", f"scan {scan.key}: {scan.energy_model_problem}", scan.start.start_time_ns)
            return []
        if event.kind == "end":
            p.ended_at = self._clock()
            end = scan.end
            if end is None:
                raise InternalError(f"scan {scan.key}: an end event without its ScanEnd")
            self._event(
                "INFO",
                f"scan {scan.key} ended ({'complete' if end.status == 1 else 'aborted'}"
                f"{': ' + end.reason if end.reason else ''}), {end.samples_sent} samples",
                end.end_time_ns,
            )
            if scan.complete and not self._requests.settling(scan, p, p.ended_at):  # (just set: a float)
                self._close(scan, p, fits_wait)
                return []
            missing = scan.missing_steps()
            # Live, a gap at ScanEnd is news.  In a file, another writer's log times may put the ScanEnd
            # before samples that follow it: what is still missing at the end is said by the terminal estimate.
            self._event(
                "WARNING" if self.recover is not None else "INFO",
                f"scan {scan.key} ended with {len(missing)} of {end.samples_sent} steps "
                f"missing so far: {ranges_text(missing)}",
                end.end_time_ns,
            )
            if self._requests.can_ask(p.recovery, p.ended_at, scan.key):
                self._requests.ask(
                    p.recovery,
                    RecoveryRequest(*scan.key, steps=tuple(int(s) for s in missing)),
                    p.ended_at,
                    scan.n_received,
                )
            return []
        step = event.step
        if live and step is not None:
            self._schedule.arrived(scan, step, p)
        if self._observer and scan.latest is not None and scan.latest.step == step:
            self._observer.step(
                scan,
                scan.latest,
                float(scan.step_energy[step]),
                float(scan.expected_energy[step]),
                float(scan.ratio[step]),
            )
        if p.ended_at is not None and scan.complete and not self._requests.settling(scan, p, self._clock()):
            self._close(scan, p, fits_wait)
            return []
        if self._schedule.defer(scan.key, p, busy):
            return []  # tick() catches up; the backlog's later samples will be in the next refit
        if not fits_wait and not self._fits_elsewhere():
            return self._provisional(scan, p)
        out = self._provisional(scan, p, fits_wait=True)
        if p.fits_wanted:
            self._send_fits(scan, p)  # to the pool, or made once the payloads waiting are in
        return out

    def _provisional(self, scan: ScanAssembly, p: Partial, *, fits_wait: bool = False) -> list[codec.Reconstruction]:
        """The provisional estimate of record, every ``refit_every`` steps (:func:`reconstruct_scan`), and the
        exact fits that waited (``fits_wait``: they wait on, and the estimate keeps the planes it has)."""
        if not self.config.provisional or scan.key in self._reopened:
            return []  # (a re-opened scan already had its verdict: only its new final is published)
        fits = not fits_wait and p.fits_wanted  # a fit that waited runs whatever the refit's gates
        if scan.n_received - p.steps_at_fit < self.config.refit_every and not fits:
            return []  # cheap: no array work per sample between refits, nor between looks for the corner
        had_corner = p.critical is not None
        if (
            had_corner
            and not fits
            and 0 < scan.newest_ns - p.provisional_ns < self._provisional_options.provisional_period * 1e9
        ):
            return []  # within the per-scan rate limit: no estimate, and no input built to learn that
        stale = self._schedule.stale(scan, p)
        if stale and not fits:
            # Counted once a refit_every steps, as the estimates it stands for (before its corner, a scan has
            # none to give); the next refit on a fresh sample covers these steps.
            if had_corner and scan.n_received - max(p.steps_at_fit, p.stale_at) >= self.config.refit_every:
                self.stats.provisionals_stale += 1
                p.stale_at = scan.n_received
            return []
        rate_mark = p.provisional_ns
        est = reconstruct_scan(scan_input(scan, provisional=True), self._provisional_options, p, fits_wait=fits_wait)
        if not had_corner and p.critical is not None:
            self._event(
                "INFO",
                f"scan {scan.key}: critical step {p.critical} confirmed at "
                f"γ = {np.rad2deg(scan.gamma[p.critical]):.1f}°",
                int(scan.time_ns[p.critical]),
            )
        if est is None:
            return []
        if stale:  # its exact fits are made (the next estimate has them); its estimate would be late
            self.stats.provisionals_stale += 1
            p.provisional_ns = rate_mark  # not published: the next fresh sample's estimate is not held back
            return []
        p.estimated_at = self._clock()
        msg = wire.estimate_message(est, scan.start.scanner_id, scan.start.scan_id, plane_messages=p.plane_messages)
        if self._observer:
            self._observer.estimate(scan, msg, None, p)
        return [self._emit(msg)]
