"""The scanner's motor as the scan loop knows it: the :class:`Motor` protocol, its configuration, its readings
and its typed errors.

The AX-12 driver that implements it through the vendor SDK is :mod:`lelsonar.acquire.devices.dynamixel`.
Every status packet's ERR byte is decoded into a typed :class:`MotorStatusError` (:func:`status_error`),
except the bits :attr:`MotorConfig.tolerated_error_bits` lets through, which are carried in
:attr:`MotorPosition.error_bits` (and so in ``Sample.motor.error_bits``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from types import TracebackType
from typing import Protocol, Self, runtime_checkable

from lelsonar.acquire.devices import ax12
from lelsonar.acquire.devices.ax12 import ErrorBit
from lelsonar.errors import ConfigError, DeviceError, DeviceTimeoutError

#: Late-reply window for a servo emulated on a pty in this process (s).  The emulator's
#: thread is scheduled by the host: with both cores saturated by other processes its
#: reply to a 6-byte request can come over a hundred milliseconds late, far past the
#: SDK's packet timeout.  A window this long costs nothing unless a reply is really lost.
EMULATED_STALE_GUARD_S = 1.0


# --- errors --------------------------------------------------------------------------
class MotorError(DeviceError):
    """The motor failed or refused a command."""


class MotorTimeoutError(DeviceTimeoutError, MotorError):
    """The servo did not answer (or its answers stayed corrupt) after the retries."""


class MotorCommunicationError(MotorError):
    """The port failed (busy, write failed): not something a retry fixes."""


class WrongModelError(MotorError):
    """Something answered PING, but it is not an AX-12."""


class GammaOutOfRangeError(MotorError):
    """A requested γ is outside the configured range or the servo's angle limits."""


class MotorNotSettledError(MotorError):
    """The servo was still moving (or stopped elsewhere) when the move deadline passed."""


class MotorStatusError(MotorError):
    """The servo set error bits in its status packet.

    Attributes
    ----------
    bits : int
        The raw ERR byte.
    names : tuple of str
        Decoded names of every set bit, e.g. ``("angle_limit", "overload")``.
    """

    #: The bit a subclass stands for (the base class: none in particular).
    bit: ErrorBit | None = None

    def __init__(self, bits: int, context: str) -> None:
        self.bits = bits
        self.names = ax12.error_bit_names(bits)
        super().__init__(f"{context}: servo reports {', '.join(self.names)} (ERR=0x{bits:02X}). {self.fix}")

    fix = ""


class InputVoltageError(MotorStatusError):
    bit = ErrorBit.INPUT_VOLTAGE
    fix = "Check the supply: the voltage is outside the Min/Max Voltage Limit (addresses 12/13)."


class AngleLimitError(MotorStatusError):
    bit = ErrorBit.ANGLE_LIMIT
    fix = "The goal is outside the CW/CCW angle limits (addresses 6/8); narrow the γ range."


class OverheatingError(MotorStatusError):
    bit = ErrorBit.OVERHEATING
    fix = "Let the servo cool below its Temperature Limit (address 11) and reduce the load."


class MotorRangeError(MotorStatusError):
    bit = ErrorBit.RANGE
    fix = "A written value is out of the register's range or the address is read-only."


class MotorChecksumError(MotorStatusError):
    bit = ErrorBit.CHECKSUM
    fix = "The servo received a corrupt instruction: check cabling and termination."


class OverloadError(MotorStatusError):
    bit = ErrorBit.OVERLOAD
    fix = "The servo dropped torque: free the mechanism, then re-enable torque (reconnect)."


class InstructionError(MotorStatusError):
    bit = ErrorBit.INSTRUCTION
    fix = "Undefined instruction, or ACTION without REG_WRITE."


# Most severe first: when several bits are set, the first one present names the error.
_STATUS_ERRORS: tuple[type[MotorStatusError], ...] = (
    OverloadError,
    OverheatingError,
    InputVoltageError,
    AngleLimitError,
    MotorRangeError,
    MotorChecksumError,
    InstructionError,
)


def status_error(bits: int, context: str) -> MotorStatusError:
    """The typed error for an ERR byte (``bits`` must be non-zero)."""
    for cls in _STATUS_ERRORS:
        if cls.bit is not None and bits & cls.bit:
            return cls(bits, context)
    return MotorStatusError(bits, context)


