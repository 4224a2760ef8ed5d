"""Serve what ``acquire`` recorded: ``get <prefix>/<scanner>/log/<scan_id>?steps=A-B;start=1;end=1``.

Whoever writes the log serves it.  The scan loop hands every message to the
recorder first; :class:`ScanLog` then keeps the very bytes it recorded, per
scan, and :class:`LogServer` answers queries for them, so a reconstructor that
missed steps (a partition, a late start, a lost ScanEnd) recovers them from
the acquirer's own record instead of publishing a partial scan as final.

Why memory and not the MCAP file: the file of the scan in progress is not
readable until it is finished (chunks, then the summary), and reading it back
per query would cost a decompression per chunk.  The copy is bounded: at most
``max_scans`` scans and ``max_bytes`` bytes; a scan that ended more than
``keep_for`` seconds ago is dropped.  Every drop is counted by reason.

Queries (see :mod:`lelsonar.keys`): ``steps=A-B`` asks for the samples of steps
A..B inclusive (at most ``MAX_LOG_STEPS_PER_QUERY``), ``start=1`` for the
ScanStart, ``end=1`` for the ScanEnd.  One reply per message, on the concrete
key, the type in the encoding.  Queries are answered on a worker thread, not in
Zenoh's callback.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter, OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field

import zenoh
from google.protobuf.message import Message

from lelsonar import codec
from lelsonar.errors import ConfigError, LelsonarError
from lelsonar.keys import LOG_NOT_HELD_ENCODING, MAX_LOG_STEPS_PER_QUERY, ScannerKeys
from lelsonar.v1 import reconstruction_pb2

_log = logging.getLogger(__name__)

#: Reconstructors and settled scans remembered by :class:`Receipts` (keys are wire data: bounded).
_MAX_RECEIPTS = 1024


@dataclass
class _ScanRecord:
    start: bytes | None = None
    samples: dict[int, bytes] = field(default_factory=dict)
    end: bytes | None = None
    ended_at: float | None = None
    size: int = 0


class ScanLog:
    """The recorded payloads of the last scans of one scanner, by scan id and step (thread-safe)."""

    def __init__(
        self,
        *,
        max_scans: int = 8,
        max_bytes: int = 256 * 1024 * 1024,
        keep_for: float = 60.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if max_scans < 1 or max_bytes < 1 or keep_for < 0:
            raise ConfigError("ScanLog needs max_scans >= 1, max_bytes >= 1 and keep_for >= 0 s")
        self.max_scans, self.max_bytes, self.keep_for = max_scans, max_bytes, keep_for
        self._clock = clock
        self._lock = threading.Lock()
        self._scans: OrderedDict[int, _ScanRecord] = OrderedDict()
        self._bytes = 0
        #: What the bounds dropped, by reason.
        self.evicted: Counter[str] = Counter()

    def add(self, message: codec.ScanMessage, payload: bytes | None = None) -> None:
        """Keep one recorded message (``payload``: its bytes as recorded; serialised if not given)."""
        data = payload if payload is not None else message.SerializeToString()
        with self._lock:
            rec = self._scans.get(message.scan_id)
            if rec is None:
                rec = self._scans[message.scan_id] = _ScanRecord()
            if isinstance(message, codec.ScanStart):
                rec.start = data
            elif isinstance(message, codec.Sample):
                old = rec.samples.get(message.step)
                rec.size -= len(old) if old else 0
                self._bytes -= len(old) if old else 0
                rec.samples[message.step] = data
            elif isinstance(message, codec.ScanEnd):
                rec.end = data
                rec.ended_at = self._clock()
            else:
                return
            rec.size += len(data)
            self._bytes += len(data)
            self._enforce(keep=message.scan_id)

    def lookup(
        self, scan_id: int, steps: tuple[int, int] | None, start: bool, end: bool
    ) -> list[tuple[type[Message], bytes]] | None:
        """The recorded messages asked for, ScanStart first; None if the scan is not (or no longer) held."""
        with self._lock:
            self._enforce()
            rec = self._scans.get(scan_id)
            if rec is None:
                return None
            out: list[tuple[type[Message], bytes]] = []
            if start and rec.start is not None:
                out.append((codec.ScanStart, rec.start))
            if steps is not None:
                out += [(codec.Sample, rec.samples[s]) for s in range(steps[0], steps[1] + 1) if s in rec.samples]
            if end and rec.end is not None:
                out.append((codec.ScanEnd, rec.end))
            return out

    @property
    def scan_ids(self) -> list[int]:
        with self._lock:
            return list(self._scans)

    def _enforce(self, keep: int | None = None) -> None:
        now = self._clock()
        for sid, rec in list(self._scans.items()):
            if rec.ended_at is not None and now - rec.ended_at > self.keep_for and sid != keep:
                self._drop(sid, "ended longer ago than keep_for")
        while len(self._scans) > self.max_scans:
            self._drop(next(iter(self._scans)), "more scans than max_scans")
        while self._bytes > self.max_bytes and len(self._scans) > 1:
            self._drop(next(iter(self._scans)), "more bytes than max_bytes")

    def _drop(self, scan_id: int, reason: str) -> None:
        rec = self._scans.pop(scan_id)
        self._bytes -= rec.size
        self.evicted[reason] += 1
        _log.info("log server: no longer serving scan %d (%s)", scan_id, reason)


def parse_parameters(params: zenoh.Parameters | str) -> tuple[tuple[int, int] | None, bool, bool]:
    """``steps=A-B;start=1;end=1`` → ((A, B) or None, start, end).

    Raises
    ------
    ConfigError
        A malformed range, or more than ``MAX_LOG_STEPS_PER_QUERY`` steps.
    """
    if isinstance(params, str):
        params = zenoh.Parameters(params)
    steps = params.get("steps")
    rng = None
    if steps:
        first, sep, last = steps.partition("-")
        if not (sep and first.isdigit() and last.isdigit() and len(first) <= 10 and len(last) <= 10):
            raise ConfigError(f"steps={steps[:40]!r}: expected steps=FIRST-LAST, e.g. steps=40-73")
        rng = (int(first), int(last))
        if rng[1] < rng[0] or rng[1] - rng[0] + 1 > MAX_LOG_STEPS_PER_QUERY:
            raise ConfigError(f"steps={steps}: ask for 1 to {MAX_LOG_STEPS_PER_QUERY} steps, FIRST <= LAST")
    flag = {"1": True, "true": True, "0": False, "false": False, None: False}
    start, end = params.get("start"), params.get("end")
    if start not in flag or end not in flag:
        raise ConfigError("start= and end= take 1 or 0")
    return rng, flag[start], flag[end]


class Receipts:
    """Whether a reconstructor may still need the log of a scan (so ``acquire`` keeps serving it).

    A reconstructor declares ``<prefix>/<scanner>/alive/reconstruct`` and publishes its estimates on
    ``<prefix>/<scanner>/planes``.  A scan is *settled* once a terminal estimate of it is heard.  An
    unsettled scan is still wanted while a reconstructor is alive, or was lost less than ``lost_grace``
    seconds ago (a partition drops its token after the lease; it may come back and ask).  Runs short
    callbacks on Zenoh's threads: one per liveliness change, one per estimate.
    """

    def __init__(
        self,
        session: zenoh.Session,
        keys: ScannerKeys,
        *,
        lost_grace: float = 30.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._scanner = keys.scanner_id
        self.lost_grace = lost_grace
        self._clock = clock
        self._lock = threading.Lock()
        self._alive: OrderedDict[str, None] = OrderedDict()  # token keys present (bounded: wire data)
        self._lost_at: float | None = None
        self._settled: OrderedDict[int, None] = OrderedDict()
        self._entities = [
            session.liveliness().declare_subscriber(keys.alive("reconstruct"), self._token, history=True),
            session.declare_subscriber(keys.planes, self._estimate),
        ]

    def _token(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)[:300]
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self._alive[key] = None
                while len(self._alive) > _MAX_RECEIPTS:
                    self._alive.popitem(last=False)
            elif self._alive.pop(key, 0) is None:
                self._lost_at = self._clock()

    def _estimate(self, sample: zenoh.Sample) -> None:
        try:
            msg = codec.decode(sample.payload.to_bytes(), codec.Reconstruction)
        except LelsonarError:
            return  # not an estimate we can read: it settles nothing
        if msg.scanner_id != self._scanner or msg.status == reconstruction_pb2.ESTIMATE_STATUS_PROVISIONAL:
            return
        with self._lock:
            self._settled[int(msg.scan_id)] = None
            while len(self._settled) > _MAX_RECEIPTS:
                self._settled.popitem(last=False)

    def wanted(self, scan_id: int) -> bool:
        """Whether scan ``scan_id`` may still be asked for (see the class)."""
        with self._lock:
            if scan_id in self._settled:
                return False
            if self._alive:
                return True
            return self._lost_at is not None and self._clock() - self._lost_at < self.lost_grace

    def close(self) -> None:
        for entity in self._entities:
            try:
                entity.undeclare()
            except zenoh.ZError as exc:
                _log.warning("log server: undeclaring a receipts subscriber failed: %s", exc)


class LogServer:
    """Answers log queries of one scanner from a :class:`ScanLog`, on a worker thread.

    Use as a context manager inside an open session.
    """

    def __init__(self, session: zenoh.Session, keys: ScannerKeys, log: ScanLog) -> None:
        self._keys = keys
        self._log = log
        self._queryable = session.declare_queryable(keys.log("*"), zenoh.handlers.FifoChannel(64))
        self._thread = threading.Thread(target=self._serve, name="log-server", daemon=True)
        #: Queries answered, replies sent, queries refused by reason.
        self.stats: Counter[str] = Counter()

    def __enter__(self) -> LogServer:
        self._thread.start()
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def close(self) -> None:
        try:
            self._queryable.undeclare()  # ends the worker's iteration
        except zenoh.ZError as exc:
            _log.warning("log server: undeclaring the queryable failed: %s", exc)
        self._thread.join(timeout=5)

    def _serve(self) -> None:
        try:
            for query in self._queryable:
                with query:  # leaving the block ends the query: the querier's get returns
                    try:
                        self._answer(query)
                    except Exception:  # noqa: BLE001 - one bad query must not stop the server
                        self.stats["errors"] += 1
                        _log.exception("log server: answering %s failed; carrying on", query.selector)
        except zenoh.ZError:
            pass  # undeclared at shutdown

    def _answer(self, query: zenoh.Query) -> None:
        key = str(query.key_expr)
        try:
            scanner, scan_id = self._keys.scan_of_log_key(key)
            if scanner != self._keys.scanner_id:
                raise ConfigError(f"this acquirer serves scanner {self._keys.scanner_id!r}, not {scanner!r}")
            rng, start, end = parse_parameters(query.parameters)
        except LelsonarError as exc:
            self.stats["refused: bad query"] += 1
            query.reply_err(f"bad log query {str(query.selector)[:200]!r}: {exc}")
            return
        found = self._log.lookup(scan_id, rng, start, end)
        if found is None:
            self.stats["refused: scan not held"] += 1
            query.reply_err(
                f"scan {scan_id} is not (or no longer) in the log of {scanner}; held: "
                f"{self._log.scan_ids[-8:]} (acquire --serve-log-for keeps ended scans longer)",
                encoding=zenoh.Encoding(LOG_NOT_HELD_ENCODING),
            )
            return
        self.stats["queries"] += 1
        for cls, payload in found:
            # (Zenoh 1.10 ignores a congestion control on replies; they follow the queryable's defaults.)
            query.reply(key, payload, encoding=zenoh.Encoding(codec.encoding_name(cls())))
            self.stats["replies"] += 1
