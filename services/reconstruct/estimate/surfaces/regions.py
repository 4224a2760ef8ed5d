"""Regions of constant depth (RCDs) of one sweep.

A specular target (a plane, a concave corner, a convex edge) answers a rotating
sonar over a run of steps at a steady range: the region of constant depth of
Leonard & Durrant-Whyte.  The range is the target's distance from the rotation
axis less the capsule's radial offset, to first order at every step of the run
(``d ≈ ρ − r·cos(γ − β)``), so the run's *centre* is the target's bearing β and
its *minimum* the depth ρ.  What its ranges say along the capsule stack is
:mod:`~lelsonar.reconstruct.estimate.surfaces.stack`'s.

Pure functions: no I/O, no state.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lelsonar.errors import ConfigError
from lelsonar.reconstruct.estimate.robust import median
from lelsonar.signal.compiled import kernel

__all__ = [
    "Region",
    "find_regions",
    "subregion",
    "capsule_subregion",
]


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
    part : bool
        The region's run held two targets at ranges apart by more than the stack's length, each heard by
        part of the capsules: this is one of them (:func:`find_regions`).
    """

    steps: np.ndarray
    rows: np.ndarray
    capsules: np.ndarray
    cut_before: bool
    cut_after: bool
    part: bool = False

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
    for k, run in enumerate(np.split(labelled, bounds) if labelled.size else []):
        rows_all, caps_all = np.nonzero(keep[run])
        groups = (
            _range_groups(d[run][rows_all, caps_all], caps_all, max_spread) if math.isfinite(max_spread) else [None]
        )
        for group in groups:
            steps, rows, caps = run, rows_all, caps_all
            if group is not None:
                rows, caps = _group_readings(d[run], keep[run], rows_all, caps_all, group, max_spread)
            if math.isfinite(max_spread) and rows.size:
                # A step joins its run near the capsules' medians as they stand then, and a reading is the region's
                # near their medians over the whole run: where the range moves along the run by more than that (a
                # wide run's radial-offset drift, ranges on another scale, another target's echo opening the run),
                # a step at one of its ends holds none of the region's readings.  It is no step of the region:
                # only the steps that hold one have a median.
                steps, rows = _holding(steps, rows)
                block = np.full((steps.size, d.shape[1]), np.nan)
                block[rows, caps] = d[steps[rows], caps]
                with np.errstate(invalid="ignore"):  # an infinite reading against an infinite median
                    med = _row_nan_medians(block)
                    near = np.abs(block[rows, caps] - med[rows]) <= max_spread
                rows, caps = rows[near], caps[near]
                steps, rows = _holding(steps, rows)
                if steps.size < min_steps:
                    continue
            out.append(
                Region(
                    steps=steps.astype(np.intp),
                    rows=steps[rows].astype(np.intp),
                    capsules=caps.astype(np.intp),
                    cut_before=bool(cut[k, 0]),
                    cut_after=bool(cut[k, 1]),
                    part=len(groups) > 1,
                )
            )
    return out


def _range_groups(d: np.ndarray, caps: np.ndarray, max_spread: float) -> list[np.ndarray | None]:
    """The run's capsules grouped by the target they hear: ``[None]`` (one group, all of them) unless their
    medians over the run fall apart by more than ``max_spread``.

    One target's ranges differ between two capsules by at most their distance apart (the triangle inequality),
    so capsules whose medians lie farther apart than the stack's length hear two targets through the run (a
    nearer one some capsules' beams hold, a farther one past it in the others).  Their step medians fall
    between the two, so each group is a region of its own, heard by part of the stack.
    """
    heard = np.unique(caps)
    if heard.size < 2:
        return [None]
    med = np.array([median(d[caps == c]) for c in heard])
    if not np.all(np.isfinite(med)):
        return [None]
    order = np.argsort(med)
    cuts = np.flatnonzero(np.diff(med[order]) > max_spread) + 1
    if not cuts.size:
        return [None]
    return [np.sort(heard[g]) for g in np.split(order, cuts)]


