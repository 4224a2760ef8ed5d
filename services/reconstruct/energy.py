"""The energy indicator that finds the corner (paper §4, eq. 10–14).

Pure functions: arrays in, typed results out, no I/O.
"""

from __future__ import annotations

import numpy as np

from lelsonar.energy_model import EnergyModel
from lelsonar.errors import ConfigError

__all__ = ["EnergyModel", "waveform_energy", "total_energy", "fit_energy_model", "median_range", "energy_ratio"]


def waveform_energy(waveforms: np.ndarray, sample_rate: float) -> np.ndarray:
    """Signal energy of each waveform, the paper's eq. (10).

    ``E_i^γ = ∫ w²(t) dt``, integrated by the rectangle rule.

    Parameters
    ----------
    waveforms : (..., n_samples) array
        Echo signal, V.
    sample_rate : float
        Hz.

    Returns
    -------
    (...) array
        Energy, V²·s.
    """
    w = np.asarray(waveforms, dtype=np.float64)
    return np.einsum("...i,...i->...", w, w) / float(sample_rate)


def total_energy(sensor_energy: np.ndarray) -> np.ndarray:
    """Total energy of a step over its capsules, the paper's eq. (11).

    Parameters
    ----------
    sensor_energy : (..., n_capsules) array
        ``E_i^γ`` from :func:`waveform_energy`, V²·s.
    """
    return np.sum(np.asarray(sensor_energy, dtype=np.float64), axis=-1)


def fit_energy_model(distance: np.ndarray, energy: np.ndarray) -> EnergyModel:
    """Least-squares calibration of eq. (12) from face-on shots, eq. (13)–(14).

    Solves ``A φ = B`` with the Vandermonde ``A = [d², d, 1]`` and ``B = 1/E``.

    Parameters
    ----------
    distance : (k,) array
        Measured wall distances, m (the paper uses six between 0.9 and 1.8 m).
    energy : (k,) array
        Total energy ``E^{0°}`` of each shot, V²·s.

    Raises
    ------
    ConfigError
        With fewer than three distinct distances or non-positive energies.
    """
    d = np.asarray(distance, dtype=np.float64).ravel()
    e = np.asarray(energy, dtype=np.float64).ravel()
    if d.shape != e.shape:
        raise ConfigError(f"need one energy per distance, got {d.size} distances and {e.size} energies")
    if np.unique(d).size < 3:
        raise ConfigError("the energy model needs shots at three or more distinct distances")
    if not (np.all(np.isfinite(d)) and np.all(np.isfinite(e)) and np.all(e > 0) and np.all(d > 0)):
        raise ConfigError("calibration distances and energies must be finite and positive")
    a = np.stack([d * d, d, np.ones_like(d)], axis=1)
    phi, *_ = np.linalg.lstsq(a, 1.0 / e, rcond=None)
    return EnergyModel(float(phi[0]), float(phi[1]), float(phi[2]), d_min=float(d.min()), d_max=float(d.max()))


def median_range(distance: np.ndarray) -> np.ndarray:
    """``d_m``: the median of each step's valid ranges (NaN = no echo), paper §4.

    Parameters
    ----------
    distance : (n_steps, n_capsules) array, m

    Returns
    -------
    (n_steps,) array
        NaN for a step with no valid range.
    """
    d = np.asarray(distance, dtype=np.float64)
    # np.nanmedian goes through masked arrays (~0.4 ms a call); sorting puts NaN last, so the
    # median of the c valid values is the mean of sorted[(c-1)//2] and sorted[c//2] — the same numbers.
    ordered = np.sort(d, axis=-1)
    count = np.isfinite(d).sum(axis=-1)
    lo = np.take_along_axis(ordered, np.maximum(count - 1, 0)[..., None] // 2, axis=-1)[..., 0]
    hi = np.take_along_axis(ordered, (count // 2)[..., None], axis=-1)[..., 0] if d.shape[-1] else lo
    return np.where(count > 0, 0.5 * (lo + hi), np.nan)


def energy_ratio(step_energy: np.ndarray, distance: np.ndarray, model: EnergyModel) -> np.ndarray:
    """The indicator ``R = E^γ / E0(d_m)`` of each step (paper §4, Fig. 6).

    Steps with no valid range get R = 0: they cannot be the corner, whose
    double bounce always returns an echo.
    """
    d_m = median_range(distance)
    r = np.zeros_like(np.asarray(step_energy, dtype=np.float64))
    ok = np.isfinite(d_m)
    r[ok] = np.asarray(step_energy, dtype=np.float64)[ok] / model.expected_energy(d_m[ok])
    return r
