"""Corners and edges of the map: where fused walls meet, and the scans' own corners and edges fused by position."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from lelsonar.map.observation import FeatureObservation
from lelsonar.map.result import FusedFeature, FusedWall

#: Two walls make a corner only if their normals are at least this far apart (parallel walls never meet).
MIN_CORNER_ANGLE = math.radians(30.0)

#: Observed features closer than this (m), or 3σ, are one feature.
MIN_FEATURE_GATE = 0.05


def line_intersection(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where two wall lines ``(θ, ρ)`` cross, and the Jacobian (2, 4) of the point wrt ``(θ_a, ρ_a, θ_b, ρ_b)``.

    The point solves ``A p = (ρ_a, ρ_b)`` with ``A``'s rows the normals; differentiating,
    ``A dp = (dρ_a − p·n'(θ_a) dθ_a, dρ_b − p·n'(θ_b) dθ_b)`` with ``n'(θ) = (−sin θ, cos θ)``.
    """
    ta, tb = float(a[0]), float(b[0])
    mat = np.array([[math.cos(ta), math.sin(ta)], [math.cos(tb), math.sin(tb)]])
    p = np.linalg.solve(mat, np.array([a[1], b[1]], float))
    inv = np.linalg.inv(mat)
    da = -(-math.sin(ta) * p[0] + math.cos(ta) * p[1])
    db = -(-math.sin(tb) * p[0] + math.cos(tb) * p[1])
    jac = np.column_stack([inv[:, 0] * da, inv[:, 0], inv[:, 1] * db, inv[:, 1]])
    return p, jac


#: Observed features within this angle of the vertical are corners or edges of the floor plan; the others (a wall
#: meeting the floor or the ceiling, a box's top) are not.
MAX_FEATURE_TILT = math.radians(30.0)

#: A scan's corner or edge that no two walls meet at is published only when this many scans saw it (one scan's
#: double bounce or diffraction can be a ghost of several echoes).
MIN_FEATURE_SCANS = 2

#: A wall's observed stretch reaches a crossing when it ends within 3σ of the crossing's point along it, or
#: within this, m (the end of a sonar patch is where the echoes stopped, known to about a beam step).
MEET_FLOOR = 0.05


def _along(theta: np.ndarray, px: np.ndarray, py: np.ndarray) -> np.ndarray:
    """Distance along each line's tangent ``(−sin θ, cos θ)`` from its foot to the points."""
    return -np.sin(theta) * px + np.cos(theta) * py


def _reach(pieces: tuple[tuple[float, float], ...], s: float, tolerance: float) -> tuple[float, float]:
    """How far a wall's observed pieces stay from ``s`` along its line (0 inside one), and which way the wall
    runs off from ``s``: +1 towards larger ``s``, −1 towards smaller, 0 when a piece runs on past ``s`` both
    ways by more than ``tolerance`` (the wall passes through)."""
    best, way = math.inf, 0.0
    for lo, hi in pieces:
        gap = max(lo - s, s - hi, 0.0)
        if gap < best:
            best = gap
            if lo > s - tolerance and hi > s + tolerance:
                way = 1.0
            elif hi < s + tolerance and lo < s - tolerance:
                way = -1.0
            else:
                way = 0.0
    return best, way


