"""The scanners behind ``--device``: ``sim`` (the simulator directly), ``emulated`` (the real
drivers talking to emulators on ptys) and ``serial`` (the real drivers on hardware)."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from typing import TYPE_CHECKING

import numpy as np

from lelsonar.acquire.devices.dynamixel import DynamixelMotor
from lelsonar.acquire.devices.motor import (
    EMULATED_STALE_GUARD_S,
    Motor,
    MotorConfig,
    MotorError,
    MotorPosition,
)
from lelsonar.acquire.devices.sensor_board import SensorBoard, SensorBoardConfig, SerialSensorBoard
from lelsonar.acquire.emulate.ax12_emulator import AX12EmulatorConfig
from lelsonar.acquire.emulate.rig import EmulatedRig, emulated_rig
from lelsonar.acquire.emulate.sensor_board_emulator import SensorBoardEmulatorConfig, sim_shot_source
from lelsonar.acquire.rig import rig_links, serial_setup
from lelsonar.acquire.scanner import MotorReading, ScannerInfo, StepMeasurement
from lelsonar.sim import SimConfig, simulate_step

if TYPE_CHECKING:
    from lelsonar.acquire.config import AcquireConfig

DEVICES = ("sim", "emulated", "serial")


def sim_info(cfg: SimConfig, device: str) -> ScannerInfo:
    return ScannerInfo(
        device=device,
        geometry=cfg.geometry,
        sample_rate=cfg.sample_rate,
        window_samples=cfg.window_samples,
        air_temperature=cfg.temperature,
        sound_speed=cfg.sound_speed,
    )


class SimScanner:
    """The simulator as a scanner: no serial, no waiting — the fastest, for bulk runs.

    The servo is modelled as the AX-12 is: the goal rounds to a position unit,
    the array settles near it, and the measured γ is the unit read back.
    """

    def __init__(self, cfg: SimConfig, seed: int = 0) -> None:
        self.cfg = cfg
        self.info = sim_info(cfg, "sim")
        self._rng = np.random.default_rng(seed)

    def measure(
        self,
        step: int,
        gamma_commanded: float,
        *,
        next_gamma: float | None = None,
        while_listening: Callable[[], None] | None = None,
    ) -> StepMeasurement:
        servo = self.cfg.servo
        goal = servo.to_raw(gamma_commanded)
        gamma_true = float(servo.to_gamma(goal)) + float(self._rng.standard_normal()) * servo.position_error
        raw = int(np.clip(servo.to_raw(gamma_true), 0, 1023))
        t_ns = time.time_ns()
        shot = simulate_step(self.cfg, gamma_true, self._rng)
        return StepMeasurement(
            gamma_measured=float(servo.to_gamma(raw)),
            motor=MotorReading(present_position_raw=raw, load=0.0, voltage=12.0, temperature=313.15),
            time_of_flight=shot.tof,
            waveforms=shot.waveforms,
            t0=self.cfg.window_start,
            acquisition_time_ns=t_ns,
        )

    def close(self) -> None:
        pass


class DeviceScanner:
    """The real drivers: move the servo, wait until still, fire the board (emulated or hardware).

    ``rig`` is the emulated servo and board behind the ports, if they are emulated
    (for fault injection and diagnostics); None on hardware.

    With ``pipeline``, ``while_listening`` runs while the capsules listen, and (given a
    ``next_gamma``) the move to the next step starts as soon as this shot's answer begins
    to arrive, i.e. once its acoustic window is over, and runs while the frame crosses the
    link (:meth:`SerialSensorBoard.receive`); the next :meth:`measure` then fires at once
    from the position that move read back.  A motor fault in that move is raised by the
    next :meth:`measure`, the step it belongs to.  Without, one thing after the other.
    """

    def __init__(
        self,
        motor: Motor,
        board: SensorBoard,
        info: ScannerInfo,
        rig: EmulatedRig | None = None,
        *,
        pipeline: bool = True,
    ) -> None:
        self.motor = motor
        self.board = board
        self.info = info
        self.rig = rig
        self.pipeline = pipeline
        #: (goal γ, its read-back or the MotorError it raised) of a move made during the last transfer.
        self._ahead: tuple[float, MotorPosition | MotorError] | None = None

    def measure(
        self,
        step: int,
        gamma_commanded: float,
        *,
        next_gamma: float | None = None,
        while_listening: Callable[[], None] | None = None,
    ) -> StepMeasurement:
        pos = self._arrive(gamma_commanded)
        t_ns = time.time_ns()
        heard = self.rig.board.fires + 1 if self.rig is not None else 0
        pending = self.board.send_fire(step)
        ahead = None
        if self.pipeline:
            if while_listening is not None:
                if self.rig is not None:
                    # The emulators are threads of this process: let the board's take the FIRE (its window
                    # starts when it does) before the host's work holds the GIL for a millisecond; a board
                    # of its own hears it at once.  Bounded: a lost FIRE is the driver's business.
                    self.rig.board.wait_fires(heard, timeout=self.board.config.window_s / 2)
                while_listening()  # the host's own work, while the capsules listen
            if next_gamma is not None:
                ahead = lambda: self._move_ahead(next_gamma)  # noqa: E731
        shot = self.board.receive(pending, after_window=ahead)
        s = pos.status
        return StepMeasurement(
            gamma_measured=pos.gamma,
            motor=MotorReading(
                present_position_raw=pos.raw,
                load=s.load,
                voltage=s.voltage_v,
                temperature=s.temperature_c + 273.15,
                error_bits=pos.error_bits,
            ),
            time_of_flight=shot.tof_s,
            waveforms=shot.waveforms,
            t0=0.0,
            acquisition_time_ns=t_ns,
        )

    def _arrive(self, gamma: float) -> MotorPosition:
        """The servo at ``gamma``, still: from the move made ahead, or moved now."""
        ahead, self._ahead = self._ahead, None
        if ahead is not None and ahead[0] == gamma:
            if isinstance(ahead[1], MotorError):
                raise ahead[1]
            return ahead[1]
        return self.motor.move_to(gamma)

    def _move_ahead(self, gamma: float) -> None:
        try:
            self._ahead = (gamma, self.motor.move_to(gamma))
        except MotorError as exc:  # the shot in flight is sound; the next step reports the fault
            self._ahead = (gamma, exc)

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
        setup = serial_setup(cfg)
        with ExitStack() as stack:
            motor = stack.enter_context(DynamixelMotor(setup.motor))
            board = stack.enter_context(SerialSensorBoard(setup.board))
            yield DeviceScanner(motor, board, setup.info, None, pipeline=cfg.pipeline)
        return
    if sim is None:
        raise ValueError(f"--device {cfg.device} needs a simulator configuration")
    if cfg.device == "sim":
        yield SimScanner(sim, cfg.seed)
        return
    with ExitStack() as stack:
        rig = None
        motor_link, board_link = rig_links(cfg.rig)
        if cfg.device == "emulated":
            rig = stack.enter_context(
                emulated_rig(
                    sim_shot_source(sim, np.random.default_rng(cfg.seed)),
                    emulated_servo(cfg, sim),
                    SensorBoardEmulatorConfig(link=board_link if cfg.paced_links else None),
                    zero_raw=int(sim.servo.to_raw(0.0)),
                )
            )
            motor_port, sensor_port = rig.motor.path, rig.board.path
            # A pty has no USB latency: a short packet timeout keeps the scan near the physical bound,
            # and a long late-reply window absorbs the emulator thread's scheduling delays on a loaded host.
            latency_ms, guard_s = 2.0, EMULATED_STALE_GUARD_S
        else:
            raise ValueError(f"unknown device {cfg.device!r}")
        lo, hi = sorted((sim.gamma_start, sim.gamma_stop))
        motor = stack.enter_context(
            DynamixelMotor(
                MotorConfig(
                    port=motor_port,
                    gamma_min=lo,
                    gamma_max=hi,
                    latency_timer_ms=latency_ms,
                    stale_guard_s=guard_s,
                    zero_raw=int(sim.servo.to_raw(0.0)),
                    baudrate=motor_link.baudrate,
                )
            )
        )
        board = stack.enter_context(
            SerialSensorBoard(
                SensorBoardConfig(
                    port=sensor_port, n_samples=sim.window_samples, fs_hz=int(sim.sample_rate), link=board_link
                )
            )
        )
        yield DeviceScanner(motor, board, sim_info(sim, cfg.device), rig, pipeline=cfg.pipeline)


def emulated_servo(cfg: AcquireConfig, sim: SimConfig) -> AX12EmulatorConfig:
    """The AX-12 that ``--device emulated`` drives: at the schedule's start, Return Delay 0 (as one would
    set a real one for scanning), on the rig's bus if ``cfg.paced_links``."""
    motor_link, _ = rig_links(cfg.rig)
    return AX12EmulatorConfig(
        return_delay=0,
        initial_position=int(sim.servo.to_raw(sim.gamma_start)),
        link=motor_link if cfg.paced_links else None,
    )
