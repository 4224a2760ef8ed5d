"""Configuration of a simulated scan: scene, array, servo, air, receiver, window.

Frozen dataclasses, validated on creation (:class:`lelsonar.errors.ConfigError`).
Change one field with :func:`dataclasses.replace`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from lelsonar.errors import ConfigError
from lelsonar.geometry import ArrayGeometry
from lelsonar.sim.acoustics import Acoustics, Receiver, sound_speed
from lelsonar.sim.scene import Scene

#: AX-12 resolution: 300° over 1024 units, in degrees per unit.
AX12_DEG_PER_UNIT = 300.0 / 1024.0
#: AX-12 raw position of the middle of its range (150°).
AX12_CENTER_RAW = 512


class Rig(Protocol):
    """What the receiver chain needs of a simulated rig (:class:`SimConfig`, or a world's rig)."""

    @property
    def acoustics(self) -> Acoustics: ...

    @property
    def receiver(self) -> Receiver: ...

    @property
    def sample_rate(self) -> float: ...

    @property
    def window_samples(self) -> int: ...

    @property
    def window_start(self) -> float: ...

    @property
    def sound_speed(self) -> float: ...


@dataclass(frozen=True)
class Servo:
    """The AX-12 that turns the array, and how it is mounted.

    Mounting: ``γ = (raw − 512)·300/1024° + mount_offset``.  With the default
    ``mount_offset = 0`` the servo's centre (raw 512 = 150°) points the beams
    along +y (γ = 0), and a [-10°, 110°] scan uses raw 478…887, inside 0…1023.

    The goal position is rounded to a whole unit, so the array really sits on
    the 0.293° grid; ``position_error`` (rad, standard deviation) then models
    the compliance dead band around the goal.  The measured γ is the present
    position read back, again a whole unit (so the read-back is what is logged).

    Parameters
    ----------
    mount_offset : float
        γ at raw 512, rad.
    position_error : float
        Standard deviation of the true position around the goal, rad.
    """

    mount_offset: float = 0.0
    position_error: float = 0.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.mount_offset) and abs(self.mount_offset) <= math.pi):
            raise ConfigError(f"Servo.mount_offset must be within ±π rad, got {self.mount_offset!r}")
        if not (math.isfinite(self.position_error) and 0 <= self.position_error <= math.radians(5)):
            raise ConfigError(f"Servo.position_error must be in [0, 5°] (rad), got {self.position_error!r}")

    def to_raw(self, gamma: np.ndarray | float) -> np.ndarray:
        """Nearest AX-12 position unit for γ (rad); not clipped."""
        unit = math.radians(AX12_DEG_PER_UNIT)
        return np.rint(AX12_CENTER_RAW + (np.asarray(gamma, dtype=float) - self.mount_offset) / unit).astype(np.int64)

    def to_gamma(self, raw: np.ndarray | int) -> np.ndarray:
        """γ (rad) of AX-12 position units."""
        unit = math.radians(AX12_DEG_PER_UNIT)
        return (np.asarray(raw, dtype=float) - AX12_CENTER_RAW) * unit + self.mount_offset


@dataclass(frozen=True)
class SimConfig:
    """Everything that defines a simulated scan.

    Parameters
    ----------
    scene : Scene
        What is in front of the array; default the paper's L.
    geometry : ArrayGeometry
        Capsule positions (four on x, 8 cm apart; radial offset 3 cm).
    gamma_start, gamma_stop : float
        Commanded scan range, rad (the paper: −10° to 110°).
    steps : int
        Number of shots, evenly spaced from start to stop inclusive.
    temperature : float
        Air temperature, **kelvin** (293.15 K = 20 °C).
    sample_rate : float
        ADC rate, Hz.
    window_samples : int
        Samples per waveform; 3500 at 200 kS/s is 17.5 ms, ranges to ≈3.0 m.
    window_start : float
        Time of the first sample after firing, s (``SimulatedScan.t0``).
    acoustics, receiver, servo
        See :class:`Acoustics`, :class:`Receiver`, :class:`Servo`.
    """

    scene: Scene = field(default_factory=Scene.l_corner)
    geometry: ArrayGeometry = field(default_factory=ArrayGeometry)
    gamma_start: float = math.radians(-10.0)
    gamma_stop: float = math.radians(110.0)
    steps: int = 184
    temperature: float = 293.15
    sample_rate: float = 200_000.0
    window_samples: int = 3500
    window_start: float = 0.0
    acoustics: Acoustics = field(default_factory=Acoustics)
    receiver: Receiver = field(default_factory=Receiver)
    servo: Servo = field(default_factory=Servo)

    def __post_init__(self) -> None:
        for name, kind in (
            ("scene", Scene),
            ("geometry", ArrayGeometry),
            ("acoustics", Acoustics),
            ("receiver", Receiver),
            ("servo", Servo),
        ):
            if not isinstance(getattr(self, name), kind):
                raise ConfigError(
                    f"SimConfig.{name} must be a {kind.__name__}, got {type(getattr(self, name)).__name__}"
                )
        for name in ("gamma_start", "gamma_stop", "temperature", "sample_rate", "window_start"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value)):
                raise ConfigError(f"SimConfig.{name} must be a finite number, got {value!r}")
        if not self.gamma_start < self.gamma_stop:
            raise ConfigError("SimConfig: gamma_start must be below gamma_stop (rad)")
        raw = self.servo.to_raw(np.array([self.gamma_start, self.gamma_stop]))
        if raw.min() < 0 or raw.max() > 1023:
            raise ConfigError(
                f"SimConfig: the scan needs AX-12 positions {raw.tolist()}, outside 0…1023; "
                "narrow the range or change Servo.mount_offset"
            )
        if not (isinstance(self.steps, (int, np.integer)) and 1 <= self.steps <= 100_000):
            raise ConfigError(f"SimConfig.steps must be an int in [1, 100000], got {self.steps!r}")
        if not 223.15 <= self.temperature <= 333.15:
            raise ConfigError(
                f"SimConfig.temperature is in kelvin and must be in [223.15, 333.15] K, got {self.temperature}"
            )
        if not 2.2 * self.acoustics.frequency <= self.sample_rate <= 10e6:
            raise ConfigError(
                f"SimConfig.sample_rate must be ≥ 2.2 × the {self.acoustics.frequency:.0f} Hz carrier "
                f"and ≤ 10 MHz, got {self.sample_rate}"
            )
        if not (isinstance(self.window_samples, (int, np.integer)) and 16 <= self.window_samples <= 1_000_000):
            raise ConfigError(f"SimConfig.window_samples must be an int in [16, 1e6], got {self.window_samples!r}")
        if not 0 <= self.window_start < 0.1:
            raise ConfigError(f"SimConfig.window_start must be in [0, 0.1) s, got {self.window_start}")

    @property
    def sound_speed(self) -> float:
        """c at :attr:`temperature`, m/s."""
        return float(sound_speed(self.temperature))

    @property
    def max_range(self) -> float:
        """Range covered by the waveform window, m."""
        return self.sound_speed * (self.window_start + self.window_samples / self.sample_rate) / 2

    def gamma_commanded(self) -> np.ndarray:
        """Commanded γ of every step, rad."""
        return np.linspace(self.gamma_start, self.gamma_stop, int(self.steps))
