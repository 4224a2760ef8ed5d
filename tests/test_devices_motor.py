"""DynamixelMotor through the unmodified dynamixel-sdk against the AX-12 emulator on a pty."""

from __future__ import annotations

import math
import time

import pytest

from lelsonar.acquire.devices import ax12
from lelsonar.acquire.devices.dynamixel import DynamixelMotor
from lelsonar.acquire.devices.motor import (
    AngleLimitError,
    GammaOutOfRangeError,
    InputVoltageError,
    Motor,
    MotorCommunicationError,
    MotorConfig,
    MotorStatusError,
    MotorTimeoutError,
    OverheatingError,
    OverloadError,
    WrongModelError,
    status_error,
)
from lelsonar.acquire.emulate.ax12_emulator import AX12Emulator, AX12EmulatorConfig
from lelsonar.errors import ConfigError, DeviceError, DeviceTimeoutError

# A 22 ms packet timeout: it only costs time when a fault is injected.
LATENCY_MS = 10.0
# The late-reply window: the emulator's thread shares a possibly loaded host (starved up to
# 164 ms under two CPU hogs), so its replies may come well after the packet timeout.  The window
# only costs time when a reply is really lost (an injected drop).
WINDOW_S = 0.5


@pytest.fixture
def servo():
    with AX12Emulator(AX12EmulatorConfig(return_delay=0)) as emu:
        yield emu


def config(emu: AX12Emulator, **kw) -> MotorConfig:
    return MotorConfig(
        port=emu.path,
        latency_timer_ms=kw.pop("latency_timer_ms", LATENCY_MS),
        stale_guard_s=kw.pop("stale_guard_s", WINDOW_S),
        **kw,
    )


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
        # The dropped replies never come: nothing was binned, nothing is waiting for the next request.
        assert motor.stale_replies_binned == 0
        assert motor.read_register("present_voltage") == 120
        servo.drop_next(3)
        with pytest.raises(MotorTimeoutError) as info:
            motor.position()
        assert isinstance(info.value, DeviceTimeoutError)


def test_garbage_before_a_reply_is_skipped(servo) -> None:
    with DynamixelMotor(config(servo)) as motor:
        servo.garbage_before_next(17, n=3)
        assert motor.ping() == 12
        assert motor.position().raw == 512


@pytest.fixture
def readings(servo):
    """Voltage and temperature: two 1-byte reads whose replies have the same size, so only the value
    tells one answer from the other."""
    servo.set_register("present_voltage", 123)
    servo.set_register("present_temperature", 45)
    return servo


def test_a_late_reply_answers_its_own_request_and_no_other(readings, monkeypatch) -> None:
    """The reply comes only after the SDK's packet timeout, while the driver waits it out:
    it is the answer to the one request in flight (no resend, no error), and the next
    request gets its own answer.  Ordered by protocol state, not by the clock: the reply
    is held until the driver has timed out and is listening."""
    servo = readings
    with DynamixelMotor(config(servo, retries=0, stale_guard_s=5.0)) as motor:
        listen = motor._listen

        def release_then_listen(parse):
            servo.release_held()  # the SDK has given up on the reply: let it come now
            return listen(parse)

        monkeypatch.setattr(motor, "_listen", release_then_listen)
        servo.hold_next(1)
        assert motor.read_register("present_voltage") == 123
        assert (motor.late_replies, motor.retries_used) == (1, 0)
        assert motor.read_register("present_temperature") == 45
        assert motor.read_register("present_voltage") == 123


def test_a_reply_crossing_the_resend_is_binned_not_taken_by_the_next_request(readings) -> None:
    """No reply within the window: the driver resends.  The first reply then arrives just before
    the second (it crossed the resend on the line): one answer is used, the other binned, and
    the next request, of the same size, gets its own value."""
    servo = readings
    with DynamixelMotor(config(servo, retries=1)) as motor:
        servo.hold_next(1, until_next_packet=True)
        assert motor.read_register("present_voltage") == 123
        assert (motor.retries_used, motor.stale_replies_binned) == (1, 1)
        assert motor.read_register("present_temperature") == 45


def test_without_the_guard_the_crossing_reply_would_be_taken(readings) -> None:
    """The hazard the window exists for: no guard, and the late voltage answers 'temperature'."""
    servo = readings
    # A 202 ms packet timeout: the next read's own answer cannot time out on a loaded host.
    with DynamixelMotor(config(servo, retries=0, stale_guard_s=0.0, latency_timer_ms=100.0)) as motor:
        servo.hold_next(1, until_next_packet=True)
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
