"""Ask the acquirer's log for the steps a scan lacks (the consumer knows what it lacks).

The service (:mod:`lelsonar.reconstruct.stream.service`) decides *what* to ask — the
missing steps of an ended scan, the rest of a silent one, the beginning and the
ScanStart of a scan met late — and how often (bounded attempts).  This module
does the asking: one worker thread runs ``get`` on
``<prefix>/<scanner>/log/<scan_id>?steps=A-B;start=1;end=1`` (served by
``lelsonar acquire``, see :mod:`lelsonar.acquire.log_server`), checks every
reply, and hands the good ones back as payloads with origin "recovered", to be
decoded and validated by the same ingest as live data.

Checks on each reply (a failed one is counted by reason and dropped):

- the reply's key is the key asked (no wildcard answers, no other scan);
- its encoding names a lelsonar message that was asked for (a Sample, or the
  ScanStart / ScanEnd when asked);
- it decodes under the same :class:`~lelsonar.codec.DecodeLimits`;
- its scanner and scan ids are the key's, and a Sample's step is in the range;
- at most ``range size + 2`` replies per query are taken.

How long to keep asking (:class:`RecoveryPolicy`): a scan asks at most
``attempts`` times without progress, the interval doubling from ``interval`` up
to ``max_interval``; past that budget it keeps asking, at ``max_interval``, for
as long as the acquirer's log may still answer — its liveliness token
(``<prefix>/<scanner>/alive/acquire``, :class:`LogPresence`) has not been
absent for ``log_gone_after`` seconds and the log has not answered that it no
longer holds the scan — up to ``patience`` seconds without progress.  An outage
longer than the attempts (a partition, a router restarting) therefore loses
nothing while the acquirer still serves its log; a scanner whose acquirer was
never seen (another writer, no liveliness) keeps the bounded budget.

Why a queryable over the log and not only zenoh-ext's advanced pub/sub: the
advanced publisher's cache is a ring of the last N puts addressed by Zenoh
sequence numbers; it cannot answer "steps 40-73 of scan X" after the scan, a
late joiner only gets the last N samples, a cache large enough for a whole scan
(~10 MB) blocks ``put`` on a saturated link unless its replies DROP, and its
miss detection is an unstable API. The log is already the truth (every message
is recorded before it is published), so serving it by step index recovers
exactly what is missing, after any partition, for as long as the acquirer keeps
it.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections import Counter, OrderedDict
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import zenoh

from lelsonar import codec
from lelsonar.errors import ConfigError, LelsonarError
from lelsonar.keys import LOG_NOT_HELD_ENCODING, MAX_LOG_STEPS_PER_QUERY, ScannerKeys

_log = logging.getLogger(__name__)

ORIGIN = "recovered"
#: Scans remembered as no longer held by their acquirer's log (keys are wire data: bounded).
MAX_NOT_HELD = 4096
#: Scanners whose acquirer's presence is tracked (bounded: the oldest forgotten first).
MAX_TRACKED = 4096


@dataclass(frozen=True)
class RecoveryRequest:
    """What one scan lacks: steps (ascending), and whether its ScanStart / ScanEnd are wanted."""

    scanner_id: str
    scan_id: int
    steps: tuple[int, ...] = ()
    want_start: bool = False
    want_end: bool = False


def step_ranges(steps: Iterable[int], max_len: int) -> list[tuple[int, int]]:
    """Inclusive ``(first, last)`` runs of consecutive steps, each at most ``max_len`` long."""
    out: list[tuple[int, int]] = []
    for s in sorted(set(int(s) for s in steps)):
        if out and s == out[-1][1] + 1 and s - out[-1][0] < max_len:
            out[-1] = (out[-1][0], s)
        else:
            out.append((s, s))
    return out


def selectors(
    keys: ScannerKeys, request: RecoveryRequest, max_len: int
) -> list[tuple[str, tuple[int, int] | None, bool, bool]]:
    """The queries for one request: ``(selector, step range or None, start wanted, end wanted)``."""
    key = ScannerKeys(keys.prefix, request.scanner_id).log(request.scan_id)
    ranges: list[tuple[int, int] | None] = list(step_ranges(request.steps, max_len)) or [None]
    out = []
    for i, rng in enumerate(ranges):
        start = request.want_start and i == 0
        end = request.want_end and i == len(ranges) - 1
        params = (
            ([f"steps={rng[0]}-{rng[1]}"] if rng else []) + (["start=1"] if start else []) + (["end=1"] if end else [])
        )
        if params:
            out.append((f"{key}?{';'.join(params)}", rng, start, end))
    return out


@dataclass(frozen=True)
class RecoveryPolicy:
    """When a scan asks the acquirer's log again, and when it gives up.

    Parameters
    ----------
    attempts : int
        Requests without progress that are always made (0: never ask).
    interval : float
        s before the second request; each later one waits twice as long, up to ``max_interval``.
    max_interval : float
        s, the longest wait between two requests.
    patience : float
        s of requests without progress after which a scan gives up even though its log seems present.

    ``log_may_answer(scanner, scan_id)`` (set by the live source) says whether the log may still
    answer: past ``attempts``, the requests go on while it does.  Without it, ``attempts`` is the budget.
    """

    attempts: int = 5
    interval: float = 1.0
    max_interval: float = 4.0
    patience: float = 120.0
    log_may_answer: Callable[[str, int], bool] | None = None

    def __post_init__(self) -> None:
        if self.attempts < 0:
            raise ConfigError(f"recovery attempts must be >= 0, got {self.attempts}")
        if not (self.interval > 0 and self.max_interval >= self.interval and self.patience >= 0):
            raise ConfigError(
                "recovery interval must be > 0 s, its maximum >= the interval, and the patience >= 0 s; "
                f"got {self.interval}, {self.max_interval} and {self.patience}"
            )

    def wait_after(self, attempts: int) -> float:
        """s to wait after the ``attempts``-th request before the next: doubling, capped."""
        return min(self.interval * 2.0 ** max(attempts - 1, 0), self.max_interval)

    def _asked_for(self, attempts: int) -> float:
        """s spanned by ``attempts`` requests (the waits between them)."""
        return sum(self.wait_after(a) for a in range(1, attempts))

    def _may_go_on(self, attempts: int, key: tuple[str, int] | None) -> bool:
        if attempts < self.attempts:
            return True
        if self.log_may_answer is None or key is None or self._asked_for(attempts) >= self.patience:
            return False
        return self.log_may_answer(*key)

    def can_ask(self, attempts: int, last_at: float | None, now: float, key: tuple[str, int] | None = None) -> bool:
        """Whether a scan that made ``attempts`` requests (the last at ``last_at``) may ask now."""
        if self.attempts == 0 or not self._may_go_on(attempts, key):
            return False
        return last_at is None or now - last_at >= self.wait_after(attempts)

    def exhausted(self, attempts: int, last_at: float | None, now: float, key: tuple[str, int] | None = None) -> bool:
        """Whether a scan has given up: no request is left, and the last one has had its time to answer."""
        if self.attempts == 0:
            return True
        if self._may_go_on(attempts, key):
            return False
        return last_at is None or now - last_at >= self.wait_after(attempts)


class LogPresence:
    """Whether each scanner's acquirer — and so its log — is reachable, from its liveliness token.

    ``acquire`` declares ``<prefix>/<scanner>/alive/acquire`` while it runs (scanning and serving its
    log).  A token seen and then lost (DELETE: the acquirer ended, or the link or its lease dropped) marks
    the log gone once it stays absent ``gone_after`` seconds; it may come back (a partition heals, a
    router restarts).  A scanner whose token was never seen is unknown: :meth:`may_answer` is False.
    Liveliness changes run a short callback on Zenoh's thread (rare: one per change).
    """

    def __init__(
        self,
        session: zenoh.Session | None,
        keys: ScannerKeys,
        gone_after: float,
        *,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if not gone_after >= 0:
            raise ConfigError(f"the log's gone-after bound must be >= 0 s, got {gone_after}")
        self.gone_after = gone_after
        self._clock = clock
        self._keys = keys
        self._lock = threading.Lock()
        #: scanner → monotonic time its token went absent (None: present).
        self._absent_since: OrderedDict[str, float | None] = OrderedDict()
        self._subscriber = (
            session.liveliness().declare_subscriber(
                ScannerKeys(keys.prefix, keys.scanner_id).alive("acquire"), self._changed, history=True
            )
            if session is not None
            else None
        )

    def _changed(self, sample: zenoh.Sample) -> None:
        try:
            scanner = self._keys.scanner_of(str(sample.key_expr))
        except LelsonarError:
            return  # not a scanner id: nobody asks for it
        self.note(scanner, sample.kind == zenoh.SampleKind.PUT)

    def note(self, scanner: str, present: bool) -> None:
        """Record that ``scanner``'s acquirer appeared (``present``) or went away."""
        with self._lock:
            was = self._absent_since.get(scanner, 0.0)
            if present:
                self._absent_since[scanner] = None
            elif was is None or scanner not in self._absent_since:
                self._absent_since[scanner] = self._clock()
            self._absent_since.move_to_end(scanner)
            while len(self._absent_since) > MAX_TRACKED:
                self._absent_since.popitem(last=False)

    def may_answer(self, scanner: str) -> bool:
        """Seen, and present or absent for less than ``gone_after`` s."""
        with self._lock:
            if scanner not in self._absent_since:
                return False
            since = self._absent_since[scanner]
        return since is None or self._clock() - since < self.gone_after

    def close(self) -> None:
        if self._subscriber is not None:
            try:
                self._subscriber.undeclare()
            except zenoh.ZError as exc:
                _log.warning("undeclaring the acquirers' liveliness subscriber failed: %s", exc)


