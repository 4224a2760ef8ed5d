"""A hermetic live rig for the gap-recovery tests: a hub, an acquirer side that records to a
served log and publishes (with chosen steps left out), and a reconstructor (LiveSource)."""

from __future__ import annotations

import threading
from collections.abc import Iterable
from contextlib import ExitStack

import zenoh

from lelsonar import codec
from lelsonar.acquire.log_server import LogServer, ScanLog
from lelsonar.acquire.scan_loop import ScanPublisher
from lelsonar.keys import ScannerKeys
from lelsonar.net.transport import hermetic_settings, open_session
from lelsonar.reconstruct.estimate import wire
from lelsonar.reconstruct.stream.config import ReconstructConfig
from lelsonar.reconstruct.stream.recovery import RecoveryConfig
from lelsonar.reconstruct.stream.service import ReconstructionService
from lelsonar.reconstruct.stream.sources import LiveSource

PREFIX = "lelsonar"


def renamed(messages: Iterable, scanner_id: str) -> list:
    """Copies of a scan's messages for another scanner."""
    out = []
    for m in messages:
        c = type(m)()
        c.CopyFrom(m)
        c.scanner_id = scanner_id
        out.append(c)
    return out


class Acquirer:
    """What `acquire` does with each message: record it (the served log), then publish it."""

    def __init__(self, session: zenoh.Session, scanner_id: str, log: ScanLog | None = None) -> None:
        self.keys = ScannerKeys(PREFIX, scanner_id)
        self.log = log if log is not None else ScanLog()
        self.server = LogServer(session, self.keys, self.log).__enter__()
        self.publisher = ScanPublisher(session, self.keys)

    def send(
        self,
        messages: Iterable,
        *,
        unpublished: set[int] = frozenset(),
        unrecorded: set[int] = frozenset(),
        events: bool = True,
    ) -> None:
        """Record then publish; steps in ``unpublished`` are only recorded (lost on the way), steps in
        ``unrecorded`` only published.  ``events=False`` leaves ScanStart/ScanEnd unpublished."""
        for m in messages:
            step = m.step if isinstance(m, codec.Sample) else None
            if step not in unrecorded:
                self.log.add(m)
            if (step is None and events) or (step is not None and step not in unpublished):
                self.publisher.publish(m)

    def close(self) -> None:
        self.publisher.close()
        self.server.close()


class Rig:
    """Hub + acquirer session + reconstructor session, on one unix socket."""

    def __init__(
        self,
        socket_path,
        config: ReconstructConfig = ReconstructConfig(provisional=False),
        recovery: RecoveryConfig | None = RecoveryConfig(query_timeout=2.0),
        expect: int = 1,
    ) -> None:
        self.stack = ExitStack()
        self.socket_path = socket_path
        self.config = config
        self.recovery = recovery
        self.terminal: list[codec.Reconstruction] = []
        self.done = threading.Event()
        self.expect = expect
        self._lock = threading.Lock()
        self.live: LiveSource | None = None
        self.service: ReconstructionService | None = None

    def __enter__(self) -> Rig:
        self.hub = self.stack.enter_context(open_session(hermetic_settings(self.socket_path, listen=True)))
        self.acq_session = self.stack.enter_context(open_session(hermetic_settings(self.socket_path, listen=False)))
        return self

    def __exit__(self, *exc) -> None:
        self.stack.close()

    def collect(self, msg: codec.Reconstruction) -> None:
        if wire.is_terminal(msg):
            with self._lock:
                self.terminal.append(msg)
                if len(self.terminal) >= self.expect:
                    self.done.set()

    def start_reconstructor(self, service: ReconstructionService | None = None) -> ReconstructionService:
        """Start the LiveSource and wait until the acquirer's session sees it (its token)."""
        session = self.stack.enter_context(open_session(hermetic_settings(self.socket_path, listen=False)))
        self.service = service or ReconstructionService(self.config, publish=self.collect)
        self.stop = threading.Event()
        self.live = self.stack.enter_context(
            LiveSource(session, ScannerKeys(PREFIX, "*"), self.service, self.stop, recovery=self.recovery)
        )
        seen = threading.Event()
        sub = self.acq_session.liveliness().declare_subscriber(
            f"{PREFIX}/*/alive/reconstruct", lambda _s: seen.set(), history=True
        )
        token = session.liveliness().declare_token(ScannerKeys(PREFIX, "any").alive("reconstruct"))
        self.stack.callback(token.undeclare)
        assert seen.wait(10), "the reconstructor's declarations never reached the acquirer's session"
        sub.undeclare()
        return self.service

    def acquirer(self, scanner_id: str, log: ScanLog | None = None) -> Acquirer:
        a = Acquirer(self.acq_session, scanner_id, log)
        self.stack.callback(a.close)
        return a
