"""What the live service asks of the acquirer's log, and when (the asking itself:
:class:`~lelsonar.reconstruct.stream.recovery.LogRecoveryClient`).

Per scan, :class:`LogRequests` counts the attempts made without progress (any new step starts the budget
again), spaces them by the :class:`~lelsonar.reconstruct.stream.recovery.RecoveryPolicy`, says when the
budget is exhausted, and asks for a scan met in the middle (its ScanStart and the steps before) and for
the steps that came twice with different content (the log's copy settles them).
"""

from __future__ import annotations

import logging
from collections.abc import Callable

from lelsonar import codec
from lelsonar.errors import InternalError
from lelsonar.reconstruct.stream.assembly import ScanAssembly
from lelsonar.reconstruct.stream.config import ReconstructConfig, ServiceStats
from lelsonar.reconstruct.stream.ingest import ScanKey
from lelsonar.reconstruct.stream.partial import Partial, RecoveryState
from lelsonar.reconstruct.stream.reasons import ranges_text
from lelsonar.reconstruct.stream.recovery import RecoveryPolicy, RecoveryRequest

_log = logging.getLogger(__name__)


class LogRequests:
    """The requests of one service to the acquirer's log.

    ``recover`` asks the log (returns False when the request was refused; None: nothing can be asked, as
    in a replay); ``policy`` says when to ask again and when to give up (a live source lets it ask on while
    the log may answer).
    """

    def __init__(self, config: ReconstructConfig, stats: ServiceStats, event: Callable[[str, str], None]) -> None:
        self.config = config
        self.stats = stats
        self._event = event
        self.recover: Callable[[RecoveryRequest], bool] | None = None
        self.policy = RecoveryPolicy(
            config.recovery_attempts,
            config.recovery_interval,
            max(config.recovery_interval, RecoveryPolicy.max_interval),
        )
        #: Samples held while their ScanStart is missing: since when, and the requests for the ScanStart.
        self.pending_since: dict[ScanKey, tuple[float, RecoveryState]] = {}

    def note_progress(self, r: RecoveryState, held: int) -> None:
        if r.mark >= 0 and held > r.mark:
            r.attempts, r.mark = 0, held  # new steps came: the budget starts again

    def can_ask(self, r: RecoveryState, now: float, key: ScanKey) -> bool:
        return self.recover is not None and self.policy.can_ask(r.attempts, r.last_at, now, key)

    def exhausted(self, r: RecoveryState, now: float, key: ScanKey) -> bool:
        return self.recover is None or self.policy.exhausted(r.attempts, r.last_at, now, key)

    def settle(self, scan: ScanAssembly, p: Partial, now: float) -> None:
        """Ask the acquirer's log for the steps that arrived twice with different content (its copy wins)."""
        if scan.unsettled and self.recover is not None and p.settling != scan.unsettled:
            p.settling, p.settle_at = frozenset(scan.unsettled), now
            self._event(
                "WARNING",
                f"scan {scan.key}: {scan.conflicts} conflicting copies of steps {ranges_text(sorted(p.settling))}; "
                "asking the acquirer's log which is right",
            )
            self.request(RecoveryRequest(*scan.key, steps=tuple(sorted(p.settling))))

    def request(self, request: RecoveryRequest) -> None:
        """One request to the acquirer's log (counted; a refusal or a failure counted as refused)."""
        self.stats.recovery_requests += 1
        try:
            ok = self.recover is not None and self.recover(request)
        except Exception:  # noqa: BLE001 - a failed request is a refused one, not a dead service
            _log.exception("recovery request failed; counted as refused")
            ok = False
        if not ok:
            self.stats.recovery_refused += 1

    def settling(self, scan: ScanAssembly, p: Partial, now: float) -> bool:
        """Whether the final waits for the log to settle conflicting copies (live, for up to ``scan_timeout``)."""
        if not scan.unsettled or self.recover is None:
            return False
        if p.settle_at is None:
            self.settle(scan, p, now)
        return p.settle_at is not None and now - p.settle_at < self.config.scan_timeout

    def ask(self, r: RecoveryState, request: RecoveryRequest, now: float, held: int) -> None:
        """One attempt of a scan's budget (``held``: the steps it holds now, to tell progress later)."""
        if self.recover is None:
            raise InternalError("a recovery request was made by a service given no recover callback")
        r.attempts += 1
        r.requests += 1
        r.last_at, r.mark = now, held
        what = ", ".join(
            x
            for x in (
                f"{len(request.steps)} steps" if request.steps else "",
                "ScanStart" if request.want_start else "",
                "ScanEnd" if request.want_end else "",
            )
            if x
        )
        self._event(
            "INFO",
            f"scan ({request.scanner_id}, {request.scan_id}): asking the acquirer's log for "
            f"{what} (attempt {r.attempts}"
            + (
                f"/{self.config.recovery_attempts})"
                if r.attempts <= self.config.recovery_attempts
                else f", past {self.config.recovery_attempts}: its log may still answer)"
            ),
        )
        self.request(request)

    def ask_for_start(self, key: ScanKey, now: float, held: list) -> None:
        """A scan met in the middle: ask for its ScanStart and the steps before what is held
        (all the steps its ScanEnd counts, when the ScanEnd is what is held)."""
        _, r = self.pending_since[key]
        self.note_progress(r, len(held))
        if not held or not self.can_ask(r, now, key):
            return
        have = {m.step for m, _ in held if isinstance(m, codec.Sample)}
        ends = [m for m, _ in held if isinstance(m, codec.ScanEnd)]
        upto = int(ends[0].samples_sent) if ends else max(have) + 1
        wanted = tuple(s for s in range(upto) if s not in have)
        self.ask(r, RecoveryRequest(*key, steps=wanted, want_start=True), now, len(held))
