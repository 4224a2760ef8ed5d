"""Regions of constant depth (RCDs) of one sweep, and what each one's echoes say.

A specular target (a plane, a concave corner, a convex edge) answers a rotating
sonar over a run of steps at a steady range: the region of constant depth of
Leonard & Durrant-Whyte.  The range is the target's distance from the rotation
axis less the capsule's radial offset, to first order at every step of the run
(``d ≈ ρ − r·cos(γ − β)``), so the run's *centre* is the target's bearing β and
its *minimum* the depth ρ.  Along the capsule stack (the rotation axis x) the
four ranges are a straight line for a plane (the array's mirror image is a
straight array: slope ``−n_x``, the tilt) and a hyperbola for a line or a point
across the stack (``d = √(ρ² + (x − x₀)²)``: curvature ``1/(2ρ)``).

Pure functions: no I/O, no state.
"""

from __future__ import annotations

import math
import statistics
from dataclasses import dataclass

import numpy as np

from lelsonar.errors import ConfigError
from lelsonar.geometry import ArrayGeometry

__all__ = ["Region", "find_regions", "stack_fit", "bearing_from_amplitude", "PLATEAU"]

#: Amplitudes within this share of the largest are the receiver clipping: a plateau, not a peak.
PLATEAU = 0.001


@dataclass(frozen=True, eq=False)
class Region:
    """One region of constant depth.

    Attributes
    ----------
    steps : (k,) int array
        The scan's steps in the region (each with at least one reading in it).
    rows, capsules : (N,) int arrays
        The readings in the region: step index and capsule index of each.
    cut_before, cut_after : bool
        The region ends on that side not because its echo faded but because a
        nearer echo took over or the sweep ended: its centre is not its bearing.
    """

    steps: np.ndarray
    rows: np.ndarray
    capsules: np.ndarray
    cut_before: bool
    cut_after: bool

    @property
    def n_echoes(self) -> int:
        return int(self.rows.size)


def _step_range(distance: np.ndarray) -> np.ndarray:
    """Median range of each step over its capsules (NaN: no echo)."""
    d = np.asarray(distance, dtype=np.float64)
    out = np.full(d.shape[0], np.nan)
    have = np.isfinite(d).any(axis=1)
    if have.any():
        out[have] = np.nanmedian(d[have], axis=1)
    return out


def find_regions(
    distance: np.ndarray, *, tolerance: float = 0.015, max_gap: int = 2, min_steps: int = 3
) -> list[Region]:
    """Split a sweep into regions of constant depth.

    Parameters
    ----------
    distance : (n_steps, n_capsules) array
        Ranges, m (NaN: no echo), steps in sweep order.
    tolerance : float
        A step joins the current run while its median range is within this of
        the run's median, m (the range noise plus the radial offset's
        ``r·(1 − cos Δγ)`` over a beam width).
    max_gap : int
        Steps without an echo a run may bridge.
    min_steps : int
        Shorter runs are not regions (their echoes stay unexplained).

    Returns
    -------
    list of Region, in sweep order.
    """
    d = np.asarray(distance, dtype=np.float64)
    if d.ndim != 2:
        raise ConfigError(f"distance must be (n_steps, n_capsules), got shape {d.shape}")
    if not (tolerance > 0 and max_gap >= 0 and min_steps >= 1):
        raise ConfigError("find_regions: tolerance > 0, max_gap >= 0 and min_steps >= 1")
    rs = _step_range(d)
    n, m = d.shape
    runs: list[list[int]] = []
    run: list[int] = []
    seen: list[list[float]] = [[] for _ in range(m)]  # each capsule's ranges in the run
    gap = 0
    for s in range(n):
        if not math.isfinite(rs[s]):
            gap += 1
            if run and gap > max_gap:
                runs.append(run)
                run = []
            continue
        if not (run and _steady(d[s], rs[s], seen, rs[run]) <= tolerance):
            if run:
                runs.append(run)
            run = []
            seen = [[] for _ in range(m)]
        run.append(s)
        for c in range(m):
            if math.isfinite(d[s, c]):
                seen[c].append(float(d[s, c]))
        gap = 0
    if run:
        runs.append(run)
    out = []
    for r in runs:
        if len(r) < min_steps:
            continue
        steps = np.asarray(r, dtype=np.intp)
        ref = float(np.median(rs[steps]))
        block = d[steps]
        # A capsule's reading joins when it is within twice the tolerance of that capsule's median over the
        # region: a tilt or a line across the stack spreads the four ranges steadily (by several cm for a line
        # below the stack), another target in one capsule's beam does not.
        keep = np.isfinite(block) & (np.abs(block - _capsule_medians(block)) <= 2 * tolerance)
        rows, caps = np.nonzero(keep)
        first, last = int(steps[0]), int(steps[-1])
        out.append(
            Region(
                steps=steps,
                rows=steps[rows],
                capsules=caps.astype(np.intp),
                cut_before=_cut(rs, first, -1, ref, tolerance, max_gap),
                cut_after=_cut(rs, last, +1, ref, tolerance, max_gap),
            )
        )
    return out