def wall_corners(
    walls: list[FusedWall], reach: float, observed: Sequence[FusedFeature] = ()
) -> tuple[list[FusedFeature], list[FusedFeature]]:
    """Vertical corners where two fused walls meet, and the observed features no corner took.

    Two walls at least :data:`MIN_CORNER_ANGLE` apart meet at their lines' crossing ``p`` (σ from both walls'
    covariances, first order) when

    * each wall's observed pieces reach ``p`` within 3σ of ``p`` along it (at least :data:`MEET_FLOOR`); or
    * a scan's own vertical corner (a double bounce) or edge (diffraction) of that kind, ``observed``, lies
      within 3σ of ``p`` (σ of both; at least :data:`MEET_FLOOR`, at most ``reach``).  Sonar sees a wall only
      near the foot of its perpendicular, so the pieces seldom reach a corner; the corner's own echo sees it.

    Where neither holds the lines' crossing is no corner: two walls' lines cross in many places where the
    walls do not meet (an opening, a wall that ends before the other).  Nor is a crossing the map places
    worse than ``reach`` at 3σ (walls whose poses are that uncertain).

    The kind comes from the sides the walls run off the crossing on: the normals point away from the free space
    that saw them, so at a concave corner each wall runs off on the side of the other opposite that one's
    normal, at a convex one on its side.  A wall whose pieces pass through ``p`` (a T) leaves the kind to the
    other; walls that run off on opposite sides cross, and make no corner.

    Returns
    -------
    corners : list of FusedFeature
        Source ``walls``; ``observations`` counts both walls' good observations and the scans' features that
        vouch for it.
    rest : list of FusedFeature
        The vertical ``observed`` features no two walls explain, that :data:`MIN_FEATURE_SCANS` scans saw and
        the map places within ``reach`` at 3σ (the others, and a wall meeting the floor or the ceiling, no
        corner of a floor plan, are left out).
    """
    feats = [f for f in observed if abs(float(f.direction[2])) >= math.cos(MAX_FEATURE_TILT)]
    n = len(walls)
    if n < 2:
        return [], [f for f in feats if _lone(f, reach)]
    theta = np.array([w.line[0] for w in walls])
    rho = np.array([w.line[1] for w in walls])
    lo = np.array([w.interval[0] for w in walls])
    hi = np.array([w.interval[1] for w in walls])
    i, j = np.triu_indices(n, 1)
    sin_ij = np.sin(theta[j] - theta[i])
    keep = np.abs(sin_ij) >= math.sin(MIN_CORNER_ANGLE)
    i, j, sin_ij = i[keep], j[keep], sin_ij[keep]
    # Where the lines cross (Cramer's rule on the two normals); the pairs whose stretches come within reach of it
    # or that have a scan's feature within reach.
    px = (rho[i] * np.sin(theta[j]) - rho[j] * np.sin(theta[i])) / sin_ij
    py = (rho[j] * np.cos(theta[i]) - rho[i] * np.cos(theta[j])) / sin_ij
    s_i, s_j = _along(theta[i], px, py), _along(theta[j], px, py)
    ok = (s_i >= lo[i] - reach) & (s_i <= hi[i] + reach) & (s_j >= lo[j] - reach) & (s_j <= hi[j] + reach)
    fpts = np.array([f.point[:2] for f in feats]).reshape(-1, 2)
    fsig = np.array([f.point_stderr for f in feats])
    if len(fpts):
        dist = np.hypot(px[:, None] - fpts[None, :, 0], py[:, None] - fpts[None, :, 1])
        ok |= dist.min(axis=1) <= reach
    i, j, px, py, sin_ij, s_i, s_j = i[ok], j[ok], px[ok], py[ok], sin_ij[ok], s_i[ok], s_j[ok]
    if len(i) == 0:
        return [], [f for f in feats if _lone(f, reach)]
    # The crossing's covariance, first order (line_intersection's Jacobian, all pairs at once): A⁻¹ has columns
    # (sin θ_b, −cos θ_b) / s and (−sin θ_a, cos θ_a) / s with s = sin(θ_b − θ_a).
    ta, tb = theta[i], theta[j]
    inv0 = np.stack([np.sin(tb), -np.cos(tb)], axis=1) / sin_ij[:, None]
    inv1 = np.stack([-np.sin(ta), np.cos(ta)], axis=1) / sin_ij[:, None]
    da = -(-np.sin(ta) * px + np.cos(ta) * py)
    db = -(-np.sin(tb) * px + np.cos(tb) * py)
    jac = np.stack([inv0 * da[:, None], inv0, inv1 * db[:, None], inv1], axis=2)  # (k, 2, 4)
    covs = np.array([w.covariance for w in walls])
    block = np.zeros((len(i), 4, 4))
    block[:, :2, :2] = covs[i]
    block[:, 2:, 2:] = covs[j]
    cov = jac @ block @ jac.transpose(0, 2, 1)
    tangents = np.stack([-np.sin(theta), np.cos(theta)], axis=1)
    # σ of the crossing along each wall, and its largest.
    sig_i = np.sqrt(np.clip(np.einsum("kj,kjl,kl->k", tangents[i], cov, tangents[i]), 0.0, None))
    sig_j = np.sqrt(np.clip(np.einsum("kj,kjl,kl->k", tangents[j], cov, tangents[j]), 0.0, None))
    sigma = np.sqrt(np.clip(np.linalg.eigvalsh(cov)[:, -1], 0.0, None))
    normals = np.stack([np.cos(theta), np.sin(theta)], axis=1)
    candidates = []
    for k, (ia, ib) in enumerate(zip(i.tolist(), j.tolist())):
        a, b = walls[ia], walls[ib]
        meet_a = max(3.0 * float(sig_i[k]), MEET_FLOOR)
        meet_b = max(3.0 * float(sig_j[k]), MEET_FLOOR)
        gap_a, run_a = _reach(a.pieces, float(s_i[k]), meet_a)
        gap_b, run_b = _reach(b.pieces, float(s_j[k]), meet_b)
        # Which side of the other wall each one runs off on: −1 behind its normal (concave), +1 in front.
        side_a = float(np.sign(run_a * (tangents[ia] @ normals[ib])))
        side_b = float(np.sign(run_b * (tangents[ib] @ normals[ia])))
        sides = {v for v in (side_a, side_b) if v != 0.0}
        if len(sides) != 1:
            continue  # they cross, or both pass through
        kind = "concave" if sides == {-1.0} else "convex"
        near: list[int] = []
        if len(fpts):
            d = np.hypot(*(fpts - np.array([px[k], py[k]])).T)
            gate = np.minimum(np.maximum(3.0 * np.hypot(fsig, sigma[k]), MEET_FLOOR), reach)
            near = [m for m in np.flatnonzero(d <= gate).tolist() if _kind_agrees(feats[m].kind, kind)]
        if not (near or (gap_a <= meet_a and gap_b <= meet_b)):
            continue
        # Placed too loosely it is no corner of the map, and the scans' features it explains are none either
        # (they went through the same poses).
        candidates.append((k, ia, ib, kind, near, 3.0 * float(sigma[k]) <= reach))
    taken = {m for *_, near, _ in candidates for m in near}
    out: list[FusedFeature] = []
    for k, ia, ib, kind, near, placed in candidates:
        if not placed:
            continue
        a, b = walls[ia], walls[ib]
        z_lo, z_hi = max(a.z_range[0], b.z_range[0]), min(a.z_range[1], b.z_range[1])
        z = 0.5 * (z_lo + z_hi) if z_lo <= z_hi else 0.5 * (a.z_range[0] + b.z_range[0])
        out.append(
            FusedFeature(
                point=np.array([px[k], py[k], z]),
                direction=np.array([0.0, 0.0, 1.0]),
                kind=kind,
                point_stderr=float(sigma[k]),
                source="walls",
                observations=a.good_observations + b.good_observations + sum(feats[m].observations for m in near),
                walls=(a.id, b.id),
            )
        )
    return out, [f for m, f in enumerate(feats) if m not in taken and _lone(f, reach)]


