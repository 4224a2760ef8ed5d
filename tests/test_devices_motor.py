"""DynamixelMotor through the unmodified dynamixel-sdk against the AX-12 emulator on a pty."""

from __future__ import annotations

import math
import time

import pytest

from lelsonar.acquire.devices import ax12
from lelsonar.acquire.devices.motor import (
    AngleLimitError,
    DynamixelMotor,
    GammaOutOfRangeError,
    InputVoltageError,
    Motor,
    MotorConfig,
    MotorCommunicationError,
    MotorStatusError,
    MotorTimeoutError,
    OverheatingError,
    OverloadError,
    WrongModelError,
    status_error,
)
from lelsonar.acquire.emulate.ax12_emulator import AX12Emulator, AX12EmulatorConfig
from lelsonar.errors import ConfigError, DeviceError, DeviceTimeoutError

# A 22 ms packet timeout: it only costs time when a fault is injected, and leaves a loaded CPU room.
LATENCY_MS = 10.0


@pytest.fixture
def servo():
    with AX12Emulator(AX12EmulatorConfig(return_delay=0)) as emu:
        yield emu


def config(emu: AX12Emulator, **kw) -> MotorConfig:
    return MotorConfig(port=emu.path, latency_timer_ms=kw.pop("latency_timer_ms", LATENCY_MS), **kw)


def test_ping_returns_model_12_and_torque_follows_the_context(servo) -> None:
    with DynamixelMotor(config(servo)) as motor:
        assert isinstance(motor, Motor)
        assert motor.ping() == 12
        assert servo.read_register("torque_enable") == 1
    assert servo.read_register("torque_enable") == 0


def test_move_then_read_back_the_position(servo) -> None:
    with DynamixelMotor(config(servo)) as motor:
        target = math.radians(30.0)
        start = time.monotonic()
        reading = motor.move_to(target)
        elapsed = time.monotonic() - start
        goal = ax12.raw_from_gamma(target)
        assert reading.raw == goal == servo.present_position()
        assert reading.gamma == pytest.approx(ax12.gamma_from_raw(goal))
        assert abs(reading.gamma - target) <= ax12.RAD_PER_UNIT / 2
        # It waited for the emulated travel (30° at 59 rpm = 85 ms); how much longer is `lelsonar bench acquire`'s.
        travel = ax12.travel_time_s(512, goal, 0)
        assert travel * 0.95 <= elapsed
        assert motor.position() == reading


def test_status_reads_load_voltage_temperature(servo) -> None:
    servo.set_register("present_voltage", 117)
    servo.set_register("present_temperature", 41)
    with DynamixelMotor(config(servo)) as motor:
        s = motor.status()
        assert motor.position().status == s
    assert (s.voltage_v, s.temperature_c, s.load) == (pytest.approx(11.7), 41.0, 0.0)


def test_gamma_range_is_checked_before_moving(servo) -> None:
    servo.set_register("ccw_angle_limit", 700)  # γ ≤ 55°
    with DynamixelMotor(config(servo)) as motor:
        lo, hi = motor.gamma_range
        assert lo == pytest.approx(math.radians(-10.0))
        assert hi == pytest.approx(ax12.gamma_from_raw(700))
        seen = servo.packets_seen
        with pytest.raises(GammaOutOfRangeError, match="outside"):
            motor.move_to(math.radians(60.0))
        with pytest.raises(GammaOutOfRangeError):
            motor.move_to(math.nan)
        assert servo.packets_seen == seen  # nothing was sent
        assert servo.read_register("goal_position") == 512


@pytest.mark.parametrize(
    ("inject", "error"),
    [
        (lambda emu: emu.set_register("present_voltage", 40), InputVoltageError),
        (lambda emu: emu.set_register("present_temperature", 90), OverheatingError),
        (lambda emu: emu.inject_overload(), OverloadError),
    ],
)
def test_status_error_bits_surface_as_typed_errors(servo, inject, error) -> None:
    with DynamixelMotor(config(servo)) as motor:
        inject(servo)
        with pytest.raises(error) as info:
            motor.position()
        assert isinstance(info.value, MotorStatusError) and isinstance(info.value, DeviceError)
        assert info.value.bits & error.bit
        assert error.bit.name.lower() in info.value.names


