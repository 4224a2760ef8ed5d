"""A region of constant depth that holds two targets at its ends: its flanks, told apart along the stack."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from lelsonar.geometry import ArrayGeometry
from lelsonar.reconstruct.estimate.surfaces.evidence import Measured, measure_region, stack_dihedral, unit_normal
from lelsonar.reconstruct.estimate.surfaces.regions import subregion
from lelsonar.reconstruct.estimate.surfaces.results import SurfaceOptions

__all__ = ["split_flanks", "step_slopes"]


def step_slopes(m: Measured) -> tuple[np.ndarray, np.ndarray]:
    """Each of the region's steps' slope of range along the capsule stack, ``∂d/∂x``, and its σ.

    A plane gives every step its one slope, ``−n_x`` (its tilt); a line across the stack (a wall's foot on
    the floor, a box's top edge) a slope that follows the capsules' offset from it.  The σ is the range
    noise (pooled over the steps' residuals about their own lines, so whatever target a step holds) over
    ``√Σ(x − x̄)²`` of that step's capsules.

    Returns
    -------
    slopes, sigmas : (k,) arrays over ``region.steps`` (NaN under two capsules, or without residual dof).
    """
    r = m.region
    k = r.steps.size
    pos = np.searchsorted(r.steps, r.rows)
    x, d = m.positions[:, 0], m.ranges
    n = np.bincount(pos, minlength=k).astype(float)
    with np.errstate(invalid="ignore", divide="ignore"):
        mx = np.bincount(pos, weights=x, minlength=k) / n
        md = np.bincount(pos, weights=d, minlength=k) / n
        sxx = np.bincount(pos, weights=(x - mx[pos]) ** 2, minlength=k)
        sxd = np.bincount(pos, weights=(x - mx[pos]) * (d - md[pos]), minlength=k)
        slopes = np.where((n >= 2) & (sxx > 0), sxd / sxx, np.nan)
        resid = d - md[pos] - np.nan_to_num(slopes[pos]) * (x - mx[pos])
    dof = float(np.sum(np.maximum(n - 2, 0)))
    if not dof > 0:
        return slopes, np.full(k, np.nan)
    noise = math.sqrt(float(np.sum(np.where(n[pos] > 2, resid * resid, 0.0))) / dof)
    with np.errstate(divide="ignore"):
        return slopes, np.where(np.isfinite(slopes), noise / np.sqrt(sxx), np.nan)


def _flank(z: np.ndarray, min_steps: int, sigmas: float) -> int:
    """The run of steps at the start whose slopes stand off the rest together: its length, 0 for none.

    ``z``: each step's deviation from the region's slope in its own σ (NaN: none).  The run is the one of
    largest ``t = Σ z / √n`` (``n`` its steps with a slope), which must exceed ``sigmas``, with at least
    ``min_steps`` slopes in it and twice that left after it.
    """
    ok = np.isfinite(z)
    zs = np.cumsum(np.where(ok, z, 0.0))
    ns = np.cumsum(ok)
    left = ns[-1] - ns
    best, length = 0.0, 0
    for b in range(z.size):
        if ns[b] < min_steps or not ok[b]:
            continue
        if left[b] < 2 * min_steps:
            break
        t = abs(float(zs[b])) / math.sqrt(float(ns[b]))
        if t > best:
            best, length = t, b + 1
    return length if best > sigmas else 0


def split_flanks(
    m: Measured,
    gamma: np.ndarray,
    distance: np.ndarray,
    amplitude: np.ndarray | None,
    geometry: ArrayGeometry,
    opts: SurfaceOptions,
) -> list[Measured] | None:
    """A plane's region whose end steps slope along the stack as its middle's do not: another target there.

    Where a wall meets the floor below a horizontal fan, the corner's double bounce lies behind the wall by
    ``z²/(2h)`` only (``z`` the array's height, ``h`` the wall's depth): within the range tolerance, and at
    the wall's own bearing.  Where the beam turns off the wall, the corner (brighter: two reflections of a
    retro-reflector against one mirror) stays over the receiver's threshold a few steps longer than the wall,
    so the region's ends are the corner's.  The capsule stack tells them apart: the wall's ranges take its one
    slope at every step, the corner's the slope of the capsules' distances to a line off the stack's middle.
    Each end's run of steps whose slopes stand off the region's median slope together by more than
    ``curvature_sigmas`` of their σ (:func:`step_slopes`, ``Σz/√n``), ``min_steps`` long, splits off, cut on
    the middle's side, where the middle's own double bounce with a surface across the fan explains its
    ranges (:func:`~.evidence.stack_dihedral`); else it stays the plane's.  The
    middle keeps the whole region's bearing when that came from its centre: the flanks' target shares it (a
    line's nearest point lies at the wall's foot), so the span stays symmetric about the foot.

    Returns
    -------
    The region's replacement (the flanks and the middle, in sweep order), or None.
    """
    r = m.region
    if r.steps.size < 3 * opts.min_steps:
        return None
    slopes, sigmas = step_slopes(m)
    ok = np.isfinite(slopes) & np.isfinite(sigmas) & (sigmas > 0)
    if np.count_nonzero(ok) < 3 * opts.min_steps:
        return None
    ref = float(np.median(slopes[ok]))
    z = np.where(ok, (slopes - ref) / np.where(ok, sigmas, 1.0), np.nan)
    head = _flank(z, opts.min_steps, opts.curvature_sigmas)
    tail = _flank(z[::-1], opts.min_steps, opts.curvature_sigmas)
    if not (head or tail) or np.count_nonzero(ok[head : r.steps.size - tail]) < opts.min_steps:
        return None

    def middle_of(head: int, tail: int) -> Measured:
        middle = subregion(r, r.steps[head : r.steps.size - tail], r.cut_before, r.cut_after)
        centre = measure_region(middle, gamma, distance, amplitude, geometry, opts, step=m.step)
        if m.bearing_source != "region centre":
            return centre
        h_i = centre.ranges + centre.positions @ unit_normal(m.bearing, centre.tilt)
        return replace(
            centre,
            bearing=m.bearing,
            bearing_stderr=m.bearing_stderr,
            bearing_source=m.bearing_source,
            findings=m.findings,
            depth=float(np.median(h_i)),
        )

    centre = middle_of(head, tail)
    # A flank stays split only where the middle's own double bounce with a surface across the fan explains it.
    first = last = None
    if head:
        first = measure_region(
            subregion(r, r.steps[:head], r.cut_before, True), gamma, distance, amplitude, geometry, opts, step=m.step
        )
        if stack_dihedral(first, [centre], opts) is None:
            first, head = None, 0
    if tail:
        last = measure_region(
            subregion(r, r.steps[r.steps.size - tail :], True, r.cut_after),
            gamma,
            distance,
            amplitude,
            geometry,
            opts,
            step=m.step,
        )
        if stack_dihedral(last, [centre], opts) is None:
            last, tail = None, 0
    if first is None and last is None:
        return None
    if first is None or last is None:
        centre = middle_of(head, tail)
    return [x for x in (first, centre, last) if x is not None]
