"""What the scan loop needs from a scanner, whatever drives it.

A :class:`Scanner` turns "go to γ and fire" into one :class:`StepMeasurement`.
Three implementations exist: the simulator directly (``sim``), the real drivers
talking to emulated devices on ptys (``emulated``), and the real drivers talking
to hardware (``serial``).  The scan loop cannot tell them apart.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from lelsonar.geometry import ArrayGeometry
from lelsonar.v1.scan_pb2 import PoseWithCovariance


@dataclass(frozen=True)
class ScannerInfo:
    """Static facts about a scanner, published in ``ScanStart``."""

    device: str  # "sim", "emulated" or "serial"
    geometry: ArrayGeometry
    sample_rate: float  # Hz
    window_samples: int
    air_temperature: float  # K
    sound_speed: float  # m/s
    pose: PoseWithCovariance | None = None  # the array frame (γ = 0) in a world frame, when known


@dataclass(frozen=True)
class MotorReading:
    """The servo's state after a move (see ``lelsonar.v1.MotorStatus``)."""

    present_position_raw: int
    load: float = 0.0  # signed fraction of max torque
    voltage: float = 0.0  # V
    temperature: float = 0.0  # K
    error_bits: int = 0


@dataclass(frozen=True)
class StepMeasurement:
    """One shot of every capsule at one motor position.

    Attributes
    ----------
    gamma_measured : float
        rad, from the motor's Present Position.
    motor : MotorReading
    time_of_flight : (n_capsules,) array
        Round-trip s; NaN where no echo crossed the threshold.
    waveforms : (n_capsules, n_samples) float32 array
        V.
    t0 : float
        s after firing of the first waveform sample.
    acquisition_time_ns : int
        Unix ns at firing.
    """

    gamma_measured: float
    motor: MotorReading
    time_of_flight: np.ndarray
    waveforms: np.ndarray
    t0: float
    acquisition_time_ns: int


class Scanner(Protocol):
    """A rotating array that can be moved and fired, step by step."""

    info: ScannerInfo

    def measure(
        self,
        step: int,
        gamma_commanded: float,
        *,
        next_gamma: float | None = None,
        while_listening: Callable[[], None] | None = None,
    ) -> StepMeasurement:
        """Move to ``gamma_commanded`` (rad), wait until still, fire, return the shot.

        ``next_gamma``: the next step's angle, which a scanner may move to once this shot's
        acoustic window is over (never during it).  ``while_listening``: the caller's work,
        which a scanner may run while the capsules listen; if it does not, the caller runs
        it after.  What either raises is raised as is.
        """
        ...

    def close(self) -> None:
        """Release the devices (torque off, ports closed)."""
        ...