def test_overload_drops_torque(servo) -> None:
    with DynamixelMotor(config(servo)) as motor:
        motor.move_to(0.2)
        servo.inject_overload()
        assert servo.read_register("torque_enable") == 0
        with pytest.raises(OverloadError, match="overload"):
            motor.move_to(0.5)


def test_angle_limit_bit_from_the_servo(servo) -> None:
    with DynamixelMotor(config(servo)) as motor:
        # The limits change behind the driver's back: its cached check passes, the servo refuses.
        servo.set_register("ccw_angle_limit", 600)
        with pytest.raises(AngleLimitError, match="angle limit"):
            motor.move_to(math.radians(40.0))
        assert servo.read_register("goal_position") == 512


def test_most_severe_bit_names_the_error() -> None:
    err = status_error(int(ax12.ErrorBit.ANGLE_LIMIT | ax12.ErrorBit.OVERLOAD), "ctx")
    assert isinstance(err, OverloadError) and err.names == ("angle_limit", "overload")


def test_dropped_replies_are_retried(servo) -> None:
    with DynamixelMotor(config(servo, retries=2)) as motor:
        servo.drop_next(2)
        assert motor.position().raw == 512
        assert motor.retries_used == 2
        servo.drop_next(3)
        with pytest.raises(MotorTimeoutError) as info:
            motor.position()
        assert isinstance(info.value, DeviceTimeoutError)


def test_garbage_before_a_reply_is_skipped(servo) -> None:
    with DynamixelMotor(config(servo)) as motor:
        servo.garbage_before_next(17, n=3)
        assert motor.ping() == 12
        assert motor.position().raw == 512


def test_late_reply_is_not_taken_as_the_next_answer(servo) -> None:
    """A reply arriving after the timeout must not answer the retry or the next request."""
    servo.set_register("present_voltage", 123)
    servo.set_register("present_temperature", 45)
    # 10 ms latency: a 22 ms timeout, and margins of one timeout either side of the late reply
    # (it comes after the timeout, and before the guard of two more timeouts ends), so a loaded CPU is no issue.
    cfg = config(servo, retries=0, latency_timer_ms=10.0)
    late = 2.0 * cfg.packet_timeout_s
    with DynamixelMotor(cfg) as motor:
        servo.answer_late(late)
        with pytest.raises(MotorTimeoutError):
            motor.read_register("present_voltage")
        assert motor.read_register("present_temperature") == 45
        assert motor.read_register("present_voltage") == 123
    # With retries, the same fault is absorbed and the answer is right.
    with DynamixelMotor(config(servo, retries=2, latency_timer_ms=10.0)) as motor:
        servo.answer_late(late)
        assert motor.read_register("present_voltage") == 123
        assert motor.read_register("present_temperature") == 45
        assert motor.retries_used >= 1


def test_without_the_guard_the_stale_reply_would_be_taken(servo) -> None:
    """The hazard the guard exists for: same-size reads, no guard, the late voltage answers 'temperature'."""
    servo.set_register("present_voltage", 123)
    servo.set_register("present_temperature", 45)
    cfg = config(servo, retries=0, stale_guard_s=0.0, latency_timer_ms=20.0)
    with DynamixelMotor(cfg) as motor:
        servo.answer_late(1.5 * cfg.packet_timeout_s)
        with pytest.raises(MotorTimeoutError):
            motor.read_register("present_voltage")
        assert motor.read_register("present_temperature") == 123


def test_wrong_model_and_bad_port(servo) -> None:
    servo.set_register("model_number", 29)  # an MX-28
    with pytest.raises(WrongModelError, match="not an AX-12"):
        DynamixelMotor(config(servo))
    with pytest.raises(MotorCommunicationError):
        DynamixelMotor(MotorConfig(port="/dev/does-not-exist"))


def test_config_is_validated() -> None:
    with pytest.raises(ConfigError, match="gamma_min"):
        MotorConfig(port="/dev/null", gamma_min=1.0, gamma_max=0.5)
    with pytest.raises(ConfigError, match="moving_speed"):
        MotorConfig(port="/dev/null", moving_speed=2000)
    assert MotorConfig(port="x").packet_timeout_s == pytest.approx(0.034)


