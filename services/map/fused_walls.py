"""One wall of the map as it is read out: its verdict, its world line and σ, the pieces its scans saw.

:func:`wall_verdict` says whether a wall of good evidence stays good, :func:`fused_wall` carries a track's line
from the local frame into the world with its pieces, and :func:`checked_placement` degrades a good wall the map cannot
place within ``good_tolerance``.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from lelsonar.map.lines import wrap
from lelsonar.map.placement import observed_points, wall_placement_sigma
from lelsonar.map.result import FusedWall
from lelsonar.map.tracks import Track


def checked_placement(wall: FusedWall, good_tolerance: float) -> FusedWall:
    """A good wall the map places less well than ``good_tolerance`` (3σ over its stretch) is degraded."""
    if wall.quality != "good":
        return wall
    sigma = wall_placement_sigma(wall)
    if 3.0 * sigma <= good_tolerance:
        return wall
    reason = (
        f"placed to ±{100 * sigma:.1f} cm (1σ) over its stretch in the map's frame, more than "
        f"{100 * good_tolerance / 3:.2g} cm: the poses that saw it are that uncertain"
    )
    return replace(wall, quality="degraded", reasons=wall.reasons + (reason,))


def wall_verdict(
    t: Track, line: np.ndarray, poses: list[np.ndarray], by_id: dict[int, Track], gate_chi2: float
) -> tuple[str, tuple[str, ...]]:
    """A wall of good evidence stays good unless its observations disagree with it or with each other."""
    reasons = []
    if t.seen:
        # Each observation's residual against the fused wall, all at once (graph.wall_error's model).
        p = np.array([poses[s.pose_index] for s in t.seen])
        z = np.array([s.obs.line for s in t.seen])
        c = np.array([s.obs.covariance for s in t.seen])
        theta, rho = float(line[0]), float(line[1])
        e = np.stack(
            [
                np.remainder(theta - p[:, 2] - z[:, 0] + np.pi, 2 * np.pi) - np.pi,
                rho - (math.cos(theta) * p[:, 0] + math.sin(theta) * p[:, 1]) - z[:, 1],
            ],
            axis=1,
        )
        d2 = np.einsum("ni,ni->n", e, np.linalg.solve(c, e[..., None])[..., 0])
        for s, v in zip(t.seen, d2.tolist()):
            if v > gate_chi2:
                reasons.append(f"scan {s.scan_id}'s observation is {math.sqrt(v):.1f}σ from the fused wall")
    for other_id, what in sorted(t.conflicts.items()):
        other = by_id.get(other_id)
        n_other = len(other.seen) if other is not None else 0
        if not (len(t.seen) >= 2 and len(t.seen) > n_other):
            reasons.append(f"disagrees with wall {other_id} on the same surface: {what}; kept apart, not averaged")
    return ("good" if not reasons else "degraded"), tuple(reasons)


def fused_wall(
    t: Track,
    line_local: np.ndarray,
    cov_local: np.ndarray,
    poses: list[np.ndarray],
    verdict: tuple[str, tuple[str, ...]],
    heights: list[float],
    origin: np.ndarray,
    join_gap: float,
) -> FusedWall:
    """The wall of a track in the world frame: its line and σ carried from the local frame, the pieces its
    observations cover (stretches closer than ``join_gap`` joined), its heights and ``verdict``."""
    everything = t.seen + t.flagged
    pts, starts = observed_points(
        [s.obs.extent for s in everything], [s.pose_index for s in everything], np.asarray(poses)
    )
    theta_l = float(line_local[0])
    along = (pts - float(line_local[1]) * np.array([math.cos(theta_l), math.sin(theta_l)])) @ np.array(
        [-math.sin(theta_l), math.cos(theta_l)]
    )
    spans = sorted(
        zip(
            np.minimum.reduceat(along, starts).tolist(),
            np.maximum.reduceat(along, starts).tolist(),
            (s.scan_id for s in everything),
        )
    )
    pieces = [[spans[0][0], spans[0][1]]]
    piece_scans = [[spans[0][2]]]
    for lo, hi, scan_id in spans[1:]:
        if lo - pieces[-1][1] <= join_gap:
            pieces[-1][1] = max(pieces[-1][1], hi)
            piece_scans[-1].append(scan_id)
        else:
            pieces.append([lo, hi])
            piece_scans.append([scan_id])
    zs = np.concatenate([s.obs.extent[:, 2] + heights[s.pose_index] for s in everything])
    # Local → world: ρ_w = ρ_l + n(θ)·o, so dρ_w/dθ = −sin θ o_x + cos θ o_y.
    theta = wrap(float(line_local[0]))
    ox, oy = origin
    b = -math.sin(theta) * ox + math.cos(theta) * oy
    j = np.array([[1.0, 0.0], [b, 1.0]])
    line_world = np.array([theta, line_local[1] + math.cos(theta) * ox + math.sin(theta) * oy])
    return FusedWall(
        id=t.id,
        line=line_world,
        covariance=j @ cov_local @ j.T,
        interval=(pieces[0][0] + b, max(p[1] for p in pieces) + b),
        pieces=tuple((lo + b, hi + b) for lo, hi in pieces),
        z_range=(float(zs.min()), float(zs.max())),
        quality=verdict[0],
        reasons=verdict[1],
        scans=tuple(dict.fromkeys(s.scan_id for s in everything)),
        good_observations=len(t.seen),
        flagged_observations=len(t.flagged),
        piece_scans=tuple(tuple(dict.fromkeys(ids)) for ids in piece_scans),
    )
