"""When a scan's provisional refit runs while a backlog waits: deferred, caught up within a budget, or shed.

A refit behind a long backlog is deferred: with many scanners a backlog builds where their scans reach the
same costly refit together (the corner's confirmation, plane b's exact fits, when the scans run in step), and
samples that wait behind those refits are late for every scan.  Behind a short backlog the refit runs at once
without its exact fits, which wait (:meth:`ProvisionalSchedule.fits_later`): its update costs the samples
behind it a fraction of a millisecond, where deferring it would cost its estimate the backlog's drain.
Live, a refit due on a sample that waited over ``provisional_deadline`` beyond its scan's quickest is stale
(:meth:`ProvisionalSchedule.stale`): not published, and counted.
:meth:`ProvisionalSchedule.catch_up` runs the deferred ones oldest estimate first, for at most
``provisional_budget`` of the service's clock, leaving the rest for the next call (the source calls it when
the backlog has drained, and on every tick); a tick that still finds a backlog sheds, and counts, the refit
of a scan that has had no estimate for over twice ``max_provisional_delay``: the scan's next refit covers the
samples it would have.

A caught-up refit runs no exact fit (the costly part, milliseconds against the update's tenths): it publishes
at once what the planes give in O(new samples), and a plane whose exact fit is due keeps its last estimate
(a scan whose plane a waits for its first fit has none to give yet).  Those fits run after the refits, oldest
scan first, with what the budget leaves; the next estimate of their scan has them.  A fit is never shed.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Protocol

from lelsonar import codec
from lelsonar.reconstruct.stream.assembly import ScanAssembly
from lelsonar.reconstruct.stream.config import ReconstructConfig, ServiceStats
from lelsonar.reconstruct.stream.ingest import ScanKey
from lelsonar.reconstruct.stream.partial import Partial


class Refit(Protocol):
    """Runs one scan's provisional refit (``fits_wait``: without its exact fits); returns the estimates it
    published."""

    def __call__(self, scan: ScanAssembly, p: Partial, *, fits_wait: bool = ...) -> list[codec.Reconstruction]: ...


class ProvisionalSchedule:
    """The scans whose provisional refit waits for a backlog, and the catching up on them."""

    def __init__(self, config: ReconstructConfig, stats: ServiceStats, clock: Callable[[], float]) -> None:
        self.config = config
        self.stats = stats
        self._clock = clock
        self._deferred: set[ScanKey] = set()
        self._fits: set[ScanKey] = set()  # scans whose exact fit waits
        #: The wall clock (ns) a live source gives (None: no estimate is stale, as in a replay).
        self.wall_ns: Callable[[], int] | None = None

    def __bool__(self) -> bool:
        """Whether a refit or an exact fit waits."""
        return bool(self._deferred or self._fits)

    def defer(self, key: ScanKey, p: Partial, busy: bool) -> bool:
        """Whether the scan's refit waits (it does whenever a backlog waits)."""
        if busy:
            p.deferred = True
            self._deferred.add(key)
            return True
        return False

    def arrived(self, scan: ScanAssembly, step: int, p: Partial) -> None:
        """A live sample was handled: keep its scan's transit floor (the least wall clock − acquisition time)."""
        if self.wall_ns is not None:
            lag = self.wall_ns() - int(scan.time_ns[step])
            if p.transit_floor_ns is None or lag < p.transit_floor_ns:
                p.transit_floor_ns = lag

    def stale(self, scan: ScanAssembly, p: Partial) -> bool:
        """Whether the scan's newest sample waited over ``provisional_deadline`` beyond the quickest of its
        scan's (the transit and the clocks' offset): its provisional estimate would be published late."""
        deadline = self.config.provisional_deadline
        if self.wall_ns is None or not deadline or p.transit_floor_ns is None:
            return False
        return self.wall_ns() - scan.newest_ns - p.transit_floor_ns > deadline * 1e9

    def fits_later(self, key: ScanKey) -> None:
        """The scan's refit ran without its exact fits (payloads waited): they run when the backlog drains."""
        self._fits.add(key)

    def catch_up(
        self,
        partials: Mapping[ScanKey, Partial],
        scans: Mapping[ScanKey, ScanAssembly],
        busy: bool,
        refit: Refit,
        start: float | None = None,
        *,
        run_fits: Callable[[ScanAssembly, Partial], list[codec.Reconstruction]] | None = None,
    ) -> list[codec.Reconstruction]:
        """Run the deferred provisional refits without their exact fits, oldest estimate first, then the exact
        fits that wait, oldest first, for at most ``provisional_budget`` in all (from ``start`` on the service's
        clock: by default now).

        Those left wait for the next call; under a backlog (``busy``) a refit deferred for over twice
        ``max_provisional_delay`` is shed and counted instead: its scan's next refit covers its samples.
        ``run_fits`` runs a scan's exact fits that wait (default: ``refit`` without ``fits_wait``); it may hand them
        elsewhere.
        """
        cfg = self.config
        out: list[codec.Reconstruction] = []
        start = self._clock() if start is None else start
        waiting = sorted((p.estimated_at, key, p) for key in self._deferred if (p := partials.get(key)) is not None)
        self._deferred.clear()
        for n, (estimated_at, key, p) in enumerate(waiting):
            scan = scans.get(key)
            if scan is None or not p.deferred:
                continue
            if self._clock() - start >= cfg.provisional_budget:
                self._deferred.update(k for _, k, _ in waiting[n:])
                return out
            p.deferred = False
            if busy and start - estimated_at >= 2 * cfg.max_provisional_delay:
                self.stats.provisionals_shed += 1
                p.estimated_at = start  # the next deferral waits a full delay again
            else:
                out += refit(scan, p, fits_wait=True)
            if p.fits_wanted:
                self._fits.add(key)
        fits = sorted((p.estimated_at, key, p) for key in self._fits if (p := partials.get(key)) is not None)
        self._fits.clear()
        for n, (_, key, p) in enumerate(fits):
            scan = scans.get(key)
            if scan is None or not p.fits_wanted:
                continue  # (gone, or its fit ran in a refit meanwhile)
            if self._clock() - start >= cfg.provisional_budget:
                self._fits.update(k for _, k, _ in fits[n:])
                break
            out += run_fits(scan, p) if run_fits is not None else refit(scan, p)
        return out
