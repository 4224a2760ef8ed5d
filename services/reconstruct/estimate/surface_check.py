"""An L plane of record against the surface the same sweep extracts from the same echoes.

The L model (the paper's, §4) places each echo along its beam and fits the
two walls it assumes, each near the normal its correction takes (``y`` for a,
``z`` for b).  Where the sweep holds something else than that L (a third wall,
a wall far from the assumed normal), its fit can land on the right range with
the wrong normal: a wall's bearing from ranges alone is ill-posed, since it
answers only near the foot of its perpendicular (a region of constant depth).
The surface extractor measures the same region's bearing from the beam
pattern (the region's centre or its amplitude peak), independently of the L
premise.  When the two disagree by more than both σ allow and by more than the
verdict's own bound on a normal's σ, the plane's normal is not known within
that bound: it is not good.
"""

from __future__ import annotations

import math

import numpy as np

from lelsonar.reconstruct.estimate.fit import PlaneData
from lelsonar.reconstruct.estimate.quality import DEGRADED, GOOD, QualityLimits
from lelsonar.reconstruct.estimate.results import PlaneFit, PlaneResult
from lelsonar.reconstruct.estimate.surfaces import SurfaceSet

__all__ = ["surface_finding"]

#: The share of a plane's inlier steps a surface must hold to be that plane's own echoes.
OWN_SHARE = 0.5


def surface_finding(
    plane: PlaneResult, data: PlaneData | None, surfaces: SurfaceSet, limits: QualityLimits | None = None
) -> tuple[tuple[str, str], ...]:
    """The finding that degrades a good L ``plane`` its own echoes' surface contradicts (empty: none).

    Parameters
    ----------
    plane : PlaneFit or FitFailure
        An L plane of record (eq. 9 points, §4 fit) with its verdict.
    data : PlaneData or None
        Its points' steps (``data.step``, aligned with ``plane.inlier_mask``).
    surfaces : SurfaceSet
        The same sweep's surfaces.
    limits : QualityLimits
        ``max_normal_stderr``: the most a good plane's normal may be unknown by, rad.

    Returns
    -------
    ``((DEGRADED, reason),)`` when a surface good on its own echoes (``Surface.own_quality``) holding most
    of the plane's inlier steps has a normal
    more than ``3 √(σ_L² + σ_s²)`` and more than ``max_normal_stderr`` from the plane's; else ``()``.
    """
    if not isinstance(plane, PlaneFit) or plane.quality != GOOD or data is None or not surfaces.surfaces:
        return ()
    lim = limits or QualityLimits()
    steps = data.step[plane.inlier_mask] if plane.inlier_mask.shape == data.step.shape else data.step
    if steps.size == 0:
        return ()
    shares = [_share(steps, s.steps) for s in surfaces.surfaces]
    k = max(range(len(shares)), key=shares.__getitem__)  # (the first of the largest, as max() picks it)
    best = surfaces.surfaces[k]
    # What the surface's own echoes say of its plane: a lone region the sweep does not confirm a plane still
    # measures the bearing of the echoes the L plane holds.
    if best.own_quality != GOOD or shares[k] < OWN_SHARE:
        return ()
    angle = math.acos(min(1.0, abs(float(best.normal @ plane.normal))))
    sigma = math.hypot(plane.normal_stderr, math.sqrt(max(float(best.covariance[0, 0] + best.covariance[1, 1]), 0.0)))
    if angle <= 3.0 * sigma or angle <= lim.max_normal_stderr:
        return ()
    return (
        (
            DEGRADED,
            f"the surface {best.label} of the same echoes, its bearing from the beam pattern ({best.bearing_source}), "
            f"puts the normal {math.degrees(angle):.1f}° from this plane's (σ {math.degrees(sigma):.1f}°): a wall "
            "the L's two planes do not model",
        ),
    )


def _share(steps: np.ndarray, held: np.ndarray) -> float:
    """The share of ``steps`` (non-negative step indices) in ``held``: ``np.isin(steps, held).mean()``, the same
    number (a count over a size), through a table of the held steps."""
    size = int(steps.max()) + 1
    table = np.zeros(size, dtype=np.bool_)
    table[held[held < size]] = True
    return np.count_nonzero(table[steps]) / steps.size
