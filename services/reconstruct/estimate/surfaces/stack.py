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

__all__ = [
    "StackFit",
    "StackProfile",
    "StackTilt",
    "capsule_x",
    "stack_fits",
    "stack_profile",
    "stack_tilt",
    "two_targets",
]


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


#: The slope ``b`` (m) and curvature ``κ`` of the squared ranges along the stack, ``b``'s σ, the capsules kept, the
#: residual σ in range (m) about them and whether that σ is one reading's noise (one target).
StackTilt = tuple[float, float, float, np.ndarray, float, bool]


def _square_fit(x: np.ndarray, group: np.ndarray, y: np.ndarray, kappa: float | None) -> StackFit:
    """``y = a_s + b·x + κ·x²`` with one intercept per step: κ free (None) or fixed; coefficients (b,) or (b, κ)."""
    counts = np.bincount(group)
    yk = y if kappa is None else y - kappa * x * x
    cols = [x] if kappa is not None else [x, x * x]
    am = np.stack([c - (np.bincount(group, weights=c) / counts)[group] for c in cols], axis=1)
    ym = yk - (np.bincount(group, weights=yk) / counts)[group]
    return _demeaned_fit(am, ym, counts.size)


def _tilt_of(x: np.ndarray, rows: np.ndarray, d: np.ndarray, depth: float) -> tuple[float, float, float, float] | None:
    """``b``, ``κ``, ``b``'s σ and the residual σ in range (m) of one target's squared ranges along the stack."""
    group = _step_groups(rows)
    y = d * d
    heard = np.unique(x).size
    if heard >= 3:
        coef, cov, s = _square_fit(x, group, y, None)
        if np.all(np.isfinite(coef)):
            kappa = float(coef[1])
            if 0.0 <= kappa <= 1.0:
                b, b_se = float(coef[0]), math.sqrt(max(float(cov[0, 0]), 0.0))
            else:
                # Past a bound no one target reaches: at that bound.
                coef, cov, s = _square_fit(x, group, y, min(1.0, max(0.0, kappa)))
                b, b_se = float(coef[0]), math.sqrt(max(float(cov[0, 0]), 0.0))
            if math.isfinite(b) and math.isfinite(b_se):
                return b, min(1.0, max(0.0, kappa)), b_se, s / (2.0 * depth)
    # κ unknown: the slope anywhere between the two bounds' (uniform), beside their σ.
    ends = [_square_fit(x, group, y, k) for k in (0.0, 1.0)]
    if not all(np.all(np.isfinite(e[0])) for e in ends):
        return None
    b0, b1 = float(ends[0][0][0]), float(ends[1][0][0])
    se = max(math.sqrt(max(float(e[1][0, 0]), 0.0)) for e in ends)
    b, b_se, s = 0.5 * (b0 + b1), math.hypot(se, abs(b1 - b0) / math.sqrt(12.0)), min(ends[0][2], ends[1][2])
    return b, 0.5, b_se, s / (2.0 * depth)


def stack_tilt(
    x: np.ndarray, rows: np.ndarray, capsules: np.ndarray, d: np.ndarray, depth: float, noise: float
) -> StackTilt | None:
    """How far off the fan one target lies, seen from the array's centre, from its squared ranges along the stack.

    Whatever the target, a capsule at ``p_c = x_c·e_x + q`` (``q`` the radial offset, shared by the stack at a
    step) is at ``d_c² = |X_c − p_c|²`` from the point ``X_c`` that echoes to it.  For a point, or a line across
    the stack (every capsule's nearest point is the same), ``d² = a_s − 2 X_x x + x²``; for a plane of normal
    ``n``, ``d = h_s − n_x x``, so ``d² = a_s − 2 h n_x x + n_x² x²``; a line of direction ``u`` gives
    ``(1 − u_x²) x²``.  So ``d² = a_s + b x + κ x²`` with ``κ ∈ [0, 1]`` for any one target, and
    ``sin t = −b/(2ρ)`` at the array's centre (``−b/2`` the target's offset along the stack): exact for a point,
    a line or a plane, where a straight fit of the ranges turns a curved profile heard by uneven capsules into a
    slope.  With three capsules or more ``κ`` is fitted (at its nearer bound when past one); with two, the slope
    lies anywhere between its two bounds' and its σ spans them.

    One target's ranges about that fit scatter as one reading's noise.  Past it (the sample σ's 3 σ bound), some
    capsule hears another target (a first-echo receiver's capsule that does not hear this one reports the next):
    the capsule whose readings leave the rest within the noise goes, where one does.

    Parameters
    ----------
    x : (n_capsules,) array
        Each capsule's position along the stack, m.
    rows, capsules : (N,) int arrays
        Each reading's step and capsule.
    d : (N,) array
        Ranges, m.
    depth : float
        The target's range ``ρ``, m.
    noise : float
        One reading's range σ, m.

    Returns
    -------
    (``b``, ``κ`` (½ where unknown), ``b``'s σ, the capsules kept, the residual σ in range (m), whether it is
    within the noise's bound);
    None when fewer than two capsules hear it or their readings leave no degree of freedom.  Past that bound no
    one target explains the readings, with or without any one capsule: every capsule is kept.
    """
    if not (depth > 0 and noise > 0) or not np.all(np.isfinite(d)):
        return None
    heard = np.unique(capsules)

    def fit(keep: np.ndarray) -> tuple[float, float, float, float, int] | None:
        sel = np.isin(capsules, keep)
        if np.unique(x[capsules[sel]]).size < 2:
            return None
        out = _tilt_of(x[capsules[sel]], rows[sel], d[sel], depth)
        if out is None or not all(math.isfinite(v) for v in out):
            return None
        dof = int(np.count_nonzero(sel)) - np.unique(rows[sel]).size - (2 if keep.size >= 3 else 1)
        return (*out, max(dof, 1))

    def within(f: tuple[float, float, float, float, int]) -> bool:
        return f[3] <= noise * (1.0 + 3.0 / math.sqrt(2.0 * f[4]))

    whole = fit(heard)
    if whole is None:
        return None
    if within(whole) or heard.size < 3:
        return *whole[:3], heard, whole[3], within(whole)
    best: tuple[tuple[float, float, float, float, int], np.ndarray] | None = None
    for c in heard:
        keep = heard[heard != c]
        f = fit(keep)
        if f is not None and within(f) and (best is None or f[3] < best[0][3]):
            best = (f, keep)
    if best is None:
        return *whole[:3], heard, whole[3], False
    return *best[0][:3], best[1], best[0][3], True