def horizontal_corners(observed: Sequence[FusedFeature]) -> list[FusedFeature]:
    """The scans' corners that are no corner of the floor plan: a wall meeting the floor or the ceiling (a line
    more than :data:`MAX_FEATURE_TILT` from the vertical), those :data:`MIN_FEATURE_SCANS` scans saw."""
    return [
        f
        for f in observed
        if abs(float(f.direction[2])) < math.cos(MAX_FEATURE_TILT)
        and f.kind != "edge"
        and len(f.scans) >= MIN_FEATURE_SCANS
    ]


def _lone(f: FusedFeature, reach: float) -> bool:
    """Whether a scan's feature no two walls explain is published: seen by enough scans, placed within reach."""
    return len(f.scans) >= MIN_FEATURE_SCANS and 3.0 * f.point_stderr <= reach


def _kind_agrees(observed: str, kind: str) -> bool:
    """A scan's concave corner vouches for a concave wall corner; its convex corner or edge for a convex one."""
    return observed == kind or (observed == "edge" and kind == "convex")


def _to_world(pose: np.ndarray, height: float, f: FeatureObservation) -> tuple[np.ndarray, np.ndarray]:
    c, s = math.cos(pose[2]), math.sin(pose[2])
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return rot @ f.point + np.array([pose[0], pose[1], height]), rot @ f.direction


