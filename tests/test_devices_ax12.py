"""The AX-12 table and units, and the emulator's protocol 1.0, byte for byte (no SDK)."""

from __future__ import annotations

import math
import os
import select
import time

import pytest

from lelsonar.acquire.devices import ax12
from lelsonar.acquire.emulate.ax12_emulator import AX12Emulator, AX12EmulatorConfig, checksum, encode_packet
from lelsonar.errors import ConfigError


# --- table and units ------------------------------------------------------------------
def test_control_table_matches_the_datasheet_addresses() -> None:
    expect = {
        "model_number": (0, 2, 12),
        "id": (3, 1, 1),
        "baud_rate": (4, 1, 1),
        "return_delay_time": (5, 1, 250),
        "cw_angle_limit": (6, 2, 0),
        "ccw_angle_limit": (8, 2, 1023),
        "status_return_level": (16, 1, 2),
        "torque_enable": (24, 1, 0),
        "led": (25, 1, 0),
        "goal_position": (30, 2, None),
        "moving_speed": (32, 2, None),
        "torque_limit": (34, 2, None),
        "present_position": (36, 2, None),
        "present_speed": (38, 2, None),
        "present_load": (40, 2, None),
        "present_voltage": (42, 1, None),
        "present_temperature": (43, 1, None),
        "moving": (46, 1, 0),
        "lock": (47, 1, 0),
        "punch": (48, 2, 32),
    }
    for name, (address, size, default) in expect.items():
        reg = ax12.register(name)
        assert (reg.address, reg.size) == (address, size), name
        if default is not None:
            assert reg.default == default, name
    assert ax12.register("model_number").access is ax12.Access.R
    assert ax12.register("present_position").area is ax12.Area.RAM
    assert ax12.register("ccw_angle_limit").area is ax12.Area.EEPROM
    # No two registers overlap.
    spans = sorted((r.address, r.end) for r in ax12.CONTROL_TABLE)
    assert all(a_end <= b_start for (_, a_end), (b_start, _) in zip(spans, spans[1:]))
    with pytest.raises(KeyError, match="goal_positon"):
        ax12.register("goal_positon")


def test_units_512_is_150_degrees_and_round_trips() -> None:
    assert math.degrees(ax12.raw_to_rad(512)) == pytest.approx(150.0)
    assert math.degrees(ax12.raw_to_rad(1)) == pytest.approx(0.293, abs=1e-3)
    assert ax12.rad_to_raw(math.radians(150.0)) == 512
    assert ax12.rad_to_raw(math.radians(400.0)) == 1023 and ax12.rad_to_raw(-1.0) == 0
    for raw in (0, 1, 341, 512, 1023):
        assert ax12.rad_to_raw(ax12.raw_to_rad(raw)) == raw
    assert ax12.gamma_from_raw(512 + 307, 512) == pytest.approx(math.radians(307 * 300 / 1024))
    assert ax12.raw_from_gamma(math.radians(120.0), 0) == 410  # 120° is 409.6 units: steps quantise


def test_speed_model_saturates_at_the_no_load_speed() -> None:
    assert ax12.speed_rad_s(0) == pytest.approx(59 * 2 * math.pi / 60)
    assert ax12.speed_rad_s(100) == pytest.approx(11.1 * 2 * math.pi / 60)
    assert ax12.speed_rad_s(1023) == ax12.speed_rad_s(0)  # 114 rpm asked, 59 rpm delivered
    # 60° at 59 rpm: 0.169 s.
    assert ax12.travel_time_s(0, round(60 / ax12.DEG_PER_UNIT), 0) == pytest.approx(60 / 354, rel=1e-2)
    assert ax12.signed_load(0x400 | 1023) == pytest.approx(-1.0) and ax12.signed_load(511) == pytest.approx(
        0.4995, abs=1e-3
    )
    assert ax12.error_bit_names(0b0100010) == ("angle_limit", "overload")


def test_emulator_config_is_validated() -> None:
    with pytest.raises(ConfigError, match="cw_limit"):
        AX12EmulatorConfig(cw_limit=600, ccw_limit=500)
    with pytest.raises(ConfigError, match="status_return_level"):
        AX12EmulatorConfig(status_return_level=3)


# --- the emulator on the wire ------------------------------------------------------------
class RawPort:
    """Plain fd I/O on the emulator's pty, to send what the SDK never would."""

    def __init__(self, path: str) -> None:
        self.fd = os.open(path, os.O_RDWR | os.O_NOCTTY)

    def close(self) -> None:
        os.close(self.fd)

    def send(self, data: bytes) -> None:
        os.write(self.fd, data)

    def recv(self, n: int, timeout: float = 1.0) -> bytes:
        out = b""
        deadline = time.monotonic() + timeout
        while len(out) < n:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([self.fd], [], [], left)[0]:
                break
            out += os.read(self.fd, n - len(out))
        return out


@pytest.fixture
def servo():
    with AX12Emulator(AX12EmulatorConfig(return_delay=0)) as emu:
        port = RawPort(emu.path)
        try:
            yield emu, port
        finally:
            port.close()


def status(motor_id: int, error: int, params: bytes = b"") -> bytes:
    return encode_packet(motor_id, error, params)


def assert_no_reply_before_a_marker(port: RawPort) -> None:
    """What was sent before got no reply: the emulator answers in order, so the next bytes on the
    line must be the reply to this marker, a READ of the model number whose 8-byte reply no
    PING or WRITE status looks like (an explicit protocol state, not a quiet period)."""
    port.send(encode_packet(1, 0x02, bytes((0, 2))))
    assert port.recv(8, timeout=10.0) == status(1, 0, bytes((12, 0)))


