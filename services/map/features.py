"""Corners and edges of the map: where fused walls meet, and the scans' own corners and edges fused by position."""

from __future__ import annotations

import math

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


def wall_corners(walls: list[FusedWall], reach: float) -> list[FusedFeature]:
    """Vertical corners where two fused walls' lines cross within ``reach`` of both observed stretches
    (and of an end of one of them).

    A corner is concave when each wall runs from it away from the other's face into the free space (the
    normals point into the walls): the stretch of ``a`` lies on the side of ``b`` opposite ``b``'s normal.
    """
    n = len(walls)
    if n < 2:
        return []
    theta = np.array([w.line[0] for w in walls])
    rho = np.array([w.line[1] for w in walls])
    lo = np.array([w.interval[0] for w in walls])
    hi = np.array([w.interval[1] for w in walls])
    i, j = np.triu_indices(n, 1)
    sin_ij = np.sin(theta[j] - theta[i])
    keep = np.abs(sin_ij) >= math.sin(MIN_CORNER_ANGLE)
    i, j, sin_ij = i[keep], j[keep], sin_ij[keep]
    # Where the lines cross (Cramer's rule on the two normals), and how far along each line that is.
    px = (rho[i] * np.sin(theta[j]) - rho[j] * np.sin(theta[i])) / sin_ij
    py = (rho[j] * np.cos(theta[i]) - rho[i] * np.cos(theta[j])) / sin_ij
    along = []
    for k in (i, j):
        s_k = -np.sin(theta[k]) * px + np.cos(theta[k]) * py  # the foot ρ n is at 0 along the line
        inside = (s_k >= lo[k] - reach) & (s_k <= hi[k] + reach)
        at_end = np.minimum(np.abs(s_k - lo[k]), np.abs(s_k - hi[k])) <= reach
        along.append((inside, at_end))
    ok = along[0][0] & along[1][0] & (along[0][1] | along[1][1])
    i, j, px, py, sin_ij = i[ok], j[ok], px[ok], py[ok], sin_ij[ok]
    if len(i) == 0:
        return []
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
    sigma = np.sqrt(np.clip(np.linalg.eigvalsh(cov)[:, -1], 0.0, None))
    middles = np.array([w.segment.mean(axis=0) for w in walls])
    normals = np.stack([np.cos(theta), np.sin(theta)], axis=1)
    concave = np.einsum("kj,kj->k", middles[i] - np.stack([px, py], axis=1), normals[j]) < 0.0
    out: list[FusedFeature] = []
    for k, (ia, ib) in enumerate(zip(i.tolist(), j.tolist())):
        a, b = walls[ia], walls[ib]
        z_lo, z_hi = max(a.z_range[0], b.z_range[0]), min(a.z_range[1], b.z_range[1])
        z = 0.5 * (z_lo + z_hi) if z_lo <= z_hi else 0.5 * (a.z_range[0] + b.z_range[0])
        out.append(
            FusedFeature(
                point=np.array([px[k], py[k], z]),
                direction=np.array([0.0, 0.0, 1.0]),
                kind="concave" if concave[k] else "convex",
                point_stderr=float(sigma[k]),
                source="walls",
                observations=a.good_observations + b.good_observations,
                walls=(a.id, b.id),
            )
        )
    return out


def _to_world(pose: np.ndarray, height: float, f: FeatureObservation) -> tuple[np.ndarray, np.ndarray]:
    c, s = math.cos(pose[2]), math.sin(pose[2])
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return rot @ f.point + np.array([pose[0], pose[1], height]), rot @ f.direction


def fuse_features(observed: list[tuple[int, np.ndarray, float, FeatureObservation]]) -> list[FusedFeature]:
    """The scans' own corners and edges in the world frame, one per physical feature.

    Parameters
    ----------
    observed : list of (scan_id, pose, height, feature)
        Each feature with its scan's corrected world pose ``(x, y, ψ)`` and height.

    Features of one kind whose lines are parallel within 10° and pass within 3σ (at least
    :data:`MIN_FEATURE_GATE`) of each other are one; its point is the mean of theirs, slid along the line
    to the first one's foot, and its σ that of a mean.
    """
    clusters: list[dict] = []
    for _sid, pose, height, f in observed:
        p, d = _to_world(pose, height, f)
        for c in clusters:
            if c["kind"] != f.kind or abs(float(d @ c["direction"])) < math.cos(math.radians(10.0)):
                continue
            off = p - c["anchor"]
            across = off - (off @ c["direction"]) * c["direction"]
            gate = max(3.0 * math.hypot(f.point_stderr, c["stderr"]), MIN_FEATURE_GATE)
            if float(np.linalg.norm(across)) <= gate:
                c["points"].append(c["anchor"] + across)
                c["stderrs"].append(f.point_stderr)
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
                }
            )
    return [
        FusedFeature(
            point=np.mean(c["points"], axis=0),
            direction=c["direction"],
            kind=c["kind"],
            point_stderr=math.sqrt(sum(s * s for s in c["stderrs"])) / len(c["stderrs"]),
            source="observed",
            observations=len(c["points"]),
        )
        for c in clusters
    ]
