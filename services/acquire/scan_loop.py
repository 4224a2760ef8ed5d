"""The scan loop: ScanStart, one Sample per step, ScanEnd — recorded, then published.

Recording comes first and does not depend on the network: a Zenoh failure is
logged and counted, and the MCAP file stays complete.  A stop request (SIGINT,
SIGTERM) is honoured between steps: the current step finishes, ``ScanEnd``
says ``ABORTED`` with the reason, and the caller finishes the file.

Pipelining: each sample is built, recorded and published while the next shot's
capsules listen (the scanner calls ``while_listening`` during the acoustic window,
when the host has nothing else to do), and the scanner may move the servo to the
next step while the board sends the current frame.  Every sample is still recorded
before it is published, in step order, and the samples measured before a fault are
all emitted before ``ScanEnd``.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import zenoh
from google.protobuf.message import Message

from lelsonar import codec
from lelsonar.acquire import messages
from lelsonar.acquire.log_server import ScanLog
from lelsonar.acquire.scanner import Scanner, StepMeasurement
from lelsonar.energy_model import EnergyModel
from lelsonar.errors import DeviceError, RecordingError
from lelsonar.keys import ScannerKeys
from lelsonar.log.recording import McapRecorder

_log = logging.getLogger(__name__)


class ScanPublisher:
    """Puts contract messages on their Zenoh keys; samples use congestion control BLOCK.

    Counts the samples put while no subscriber matched their key (Zenoh's matching status, kept
    current by a listener): nobody received those live.  Samples lost on a link that still looked
    matched (the first seconds of a partition, before the lease expires) cannot be counted here.
    """

    def __init__(self, session: zenoh.Session, keys: ScannerKeys) -> None:
        block = zenoh.CongestionControl.BLOCK
        self._sample = session.declare_publisher(
            keys.sample, encoding=zenoh.Encoding(codec.encoding_name(codec.Sample())), congestion_control=block
        )
        # Same priority as the samples, so start, samples and end stay in order on the link.
        self._scan = session.declare_publisher(keys.scan, congestion_control=block)
        status: Any = self._sample.matching_status  # a MatchingStatus (the stubs say bool)
        self._matching = bool(status.matching)
        self._listener = self._sample.declare_matching_listener(self._matched)
        #: Samples put while no subscriber matched, since the last :meth:`take_unmatched`.
        self.unmatched = 0

    def _matched(self, status: zenoh.MatchingStatus) -> None:
        self._matching = bool(status.matching)

    def publish(self, message: Message) -> None:
        payload = message.SerializeToString()
        if isinstance(message, codec.Sample):
            self._sample.put(payload)
            if not self._matching:
                self.unmatched += 1
        else:
            self._scan.put(payload, encoding=zenoh.Encoding(codec.encoding_name(message)))

    def take_unmatched(self) -> int:
        """Samples put with no subscriber matching since the last call (then reset)."""
        n, self.unmatched = self.unmatched, 0
        return n

    def close(self) -> None:
        self._listener.undeclare()
        self._sample.undeclare()
        self._scan.undeclare()


@dataclass
class ScanOutput:
    """Where a scan's messages go: an MCAP file first, then the served log, then Zenoh.

    ``scan_log`` keeps what was recorded so :class:`~lelsonar.acquire.log_server.LogServer`
    can serve it to a reconstructor that missed it.
    """

    recorder: McapRecorder | None = None
    publisher: ScanPublisher | None = None
    publish_failures: int = 0
    scan_log: ScanLog | None = None
    #: Why recording failed (a full or read-only disk), or None.  Nothing is recorded after it.
    recording_failure: str | None = None

    def emit(self, message: codec.ScanMessage) -> None:
        """Record, keep for the log server, publish.

        Raises
        ------
        RecordingError
            The message could not be recorded (then it is not published either), except a ScanEnd: after a
            failed recording, the ScanEnd that says so is published unrecorded, so consumers learn of it.
        """
        if self.recorder is not None and self.recording_failure is None:
            try:
                self.recorder.write(message)  # returns once the step is with the OS: durable before published
            except RecordingError as exc:
                self.recording_failure = str(exc)
                if not isinstance(message, codec.ScanEnd):
                    raise
        if self.scan_log is not None:
            self.scan_log.add(message)
        if self.publisher is not None:
            try:
                self.publisher.publish(message)
            except zenoh.ZError as exc:  # the network is down: the file still has it
                self.publish_failures += 1
                _log.warning("publish failed (%d so far): %s", self.publish_failures, exc)

    def log(self, level: str, text: str) -> None:
        getattr(_log, level.lower(), _log.info)(text)
        if self.recorder is not None and self.recording_failure is None:
            try:
                self.recorder.log(level, text)
            except RecordingError as exc:
                self.recording_failure = str(exc)


def gamma_schedule(gamma_start: float, gamma_stop: float, steps: int) -> np.ndarray:
    """The commanded angles, rad: ``steps`` evenly spaced from start to stop inclusive."""
    return np.linspace(gamma_start, gamma_stop, steps)


@dataclass(frozen=True)
class ScanIdentity:
    scanner_id: str
    scan_id: int


def run_scan(
    scanner: Scanner,
    schedule: np.ndarray,
    who: ScanIdentity,
    energy_model: EnergyModel,
    output: ScanOutput,
    stop: threading.Event,
    *,
    on_step: Callable[[int, float], None] | None = None,
    int16_scale: float | None = None,
) -> codec.ScanEnd:
    """Acquire one scan; return its ``ScanEnd`` (complete or aborted, never raising on device faults).

    ``on_step(step, gamma_measured)`` is called once each sample is emitted (in the pipelined
    loop, during the next step's acoustic window).  A recording that fails mid-scan (a full disk)
    ends the scan ``ABORTED`` with the reason, its ScanEnd published.

    Raises
    ------
    RecordingError
        The ScanStart itself could not be recorded: the scan did not start, nothing was published.
    """
    info = scanner.info
    output.emit(messages.scan_start(who.scanner_id, who.scan_id, time.time_ns(), info, schedule, energy_model))
    output.log(
        "INFO",
        f"scan {who.scan_id} of {who.scanner_id} started: {len(schedule)} steps, "
        f"γ {np.rad2deg(schedule[0]):.1f}° → {np.rad2deg(schedule[-1]):.1f}°, device {info.device}",
    )
    sent = missing = 0
    reason = ""
    measured: tuple[int, float, StepMeasurement] | None = None  # the last shot, not yet emitted

    def emit_measured() -> None:
        nonlocal measured, sent, missing
        if measured is None:
            return
        step, gamma, shot = measured
        measured = None
        output.emit(messages.sample(who.scanner_id, who.scan_id, step, gamma, shot, info, int16_scale=int16_scale))
        sent += 1
        missing += int(np.count_nonzero(~(np.isfinite(shot.time_of_flight) & (shot.time_of_flight > 0))))
        if on_step is not None:
            on_step(step, shot.gamma_measured)

    listened = False

    def while_listening() -> None:
        nonlocal listened
        listened = True
        emit_measured()

    try:
        for step, gamma in enumerate(schedule):
            if stop.is_set():
                reason = f"stopped by request before step {step}"
                break
            next_gamma = float(schedule[step + 1]) if step + 1 < len(schedule) else None
            listened = False
            try:
                shot = scanner.measure(step, float(gamma), next_gamma=next_gamma, while_listening=while_listening)
            except DeviceError as exc:
                emit_measured()  # the step before the fault was measured whole: it is kept
                reason = f"device failure at step {step}: {exc}"
                output.log("ERROR", reason)
                break
            except RecordingError:
                raise
            except BaseException:
                emit_measured()  # whatever else stops the loop, what was measured is recorded
                raise
            emit_measured()
            measured = (step, float(gamma), shot)
            if not listened:  # a scanner that does not work while listening: out at once, as ever
                emit_measured()
        emit_measured()
    except RecordingError as exc:
        measured = None  # not recorded, so not published
        reason = f"recording failed after {sent} samples: {exc}"  # the caller's status line says it, once
    complete = sent == len(schedule)
    end = messages.scan_end(
        who.scanner_id,
        who.scan_id,
        time.time_ns(),
        complete=complete,
        reason=reason,
        steps_planned=len(schedule),
        samples_sent=sent,
        echoes_missing=missing,
    )
    output.log(
        # (A failed recording cannot take this line, and the caller's status line says it.)
        "INFO" if complete or output.recording_failure else "WARNING",
        f"scan {who.scan_id} {'complete' if complete else 'aborted'}: {sent}/{len(schedule)} samples"
        + (f" ({reason})" if reason else ""),
    )
    output.emit(end)
    return end
