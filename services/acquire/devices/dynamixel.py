"""The AX-12 driver of the :class:`~lelsonar.acquire.devices.motor.Motor` protocol, through dynamixel-sdk.

This is the only module that imports ``dynamixel_sdk``.  The SDK is used
unmodified, with protocol 1.0 at 1 Mbps.  Two SDK traits shape the driver:

* **Timeouts.**  The SDK's packet timeout is ``2 × LATENCY_TIMER + 2 ms`` plus the
  line time; ``LATENCY_TIMER`` is a module global (16 ms, an FTDI adapter's default
  latency).  Rather than mutate that global, :class:`_PortHandler` subclasses the
  SDK's ``PortHandler`` and uses :attr:`MotorConfig.latency_timer_ms`.  It also
  waits for reply bytes with ``select`` instead of the SDK's spin on a
  non-blocking read, which would starve an emulator or a sensor thread of CPU.
* **Stale replies.**  Replies are matched by ID only, so after a timeout a late
  reply can be taken as the answer to the *next* request.  The driver never has two
  requests outstanding if it can help it: after an SDK timeout it keeps listening
  for :attr:`MotorConfig.stale_guard_s` ("waits the timeout out"), and a reply that
  comes in that window *is* the answer to the one request in flight, so it is used.
  Only when the window passes in silence is the request presumed lost: the input is
  cleared and the request sent again (reads and absolute writes are idempotent).
  If a resend is answered, the first request's reply may still come: the driver
  listens for it once more and bins it before going on.  A corrupt reply, or a read
  whose reply has the wrong number of bytes (someone else's), is waited out and
  binned the same way.  Replies later than the window cannot be told from a fresh
  answer; a pty emulator's thread can be starved for 100+ ms on a loaded host,
  hence the long window the emulated backend uses (:data:`EMULATED_STALE_GUARD_S`).

Every status packet's ERR byte is decoded into a typed
:class:`~lelsonar.acquire.devices.motor.MotorStatusError`, except the bits
:attr:`~lelsonar.acquire.devices.motor.MotorConfig.tolerated_error_bits` lets through, which are carried in
:attr:`~lelsonar.acquire.devices.motor.MotorPosition.error_bits` (and so in ``Sample.motor.error_bits``).
"""

from __future__ import annotations

import logging
import math
import select
import time
from collections.abc import Callable
from types import TracebackType
from typing import Self, TypeVar, cast

from dynamixel_sdk import COMM_RX_CORRUPT, COMM_RX_TIMEOUT, COMM_SUCCESS, PacketHandler, PortHandler
from dynamixel_sdk.protocol1_packet_handler import (
    INST_PING,
    PKT_ERROR,
    PKT_ID,
    PKT_INSTRUCTION,
    PKT_LENGTH,
    PKT_PARAMETER0,
)

from lelsonar.acquire.devices import ax12
from lelsonar.acquire.devices.ax12 import ErrorBit
from lelsonar.acquire.devices.motor import (
    GammaOutOfRangeError,
    MotorCommunicationError,
    MotorConfig,
    MotorError,
    MotorNotSettledError,
    MotorPosition,
    MotorRangeError,
    MotorStatus,
    MotorTimeoutError,
    WrongModelError,
    status_error,
)

T = TypeVar("T")
_log = logging.getLogger(__name__)


# --- the SDK port, tuned ------------------------------------------------------------
class _PortHandler(PortHandler):
    """The SDK's PortHandler with a per-instance latency and a blocking wait for bytes."""

    def __init__(self, port_name: str, latency_timer_ms: float) -> None:
        super().__init__(port_name)
        self.latency_timer_ms = latency_timer_ms

    def setPacketTimeout(self, packet_length: int) -> None:  # noqa: N802 (SDK name)
        # Same formula as the SDK, with our latency instead of the module global.
        self.packet_start_time = self.getCurrentTime()
        self.packet_timeout = self.tx_time_per_byte * packet_length + self.latency_timer_ms * 2.0 + 2.0

    def readPort(self, length: int) -> bytes:  # noqa: N802 (SDK name)
        data = self.ser.read(length)
        if data:
            return data
        # Nothing yet: sleep in select until bytes arrive or the packet times out,
        # instead of letting the SDK's rx loop spin at 100 % CPU.
        remaining_ms = self.packet_timeout - self.getTimeSinceStart()
        if remaining_ms > 0:
            select.select([self.ser.fileno()], [], [], remaining_ms / 1000.0)
            return self.ser.read(length)
        return data


