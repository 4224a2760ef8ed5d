"""The Dynamixel AX-12(A) as data: control table, error bits, units, speed model.

Nothing here talks to a port.  The driver (:mod:`lelsonar.acquire.devices.dynamixel`)
and the emulator (:mod:`lelsonar.acquire.emulate.ax12_emulator`) both read this
table, so they cannot drift apart.

Source: ROBOTIS e-Manual, AX-12/AX-12A control table (protocol 1.0),
https://emanual.robotis.com/docs/en/dxl/ax/ax-12a/ .  The SDK's own protocol-1.0
examples use X-series addresses, which are wrong for the AX.

Units
-----
Positions run 0–1023 over 0–300°, with 512 = 150°, so one unit is
300/1024 ≈ 0.293° (the datasheet rounds it to 0.29°).  The scanner angle γ is
the servo angle measured from a mount-dependent *zero* position
(``zero_raw``), counter-clockwise positive, in radians.

Speed model
-----------
Moving Speed (address 32) is 0.111 rpm per unit, so the register can ask for up
to 1023 × 0.111 ≈ 114 rpm, but the motor itself saturates at its no-load speed,
59 rpm at 12 V (datasheet).  Value 0 means "no speed control", i.e. the no-load
speed.  We therefore model the travel speed as
``min(value × 0.111, 59) rpm`` (``59 rpm`` for 0): 59 rpm is 354 °/s, so 60°
takes 0.169 s and the 120° scan sweep 0.34 s of pure travel.  Acceleration and
compliance settling are not modelled; the driver adds a margin for them.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

#: Model number reported at address 0 (and by PING via the SDK).
MODEL_NUMBER = 12
#: Broadcast ID: instructions sent to it get no status packet.
BROADCAST_ID = 0xFE
#: Highest valid position value, and the angle it maps to.
POSITION_MAX = 1023
#: Degrees per position unit: 512 units = 150°.
DEG_PER_UNIT = 300.0 / 1024.0
RAD_PER_UNIT = math.radians(DEG_PER_UNIT)
#: Raw position of the servo's mechanical centre (150°).
CENTER_RAW = 512
#: rpm per Moving Speed unit (datasheet).
RPM_PER_SPEED_UNIT = 0.111
#: No-load speed at 12 V (datasheet); the motor cannot turn faster whatever the register says.
NO_LOAD_RPM = 59.0
#: Return Delay Time unit (address 5), seconds.
RETURN_DELAY_UNIT_S = 2e-6
#: Present Load / Present Speed: bit 10 is the direction, bits 0–9 the magnitude.
DIRECTION_BIT = 1 << 10


class Area(enum.Enum):
    """Where a register lives: EEPROM survives power-off, RAM does not."""

    EEPROM = "eeprom"
    RAM = "ram"


class Access(enum.Enum):
    R = "r"
    RW = "rw"


@dataclass(frozen=True)
class Register:
    """One control-table entry.

    Attributes
    ----------
    name : str
        Snake-case name used throughout lelsonar.
    address : int
        First byte in the control table.
    size : int
        1 or 2 bytes, little-endian.
    area, access : Area, Access
    default : int
        Value after power-on (what the emulator starts with).
    minimum, maximum : int
        Valid range for a WRITE; outside it the servo answers with the range error bit.
    """

    name: str
    address: int
    size: int
    area: Area
    access: Access
    default: int
    minimum: int = 0
    maximum: int = 0xFF

    def __post_init__(self) -> None:
        if self.size not in (1, 2):
            raise ValueError(f"register {self.name}: size must be 1 or 2, not {self.size}")
        if not 0 <= self.address < 50:
            raise ValueError(f"register {self.name}: address {self.address} outside the AX-12 table")

    @property
    def end(self) -> int:
        """One past the last byte."""
        return self.address + self.size


_E, _R = Area.EEPROM, Area.RAM
_RO, _RW = Access.R, Access.RW

#: The AX-12A control table, in address order.
CONTROL_TABLE: tuple[Register, ...] = (
    Register("model_number", 0, 2, _E, _RO, MODEL_NUMBER, 0, 0xFFFF),
    # Firmware varies between units; the emulator reports this value.
    Register("firmware_version", 2, 1, _E, _RO, 24),
    Register("id", 3, 1, _E, _RW, 1, 0, 253),
    Register("baud_rate", 4, 1, _E, _RW, 1, 0, 254),  # 1 = 1 Mbps (2000000 / (value + 1))
    Register("return_delay_time", 5, 1, _E, _RW, 250, 0, 254),  # 2 µs units
    Register("cw_angle_limit", 6, 2, _E, _RW, 0, 0, POSITION_MAX),
    Register("ccw_angle_limit", 8, 2, _E, _RW, POSITION_MAX, 0, POSITION_MAX),
    Register("temperature_limit", 11, 1, _E, _RW, 70, 0, 150),  # °C
    Register("min_voltage_limit", 12, 1, _E, _RW, 60, 50, 160),  # 0.1 V
    Register("max_voltage_limit", 13, 1, _E, _RW, 140, 50, 160),  # 0.1 V
    Register("max_torque", 14, 2, _E, _RW, 1023, 0, 1023),
    Register("status_return_level", 16, 1, _E, _RW, 2, 0, 2),  # 0 none, 1 PING+READ, 2 all
    Register("alarm_led", 17, 1, _E, _RW, 36, 0, 127),
    Register("shutdown", 18, 1, _E, _RW, 36, 0, 127),
    Register("torque_enable", 24, 1, _R, _RW, 0, 0, 1),
    Register("led", 25, 1, _R, _RW, 0, 0, 1),
    Register("cw_compliance_margin", 26, 1, _R, _RW, 1),
    Register("ccw_compliance_margin", 27, 1, _R, _RW, 1),
    Register("cw_compliance_slope", 28, 1, _R, _RW, 32, 1, 254),
    Register("ccw_compliance_slope", 29, 1, _R, _RW, 32, 1, 254),
    Register("goal_position", 30, 2, _R, _RW, CENTER_RAW, 0, POSITION_MAX),
    Register("moving_speed", 32, 2, _R, _RW, 0, 0, 1023),
    Register("torque_limit", 34, 2, _R, _RW, 1023, 0, 1023),
    Register("present_position", 36, 2, _R, _RO, CENTER_RAW, 0, POSITION_MAX),
    Register("present_speed", 38, 2, _R, _RO, 0, 0, 2047),
    Register("present_load", 40, 2, _R, _RO, 0, 0, 2047),
    Register("present_voltage", 42, 1, _R, _RO, 120),  # 0.1 V
    Register("present_temperature", 43, 1, _R, _RO, 35),  # °C
    Register("registered", 44, 1, _R, _RO, 0, 0, 1),
    Register("moving", 46, 1, _R, _RO, 0, 0, 1),
    Register("lock", 47, 1, _R, _RW, 0, 0, 1),
    Register("punch", 48, 2, _R, _RW, 32, 32, 1023),
)

#: Registers by name.
REGISTERS: dict[str, Register] = {r.name: r for r in CONTROL_TABLE}
#: Size of the table in bytes (addresses 0..49).
TABLE_SIZE = 50


def register(name: str) -> Register:
    """Look a register up by name, with a helpful error."""
    try:
        return REGISTERS[name]
    except KeyError:
        raise KeyError(f"no AX-12 register {name!r}; known: {', '.join(REGISTERS)}") from None


class Instruction(enum.IntEnum):
    """Protocol 1.0 instruction codes."""

    PING = 0x01
    READ = 0x02
    WRITE = 0x03
    REG_WRITE = 0x04
    ACTION = 0x05
    RESET = 0x06
    SYNC_WRITE = 0x83


class ErrorBit(enum.IntFlag):
    """Bits of the ERR byte of a protocol 1.0 status packet."""

    INPUT_VOLTAGE = 1 << 0
    ANGLE_LIMIT = 1 << 1
    OVERHEATING = 1 << 2
    RANGE = 1 << 3
    CHECKSUM = 1 << 4
    OVERLOAD = 1 << 5
    INSTRUCTION = 1 << 6


def error_bit_names(bits: int) -> tuple[str, ...]:
    """Names of the set error bits, lowest bit first (e.g. ``("angle_limit",)``)."""
    return tuple(b.name.lower() for b in ErrorBit if bits & b and b.name is not None)


# --- units -------------------------------------------------------------------------
def raw_to_rad(raw: int) -> float:
    """Servo angle in radians for a position value (0 → 0 rad, 512 → 150°)."""
    return raw * RAD_PER_UNIT


def rad_to_raw(angle: float) -> int:
    """Nearest position value for a servo angle in radians, clipped to 0..1023."""
    return min(POSITION_MAX, max(0, round(angle / RAD_PER_UNIT)))


def gamma_from_raw(raw: int, zero_raw: int = CENTER_RAW) -> float:
    """Scanner angle γ (rad) of a position value, with γ = 0 at ``zero_raw``."""
    return (raw - zero_raw) * RAD_PER_UNIT


def raw_from_gamma(gamma: float, zero_raw: int = CENTER_RAW) -> int:
    """Nearest position value for a scanner angle γ (rad); not clipped."""
    return zero_raw + round(gamma / RAD_PER_UNIT)


def speed_rad_s(moving_speed: int, no_load_rpm: float = NO_LOAD_RPM) -> float:
    """Travel speed (rad/s) for a Moving Speed value, saturating at the no-load speed."""
    rpm = no_load_rpm if moving_speed == 0 else min(moving_speed * RPM_PER_SPEED_UNIT, no_load_rpm)
    return rpm * 2.0 * math.pi / 60.0


def speed_units_per_s(moving_speed: int, no_load_rpm: float = NO_LOAD_RPM) -> float:
    """Travel speed in position units per second."""
    return speed_rad_s(moving_speed, no_load_rpm) / RAD_PER_UNIT


def travel_time_s(from_raw: int, to_raw: int, moving_speed: int, no_load_rpm: float = NO_LOAD_RPM) -> float:
    """Time to travel between two positions at constant speed (no acceleration)."""
    return abs(to_raw - from_raw) / speed_units_per_s(moving_speed, no_load_rpm)


def signed_load(raw: int) -> float:
    """Present Load as a signed fraction of max torque (CCW positive, bit 10 = CW)."""
    magnitude = (raw & 0x3FF) / 1023.0
    return -magnitude if raw & DIRECTION_BIT else magnitude


#: Bytes of a protocol-1.0 packet around its parameters: FF FF ID LEN INSTR/ERR … CKSUM.
PACKET_OVERHEAD = 6


def packet_size(n_params: int) -> int:
    """Bytes on the bus of a protocol-1.0 packet with ``n_params`` parameters.

    An instruction's parameters: READ has 2 (address, length), WRITE 1 + the data; a
    status packet's are the data read (none for PING or a WRITE's acknowledgement).
    """
    return PACKET_OVERHEAD + n_params


#: What the driver reads back in one READ per poll of a move: Present Position .. Moving (36–46, 11 bytes;
#: 45 is reserved), so each sample gets position, load, voltage and temperature from the read that saw it stop.
MOVE_READBACK_ADDRESS = register("present_position").address
MOVE_READBACK_BYTES = register("moving").end - MOVE_READBACK_ADDRESS