@dataclass(frozen=True)
class RecoveryConfig:
    """How the recovery client asks.

    Parameters
    ----------
    query_timeout : float
        s to wait for the replies of one query.
    max_steps_per_query : int
        Samples asked per query (the acquirer refuses more than ``MAX_LOG_STEPS_PER_QUERY``).
    max_queued : int
        Requests waiting for the worker; more are refused and counted.
    log_gone_after : float
        s an acquirer's liveliness token may stay absent before its log counts as gone (the Zenoh lease is
        10 s: a partition drops the token after it; the default outlives a 15 s partition and a restarting
        router, whose clients come back within their connect retry period).
    limits : DecodeLimits
    """

    query_timeout: float = 2.0
    max_steps_per_query: int = MAX_LOG_STEPS_PER_QUERY
    max_queued: int = 64
    log_gone_after: float = 30.0
    limits: codec.DecodeLimits = codec.DEFAULT_LIMITS

    def __post_init__(self) -> None:
        if not self.query_timeout > 0:
            raise ConfigError("RecoveryConfig.query_timeout must be > 0 s")
        if not 1 <= self.max_steps_per_query <= MAX_LOG_STEPS_PER_QUERY:
            raise ConfigError(f"RecoveryConfig.max_steps_per_query must be in [1, {MAX_LOG_STEPS_PER_QUERY}]")
        if self.max_queued < 1:
            raise ConfigError("RecoveryConfig.max_queued must be >= 1")
        if not self.log_gone_after >= 0:
            raise ConfigError("RecoveryConfig.log_gone_after must be >= 0 s")


