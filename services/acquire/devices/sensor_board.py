"""The sensor board: a small :class:`SensorBoard` protocol and its serial driver.

This is the only module that imports ``serial`` (pyserial).  The wire protocol
is in ``schemas/SENSOR_BOARD.md`` and its codec in :mod:`.sensor_frame`.

One :meth:`SerialSensorBoard.fire` is one request/response: FIRE with a fresh
SEQ, then wait for the ACQ (or ERR) carrying that SEQ.  Anything else on the
line is skipped: garbage (the parser resyncs), frames with another SEQ (a late
answer to an earlier request).  On a CRC failure of the answer the driver asks
again with the RESEND flag, so the board sends the acquisition it already has
instead of firing again; after a timeout it flushes the input and asks again
the same way (a board that never got the FIRE fires).  Both are bounded by
:attr:`SensorBoardConfig.retries`.

A shot can also be taken in two calls, :meth:`SerialSensorBoard.send_fire` then
:meth:`SerialSensorBoard.receive`, so the host can work while the board listens, and
``receive(after_window=...)`` runs a callable once the answer's header has arrived: the
board sends the ACQ only after the acoustic window, so from then on the servo may move
while the frame is still crossing the link (the scanner's pipelining).  If the answer
must then be asked for again, it must be a resend (status RESENT): a board that fired
anew would have fired at the new angle, and that is a :class:`SensorBoardProtocolError`.

Everything :meth:`SerialSensorBoard.fire` raises is a :class:`SensorBoardError`, so a
:class:`~lelsonar.errors.DeviceError`: an answer that cannot be decoded is a
:class:`SensorBoardDecodeError` (also a :class:`~lelsonar.errors.DecodeError`), a port
that fails is a :class:`SensorBoardCommunicationError`.  The scan loop then ends the
scan with ``ScanEnd(ABORTED)`` instead of letting the error escape.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from types import TracebackType
from typing import Protocol, Self, runtime_checkable

import numpy as np
import serial

from lelsonar.acquire.devices import sensor_frame as sf
from lelsonar.acquire.devices.link import SENSOR_BOARD_USB, Link
from lelsonar.errors import ConfigError, DecodeError, DeviceError, DeviceTimeoutError


# --- errors ---------------------------------------------------------------------------
class SensorBoardError(DeviceError):
    """The sensor board failed or refused a request."""


class SensorBoardTimeoutError(DeviceTimeoutError, SensorBoardError):
    """No valid answer to a FIRE after the retries."""


class SensorBoardReportedError(SensorBoardError):
    """The board answered with an ERR frame.

    Attributes
    ----------
    code : int
        An :class:`~.sensor_frame.ErrCode` value.
    """

    def __init__(self, code: int, text: str, context: str) -> None:
        self.code = code
        try:
            name = sf.ErrCode(code).name
        except ValueError:
            name = f"code {code}"
        super().__init__(f"{context}: board reports {name}: {text}")


class SensorBoardProtocolError(SensorBoardError):
    """The board sent a well-framed answer that does not fit the request."""


class SensorBoardDecodeError(SensorBoardError, DecodeError):
    """The board's answer cannot be decoded: another frame version, a declared length over the
    bound, or an ACQ whose fields are invalid.  The codec's error is the ``__cause__``."""


class SensorBoardCommunicationError(SensorBoardError):
    """The serial port failed (unplugged, I/O error, closed): not something a retry fixes."""