# --- the driver ------------------------------------------------------------------------
class DynamixelMotor:
    """An AX-12 on a protocol-1.0 bus, through the unmodified dynamixel-sdk.

    At construction it opens the port, pings (model 12 required), reads the angle
    limits and the Status Return Level, writes Moving Speed and enables torque.
    :meth:`close` (or leaving the ``with`` block) disables torque and closes the port.

    Parameters
    ----------
    config : MotorConfig

    Raises
    ------
    MotorCommunicationError
        The port cannot be opened.
    WrongModelError
        The device is not an AX-12.
    MotorTimeoutError, MotorStatusError
        As for every transaction.
    """

    def __init__(self, config: MotorConfig) -> None:
        self.config = config
        self._guard_s = 2.0 * config.packet_timeout_s if config.stale_guard_s is None else config.stale_guard_s
        self._port = _PortHandler(config.port, config.latency_timer_ms)
        self._packets = PacketHandler(1.0)
        self._torque_on = False
        self._ack_writes = True
        #: Transactions retried after a timeout or corrupt reply (diagnostics).
        self.retries_used = 0
        #: Replies that came after the SDK's packet timeout, inside the late-reply window.
        self.late_replies = 0
        #: Extra replies to an earlier, resent request that were binned.
        self.stale_replies_binned = 0
        #: ERR byte of the last status packet accepted (tolerated bits only, else it raised).
        self.last_error_bits = 0
        try:
            # setBaudRate opens the port (the SDK's openPort would open it at its default first).
            opened = self._port.setBaudRate(config.baudrate)
        except OSError as exc:  # pyserial's SerialException is an OSError
            raise MotorCommunicationError(f"cannot open motor port {config.port!r}: {exc}") from exc
        if not opened:
            raise MotorCommunicationError(f"cannot open motor port {config.port!r} at {config.baudrate} baud")
        try:
            self._connect()
        except BaseException:
            self._port.closePort()
            raise

    def _connect(self) -> None:
        model = self.ping()
        if model != ax12.MODEL_NUMBER:
            raise WrongModelError(
                f"device {self.config.motor_id} on {self.config.port} is model {model}, not an AX-12 "
                f"({ax12.MODEL_NUMBER}); check the ID and the port"
            )
        srl = self.read_register("status_return_level")
        # At level 1 the servo does not acknowledge writes: send them without waiting.
        self._ack_writes = srl >= 2
        cw = self.read_register("cw_angle_limit")
        ccw = self.read_register("ccw_angle_limit")
        c = self.config
        lo = max(c.gamma_min, ax12.gamma_from_raw(cw, c.zero_raw))
        hi = min(c.gamma_max, ax12.gamma_from_raw(ccw, c.zero_raw))
        if lo > hi:
            raise GammaOutOfRangeError(
                f"configured γ range [{math.degrees(c.gamma_min):.1f}°, {math.degrees(c.gamma_max):.1f}°] "
                f"does not meet the servo's angle limits (raw {cw}..{ccw} with zero_raw={c.zero_raw})"
            )
        self._gamma_range = (lo, hi)
        self._limits_raw = (cw, ccw)
        self.write_register("moving_speed", c.moving_speed)
        self.write_register("torque_enable", 1)
        self._torque_on = True
        self._present_raw = self.read_register("present_position")

    # --- lifecycle ------------------------------------------------------------------------
    def close(self) -> None:
        """Disable torque (best effort) and close the port; idempotent."""
        if not self._port.is_open:
            return
        try:
            if self._torque_on:
                self._torque_on = False
                self.write_register("torque_enable", 0)
        except MotorError as exc:
            # Do not mask the error that brought us here; the servo may be unpowered.
            _log.warning("could not disable torque on %s: %s", self.config.port, exc)
        finally:
            self._port.closePort()

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    # --- Motor protocol ----------------------------------------------------------------
    @property
    def gamma_range(self) -> tuple[float, float]:
        return self._gamma_range

    def ping(self) -> int:
        """Model number (12 for an AX-12)."""

        # The SDK's ping() is PING then READ of the model number, in one call; here the two are
        # separate transactions, so that each gets the retry and late-reply handling.
        def ping() -> tuple[None, int, int]:
            tx = [0] * 6
            tx[PKT_ID], tx[PKT_LENGTH], tx[PKT_INSTRUCTION] = self.config.motor_id, 2, INST_PING
            _, result, error = self._packets.txRxPacket(self._port, tx)
            return None, result, error

        self._transact("PING", ping, lambda rx: (None, COMM_SUCCESS))
        return self.read_register("model_number")

    def position(self) -> MotorPosition:
        """Present Position read back from the servo, its γ, and the status."""
        return self._snapshot()[0]

    def move_to(self, gamma: float) -> MotorPosition:
        """Move to ``gamma`` (rad) and wait until the servo stops.

        The wait sleeps for the travel time computed from the distance and the
        speed model, then polls; each poll is one read of addresses 36–46
        (position, speed, load, voltage, temperature, moving) and, while still
        moving, sleeps for the travel left.  It gives up after
        ``move_slack × travel + move_margin_s``.

        Returns
        -------
        MotorPosition
            Present Position once stopped: the measured γ, quantised to 0.29°, with the status.

        Raises
        ------
        GammaOutOfRangeError
            ``gamma`` is outside :attr:`gamma_range` (nothing is sent).
        MotorNotSettledError
            Still moving at the deadline.
        MotorStatusError, MotorTimeoutError
        """
        lo, hi = self._gamma_range
        if not (math.isfinite(gamma) and lo - 1e-12 <= gamma <= hi + 1e-12):
            raise GammaOutOfRangeError(
                f"γ = {math.degrees(gamma):.2f}° is outside [{math.degrees(lo):.2f}°, {math.degrees(hi):.2f}°]"
            )
        c = self.config
        goal = min(max(ax12.raw_from_gamma(gamma, c.zero_raw), self._limits_raw[0]), self._limits_raw[1])
        units_per_s = ax12.speed_units_per_s(c.moving_speed, c.no_load_rpm)
        travel = abs(goal - self._present_raw) / units_per_s
        self.write_register("goal_position", goal)
        # The servo started when the write arrived, i.e. before now: sleeping `travel` from here is enough.
        start = time.monotonic()
        deadline = start + c.move_slack * travel + c.move_margin_s
        time.sleep(travel)  # an earlier poll would only load the bus
        while True:
            position, moving = self._snapshot()
            if not moving:
                return position
            now = time.monotonic()
            if now >= deadline:
                raise MotorNotSettledError(
                    f"servo still moving {now - start:.3f} s after a goal of {goal} (at {position.raw}, "
                    f"expected {travel:.3f} s); check the load and Moving Speed"
                )
            # Sleep for the travel left (a tick at least, a poll interval at most).
            left = abs(goal - position.raw) / units_per_s
            time.sleep(min(max(left, 2e-4), c.poll_interval_s, deadline - now))

    def status(self) -> MotorStatus:
        """Present Load, Voltage and Temperature, in one 4-byte read (addresses 40–43)."""
        data = self._read_block(ax12.register("present_load").address, 4)
        return self._status_from(data)

    @staticmethod
    def _status_from(data: list[int]) -> MotorStatus:
        return MotorStatus(
            load=ax12.signed_load(data[0] | data[1] << 8), voltage_v=data[2] / 10.0, temperature_c=float(data[3])
        )

    def _snapshot(self) -> tuple[MotorPosition, bool]:
        """One read of Present Position .. Moving (36–46, 11 bytes; 45 is reserved)."""
        base = ax12.MOVE_READBACK_ADDRESS
        data = self._read_block(base, ax12.MOVE_READBACK_BYTES)
        self._present_raw = data[0] | data[1] << 8
        load_at = ax12.register("present_load").address - base
        position = MotorPosition(
            raw=self._present_raw,
            gamma=ax12.gamma_from_raw(self._present_raw, self.config.zero_raw),
            status=self._status_from(data[load_at : load_at + 4]),
            error_bits=self.last_error_bits,
        )
        return position, bool(data[ax12.register("moving").address - base])

    # --- register access ------------------------------------------------------------------
    def read_register(self, name: str) -> int:
        """Read one control-table register by name."""
        reg = ax12.register(name)
        data = self._read_block(reg.address, reg.size)
        return int.from_bytes(bytes(data), "little")

    def write_register(self, name: str, value: int) -> None:
        """Write one control-table register by name (an absolute write: safe to retry)."""
        reg = ax12.register(name)
        if reg.access is ax12.Access.R:
            raise MotorRangeError(int(ErrorBit.RANGE), f"write {name}: register is read-only")
        payload = list(int(value).to_bytes(reg.size, "little"))
        motor_id = self.config.motor_id
        if self._ack_writes:
            self._transact(
                f"WRITE {name}={value}",
                lambda: (None, *self._packets.writeTxRx(self._port, motor_id, reg.address, reg.size, payload)),
                lambda rx: (None, COMM_SUCCESS),
            )
        else:
            result = self._packets.writeTxOnly(self._port, motor_id, reg.address, reg.size, payload)
            if result != COMM_SUCCESS:
                raise MotorCommunicationError(f"WRITE {name}: {self._packets.getTxRxResult(result)}")

    def _read_block(self, address: int, size: int) -> list[int]:
        def read() -> tuple[list[int], int, int]:
            data, result, error = self._packets.readTxRx(self._port, self.config.motor_id, address, size)
            if result == COMM_SUCCESS and len(data) != size:
                # A reply of the wrong size is someone else's (stale) answer.
                return data, COMM_RX_CORRUPT, error
            return data, result, error

        def parse(rx: list[int]) -> tuple[list[int], int]:
            data = list(rx[PKT_PARAMETER0 : PKT_PARAMETER0 + size])
            return data, (COMM_SUCCESS if rx[PKT_LENGTH] == size + 2 else COMM_RX_CORRUPT)

        return self._transact(f"READ {address}+{size}", read, parse)

    def _transact(
        self, what: str, call: Callable[[], tuple[T, int, int]], parse: Callable[[list[int]], tuple[T, int]]
    ) -> T:
        """Run an idempotent SDK call with retries, the late-reply window and ERR decoding.

        ``call`` sends the request and waits the SDK's packet timeout; ``parse`` turns a
        status packet that came later into ``(value, result)``.
        """
        attempts = self.config.retries + 1
        last = ""
        in_flight = False  # an earlier request of this transaction may still be answered
        for attempt in range(attempts):
            value, result, error = call()
            if result == COMM_RX_TIMEOUT and self._guard_s > 0:
                # Silence so far.  Only this request is outstanding, so a reply that comes
                # now is its answer: wait the timeout out for it rather than resend.
                heard, result, error = self._listen(parse)
                if result == COMM_SUCCESS:
                    self.late_replies += 1
                    value = cast("T", heard)  # parse's value: _listen gives None only with a failed result
            if result == COMM_SUCCESS:
                if in_flight:
                    self._bin_stale_reply()
                    in_flight = False
                if error & ~self.config.tolerated_error_bits:
                    if error & ErrorBit.CHECKSUM and attempt + 1 < attempts:
                        # The servo saw a corrupt instruction and did nothing: resend.
                        self.retries_used += 1
                        continue
                    raise status_error(error, f"{what} on motor {self.config.motor_id}")
                self.last_error_bits = error
                return value
            last = self._packets.getTxRxResult(result)
            if result not in (COMM_RX_TIMEOUT, COMM_RX_CORRUPT):
                raise MotorCommunicationError(f"{what} on {self.config.port}: {last}")
            if result == COMM_RX_TIMEOUT:
                # The window passed in silence: presumed lost, but it may still come.
                in_flight = True
                self._port.clearPort()
            else:
                # A corrupt reply: let the rest of it (or of someone else's) arrive and bin it.
                self._settle()
            if attempt + 1 < attempts:
                self.retries_used += 1
        raise MotorTimeoutError(
            f"{what} on motor {self.config.motor_id} at {self.config.port}: {last} after {attempts} attempts; "
            "check power, ID, baud rate and cabling"
        )

    def _listen(self, parse: Callable[[list[int]], tuple[T, int]]) -> tuple[T | None, int, int]:
        """Wait up to the late-reply window for a status packet from our servo."""
        self._port.setPacketTimeoutMillis(self._guard_s * 1000.0)
        while True:
            rx, result = self._packets.rxPacket(self._port)
            if result != COMM_SUCCESS:
                return None, result, 0
            if rx[PKT_ID] == self.config.motor_id:
                value, result = parse(rx)
                return value, result, rx[PKT_ERROR]

    def _bin_stale_reply(self) -> None:
        """After an answered resend: the first request's reply may still come; bin it."""
        if self._guard_s <= 0:
            return
        _, result, _ = self._listen(lambda rx: (None, COMM_SUCCESS))
        if result == COMM_SUCCESS:
            self.stale_replies_binned += 1
        self._port.clearPort()

    def _settle(self) -> None:
        if self._guard_s > 0:
            time.sleep(self._guard_s)
        self._port.clearPort()