class LogRecoveryClient:
    """Runs recovery requests on one worker thread; delivers checked payloads.

    ``deliver(type_name, payload, origin)`` receives each good reply; it may
    block (the live source's bounded queue).  ``wanted(request)``, checked
    before each query, skips requests that no longer matter.  Use as a
    context manager.
    """

    def __init__(
        self,
        session: zenoh.Session,
        keys: ScannerKeys,
        deliver: Callable[[str, bytes, str], None],
        config: RecoveryConfig = RecoveryConfig(),
        *,
        wanted: Callable[[RecoveryRequest], bool] | None = None,
    ) -> None:
        self._session = session
        self._wanted = wanted
        self._keys = keys
        self._deliver = deliver
        self.config = config
        self._requests: queue.Queue[RecoveryRequest | None] = queue.Queue(maxsize=config.max_queued)
        self._thread = threading.Thread(target=self._run, name="recovery", daemon=True)
        #: The acquirers seen alive (their logs), and the scans their logs said they no longer hold.
        self.presence = LogPresence(session, keys, config.log_gone_after)
        self._not_held: OrderedDict[tuple[str, int], None] = OrderedDict()
        self._closed = threading.Event()
        self._cv = threading.Condition()
        self._outstanding = 0  # requests queued or being served
        #: Queries, replies, delivered payloads, refusals and bad replies, by name.
        self.stats: Counter[str] = Counter()

    def __enter__(self) -> LogRecoveryClient:
        self._thread.start()
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def close(self) -> None:
        self._closed.set()
        self.presence.close()
        try:
            self._requests.put_nowait(None)
        except queue.Full:
            pass  # the worker checks the flag between queries
        self._thread.join(timeout=self.config.query_timeout + 5)

    def may_answer(self, scanner_id: str, scan_id: int) -> bool:
        """Whether the log of ``scanner_id`` may still supply scan ``scan_id`` (see :class:`LogPresence`)."""
        with self._cv:
            if (scanner_id, scan_id) in self._not_held:
                return False
        return self.presence.may_answer(scanner_id)

    def request(self, request: RecoveryRequest) -> bool:
        """Queue a request; False (counted) when the queue is full or the client is closed."""
        if self._closed.is_set():
            self.stats["refused: client closed"] += 1
            return False
        try:
            with self._cv:
                self._requests.put_nowait(request)
                self._outstanding += 1
        except queue.Full:
            self.stats[f"refused: queue full (max_queued={self.config.max_queued})"] += 1
            _log.warning(
                "recovery request for scan (%s, %d) refused: %d requests already wait",
                request.scanner_id,
                request.scan_id,
                self.config.max_queued,
            )
            return False
        self.stats["requests"] += 1
        return True

    def wait_idle(self, timeout: float) -> bool:
        """Wait until every queued request has been served; False on timeout."""
        deadline = time.monotonic() + timeout
        with self._cv:
            while self._outstanding:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cv.wait(left)
        return True

    # --- worker --------------------------------------------------------------------------
    def _run(self) -> None:
        while not self._closed.is_set():
            req = self._requests.get()
            if req is None:
                return
            try:
                self._serve(req)
            except Exception:  # noqa: BLE001 - a bug in one request must not end recovery for all scans
                self.stats["errors: unexpected"] += 1
                _log.exception("recovery of scan (%s, %d) failed; carrying on", req.scanner_id, req.scan_id)
            finally:
                with self._cv:
                    self._outstanding -= 1
                    self._cv.notify_all()

    def _serve(self, req: RecoveryRequest) -> None:
        key = ScannerKeys(self._keys.prefix, req.scanner_id).log(req.scan_id)
        for selector, rng, want_start, want_end in selectors(self._keys, req, self.config.max_steps_per_query):
            if self._closed.is_set():
                return
            if self._wanted is not None and not self._wanted(req):
                self.stats["skipped: scan already has its verdict"] += 1
                return
            self.stats["queries"] += 1
            allowed = (rng[1] - rng[0] + 1 if rng else 0) + int(want_start) + int(want_end)
            try:
                replies = self._session.get(
                    selector, consolidation=zenoh.ConsolidationMode.NONE, timeout=self.config.query_timeout
                )
                taken = 0
                for reply in replies:
                    if reply.ok is None:
                        self.stats["errors: error reply"] += 1
                        if reply.err is not None and str(reply.err.encoding) == LOG_NOT_HELD_ENCODING:
                            self._mark_not_held(req)
                        _log.warning(
                            "log query %s answered an error: %s",
                            selector,
                            reply.err.payload.to_bytes()[:200] if reply.err is not None else "?",
                        )
                        continue
                    if taken >= allowed:
                        self.stats["rejected: more replies than asked"] += 1
                        continue
                    taken += 1
                    self._check_and_deliver(reply.ok, key, req, rng, want_start, want_end)
            except zenoh.ZError as exc:
                self.stats["errors: query failed"] += 1
                _log.warning("log query %s failed: %s", selector, exc)

    def _mark_not_held(self, req: RecoveryRequest) -> None:
        with self._cv:
            self._not_held[(req.scanner_id, req.scan_id)] = None
            while len(self._not_held) > MAX_NOT_HELD:
                self._not_held.popitem(last=False)

    def _check_and_deliver(
        self,
        sample: zenoh.Sample,
        key: str,
        req: RecoveryRequest,
        rng: tuple[int, int] | None,
        want_start: bool,
        want_end: bool,
    ) -> None:
        self.stats["replies"] += 1
        if str(sample.key_expr) != key:
            return self._bad("key mismatch", f"reply on {str(sample.key_expr)[:120]!r}, asked {key!r}")
        media, _, type_name = str(sample.encoding).partition(";")
        cls = codec.MESSAGE_TYPES.get(type_name) if media == "application/protobuf" else None
        wanted = (
            {codec.Sample} | ({codec.ScanStart} if want_start else set()) | ({codec.ScanEnd} if want_end else set())
        )
        if cls not in wanted:
            return self._bad("unexpected type", f"{str(sample.encoding)[:80]!r} on {key}")
        if len(sample.payload) > self.config.limits.max_payload_bytes:  # refused before it is copied
            return self._bad("PayloadTooLargeError", f"{len(sample.payload)} bytes on {key}")
        payload = sample.payload.to_bytes()
        try:
            message = codec.decode(payload, cls, self.config.limits)
        except LelsonarError as exc:
            return self._bad(type(exc).__name__, f"reply on {key}: {exc}")
        if (message.scanner_id, message.scan_id) != (req.scanner_id, req.scan_id):
            return self._bad(
                "identity mismatch",
                f"{type(message).__name__} of scan ({message.scanner_id}, {message.scan_id}) on {key}",
            )
        if isinstance(message, codec.Sample) and (rng is None or not rng[0] <= message.step <= rng[1]):
            return self._bad("step not asked", f"step {message.step} on {key}, asked {rng}")
        self.stats["delivered"] += 1
        self._deliver(type_name, payload, ORIGIN)

    def _bad(self, reason: str, detail: str) -> None:
        self.stats[f"rejected: {reason}"] += 1
        _log.warning("recovery reply dropped (%s): %s", reason, detail)
