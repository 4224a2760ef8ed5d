"""Where live payloads come from — a Zenoh subscription — and where estimates go.

A live source and a replay (:mod:`lelsonar.reconstruct.stream.replay`) hand (type name, payload bytes) to
the same :meth:`ReconstructionService.handle`.  Live, one processing thread applies
every payload: it drains a bounded Zenoh FIFO channel of samples and scan
events itself (no Python runs on Zenoh's receiving thread; a full channel
blocks it, which back-pressures the publisher through congestion control
BLOCK), and a bounded FIFO of the replies recovered from the acquirer's log
(:mod:`lelsonar.reconstruct.stream.recovery`) and of the messages of adopted scans.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections import Counter, OrderedDict, deque
from collections.abc import Callable
from typing import cast

import zenoh

from lelsonar import codec
from lelsonar.errors import ConfigError, LelsonarError
from lelsonar.keys import ScannerKeys, validate_identifier
from lelsonar.log.recording import McapRecorder
from lelsonar.reconstruct.stream.final_pool import FinalPool
from lelsonar.reconstruct.stream.finals import auto_workers
from lelsonar.reconstruct.stream.group import GroupMembership
from lelsonar.reconstruct.stream.recovery import LogRecoveryClient, RecoveryConfig
from lelsonar.reconstruct.stream.service import ReconstructionService

_log = logging.getLogger(__name__)

_STOP = ("", b"", "")  # queue sentinel
_FINALS = ("", b"", "finals")  # queue item: finals came back from the pool
_MAX_PARSED_KEYS = 4096
#: The leaves of the keys a live source takes (``<prefix>/<scanner>/<leaf>``).
LIVE_LEAVES = ("sample", "scan")


def live_key(keys: ScannerKeys) -> str:
    """One key expression covering the sample and scan keys of ``keys`` (and no other key of the contract).

    ``<prefix>/<scanner>/s$*``: ``$*`` matches within a chunk, so of the contract's leaves only
    ``sample`` and ``scan`` match (``planes``, ``alive/…`` and ``log/…`` do not).  One subscriber
    keeps the arrival order across both.
    """
    return f"{keys.prefix}/{keys.scanner_id}/s$*"


class PayloadFifo:
    """A bounded FIFO between Zenoh's callback (and the recovery / group threads) and one consumer.

    Producers block while ``capacity`` items wait (back-pressure, as ``queue.Queue`` does);
    the consumer takes up to ``batch`` items per lock hold and wakes blocked producers once
    per batch.  ``queue.Queue`` paid a lock round-trip per item and, when full, woke the
    producer (Zenoh's thread, which then wants the GIL) after every single item taken.
    At most ``capacity + batch`` payloads are held: the queued ones and the consumer's batch.
    The queued payloads also hold at most ``max_bytes`` (one larger item is let in alone, so
    nothing waits forever): producers block while they are over it.
    """

    def __init__(self, capacity: int, batch: int = 32, max_bytes: int = 64 * 1024 * 1024) -> None:
        if capacity < 1 or batch < 1 or max_bytes < 1:
            raise ConfigError(
                f"the payload FIFO's capacity, batch and max_bytes must be >= 1, got {capacity}, {batch} and "
                f"{max_bytes} (LiveSource fifo_capacity)"
            )
        self.capacity, self.batch, self.max_bytes = capacity, batch, max_bytes
        self._items: deque = deque()
        self._bytes = 0
        lock = threading.Lock()
        self._not_empty = threading.Condition(lock)
        self._not_full = threading.Condition(lock)

    def __len__(self) -> int:
        return len(self._items)

    def put(self, item, timeout: float | None = None) -> bool:
        """Append ``item``, waiting at most ``timeout`` s for room; False if there was none."""
        size = _item_bytes(item)
        with self._not_full:

            def room() -> bool:
                return len(self._items) < self.capacity and (not self._items or self._bytes + size <= self.max_bytes)

            if not room() and not self._not_full.wait_for(room, timeout):
                return False
            self._items.append(item)
            self._bytes += size
            if len(self._items) == 1:
                self._not_empty.notify()  # the consumer waits only on an empty FIFO
            return True

    def put_nowait(self, item) -> bool:
        return self.put(item, 0)

    def take(self, timeout: float) -> list:
        """The oldest items, up to ``batch``, in order; waits at most ``timeout`` s for one ([] if none came)."""
        with self._not_empty:
            if not self._items and not self._not_empty.wait(timeout):
                return []
            items = self._items
            n = min(len(items), self.batch)
            out = [items.popleft() for _ in range(n)]
            if n:
                self._bytes = 0 if not items else self._bytes - sum(_item_bytes(i) for i in out)
                self._not_full.notify_all()
            return out


def _item_bytes(item) -> int:
    """The payload bytes a FIFO item holds: a work item's payload, or a received Zenoh sample's."""
    if isinstance(item, tuple) and len(item) > 1 and isinstance(item[1], (bytes, zenoh.ZBytes)):
        return len(item[1])
    if isinstance(item, zenoh.Sample):
        return len(item.payload)
    return 0


class PlanesServer:
    """Publishes estimates on ``<prefix>/<scanner>/planes``; a ``get`` there returns the latest.

    At most ``max_publishers`` publishers are declared at once; the least recently used
    is undeclared first (counted in :attr:`evicted`).
    """

    def __init__(
        self,
        session: zenoh.Session,
        keys: ScannerKeys,
        latest: dict[str, codec.Reconstruction],
        *,
        max_publishers: int = 256,
        answers_for: Callable[[str], bool] | None = None,
    ) -> None:
        self._session = session
        #: In a group, a member answers a get only for the scanners it currently owns.
        self._answers_for = answers_for
        self._keys = keys
        self._latest = latest
        self._lock = threading.Lock()
        self._max_publishers = max_publishers
        self._publishers: OrderedDict[str, zenoh.Publisher] = OrderedDict()
        self.evicted: Counter[str] = Counter()
        self._queryable = session.declare_queryable(keys.planes, self._answer)

    def publish(self, message: codec.Reconstruction) -> None:
        scanner = validate_identifier(message.scanner_id)
        with self._lock:
            pub = self._publishers.get(scanner)
            if pub is None:
                pub = self._session.declare_publisher(
                    ScannerKeys(self._keys.prefix, scanner).planes,
                    congestion_control=zenoh.CongestionControl.BLOCK,
                    encoding=zenoh.Encoding(codec.encoding_name(message)),
                )
                self._publishers[scanner] = pub
                while len(self._publishers) > self._max_publishers:
                    _, old = self._publishers.popitem(last=False)
                    old.undeclare()
                    self.evicted["planes publisher undeclared (max_publishers)"] += 1
            self._publishers.move_to_end(scanner)
        pub.put(message.SerializeToString())

    def _answer(self, query: zenoh.Query) -> None:
        asked = query.key_expr
        with self._lock:
            latest = list(self._latest.items())
        for scanner, message in latest:
            if self._answers_for is not None and not self._answers_for(scanner):
                continue
            key = ScannerKeys(self._keys.prefix, scanner).planes
            if zenoh.KeyExpr(key).intersects(asked):
                query.reply(key, message.SerializeToString(), encoding=zenoh.Encoding(codec.encoding_name(message)))

    def close(self) -> None:
        self._queryable.undeclare()
        for pub in self._publishers.values():
            pub.undeclare()


class LiveSource:
    """Receives samples and scan events and feeds them to the service on one thread.

    Use as a context manager inside an open session.  Samples and scan events come
    through one subscriber (:func:`live_key`, a wildcard covering both keys) into one
    Zenoh FIFO channel, in arrival order: the acquirer publishes them from one session
    at one priority, so Zenoh delivers them in publication order, and one channel keeps
    that order across the two keys (a ``ScanEnd`` is handled after every sample it
    counts; a subscriber per key would let it overtake them).

    Zenoh's receiving thread runs no Python: it pushes each sample into the channel
    (Rust), and blocks while the channel is full, which back-pressures the publishers
    through congestion control BLOCK.  The processing thread drains the channel itself,
    a batch at a time, without waiting.  A Python callback on Zenoh's thread would take the
    GIL for every sample, against a busy worker, and so would a thread moving samples
    from the channel into a queue.
    Payloads recovered from the acquirer's log and the kept messages of scans adopted
    from a departed group member come through a :class:`PayloadFifo` drained by the
    same thread.

    The channel cannot be waited on together with that FIFO, and polling it cost an idle
    worker 3 % of a core.  So an idle worker *arms a doorbell* and waits on the FIFO
    alone: the doorbell thread waits on the channel (the GIL released), hands the first
    sample to come through the FIFO, and stops; from that sample on, the worker drains
    the channel again.  Only one of the two ever reads the channel, so the order holds;
    the doorbell takes the GIL once per idle spell, not per sample.  Held at most:
    ``fifo_capacity`` payloads in the channel, as many in the FIFO, and the worker's
    batch (``PayloadFifo.batch``) of each.

    The finals are estimated in worker processes (``final_workers`` of the service's config;
    :class:`~lelsonar.reconstruct.stream.final_pool.FinalPool`), so a scan's end does not hold every other
    scanner's samples: the pool wakes the processing thread when one comes back, which publishes it as
    the inline estimate would have been; those still on their way when the source closes are waited
    for and published.

    With ``recovery`` (the default), the service asks the acquirer's log for
    what a scan lacks (:class:`~lelsonar.reconstruct.stream.recovery.LogRecoveryClient`).
    An exception of any type while processing is logged with its traceback,
    counted in :attr:`errors` (by type in :attr:`error_types`), and the worker
    carries on with the next payload.
    """

    def __init__(
        self,
        session: zenoh.Session,
        keys: ScannerKeys,
        service: ReconstructionService,
        stop: threading.Event,
        *,
        fifo_capacity: int = 256,
        tick_s: float = 0.1,
        record: McapRecorder | None = None,
        recovery: RecoveryConfig | None = RecoveryConfig(),
        group: GroupMembership | None = None,
    ) -> None:
        if not tick_s > 0:
            raise ConfigError(f"LiveSource tick_s must be > 0 s, got {tick_s}")
        self._service = service
        # With a group, payloads of scanners another member owns are dropped before decoding (counted there).
        self._group = group
        self._keys = keys
        self._stop = stop
        self._tick_s = tick_s
        self._record = record
        # Recovered and adopted payloads.  Bounded: a full FIFO blocks their producers.
        self._queue = PayloadFifo(fifo_capacity)
        self._recovery = (
            LogRecoveryClient(session, keys, self._enqueue, recovery, wanted=service.still_wanted)
            if recovery is not None
            else None
        )
        # Bounded too: a full channel blocks Zenoh's receiving thread, and congestion control BLOCK slows the
        # publisher instead of this process growing without bound.
        self._subscriber = session.declare_subscriber(live_key(keys), zenoh.handlers.FifoChannel(fifo_capacity))
        #: key → (scanner chunk, leaf).
        self._parsed_keys: dict[str, tuple[str, str]] = {}
        self._channel = self._subscriber.handler  # read through the handler: undeclaring never waits for a reader
        #: Set while the worker is idle: the doorbell reads the channel, not the worker.
        self._armed = threading.Event()
        self._thread = threading.Thread(target=self._process, name="reconstruct", daemon=True)
        self._doorbell = threading.Thread(target=self._ring, name="reconstruct-doorbell", daemon=True)
        self.errors = 0
        self.error_types: Counter[str] = Counter()
        #: Samples the doorbell handed over (each one woke an idle worker).
        self.rings = 0
        #: Where the finals are estimated, off this source's thread (None: on it).
        workers = service.config.final_workers
        self._workers = auto_workers() if workers is None else workers
        self._pool: FinalPool | None = None
        self._finals_called = threading.Event()  # a _FINALS item waits in the FIFO

    @property
    def recovery_stats(self) -> dict[str, int]:
        return dict(self._recovery.stats) if self._recovery is not None else {}

    def __enter__(self) -> LiveSource:
        if self._group is not None:
            self._group.attach(self._enqueue)  # adopted scans' kept ScanStart / ScanEnd go through the queue
        if self._recovery is not None:
            self._recovery.__enter__()
            self._service.recover = self._recovery.request
            # Past its attempts, a scan asks on while its acquirer's log may still answer.
            self._service.recovery_policy = dataclasses.replace(
                self._service.recovery_policy, log_may_answer=self._recovery.may_answer
            )
        # Live, a provisional estimate due on a sample that waited too long is stale (a replay's never is).
        self._service.wall_ns = time.time_ns
        if self._workers:
            # Room for a job per scan the service holds, beside the pool's own: the provisional exact fits of
            # scanners in step come due together, and one that finds no room waits for a tick.
            capacity = 2 * self._workers + 2 + self._service.config.max_scans
            self._pool = FinalPool(self._workers, capacity=capacity, on_ready=self._finals_ready)
            self._service.use_pool(self._pool)
        self._thread.start()
        self._doorbell.start()
        return self

    def __exit__(self, *exc_info) -> None:
        self._stop.set()
        self._armed.set()  # a doorbell not armed returns, an armed one ...
        self._subscriber.undeclare()  # ... is woken: undeclaring closes the channel
        if self._group is not None:
            self._group.attach(None)
        if self._recovery is not None:
            self._service.recover = None
            self._service.recovery_policy = dataclasses.replace(self._service.recovery_policy, log_may_answer=None)
            self._recovery.close()
        if not self._queue.put_nowait(_STOP):
            pass  # full: the processing thread sees the stop flag within one payload
        self._thread.join(timeout=5)
        self._doorbell.join(timeout=5)
        self._service.wall_ns = None
        if self._pool is not None:
            try:
                for msg in self._service.use_pool(None):  # the finals on their way: published before the source ends
                    self._record_estimate(msg)
            finally:
                self._pool.close()

    def _finals_ready(self) -> None:
        """The pool's hook (its thread): wake the processing thread, once per wait, to publish what came back."""
        if not self._finals_called.is_set():
            self._finals_called.set()
            if not self._queue.put_nowait(_FINALS):
                self._finals_called.clear()  # full: the worker is busy, and collects after each payload anyway

    def _received(self, sample: zenoh.Sample) -> tuple[str, zenoh.ZBytes, str, str] | None:
        """A live sample as a work item, or None if it is not this worker's (or not a sample or scan event)."""
        try:
            key = str(sample.key_expr)
            parsed = self._parsed_keys.get(key)
            if parsed is None:  # parsed once per key, not per payload
                if len(self._parsed_keys) >= _MAX_PARSED_KEYS:
                    self._parsed_keys.clear()  # keys are wire data: the cache stays bounded
                parsed = self._parsed_keys[key] = (self._keys.scanner_chunk(key), key.rpartition("/")[2])
            scanner, leaf = parsed
            if leaf not in LIVE_LEAVES:
                self.error_types[f"ignored: key neither {' nor '.join(LIVE_LEAVES)}"] += 1
                return None  # the wildcard also covers other leaves beginning with "s"
            encoding = str(sample.encoding)
            if self._group is not None and not self._group.admit(scanner, leaf, encoding, sample.payload):
                return None  # another member's scanner: dropped before decoding, counted by the group
            # The scanner id in the key must be the payload's (checked in ingest): a publisher cannot
            # speak for another scanner.  The ZBytes is copied to bytes once, when it is handled.
            return encoding, sample.payload, "live", scanner
        except Exception:  # noqa: BLE001 - one bad sample must not stop the worker: counted, logged
            self.errors += 1
            self.error_types["receive"] += 1
            _log.exception("could not take a received payload; counted")
            return None

    def _enqueue(
        self, encoding: str, payload: bytes | zenoh.ZBytes, origin: str, key_scanner: str | None = None
    ) -> None:
        # key_scanner is None for recovered payloads: the recovery client checked them against the key it asked.
        if origin != "live":
            encoding = f"application/protobuf;{encoding}"  # recovery hands over the type name
        while not self._stop.is_set():
            if self._queue.put((encoding, payload, origin, key_scanner), timeout=self._tick_s):
                return

    def _ring(self) -> None:
        """The doorbell: while the worker is idle, wait for a sample and hand it over.

        The channel is the worker's again once it has that sample."""
        try:
            while self._armed.wait() and not self._stop.is_set():
                sample = self._channel.recv()  # waits with the GIL released
                self._armed.clear()  # before the hand-over: the worker reads the channel once it has this sample
                while not self._stop.is_set() and not self._queue.put(sample, timeout=self._tick_s):
                    pass
        except zenoh.ZError:
            return  # the channel is closed: the source is closing

    def _pull(self, pending: deque, channel: bool) -> None:
        """Append what waits, without waiting: up to a batch from the channel (if the worker reads it), then
        the FIFO's."""
        if channel:
            try:
                for _ in range(self._queue.batch):
                    sample = self._channel.try_recv()
                    if sample is None:
                        break
                    item = self._received(sample)
                    if item is not None:
                        pending.append(item)
            except zenoh.ZError:  # the channel is closed: the source is closing
                self._stop.set()
        if len(self._queue):
            pending.extend(self._queue.take(0))

    def _process(self) -> None:
        last_tick = 0.0
        pending: deque = deque()
        reading = True  # the worker reads the channel (False while the doorbell is armed)
        while not self._stop.is_set():
            if not pending:
                self._pull(pending, reading)
                if not pending:  # idle: the doorbell watches the channel, the worker waits on the FIFO
                    if reading:
                        reading = False
                        self._armed.set()
                    pending.extend(self._queue.take(self._tick_s))
            waiting = 0
            if pending:
                item = pending.popleft()
                if item is _STOP:
                    return
                if item is _FINALS:
                    self._finals_called.clear()
                    self._guarded(self._service.collect)
                    item = None
                if isinstance(item, zenoh.Sample):  # the doorbell's: it has stopped reading the channel
                    reading = True
                    self.rings += 1
                    item = self._received(item)
                if not pending:
                    self._pull(pending, reading)  # so that `waiting` says whether more came in
                # Payloads still waiting: pulled, and what the FIFO holds.
                waiting = len(pending) + len(self._queue)
                self._apply(item, waiting)
            now = time.monotonic()
            # tick() visits every open scan: once per tick_s (with many open scans a tick costs a fair share
            # of what a payload does); what waited for the backlog is caught up as soon as the queue drains.
            if now - last_tick >= self._tick_s:
                last_tick = now
                self._guarded(self._service.tick, busy=waiting > 0)
            elif self._service.has_deferred and not waiting:
                self._guarded(self._service.catch_up)

    def _apply(self, item: tuple[str, bytes | zenoh.ZBytes, str, str | None] | None, waiting: int) -> None:
        if item is not None:
            # Behind a short backlog a provisional refit runs now, its exact fits wait; behind a long one it waits.
            self._guarded(
                self._handle, *item, busy=waiting > self._service.config.provisional_backlog, fits_wait=waiting > 0
            )

    def _handle(
        self,
        encoding: str,
        payload: bytes | zenoh.ZBytes,
        origin: str,
        key_scanner: str | None,
        *,
        busy: bool,
        fits_wait: bool,
    ) -> list[codec.Reconstruction]:
        if not isinstance(payload, bytes) and len(payload) <= self._service.config.limits.max_payload_bytes:
            payload = payload.to_bytes()  # a live payload's ZBytes, copied once (a larger one is refused uncopied)
        media, _, type_name = encoding.partition(";")
        return self._service.handle(
            type_name if media == "application/protobuf" else encoding,
            cast(bytes, payload),  # or a ZBytes over the decode limit: ingest refuses it by its length, uncopied
            busy=busy,
            fits_wait=fits_wait,
            origin=origin,
            key_scanner=key_scanner,
        )

    def _guarded(self, step: Callable[..., list[codec.Reconstruction]], *args, **kwargs) -> None:
        """Run one step of the service and record its estimates; an exception is logged and counted, never fatal."""
        try:
            for msg in step(*args, **kwargs):
                self._record_estimate(msg)
        except LelsonarError as exc:  # e.g. a publish that failed validation: log, count, keep serving
            self.errors += 1
            self.error_types[type(exc).__name__] += 1
            _log.error("processing failed: %s", exc)
        except Exception as exc:  # noqa: BLE001 - a bug must not end the service silently: log, count, go on
            self.errors += 1
            self.error_types[type(exc).__name__] += 1
            _log.exception(
                "processing failed with an unexpected %s (%d errors so far); carrying on",
                type(exc).__name__,
                self.errors,
            )

    def _record_estimate(self, msg: codec.Reconstruction) -> None:
        if self._record is not None:
            self._record.write(msg)
