"""Both emulators running together, the sensor board reading γ from the servo: a rig on two ptys."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import dataclass

from lelsonar.acquire.devices import ax12
from lelsonar.acquire.emulate.ax12_emulator import AX12Emulator, AX12EmulatorConfig
from lelsonar.acquire.emulate.sensor_board_emulator import SensorBoardEmulator, SensorBoardEmulatorConfig, ShotSource


@dataclass(frozen=True)
class EmulatedRig:
    """A running servo emulator and sensor-board emulator, linked by the servo angle."""

    motor: AX12Emulator
    board: SensorBoardEmulator

    @property
    def paths(self) -> dict[str, str]:
        return {"motor": self.motor.path, "sensor_board": self.board.path}


@contextlib.contextmanager
def emulated_rig(
    shot_source: ShotSource,
    motor_config: AX12EmulatorConfig | None = None,
    board_config: SensorBoardEmulatorConfig | None = None,
    *,
    zero_raw: int = ax12.CENTER_RAW,
) -> Iterator[EmulatedRig]:
    """Start both emulators, the board reading γ from the servo (same ``zero_raw`` as the driver)."""
    with AX12Emulator(motor_config) as motor:
        with SensorBoardEmulator(shot_source, motor.gamma_source(zero_raw), board_config) as board:
            yield EmulatedRig(motor=motor, board=board)
