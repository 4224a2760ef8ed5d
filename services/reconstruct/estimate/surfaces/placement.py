"""Where a concave corner or a convex edge lies, and the covariance of that point.

* :func:`echo_point`: a region's echo point from its own readings.  The range's gradient along the
  capsule stack is the x component of the unit vector from the echo's point to the array, whatever the
  target (a plane's foot, a line's nearest point, a double bounce's edge), so the stack slope's tilt puts
  the point off the fan; the covariance has the depth's σ along the ray (with the arc's sagitta where the
  direction is unsure), the bearing's across it in the fan and the tilt's across the fan.
* :func:`pair_line_point`: two planes' intersection, its point nearest the array, with the planes' full
  covariance (bearing, tilt and offset of each) carried through the intersection's Jacobian.
* :func:`with_range`: that point conditioned on the corner's own double-bounce range ``|X|`` (one
  linear-Gaussian update), where the planes' fit did not use it already.
* :func:`line_yaw_stderr`: how far a plane's line with a surface across the fan may lie from the plane's foot
  in bearing, the line's turn in the plane being fixed only through its cosine by the echo's range and tilt.
* :func:`opening_spread`: how far along a plane's trace a concave corner with an unseen wall may lie past
  where its double bounce's range puts it, the opening unknown.
"""

from __future__ import annotations

import math

import numpy as np

from lelsonar.reconstruct.estimate.normals import cross3
from lelsonar.reconstruct.estimate.surfaces.measurement import unit_normal

__all__ = [
    "echo_point",
    "arc_moments",
    "pair_line_point",
    "with_range",
    "line_direction",
    "line_yaw_stderr",
    "opening_spread",
    "RANGE_FLOOR",
]

#: m: a feature's depth σ is at least the range noise's (1–3 mm of one reading, its bias with temperature).
RANGE_FLOOR = 0.003


def echo_point(
    depth: float, depth_stderr: float, bearing: float, bearing_stderr: float, tilt: float, tilt_stderr: float
) -> tuple[np.ndarray, np.ndarray]:
    """A region's echo point ``ρ·u(β, t)`` and its covariance, m².

    Parameters
    ----------
    depth, depth_stderr : float
        ``ρ`` and its σ, m (σ NaN or under :data:`RANGE_FLOOR`: that floor).
    bearing, bearing_stderr : float
        ``β`` in the fan and its σ, rad.
    tilt, tilt_stderr : float
        ``t`` off the fan (along the stack) and its σ, rad.

    Returns
    -------
    point : (3,) array
    covariance : (3, 3) array
        The second moment about the point of ``(ρ + ε) u(β + δ_β, t + δ_t)`` with Gaussian ``ε, δ_β, δ_t``:
        ``σ_ρ² u uᵀ + (ρ c σ_β)² e_β e_βᵀ + (ρ σ_t)² e_t e_tᵀ`` to first order, each ``σ²`` there
        ``E sin²δ`` (``e_β``, ``e_t`` the unit
        derivatives of ``u``; the three are orthonormal), with ``c² = E cos²(t + δ_t)`` (a bearing moves a
        target far off the fan little, unless its tilt is unsure), and the arcs' sagittas: the target lies on
        the sphere ``|X| = ρ``, so a bearing off by ``δ_β`` puts it ``ρ c (1 − cos δ_β)`` nearer the stack
        axis (along ``r``, the radial in the fan) and a tilt off by ``δ_t`` ``ρ (1 − cos δ_t)`` nearer the
        array (along ``u``), each of zero first-order mean, with moments :func:`arc_moments`.  Where the
        direction is sure these vanish; where it is unsure by a region's reach they place the target on its arc,
        not on the tangent plane.
    """
    u = unit_normal(bearing, tilt)
    ct, st = math.cos(tilt), math.sin(tilt)
    cb, sb = math.cos(bearing), math.sin(bearing)
    e_b = np.array([0.0, -sb, cb])
    e_t = np.array([ct, -st * cb, -st * sb])
    radial = np.array([0.0, cb, sb])
    sd = max(RANGE_FLOOR, depth_stderr) if math.isfinite(depth_stderr) else RANGE_FLOOR
    st_se = tilt_stderr if math.isfinite(tilt_stderr) else 0.0
    sb_se = bearing_stderr if math.isfinite(bearing_stderr) else 0.0
    # E cos²(t + δ) for Gaussian δ: (1 + cos 2t · e^(−2σ²)) / 2.
    c = math.sqrt(max(0.0, 0.5 * (1.0 + math.cos(2.0 * tilt) * math.exp(-2.0 * st_se * st_se))))
    mean_b, second_b = arc_moments(sb_se)
    mean_t, second_t = arc_moments(st_se)
    sag = (
        (depth * c) ** 2 * second_b * np.outer(radial, radial)
        + depth**2 * second_t * np.outer(u, u)
        + depth**2 * c * mean_b * mean_t * (np.outer(radial, u) + np.outer(u, radial))
    )
    # Across the ray the target moves by ρ sin δ: E sin²δ = (1 − e^(−2σ²)) / 2, σ² while σ is small.
    cov = (
        sd**2 * np.outer(u, u)
        + (depth * c) ** 2 * _mean_sin2(sb_se) * np.outer(e_b, e_b)
        + depth**2 * _mean_sin2(st_se) * np.outer(e_t, e_t)
        + sag
    )
    return depth * u, 0.5 * (cov + cov.T)


