"""Physically based simulator of the rotating ultrasonic scanner.

Pure computation: a :class:`Scene` of finite panels, the four-capsule array on
an AX-12, air acoustics, echoes, times of flight and digitised waveforms, with
ground truth kept next to each sample.

>>> from lelsonar.sim import preset, simulate_scan
>>> scan = simulate_scan(preset("paper-test1"), seed=0)
"""

from lelsonar.signal.directivity import piston_directivity
from lelsonar.sim.acoustics import Acoustics, Receiver, sound_speed
from lelsonar.sim.calibrate import (
    PAPER_CALIBRATION_DISTANCES,
    CalibrationResult,
    EnergyShotSource,
    SimulatedWallShots,
    calibrate,
    calibrate_simulator,
    default_energy_model,
)
from lelsonar.sim.config import Servo, SimConfig
from lelsonar.sim.presets import preset, preset_names
from lelsonar.sim.scan import (
    EchoSource,
    EchoTable,
    ScanTruth,
    SimulatedScan,
    SimulatedStep,
    TruePlane,
    echo_table,
    simulate_scan,
    simulate_step,
)
from lelsonar.sim.scene import Edge, Panel, Scene
from lelsonar.sim.scenes import FAMILIES, SceneDraw, draw_scene, sample_scene, simulate_family_scene

__all__ = [
    "DEFAULT_ENERGY_MODEL",
    "FAMILIES",
    "PAPER_CALIBRATION_DISTANCES",
    "SceneDraw",
    "draw_scene",
    "sample_scene",
    "simulate_family_scene",
    "Acoustics",
    "CalibrationResult",
    "EchoSource",
    "EnergyShotSource",
    "EchoTable",
    "Edge",
    "Panel",
    "Receiver",
    "ScanTruth",
    "Scene",
    "Servo",
    "SimConfig",
    "SimulatedScan",
    "SimulatedStep",
    "SimulatedWallShots",
    "TruePlane",
    "calibrate",
    "calibrate_simulator",
    "default_energy_model",
    "echo_table",
    "piston_directivity",
    "preset",
    "preset_names",
    "simulate_scan",
    "simulate_step",
    "sound_speed",
]


def __getattr__(name: str):  # noqa: ANN202
    # DEFAULT_ENERGY_MODEL is calibrated on first use (calibrate.default_energy_model), not at import.
    if name == "DEFAULT_ENERGY_MODEL":
        return default_energy_model()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
