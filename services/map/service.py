"""The mapper: one scanner's map kept from its scans' starts and final estimates, one update per scan.

:class:`MapperService` is the logic (no transport): a scan's ``ScanStart`` gives its pose, its terminal
``Reconstruction`` its walls; each terminal estimate is one :meth:`~lelsonar.map.fusion.WallMapper.add_scan`,
and the map is published after it.  Fed the same scans in the same order, it gives the map that
``lelsonar map --source`` prints.

:class:`ZenohMapper` is the transport: it listens on ``<prefix>/<scanner>/scan`` and
``<prefix>/<scanner>/planes``, publishes each map on ``<prefix>/map`` (a ``get`` there returns the
latest), and, where asked, records the maps to MCAP.  One worker thread handles the messages in order;
what it cannot handle is counted and logged, and the worker goes on.
"""

from __future__ import annotations

import logging
import queue
import threading
from collections import Counter, OrderedDict
from collections.abc import Callable
from pathlib import Path

import zenoh
from mcap_protobuf.writer import Writer

from lelsonar import codec
from lelsonar.draw.map_scene import TOPIC_MAP_SCENE, MapScene
from lelsonar.errors import LelsonarError
from lelsonar.keys import ScannerKeys, validate_prefix
from lelsonar.map.floorplan import free_space
from lelsonar.map.from_reconstruction import scan_from_reconstruction
from lelsonar.map.fusion import FusionConfig, WallMapper
from lelsonar.map.result import FusedMap
from lelsonar.map.wire import map_message
from lelsonar.reconstruct.estimate import wire
from lelsonar.v1 import map_pb2

_log = logging.getLogger("lelsonar.mapper")

#: Topic of the maps in an MCAP recording.
MAP_TOPIC = "/lelsonar/map"


def map_key(prefix: str) -> str:
    """The key the map is published on, ``<prefix>/map``."""
    return f"{validate_prefix(prefix)}/map"


class MapperService:
    """One scanner's map (see the module docstring).

    Parameters
    ----------
    scanner_id : str
        The scanner whose scans are fused (one robot: one map).
    method : str
        The estimator of record whose planes are the walls.
    publish : callable
        Called with each new ``Map``.
    max_starts : int
        ``ScanStart`` messages kept while their estimates are awaited (the oldest forgotten first).
    """

    def __init__(
        self,
        scanner_id: str,
        method: str,
        publish: Callable[[map_pb2.Map], None] | None = None,
        config: FusionConfig | None = None,
        max_starts: int = 256,
    ) -> None:
        self.scanner_id = scanner_id
        self.method = method
        self.mapper = WallMapper(config)
        self._publish = publish
        self._starts: OrderedDict[int, codec.ScanStart] = OrderedDict()
        self._max_starts = max_starts
        self._mapped: set[int] = set()
        self._pending: OrderedDict[int, codec.Reconstruction] = OrderedDict()  # finals awaiting their start
        self.latest: map_pb2.Map | None = None
        self.fused: FusedMap | None = None  # the fusion's map behind ``latest`` (its free space, for viewers)
        self.ignored: Counter[str] = Counter()

    def handle_start(self, start: codec.ScanStart) -> map_pb2.Map | None:
        """Keep a scan's start for its estimate; an estimate that came first is fused now."""
        if start.scanner_id != self.scanner_id:
            self.ignored["another scanner's scan"] += 1
            return None
        self._starts[start.scan_id] = start
        while len(self._starts) > self._max_starts:
            self._starts.popitem(last=False)
            self.ignored["scan start forgotten before its estimate (max_starts)"] += 1
        if start.scan_id in self._pending:
            return self._fuse_up_to(start.scan_id)
        return None

    def handle_estimate(self, msg: codec.Reconstruction) -> map_pb2.Map | None:
        """Fuse a terminal estimate (provisional ones wait for theirs); returns the new map, if any.

        An estimate whose scan's start has not come yet waits for it (the two travel on different keys),
        until its start comes or a later scan's estimate is fused: then it goes in at the origin, and the
        map's notes say so.
        """
        if msg.scanner_id != self.scanner_id:
            self.ignored["another scanner's estimate"] += 1
            return None
        if not wire.is_terminal(msg):
            return None
        if msg.scan_id in self._mapped or msg.scan_id in self._pending:
            self.ignored["estimate of a scan already mapped"] += 1
            return None
        self._pending[msg.scan_id] = msg
        if msg.scan_id not in self._starts:
            return None
        return self._fuse_up_to(msg.scan_id)

    def flush(self) -> map_pb2.Map | None:
        """Fuse every estimate still waiting for its start (at the end of a run)."""
        if not self._pending:
            return None
        return self._fuse_up_to(max(self._pending))

    def _fuse_up_to(self, scan_id: int) -> map_pb2.Map | None:
        """Fuse the waiting estimates of scans up to ``scan_id``, in scan order; publish the map once."""
        ready = sorted(k for k in self._pending if k <= scan_id)
        for k in ready:
            self._fuse(self._pending.pop(k))
        self.fused = self.mapper.snapshot()
        self.latest = map_message(self.fused, self.scanner_id)
        if self._publish is not None:
            self._publish(self.latest)
        return self.latest

    def _fuse(self, msg: codec.Reconstruction) -> None:
        scan = scan_from_reconstruction(msg, self._starts.pop(msg.scan_id, None), self.method)
        self._mapped.add(msg.scan_id)
        self.mapper.add_scan(scan)


