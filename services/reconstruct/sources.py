"""Where payloads come from — a Zenoh subscription or an MCAP file — and where estimates go.

Both sources hand (type name, payload bytes) to the same
:meth:`ReconstructionService.handle`.  Zenoh callbacks never do the math: FIFO
subscribers are drained by worker threads into one queue, and one processing
thread applies it, so a slow fit back-pressures through the FIFO instead of
stalling Zenoh's own threads.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from pathlib import Path

import zenoh

from lelsonar import codec
from lelsonar.errors import LelsonarError
from lelsonar.keys import ScannerKeys, validate_identifier
from lelsonar.recording import McapRecorder, iter_payloads
from lelsonar.reconstruct.service import ReconstructionService

_log = logging.getLogger(__name__)

_STOP = ("", b"")  # queue sentinel


def replay_mcap(path: Path | str, service: ReconstructionService,
                on_payload: Callable[[int], None] | None = None) -> int:
    """Feed a recording through the service in log-time order, then finalise open scans.

    Returns the number of payloads read.
    """
    n = 0
    for rec in iter_payloads(path):
        if rec.type_name == codec.Reconstruction.DESCRIPTOR.full_name:
            continue  # earlier outputs in the file are not inputs
        service.handle(rec.type_name, rec.payload)
        n += 1
        if on_payload is not None:
            on_payload(rec.log_time_ns)
    service.finish()
    return n


class PlanesServer:
    """Publishes estimates on ``<prefix>/<scanner>/planes``; a ``get`` there returns the latest."""

    def __init__(self, session: zenoh.Session, keys: ScannerKeys, latest: dict[str, codec.Reconstruction]) -> None:
        self._session = session
        self._keys = keys
        self._latest = latest
        self._lock = threading.Lock()
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._queryable = session.declare_queryable(keys.planes, self._answer)

    def publish(self, message: codec.Reconstruction) -> None:
        scanner = validate_identifier(message.scanner_id)
        with self._lock:
            pub = self._publishers.get(scanner)
            if pub is None:
                pub = self._session.declare_publisher(
                    ScannerKeys(self._keys.prefix, scanner).planes, congestion_control=zenoh.CongestionControl.BLOCK,
                    encoding=zenoh.Encoding(codec.encoding_name(message)))
                self._publishers[scanner] = pub
        pub.put(message.SerializeToString())

    def _answer(self, query: zenoh.Query) -> None:
        asked = query.key_expr
        with self._lock:
            latest = list(self._latest.items())
        for scanner, message in latest:
            key = ScannerKeys(self._keys.prefix, scanner).planes
            if zenoh.KeyExpr(key).intersects(asked):
                query.reply(key, message.SerializeToString(), encoding=zenoh.Encoding(codec.encoding_name(message)))

    def close(self) -> None:
        self._queryable.undeclare()
        for pub in self._publishers.values():
            pub.undeclare()


class LiveSource:
    """Subscribes to samples and scan events and feeds them to the service on one thread.

    Use as a context manager inside an open session; :meth:`join` returns when
    ``stop`` is set.
    """

    def __init__(self, session: zenoh.Session, keys: ScannerKeys, service: ReconstructionService,
                 stop: threading.Event, *, fifo_capacity: int = 256, tick_s: float = 0.1,
                 record: McapRecorder | None = None) -> None:
        self._service = service
        self._keys = keys
        self._stop = stop
        self._tick_s = tick_s
        self._record = record
        # Bounded: a full queue blocks the drain threads, the FIFOs fill, and Zenoh's BLOCK
        # congestion control slows the publisher instead of this process growing without bound.
        self._queue: queue.Queue[tuple[str, bytes] | tuple[str, bytes, str]] = queue.Queue(maxsize=fifo_capacity)
        self._subscribers = [
            session.declare_subscriber(keys.sample, zenoh.handlers.FifoChannel(fifo_capacity)),
            session.declare_subscriber(keys.scan, zenoh.handlers.FifoChannel(64)),
        ]
        self._threads = [threading.Thread(target=self._drain, args=(s,), name=f"drain-{i}", daemon=True)
                         for i, s in enumerate(self._subscribers)]
        self._threads.append(threading.Thread(target=self._process, name="reconstruct", daemon=True))
        self.errors = 0

    def __enter__(self) -> LiveSource:
        for t in self._threads:
            t.start()
        return self

    def __exit__(self, *exc_info) -> None:
        self._stop.set()
        for s in self._subscribers:
            s.undeclare()  # ends the drain threads' recv()
        try:
            self._queue.put_nowait(_STOP)
        except queue.Full:
            pass  # the processing thread sees the stop flag within one tick
        for t in self._threads:
            t.join(timeout=5)

    def _drain(self, subscriber: zenoh.Subscriber) -> None:
        try:
            for sample in subscriber:
                self._queue.put((str(sample.encoding), sample.payload.to_bytes(), str(sample.key_expr)))
        except zenoh.ZError:
            pass  # undeclared during shutdown

    def _process(self) -> None:
        last_tick = 0.0
        while not self._stop.is_set():
            try:
                item = self._queue.get(timeout=self._tick_s)
            except queue.Empty:
                item = None
            if item == _STOP:
                return
            try:
                if item is not None:
                    media, _, type_name = item[0].partition(";")
                    # With more payloads waiting, a provisional refit waits for them too.
                    for msg in self._service.handle(type_name if media == "application/protobuf" else item[0],
                                                    item[1], busy=not self._queue.empty(),
                                                    key_scanner=self._keys.scanner_chunk(item[2])):
                        self._record_estimate(msg)
                now = time.monotonic()
                if self._queue.empty() or now - last_tick >= self._tick_s:
                    last_tick = now
                    for msg in self._service.tick():
                        self._record_estimate(msg)
            except LelsonarError as exc:  # e.g. a publish that failed validation: log, count, keep serving
                self.errors += 1
                _log.error("processing failed: %s", exc)

    def _record_estimate(self, msg: codec.Reconstruction) -> None:
        if self._record is not None:
            self._record.write(msg)
