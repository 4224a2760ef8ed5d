"""What a reconstruction service is told (:class:`ReconstructConfig`) and what it counts (:class:`ServiceStats`)."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

from lelsonar import codec
from lelsonar.errors import ConfigError
from lelsonar.reconstruct.estimate.pipeline import DEFAULT_METHOD, METHODS, FitOptions
from lelsonar.reconstruct.estimate.record import RecordOptions
from lelsonar.reconstruct.stream.final_pool import PoolStats
from lelsonar.reconstruct.stream.ingest import Ingest
from lelsonar.v1.reconstruction_pb2 import ScanAccounting


@dataclass(frozen=True)
class ReconstructConfig:
    """How the service estimates.

    Parameters
    ----------
    method : str
        The estimator of record (a key of ``pipeline.METHODS``).
    compare_methods : tuple of str
        Also run at the end of each scan, published next to ``method``.
    refit_every : int
        Steps between provisional re-estimates of plane b (and, before the corner is confirmed,
        between looks for its peak).
    provisional_period : float
        s of scan time (the samples' ``acquisition_time_ns``): a scan gets at most one provisional
        estimate per period (default 0.08 s: at most 12.5 a second per scan, i.e. every
        ``refit_every`` = 4 steps of a 50 Hz scanner; a faster scanner, or a burst of recovered
        steps, is held to the same rate).  Scan time, not the wall clock, so a replay gives the
        same provisional estimates at any speed.  0 disables it.
    confirm_steps : int
        Steps that must follow the R peak before it is trusted.
    confirm_ratio : float
        The peak must exceed this multiple of the median R so far.
    provisional : bool
        Publish provisional estimates while a scan arrives (off for a batch replay,
        whose finals do not depend on them).
    max_provisional_delay : float
        s; while a backlog waits, every provisional refit waits for it (the samples come first); one whose
        scan has had no estimate for over twice this is shed (``ServiceStats.provisionals_shed``) when
        a tick still finds a backlog, and the scan's next refit covers it.
    provisional_deadline : float
        s a live sample may have waited, beyond the quickest of its scan's samples (the transit and the
        offset of the scanner's clock to this host's), when the provisional estimate it ends is due: an
        older one is stale, and is shed (``ServiceStats.provisionals_stale``) rather than published late;
        the scan's next refit on a fresh sample covers it.  Applies where the service is given a wall
        clock (:attr:`ReconstructionService.wall_ns`: a live source), never to a replay.  The exact fits
        due run anyway (a fit is never shed).  0 disables it.
    provisional_backlog : int
        Payloads waiting behind a sample that a live source still calls a short backlog: the sample's
        provisional refit runs at once, without its exact fits, which wait for the backlog to drain
        (``handle(..., fits_wait=True)``); behind a longer one the refit waits too (``busy``).  A refit
        deferred waits for the backlog to drain, and that wait is its estimate's latency, while the update
        run at once holds the samples behind it a fraction of a millisecond.
    provisional_budget : float
        s of work that waited for a backlog one :meth:`ReconstructionService.tick` or
        :meth:`ReconstructionService.catch_up` runs: the finals of scans completed meanwhile, then the
        deferred provisional refits (oldest estimate first, without their exact fits), then those exact
        fits; the rest wait for the next call, so catching up never holds the stream for long (at least one
        runs a call: the default is about one exact fit).
    fits_in_pool : bool
        Live, with a final pool (``final_workers``), a provisional plane's exact fit (the provisional method
        from scratch: milliseconds, where an update takes tenths) runs in the pool's workers while the samples
        go on: its plane keeps its estimate until the result is back (none is given while plane a's first fit
        is away), and the next estimate of its scan has it.  When the pool is full the fit waits for room.
        Off by default, as handing them out can hold the samples' thread (``lelsonar bench ingest``, row (b1)
        shows it). Off, or without a pool, or in a replay, the fits run on the samples' thread
        (``provisional_backlog``, ``provisional_budget``).
    scan_timeout : float
        s of silence after which an open scan is finalised (marked FINAL_TIMEOUT).
    end_grace : float
        s to wait, after a ScanEnd with steps missing, before publishing INCOMPLETE when no
        recovery is possible (no ``recover`` hook).
    recovery_attempts : int
        Requests to the acquirer's log per scan without progress before giving up (0: never ask).
    recovery_interval : float
        s before the second request for a scan; each later one waits twice as long, up to 4 s (or this).
    recovery_after : float
        s of silence after which an open scan without ScanEnd asks the log for the rest.
    max_scans : int
        Scans assembled at once; the oldest is forgotten first (counted).
    max_pending : int
        Samples held, over all scans, while their ScanStart is missing (counted when dropped).
    max_scanners : int
        Scanners whose latest estimate is kept (a `get` on planes answers from it).
    limits : DecodeLimits
    final_workers : int or None
        Worker processes a source (live or a replay) estimates the finals in, off the thread that handles
        the samples (:class:`~lelsonar.reconstruct.stream.final_pool.FinalPool`); 0 estimates them on that
        thread.  None: one per core beyond the first, at most two (none on one core); a replay uses
        what the host's load leaves idle but one core, the decompression's, for a file of fewer than a few
        hundred scans, and none for a short file while the workers' fork server has not started yet
        (:func:`~lelsonar.reconstruct.stream.replay.replay_workers`).
    """

    method: str = DEFAULT_METHOD
    compare_methods: tuple[str, ...] = ("ls",)
    refit_every: int = 4
    provisional_period: float = 0.08
    confirm_steps: int = 6
    confirm_ratio: float = 1.5
    provisional: bool = True
    max_provisional_delay: float = 0.25
    provisional_deadline: float = 0.04
    provisional_backlog: int = 32
    provisional_budget: float = 0.003
    fits_in_pool: bool = False
    keep_finals: int = 1024
    scan_timeout: float = 10.0
    end_grace: float = 1.0
    recovery_attempts: int = 5
    recovery_interval: float = 1.0
    recovery_after: float = 1.0
    max_scans: int = 256
    max_pending: int = 4096
    max_scanners: int = 256
    limits: codec.DecodeLimits = codec.DEFAULT_LIMITS
    final_workers: int | None = None

    def __post_init__(self) -> None:
        for name in (self.method, *self.compare_methods):
            if name not in METHODS:
                raise ConfigError(f"unknown method {name!r}; choose from {', '.join(sorted(METHODS))}")
        if self.provisional_backlog < 0:
            raise ConfigError(f"provisional_backlog must be >= 0 payloads, got {self.provisional_backlog}")
        if self.refit_every < 1 or self.confirm_steps < 1:
            raise ConfigError("refit_every and confirm_steps must be >= 1")
        if not self.provisional_period >= 0:
            raise ConfigError("provisional_period must be >= 0 s")
        if not self.provisional_deadline >= 0:
            raise ConfigError(f"provisional_deadline must be >= 0 s (0: off), got {self.provisional_deadline}")
        if not (self.scan_timeout > 0 and self.end_grace >= 0 and self.confirm_ratio >= 1):
            raise ConfigError("scan_timeout must be > 0 s, end_grace >= 0 s and confirm_ratio >= 1")
        if self.recovery_attempts < 0 or not (self.recovery_interval > 0 and self.recovery_after > 0):
            raise ConfigError("recovery_attempts must be >= 0, recovery_interval and recovery_after > 0 s")
        if min(self.max_scans, self.max_pending, self.max_scanners, self.keep_finals) < 1:
            raise ConfigError("max_scans, max_pending, max_scanners and keep_finals must be >= 1")
        if self.final_workers is not None and self.final_workers < 0:
            raise ConfigError(f"final_workers must be >= 0 (0: on the stream's thread), got {self.final_workers}")

    def record_options(self) -> RecordOptions:
        """How this service's scans are reconstructed (:func:`reconstruct_scan`)."""
        return RecordOptions(
            method=self.method,
            compare_methods=self.compare_methods,
            fit=FitOptions(),
            confirm_steps=self.confirm_steps,
            confirm_ratio=self.confirm_ratio,
            provisional_period=self.provisional_period,
        )


