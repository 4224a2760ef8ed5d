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
from dataclasses import dataclass

import numpy as np

from lelsonar.errors import ConfigError
from lelsonar.geometry import ArrayGeometry
from lelsonar.signal.compiled import kernel

__all__ = [
    "Region",
    "find_regions",
    "stack_fits",
    "bearing_from_amplitude",
    "amplitude_jump",
    "unfaded_ends",
    "end_crossing_stderr",
    "peak_at_bearing",
    "weaker_at",
    "subregion",
    "PLATEAU",
]

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


def find_regions(
    distance: np.ndarray,
    *,
    tolerance: float = 0.015,
    max_gap: int = 2,
    min_steps: int = 3,
    max_spread: float = math.inf,
    gamma: np.ndarray | None = None,
    radial_offset: float = 0.0,
) -> list[Region]:
    """Split a sweep into regions of constant depth.

    A step joins the current run while its ranges stay steady: the median over
    its capsules of each capsule's distance from that capsule's median over the
    run (capsule by capsule where both have echoes, so a capsule that loses its
    echo at the edge of the beam does not move the others; else the step's
    median range against the run's).  A capsule's reading belongs to a region
    when it is within twice the tolerance of that capsule's median over the
    region: a tilt or a line across the stack spreads the four ranges steadily
    (by several cm for a line below the stack), another target in one capsule's
    beam does not.

    Parameters
    ----------
    distance : (n_steps, n_capsules) array
        Ranges, m (NaN: no echo), steps in sweep order.
    tolerance : float
        A step joins the current run while it is within this of the run, m (the
        range noise plus the radial offset's ``r·(1 − cos Δγ)`` over a narrow
        beam; a wider run's drift is taken off with ``gamma``).
    max_gap : int
        Steps without an echo a run may bridge.
    min_steps : int
        Shorter runs are not regions (their echoes stay unexplained).
    max_spread : float
        m: a reading farther than this from its step's median over the region's readings is not the
        region's.  One target's ranges differ between two capsules by at most their distance apart
        (the triangle inequality), so the stack's length plus the tolerance bounds them: a capsule
        whose median sits past it sees another target through most of the region.
    gamma : (n_steps,) array, optional
        Each step's rotation, rad: with ``radial_offset``, two neighbouring runs whose ranges are one target's
        drift (:func:`_drift_joins`) are one region.
    radial_offset : float
        The capsules' distance from the rotation axis, m (``r`` of ``d ≈ ρ − r·cos(γ − β)``).

    Returns
    -------
    list of Region, in sweep order.
    """
    d = np.asarray(distance, dtype=np.float64)
    if d.ndim != 2:
        raise ConfigError(f"distance must be (n_steps, n_capsules), got shape {d.shape}")
    if not (tolerance > 0 and max_gap >= 0 and min_steps >= 1):
        raise ConfigError("find_regions: tolerance > 0, max_gap >= 0 and min_steps >= 1")
    label, keep, cut = _regions(np.ascontiguousarray(d), float(tolerance), int(max_gap), int(min_steps))
    if gamma is not None and radial_offset > 0:
        g = np.asarray(gamma, dtype=np.float64)
        if g.shape != (d.shape[0],):
            raise ConfigError(f"gamma must have shape ({d.shape[0]},), got {g.shape}")
        label, keep, cut = _drift_joins(d, g, float(radial_offset), label, keep, cut, float(tolerance), int(max_gap))
    out = []
    # Each region's steps are contiguous in the label order (a run is closed before the next one opens).
    labelled = np.flatnonzero(label >= 0)
    bounds = np.flatnonzero(np.diff(label[labelled])) + 1
    for k, steps in enumerate(np.split(labelled, bounds) if labelled.size else []):
        rows, caps = np.nonzero(keep[steps])
        if math.isfinite(max_spread) and rows.size:
            block = np.where(keep[steps], d[steps], np.nan)
            with np.errstate(all="ignore"):
                med = np.nanmedian(block, axis=1)
            near = np.abs(block[rows, caps] - med[rows]) <= max_spread
            rows, caps = rows[near], caps[near]
            held = np.unique(rows)
            if held.size < min_steps:
                continue
            # Renumber the rows over the steps that still hold a reading.
            steps, rows = steps[held], np.searchsorted(held, rows)
        out.append(
            Region(
                steps=steps.astype(np.intp),
                rows=steps[rows].astype(np.intp),
                capsules=caps.astype(np.intp),
                cut_before=bool(cut[k, 0]),
                cut_after=bool(cut[k, 1]),
            )
        )
    return out