def _mean_sin2(sigma: float) -> float:
    return -0.5 * math.expm1(-2.0 * sigma * sigma)


def arc_moments(sigma: float) -> tuple[float, float]:
    """``E(1 − cos δ)`` and ``E(1 − cos δ)²`` for ``δ`` Gaussian of σ ``sigma`` (rad): the sagitta of an arc of
    unit radius a direction off by ``δ`` lands on, its mean and second moment.

    ``E cos δ = e^(−σ²/2)`` and ``Var cos δ = (1 − e^(−σ²))²/2``, so the mean is ``1 − e^(−σ²/2)`` and the
    second moment the mean squared plus that variance: ``3σ⁴/4`` for small σ, ``3/2`` for a direction unknown.
    """
    s2 = sigma * sigma
    mean = -math.expm1(-0.5 * s2)
    var = 0.5 * math.expm1(-s2) ** 2
    return mean, mean * mean + var


def _line_point(params: np.ndarray) -> np.ndarray:
    """The least-norm point of ``n_a·X = h_a``, ``n_b·X = h_b``; ``params`` = (β_a, t_a, h_a, β_b, t_b, h_b)."""
    mat = np.stack([unit_normal(params[0], params[1]), unit_normal(params[3], params[4])])
    return mat.T @ np.linalg.solve(mat @ mat.T, np.array([params[2], params[5]]))


def line_direction(params: np.ndarray) -> np.ndarray:
    """The unit direction ``n_a × n_b`` of two planes' line; ``params`` as :func:`pair_line_point`'s."""
    d = cross3(unit_normal(params[0], params[1]), unit_normal(params[3], params[4]))
    return d / max(float(np.linalg.norm(d)), 1e-12)


