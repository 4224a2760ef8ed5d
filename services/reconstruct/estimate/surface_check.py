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

Two more readings of the plane's own echoes need no extractor.  Where the L
premise, not the echoes, set the plane's normal, its fit lands on an edge's
range with a wall's normal; the echoes still say what made them:

* along the capsule stack a plane's ranges are straight (``d = a + b x``), while
  an edge or a corner's line crossing the stack answers each capsule from its
  nearest point, ``√(ρ² + x²)``, curved by ``1/(2ρ)`` (:func:`stack_curvature_finding`);
* a mirror is heard about its foot as far on one side as on the other (its
  region of constant depth is centred there), so echoes that stop short of the
  foot on a side where nothing more is heard, yet reach farther on the other,
  come from a target off the plane's normal (:func:`foot_off_centre_finding`).
"""

from __future__ import annotations

import math

import numpy as np

from lelsonar.reconstruct.estimate.corner.pitch import amplitude_pitch, clipped_echoes
from lelsonar.reconstruct.estimate.fit import PlaneData
from lelsonar.reconstruct.estimate.quality import DEGRADED, GOOD, UNRELIABLE, QualityLimits
from lelsonar.reconstruct.estimate.results import PlaneFit, PlaneResult
from lelsonar.reconstruct.estimate.surfaces import SurfaceOptions, SurfaceSet
from lelsonar.reconstruct.estimate.surfaces.stack import stack_fits

__all__ = [
    "surface_finding",
    "diffraction_finding",
    "mirror_strength",
    "stack_curvature_finding",
    "foot_off_centre_finding",
    "echo_capsules",
]

#: The share of a plane's inlier steps a surface must hold to be that plane's own echoes.
OWN_SHARE = 0.5
#: Steps with three capsules or more the stack's curvature needs; a region's span in steps, twice that.
MIN_STEPS = 5
#: Steps past an end of a plane's echoes that must hear nothing for the end to be open.
OPEN_STEPS = 3


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
    :func:`diffraction_finding`'s finding; else those of :func:`stack_curvature_finding` and
    :func:`foot_off_centre_finding` (the plane's own echoes); else ``((DEGRADED, reason),)`` when a surface good on
    its own echoes (``Surface.own_quality``) holding most of the plane's inlier steps has a normal more than
    ``3 √(σ_L² + σ_s²)`` and more than ``max_normal_stderr`` from the plane's; else ``()``.
    """
    if not isinstance(plane, PlaneFit) or plane.quality != GOOD or data is None:
        return ()
    lim = limits or QualityLimits()
    steps = data.step[plane.inlier_mask] if plane.inlier_mask.shape == data.step.shape else data.step
    if steps.size == 0:
        return ()
    inlier = plane.inlier_mask if plane.inlier_mask.shape == data.step.shape else np.ones(data.n, dtype=bool)
    ranges = data.distance[inlier]
    if gamma is not None and distance is not None and amplitude is not None:
        found = diffraction_finding(steps, ranges, gamma, distance, amplitude, surfaces)
        if found:
            return found
    own = stack_curvature_finding(data.capsules[inlier, 0], steps, ranges)
    if distance is not None:
        own += foot_off_centre_finding(plane.normal, plane.normal_stderr, data.beam[inlier], steps, ranges, distance)
    if own:
        return own
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
    capsule = echo_capsules(steps, ranges, d)
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


