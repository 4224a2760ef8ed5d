"""A byte-exact AX-12 (Dynamixel protocol 1.0) on a raw pty.

The real ``dynamixel_sdk`` opens :attr:`AX12Emulator.path` and cannot tell the
difference from a servo behind a USB2Dynamixel, apart from timing:

* the control table (EEPROM + RAM, defaults from :mod:`..devices.ax12`);
* PING, READ, WRITE, REG_WRITE, ACTION, SYNC_WRITE; broadcast gets no reply;
* motion at a finite speed (Moving Speed; see the speed model in ``ax12``):
  Present Position is interpolated over time and Moving is 1 until it arrives;
* Return Delay Time (2 µs units) and Status Return Level are honoured;
* error bits: angle limit (goal outside CW/CCW limits, goal not applied), range
  (value outside a register's range or a read-only address), checksum, instruction,
  input voltage and overheating (from Present Voltage / Temperature vs the limits),
  overload (injected: sets bit 5 and drops torque until Torque Enable is written 1);
* fault injection: don't answer the next N packets, answer the next N late
  (to exercise a driver's stale-reply guard), garbage bytes before the next replies;
  and, for tests that must not depend on the host's scheduling, hold the next
  replies until released (:meth:`AX12Emulator.hold_next`), or until the next packet
  arrives, so that the late reply crosses the next request on the line.

Motion runs on the ``clock`` given at construction (a test can drive it by hand);
reply timing runs on the monotonic clock of the device thread.

With :attr:`AX12EmulatorConfig.link` (the backend's and ``lelsonar emulate``'s choice:
the 1 Mbps bus, 10 µs per byte) an instruction is acted on once its last byte has crossed
the bus and a status packet takes its line time to arrive (:mod:`.pty_link`); without
one the pty is unpaced.

Not modelled: acceleration, compliance, the bus's half duplex (the driver never talks
over a reply), Lock (stored, not enforced), baud changes (stored only).
"""

from __future__ import annotations

import collections
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from lelsonar.acquire.devices import ax12
from lelsonar.acquire.devices.ax12 import ErrorBit, Instruction
from lelsonar.acquire.devices.link import Link
from lelsonar.acquire.emulate.pty_link import PtyDevice
from lelsonar.errors import ConfigError


@dataclass(frozen=True)
class AX12EmulatorConfig:
    """Power-on state of the emulated servo.

    Parameters
    ----------
    motor_id : int
        ID (address 3).
    return_delay : int
        Return Delay Time register (2 µs units); the datasheet default is 250 (500 µs).
        Use 0 in tests and benches, as you would on a real bus.
    status_return_level : int
        0: reply to PING only; 1: PING and READ; 2: everything.
    cw_limit, ccw_limit : int
        Angle limits (addresses 6 and 8).
    initial_position : int
        Present (and goal) position at power-on.
    no_load_rpm : float
        Speed cap of the motion model, rpm.
    voltage_dv : int
        Present Voltage, 0.1 V.
    temperature_c : int
        Present Temperature, °C.
    seed : int
        Seed of the garbage-byte generator.
    link : Link, optional
        Pace the bus at this link (e.g. :data:`~lelsonar.acquire.devices.link.AX12_BUS`); None: unpaced.
    """

    motor_id: int = 1
    return_delay: int = 250
    status_return_level: int = 2
    cw_limit: int = 0
    ccw_limit: int = ax12.POSITION_MAX
    initial_position: int = ax12.CENTER_RAW
    no_load_rpm: float = ax12.NO_LOAD_RPM
    voltage_dv: int = 120
    temperature_c: int = 35
    seed: int = 0
    link: Link | None = None

    def __post_init__(self) -> None:
        checks = (
            (0 <= self.motor_id <= 253, "motor_id must be 0..253"),
            (0 <= self.return_delay <= 254, "return_delay must be 0..254 (2 µs units)"),
            (self.status_return_level in (0, 1, 2), "status_return_level must be 0, 1 or 2"),
            (0 <= self.cw_limit <= self.ccw_limit <= ax12.POSITION_MAX, "need 0 <= cw_limit <= ccw_limit <= 1023"),
            (0 <= self.initial_position <= ax12.POSITION_MAX, "initial_position must be 0..1023"),
            (self.no_load_rpm > 0, "no_load_rpm must be positive"),
            (0 <= self.voltage_dv <= 255 and 0 <= self.temperature_c <= 255, "voltage/temperature are one byte"),
        )
        for ok, message in checks:
            if not ok:
                raise ConfigError(f"AX12EmulatorConfig: {message}")


def checksum(body: bytes | bytearray) -> int:
    """Protocol 1.0 checksum of ID..last parameter."""
    return ~sum(body) & 0xFF