def test_ping_and_read_model_bytes(servo) -> None:
    emu, port = servo
    port.send(bytes.fromhex("FF FF 01 02 01 FB"))  # the datasheet's PING example
    assert port.recv(6) == bytes.fromhex("FF FF 01 02 00 FC")
    port.send(encode_packet(1, 0x02, bytes((0, 2))))
    assert port.recv(8) == status(1, 0, bytes((12, 0)))


def test_resyncs_on_garbage_and_ignores_other_ids(servo) -> None:
    emu, port = servo
    port.send(b"\x00\x13\xff\x42" + encode_packet(2, 0x01) + b"\xff" + encode_packet(1, 0x01))
    assert port.recv(6) == status(1, 0)
    assert emu.wait_packets(2)  # both PINGs were parsed
    assert_no_reply_before_a_marker(port)  # ID 2 got nothing


def test_checksum_and_instruction_errors(servo) -> None:
    emu, port = servo
    bad = bytearray(encode_packet(1, 0x03, bytes((30, 0, 1))))
    bad[-1] ^= 0xFF
    port.send(bytes(bad))
    assert port.recv(6) == status(1, ax12.ErrorBit.CHECKSUM)
    assert emu.read_register("goal_position") == 512  # not executed
    port.send(encode_packet(1, 0x7E))
    assert port.recv(6) == status(1, ax12.ErrorBit.INSTRUCTION)
    port.send(encode_packet(1, 0x05))  # ACTION with nothing registered
    assert port.recv(6) == status(1, ax12.ErrorBit.INSTRUCTION)


def test_write_range_and_angle_limit_errors(servo) -> None:
    emu, port = servo
    port.send(encode_packet(1, 0x03, bytes((0, 13, 0))))  # model number is read-only
    assert port.recv(6) == status(1, ax12.ErrorBit.RANGE)
    port.send(encode_packet(1, 0x03, bytes((24, 2))))  # torque enable is 0/1
    assert port.recv(6) == status(1, ax12.ErrorBit.RANGE)
    emu.set_register("cw_angle_limit", 400)
    port.send(encode_packet(1, 0x03, bytes((30, 100, 1))))  # goal 356 < 400
    assert port.recv(6) == status(1, ax12.ErrorBit.ANGLE_LIMIT)
    assert emu.read_register("goal_position") == 512


def test_broadcast_sync_write_and_reg_write_action(servo) -> None:
    emu, port = servo
    # SYNC_WRITE LED: id 1 → 1, id 2 → 0; broadcast, so no reply.
    port.send(encode_packet(ax12.BROADCAST_ID, 0x83, bytes((25, 1, 1, 1, 2, 0))))
    assert_no_reply_before_a_marker(port)
    assert emu.read_register("led") == 1
    port.send(encode_packet(1, 0x04, bytes((25, 0))))
    assert port.recv(6) == status(1, 0)
    assert emu.read_register("led") == 1 and emu.read_register("registered") == 1
    port.send(encode_packet(ax12.BROADCAST_ID, 0x05))
    assert_no_reply_before_a_marker(port)
    assert emu.read_register("led") == 0 and emu.read_register("registered") == 0


def test_status_return_level_one_answers_reads_only(servo) -> None:
    emu, port = servo
    emu.set_register("status_return_level", 1)
    port.send(encode_packet(1, 0x03, bytes((25, 1))))
    assert_no_reply_before_a_marker(port)
    port.send(encode_packet(1, 0x02, bytes((25, 1))))
    assert port.recv(7) == status(1, 0, b"\x01")


class ManualClock:
    """The emulator's motion clock, advanced by the test."""

    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


def test_motion_takes_time_at_the_moving_speed() -> None:
    clock = ManualClock()
    with AX12Emulator(AX12EmulatorConfig(return_delay=0), clock=clock) as emu:
        port = RawPort(emu.path)
        try:
            port.send(encode_packet(1, 0x03, bytes((24, 1))))
            assert port.recv(6) == status(1, 0)
            port.send(encode_packet(1, 0x03, bytes((32, 200, 0))))  # 22.2 rpm: 133 °/s, 455 units/s
            assert port.recv(6) == status(1, 0)
            port.send(encode_packet(1, 0x03, bytes((30,)) + (612).to_bytes(2, "little")))
            assert port.recv(6) == status(1, 0)
            expected = ax12.travel_time_s(512, 612, 200)
            assert expected == pytest.approx(100 / (200 * 0.111 * 6 / ax12.DEG_PER_UNIT))  # 0.22 s
            assert emu.read_register("moving") == 1 and emu.present_position() == 512
            # Linear at the Moving Speed: a quarter of the way after a quarter of the travel time ...
            clock.t += expected / 4
            assert emu.read_register("moving") == 1 and emu.present_position() == 512 + 25
            # ... what the driver reads on the wire too ...
            port.send(encode_packet(1, 0x02, bytes((36, 2))))
            assert port.recv(8) == status(1, 0, (537).to_bytes(2, "little"))
            # ... still moving just before the end, stopped at the goal after it.
            clock.t += expected * 3 / 4 - 1e-3
            assert emu.read_register("moving") == 1 and emu.present_position() == 612
            clock.t += 2e-3
            assert emu.read_register("moving") == 0 and emu.present_position() == 612
        finally:
            port.close()


def test_return_delay_is_honoured() -> None:
    with AX12Emulator(AX12EmulatorConfig(return_delay=254)) as emu:  # 508 µs
        port = RawPort(emu.path)
        try:
            times = []
            for _ in range(5):
                t = time.perf_counter()
                port.send(encode_packet(1, 0x01))
                assert port.recv(6) == status(1, 0)
                times.append(time.perf_counter() - t)
            assert min(times) >= 0.0005
        finally:
            port.close()


def test_checksum_helper() -> None:
    assert checksum(bytes((1, 2, 1))) == 0xFB