def stack_curvature_finding(x: np.ndarray, steps: np.ndarray, ranges: np.ndarray) -> tuple[tuple[str, str], ...]:
    """The finding against a plane whose ranges curve along the capsule stack as an edge's or a corner's (empty:
    none).

    A plane's ranges are linear in the capsule's offset ``x`` along the stack, ``d = a_s + b x`` at each step
    (``b = −n_x``, its tilt); a line crossing the stack (an edge, a corner's line) answers each capsule from its
    nearest point, ``√(ρ² + x²)``, so its ranges curve by up to ``c = 1/(2ρ)`` (Kleeman & Kuc's plane/edge test
    across the receivers).  A curvature above the extractor's bar (``SurfaceOptions.curvature_sigmas`` σ, the σ
    from the ranges' own scatter about the per-step fits) denies the plane, whichever premise placed it.

    Parameters
    ----------
    x : (N,) array
        Each echo's capsule offset along the stack, m.
    steps : (N,) int array
        Each echo's step.
    ranges : (N,) array
        Each echo's range, m.

    Returns
    -------
    ``((UNRELIABLE, reason),)`` when the curvature ``c``
    (:func:`~lelsonar.reconstruct.estimate.surfaces.stack.stack_fits`) lies above ``curvature_sigmas`` σ,
    measured on at least :data:`MIN_STEPS` steps with three capsules or more; else ``()``.
    """
    x = np.asarray(x, dtype=np.float64)
    r = np.asarray(ranges, dtype=np.float64)
    if x.size == 0 or np.ptp(x) <= 0:
        return ()
    order = np.argsort(steps, kind="stable")
    rows = np.asarray(steps)[order]
    held = np.unique(rows, return_counts=True)[1]
    if np.count_nonzero(held >= 3) < MIN_STEPS:
        return ()  # a curvature needs three capsules at a step
    _, (quad, cov, _) = stack_fits(x[order], rows, r[order])
    c = float(quad[1])
    sc = math.sqrt(float(cov[1, 1])) if math.isfinite(c) and float(cov[1, 1]) > 0 else float("nan")
    bar = SurfaceOptions().curvature_sigmas
    if not (math.isfinite(c) and math.isfinite(sc)) or c <= bar * sc:
        return ()  # (a negative curvature is no one target's: two targets' lower envelope bends that way)
    line = 1.0 / (2.0 * float(np.median(r)))
    return (
        (
            UNRELIABLE,
            f"its ranges curve along the capsule stack (c = {c:.3f} ± {sc:.3f}/m, a line across it "
            f"{line:.3f}/m), where a plane's are straight: an edge's or a corner's echo, not a wall's",
        ),
    )


