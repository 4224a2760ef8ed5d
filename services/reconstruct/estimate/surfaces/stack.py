"""What a region's ranges say along the capsule stack (the rotation axis x).

Along the stack the four ranges of one target are a straight line for a plane
(the array's mirror image is a straight array: slope ``−n_x``, the tilt) and a
hyperbola for a line or a point across the stack (``d = √(ρ² + (x − x₀)²)``:
curvature ``1/(2ρ)``); a first-echo receiver hearing two targets at one range
bends that profile the other way.

Pure functions: no I/O, no state.
"""

from __future__ import annotations

import math

import numpy as np

from lelsonar.geometry import ArrayGeometry

__all__ = ["StackFit", "StackProfile", "capsule_x", "stack_fits", "stack_profile", "two_targets"]


def stack_fits(x: np.ndarray, rows: np.ndarray, d: np.ndarray) -> tuple[StackFit, StackFit]:
    """Ranges along the capsule stack: ``d = a_s + b·x`` and ``d = a_s + b·x + c·x²``, one intercept per step.

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

    Returns
    -------
    The straight fit and the curved one, each its coefficients ((b,) and (b, c)), their covariance and
    residual σ (m); NaN when the readings do not constrain them (a single capsule per step).
    """
    group = _step_groups(rows)
    # Within-step demeaning removes the per-step intercepts exactly.
    counts = np.bincount(group)
    cols = np.stack([x, x * x], axis=1)
    means = np.stack([np.bincount(group, weights=x), np.bincount(group, weights=x * x)], axis=1) / counts[:, None]
    am = cols - means[group]
    dm = d - (np.bincount(group, weights=d) / counts)[group]
    straight = np.ascontiguousarray(am[:, :1])  # contiguous: BLAS's summation, not a strided loop's
    return _demeaned_fit(straight, dm, counts.size), _demeaned_fit(am, dm, counts.size)


def _step_groups(rows: np.ndarray) -> np.ndarray:
    """Each reading's step's rank among the steps (``np.unique(rows, return_inverse=True)[1]``), by runs where
    the readings come in step order, as a region's do."""
    r = np.asarray(rows)
    if r.size and np.all(r[1:] >= r[:-1]):
        group = np.empty(r.size, dtype=np.intp)
        group[0] = 0
        np.cumsum(r[1:] != r[:-1], out=group[1:])
        return group
    return np.unique(r, return_inverse=True)[1]


#: A least-squares fit's coefficients, their covariance and the residual σ.
StackFit = tuple[np.ndarray, np.ndarray, float]


def _demeaned_fit(am: np.ndarray, dm: np.ndarray, n_groups: int) -> StackFit:
    k = am.shape[1]
    dof = dm.size - n_groups - k
    if dof < 1:
        return np.full(k, np.nan), np.full((k, k), np.nan), float("nan")
    ata = am.T @ am
    # One coefficient: the condition number of a finite 1×1 is 1, or inf for 0 (np.linalg.cond's, without an SVD).
    single = k == 1 and math.isfinite(float(ata[0, 0]))
    if (float(ata[0, 0]) == 0.0) if single else np.linalg.cond(ata) > 1e10:
        return np.full(k, np.nan), np.full((k, k), np.nan), float("nan")
    coef = np.linalg.solve(ata, am.T @ dm)
    res = dm - am @ coef
    s2 = float(res @ res) / dof
    return coef, s2 * np.linalg.inv(ata), math.sqrt(s2)


def stack_profile(x: np.ndarray, rows: np.ndarray, capsules: np.ndarray, d: np.ndarray) -> StackProfile | None:
    """Each capsule's range less the steps' own, ``d = a_s + p_c``: the region's range profile along the stack.

    Whatever one target is, its range along the stack ``d(x)`` is convex: straight for a plane (its mirror image
    of the array is a straight array), ``√(ρ⊥² + (x − x₀)²)`` for a line or a point across the stack, whose
    second derivative ``ρ⊥²/d³`` lies in ``[0, 1/d]``.  A first-echo receiver hears the nearer of two targets
    in each capsule, the lower envelope of two convex profiles: it bends the other way where one hands over to
    the other.  So each inner capsule's divided second difference of ``p`` (exact for a parabola) with its σ
    says whether one target can have made the profile.

    Parameters
    ----------
    x : (n_capsules,) array
        Each capsule's position along the stack, m.
    rows, capsules : (N,) int arrays
        Each reading's step and capsule.
    d : (N,) array
        Ranges, m.

    Returns
    -------
    The capsules heard (in ``x`` order), each inner one's second difference (1/m) and its σ; None when fewer
    than three capsules are heard or the residuals leave no degree of freedom.
    """
    heard = np.unique(capsules)
    heard = heard[np.argsort(x[heard], kind="stable")]
    if heard.size < 3 or not np.all(np.isfinite(d)):
        return None
    group = _step_groups(rows)
    n_groups = int(group.max()) + 1
    dof = d.size - n_groups - (heard.size - 1)
    if dof < 1:
        return None
    # One indicator column per capsule but the first, demeaned within each step: the steps' intercepts drop out
    # exactly (as in stack_fits).
    lookup = np.zeros(int(heard.max()) + 1, dtype=np.intp)
    lookup[heard] = np.arange(heard.size)
    which = lookup[capsules]  # each reading's capsule's place in x order
    cols = (which[:, None] == np.arange(1, heard.size)[None, :]).astype(np.float64)
    counts = np.bincount(group)
    means = np.stack([np.bincount(group, weights=c) for c in cols.T], axis=1) / counts[:, None]
    am = cols - means[group]
    dm = d - (np.bincount(group, weights=d) / counts)[group]
    ata = am.T @ am
    if np.linalg.cond(ata) > 1e10:
        return None
    coef = np.linalg.solve(ata, am.T @ dm)
    res = dm - am @ coef
    s2 = float(res @ res) / dof
    cov = np.zeros((heard.size, heard.size))
    cov[1:, 1:] = s2 * np.linalg.inv(ata)
    p = np.concatenate([[0.0], coef])
    xs = x[heard]
    second = np.empty(heard.size - 2)
    sigma = np.empty(heard.size - 2)
    for j in range(1, heard.size - 1):
        a, b, c = float(xs[j - 1]), float(xs[j]), float(xs[j + 1])
        w = np.zeros(heard.size)
        w[j - 1], w[j], w[j + 1] = 2 / ((b - a) * (c - a)), -2 / ((b - a) * (c - b)), 2 / ((c - a) * (c - b))
        second[j - 1] = float(w @ p)
        sigma[j - 1] = math.sqrt(max(float(w @ cov @ w), 0.0))
    return heard, second, sigma