# --- configuration and results --------------------------------------------------------
@dataclass(frozen=True)
class SensorBoardConfig:
    """How to reach the board and what to ask it for.

    Parameters
    ----------
    port : str
        Serial device (a USB-CDC board ignores the baud rate).
    n_samples : int
        Samples per channel per shot (the acoustic window is ``n_samples / fs_hz``).
    fs_hz : int
        Sample rate, Hz.
    mask : int
        Capsules to fire, bit i = channel i.
    baudrate : int
        Opens the port at this rate (a USB-CDC board ignores it).
    link : Link
        What the bytes cross: USB full speed (default) or a UART; its rate is the line-time
        part of the answer timeout.
    full_scale_v : float
        Volts at the ADC's positive rail relative to mid-scale (see :class:`~.sensor_frame.WaveScale`).
    max_payload_bytes : int
        Largest frame payload accepted; a header declaring more raises
        :class:`~.sensor_frame.FrameTooLargeError` before the payload is read.
    retries : int
        Extra requests after a corrupt answer or a timeout.
    timeout_margin_s : float
        Added to the acoustic window and the line time to bound the wait for an answer: USB
        latency and the host's scheduling (an emulator thread on a loaded host answers 100+ ms
        late); a lost answer costs this much.
    """

    port: str
    n_samples: int = 3500
    fs_hz: int = 200_000
    mask: int = 0x0F
    baudrate: int = 1_000_000
    link: Link = SENSOR_BOARD_USB
    full_scale_v: float = 1.65
    max_payload_bytes: int = 256 * 1024
    retries: int = 3
    timeout_margin_s: float = 0.25

    def __post_init__(self) -> None:
        checks = (
            (bool(self.port), "port must be a device path"),
            (0 < self.n_samples <= 0xFFFF, "n_samples must be 1..65535"),
            (0 < self.fs_hz <= 0xFFFFFFFF, "fs_hz must be a positive u32"),
            (0 < self.mask <= 0x0F, "mask must select at least one of the 4 channels"),
            (self.baudrate > 0, "baudrate must be positive"),
            (math.isfinite(self.full_scale_v) and self.full_scale_v > 0, "full_scale_v must be positive"),
            (self.retries >= 0, "retries must be >= 0"),
            (self.timeout_margin_s > 0, "timeout_margin_s must be positive"),
            (
                sf.acq_payload_size(self.n_samples) <= self.max_payload_bytes,
                f"an ACQ of {self.n_samples} samples ({sf.acq_payload_size(self.n_samples)} B) exceeds "
                f"max_payload_bytes={self.max_payload_bytes}; raise the bound or take fewer samples",
            ),
        )
        for ok, message in checks:
            if not ok:
                raise ConfigError(f"SensorBoardConfig: {message}")

    @property
    def window_s(self) -> float:
        """Acoustic window of one shot, s."""
        return self.n_samples / self.fs_hz

    @property
    def acq_frame_bytes(self) -> int:
        """Bytes on the wire of one ACQ with waveforms."""
        return sf.frame_size(sf.acq_payload_size(self.n_samples))

    @property
    def answer_timeout_s(self) -> float:
        """Longest wait for an ACQ: window + its line time on the link + margin."""
        return self.window_s + self.link.seconds(self.acq_frame_bytes) + self.timeout_margin_s


@dataclass(frozen=True, eq=False)
class Acquisition:
    """One shot of the four capsules, in SI units.

    Attributes
    ----------
    step : int
        Scan step the shot was fired for.
    seq : int
        SEQ of the FIRE that got this answer.
    fs_hz : float
        Sample rate, Hz.
    status : int
        :class:`~.sensor_frame.AcqStatus` bits.
    t_fire_us : int
        Board clock at firing, µs (u32, wraps).
    tof_s : numpy.ndarray
        ``float64 (4,)`` time of flight, s; NaN where there was no echo.
    waveforms : numpy.ndarray
        ``float32 (4, n_samples)``, volts.
    requests : int
        FIRE frames it took (1 without retries).
    """

    step: int
    seq: int
    fs_hz: float
    status: int
    t_fire_us: int
    tof_s: np.ndarray
    waveforms: np.ndarray
    requests: int = 1