# --- configuration and readings -------------------------------------------------------
@dataclass(frozen=True)
class MotorConfig:
    """How to reach and drive the servo.

    Parameters
    ----------
    port : str
        Serial device, e.g. ``/dev/ttyUSB0`` or an emulator's pty path.
    motor_id : int
        Servo ID (1 from the factory).
    baudrate : int
        Must match the servo's Baud Rate register; 1 Mbps is the AX-12 default.
    gamma_min, gamma_max : float
        Allowed scanner angles γ (rad); a move outside raises before anything is sent.
    zero_raw : int
        Raw position at γ = 0 (mount calibration); γ is CCW positive.
    moving_speed : int
        Moving Speed register value written at connect (0 = no-load speed).
    latency_timer_ms : float
        The SDK's LATENCY_TIMER: the packet timeout is ``2 × this + 2 ms``.  16 ms
        matches an FTDI adapter's default latency; set the adapter's latency to 1 ms
        and this to 2 ms for fast scans.
    retries : int
        Extra attempts after a timeout or corrupt reply.
    stale_guard_s : float or None
        The late-reply window: how long to keep listening after the SDK's packet
        timeout (a reply in it answers the request in flight), and after a corrupt
        reply or an answered resend (a reply in it is binned), before the port is
        cleared.  Replies up to ``packet timeout + stale_guard_s`` late are handled;
        later ones cannot be told from a fresh answer.  None: two packet timeouts
        (a USB adapter buffers the reply whatever the host's load); use
        :data:`EMULATED_STALE_GUARD_S` for an emulator in this process.  0 disables
        the guard (only to demonstrate the hazard).
    move_margin_s : float
        Added to the computed travel time to bound a move (compliance, acceleration).
    move_slack : float
        Multiplies the computed travel time when bounding a move.
    poll_interval_s : float
        Longest sleep between Moving polls once the expected travel time has passed.
    no_load_rpm : float
        Speed cap of the travel-time model (see ``ax12``).
    tolerated_error_bits : int
        ERR bits that are reported, not raised: the transaction succeeds and the bits are
        carried in :attr:`MotorPosition.error_bits` (and so in every ``Sample.motor``).
        E.g. ``ErrorBit.INPUT_VOLTAGE`` to keep scanning on a sagging supply, which the
        servo itself survives.  0 (the default): every set bit raises its typed error.
    """

    port: str
    motor_id: int = 1
    baudrate: int = 1_000_000
    gamma_min: float = math.radians(-10.0)
    gamma_max: float = math.radians(110.0)
    zero_raw: int = ax12.CENTER_RAW
    moving_speed: int = 0
    latency_timer_ms: float = 16.0
    retries: int = 3
    stale_guard_s: float | None = None
    move_margin_s: float = 0.25
    move_slack: float = 1.5
    poll_interval_s: float = 0.002
    no_load_rpm: float = ax12.NO_LOAD_RPM
    tolerated_error_bits: int = 0

    def __post_init__(self) -> None:
        checks = (
            (bool(self.port), "port must be a device path"),
            (0 <= self.motor_id <= 253, "motor_id must be 0..253"),
            (self.baudrate > 0, "baudrate must be positive"),
            (
                math.isfinite(self.gamma_min) and math.isfinite(self.gamma_max) and self.gamma_min < self.gamma_max,
                "need finite gamma_min < gamma_max",
            ),
            (0 <= self.zero_raw <= ax12.POSITION_MAX, "zero_raw must be 0..1023"),
            (0 <= self.moving_speed <= 1023, "moving_speed must be 0..1023"),
            (self.latency_timer_ms >= 0, "latency_timer_ms must be >= 0"),
            (self.retries >= 0, "retries must be >= 0"),
            (self.stale_guard_s is None or self.stale_guard_s >= 0, "stale_guard_s must be >= 0"),
            (self.move_margin_s >= 0 and self.move_slack >= 1, "need move_margin_s >= 0 and move_slack >= 1"),
            (self.poll_interval_s > 0, "poll_interval_s must be positive"),
            (self.no_load_rpm > 0, "no_load_rpm must be positive"),
            (0 <= self.tolerated_error_bits <= 0x7F, "tolerated_error_bits must be 0..0x7F"),
        )
        for ok, message in checks:
            if not ok:
                raise ConfigError(f"MotorConfig: {message}")

    @property
    def packet_timeout_s(self) -> float:
        """The SDK's timeout for a short status packet with this latency."""
        return (2.0 * self.latency_timer_ms + 2.0) / 1000.0


@dataclass(frozen=True)
class MotorPosition:
    """A position read back from the servo.

    Attributes
    ----------
    raw : int
        Present Position (0..1023): log this, the angle steps quantise.
    gamma : float
        The scanner angle γ (rad) it stands for.
    status : MotorStatus
        Load, voltage and temperature from the same read.
    error_bits : int
        The ERR byte of that read's status packet: 0, or bits the configuration tolerates
        (:attr:`MotorConfig.tolerated_error_bits`); any other bit raised instead.
    """

    raw: int
    gamma: float
    status: MotorStatus
    error_bits: int = 0


@dataclass(frozen=True)
class MotorStatus:
    """Health readings of the servo.

    Attributes
    ----------
    load : float
        Present Load as a signed fraction of max torque (CCW positive).
    voltage_v : float
        Supply voltage, V.
    temperature_c : float
        Internal temperature, °C.
    """

    load: float
    voltage_v: float
    temperature_c: float


@runtime_checkable
class Motor(Protocol):
    """What the acquisition loop needs from the motor.

    Angles are the scanner angle γ in radians.  Implementations are context
    managers: torque on at ``__enter__`` (or construction), off at ``close()``.
    """

    @property
    def gamma_range(self) -> tuple[float, float]:
        """The γ interval moves are allowed in (configured range ∩ servo limits)."""
        ...

    def ping(self) -> int:
        """Model number of the servo (12 for an AX-12)."""
        ...

    def move_to(self, gamma: float) -> MotorPosition:
        """Move to ``gamma``, wait until stopped, return the position read back (the measured γ) and status."""
        ...

    def position(self) -> MotorPosition:
        """Present position read back from the servo, with status."""
        ...

    def status(self) -> MotorStatus:
        """Load, voltage and temperature."""
        ...

    def close(self) -> None: ...

    def __enter__(self) -> Self: ...

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None: ...