def placement_sigma(pose_covariance: np.ndarray, reach: float) -> float:
    """σ (m) a pose's uncertainty gives a point ``reach`` m from it: its position's largest σ and its heading's
    σ times the lever arm, first order.

    Parameters
    ----------
    pose_covariance : (3, 3) array
        Over ``(x, y, ψ)``, world axes.
    """
    xy = float(np.linalg.eigvalsh(np.asarray(pose_covariance)[:2, :2])[-1])
    return math.sqrt(max(xy, 0.0) + reach * reach * max(float(pose_covariance[2, 2]), 0.0))


def fuse_features(
    observed: list[tuple[int, np.ndarray, float, FeatureObservation]], pose_sigmas: Sequence[float] | None = None
) -> list[FusedFeature]:
    """The scans' own corners and edges in the world frame, one per physical feature.

    Parameters
    ----------
    observed : list of (scan_id, pose, height, feature)
        Each feature with its scan's corrected world pose ``(x, y, ψ)`` and height.
    pose_sigmas : sequence of float, optional
        σ (m) each feature's pose gives its point in the world (:func:`placement_sigma`); none: exact poses.

    Features of one kind whose lines are parallel within 10° and pass within 3σ (at least
    :data:`MIN_FEATURE_GATE`) of each other are one; its point is the mean of theirs, slid along the line
    to the first one's foot, and its σ that of a mean of the scans' own errors, with the smallest of the poses'
    (the poses are placed by one map: their errors do not average out).
    """
    clusters: list[dict] = []
    for k, (sid, pose, height, f) in enumerate(observed):
        p, d = _to_world(pose, height, f)
        placed = 0.0 if pose_sigmas is None else float(pose_sigmas[k])
        for c in clusters:
            if c["kind"] != f.kind or abs(float(d @ c["direction"])) < math.cos(math.radians(10.0)):
                continue
            off = p - c["anchor"]
            across = off - (off @ c["direction"]) * c["direction"]
            gate = max(3.0 * math.hypot(f.point_stderr, c["stderr"], placed, c["placed"]), MIN_FEATURE_GATE)
            if float(np.linalg.norm(across)) <= gate:
                c["points"].append(c["anchor"] + across)
                c["stderrs"].append(f.point_stderr)
                c["scans"].append(sid)
                c["placed"] = min(c["placed"], placed)
                break
        else:
            clusters.append(
                {
                    "kind": f.kind,
                    "direction": d,
                    "anchor": p,
                    "stderr": f.point_stderr,
                    "points": [p],
                    "stderrs": [f.point_stderr],
                    "scans": [sid],
                    "placed": placed,
                }
            )
    return [
        FusedFeature(
            point=np.mean(c["points"], axis=0),
            direction=c["direction"],
            kind=c["kind"],
            point_stderr=math.hypot(math.sqrt(sum(s * s for s in c["stderrs"])) / len(c["stderrs"]), c["placed"]),
            source="observed",
            observations=len(c["points"]),
            scans=tuple(dict.fromkeys(c["scans"])),
        )
        for c in clusters
    ]
