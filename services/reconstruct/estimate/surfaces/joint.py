"""The joint corner model of a sweep's surfaces: walls that meet at concave corners, fitted together.

The corner model of the L scan (:mod:`lelsonar.reconstruct.estimate.corner`) ties two walls through the
double bounce of their edge: an edge echo's range is the capsule's distance to the walls' intersection
(:func:`~lelsonar.reconstruct.estimate.corner.solver.joint_residuals`).  Here the same residuals tie every
pair of walls the extractor found meeting at a corner, and each wall keeps its own echoes (the mirror
condition) and its bearing from the beam pattern, which the ranges of the fan mount barely constrain:

* wall rows ``(n·p_c + d − h)/σ_w`` (:func:`~lelsonar.reconstruct.estimate.corner.model.mirror_residuals`);
* corner rows ``(d − |X − p_c|)/σ_c`` of the walls it joins;
* one row per wall ``(β − β₀)/σ_β``: the beam pattern's bearing, independent of the ranges.

Parameters per wall: bearing ``β``, tilt ``t`` (along the stack) and offset ``h``.  The covariance is
``(JᵀJ)⁻¹`` of the whitened rows, scaled up by the reduced χ² when the rows scatter more than their σ.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from lelsonar.reconstruct.estimate.corner.model import ECHO_EDGE, ScanPoints, Wall, mirror_residuals
from lelsonar.reconstruct.estimate.corner.solver import joint_residuals

__all__ = ["WallEvidence", "CornerEvidence", "JointWall", "joint_walls"]


@dataclass(frozen=True, eq=False)
class WallEvidence:
    """One wall's own echoes and its independent bearing.

    Attributes
    ----------
    positions : (N, 3) array
        Capsule positions of its echoes, m.
    ranges : (N,) array
        m.
    bearing, bearing_stderr : float
        rad: from the beam pattern (or the region's centre).
    tilt, offset : float
        The start (rad, m).
    sigma : float
        m: σ of one range about the wall.
    """

    positions: np.ndarray
    ranges: np.ndarray
    bearing: float
    bearing_stderr: float
    tilt: float
    offset: float
    sigma: float


@dataclass(frozen=True, eq=False)
class CornerEvidence:
    """A concave corner's echoes and the two walls (indices) it joins."""

    positions: np.ndarray
    ranges: np.ndarray
    walls: tuple[int, int]
    sigma: float


@dataclass(frozen=True)
class JointWall:
    """A wall of the joint fit: bearing, tilt (rad), offset (m) and their (3, 3) covariance.

    ``index`` is its place in the fit and ``full`` the fit's whole covariance (3 rows per wall, in order):
    the corners tie the walls, so two walls' parameters are correlated.
    """

    bearing: float
    tilt: float
    offset: float
    covariance: np.ndarray
    index: int = 0
    full: np.ndarray | None = None


def _normal(bearing: float, tilt: float) -> np.ndarray:
    c = math.cos(tilt)
    return np.array([math.sin(tilt), c * math.cos(bearing), c * math.sin(bearing)])


def _points(positions: np.ndarray, ranges: np.ndarray) -> ScanPoints:
    n = ranges.size
    zeros = np.zeros(n)
    return ScanPoints(
        step=np.zeros(n, dtype=np.intp),
        capsule_index=np.zeros(n, dtype=np.intp),
        gamma=zeros,
        capsule=np.ascontiguousarray(positions, dtype=np.float64),
        distance=np.ascontiguousarray(ranges, dtype=np.float64),
        beam=np.zeros((n, 3)),
    )


def joint_walls(walls: list[WallEvidence], corners: list[CornerEvidence]) -> list[JointWall] | None:
    """Fit the walls and the corners that join them at once (see the module's rows).

    Returns
    -------
    One :class:`JointWall` per wall, in order, or None when the fit does not converge or is not
    determined (a singular system).
    """
    if not walls or not corners:
        return None
    wall_pts = [_points(w.positions, w.ranges) for w in walls]
    corner_pts = [_points(c.positions, c.ranges) for c in corners]
    corner_labels = [np.full(c.ranges.size, ECHO_EDGE, dtype=np.intp) for c in corners]

    def unpack(x: np.ndarray) -> list[Wall]:
        return [Wall(_normal(x[3 * k], x[3 * k + 1]), float(x[3 * k + 2])) for k in range(len(walls))]

    def rows(x: np.ndarray) -> np.ndarray:
        ws = unpack(x)
        out = [mirror_residuals(ws[k], wall_pts[k]) / walls[k].sigma for k in range(len(walls))]
        for c, pts, lab in zip(corners, corner_pts, corner_labels, strict=True):
            a, b = c.walls
            out.append(joint_residuals(ws[a], ws[b], pts, lab) / c.sigma)
        out.append(np.array([(x[3 * k] - w.bearing) / w.bearing_stderr for k, w in enumerate(walls)]))
        return np.concatenate(out)

    x0 = np.array([v for w in walls for v in (w.bearing, w.tilt, w.offset)], dtype=np.float64)
    start = rows(x0)
    if start.size <= x0.size or not np.all(np.isfinite(start)):
        return None  # fewer rows than unknowns, or a wall's σ or a start not finite
    fit = least_squares(rows, x0, method="lm", x_scale=np.tile([1e-2, 1e-2, 1e-3], len(walls)))
    if not fit.success or not np.all(np.isfinite(fit.x)):
        return None
    jac = np.asarray(fit.jac)
    jtj = jac.T @ jac
    if np.linalg.cond(jtj) > 1e12:
        return None
    dof = max(fit.fun.size - x0.size, 1)
    chi2 = float(fit.fun @ fit.fun) / dof
    cov = np.linalg.inv(jtj) * max(1.0, chi2)
    return [
        JointWall(
            float(fit.x[3 * k]),
            float(fit.x[3 * k + 1]),
            float(fit.x[3 * k + 2]),
            cov[3 * k : 3 * k + 3, 3 * k : 3 * k + 3],
            k,
            cov,
        )
        for k in range(len(walls))
    ]
