"""Closed forms and fused paths of the default fit against independent references.

Each replaced a NumPy/LAPACK call on the fit's hot path; each must give what that call gives: the
scanner's frames exactly, the standard errors to 1e-12 relative on well-conditioned cases.
"""

from __future__ import annotations

import numpy as np

from lelsonar.geometry import ArrayGeometry, boresight, rotation_x
from lelsonar.reconstruct.estimate.corner.pitch import fixed_pitch_wall
from lelsonar.reconstruct.estimate.fit import normal_offset_stderr
from lelsonar.reconstruct.estimate.quality import _nearest_beam_cosine

GEO = ArrayGeometry()


def test_the_frames_are_eq_9_whichever_path_builds_them() -> None:
    rng = np.random.default_rng(0)
    g = rng.uniform(-4.0, 4.0, 500)
    b = boresight(g)
    assert np.array_equal(b, np.stack([np.zeros_like(g), np.cos(g), np.sin(g)], axis=-1))
    caps = GEO.capsule_positions(g)
    x = np.asarray(GEO.capsule_x)
    assert np.array_equal(caps[..., 0], np.broadcast_to(x, caps.shape[:2]))
    assert np.array_equal(caps[..., 1], np.broadcast_to(GEO.radial_offset * np.cos(g)[:, None], caps.shape[:2]))
    assert np.array_equal(caps[..., 2], np.broadcast_to(GEO.radial_offset * np.sin(g)[:, None], caps.shape[:2]))
    assert np.array_equal(GEO.capsule_positions(g, b), caps)  # reusing the boresight's cos, sin
    for gamma in g[:50]:
        r = rotation_x(gamma)  # one angle: the fast path
        assert np.array_equal(r, rotation_x(np.array([gamma]))[0])
        assert np.allclose(r @ [0.0, 1.0, 0.0], boresight(gamma), rtol=0, atol=1e-15)


def test_nearest_beam_is_the_largest_cosine_over_the_finite_steps() -> None:
    rng = np.random.default_rng(1)
    for _ in range(200):
        g = rng.uniform(-1.0, 2.5, rng.integers(1, 60))
        g[rng.random(g.size) < 0.2] = np.nan
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        c, seen = _nearest_beam_cosine(g, n[1], n[2])
        f = g[np.isfinite(g)]
        assert seen == bool(f.size)
        if f.size:
            assert c == float((np.cos(f) * n[1] + np.sin(f) * n[2]).max())


def _reference_stderr(
    p: np.ndarray, d: np.ndarray, normal: np.ndarray, h: float, phi: float, phi_se: float
) -> tuple[float, float]:
    """fixed_pitch_wall's standard errors at its solution, from NumPy's pseudo-inverse of JᵀJ."""
    psi = np.arcsin(normal[0])
    dn = np.array([np.cos(psi), -np.sin(psi) * np.cos(phi), -np.sin(psi) * np.sin(phi)])
    r = p @ normal + d - h
    j = np.stack([p @ dn, -np.ones_like(d)], axis=1)
    cov = (r @ r) / (d.size - 2) * np.linalg.pinv(j.T @ j)
    dh_dphi = np.mean(p @ np.array([0.0, -np.cos(psi) * np.sin(phi), np.cos(psi) * np.cos(phi)]))
    return np.sqrt(cov[0, 0] + phi_se**2), np.sqrt(cov[1, 1] + (dh_dphi * phi_se) ** 2)


def test_fixed_pitch_wall_finds_the_wall_and_its_standard_errors() -> None:
    rng = np.random.default_rng(2)
    for _ in range(300):
        phi, psi, h = rng.uniform(-0.3, 1.9), rng.normal(0.0, 0.08), rng.uniform(0.4, 4.0)
        truth = np.array([np.sin(psi), np.cos(psi) * np.cos(phi), np.cos(psi) * np.sin(phi)])
        g = phi + rng.uniform(-0.6, 0.6, rng.integers(4, 100))
        p = GEO.capsule_positions(g).reshape(-1, 3)  # every capsule: the lever arm along x
        exact = h - p @ truth
        wall, _, _ = fixed_pitch_wall(p, exact, phi, 0.0, np.array([0.0, 1.0, 0.0]))
        assert np.allclose(wall.normal, truth, rtol=0, atol=1e-12) and abs(wall.offset - h) < 1e-12
        d = exact + rng.normal(0.0, 0.003, exact.size)  # range noise (design notes §8)
        phi_se = abs(rng.normal(0.0, 0.01))
        wall, se_n, se_h = fixed_pitch_wall(p, d, phi, phi_se, np.array([0.0, 1.0, 0.0]))
        ref_n, ref_h = _reference_stderr(p, d, wall.normal, wall.offset, phi, phi_se)
        assert abs(se_n - ref_n) <= 1e-12 * ref_n and abs(se_h - ref_h) <= 1e-12 * ref_h


def test_normal_offset_stderr_is_the_first_order_propagation() -> None:
    rng = np.random.default_rng(3)
    for _ in range(300):
        t = rng.normal(size=3) + [0.0, 2.0, 0.0]
        q = rng.normal(size=(3, 3))
        cov = q @ q.T * 10.0 ** rng.uniform(-8, -2)
        nt = np.linalg.norm(t)
        n = t / nt
        jn = (np.eye(3) - np.outer(n, n)) / nt
        ref_n = np.sqrt(np.trace(jn @ cov @ jn.T))
        ref_h = np.sqrt(nt**-4 * n @ cov @ n)
        se_n, se_h = normal_offset_stderr(t, cov)
        assert abs(se_n - ref_n) <= 1e-12 * ref_n and abs(se_h - ref_h) <= 1e-12 * ref_h
