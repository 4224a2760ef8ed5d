"""Every surface of one sweep: planes, concave corners and convex edges, each with its evidence.

Per region of constant depth (:mod:`.regions`):

* **bearing** from the beam pattern: the peak of the echo amplitudes across γ
  (:func:`~.regions.bearing_from_amplitude`), else the region's centre when it
  is not cut; a cut region without an amplitude peak leaves the bearing
  undetermined, and says so.  A range-only fit of a wall seen near the foot of
  its perpendicular is ill-posed in bearing (the capsules differ across the
  beam only by the radial offset), so the bearing never comes from it.
* **depth** ``ρ`` from the ranges with the bearing fixed (the mirror condition
  ``n · p_c + d = h``), **tilt** from the differential ranges along the capsule
  stack.
* **class** by physics:

  - ranges curved along the stack as ``1/(2ρ)``: a line or point *across* the
    stack (the image of the array is not a straight array), so not a plane;
  - a region whose point lies on the trace of two other planes, at the range
    their intersection predicts for the double bounce: a **concave corner**;
  - on one other plane's trace (off that plane's own foot): that plane's end,
    a **corner** if its echo is as strong as a mirror's, an **edge** if weak;
  - an echo much weaker than a mirror's at its range (diffraction): an **edge**;
  - anything else: a **plane**.

The planes' verdicts go through :func:`~lelsonar.reconstruct.estimate.quality.assess_plane`
with the extractor's own findings (bearing undetermined or disputed, region cut).
Their covariance is over (bearing, tilt, offset): a wall well placed in range can
be poorly placed in bearing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from lelsonar.errors import ConfigError
from lelsonar.geometry import ArrayGeometry
from lelsonar.reconstruct.estimate.fit import make_plane_fit, plane_data_of
from lelsonar.reconstruct.estimate.quality import DEGRADED, GOOD, UNRELIABLE, assess_plane
from lelsonar.reconstruct.estimate.results import PlaneFit, SolverDiagnostics
from lelsonar.reconstruct.estimate.surfaces.regions import (
    PLATEAU,
    Region,
    bearing_from_amplitude,
    capsule_x,
    find_regions,
    stack_fit,
)
from lelsonar.reconstruct.estimate.surfaces.results import Feature, Surface, SurfaceOptions, SurfaceSet

__all__ = ["SurfaceOptions", "Surface", "Feature", "SurfaceSet", "extract_surfaces", "METHOD"]

#: The method name the surfaces' plane fits carry.
METHOD = "rcd"


@dataclass(frozen=True, eq=False)
class _Measured:
    """A region with what its echoes say, before its class is decided."""

    region: Region
    bearing: float
    bearing_stderr: float
    bearing_source: str
    findings: tuple[tuple[str, str], ...]
    depth: float
    tilt: float
    tilt_stderr: float
    curvature: float
    curvature_stderr: float
    stack_slope: float
    strength: float  # peak amplitude over a mirror's at this depth (NaN: unknown)
    peak: float
    peak_inside: bool  # the region holds its amplitude peak
    exact: bool  # its peak is inside and not clipped (else its strength is only a lower bound)
    span: tuple[float, float]  # γ of the region's first and last steps, rad
    step: float  # the sweep's step, rad


def _direction(bearing: float, tilt: float = 0.0) -> np.ndarray:
    c = math.cos(tilt)
    return np.array([math.sin(tilt), c * math.cos(bearing), c * math.sin(bearing)])


def _measure(
    region: Region,
    gamma: np.ndarray,
    distance: np.ndarray,
    amplitude: np.ndarray | None,
    geometry: ArrayGeometry,
    opts: SurfaceOptions,
) -> _Measured:
    g = gamma[region.steps]
    step = float(np.median(np.abs(np.diff(gamma)))) if gamma.size > 1 else math.radians(1.0)
    quant = step / math.sqrt(24.0)  # each end of the region uniform within a step
    findings: list[tuple[str, str]] = []
    cut = region.cut_before or region.cut_after
    mid = 0.5 * (float(g[0]) + float(g[-1]))
    peak_fit = None
    peak = float("nan")
    clipped: bool | None = None
    if amplitude is not None:
        a = amplitude[region.rows, region.capsules]
        per_step = np.full(region.steps.size, np.nan)
        pos = np.searchsorted(region.steps, region.rows)
        for k in range(region.steps.size):
            v = a[pos == k]
            v = v[np.isfinite(v)]
            if v.size:
                per_step[k] = float(np.median(v))
        peak = float(np.nanmax(per_step)) if np.isfinite(per_step).any() else float("nan")
        clipped = bool(np.count_nonzero(per_step >= (1.0 - PLATEAU) * peak) >= 3) if math.isfinite(peak) else None
        peak_fit = bearing_from_amplitude(g, per_step)
    if not cut:
        # The region's ends are where the beam pattern falls under the threshold on either side: symmetric
        # about the target, so the centre is its bearing (the amplitudes can be bent by a later echo ringing
        # into the same window).
        bearing, sb, source = mid, quant, "region centre"
    elif peak_fit is not None:
        bearing, sb, source = peak_fit[0], math.hypot(peak_fit[1], quant), "amplitude peak"
        # The peak of a cut region rests on the amplitudes alone, which other echoes ringing into the same
        # window bend (and a receiver's clipping flattens): usable, not good.
        findings.append(
            (
                DEGRADED,
                "bearing from the amplitude peak alone: the region of constant depth is cut "
                "(a nearer echo or the sweep's end), so its centre is not the wall's",
            )
        )
    else:
        bearing, source = mid, "undetermined"
        sb = 0.5 * (float(g[-1]) - float(g[0])) + step
        side = "both sides" if region.cut_before and region.cut_after else "one side"
        findings.append(
            (
                UNRELIABLE,
                f"bearing not determined: the region of constant depth is cut on {side} "
                "(a nearer echo or the sweep's end) and no amplitude peak is in it",
            )
        )
    caps = geometry.capsule_positions(gamma[region.rows])[np.arange(region.rows.size), region.capsules]
    d = distance[region.rows, region.capsules]
    x = capsule_x(geometry)[region.capsules]
    lin, lin_cov, _ = stack_fit(x, region.rows, d, curved=False)
    quad, quad_cov, _ = stack_fit(x, region.rows, d, curved=True)
    slope = float(lin[0])
    tilt = math.asin(max(-1.0, min(1.0, -slope))) if math.isfinite(slope) else 0.0
    tilt_se = math.sqrt(float(lin_cov[0, 0])) if math.isfinite(slope) else float("nan")
    n = _direction(bearing, tilt)
    depth = float(np.median(d + caps @ n))
    strength = float("nan")
    if math.isfinite(peak):
        strength = peak * 2 * depth * 10 ** (opts.absorption_db_per_m * 2 * depth / 20)  # mirror-normalised
    return _Measured(
        region=region,
        bearing=bearing,
        bearing_stderr=sb,
        bearing_source=source,
        findings=tuple(findings),
        depth=depth,
        tilt=tilt,
        tilt_stderr=tilt_se,
        curvature=float(quad[1]),
        curvature_stderr=math.sqrt(float(quad_cov[1, 1])) if math.isfinite(quad[1]) else float("nan"),
        stack_slope=slope,
        strength=strength,
        peak=peak,
        peak_inside=not cut or peak_fit is not None,
        exact=(not cut or peak_fit is not None) and clipped is False,
        span=(float(g[0]), float(g[-1])),
        step=step,
    )


def _across_stack(m: _Measured, opts: SurfaceOptions) -> bool:
    """Ranges curved along the stack as a line or point across it (``c ≈ 1/(2ρ)``), not as a plane (``c = 0``)."""
    c, sc = m.curvature, m.curvature_stderr
    if not (math.isfinite(c) and math.isfinite(sc) and sc > 0):
        return False
    expected = 1.0 / (2.0 * m.depth)
    return c > opts.curvature_sigmas * sc and abs(c - expected) < max(0.5 * expected, 3 * sc)


def _point(m: _Measured) -> np.ndarray:
    return m.depth * _direction(m.bearing)


def _fit_surface(
    label: str, m: _Measured, gamma: np.ndarray, distance: np.ndarray, geometry: ArrayGeometry, opts: SurfaceOptions
) -> Surface | None:
    r = m.region
    caps = geometry.capsule_positions(gamma[r.rows])[np.arange(r.rows.size), r.capsules]
    d = distance[r.rows, r.capsules]
    beam = np.stack([np.zeros(r.rows.size), np.cos(gamma[r.rows]), np.sin(gamma[r.rows])], axis=1)
    n = _direction(m.bearing, m.tilt)
    h_i = d + caps @ n
    h = float(np.median(h_i))
    resid = h_i - h
    sigma = float(np.std(resid, ddof=1)) if resid.size > 1 else float("nan")
    # How h moves with the bearing and the tilt (the capsules' own offsets along n), for the covariance.
    dn_db = np.array([0.0, -math.cos(m.tilt) * math.sin(m.bearing), math.cos(m.tilt) * math.cos(m.bearing)])
    dn_dt = np.array(
        [math.cos(m.tilt), -math.sin(m.tilt) * math.cos(m.bearing), -math.sin(m.tilt) * math.sin(m.bearing)]
    )
    jac = np.array([float(np.mean(caps @ dn_db)), float(np.mean(caps @ dn_dt))])
    tilt_var = m.tilt_stderr**2 if math.isfinite(m.tilt_stderr) else (math.pi / 2) ** 2
    ang = np.diag([m.bearing_stderr**2, tilt_var])
    var_h = (sigma**2 / max(r.rows.size, 1) if math.isfinite(sigma) else 0.0) + float(jac @ ang @ jac)
    cov = np.zeros((3, 3))
    cov[:2, :2] = ang
    cov[2, :2] = cov[:2, 2] = ang @ jac
    cov[2, 2] = var_h
    findings = list(m.findings)
    if not math.isfinite(m.tilt_stderr):
        findings.append((DEGRADED, "tilt not determined: one capsule per step"))
    data = plane_data_of(caps[:, None, :], beam, d[:, None], r.rows, "a", n)
    fit = make_plane_fit(
        data,
        n / h,
        method=METHOD,
        inlier_mask=np.ones(data.n, dtype=bool),
        diagnostics=SolverDiagnostics(solver=METHOD, notes=(f"bearing: {m.bearing_source}",)),
        model="constant-depth",
        stderr=(math.sqrt(m.bearing_stderr**2 + tilt_var), math.sqrt(var_h)),
    )
    if not isinstance(fit, PlaneFit):
        return None
    fit = assess_plane(fit, gamma, findings=tuple(findings), limits=opts.limits)
    return Surface(
        label=label,
        plane=fit,
        bearing=m.bearing,
        tilt=m.tilt,
        covariance=cov,
        bearing_source=m.bearing_source,
        steps=r.steps.copy(),
        n_echoes=r.n_echoes,
    )


def _feature(
    kind: str, label: str, m: _Measured, direction: np.ndarray, surfaces: tuple[str, ...], reasons: list[str]
) -> Feature:
    b = _direction(m.bearing)
    across = np.cross(direction, b)
    nrm = float(np.linalg.norm(across))
    across = across / nrm if nrm > 1e-9 else np.zeros(3)
    # Along the beam: the depth's scatter; across it: the bearing's, at this depth.
    sd = 0.003 + 0.5 * (m.depth * 0.0)  # range noise floor
    cov = sd**2 * np.outer(b, b) + (m.depth * m.bearing_stderr) ** 2 * np.outer(across, across)
    return Feature(
        kind=kind,
        label=label,
        point=_point(m),
        direction=direction,
        covariance=cov,
        bearing=m.bearing,
        depth=m.depth,
        surfaces=surfaces,
        reasons=tuple(reasons),
        steps=m.region.steps.copy(),
        n_echoes=m.region.n_echoes,
    )


def extract_surfaces(
    gamma: np.ndarray,
    distance: np.ndarray,
    geometry: ArrayGeometry,
    *,
    amplitude: np.ndarray | None = None,
    options: SurfaceOptions | None = None,
) -> SurfaceSet:
    """Every plane, concave corner and convex edge of one sweep, in the array frame.

    Parameters
    ----------
    gamma : (n_steps,) array
        Measured rotation of each step, rad, in sweep order.
    distance : (n_steps, n_capsules) array
        Ranges, m (NaN: no echo).
    geometry : ArrayGeometry
    amplitude : (n_steps, n_capsules) array, optional
        Each echo's peak amplitude, V (:func:`lelsonar.signal.energy.echo_amplitude`); without it the
        bearing comes from the regions' centres and the weak-echo test is not made.
    options : SurfaceOptions, optional

    Returns
    -------
    SurfaceSet
    """
    opts = options or SurfaceOptions()
    g = np.asarray(gamma, dtype=np.float64)
    d = np.asarray(distance, dtype=np.float64)
    if d.shape != (g.size, geometry.n_capsules):
        raise ConfigError(f"distance must have shape ({g.size}, {geometry.n_capsules}), got {d.shape}")
    amp = None if amplitude is None else np.asarray(amplitude, dtype=np.float64)
    if amp is not None and amp.shape != d.shape:
        raise ConfigError(f"amplitude must have the shape of distance {d.shape}, got {amp.shape}")
    regions = find_regions(d, tolerance=opts.range_tolerance, max_gap=opts.max_gap, min_steps=opts.min_steps)
    measured = [_measure(r, g, d, amp, geometry, opts) for r in regions]

    # The mirror amplitude at unit range: the median over the regions (most are mirrors, and an edge's is
    # weaker by an order of magnitude, so it does not pull the median).
    # The strongest echo of the sweep, range-corrected, is a mirror's or a corner's (a clipped or cut one's is
    # a lower bound of its own, so the largest is still no edge's unless the sweep saw only edges); an echo
    # far below it diffracts.  A median would not do: in a cluttered sweep most regions may be edges.
    strengths = [m.strength for m in measured if math.isfinite(m.strength)]
    mirror = max(strengths) if len(strengths) >= 2 else float("nan")

    def weak(m: _Measured) -> bool:
        return (
            m.peak_inside
            and math.isfinite(mirror)
            and math.isfinite(m.strength)
            and m.strength < opts.weak_echo * mirror
        )

    def strong(m: _Measured) -> bool:
        return math.isfinite(mirror) and math.isfinite(m.strength) and m.strength >= opts.weak_echo * mirror

    across = [_across_stack(m, opts) for m in measured]
    candidates = [i for i, m in enumerate(measured) if not across[i]]
    # Only planes whose bearing is determined, and whose echo is not a diffraction's, hold traces.
    determined = [i for i in candidates if measured[i].bearing_source != "undetermined" and not weak(measured[i])]

    def on_traces(i: int, pool: list[int]) -> list[int]:
        p = _point(measured[i])
        out = []
        for j in pool:
            if j == i:
                continue
            mj = measured[j]
            if abs(_wrap(measured[i].bearing - mj.bearing)) < opts.foot_separation:
                continue
            nj = _direction(mj.bearing)
            tol = opts.on_trace + 3 * mj.depth * abs(math.sin(measured[i].bearing - mj.bearing)) * mj.bearing_stderr
            if abs(float(nj @ p) - mj.depth) <= tol:
                out.append(j)
        return out

    # A region on another's trace is that one's end or corner; once those are set aside, the ties are
    # counted again against the planes alone (a corner's own trace is no wall).
    ends = {i for i in determined if on_traces(i, determined)}
    planes = [i for i in determined if i not in ends]
    kinds: dict[int, tuple[str, list[str], list[int]]] = {}
    for i, m in enumerate(measured):
        if across[i]:
            text = (
                f"ranges curve along the capsule stack (c = {m.curvature:.2f}/m ≈ 1/(2ρ) = "
                f"{1 / (2 * m.depth):.2f}/m): a line across the stack, not a plane"
            )
            kinds[i] = ("edge" if weak(m) else "corner", [text], [])
            continue
        if m.bearing_source == "undetermined":
            placed = _place_between(m, [measured[j] for j in planes], opts)
            if placed is None:
                continue
            which, bearing = placed
            ties = [planes[j] for j in which]
            measured[i] = m = replace(m, bearing=bearing, bearing_stderr=_pair_stderr(m, which, planes, measured))
        else:
            ties = on_traces(i, planes)
        if len(ties) >= 2:
            kinds[i] = (
                "corner",
                ["at the double-bounce range of the two planes it joins (their intersection)"],
                ties[:2],
            )
        elif len(ties) == 1:
            if weak(m):
                kinds[i] = ("edge", ["on a plane's trace off its foot, with a weak (diffracted) echo"], ties)
            elif strong(m):
                kinds[i] = ("corner", ["on a plane's trace off its foot, with a mirror-strong echo"], ties)
            else:
                kinds[i] = ("edge", ["on a plane's trace off its foot (its end); echo strength unknown"], ties)
        elif weak(m):
            kinds[i] = (
                "edge",
                [f"echo {100 * m.strength / mirror:.0f} % of the sweep's strongest at its range: diffraction"],
                [],
            )

    surfaces: list[Surface] = []
    label_of: dict[int, str] = {}
    failed = 0
    for i, m in enumerate(measured):
        if i in kinds:
            continue
        s = _fit_surface(f"s{len(surfaces) + 1}", m, g, d, geometry, opts)
        if s is None:
            failed += m.region.n_echoes
            continue
        label_of[i] = s.label
        surfaces.append(s)
    corners: list[Feature] = []
    edges: list[Feature] = []
    for i, (kind, reasons, ties) in sorted(kinds.items()):
        m = measured[i]
        tied = tuple(label_of[j] for j in ties if j in label_of)
        if across[i]:
            direction = np.cross(np.array([1.0, 0.0, 0.0]), _direction(m.bearing))
        elif len(ties) >= 2:
            direction = np.cross(_direction(measured[ties[0]].bearing), _direction(measured[ties[1]].bearing))
        else:
            direction = np.array([1.0, 0.0, 0.0])  # along the stack: a line the fan crosses
        direction = direction / max(float(np.linalg.norm(direction)), 1e-12)
        if direction[int(np.argmax(np.abs(direction)))] < 0:
            direction = -direction
        out = corners if kind == "corner" else edges
        out.append(_feature(kind, f"{kind[0]}{len(out) + 1}", m, direction, tied, reasons))

    valid = np.isfinite(d)
    in_region = np.zeros_like(valid)
    in_run = np.zeros(g.size, dtype=bool)
    for r in regions:
        in_region[r.rows, r.capsules] = True
        in_run[r.steps] = True
    n_valid = int(np.count_nonzero(valid))
    off_step = int(np.count_nonzero(valid & ~in_region & in_run[:, None]))
    short = int(np.count_nonzero(valid & ~in_run[:, None]))
    unexplained = {
        "in runs shorter than a region of constant depth": short,
        "off their step's range (another target in the same beam)": off_step,
    }
    if failed:
        unexplained["in regions no plane fits"] = failed
    return SurfaceSet(
        surfaces=tuple(surfaces),
        corners=tuple(corners),
        edges=tuple(edges),
        n_echoes=n_valid,
        unexplained=unexplained,
    )


def _in_span(bearing: float, m: _Measured, margin: float, beyond_cut: float) -> bool:
    """``bearing`` within the region's span of γ; on a cut side the target may lie up to ``beyond_cut`` past it."""
    g0, g1 = m.span
    lo = g0 - margin - (beyond_cut if m.region.cut_before else 0.0)
    hi = g1 + margin + (beyond_cut if m.region.cut_after else 0.0)
    return lo <= bearing <= hi