def encode_packet(motor_id: int, code: int, params: bytes = b"") -> bytes:
    """``FF FF ID LEN CODE P… CKSUM``; CODE is INSTR or, in a status packet, ERR."""
    body = bytes((motor_id, len(params) + 2, code)) + params
    return b"\xff\xff" + body + bytes((checksum(body),))


class AX12Emulator(PtyDevice):
    """An AX-12 on a pty; see the module docstring for what it models.

    Examples
    --------
    >>> with AX12Emulator(AX12EmulatorConfig(return_delay=0)) as servo:   # doctest: +SKIP
    ...     motor = DynamixelMotor(MotorConfig(port=servo.path))
    """

    def __init__(self, config: AX12EmulatorConfig | None = None, *, clock: Callable[[], float] = time.monotonic):
        self.config = config or AX12EmulatorConfig()
        super().__init__("ax12", self.config.link)
        self._clock = clock
        self._lock = threading.RLock()
        self._rng = np.random.default_rng(self.config.seed)
        self._table = bytearray(ax12.TABLE_SIZE)
        for reg in ax12.CONTROL_TABLE:
            self._put(reg, reg.default)
        c = self.config
        for name, value in (
            ("id", c.motor_id),
            ("return_delay_time", c.return_delay),
            ("status_return_level", c.status_return_level),
            ("cw_angle_limit", c.cw_limit),
            ("ccw_angle_limit", c.ccw_limit),
            ("goal_position", c.initial_position),
            ("present_position", c.initial_position),
            ("present_voltage", c.voltage_dv),
            ("present_temperature", c.temperature_c),
        ):
            self._put(ax12.register(name), value)
        # Motion: linear from _from_raw at _t0 towards the goal.
        self._from_raw = float(c.initial_position)
        self._t0 = clock()
        self._registered: tuple[int, bytes] | None = None
        self._overload = False
        self._drop_next = 0
        self._late_next = 0
        self._late_s = 0.0
        self._garbage_next = 0
        self._garbage_bytes = 0
        self._hold_next = 0
        self._hold_until_next_packet = False
        self._held: list[bytes] = []
        self._rx = bytearray()
        #: (start, end) of the latest moves on the motion clock: when the servo travels (bounded).
        self.moves: collections.deque[tuple[float, float]] = collections.deque(maxlen=4096)
        #: Packets parsed (valid or not), for tests to wait on.
        self.packets_seen = 0
        self.packet_event = threading.Condition(self._lock)

    # --- state access (thread-safe) ----------------------------------------------------
    def read_register(self, name: str) -> int:
        """Current value of a register (Present Position and Moving are up to date)."""
        with self._lock:
            self._update_motion(self._clock())
            return self._get(ax12.register(name))

    def set_register(self, name: str, value: int) -> None:
        """Set a register directly, bypassing access rules (e.g. Present Voltage, the limits)."""
        reg = ax12.register(name)
        with self._lock:
            self._update_motion(self._clock())
            self._put(reg, value)
            if name == "present_position":  # a teleport: restart the motion from here
                self._from_raw, self._t0 = float(value), self._clock()

    def present_position(self) -> int:
        """Present Position now."""
        return self.read_register("present_position")

    def gamma_source(self, zero_raw: int = ax12.CENTER_RAW) -> Callable[[], float]:
        """A callable giving the scanner angle γ (rad) of the present position.

        Give it to the sensor-board emulator so each shot sees the angle the
        servo is really at, with the same ``zero_raw`` as the motor driver.
        """
        return lambda: ax12.gamma_from_raw(self.present_position(), zero_raw)

    # --- fault injection ----------------------------------------------------------------
    def inject_overload(self) -> None:
        """Raise the overload alarm: bit 5 in every reply and torque off, until torque is re-enabled."""
        with self._lock:
            self._update_motion(self._clock())
            self._overload = True
            self._put(ax12.register("torque_enable"), 0)
            self._stop_motion()

    def drop_next(self, n: int = 1) -> None:
        """Do not answer the next ``n`` packets addressed to this servo (they are still executed)."""
        with self._lock:
            self._drop_next = n

    def answer_late(self, delay_s: float, n: int = 1) -> None:
        """Answer the next ``n`` packets ``delay_s`` late; later replies queue behind them."""
        with self._lock:
            self._late_next, self._late_s = n, delay_s

    def garbage_before_next(self, nbytes: int, n: int = 1) -> None:
        """Send ``nbytes`` random bytes (never FF) before each of the next ``n`` replies."""
        with self._lock:
            self._garbage_next, self._garbage_bytes = n, nbytes

    def hold_next(self, n: int = 1, *, until_next_packet: bool = False) -> None:
        """Hold the replies to the next ``n`` packets (they are executed) until :meth:`release_held`,
        or, with ``until_next_packet``, until the next packet arrives: the held replies then go out
        just before that packet's own reply, as a late reply that crosses the next request would."""
        with self._lock:
            self._hold_next, self._hold_until_next_packet = n, until_next_packet

    def release_held(self) -> None:
        """Send the held replies now, and hold no more (a hold not yet used is cancelled)."""
        with self._lock:
            self._hold_next = 0
            self._flush_held(time.monotonic())

    @property
    def held(self) -> int:
        """Replies held now."""
        with self._lock:
            return len(self._held)

    def _flush_held(self, now: float) -> None:
        held, self._held = self._held, []
        for packet in held:
            self._schedule(packet, now)

    def wait_packets(self, count: int, timeout: float = 2.0) -> bool:
        """Block until at least ``count`` packets have been seen in total."""
        with self.packet_event:
            return self.packet_event.wait_for(lambda: self.packets_seen >= count, timeout)

    # --- table helpers (call with the lock held) ---------------------------------------
    def _get(self, reg: ax12.Register) -> int:
        return int.from_bytes(self._table[reg.address : reg.end], "little")

    def _put(self, reg: ax12.Register, value: int) -> None:
        self._table[reg.address : reg.end] = int(value).to_bytes(reg.size, "little")

    def _speed(self) -> float:
        return ax12.speed_units_per_s(self._get(ax12.register("moving_speed")), self.config.no_load_rpm)

    def _update_motion(self, now: float) -> None:
        """Refresh Present Position / Speed / Load and Moving from the motion model."""
        goal = self._get(ax12.register("goal_position"))
        torque = self._get(ax12.register("torque_enable"))
        start = self._from_raw
        speed = self._speed()
        if torque and goal != round(start):
            travelled = speed * (now - self._t0)
            distance = goal - start
            if travelled >= abs(distance):
                position, moving = float(goal), 0
            else:
                position, moving = start + np.copysign(travelled, distance), 1
        else:
            position, moving = start, 0
        raw = round(position)
        self._put(ax12.register("present_position"), raw)
        self._put(ax12.register("moving"), moving)
        direction = ax12.DIRECTION_BIT if moving and goal < start else 0  # bit 10 = CW (decreasing)
        speed_units = min(1023, round(speed / (ax12.RPM_PER_SPEED_UNIT * 6.0 / ax12.DEG_PER_UNIT)))
        self._put(ax12.register("present_speed"), (speed_units | direction) if moving else 0)
        load = 1023 if self._overload else (40 | direction if moving else 0)
        self._put(ax12.register("present_load"), load)
        if not moving:  # re-anchor so a later goal starts from here
            self._from_raw, self._t0 = position, now

    def _stop_motion(self) -> None:
        here = self._get(ax12.register("present_position"))
        self._put(ax12.register("goal_position"), here)
        self._put(ax12.register("moving"), 0)
        self._from_raw, self._t0 = float(here), self._clock()

    def _status_bits(self) -> int:
        bits = 0
        voltage = self._get(ax12.register("present_voltage"))
        if not (
            self._get(ax12.register("min_voltage_limit")) <= voltage <= self._get(ax12.register("max_voltage_limit"))
        ):
            bits |= ErrorBit.INPUT_VOLTAGE
        if self._get(ax12.register("present_temperature")) > self._get(ax12.register("temperature_limit")):
            bits |= ErrorBit.OVERHEATING
        if self._overload:
            bits |= ErrorBit.OVERLOAD
        return bits

    # --- protocol ----------------------------------------------------------------------
    def _on_input(self, data: bytes, now: float) -> None:
        rx = self._rx
        rx += data
        while True:
            start = rx.find(b"\xff\xff")
            if start < 0:
                # Keep a trailing FF: it may be the first half of the next header.
                del rx[: len(rx) - 1 if rx.endswith(b"\xff") else len(rx)]
                return
            del rx[:start]
            # FF FF FF ID...: the header is the last two FFs (IDs never are 0xFF).
            while len(rx) > 2 and rx[2] == 0xFF:
                del rx[0]
            if len(rx) < 4:
                return
            length = rx[3]
            if length < 2:
                del rx[:2]
                continue
            total = 4 + length
            if len(rx) < total:
                return
            packet = bytes(rx[:total])
            del rx[:total]
            self._handle(packet, now)

    def _handle(self, packet: bytes, now: float) -> None:
        motor_id, _, code = packet[2], packet[3], packet[4]
        params = packet[5:-1]
        with self._lock:
            self.packets_seen += 1
            self.packet_event.notify_all()
            if self._held and self._hold_until_next_packet:
                self._flush_held(now)
            my_id = self._get(ax12.register("id"))
            broadcast = motor_id == ax12.BROADCAST_ID
            if not broadcast and motor_id != my_id:
                return
            self._update_motion(self._clock())
            if checksum(packet[2:-1]) != packet[-1]:
                # The servo cannot trust the instruction: report, do nothing.
                if not broadcast:
                    self._reply(my_id, int(ErrorBit.CHECKSUM), b"", code, now)
                return
            error, reply = self._execute(code, params, broadcast)
            if not broadcast:
                self._reply(my_id, error, reply, code, now)

    def _execute(self, code: int, params: bytes, broadcast: bool) -> tuple[int, bytes]:
        """Run one instruction; returns (transient error bits, reply parameters)."""
        if code == Instruction.PING:
            return 0, b""
        if code == Instruction.READ:
            if len(params) != 2:
                return int(ErrorBit.INSTRUCTION), b""
            address, size = params
            if address + size > ax12.TABLE_SIZE or size == 0:
                return int(ErrorBit.RANGE), b""
            return 0, bytes(self._table[address : address + size])
        if code == Instruction.WRITE:
            if len(params) < 2:
                return int(ErrorBit.INSTRUCTION), b""
            return self._write(params[0], params[1:]), b""
        if code == Instruction.REG_WRITE:
            if len(params) < 2:
                return int(ErrorBit.INSTRUCTION), b""
            self._registered = (params[0], bytes(params[1:]))
            self._put(ax12.register("registered"), 1)
            return 0, b""
        if code == Instruction.ACTION:
            if self._registered is None:
                return int(ErrorBit.INSTRUCTION), b""
            address, data = self._registered
            self._registered = None
            self._put(ax12.register("registered"), 0)
            return self._write(address, data), b""
        if code == Instruction.SYNC_WRITE:
            if len(params) < 2 or params[1] == 0 or (len(params) - 2) % (params[1] + 1):
                return int(ErrorBit.INSTRUCTION), b""
            address, size = params[0], params[1]
            my_id = self._get(ax12.register("id"))
            for i in range(2, len(params), size + 1):
                if params[i] == my_id:
                    self._write(address, params[i + 1 : i + 1 + size])
            return 0, b""
        return int(ErrorBit.INSTRUCTION), b""

    def _write(self, address: int, data: bytes) -> int:
        """Apply a WRITE all-or-nothing; returns the error bits."""
        if address + len(data) > ax12.TABLE_SIZE:
            return int(ErrorBit.RANGE)
        staged = bytearray(self._table)
        staged[address : address + len(data)] = data
        touched = [r for r in ax12.CONTROL_TABLE if r.address < address + len(data) and address < r.end]
        if not touched:
            return int(ErrorBit.RANGE)
        for reg in touched:
            value = int.from_bytes(staged[reg.address : reg.end], "little")
            if reg.access is ax12.Access.R or not reg.minimum <= value <= reg.maximum:
                return int(ErrorBit.RANGE)
        goal_reg = ax12.register("goal_position")
        if goal_reg in touched:
            goal = int.from_bytes(staged[goal_reg.address : goal_reg.end], "little")
            cw = int.from_bytes(staged[6:8], "little")
            ccw = int.from_bytes(staged[8:10], "little")
            if not cw <= goal <= ccw:
                return int(ErrorBit.ANGLE_LIMIT)
        self._table[:] = staged
        if ax12.register("torque_enable") in touched:
            if self._get(ax12.register("torque_enable")):
                self._overload = False  # re-enabling torque clears the overload alarm
            else:
                self._stop_motion()
        if goal_reg in touched or ax12.register("moving_speed") in touched:
            # Restart the linear motion from where we are now, towards the (new) goal.
            self._from_raw = float(self._get(ax12.register("present_position")))
            self._t0 = self._clock()
            goal = self._get(goal_reg)
            if self._get(ax12.register("torque_enable")) and goal != round(self._from_raw):
                self.moves.append((self._t0, self._t0 + abs(goal - self._from_raw) / self._speed()))
        return 0

    def _reply(self, my_id: int, error: int, params: bytes, code: int, now: float) -> None:
        level = self._get(ax12.register("status_return_level"))
        if code != Instruction.PING and (level == 0 or (level == 1 and code != Instruction.READ)):
            return
        if self._drop_next > 0:
            self._drop_next -= 1
            return
        due = now + self._get(ax12.register("return_delay_time")) * ax12.RETURN_DELAY_UNIT_S
        if self._late_next > 0:
            self._late_next -= 1
            due = now + self._late_s
        packet = encode_packet(my_id, (error | self._status_bits()) & 0x7F, params)
        if self._garbage_next > 0:
            self._garbage_next -= 1
            garbage = self._rng.integers(0, 0xFF, size=self._garbage_bytes, dtype=np.uint8).tobytes()
            packet = garbage + packet
        if self._hold_next > 0:
            self._hold_next -= 1
            self._held.append(packet)
            self.packet_event.notify_all()
            return
        self._schedule(packet, due)