def _steady(row: np.ndarray, step_range: float, seen: list[list[float]], run_ranges: np.ndarray) -> float:
    """How far a step is from the run: capsule by capsule where both have echoes (a capsule that loses its
    echo at the edge of the beam does not move the others), else by the steps' medians, m."""
    # (statistics.median: these lists are short, and NumPy's call costs more than the sort)
    devs = [abs(float(row[c]) - statistics.median(v)) for c, v in enumerate(seen) if v and math.isfinite(row[c])]
    if devs:
        return statistics.median(devs)
    return abs(float(step_range) - float(np.median(run_ranges)))


def _capsule_medians(block: np.ndarray) -> np.ndarray:
    out = np.full(block.shape[1], np.nan)
    have = np.isfinite(block).any(axis=0)
    if have.any():
        out[have] = np.nanmedian(block[:, have], axis=0)
    return out


def _cut(rs: np.ndarray, end: int, direction: int, ref: float, tolerance: float, max_gap: int) -> bool:
    """Whether a run's end is a cut: the sweep's end, or a nearer echo within ``max_gap + 2`` steps (a step
    between two targets may hold a little of both, and belong to neither)."""
    if not 0 <= end + direction < rs.size:
        return True
    for k in range(1, max_gap + 3):
        s = end + direction * k
        if 0 <= s < rs.size and math.isfinite(rs[s]) and rs[s] < ref - tolerance:
            return True
    return False


def stack_fit(x: np.ndarray, rows: np.ndarray, d: np.ndarray, *, curved: bool) -> tuple[np.ndarray, np.ndarray, float]:
    """Ranges along the capsule stack: ``d = a_s + b·x (+ c·x²)`` with one intercept per step.

    The slope ``b = −n_x`` of a plane (its tilt along the stack); the curvature
    ``c ≈ 1/(2ρ)`` of a line or point across the stack and 0 for a plane.

    Parameters
    ----------
    x : (N,) array
        Each reading's capsule position along the stack, m.
    rows : (N,) int array
        Each reading's step (the intercepts' grouping).
    d : (N,) array
        Ranges, m.
    curved : bool
        Fit ``c`` too.

    Returns
    -------
    coefficients (b[, c]), their covariance, residual σ (m); NaN when the
    readings do not constrain them (a single capsule per step).
    """
    k = 2 if curved else 1
    _, group = np.unique(rows, return_inverse=True)
    cols = [x, x * x][:k]
    a = np.stack(cols, axis=1)
    # Within-step demeaning removes the per-step intercepts exactly.
    counts = np.bincount(group)
    am = a - (np.stack([np.bincount(group, weights=c) for c in cols], axis=1) / counts[:, None])[group]
    dm = d - (np.bincount(group, weights=d) / counts)[group]
    dof = d.size - counts.size - k
    if dof < 1:
        return np.full(k, np.nan), np.full((k, k), np.nan), float("nan")
    ata = am.T @ am
    if np.linalg.cond(ata) > 1e10:
        return np.full(k, np.nan), np.full((k, k), np.nan), float("nan")
    coef = np.linalg.solve(ata, am.T @ dm)
    res = dm - am @ coef
    s2 = float(res @ res) / dof
    return coef, s2 * np.linalg.inv(ata), math.sqrt(s2)


def bearing_from_amplitude(gamma: np.ndarray, amplitude: np.ndarray) -> tuple[float, float] | None:
    """The beam pattern's peak across γ: the vertex of a parabola in ``log A`` over the top of the region.

    ``D(ψ)²`` is symmetric about the target's direction and, in ``log``, close to
    a parabola over its upper half, so the vertex of that fit is the bearing
    even when the region is cut on one side, as long as its peak is in it.

    Parameters
    ----------
    gamma : (k,) array
        Steps' γ, rad.
    amplitude : (k,) array
        Each step's echo peak amplitude, V (NaN: none).

    Returns
    -------
    (bearing, σ) in rad, or None when the amplitudes have no interior peak.
    """
    g = np.asarray(gamma, dtype=np.float64)
    a = np.asarray(amplitude, dtype=np.float64)
    ok = np.isfinite(a) & (a > 0)
    if np.count_nonzero(ok) < 5:
        return None
    g, a = g[ok], a[ok]
    order = np.argsort(g)
    g, a = g[order], a[order]
    # A receiver that clips flattens the top: the plateau's centre is the peak when both of its ends are
    # inside the region (an unclipped echo on either side), and nothing can be said when one is not.
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
    if np.linalg.matrix_rank(m) < 3:
        return None
    coef, *_ = np.linalg.lstsq(m, la, rcond=None)
    c0, b, c = (float(v) for v in coef)
    if not c < 0:
        return None
    vertex = -b / (2 * c)
    # The vertex must be held by the samples on both of its sides, not extrapolated past the region's end.
    if np.count_nonzero(u < vertex) < 2 or np.count_nonzero(u > vertex) < 2:
        return None
    res = la - m @ coef
    dof = max(u.size - 3, 1)
    cov = float(res @ res) / dof * np.linalg.pinv(m.T @ m)
    # Delta method on −b/(2c).
    jac = np.array([0.0, -1 / (2 * c), b / (2 * c * c)])
    var = float(jac @ cov @ jac)
    return g0 + vertex, math.sqrt(max(var, 0.0))


def capsule_x(geometry: ArrayGeometry) -> np.ndarray:
    """Each capsule's position along the stack (the rotation axis), m."""
    return np.asarray(geometry.capsules_in_array_frame()[:, 0], dtype=np.float64)