def _place_between(m: _Measured, planes: list[_Measured], opts: SurfaceOptions) -> tuple[list[int], float] | None:
    """Where a region whose own bearing is not determined sits, if the planes say.

    A concave corner's echo comes from the intersection of its two walls: at the double-bounce range
    ``|X|`` and the bearing of ``X``.  A wall's end lies on its trace at the region's depth: at
    ``β_j ± acos(h_j/ρ)``.  Either must fall within the region's span of γ.

    Returns
    -------
    (indices into ``planes``, bearing) or None.
    """
    margin = m.step
    best: tuple[float, list[int], float] | None = None
    for a in range(len(planes)):
        for b in range(a + 1, len(planes)):
            na, nb = _direction(planes[a].bearing)[1:], _direction(planes[b].bearing)[1:]
            mat = np.stack([na, nb])
            if abs(float(np.linalg.det(mat))) < 0.2:  # nearly parallel: no corner
                continue
            x = np.linalg.solve(mat, np.array([planes[a].depth, planes[b].depth]))
            rho = float(np.hypot(*x))
            bearing = math.atan2(float(x[1]), float(x[0]))
            miss = abs(rho - m.depth)
            if (
                miss <= opts.on_trace
                and _in_span(bearing, m, margin, opts.beyond_cut)
                and (best is None or miss < best[0])
            ):
                best = (miss, [a, b], bearing)
    if best is not None:
        return best[1], best[2]
    for j, pj in enumerate(planes):
        if pj.depth >= m.depth:
            continue
        half = math.acos(pj.depth / m.depth)
        for bearing in (pj.bearing - half, pj.bearing + half):
            if half > opts.foot_separation and _in_span(_wrap(bearing), m, margin, opts.beyond_cut):
                return [j], _wrap(bearing)
    return None


def _pair_stderr(m: _Measured, which: list[int], planes: list[int], measured: list[_Measured]) -> float:
    """A placed region's bearing σ: the planes' bearing σ, at least one step's quantisation."""
    return max(math.sqrt(sum(measured[planes[j]].bearing_stderr ** 2 for j in which)), m.step / math.sqrt(24.0))


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def good_surfaces(result: SurfaceSet) -> tuple[Surface, ...]:
    """The surfaces whose verdict is good."""
    return tuple(s for s in result.surfaces if s.quality == GOOD)
