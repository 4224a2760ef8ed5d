"""The scanners behind ``--device``: ``sim`` (the simulator directly), ``emulated`` (the real
drivers talking to emulators on ptys) and ``serial`` (the real drivers on hardware)."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from typing import TYPE_CHECKING

import numpy as np

from lelsonar.acquire.devices.motor import EMULATED_STALE_GUARD_S, DynamixelMotor, Motor, MotorConfig
from lelsonar.acquire.devices.sensor_board import SensorBoard, SensorBoardConfig, SerialSensorBoard
from lelsonar.acquire.emulate.ax12_emulator import AX12EmulatorConfig
from lelsonar.acquire.emulate.cli import EmulatedRig, emulated_rig
from lelsonar.acquire.emulate.sensor_board_emulator import SensorBoardEmulatorConfig, sim_shot_source
from lelsonar.acquire.scanner import MotorReading, ScannerInfo, StepMeasurement
from lelsonar.acquire.sim import SimConfig, simulate_step

if TYPE_CHECKING:
    from lelsonar.acquire.config import AcquireConfig

DEVICES = ("sim", "emulated", "serial")


def sim_info(cfg: SimConfig, device: str) -> ScannerInfo:
    return ScannerInfo(device=device, geometry=cfg.geometry, sample_rate=cfg.sample_rate,
                       window_samples=cfg.window_samples, air_temperature=cfg.temperature,
                       sound_speed=cfg.sound_speed)


class SimScanner:
    """The simulator as a scanner: no serial, no waiting — the fastest, for bulk runs.

    The servo is modelled as the AX-12 is: the goal rounds to a position unit,
    the array settles near it, and the measured γ is the unit read back.
    """

    def __init__(self, cfg: SimConfig, seed: int = 0) -> None:
        self.cfg = cfg
        self.info = sim_info(cfg, "sim")
        self._rng = np.random.default_rng(seed)

    def measure(self, step: int, gamma_commanded: float) -> StepMeasurement:
        servo = self.cfg.servo
        goal = servo.to_raw(gamma_commanded)
        gamma_true = float(servo.to_gamma(goal)) + float(self._rng.standard_normal()) * servo.position_error
        raw = int(np.clip(servo.to_raw(gamma_true), 0, 1023))
        t_ns = time.time_ns()
        shot = simulate_step(self.cfg, gamma_true, self._rng)
        return StepMeasurement(
            gamma_measured=float(servo.to_gamma(raw)),
            motor=MotorReading(present_position_raw=raw, load=0.0, voltage=12.0, temperature=313.15),
            time_of_flight=shot.tof, waveforms=shot.waveforms, t0=self.cfg.window_start, acquisition_time_ns=t_ns)

    def close(self) -> None:
        pass


class DeviceScanner:
    """The real drivers: move the servo, wait until still, fire the board (emulated or hardware).

    ``rig`` is the emulated servo and board behind the ports, if they are emulated
    (for fault injection and diagnostics); None on hardware.
    """

    def __init__(self, motor: Motor, board: SensorBoard, info: ScannerInfo, rig: EmulatedRig | None = None) -> None:
        self.motor = motor
        self.board = board
        self.info = info
        self.rig = rig

    def measure(self, step: int, gamma_commanded: float) -> StepMeasurement:
        pos = self.motor.move_to(gamma_commanded)
        t_ns = time.time_ns()
        shot = self.board.fire(step)
        s = pos.status
        return StepMeasurement(
            gamma_measured=pos.gamma,
            motor=MotorReading(present_position_raw=pos.raw, load=s.load, voltage=s.voltage_v,
                               temperature=s.temperature_c + 273.15, error_bits=pos.error_bits),
            time_of_flight=shot.tof_s, waveforms=shot.waveforms, t0=0.0, acquisition_time_ns=t_ns)

    def close(self) -> None:
        try:
            self.board.close()
        finally:
            self.motor.close()  # torque off


@contextmanager
def open_scanner(cfg: AcquireConfig, sim: SimConfig | None) -> Iterator[SimScanner | DeviceScanner]:
    """The scanner ``cfg.device`` names, closed (torque off, ports closed) on exit.

    ``sim`` drives ``sim`` and ``emulated``; ``serial`` takes everything from the rig
    (:func:`lelsonar.acquire.rig.serial_setup`) and ignores it.
    """
    if cfg.device == "serial":
        from lelsonar.acquire.rig import serial_setup

        setup = serial_setup(cfg)
        with ExitStack() as stack:
            motor = stack.enter_context(DynamixelMotor(setup.motor))
            board = stack.enter_context(SerialSensorBoard(setup.board))
            yield DeviceScanner(motor, board, setup.info, None)
        return
    if sim is None:
        raise ValueError(f"--device {cfg.device} needs a simulator configuration")
    if cfg.device == "sim":
        yield SimScanner(sim, cfg.seed)
        return
    with ExitStack() as stack:
        rig = None
        if cfg.device == "emulated":
            rig = stack.enter_context(emulated_rig(
                sim_shot_source(sim, np.random.default_rng(cfg.seed)),
                AX12EmulatorConfig(return_delay=0, initial_position=int(sim.servo.to_raw(sim.gamma_start))),
                SensorBoardEmulatorConfig(), zero_raw=int(sim.servo.to_raw(0.0))))
            motor_port, sensor_port = rig.motor.path, rig.board.path
            # A pty has no USB latency: a short packet timeout keeps the scan near the physical bound,
            # and a long late-reply window absorbs the emulator thread's scheduling delays on a loaded host.
            latency_ms, guard_s = 2.0, EMULATED_STALE_GUARD_S
        else:
            raise ValueError(f"unknown device {cfg.device!r}")
        lo, hi = sorted((sim.gamma_start, sim.gamma_stop))
        motor = stack.enter_context(DynamixelMotor(MotorConfig(
            port=motor_port, gamma_min=lo, gamma_max=hi, latency_timer_ms=latency_ms, stale_guard_s=guard_s,
            zero_raw=int(sim.servo.to_raw(0.0)))))
        board = stack.enter_context(SerialSensorBoard(SensorBoardConfig(
            port=sensor_port, n_samples=sim.window_samples, fs_hz=int(sim.sample_rate))))
        yield DeviceScanner(motor, board, sim_info(sim, cfg.device), rig)