def _drift_joins(
    d: np.ndarray,
    gamma: np.ndarray,
    radial_offset: float,
    label: np.ndarray,
    keep: np.ndarray,
    cut: np.ndarray,
    tolerance: float,
    max_gap: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Join neighbouring runs that are one target's echo, split only by the radial offset's drift.

    The capsules turn ``r`` off the axis, so one target's range follows ``d ≈ ρ − r·cos(γ − β)`` over its
    run: a run wide enough drifts by more than the tolerance from its own median, ``r·(1 − cos Δγ)``, and
    is split where the echo carries on.  Two neighbouring runs are one when neither is cut at the seam (no
    nearer echo took over), no echo lies between them, and with the drift taken off at the bearing that
    makes the joined ranges steadiest, every step of both is within the tolerance of their median: one
    depth ρ.  A target at another depth stays apart by more than the tolerance once the drift is off.

    Parameters
    ----------
    d : (n_steps, n_capsules) array
        Ranges, m (NaN: no echo).
    gamma : (n_steps,) array
        Steps' rotation, rad.
    radial_offset : float
        ``r``, m.
    label, keep, cut
        :func:`_regions`' output.
    tolerance : float
        m, as :func:`find_regions`.
    max_gap : int
        Steps without an echo the seam may bridge.

    Returns
    -------
    ``label``, ``keep``, ``cut`` with the joined runs as one region (renumbered in sweep order).
    """
    n_regions = cut.shape[0]
    if n_regions < 2:
        return label, keep, cut
    label, keep, cut = label.copy(), keep.copy(), cut.copy()
    with np.errstate(all="ignore"):
        any_echo = np.isfinite(d).any(axis=1)
    spans = [np.flatnonzero(label == k) for k in range(n_regions)]
    merged: list[list[int]] = [[0]]
    for k in range(1, n_regions):
        prev = merged[-1]
        a, b = np.concatenate([spans[i] for i in prev]), spans[k]
        between = np.arange(int(a[-1]) + 1, int(b[0]))
        if (
            not cut[prev[-1], 1]
            and not cut[k, 0]
            and between.size <= max_gap
            and not any_echo[between].any()
            and _one_depth(d, gamma, radial_offset, keep, np.concatenate([a, b]), tolerance) is not None
        ):
            prev.append(k)
        else:
            merged.append([k])
    if len(merged) == n_regions:
        return label, keep, cut
    out_cut = np.zeros((len(merged), 2), dtype=np.bool_)
    for j, group in enumerate(merged):
        steps = np.concatenate([spans[i] for i in group])
        label[steps] = j
        out_cut[j] = cut[group[0], 0], cut[group[-1], 1]
        if len(group) > 1:
            beta = _one_depth(d, gamma, radial_offset, keep, steps, tolerance)
            # A capsule's reading is the region's within twice the tolerance of its median, drift taken off.
            flat = d[steps] + radial_offset * np.cos(gamma[steps] - beta)[:, None]
            with np.errstate(all="ignore"):
                med = np.nanmedian(flat, axis=0)
                keep[steps] = np.isfinite(flat) & (np.abs(flat - med) <= 2 * tolerance)
    return label, keep, out_cut


def _one_depth(
    d: np.ndarray, gamma: np.ndarray, radial_offset: float, keep: np.ndarray, steps: np.ndarray, tolerance: float
) -> float | None:
    """The bearing β (one of the steps' γ) at which the steps' held ranges, plus ``r·cos(γ − β)``, are all
    within ``tolerance`` of their median (each step's median over its held capsules), the steadiest such;
    None when no β makes them one depth."""
    block = np.where(keep[steps], d[steps], np.nan)
    with np.errstate(all="ignore"):
        rs = np.nanmedian(block, axis=1)
    ok = np.isfinite(rs)
    g, rs = gamma[steps][ok], rs[ok]
    if g.size < 2:
        return None
    # Rows: candidate β; columns: the steps' ranges with that β's drift taken off.
    flat = rs[None, :] + radial_offset * np.cos(g[None, :] - g[:, None])
    worst = np.max(np.abs(flat - np.median(flat, axis=1, keepdims=True)), axis=1)
    best = int(np.argmin(worst))
    return float(g[best]) if worst[best] <= tolerance else None


def subregion(region: Region, steps: np.ndarray, cut_before: bool, cut_after: bool) -> Region:
    """The part of ``region`` over ``steps`` (its readings there), with the cut flags given."""
    keep = np.isin(region.rows, steps)
    return Region(
        steps=steps, rows=region.rows[keep], capsules=region.capsules[keep], cut_before=cut_before, cut_after=cut_after
    )


@kernel
def _median_sorted(v: np.ndarray, n: int) -> float:
    """Median of the first ``n`` values of a sorted array, as ``np.median`` (the mean of the middle two)."""
    h = n // 2
    if n % 2:
        return v[h]
    return (v[h - 1] + v[h]) / 2


@kernel
def _insert_sorted(v: np.ndarray, n: int, x: float) -> None:
    """Insert ``x`` into the sorted first ``n`` values of ``v`` (which has room)."""
    i = n
    while i > 0 and v[i - 1] > x:
        v[i] = v[i - 1]
        i -= 1
    v[i] = x


@kernel
def _nan_median(values: np.ndarray) -> float:
    """Median of the values that are not NaN (NaN if none), as ``np.nanmedian``."""
    buf = np.empty(values.shape[0])
    n = 0
    for x in values:
        if not np.isnan(x):
            _insert_sorted(buf, n, x)
            n += 1
    return _median_sorted(buf, n) if n else np.nan


@kernel
def _regions(
    d: np.ndarray, tolerance: float, max_gap: int, min_steps: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`find_regions`' arithmetic: each step's region (−1: none), each reading's membership, the cuts.

    Returns
    -------
    label : (n_steps,) int array
        The step's region, numbered in sweep order; −1 for a step in none.
    keep : (n_steps, n_capsules) bool array
        The readings of the regions' steps that belong to their region.
    cut : (n_regions, 2) bool array
        Whether each region is cut before and after.
    """
    n, m = d.shape
    rs = np.empty(n)  # each step's median range over its capsules (NaN: no echo)
    for s in range(n):
        rs[s] = _nan_median(d[s])
    run = np.full(n, -1, dtype=np.int64)
    seen = np.empty((m, n))  # each capsule's ranges in the run, sorted
    n_seen = np.zeros(m, dtype=np.int64)
    run_ranges = np.empty(n)  # the run's steps' ranges, sorted
    devs = np.empty(m)
    n_run = 0
    current = -1
    gap = 0
    for s in range(n):
        if not np.isfinite(rs[s]):
            gap += 1
            if n_run and gap > max_gap:
                n_run = 0
            continue
        joins = False
        if n_run:
            k = 0
            for c in range(m):
                if n_seen[c] and np.isfinite(d[s, c]):
                    _insert_sorted(devs, k, abs(d[s, c] - _median_sorted(seen[c], n_seen[c])))
                    k += 1
            steady = _median_sorted(devs, k) if k else abs(rs[s] - _median_sorted(run_ranges, n_run))
            joins = steady <= tolerance
        if not joins:
            current += 1
            n_run = 0
            n_seen[:] = 0
        run[s] = current
        _insert_sorted(run_ranges, n_run, rs[s])
        n_run += 1
        for c in range(m):
            if np.isfinite(d[s, c]):
                _insert_sorted(seen[c], n_seen[c], d[s, c])
                n_seen[c] += 1
        gap = 0
    # Runs shorter than a region are dropped; the others are renumbered.
    n_runs = current + 1
    first = np.full(n_runs, n, dtype=np.int64)
    last = np.full(n_runs, -1, dtype=np.int64)
    size = np.zeros(n_runs, dtype=np.int64)
    for s in range(n):
        r = run[s]
        if r >= 0:
            first[r] = min(first[r], s)
            last[r] = max(last[r], s)
            size[r] += 1
    label = np.full(n, -1, dtype=np.int64)
    keep = np.zeros((n, m), dtype=np.bool_)
    cut = np.zeros((n_runs, 2), dtype=np.bool_)
    n_regions = 0
    block = np.empty(n)
    for r in range(n_runs):
        if size[r] < min_steps:
            continue
        k = 0
        for s in range(first[r], last[r] + 1):
            if run[s] == r:
                label[s] = n_regions
                _insert_sorted(block, k, rs[s])
                k += 1
        ref = _median_sorted(block, k)
        for c in range(m):
            k = 0
            for s in range(first[r], last[r] + 1):
                if run[s] == r:
                    block[k] = d[s, c]
                    k += 1
            med = _nan_median(block[:k])
            for s in range(first[r], last[r] + 1):
                if run[s] == r and np.isfinite(d[s, c]) and abs(d[s, c] - med) <= 2 * tolerance:
                    keep[s, c] = True
        cut[n_regions, 0] = _cut(rs, first[r], -1, ref, tolerance, max_gap)
        cut[n_regions, 1] = _cut(rs, last[r], 1, ref, tolerance, max_gap)
        n_regions += 1
    return label, keep, cut[:n_regions]


@kernel
def _cut(rs: np.ndarray, end: int, direction: int, ref: float, tolerance: float, max_gap: int) -> bool:
    """Whether a run's end is a cut: the sweep's end, or a nearer echo within ``max_gap + 2`` steps (a step
    between two targets may hold a little of both, and belong to neither)."""
    n = rs.shape[0]
    if not 0 <= end + direction < n:
        return True
    for k in range(1, max_gap + 3):
        s = end + direction * k
        if 0 <= s < n and np.isfinite(rs[s]) and rs[s] < ref - tolerance:
            return True
    return False


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
    _, group = np.unique(rows, return_inverse=True)
    # Within-step demeaning removes the per-step intercepts exactly.
    counts = np.bincount(group)
    cols = np.stack([x, x * x], axis=1)
    means = np.stack([np.bincount(group, weights=x), np.bincount(group, weights=x * x)], axis=1) / counts[:, None]
    am = cols - means[group]
    dm = d - (np.bincount(group, weights=d) / counts)[group]
    straight = np.ascontiguousarray(am[:, :1])  # contiguous: BLAS's summation, not a strided loop's
    return _demeaned_fit(straight, dm, counts.size), _demeaned_fit(am, dm, counts.size)


#: A least-squares fit's coefficients, their covariance and the residual σ.
StackFit = tuple[np.ndarray, np.ndarray, float]


def _demeaned_fit(am: np.ndarray, dm: np.ndarray, n_groups: int) -> StackFit:
    k = am.shape[1]
    dof = dm.size - n_groups - k
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


def log_amplitude_curvature(gamma: np.ndarray, amplitude: np.ndarray, *, plateau: bool = False) -> float | None:
    """The beam pattern's curvature in ``log A`` across γ, from a region whose peak is inside it.

    Every echo of a rotating transceiver, a mirror's, a corner's or an edge's,
    follows ``D(γ − β)²`` across γ; in ``log`` its top is close to a parabola
    ``log A ≈ P − k (γ − β)²``.  A sweep's uncut regions give ``k`` for that
    sweep's own capsules (no beam model assumed).

    Parameters
    ----------
    gamma, amplitude : (k,) arrays
        Steps' γ (rad) and each step's echo amplitude (NaN: none).
    plateau : bool
        Fit a top whose largest values are equal too (a flat top under the receiver's full scale is the
        amplitude's quantisation, or a wide echo), rather than say nothing.

    Returns
    -------
    ``k`` (1/rad², > 0), or None when the top of the amplitudes is no parabola opening down.
    """
    g = np.asarray(gamma, dtype=np.float64)
    a = np.asarray(amplitude, dtype=np.float64)
    ok = np.isfinite(a) & (a > 0)
    if np.count_nonzero(ok) < 5:
        return None
    g, a = g[ok], a[ok]
    top = a >= 0.5 * a.max()
    if np.count_nonzero(top) < 5 or (not plateau and np.count_nonzero(a >= (1.0 - PLATEAU) * a.max()) >= 3):
        return None  # too few samples on the top, or a clipped plateau
    u = g[top] - float(np.mean(g[top]))
    m = np.stack([np.ones_like(u), u, u * u], axis=1)
    if np.linalg.matrix_rank(m) < 3:
        return None
    coef, *_ = np.linalg.lstsq(m, np.log(a[top]), rcond=None)
    return float(-coef[2]) if coef[2] < 0 else None


def extrapolated_peak(
    gamma: np.ndarray, amplitude: np.ndarray, curvature: float, *, before: float, after: float
) -> float | None:
    """The peak amplitude of a region whose peak lies past a cut end, from the flank it shows.

    With the sweep's beam curvature ``k`` fixed, ``log A + k u² = P − k v² + 2 k v u``
    is a line in ``u``: its slope puts the vertex ``v``, and ``P`` follows.
    On the flank the piston pattern falls faster than its parabola, so the
    slope overstates how far the peak is and ``P`` overstates the peak: an
    upper estimate, safe to call an echo weak by, never strong.

    Parameters
    ----------
    gamma, amplitude : (k,) arrays
        Steps' γ (rad) and each step's echo amplitude (NaN: none).
    curvature : float
        ``k`` of :func:`log_amplitude_curvature`, 1/rad².
    before, after : float
        rad: how far before the first and after the last step the vertex may lie (0 on a side the
        region's echo faded on: its peak is not there).

    Returns
    -------
    The peak amplitude, or None when the vertex falls outside that reach or too few steps have echoes.
    """
    g = np.asarray(gamma, dtype=np.float64)
    a = np.asarray(amplitude, dtype=np.float64)
    ok = np.isfinite(a) & (a > 0)
    if np.count_nonzero(ok) < 3 or not curvature > 0:
        return None
    g, a = g[ok], a[ok]
    g0 = float(np.mean(g))
    u = g - g0
    y = np.log(a) + curvature * u * u
    slope, icpt = np.polyfit(u, y, 1)
    v = float(slope) / (2 * curvature)
    lo, hi = float(u.min()) - before, float(u.max()) + after
    if not lo <= v <= hi:
        return None
    peak = math.exp(float(icpt) + curvature * v * v)
    return max(peak, float(a.max()))


def peak_at_bearing(
    gamma: np.ndarray, amplitude: np.ndarray, bearing: float, curvature: float
) -> tuple[float, float] | None:
    """The peak amplitude of an echo whose bearing is known from elsewhere, from the flank a region shows.

    Every echo of a rotating transceiver follows the beam ``D(γ − β)²``, in
    ``log`` close to ``P − k (γ − β)²`` (:func:`log_amplitude_curvature`).  With
    ``β`` placed by the geometry (a plane's trace), each step gives the peak,
    ``A(γ) · exp(k (γ − β)²)``, and their median is the estimate.  The piston
    falls at least as fast as its parabola off the top (within a few % of it
    over a wide main lobe, much faster on a narrow one's far flank), so the
    estimate does not overstate the peak by more than that: safe to call an
    echo strong by.  It is close to the peak (safe to call an echo weak by)
    only where some step lies within the top the curvature was fitted over
    (``k (γ − β)² ≤ log 2``).

    Parameters
    ----------
    gamma, amplitude : (k,) arrays
        Steps' γ (rad) and each step's echo amplitude (NaN: none).
    bearing : float
        The echo's bearing, rad.
    curvature : float
        ``k`` of :func:`log_amplitude_curvature`, 1/rad².

    Returns
    -------
    (peak amplitude, ``k`` times the nearest step's squared offset from ``bearing``), or None when no step
    has an amplitude or the curvature is not positive.
    """
    g = np.asarray(gamma, dtype=np.float64)
    a = np.asarray(amplitude, dtype=np.float64)
    ok = np.isfinite(a) & (a > 0)
    if not ok.any() or not curvature > 0:
        return None
    off = np.angle(np.exp(1j * (g[ok] - bearing)))  # wrapped to (−π, π]
    peaks = a[ok] * np.exp(curvature * off * off)
    return float(np.median(peaks)), float(curvature * np.min(off * off))


def weaker_at(gamma: np.ndarray, amplitude: np.ndarray, bearing: float, *, sigmas: float = 3.0) -> bool:
    """Whether a region's echo is weaker at ``bearing``, inside its span, than elsewhere in it beyond what one
    beam pattern and the amplitude noise allow: a target there would be the strongest echo of its own region.

    One target's echo follows ``D(γ − β)²``, largest at ``γ = β``: every step's amplitude is at most the
    peak, and the steps on either side of ``β`` are within the beam's change over one step of it (at most
    ``8 R Δγ / L`` in ``log``, as :func:`amplitude_jump` bounds it, ``R`` the region's range of log amplitude
    over its span ``L``).  The region's largest amplitude above the larger of the two steps around
    ``β`` by more than that and ``sigmas`` σ of a two-step difference of the amplitude noise contradicts a
    target at ``β``.

    Parameters
    ----------
    gamma, amplitude : (k,) arrays
        Steps' γ (rad) and each step's echo amplitude (NaN: none).
    bearing : float
        rad.
    sigmas : float

    Returns
    -------
    True where the amplitudes contradict a target at ``bearing``; False where they do not, where ``bearing``
    lies outside the steps' span, or where too few steps have an amplitude to say.
    """
    g = np.asarray(gamma, dtype=np.float64)
    a = np.asarray(amplitude, dtype=np.float64)
    ok = np.isfinite(a) & (a > 0)
    if np.count_nonzero(ok) < 5:
        return False
    g, la = g[ok], np.log(a[ok])
    order = np.argsort(g)
    g, la = g[order], la[order]
    if not g[0] < bearing < g[-1]:
        return False
    span = float(g[-1] - g[0])
    slope, sigma = _beam_slope_and_noise(la, span)
    i = int(np.searchsorted(g, bearing))
    there = max(float(la[i - 1]), float(la[i]))
    step = float(g[i] - g[i - 1])
    return float(la.max()) - there > slope * step + sigmas * math.sqrt(2.0) * sigma


def amplitude_jump(gamma: np.ndarray, amplitude: np.ndarray, *, sigmas: float = 3.0) -> tuple[float, int] | None:
    """Where one echo takes over from another inside a region: an amplitude step no beam pattern makes.

    One target's echo follows ``D(γ − β)²`` across γ, in ``log`` a parabola
    ``log A = P − k (γ − β)²`` opening down.  Over a region of span ``L`` whose
    amplitudes range over ``R = log(A_max / A_min)``, such a parabola changes by
    at most ``4 R |Δγ| / L`` between two steps ``Δγ`` apart (its slope is
    largest at the end farthest from its vertex, ``2 R / max(u, L − u) ≤ 4 R / L``).
    A piston's flank falls faster than its parabola, at most twice as steep
    down to 35 dB under its peak, so the bound is doubled: ``8 R |Δγ| / L``.

    A jump beyond it (and beyond ``sigmas`` σ of the steps' amplitude noise, σ
    from the second differences' median absolute deviation) that persists,
    the two-step changes across it (from the step before it, and to the step
    after next) beyond their bound the same way, is one echo taking over from another at the same range: a weak
    edge's diffraction beside a strong mirror whose foot leaves its face, say.
    One step out of line is not (a ringing echo bends one step's amplitude).

    Parameters
    ----------
    gamma, amplitude : (k,) arrays
        Steps' γ (rad) and each step's echo amplitude (NaN: none).
    sigmas : float
        How many σ of the amplitude noise a jump must exceed the bound by.

    Returns
    -------
    (γ midway between the two steps of the largest such jump, how many of the region's steps with an
    amplitude lie on its shorter side), or None.
    """
    g = np.asarray(gamma, dtype=np.float64)
    a = np.asarray(amplitude, dtype=np.float64)
    ok = np.isfinite(a) & (a > 0)
    if np.count_nonzero(ok) < 6:
        return None
    g, la = g[ok], np.log(a[ok])
    order = np.argsort(g)
    g, la = g[order], la[order]
    span = float(g[-1] - g[0])
    if not span > 0:
        return None
    slope, sigma = _beam_slope_and_noise(la, span)
    noise = sigmas * math.sqrt(2.0) * sigma

    def beyond(i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """How far the change from step i to step j exceeds one beam pattern's, signed as the change (0: not)."""
        change = la[j] - la[i]
        excess = np.abs(change) - (slope * (g[j] - g[i]) + noise)
        return np.where(excess > 0, np.sign(change) * excess, 0.0)

    # Jump k lies between steps k and k + 1; it persists if k − 1 to k + 1 and k to k + 2 jump the same way.
    k = np.arange(1, g.size - 2)
    one = beyond(k, k + 1)
    before, after = beyond(k - 1, k + 1), beyond(k, k + 2)
    persists = ((one > 0) & (before > 0) & (after > 0)) | ((one < 0) & (before < 0) & (after < 0))
    one = np.abs(one)
    if not persists.any():
        return None
    j = int(k[persists][int(np.argmax(one[persists]))])
    return 0.5 * float(g[j] + g[j + 1]), min(j + 1, g.size - j - 1)


def _beam_slope_and_noise(la: np.ndarray, span: float) -> tuple[float, float]:
    """The steepest change of log amplitude one beam pattern can make over a region (per rad) and the log
    amplitudes' noise σ, for :func:`amplitude_jump` and :func:`unfaded_ends`.

    ``la``: the region's log amplitudes in γ order; ``span``: its γ extent, rad.  The slope bound is
    ``8 Δ/span`` (``Δ`` the region's range of log amplitude); the σ is robust (1.4826 MAD) from the second
    differences, whose variance is 6 σ² for white noise.
    """
    second = np.diff(la, 2)
    sigma = 1.4826 * float(np.median(np.abs(second - np.median(second)))) / math.sqrt(6.0)
    return 8.0 * float(la.max() - la.min()) / span, sigma


def unfaded_ends(gamma: np.ndarray, amplitude: np.ndarray, *, sigmas: float = 3.0) -> tuple[bool, bool] | None:
    """Which ends of a region the echo stops at while still strong: not where the beam pattern fades it.

    A region at one range ends on each side where ``D(γ − β)²`` falls under
    the receiver's threshold, the same threshold on both sides (one range), so
    its two end amplitudes are equal up to where each crossing falls within
    its step: at most the beam's change over one step at the end.  With the
    region's amplitudes spanning ``R = log(A_max / A_min)`` over a span ``L``,
    that change is at most ``8 R Δγ / L`` (the parabola's end slope ``4 R / L``,
    doubled for a piston's flank, as in :func:`amplitude_jump`).  An end whose
    amplitude exceeds the other's by more than that (and by ``sigmas`` σ of
    the amplitude noise) is not a fade: the echo stops there because its
    mirror does (the foot leaves the wall where the wall ends), and the
    region's centre is not the wall's bearing.

    Parameters
    ----------
    gamma, amplitude : (k,) arrays
        Steps' γ (rad) and each step's echo amplitude (NaN: none), in sweep order.
    sigmas : float
        How many σ of the amplitude noise the difference must exceed the bound by.

    Returns
    -------
    (the first end is not a fade, the last end is not a fade), or None when too few steps have an amplitude.
    """
    g = np.asarray(gamma, dtype=np.float64)
    a = np.asarray(amplitude, dtype=np.float64)
    ok = np.isfinite(a) & (a > 0)
    if np.count_nonzero(ok) < 5:
        return None
    g, la = g[ok], np.log(a[ok])
    span = abs(float(g[-1] - g[0]))
    if not span > 0:
        return None
    step = float(np.median(np.abs(np.diff(g))))
    slope, sigma = _beam_slope_and_noise(la, span)
    # A difference of two steps' log amplitudes has variance 2 σ².
    bound = slope * step + sigmas * math.sqrt(2.0) * sigma
    diff = float(la[0] - la[-1])
    return diff > bound, -diff > bound


def end_crossing_stderr(gamma: np.ndarray, amplitude: np.ndarray) -> tuple[float, float]:
    """How far the amplitude noise moves where a region's echo crosses the receiver's threshold, at each end.

    A region ends where ``D(γ − β)²`` falls under the threshold.  A noise of σ in ``log A`` moves that
    crossing by ``σ / |∂ log A/∂γ|`` at the end (the beam's log slope there, from a line through the end's
    own steps): an upper bound, as the first of several noisy steps near the threshold to pass it wanders
    less than one crossing would.  The σ is robust (1.4826 MAD of the second differences, whose variance
    is 6 σ² for white noise, as :func:`amplitude_jump` has it); noise-free amplitudes move nothing.  An end
    whose slope is not resolved (flat, clipped) is anywhere in the region: the span's ``1/√12``.

    Parameters
    ----------
    gamma, amplitude : (k,) arrays
        Steps' γ (rad) and each step's echo amplitude (NaN: none), in sweep order.

    Returns
    -------
    (σ at the first end, σ at the last end), rad; (0, 0) when too few steps have an amplitude.
    """
    g = np.asarray(gamma, dtype=np.float64)
    a = np.asarray(amplitude, dtype=np.float64)
    ok = np.isfinite(a) & (a > 0)
    if np.count_nonzero(ok) < 6:
        return 0.0, 0.0
    g, la = g[ok], np.log(a[ok])
    span = abs(float(g[-1] - g[0]))
    _, sigma = _beam_slope_and_noise(la, span) if span > 0 else (0.0, 0.0)
    if not sigma > 0:
        return 0.0, 0.0
    m = max(3, g.size // 6)
    out = []
    for sel in (slice(0, m), slice(g.size - m, g.size)):
        slope = float(np.polyfit(g[sel], la[sel], 1)[0])
        out.append(min(sigma / abs(slope), span / math.sqrt(12.0)) if slope != 0 else span / math.sqrt(12.0))
    return out[0], out[1]