def pair_line_point(params: np.ndarray, covariance: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Two planes' line: its point nearest the array and that point's covariance, ``J Σ Jᵀ``.

    Parameters
    ----------
    params : (6,) array
        Bearing, tilt (rad) and offset (m) of each plane.
    covariance : (6, 6) array
        Their joint covariance (block-diagonal for planes fitted apart).

    Returns
    -------
    (point, covariance) or None when the planes are nearly parallel (``|n_a × n_b| < 0.2``).  The
    Jacobian is taken by central differences, each step far below its parameter's σ and far above
    rounding.
    """
    p = np.asarray(params, dtype=np.float64)
    size = float(np.linalg.norm(cross3(unit_normal(p[0], p[1]), unit_normal(p[3], p[4]))))
    if size < 0.2 or not np.all(np.isfinite(p)):
        return None
    x = _line_point(p)
    jac = np.empty((3, 6))
    for k in range(6):
        h = 1e-6 * (1.0 if k % 3 != 2 else max(abs(p[k]), 1.0))
        dp = np.zeros(6)
        dp[k] = h
        jac[:, k] = (_line_point(p + dp) - _line_point(p - dp)) / (2 * h)
    cov = jac @ np.asarray(covariance, dtype=np.float64) @ jac.T
    return x, 0.5 * (cov + cov.T)


def with_range(
    point: np.ndarray, covariance: np.ndarray, depth: float, depth_stderr: float
) -> tuple[np.ndarray, np.ndarray]:
    """A point conditioned on a measured range to it, ``|X| = ρ ± σ_ρ`` (one Kalman update, linearised at X).

    A concave corner's double bounce comes back from its edge's point nearest the array: its range is
    ``|X|``, a measurement the planes' line does not use when the walls are fitted apart.

    Returns
    -------
    (point, covariance)
    """
    norm = float(np.linalg.norm(point))
    sd = max(RANGE_FLOOR, depth_stderr) if math.isfinite(depth_stderr) else RANGE_FLOOR
    if not norm > 0:
        return point, covariance
    h = point / norm
    s = float(h @ covariance @ h) + sd * sd
    gain = covariance @ h / s
    new_point = point + gain * (depth - norm)
    new_cov = covariance - np.outer(gain, h @ covariance)
    return new_point, 0.5 * (new_cov + new_cov.T)


def line_yaw_stderr(
    depth: float, depth_stderr: float, tilt: float, tilt_stderr: float, plane_depth: float, plane_stderr: float
) -> float:
    """The bearing σ of a plane's line with a surface across the fan placed at the plane's foot, rad (0: none).

    A line in plane ``n·X = h`` at in-plane distance ``q`` from the foot ``h n``, turned by ``φ`` from square
    to the capsule stack, has its point nearest the array at ``X = h n + q (cos φ x̂ − sin φ e)`` (``e`` the
    plane's direction in the fan): range ``ρ² = h² + q²``, tilt ``sin t = q cos φ / ρ``, bearing off the foot
    ``tan δ = q sin φ / h``.  The echo's range and tilt give ``q = √(ρ² − h²)`` and ``c = cos φ = ρ sin|t| / q``;
    the foot takes ``φ = 0``.  Near square ``c`` is flat in ``φ``: a tilt within its σ of a square line's leaves
    ``φ`` open to ``acos(c − σ_c)``, and the bearing off the foot to ``δ`` there.

    Parameters
    ----------
    depth, depth_stderr : float
        ``ρ`` and its σ, m: the echo's range (at least :data:`RANGE_FLOOR`).
    tilt, tilt_stderr : float
        ``t`` off the fan and its σ, rad.
    plane_depth, plane_stderr : float
        ``h`` and its σ, m.

    Returns
    -------
    ``δ`` at ``cos φ = min(c, 1) − σ_c`` (``σ_c`` through ``t``, ``ρ`` and ``h`` to first order), rad; 0 where the
    range does not reach past the plane or any input is not finite.
    """
    vals = (depth, tilt, tilt_stderr, plane_depth)
    if not all(math.isfinite(v) for v in vals) or not depth > plane_depth > 0:
        return 0.0
    q = math.sqrt(depth * depth - plane_depth * plane_depth)
    st = abs(math.sin(tilt))
    c = depth * st / q
    sr = max(RANGE_FLOOR, depth_stderr) if math.isfinite(depth_stderr) else RANGE_FLOOR
    sh = max(RANGE_FLOOR, plane_stderr) if math.isfinite(plane_stderr) else RANGE_FLOOR
    q3 = q**3
    dc_dt = depth * math.cos(tilt) / q
    dc_dr = -st * plane_depth**2 / q3
    dc_dh = depth * st * plane_depth / q3
    sc = math.sqrt((dc_dt * tilt_stderr) ** 2 + (dc_dr * sr) ** 2 + (dc_dh * sh) ** 2)
    low = min(c, 1.0) - sc
    sin_phi = 1.0 if low <= 0.0 else math.sqrt(max(0.0, 1.0 - low * low))
    return math.atan2(q * sin_phi, plane_depth)


def opening_spread(
    depth: float,
    bearing: float,
    plane_bearing: float,
    plane_depth: float,
    beam_k: float,
    weak_echo: float,
    off_foot: float = math.inf,
) -> np.ndarray:
    """The second moment of where a concave corner with an unseen wall lies along its plane's trace, past the
    point its double bounce's range puts it at, its opening unknown, m².

    Two walls meeting at opening ``α`` turn the capsule's image by ``2α`` about their line: the double bounce
    comes back from ``ρ = |X| sin α`` (``|X|`` the line's distance), leaving and arriving ``δ = |α − 90°|`` either
    side of the ray to the line, so the beam weighs it by ``D(δ)²``, ``exp(−k δ²)`` in log amplitude (``k`` the
    beam's curvature across γ).  An echo called a corner's for being at least ``weak_echo`` of a mirror's may so
    be a double bounce up to ``δ_max = √(ln(1/weak_echo)/k)`` off a right angle: the line lies at
    ``ρ ≤ |X| ≤ ρ / cos δ_max``.  On the trace ``n·X = h`` (in the fan) that is
    ``s = √(|X|² − h²)`` from the foot, so the corner lies past its placement by up to
    ``Δs = √(ρ²/cos²δ_max − h²) − √(ρ² − h²)``, uniformly as far as anything says: second moment ``Δs²/3``
    along the trace, away from the foot.  A bearing of the corner's own, ``off_foot`` at most from the foot
    (3 σ past its measure and the foot's), stops the trace at ``s = h tan(off_foot)`` where that comes first.

    Parameters
    ----------
    depth : float
        ``ρ``, m: the region's range in the fan.
    bearing : float
        rad: where on the trace the corner is placed (its side of the foot).
    plane_bearing, plane_depth : float
        The plane's bearing (rad) and its trace's distance in the fan ``h``, m.
    beam_k : float
        ``k``, 1/rad² (not finite or not positive: ``δ_max`` a quarter turn, the line anywhere past ``ρ``).
    weak_echo : float
        The share of a mirror's echo under which an echo diffracts, in (0, 1).
    off_foot : float
        rad: how far from the foot the corner's own bearing allows it (inf: anywhere).

    Returns
    -------
    (3, 3) array: ``(Δs²/3) t tᵀ``, ``t`` the trace's unit direction away from the foot (zeros where the
    trace does not reach ``ρ``).
    """
    if not (math.isfinite(depth) and depth > plane_depth > 0):
        return np.zeros((3, 3))
    if math.isfinite(beam_k) and beam_k > 0:
        delta = min(math.sqrt(math.log(1.0 / weak_echo) / beam_k), 0.25 * math.pi)
    else:
        delta = 0.25 * math.pi
    far = depth / math.cos(delta)
    s_far = math.sqrt(far * far - plane_depth * plane_depth)
    if off_foot < 0.5 * math.pi:
        s_far = min(s_far, plane_depth * math.tan(off_foot))
    ds = max(0.0, s_far - math.sqrt(depth * depth - plane_depth * plane_depth))
    side = 1.0 if math.sin(bearing - plane_bearing) >= 0 else -1.0
    along = side * np.array([0.0, -math.sin(plane_bearing), math.cos(plane_bearing)])
    return (ds * ds / 3.0) * np.outer(along, along)