#: The capsules heard in stack order, each inner one's second difference of the range profile (1/m), its σ.
StackProfile = tuple[np.ndarray, np.ndarray, np.ndarray]


def two_targets(profile: StackProfile, apart: np.ndarray, sigmas: float) -> tuple[np.ndarray, np.ndarray] | str | None:
    """Whether a region holds two targets along the stack, and which capsules hear each.

    Two tests, from what one target can do to a first-echo receiver (Kleeman & Kuc: the receivers' differential
    ranges tell targets apart):

    * **a capsule between**: a capsule between two that hear one target is no farther from it than the farther
      of the two (the range is convex along the stack) and no farther off its beam's axis (the capsules' beams are
      parallel, ``cos ψ = h/d``), so it hears that target at least as early and as strongly.  One that hears only
      something farther there (``apart``) parts two targets.
    * **the profile bends the other way**: one target's range profile is convex (:func:`stack_profile`): every
      inner second difference at least ``−sigmas`` σ.  Where one is not, the capsule there (the most concave, in
      σ) is where the nearer target hands over to the other: the capsules on either side of it hear one target
      each, and it hears one of the two.

    Each side must be convex on its own; where both sides can take the capsule at the bend, nothing says which
    target it heard and it goes to neither.

    Parameters
    ----------
    profile : StackProfile
        The capsules the region holds in stack order and their inner second differences with σ (empty with
        fewer than three capsules).
    apart : (len(heard) − 1,) bool array
        Whether a capsule between each two neighbours of ``heard`` hears only something farther at their steps.
    sigmas : float
        How many σ a second difference must fall under 0 to bend as no one target does.

    Returns
    -------
    None: one target.  Else the two sides' capsules, or a reason when no split into two convex sides exists (more
    than two targets, or a profile no split explains).
    """
    heard, second, sigma = profile
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(sigma > 0, second / sigma, np.where(second < 0, -np.inf, 0.0))

    def convex_without(skip: set[int]) -> bool:
        """Every inner second difference but those at ``skip`` (indices into heard) within ``sigmas`` of convex."""
        return all(z[j - 1] >= -sigmas for j in range(1, heard.size - 1) if j not in skip)

    gaps = np.flatnonzero(apart)
    if gaps.size > 1:
        return f"{gaps.size} capsules between those that hear it hear only something farther: more than two targets"
    if gaps.size == 1:
        # The right side starts at heard[k]; the second differences across the gap are no one target's.
        k = int(gaps[0]) + 1
        if convex_without({k - 1, k}):
            return heard[:k], heard[k:]
        return "a capsule between those that hear it hears only something farther, and no two convex sides explain it"
    if not np.any(z < -sigmas):
        return None
    apex = int(np.argmin(z)) + 1  # index into heard
    # The apex with the left side: the sides' ends at the apex and the capsule after it have no second difference
    # of their own; with the right side: the capsule before it and the apex.
    left = convex_without({apex, apex + 1})
    right = convex_without({apex - 1, apex})
    if left and right:
        return heard[:apex], heard[apex + 1 :]
    if left:
        return heard[: apex + 1], heard[apex + 1 :]
    if right:
        return heard[:apex], heard[apex:]
    return (
        f"its ranges along the capsule stack bend as no one target's and no two do (second difference "
        f"{second[apex - 1]:.2f}/m = {z[apex - 1]:.1f} σ at capsule {int(heard[apex])})"
    )


def capsule_x(geometry: ArrayGeometry) -> np.ndarray:
    """Each capsule's position along the stack (the rotation axis), m."""
    return np.array(geometry.capsule_x, dtype=np.float64)  # (capsules_in_array_frame's first column)