@dataclass
class ServiceStats:
    """Totals over the scans finalised so far (rejected input: ``ingest.rejected``; all of it: ``stats_dict``)."""

    estimates: int = 0
    finals: int = 0  # every terminal estimate: final, final_timeout, incomplete
    timeouts: int = 0
    incomplete: int = 0
    published: int = 0
    received_live: int = 0
    recovered: int = 0
    duplicates: int = 0
    missing: int = 0
    recovery_requests: int = 0
    recovery_refused: int = 0
    #: Deferred provisional refits dropped under a backlog (the final is never shed).
    provisionals_shed: int = 0
    #: Provisional estimates due on a live sample that had waited past ``provisional_deadline``: not published.
    provisionals_stale: int = 0
    #: Scans that ended (input over) without their ScanStart ever arriving: not reconstructed.
    without_start: int = 0
    #: Jobs run in a pool's workers (the finals, and live the provisional exact fits: ``fits_from_pool``),
    #: workers lost (killed, crashed), jobs run again after a loss.
    finals_in_workers: int = 0
    final_workers_lost: int = 0
    finals_rerun: int = 0
    #: Finals whose estimate raised (logged with the traceback; nothing published for the scan).
    final_errors: int = 0
    #: Finals on their way when their source stopped on an error (logged).
    finals_dropped: int = 0
    #: Provisional exact fits whose result came back from a pool (run by its workers, or by the pool in the
    #: caller when no worker was ready), and those that raised there (logged; the plane's estimate says its fit
    #: failed).
    fits_from_pool: int = 0
    fit_errors: int = 0
    #: What a bound pushed out of the service's own tables, by reason.
    evicted: Counter = field(default_factory=Counter)

    def add_final(self, acc: ScanAccounting, status: str) -> None:
        """Count one terminal estimate and its scan's accounting."""
        self.finals += 1
        self.incomplete += status == "incomplete"
        self.published += acc.published
        self.received_live += acc.received_live
        self.recovered += acc.recovered
        self.duplicates += acc.duplicates
        self.missing += acc.missing

    def add_pool(self, pool: PoolStats) -> None:
        """Add what a final pool the service is done with counted."""
        self.finals_in_workers += pool.pooled
        self.final_workers_lost += pool.workers_lost
        self.finals_rerun += pool.rerun

    def as_dict(self, ingest: Ingest, pool: PoolStats | None) -> dict:
        """Everything counted so far, with what ``ingest`` counted and the pool in use (``stats_dict``)."""
        return {
            "estimates": self.estimates,
            "finals": self.finals,
            "final_timeouts": self.timeouts,
            "incomplete": self.incomplete,
            "samples": {
                "published": self.published,
                "received_live": self.received_live,
                "recovered": self.recovered,
                "duplicates": self.duplicates,
                "missing": self.missing,
                # carried Sample.sensor_energy that disagreed with the waveforms (recomputed, not lost)
                "energy_mismatches": ingest.energy_mismatches,
            },
            "rejected": dict(ingest.rejected),
            "evicted": dict(ingest.evicted + self.evicted),
            "recovery": {
                "requests": self.recovery_requests,
                "refused": self.recovery_refused,
                "replies_after_verdict": ingest.recovered_after_close,
            },
            "provisionals_shed": self.provisionals_shed,
            "provisional_fits": {"from_pool": self.fits_from_pool, "errors": self.fit_errors},
            "provisionals_stale": self.provisionals_stale,
            "finals_pool": self.pool_dict(pool),
            "open_scans": len(ingest.scans),
            "pending_samples": ingest.n_pending,
            "scans_without_start": self.without_start,
        }

    def pool_dict(self, current: PoolStats | None) -> dict[str, int]:
        """The final pool's work, for ``stats_dict``: with ``current``, the pool in use, counted so far (its jobs
        are the finals, and live the provisional exact fits)."""
        return {
            "in_workers": self.finals_in_workers + (current.pooled if current else 0),
            "workers_lost": self.final_workers_lost + (current.workers_lost if current else 0),
            "rerun": self.finals_rerun + (current.rerun if current else 0),
            "errors": self.final_errors,
            "dropped": self.finals_dropped,
        }
