"""The piston fits' own solver against SciPy's: the same least squares minimum, far inside its σ.

* :func:`piston_lm` over ``(log P, β, ka)`` and over ``(log P, β)`` with ``ka`` fixed lands where
  ``scipy.optimize.least_squares`` (Levenberg–Marquardt, tight tolerances) does on the full problem, over
  seeded log-normal amplitude noise, whole profiles and one flank alike; the σ of ``ka`` it gives is the full
  problem's covariance's;
* rows of different lengths fitted together give what each gives alone;
* the piston's log pattern and its slopes are the directivity's and its derivatives'.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import special
from scipy.optimize import least_squares

from lelsonar.reconstruct.estimate.surfaces.piston import Profiles, bessel_j01, log_piston_point, piston_lm
from lelsonar.reconstruct.estimate.surfaces.piston_beam import piston_fit
from lelsonar.signal.directivity import piston_directivity

KA = 5.13  # a 7 mm piston at 40 kHz
NOISE = 0.02  # σ of log A


def _profile(rng: np.random.Generator, g: np.ndarray, bearing: float) -> np.ndarray:
    """log A of a piston's echo across ``g`` with seeded log-normal noise."""
    return np.log(1.5 * piston_directivity(g - bearing, KA) ** 2) + NOISE * rng.normal(size=g.size)


def _scipy_fit(g: np.ndarray, la: np.ndarray, start: np.ndarray, ka: float | None) -> tuple[np.ndarray, np.ndarray]:
    """SciPy's LM on the full problem (level, β[, ka]): the solution and its covariance at the residuals' scale."""

    def res(p: np.ndarray) -> np.ndarray:
        k = p[2] if ka is None else ka
        return p[0] + 2.0 * np.log(np.abs(piston_directivity(g - p[1], k))) - la

    fit = least_squares(res, start, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    assert fit.success
    s2 = float(fit.fun @ fit.fun) / (g.size - start.size)
    return fit.x, s2 * np.linalg.inv(fit.jac.T @ fit.jac)


@pytest.mark.parametrize("seed", range(6))
def test_a_whole_profiles_piston_fit_lands_on_scipys_minimum(seed):
    rng = np.random.default_rng(40 + seed)
    bearing = rng.uniform(-1.0, 1.0)
    g = bearing + np.radians(np.arange(-25.0, 25.5, 1.0)) + rng.uniform(0.0, math.radians(1.0))
    la = _profile(rng, g, bearing)
    start_b, start_ka = bearing + rng.normal(0.0, 0.02), KA * rng.uniform(0.9, 1.1)
    x, cov = _scipy_fit(g, la, np.array([la.max(), start_b, start_ka]), None)
    fit = piston_lm(Profiles.pack([(g, la)]), np.array([start_b]), np.array([start_ka]), free_ka=True)
    assert fit.ok[0]
    sb, sk = math.sqrt(cov[1, 1]), math.sqrt(cov[2, 2])
    assert abs(fit.bearing[0] - x[1]) <= 1e-4 * sb
    assert abs(fit.ka[0] - x[2]) <= 1e-4 * sk
    # piston_fit's σ of ka is the full problem's covariance's (the level and β eliminated, not fixed).
    out = piston_fit(g, np.exp(la), start_b, start_ka)
    assert out is not None
    assert abs(out[0] - x[2]) <= 1e-4 * sk and out[1] == pytest.approx(sk, rel=1e-4)


@pytest.mark.parametrize(("seed", "past_deg"), [(s, p) for s in range(4) for p in (3.0, 15.0, 28.0)])
def test_a_flanks_fit_with_ka_fixed_lands_on_scipys_minimum(seed, past_deg):
    rng = np.random.default_rng(70 + seed)
    g = np.radians(np.arange(-150.0, -120.0, 1.0)) + rng.uniform(0.0, math.radians(1.0))
    true = float(g[0]) - math.radians(past_deg)
    la = _profile(rng, g, true)
    keep = (la > math.log(0.02)) & (KA * np.abs(np.sin(g - true)) < 3.8317)
    g, la = g[keep], la[keep]
    start = float(g[0]) - math.radians(5.0)
    x, cov = _scipy_fit(g, la, np.array([la.max(), start]), KA)
    fit = piston_lm(Profiles.pack([(g, la)]), np.array([start]), np.array([KA]), free_ka=False)
    assert fit.ok[0] and fit.ka[0] == KA
    assert abs(fit.bearing[0] - x[1]) <= 1e-4 * math.sqrt(cov[1, 1])


def test_rows_of_different_lengths_fitted_together_give_what_each_gives_alone():
    rng = np.random.default_rng(9)
    rows, starts = [], []
    for n in (12, 31, 47):
        bearing = rng.uniform(-1.0, 1.0)
        g = bearing + np.linspace(-math.radians(0.5 * n), math.radians(0.5 * n), n)
        rows.append((g, _profile(rng, g, bearing)))
        starts.append((bearing + 0.01, KA * 1.05))
    start = np.array(starts)
    together = piston_lm(Profiles.pack(rows), start[:, 0], start[:, 1], free_ka=True)
    for i, row in enumerate(rows):
        alone = piston_lm(Profiles.pack([row]), start[i : i + 1, 0], start[i : i + 1, 1], free_ka=True)
        _, cov = _scipy_fit(row[0], row[1], np.array([row[1].max(), *start[i]]), None)
        assert together.ok[i] and alone.ok[0]
        assert abs(together.bearing[i] - alone.bearing[0]) <= 1e-9 * math.sqrt(cov[1, 1])
        assert abs(together.ka[i] - alone.ka[0]) <= 1e-9 * math.sqrt(cov[2, 2])


def test_j0_and_j1_are_scipys_over_and_past_the_main_lobe():
    for x in np.concatenate([np.linspace(-30.0, 30.0, 601), [1e-9, 3.8317059702075125, 11.999, 12.0, 12.001]]):
        j0, j1 = bessel_j01(float(x))
        assert abs(j0 - special.j0(x)) <= 1e-11 and abs(j1 - special.j1(x)) <= 1e-11, x
    for x in np.linspace(0.0, 3.9, 40):  # the main lobe: to rounding
        j0, j1 = bessel_j01(float(x))
        assert abs(j0 - special.j0(x)) <= 1e-15 and abs(j1 - special.j1(x)) <= 1e-15, x


def log_piston_terms(u: np.ndarray, ka: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    out = np.array([log_piston_point(float(v), ka) for v in u])
    return out[:, 0], out[:, 1], out[:, 2]


def test_the_log_pattern_and_its_slopes_are_the_directivitys():
    u = np.radians(np.linspace(-40.0, 40.0, 161))
    log_d, du, dka = log_piston_terms(u, KA)
    assert np.allclose(np.exp(log_d), piston_directivity(u, KA) ** 2, rtol=1e-12, atol=0.0)
    h = 1e-6
    fd_u = (log_piston_terms(u + h, KA)[0] - log_piston_terms(u - h, KA)[0]) / (2 * h)
    fd_ka = (log_piston_terms(u, KA + h)[0] - log_piston_terms(u, KA - h)[0]) / (2 * h)
    finite = np.isfinite(log_d)
    assert np.allclose(du[finite], fd_u[finite], rtol=1e-6, atol=1e-6)
    assert np.allclose(dka[finite], fd_ka[finite], rtol=1e-6, atol=1e-6)