def foot_off_centre_finding(
    normal: np.ndarray,
    normal_stderr: float,
    beam: np.ndarray,
    steps: np.ndarray,
    ranges: np.ndarray,
    distance: np.ndarray,
) -> tuple[tuple[str, str], ...]:
    """The finding against a plane whose foot is not where its echoes' open end puts it (empty: none).

    A mirror answers while the beam is within its reach ``w`` of the plane's foot on either side (the region of
    constant depth, Leonard & Durrant-Whyte's RCD), so its echoes span ``[−w, w]`` about the foot in the scan
    plane, less what another echo hides (a cut end).  An end after which the next :data:`OPEN_STEPS` steps hear
    nothing at all is open: the beam's reach ends there.  Where the echoes reach farther on the other
    side of the plane's foot than at an open end, by more than the normal's 3 σ and the ends' placement
    (a step each, and a step for the detection's threshold), the foot lies off the centre of the echoes' region:
    their target is off this plane's normal (an edge, or a wall at another bearing), which only the fit's
    premise put there.

    Parameters
    ----------
    normal : (3,) array
        The plane's unit normal (``x`` along the rotation axis).
    normal_stderr : float
        Its σ, rad.
    beam : (N, 3) array
        Each echo's unit boresight.
    steps, ranges : (N,) arrays
        Each echo's step index into the scan, and range (m).
    distance : (n_steps, n_capsules) array
        The scan's ranges per step and capsule, m; NaN: none.

    Returns
    -------
    ``((UNRELIABLE, reason),)`` as above, else ``()``.
    """
    d = np.asarray(distance, dtype=np.float64)
    if d.ndim != 2 or steps.size == 0:
        return ()
    n = np.array(normal, dtype=np.float64)
    n[0] = 0.0
    b = np.array(beam, dtype=np.float64)
    b[:, 0] = 0.0
    nn, bn = float(np.linalg.norm(n)), np.linalg.norm(b, axis=1)
    if nn <= 0 or np.any(bn <= 0):
        return ()
    n, b = n / nn, b / bn[:, None]
    # Each echo's signed angle from the foot in the scan plane.
    angle = np.arctan2(np.cross(b, n)[:, 0], b @ n)
    # The region: the steps where the plane holds most of the step's echoes (where it holds a few, another target
    # at a like range answers, a corner's beside an L's wall), in a run about the one nearest the foot, gaps of up
    # to ``max_gap`` steps bridged (stray echoes past a gap are not the region's).
    own, count = np.unique(steps, return_counts=True)
    heard = np.count_nonzero(np.isfinite(d[own]), axis=1)
    held = own[2 * count > heard]
    if held.size == 0:
        return ()
    breaks = np.flatnonzero(np.diff(held) > SurfaceOptions().max_gap + 1)
    near = int(np.searchsorted(held, steps[np.argmin(np.abs(angle))]))
    run = np.searchsorted(breaks, min(near, held.size - 1))
    first = int(held[breaks[run - 1] + 1]) if run > 0 else int(held[0])
    last = int(held[breaks[run]]) if run < breaks.size else int(held[-1])
    if last - first < 2 * MIN_STEPS:
        return ()
    # How far each end reaches past the foot on its own side (negative: it stops short of the foot), the sides
    # told apart by the ends' own angles (the sweep may turn either way about the normal).
    at_first, at_last = float(np.median(angle[steps == first])), float(np.median(angle[steps == last]))
    side = 1.0 if at_first >= at_last else -1.0
    reach_first, reach_last = side * at_first, -side * at_last
    step = abs(at_first - at_last) / max(last - first, 1)

    def open_end(end: int, way: int) -> bool:
        beyond = end + way * np.arange(1, OPEN_STEPS + 1)
        if beyond.min() < 0 or beyond.max() >= d.shape[0]:
            return False  # the sweep's end: nothing says what lies past it
        # Silent: a later echo there, even a farther one, may have masked the plane's weakening echo.
        return not bool(np.any(np.isfinite(d[beyond])))

    margin = 3.0 * normal_stderr + 3.0 * step
    found = []
    for reach_open, reach_other, end, way in ((reach_first, reach_last, first, -1), (reach_last, reach_first, last, 1)):
        if reach_other > reach_open + margin and open_end(end, way):
            found.append((reach_open, reach_other))
    if not found:
        return ()
    reach_open, reach_other = found[0]
    return (
        (
            UNRELIABLE,
            f"its echoes end {math.degrees(abs(reach_open)):.0f}° {'past' if reach_open >= 0 else 'short of'} its "
            "foot, with nothing heard past them, yet reach "
            f"{math.degrees(reach_other):.0f}° past it on the other side (σ of the normal "
            f"{math.degrees(normal_stderr):.1f}°): a mirror's are centred on its foot, so their target lies off "
            "this plane's normal (an edge, another wall), which only the fit's premise put there",
        ),
    )


def echo_capsules(steps: np.ndarray, ranges: np.ndarray, distance: np.ndarray) -> np.ndarray:
    """Each of a plane's echoes' capsule in the scan: the one whose range at its step is the echo's (a plane's
    ranges are the scan's)."""
    rows = distance[steps]
    return np.argmin(np.abs(np.where(np.isfinite(rows), rows, np.inf) - ranges[:, None]), axis=1)


def _share(steps: np.ndarray, held: np.ndarray) -> float:
    """The share of ``steps`` (non-negative step indices) in ``held``: ``np.isin(steps, held).mean()``, the same
    number (a count over a size), through a table of the held steps."""
    size = int(steps.max()) + 1
    table = np.zeros(size, dtype=np.bool_)
    table[held[held < size]] = True
    return np.count_nonzero(table[steps]) / steps.size