@dataclass(frozen=True)
class PendingShot:
    """A FIRE sent and not yet answered (:meth:`SerialSensorBoard.send_fire`).

    Attributes
    ----------
    step, seq : int
    deadline : float
        Monotonic s by which the answer is due (the board's window, line time and margin).
    """

    step: int
    seq: int
    deadline: float


@runtime_checkable
class SensorBoard(Protocol):
    """What the acquisition loop needs from the sensor board."""

    @property
    def config(self) -> SensorBoardConfig:
        """The board's configuration (its acoustic window paces the loop)."""
        ...

    def fire(self, step: int) -> Acquisition:
        """Fire all configured capsules for ``step`` and return the shot."""
        ...

    def send_fire(self, step: int) -> PendingShot:
        """Fire for ``step`` and return at once; :meth:`receive` collects the shot."""
        ...

    def receive(self, shot: PendingShot, *, after_window: Callable[[], None] | None = None) -> Acquisition:
        """Wait for the shot; call ``after_window`` once its answer has begun (the window is over)."""
        ...

    def close(self) -> None: ...

    def __enter__(self) -> Self: ...

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None: ...


# --- the driver -----------------------------------------------------------------------
class SerialSensorBoard:
    """The sensor board over a serial port (pyserial).

    Parameters
    ----------
    config : SensorBoardConfig

    Raises
    ------
    SensorBoardError
        The port cannot be opened.
    """

    #: pyserial read timeout: how often the wait loop checks its deadline when the line is silent.
    _READ_POLL_S = 0.01

    def __init__(self, config: SensorBoardConfig) -> None:
        self.config = config
        self._scale = sf.WaveScale(config.full_scale_v)
        self._parser = sf.FrameParser(config.max_payload_bytes)
        self._seq = 0
        #: Counters for diagnostics: re-requests after a CRC failure, after a timeout, stale frames skipped.
        self.crc_retries = 0
        self.timeout_retries = 0
        self.stale_frames = 0
        try:
            self._ser = serial.Serial(config.port, baudrate=config.baudrate, timeout=self._READ_POLL_S)
        except (serial.SerialException, ValueError) as exc:
            raise SensorBoardError(f"cannot open sensor board port {config.port!r}: {exc}") from exc
        self._ser.reset_input_buffer()

    def close(self) -> None:
        """Close the port; idempotent."""
        self._ser.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    @property
    def discarded_bytes(self) -> int:
        """Bytes skipped while resynchronising (garbage, corrupt frames)."""
        return self._parser.discarded

    def fire(self, step: int) -> Acquisition:
        """Fire the capsules for ``step`` and wait for the acquisition: :meth:`send_fire` then :meth:`receive`.

        Raises
        ------
        SensorBoardTimeoutError
            No valid ACQ after the retries.
        SensorBoardReportedError
            The board answered ERR (other than a CRC complaint, which is retried).
        SensorBoardDecodeError
            The answer declares a payload over ``max_payload_bytes``
            (cause: :class:`~.sensor_frame.FrameTooLargeError`), has another frame version,
            or is a well-framed but invalid ACQ (wrong sizes, channel count...).
        SensorBoardCommunicationError
            The port failed.
        """
        return self.receive(self.send_fire(step))

    def send_fire(self, step: int) -> PendingShot:
        """Send FIRE for ``step`` and return without waiting; pass the result to :meth:`receive`.

        Raises
        ------
        SensorBoardCommunicationError
            The port failed.
        """
        try:
            seq = self._request(step, sf.FireFlag.WAVEFORMS)
        except (serial.SerialException, OSError) as exc:
            raise self._port_failed(step, exc) from exc
        return PendingShot(step, seq, time.monotonic() + self.config.answer_timeout_s)

    def receive(self, shot: PendingShot, *, after_window: Callable[[], None] | None = None) -> Acquisition:
        """Wait for the answer to ``shot``, asking again as the module docstring says.

        Parameters
        ----------
        shot : PendingShot
        after_window : callable, optional
            Called once, as soon as the (sound) header of an ACQ for this shot has arrived: the
            board has listened for its window and is sending, whether or not the frame then
            passes its CRC.  What it raises is raised as is.

        Raises
        ------
        As :meth:`fire`; and :class:`SensorBoardProtocolError` if, after ``after_window`` ran,
        a re-requested answer is a fresh shot instead of a resend.
        """
        try:
            return self._receive(shot, after_window)
        except _HookFailed as exc:
            raise exc.cause from None  # the caller's own error, not the board's
        except SensorBoardError:
            raise
        except DecodeError as exc:
            self._flush_quietly()
            raise SensorBoardDecodeError(
                f"FIRE step {shot.step}: the answer on {self.config.port} cannot be decoded: {exc}"
            ) from exc
        except (serial.SerialException, OSError) as exc:  # SerialException is an OSError; both for clarity
            raise self._port_failed(shot.step, exc) from exc

    def _port_failed(self, step: int, exc: BaseException) -> SensorBoardCommunicationError:
        return SensorBoardCommunicationError(
            f"FIRE step {step}: serial I/O on {self.config.port} failed: {exc}; check the cable and the board"
        )

    def _flush_quietly(self) -> None:
        try:
            self._flush()
        except (serial.SerialException, OSError):
            self._parser.reset()

    def _request(self, step: int, flags: int) -> int:
        """Write one FIRE with a fresh SEQ; returns the SEQ."""
        c = self.config
        seq = self._next_seq()
        fire = sf.FireRequest(step=step, mask=c.mask, flags=int(flags), n_samples=c.n_samples, fs_hz=c.fs_hz)
        self._ser.write(sf.encode_fire(seq, fire))
        return seq

    def _receive(self, shot: PendingShot, after_window: Callable[[], None] | None) -> Acquisition:
        c = self.config
        step, seq = shot.step, shot.seq
        # The host may have been busy since it fired (that is what send_fire is for): give the
        # answer at least its line time from now, as the board may have waited for us to read.
        deadline = max(shot.deadline, time.monotonic() + c.link.seconds(c.acq_frame_bytes) + c.timeout_margin_s)
        flags = sf.FireFlag.WAVEFORMS
        window_over = _Once(after_window)
        for request in range(1, c.retries + 2):
            if request > 1:
                seq = self._request(step, flags)
                deadline = time.monotonic() + c.answer_timeout_s
            window_over.current_request = request
            try:
                frame = self._await(seq, deadline, window_over)
            except sf.FrameCrcError:
                # The board has the shot; ask for the same data again rather than re-firing.
                self.crc_retries += 1
                flags = sf.FireFlag.WAVEFORMS | sf.FireFlag.RESEND
                continue
            except sf.FrameTooLargeError:
                self._flush()
                raise  # a DecodeError: receive() raises it as a SensorBoardDecodeError
            if frame is None:
                self.timeout_retries += 1
                self._flush()  # bin whatever half-frame is left before asking again
                flags = sf.FireFlag.WAVEFORMS | sf.FireFlag.RESEND
                continue
            if frame.type == sf.FrameType.ERR:
                report = sf.decode_err(frame.payload)
                if report.code == sf.ErrCode.BAD_CRC:
                    self.crc_retries += 1
                    continue
                raise SensorBoardReportedError(report.code, report.text, f"FIRE step {step} (seq {seq})")
            acq = self._to_acquisition(frame, step, seq, request)
            if window_over.called_before(request) and not acq.status & sf.AcqStatus.RESENT:
                raise SensorBoardProtocolError(
                    f"FIRE step {step}: asked again after the servo had moved on, the board fired anew instead of "
                    "resending the shot it had (status without RESENT): that shot is at the wrong angle"
                )
            return acq
        raise SensorBoardTimeoutError(
            f"no valid answer from the sensor board on {c.port} for step {step} after {c.retries + 1} requests; "
            "check the cable and the board's power"
        )

    def _next_seq(self) -> int:
        self._seq = (self._seq + 1) & 0xFFFF
        return self._seq

    def _flush(self) -> None:
        self._ser.reset_input_buffer()
        self._parser.reset()

    def _await(self, seq: int, deadline: float, window_over: _Once) -> sf.Frame | None:
        """Read until a frame with ``seq`` arrives (returned) or the deadline passes (None).

        A CRC failure is raised only for a frame that could be ours: a corrupt
        frame with another SEQ is just a lost stale frame.  ``window_over`` runs once
        the header of our ACQ is in (whether or not the rest then checks out).  At the deadline,
        what already waits in the port is read before giving up (the host may have been busy, not
        the board late).
        """
        parser = self._parser
        drained = False
        while True:
            while True:
                try:
                    frame = parser.next_frame()
                except sf.FrameCrcError as exc:
                    if exc.seq == seq:
                        if exc.frame_type == sf.FrameType.ACQ:
                            window_over()  # its header was sound: the board had listened and was sending
                        raise
                    self.stale_frames += 1
                    continue
                if frame is None:
                    break
                if frame.seq == seq and frame.type in (sf.FrameType.ACQ, sf.FrameType.ERR):
                    if frame.type == sf.FrameType.ACQ:
                        window_over()
                    return frame
                self.stale_frames += 1  # an answer to an earlier request, or not an answer at all
            if window_over.pending and parser.pending_header() == (sf.FrameType.ACQ, seq):
                window_over()
            if time.monotonic() >= deadline:
                waiting = self._ser.in_waiting
                if drained or not waiting:
                    return None
                drained = True
                parser.feed(self._ser.read(waiting))
                continue
            # Block for at least one byte (up to the poll period), then take all that is waiting.
            data = self._ser.read(max(1, self._ser.in_waiting))
            if data:
                waiting = self._ser.in_waiting
                parser.feed(data + self._ser.read(waiting) if waiting else data)

    def _to_acquisition(self, frame: sf.Frame, step: int, seq: int, requests: int) -> Acquisition:
        acq = sf.decode_acq(frame.payload, max_samples=self.config.n_samples)
        c = self.config
        if acq.step != step or acq.n_samples != c.n_samples or acq.fs_hz != c.fs_hz:
            raise SensorBoardProtocolError(
                f"ACQ for seq {seq} is step {acq.step}, {acq.n_samples} samples at {acq.fs_hz} Hz; "
                f"asked for step {step}, {c.n_samples} samples at {c.fs_hz} Hz"
            )
        tof_s = np.where(acq.tof_ns == sf.NO_ECHO, np.nan, acq.tof_ns.astype(np.float64) * 1e-9)
        return Acquisition(
            step=acq.step,
            seq=seq,
            fs_hz=float(acq.fs_hz),
            status=acq.status,
            t_fire_us=acq.t_fire_us,
            tof_s=tof_s,
            waveforms=self._scale.to_volts(acq.waves, acq.bits),
            requests=requests,
        )


class _HookFailed(Exception):
    """Carries what a caller's ``after_window`` raised through the driver's own error mapping."""

    def __init__(self, cause: Exception) -> None:
        super().__init__(cause)
        self.cause = cause


class _Once:
    """Runs the caller's ``after_window`` at most once and remembers during which request it ran."""

    def __init__(self, fn: Callable[[], None] | None) -> None:
        self._fn = fn
        self._request = 0
        self.pending = fn is not None
        self.current_request = 1

    def __call__(self) -> None:
        if not self.pending or self._fn is None:
            return
        self.pending = False
        self._request = self.current_request
        try:
            self._fn()
        except Exception as exc:  # noqa: BLE001 - re-raised as is by receive()
            raise _HookFailed(exc) from exc

    def called_before(self, request: int) -> bool:
        """Whether it ran during a request earlier than ``request``."""
        return 0 < self._request < request
