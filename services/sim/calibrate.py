"""The paper's energy calibration (§4, eq. 12–14) as a routine, with the simulator as a shot source.

Six face-on shots of a wall between 0.9 and 1.8 m give ``(d_i, E^{0°}(d_i))``;
:func:`lelsonar.signal.energy.fit_energy_model` fits
``1/E0(d) = φ0·d² + φ1·d + φ2``.

A shot source is anything with ``total_energy(distance) -> float``; the
simulator's is :class:`SimulatedWallShots`.  Hardware calibration plugs in
by implementing the same protocol around the sensor board (the user places
the wall and types the distance it measured).

The distance is the range from the capsule faces to the wall, what the
sensors report and what ``d_m`` is compared with in ``R = E^γ/E0(d_m)``.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, replace
from typing import Protocol

import numpy as np

from lelsonar.errors import ConfigError
from lelsonar.signal.energy import EnergyModel, fit_energy_model, total_energy, waveform_energy
from lelsonar.sim.config import SimConfig
from lelsonar.sim.presets import preset
from lelsonar.sim.scan import simulate_step
from lelsonar.sim.scene import Scene

#: Six wall distances spanning the paper's calibrated interval, 0.9–1.8 m.
PAPER_CALIBRATION_DISTANCES: tuple[float, ...] = (0.90, 1.08, 1.26, 1.44, 1.62, 1.80)


class EnergyShotSource(Protocol):
    """Something that can fire one face-on shot at a wall ``distance`` m away."""

    def total_energy(self, distance: float) -> float:
        """``E^{0°}``: the summed waveform energy of all capsules, V²·s (eq. 10–11)."""
        ...


@dataclass(frozen=True, eq=False)
class CalibrationResult:
    """The shots and the fitted model.

    Attributes
    ----------
    distances : (k,) array, m
    energies : (k,) array, V²·s
    model : EnergyModel
    """

    distances: np.ndarray
    energies: np.ndarray
    model: EnergyModel

    def residuals(self) -> np.ndarray:
        """Relative misfit ``E/E0(d) − 1`` of each shot."""
        return self.energies / self.model.expected_energy(self.distances) - 1.0


class SimulatedWallShots:
    """Face-on shots of a flat wall, with the air, array and receiver of ``cfg``.

    The wall has the reflectivity of the scene's first panel (plane a).  Each
    shot is one :func:`simulate_step` at γ = 0 with the wall placed so that
    the capsule faces are ``distance`` m from it.
    """

    def __init__(self, cfg: SimConfig, rng: np.random.Generator) -> None:
        self._cfg = cfg
        self._rng = rng

    def total_energy(self, distance: float) -> float:
        cfg = self._cfg
        wall = Scene.wall(distance + cfg.geometry.radial_offset, reflectivity=cfg.scene.panels[0].reflectivity)
        shot = simulate_step(replace(cfg, scene=wall), 0.0, self._rng)
        return float(total_energy(waveform_energy(shot.waveforms, cfg.sample_rate)))


def calibrate(
    source: EnergyShotSource, distances: tuple[float, ...] = PAPER_CALIBRATION_DISTANCES
) -> CalibrationResult:
    """Fire one shot per distance and fit eq. (12) by eq. (13)–(14).

    Raises
    ------
    ConfigError
        From :func:`fit_energy_model` (too few distances, non-positive energy).
    """
    d = np.asarray(distances, dtype=float)
    if d.ndim != 1 or not np.all(np.isfinite(d)) or np.any(d <= 0):
        raise ConfigError(f"calibration distances must be positive numbers (m), got {distances!r}")
    e = np.array([source.total_energy(float(x)) for x in d])
    return CalibrationResult(distances=d, energies=e, model=fit_energy_model(d, e))


def calibrate_simulator(
    cfg: SimConfig, seed: int = 0, distances: tuple[float, ...] = PAPER_CALIBRATION_DISTANCES
) -> CalibrationResult:
    """The paper's six-shot calibration against the simulator (seeded)."""
    return calibrate(SimulatedWallShots(cfg, np.random.default_rng(seed)), distances)


@functools.lru_cache(maxsize=1)
def default_energy_model() -> EnergyModel:
    """``E0(d)`` of the default simulator: its own six-shot calibration (seed 0), computed once.

    Every preset shares the default air, array and receiver, so one model
    serves them all.  It is calibrated, not pasted: a change to the acoustics
    changes it too.  The three φ are poorly conditioned (other seeds give φ1
    from 0.8e3 to 1.9e3) while ``E0`` itself agrees within a few per cent.
    """
    return calibrate_simulator(preset("paper-test1"), seed=0).model


def __getattr__(name: str) -> EnergyModel:
    # ``DEFAULT_ENERGY_MODEL`` is computed on first use, not at import.
    if name == "DEFAULT_ENERGY_MODEL":
        return default_energy_model()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
