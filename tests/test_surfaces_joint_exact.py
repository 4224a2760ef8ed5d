"""The joint corner fit's own Jacobian is scipy's forward difference: the fit is least_squares' to the bit.

:func:`~lelsonar.reconstruct.estimate.surfaces.joint.joint_walls` differences only the rows each parameter moves
and calls MINPACK through ``leastsq``.  The reference here is the plain route: every row through the corner
model's residual functions, ``least_squares(method="lm")`` with its own ``'2-point'`` Jacobian.  Both must
give the same walls and covariance, bit for bit, on seeded scenes of two and three walls.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.optimize import least_squares

from lelsonar.reconstruct.estimate.corner.model import ECHO_EDGE, ScanPoints, Wall, mirror_residuals
from lelsonar.reconstruct.estimate.corner.solver import joint_residuals
from lelsonar.reconstruct.estimate.surfaces.joint import CornerEvidence, WallEvidence, joint_walls

RADIAL = 0.03
CAPSULE_X = np.array([-0.12, -0.04, 0.04, 0.12])


def _normal(bearing: float, tilt: float) -> np.ndarray:
    c = math.cos(tilt)
    return np.array([math.sin(tilt), c * math.cos(bearing), c * math.sin(bearing)])


def _capsules(gamma: np.ndarray) -> np.ndarray:
    """(N·4, 3) capsule positions of a fan sweep over ``gamma``, capsule by capsule within a step."""
    g = np.repeat(gamma, CAPSULE_X.size)
    return np.stack([np.tile(CAPSULE_X, gamma.size), RADIAL * np.cos(g), RADIAL * np.sin(g)], axis=1)


def _scene(rng: np.random.Generator, bearings: list[float], offsets: list[float], noise: float):
    """Walls at ``bearings`` (each seen around its own bearing), corners between neighbours."""
    walls, corners = [], []
    truth = [(_normal(b, 0.0), h) for b, h in zip(bearings, offsets, strict=True)]
    for b, (n, h) in zip(bearings, truth, strict=True):
        p = _capsules(b + np.linspace(-0.08, 0.08, 9))
        d = h - p @ n + rng.normal(0.0, noise, len(p))
        start = b + rng.normal(0.0, 0.01)
        walls.append(WallEvidence(p, d, start, 0.02, rng.normal(0.0, 0.01), h + rng.normal(0.0, 0.005), noise))
    for k in range(len(bearings) - 1):
        (na, ha), (nb, hb) = truth[k], truth[k + 1]
        edge = math.atan2(
            *(np.linalg.solve(np.array([na[1:], nb[1:]]), np.array([ha, hb])))[::-1]
        )  # the bearing of the line the two walls meet on
        p = _capsules(edge + np.linspace(-0.03, 0.03, 5))
        a, b_ = ha - p @ na, hb - p @ nb
        c = float(na @ nb)
        d = np.sqrt(a * a + b_ * b_ - 2 * c * a * b_) + rng.normal(0.0, noise, len(p))
        corners.append(CornerEvidence(p, d, (k, k + 1), noise))
    return walls, corners


def _reference(walls: list[WallEvidence], corners: list[CornerEvidence]):
    """The plain route: every row through the corner model's functions, least_squares' own Jacobian."""

    def points(positions: np.ndarray, ranges: np.ndarray) -> ScanPoints:
        n = ranges.size
        return ScanPoints(
            step=np.zeros(n, dtype=np.intp),
            capsule_index=np.zeros(n, dtype=np.intp),
            gamma=np.zeros(n),
            capsule=np.ascontiguousarray(positions, dtype=np.float64),
            distance=np.ascontiguousarray(ranges, dtype=np.float64),
            beam=np.zeros((n, 3)),
        )

    wall_pts = [points(w.positions, w.ranges) for w in walls]
    corner_pts = [points(c.positions, c.ranges) for c in corners]
    labels = [np.full(c.ranges.size, ECHO_EDGE, dtype=np.intp) for c in corners]

    def rows(x: np.ndarray) -> np.ndarray:
        ws = [Wall(_normal(x[3 * k], x[3 * k + 1]), float(x[3 * k + 2])) for k in range(len(walls))]
        out = [mirror_residuals(ws[k], wall_pts[k]) / walls[k].sigma for k in range(len(walls))]
        for c, pts, lab in zip(corners, corner_pts, labels, strict=True):
            out.append(joint_residuals(ws[c.walls[0]], ws[c.walls[1]], pts, lab) / c.sigma)
        out.append(np.array([(x[3 * k] - w.bearing) / w.bearing_stderr for k, w in enumerate(walls)]))
        return np.concatenate(out)

    x0 = np.array([v for w in walls for v in (w.bearing, w.tilt, w.offset)], dtype=np.float64)
    fit = least_squares(rows, x0, method="lm", x_scale=np.tile([1e-2, 1e-2, 1e-3], len(walls)))
    assert fit.success
    jac = np.asarray(fit.jac)
    jtj = jac.T @ jac
    dof = max(fit.fun.size - x0.size, 1)
    return fit.x, np.linalg.inv(jtj) * max(1.0, float(fit.fun @ fit.fun) / dof)


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize(
    ("bearings", "offsets"),
    [([0.4, 0.4 + math.pi / 2], [1.6, 1.1]), ([0.2, 1.5, 2.9], [1.3, 0.9, 1.7])],
    ids=["two walls", "three walls"],
)
def test_the_joint_fit_is_least_squares_to_the_bit(seed, bearings, offsets):
    walls, corners = _scene(np.random.default_rng(seed), bearings, offsets, 0.004)
    got = joint_walls(walls, corners)
    assert got is not None
    x, cov = _reference(walls, corners)
    for k, jw in enumerate(got):
        assert (jw.bearing, jw.tilt, jw.offset) == (x[3 * k], x[3 * k + 1], x[3 * k + 2])
        assert np.array_equal(jw.full, cov)
        # and the fit found the walls (the reference agreeing on a wrong answer would prove nothing)
        assert abs(jw.bearing - bearings[k]) < 0.02
        assert abs(jw.offset - offsets[k]) < 0.02