def _group_readings(
    d: np.ndarray, keep: np.ndarray, rows: np.ndarray, caps: np.ndarray, group: np.ndarray, max_spread: float
) -> tuple[np.ndarray, np.ndarray]:
    """One range group's readings over a run (``d``, ``keep``: the run's steps; ``rows``, ``caps``: its kept
    readings): the group's capsules' kept readings, and any capsule's reading the run did not keep (its capsule
    hears the other target through most of the run) within ``max_spread`` of the group's step median."""
    mine = np.isin(caps, group)
    table = np.full(d.shape, np.nan)
    table[rows[mine], caps[mine]] = d[rows[mine], caps[mine]]
    with np.errstate(invalid="ignore"):
        med = _row_nan_medians(np.where(np.isnan(table).all(axis=1, keepdims=True), np.inf, table))
        stray = ~keep & np.isfinite(d) & (np.abs(d - med[:, None]) <= max_spread)
    out = np.isfinite(table) | stray
    r, c = np.nonzero(out)
    return r, c


def _holding(steps: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The steps that hold a reading (``rows``: each reading's index into ``steps``), the rows renumbered."""
    present = np.zeros(steps.size, dtype=np.bool_)
    present[rows] = True
    # Each held step's rank among the held ones (np.unique and searchsorted's numbers, without a sort).
    rank = np.cumsum(present, dtype=np.intp) - 1
    return steps[present], rank[rows]


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
            # (A capsule that hears nothing over the joined steps has no median, and no reading to keep.)
            heard = np.isfinite(flat).any(axis=0)
            med = np.full(flat.shape[1], np.nan)
            with np.errstate(invalid="ignore"):  # an infinite reading against an infinite median
                med[heard] = _row_nan_medians(np.ascontiguousarray(flat[:, heard].T))
                keep[steps] = np.isfinite(flat) & (np.abs(flat - med) <= 2 * tolerance)
    return label, keep, out_cut


def _one_depth(
    d: np.ndarray, gamma: np.ndarray, radial_offset: float, keep: np.ndarray, steps: np.ndarray, tolerance: float
) -> float | None:
    """The bearing β (one of the steps' γ) at which the steps' held ranges, plus ``r·cos(γ − β)``, are all
    within ``tolerance`` of their median (each step's median over its held capsules), the steadiest such;
    None when no β makes them one depth."""
    # Each step's median over its held capsules; a step at a drifting run's end may hold none (see find_regions).
    held = keep[steps].any(axis=1)
    block = np.where(keep[steps][held], d[steps][held], np.nan)
    with np.errstate(invalid="ignore"):  # an infinite reading
        rs = _row_nan_medians(block)
    ok = np.isfinite(rs)
    g, rs = gamma[steps][held][ok], rs[ok]
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
        steps=steps,
        rows=region.rows[keep],
        capsules=region.capsules[keep],
        cut_before=cut_before,
        cut_after=cut_after,
        part=region.part,
    )


def capsule_subregion(region: Region, capsules: np.ndarray) -> Region:
    """The part of ``region`` its ``capsules`` hear: their readings, on the steps that hold one (cuts as the
    region's)."""
    keep = np.isin(region.capsules, capsules)
    rows = region.rows[keep]
    return Region(
        steps=np.unique(rows),
        rows=rows,
        capsules=region.capsules[keep],
        cut_before=region.cut_before,
        cut_after=region.cut_after,
        part=True,
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
def _row_nan_medians(block: np.ndarray) -> np.ndarray:
    """``np.nanmedian(block, axis=1)`` of a 2-D array, the same numbers, without its masked-array path."""
    out = np.empty(block.shape[0])
    for i in range(block.shape[0]):
        out[i] = _nan_median(block[i])
    return out


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
