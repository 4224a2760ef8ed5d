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

The L model also takes every band of steady echoes it labels a wall for a
wall.  A convex edge (a box's or a thin wall's end) diffracts a point
source's echo: over its region of constant depth it changes with γ exactly as
a wall's echo does (a range ``ρ − r cos(γ − β)`` either way, ``r`` the
capsules' radial offset), so the ranges cannot tell it from a wall.  Its
strength can: a diffraction is weak against a mirror at its range.  Where the
plane's own echoes, at their strongest, are that weak against the sweep's
strongest echo and the sweep's surfaces hold them as an edge, not as a plane,
two independent readings of the same echoes (their amplitude, the extractor's
regions) say the L model took an edge for a wall.  Neither alone does: a wall
of low reflectivity is weak too, and the extractor can read a foreign rig's
wall as an edge or as nothing.
"""

from __future__ import annotations

import math

import numpy as np

from lelsonar.reconstruct.estimate.corner.pitch import amplitude_pitch, clipped_echoes
from lelsonar.reconstruct.estimate.fit import PlaneData
from lelsonar.reconstruct.estimate.quality import DEGRADED, GOOD, UNRELIABLE, QualityLimits
from lelsonar.reconstruct.estimate.results import PlaneFit, PlaneResult
from lelsonar.reconstruct.estimate.surfaces import SurfaceOptions, SurfaceSet

__all__ = ["surface_finding", "diffraction_finding", "mirror_strength"]

#: The share of a plane's inlier steps a surface must hold to be that plane's own echoes.
OWN_SHARE = 0.5


def surface_finding(
    plane: PlaneResult,
    data: PlaneData | None,
    surfaces: SurfaceSet,
    limits: QualityLimits | None = None,
    *,
    gamma: np.ndarray | None = None,
    distance: np.ndarray | None = None,
    amplitude: np.ndarray | None = None,
) -> tuple[tuple[str, str], ...]:
    """The finding against a good L ``plane`` that the sweep's own evidence contradicts (empty: none):
    :func:`diffraction_finding` where the scan's ``gamma``, ``distance`` and echo ``amplitude`` are given,
    else (or where it finds nothing) the surface of its own echoes against its normal.

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
    gamma, distance, amplitude : arrays, optional
        The scan's γ per step (rad), range and peak echo amplitude per step and capsule (m, V; NaN: none).

    Returns
    -------
    :func:`diffraction_finding`'s finding; else ``((DEGRADED, reason),)`` when a surface good on its own echoes
    (``Surface.own_quality``) holding most of the plane's inlier steps has a normal more than
    ``3 √(σ_L² + σ_s²)`` and more than ``max_normal_stderr`` from the plane's; else ``()``.
    """
    if not isinstance(plane, PlaneFit) or plane.quality != GOOD or data is None:
        return ()
    lim = limits or QualityLimits()
    steps = data.step[plane.inlier_mask] if plane.inlier_mask.shape == data.step.shape else data.step
    if steps.size == 0:
        return ()
    if gamma is not None and distance is not None and amplitude is not None:
        inlier = plane.inlier_mask if plane.inlier_mask.shape == data.step.shape else np.ones(data.n, dtype=bool)
        found = diffraction_finding(steps, data.distance[inlier], gamma, distance, amplitude, surfaces)
        if found:
            return found
    if not surfaces.surfaces:
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


def mirror_strength(amplitude: np.ndarray, distance: np.ndarray, absorption_db_per_m: float) -> np.ndarray:
    """Echo amplitudes over a mirror's spreading and absorption at their ranges: ``A · 2d · 10^(α·2d/20)``.

    A mirror echo's amplitude is ``∝ D(ψ)² / (2d)`` less the air's absorption over the round trip ``2d``
    (the paper's §3 sonar equation): the product is the same for every mirror at every range, so echoes at
    different ranges compare by it.
    """
    a = np.asarray(amplitude, dtype=np.float64)
    d = np.asarray(distance, dtype=np.float64)
    return a * 2.0 * d * 10.0 ** (absorption_db_per_m * 2.0 * d / 20.0)


def diffraction_finding(
    steps: np.ndarray,
    ranges: np.ndarray,
    gamma: np.ndarray,
    distance: np.ndarray,
    amplitude: np.ndarray,
    surfaces: SurfaceSet,
    opts: SurfaceOptions | None = None,
) -> tuple[tuple[str, str], ...]:
    """The finding against an L plane whose echoes are a convex edge's diffraction, not a wall's (empty: none).

    Two readings of the plane's echoes must agree: their strength, and the sweep's surfaces.

    * At their strongest (the amplitude peak inside them, :func:`amplitude_pitch`, and none of them clipped,
      :func:`clipped_echoes`: else the strongest is a lower bound of their echo's), range-corrected
      (:func:`mirror_strength`), they are under ``opts.weak_echo`` of the sweep's strongest echo.  That one is a
      mirror's or a corner's double bounce (up to ~1.5× a mirror's); a diffraction is ~0.2× a mirror's.
    * No plane of the sweep holds most (:data:`OWN_SHARE`) of their steps, and an edge of the sweep does.

    Parameters
    ----------
    steps, ranges : (N,) arrays
        The plane's inlier echoes: step index into the scan, range (m).
    gamma : (n_steps,) array
        The scan's γ per step, rad.
    distance, amplitude : (n_steps, n_capsules) arrays
        The scan's range (m) and peak echo amplitude (V) per step and capsule; NaN: none.
    surfaces : SurfaceSet
        The same sweep's surfaces.
    opts : SurfaceOptions
        ``weak_echo`` and ``absorption_db_per_m`` (the extractor's own).

    Returns
    -------
    ``((UNRELIABLE, reason),)`` when both say edge, else ``()``.
    """
    o = opts or SurfaceOptions()
    d = np.asarray(distance, dtype=np.float64)
    a = np.asarray(amplitude, dtype=np.float64)
    if d.shape != a.shape or d.ndim != 2 or steps.size == 0:
        return ()
    if max((_share(steps, s.steps) for s in surfaces.surfaces), default=0.0) >= OWN_SHARE:
        return ()
    edges = [(_share(steps, f.steps), f) for f in surfaces.edges]
    held, edge = max(edges, key=lambda e: e[0], default=(0.0, None))
    if edge is None or held < OWN_SHARE:
        return ()
    # Each of the plane's echoes in the scan: the capsule whose range it is (the plane's ranges are the scan's).
    rows = d[steps]
    capsule = np.argmin(np.abs(np.where(np.isfinite(rows), rows, np.inf) - ranges[:, None]), axis=1)
    own = a[steps, capsule]
    # A clipped echo's amplitude is only a lower bound of its strength: nothing says such echoes are weak.
    clipped = clipped_echoes(a.ravel()).reshape(a.shape)
    if np.any(clipped[steps, capsule]):
        return ()
    if amplitude_pitch(np.asarray(gamma, dtype=np.float64)[steps], own, ranges) is None:
        return ()
    strength = mirror_strength(own, ranges, o.absorption_db_per_m)
    every = mirror_strength(a, d, o.absorption_db_per_m)
    ok = np.isfinite(every) & (every > 0)
    if np.count_nonzero(ok) < 2 or not np.any(np.isfinite(strength)):
        return ()
    ratio = float(np.nanmax(strength)) / float(np.max(every[ok]))
    if ratio >= o.weak_echo:
        return ()
    return (
        (
            UNRELIABLE,
            f"its echoes at their strongest are {ratio:.2f} of the sweep's strongest at their range, as weak as "
            f"a convex edge's diffraction, and {100 * held:.0f} % of them are the sweep's edge {edge.label}, no "
            "plane's: the L model has taken the edge for a wall; read this scan's walls from its surfaces",
        ),
    )


def _share(steps: np.ndarray, held: np.ndarray) -> float:
    """The share of ``steps`` (non-negative step indices) in ``held``: ``np.isin(steps, held).mean()``, the same
    number (a count over a size), through a table of the held steps."""
    size = int(steps.max()) + 1
    table = np.zeros(size, dtype=np.bool_)
    table[held[held < size]] = True
    return np.count_nonzero(table[steps]) / steps.size
