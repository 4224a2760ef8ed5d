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
from scipy.optimize import leastsq

from lelsonar.reconstruct.estimate.corner.model import ECHO_EDGE, mirror_rows
from lelsonar.reconstruct.estimate.corner.solver import joint_residuals_of, labelled_order

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


#: The relative step of the forward differences (scipy's ``'2-point'`` rule for float64).
_REL_STEP = np.finfo(np.float64).eps ** 0.5


def joint_walls(walls: list[WallEvidence], corners: list[CornerEvidence]) -> list[JointWall] | None:
    """Fit the walls and the corners that join them at once (see the module's rows).

    The Jacobian is scipy's ``'2-point'`` forward difference (its steps, its quotients), with each step's
    residuals computed only for the rows its parameter moves: a wall's parameters move its own rows, the
    corners it joins and its bearing row; every other row's difference is the row's own, ``f − f``.

    Returns
    -------
    One :class:`JointWall` per wall, in order, or None when the fit does not converge or is not
    determined (a singular system).
    """
    if not walls or not corners:
        return None
    n_walls = len(walls)
    positions = [np.ascontiguousarray(w.positions, dtype=np.float64) for w in walls]
    ranges = [np.ascontiguousarray(w.ranges, dtype=np.float64) for w in walls]
    corner_rows = []
    for c in corners:
        labels = np.full(c.ranges.size, ECHO_EDGE, dtype=np.intp)
        corner_rows.append(
            (
                np.ascontiguousarray(c.positions, dtype=np.float64),
                np.ascontiguousarray(c.ranges, dtype=np.float64),
                labelled_order(labels),
                labels,
            )
        )
    bearings = [(w.bearing, w.bearing_stderr) for w in walls]
    # Row blocks, in the order of the rows: each wall's echoes, each corner's, the bearings.
    sizes = [r.size for r in ranges] + [c.ranges.size for c in corners] + [n_walls]
    bounds = np.concatenate(([0], np.cumsum(sizes))).tolist()
    # The blocks each wall's parameters move.
    moved = [
        [k, *(n_walls + j for j, c in enumerate(corners) if k in c.walls), n_walls + len(corners)]
        for k in range(n_walls)
    ]

    def wall(x: np.ndarray, k: int) -> tuple[np.ndarray, float]:
        return _normal(x[3 * k], x[3 * k + 1]), float(x[3 * k + 2])

    def block(ws: list[tuple[np.ndarray, float]], x: np.ndarray, j: int) -> np.ndarray:
        """Block ``j``'s rows at ``x``, whose walls (normal, offset) are ``ws``."""
        if j < n_walls:
            n, h = ws[j]
            return mirror_rows(positions[j], ranges[j], n, h) / walls[j].sigma
        if j < n_walls + len(corners):
            c = corners[j - n_walls]
            (na, ha), (nb, hb) = ws[c.walls[0]], ws[c.walls[1]]
            return joint_residuals_of(*corner_rows[j - n_walls], na, ha, nb, hb) / c.sigma  # joint_residuals
        return np.array([(x[3 * k] - b) / se for k, (b, se) in enumerate(bearings)])

    last: list[tuple[bytes, np.ndarray, list[tuple[np.ndarray, float]]]] = []

    def evaluate(x: np.ndarray) -> tuple[np.ndarray, list[tuple[np.ndarray, float]]]:
        ws = [wall(x, k) for k in range(n_walls)]
        f = np.concatenate([block(ws, x, j) for j in range(len(sizes))])
        last[:] = [(x.tobytes(), f.copy(), ws)]
        return f, ws

    def rows(x: np.ndarray) -> np.ndarray:
        # leastsq checks the rows at x0 and lmder starts there: the same numbers, computed once.
        return last[0][1].copy() if last and last[0][0] == x.tobytes() else evaluate(x)[0]

    jacobian: list[tuple[bytes, np.ndarray]] = []

    def forward_differences(x: np.ndarray) -> np.ndarray:
        # leastsq checks the Jacobian at x0 and lmder asks for it there again: the same numbers, computed once.
        if jacobian and jacobian[0][0] == x.tobytes():
            return jacobian[0][1].copy().T  # (the layout of a fresh one: BLAS sums it alike)
        f0, ws = (last[0][1], last[0][2]) if last and last[0][0] == x.tobytes() else evaluate(x)
        sign = (x >= 0).astype(float) * 2 - 1
        h = _REL_STEP * sign * np.maximum(1.0, np.abs(x))
        out = np.empty((x.size, f0.size))
        for i in range(x.size):
            x1 = np.copy(x)
            x1[i] = x[i] + h[i]
            dx = (x[i] + h[i]) - x[i]
            ws1 = list(ws)
            ws1[i // 3] = wall(x1, i // 3)
            df = f0 - f0
            for j in moved[i // 3]:
                df[bounds[j] : bounds[j + 1]] = block(ws1, x1, j) - f0[bounds[j] : bounds[j + 1]]
            out[i] = df / dx
        jacobian[:] = [(x.tobytes(), out.copy())]
        return out.T

    x0 = np.array([v for w in walls for v in (w.bearing, w.tilt, w.offset)], dtype=np.float64)
    start = rows(x0)
    if start.size <= x0.size or not np.all(np.isfinite(start)):
        return None  # fewer rows than unknowns, or a wall's σ or a start not finite
    # MINPACK's lmder as least_squares(method="lm") calls it (its tolerances, evaluations and diag = 1/x_scale),
    # without the wrapper's bookkeeping.
    n_par = x0.size
    x, _, info, _, status = leastsq(
        rows,
        x0,
        Dfun=forward_differences,
        full_output=True,
        ftol=1e-8,
        xtol=1e-8,
        gtol=1e-8,
        maxfev=100 * n_par,
        factor=100.0,
        diag=1 / np.tile([1e-2, 1e-2, 1e-3], len(walls)),
    )
    if status not in (1, 2, 3, 4) or not np.all(np.isfinite(x)):
        return None
    jac = forward_differences(x)
    jtj = jac.T @ jac
    if np.linalg.cond(jtj) > 1e12:
        return None
    fun = info["fvec"]
    dof = max(fun.size - n_par, 1)
    chi2 = float(fun @ fun) / dof
    cov = np.linalg.inv(jtj) * max(1.0, chi2)
    return [
        JointWall(
            float(x[3 * k]),
            float(x[3 * k + 1]),
            float(x[3 * k + 2]),
            cov[3 * k : 3 * k + 3, 3 * k : 3 * k + 3],
            k,
            cov,
        )
        for k in range(len(walls))
    ]
