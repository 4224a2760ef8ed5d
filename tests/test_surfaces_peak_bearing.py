"""The beam pattern's peak (:func:`bearing_from_amplitude`) and curvature (:func:`log_amplitude_curvature`),
their tops found in one compiled pass: the NumPy formulas' numbers to the bit.

The reference here is the same steps in NumPy (finite positive amplitudes, sorted by γ, a clipped plateau's
centre, else the parabola through the top half in ``log A`` by ``np.linalg.lstsq``, its σ by the delta method
through ``np.linalg.pinv``), on seeded sweeps rising, falling, with repeated γ, gaps and clipped tops.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from lelsonar.reconstruct.estimate.surfaces.beam_pattern import PLATEAU, bearing_from_amplitude, log_amplitude_curvature


def _reference(gamma: np.ndarray, amplitude: np.ndarray) -> tuple[float, float] | None:
    ok = np.isfinite(amplitude) & (amplitude > 0)
    if np.count_nonzero(ok) < 5:
        return None
    g, a = gamma[ok], amplitude[ok]
    order = np.argsort(g)
    g, a = g[order], a[order]
    flat = np.flatnonzero(a >= (1.0 - PLATEAU) * a.max())
    if flat.size >= 3:
        if flat[0] == 0 or flat[-1] == a.size - 1:
            return None
        step = float(np.median(np.diff(g)))
        width = float(g[flat[-1]]) - float(g[flat[0]])
        return 0.5 * (float(g[flat[0]]) + float(g[flat[-1]])), math.hypot(step, width / flat.size) / math.sqrt(12.0)
    top = a >= 0.5 * a.max()
    if np.count_nonzero(top) < 5:
        return None
    gt, la = g[top], np.log(a[top])
    g0 = float(np.mean(gt))
    u = gt - g0
    m = np.stack([np.ones_like(u), u, u * u], axis=1)
    coef = np.linalg.lstsq(m, la, rcond=None)[0]
    _, b, c = coef.tolist()
    if not c < 0:
        return None
    vertex = -b / (2 * c)
    if np.count_nonzero(u < vertex) < 2 or np.count_nonzero(u > vertex) < 2:
        return None
    res = la - m @ coef
    cov = float(res @ res) / max(u.size - 3, 1) * np.linalg.pinv(m.T @ m)
    jac = np.array([0.0, -1 / (2 * c), b / (2 * c * c)])
    return g0 + vertex, math.sqrt(max(float(jac @ cov @ jac), 0.0))


def _sweep(rng: np.random.Generator, case: str) -> tuple[np.ndarray, np.ndarray]:
    k = 41
    gamma = np.cumsum(rng.uniform(0.012, 0.022, k)) - 0.35
    if case == "falling":
        gamma = gamma[::-1].copy()
    if case == "repeated":
        gamma[10:13] = gamma[10]  # a servo that held its position over three steps
    peak = rng.uniform(-0.1, 0.1)
    amplitude = 0.8 * np.exp(-((gamma - peak) ** 2) / (2 * 0.08**2)) * (1 + rng.normal(0.0, 0.03, k))
    if case == "gaps":
        amplitude[rng.choice(k, 8, replace=False)] = np.nan
        amplitude[3] = 0.0
    if case == "clipped":
        amplitude = np.minimum(amplitude, 0.5)
    if case == "clipped end":
        amplitude = np.minimum(amplitude, 0.5)[: int(np.argmax(amplitude)) + 1]
        gamma = gamma[: amplitude.size]
    return gamma, amplitude


@pytest.mark.parametrize("case", ["rising", "falling", "repeated", "gaps", "clipped", "clipped end"])
@pytest.mark.parametrize("seed", range(6))
def test_peak_bearing_matches_numpy_bit_for_bit(case, seed):
    gamma, amplitude = _sweep(np.random.default_rng(seed), case)
    got, want = bearing_from_amplitude(gamma, amplitude), _reference(gamma, amplitude)
    if want is None:
        assert got is None
    else:
        assert got is not None
        assert (float(got[0]).hex(), float(got[1]).hex()) == (float(want[0]).hex(), float(want[1]).hex())


def _curvature_reference(gamma: np.ndarray, amplitude: np.ndarray, plateau: bool) -> float | None:
    ok = np.isfinite(amplitude) & (amplitude > 0)
    if np.count_nonzero(ok) < 5:
        return None
    g, a = gamma[ok], amplitude[ok]
    top = a >= 0.5 * a.max()
    if np.count_nonzero(top) < 5 or (not plateau and np.count_nonzero(a >= (1.0 - PLATEAU) * a.max()) >= 3):
        return None
    gt = g[top]
    u = gt - float(np.mean(gt))
    coef = np.linalg.lstsq(np.stack([np.ones_like(u), u, u * u], axis=1), np.log(a[top]), rcond=None)[0]
    return float(-coef[2]) if coef[2] < 0 else None


@pytest.mark.parametrize("plateau", [False, True])
@pytest.mark.parametrize("case", ["rising", "falling", "repeated", "gaps", "clipped", "clipped end"])
@pytest.mark.parametrize("seed", range(4))
def test_log_amplitude_curvature_matches_numpy_bit_for_bit(case, seed, plateau):
    gamma, amplitude = _sweep(np.random.default_rng(seed), case)
    got, want = (
        log_amplitude_curvature(gamma, amplitude, plateau=plateau),
        _curvature_reference(gamma, amplitude, plateau),
    )
    assert (got is None) == (want is None)
    if want is not None:
        assert float(got).hex() == float(want).hex()