class ZenohMapper:
    """The mapper on Zenoh (see the module docstring); a context manager that stops its worker on exit."""

    def __init__(
        self,
        session: zenoh.Session,
        prefix: str,
        service: MapperService,
        *,
        record: Path | None = None,
        on_map: Callable[[map_pb2.Map], None] | None = None,
    ) -> None:
        self._session = session
        self._service = service
        self._keys = ScannerKeys(prefix, service.scanner_id)
        self._key = map_key(prefix)
        self._on_map = on_map
        self._queue: queue.Queue = queue.Queue(maxsize=4096)
        self.errors: Counter[str] = Counter()
        self._writer = None
        self._file = None
        if record is not None:
            self._file = open(record, "wb")  # closed by close(), after the writer has finished it
            self._writer = Writer(self._file)
        self._scene = MapScene()  # the recorded map as Foxglove draws it
        self._publisher = session.declare_publisher(
            self._key, encoding=zenoh.Encoding(f"application/protobuf;{map_pb2.Map.DESCRIPTOR.full_name}")
        )
        self._queryable = session.declare_queryable(self._key, self._answer)
        self._subscribers = [
            session.declare_subscriber(self._keys.scan, self._enqueue),
            session.declare_subscriber(self._keys.planes, self._enqueue),
        ]
        service._publish = self._published
        self._worker = threading.Thread(target=self._run, name="mapper", daemon=True)
        self._worker.start()

    def __enter__(self) -> ZenohMapper:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def _enqueue(self, sample: zenoh.Sample) -> None:
        try:
            self._queue.put_nowait((str(sample.key_expr), sample.payload.to_bytes(), str(sample.encoding)))
        except queue.Full:
            self.errors["queue full: message dropped"] += 1

    def _answer(self, query: zenoh.Query) -> None:
        latest = self._service.latest
        if latest is not None:
            query.reply(self._key, latest.SerializeToString(), encoding=self._publisher.encoding)

    def _published(self, msg: map_pb2.Map) -> None:
        self._publisher.put(msg.SerializeToString())
        if self._writer is not None:
            self._writer.write_message(MAP_TOPIC, msg, log_time=msg.stamp_ns, publish_time=msg.stamp_ns)
            fused = self._service.fused
            scene = self._scene.update(msg, free_space=None if fused is None else free_space(fused))
            self._writer.write_message(TOPIC_MAP_SCENE, scene, log_time=msg.stamp_ns, publish_time=msg.stamp_ns)
        if self._on_map is not None:
            self._on_map(msg)

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:  # close(): everything received before it is handled
                return
            key, payload, encoding = item
            try:
                if key.endswith("/planes"):
                    self._service.handle_estimate(wire.decode_estimate(key, payload, self._keys.prefix))
                else:
                    msg = codec.decode(payload, codec.type_from_encoding(encoding))
                    if isinstance(msg, codec.ScanStart):
                        self._service.handle_start(msg)
            except LelsonarError as exc:
                self.errors[type(exc).__name__] += 1
                _log.warning("mapper: %s on %s: %s", type(exc).__name__, key, exc)
            except Exception:  # the worker must not die: count it, log it with its traceback, go on
                self.errors["unexpected"] += 1
                _log.exception("mapper: unexpected error on %s", key)

    def close(self) -> None:
        for sub in self._subscribers:
            sub.undeclare()
        self._queue.put(None)
        self._worker.join()
        try:
            self._service.flush()
        except LelsonarError as exc:
            self.errors[type(exc).__name__] += 1
            _log.warning("mapper: %s while fusing the last estimates: %s", type(exc).__name__, exc)
        self._queryable.undeclare()
        self._publisher.undeclare()
        if self._writer is not None:
            self._writer.finish()
        if self._file is not None:
            self._file.close()
