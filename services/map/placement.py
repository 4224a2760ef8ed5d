"""Observations placed through their poses: patch points, echo paths, a wall's placement σ (world frame)."""

from __future__ import annotations

import math

import numpy as np

from lelsonar.map.lines import wrap
from lelsonar.map.result import FusedWall


def sensor_points_to_world(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points (k, ≥2) of a scan's level sensor frame on the floor plane of the frame its ``pose`` is in."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return points[:, :2] @ np.array([[c, s], [-s, c]]) + pose[:2]


def wall_placement_sigma(wall: FusedWall) -> float:
    """The largest σ, m, of the wall's position across its line over its observed stretch.

    A point ``s`` along the line from its foot moves across it by ``δρ − s δθ``: its variance is
    ``C_ρρ − 2 s C_θρ + s² C_θθ``, largest at an end of the stretch.
    """
    c = wall.covariance
    return math.sqrt(max(max(float(c[1, 1] - 2 * s * c[0, 1] + s * s * c[0, 0]) for s in wall.interval), 0.0))


def observed_points(
    extents: list[np.ndarray], pose_index: list[int], poses: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The observations' patch points (k, 2) through their poses (``poses[pose_index[i]]``, rows ``(x, y, ψ)``),
    and where each observation's points start."""
    counts = [len(e) for e in extents]
    ext = np.concatenate([e[:, :2] for e in extents])
    p = poses[pose_index][np.repeat(np.arange(len(extents)), counts)]
    c, sn = np.cos(p[:, 2]), np.sin(p[:, 2])
    pts = np.stack([c * ext[:, 0] - sn * ext[:, 1] + p[:, 0], sn * ext[:, 0] + c * ext[:, 1] + p[:, 1]], axis=1)
    return pts, np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(int)


def observation_views(extents: list[np.ndarray], thetas: list[float], poses: np.ndarray) -> list[np.ndarray]:
    """Each observation's echo paths: the triangle from its scanner to its patch's two ends along the wall.

    ``extents`` and ``thetas`` are the observations' patches and normal azimuths (sensor frame), ``poses`` their
    own world poses, one a row.
    """
    counts = np.array([len(e) for e in extents])
    owner = np.repeat(np.arange(len(extents)), counts)
    ext = np.concatenate([e[:, :2] for e in extents])
    p = poses[owner]
    c, sn = np.cos(p[:, 2]), np.sin(p[:, 2])
    pts = np.stack([c * ext[:, 0] - sn * ext[:, 1] + p[:, 0], sn * ext[:, 0] + c * ext[:, 1] + p[:, 1]], axis=1)
    theta = p[:, 2] + np.asarray(thetas, float)[owner]
    along = -np.sin(theta) * pts[:, 0] + np.cos(theta) * pts[:, 1]
    order = np.lexsort((along, owner))
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(int)
    first, last = pts[order[starts]], pts[order[starts + counts - 1]]
    return list(np.stack([poses[:, :2], first, last], axis=1))


def world_pose_covariance(pose: np.ndarray, body_cov: np.ndarray) -> np.ndarray:
    """A Pose2 marginal (body-frame tangent) turned to world axes ``(x, y, ψ)``."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    r = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return r @ body_cov @ r.T


def line_distance2(a: np.ndarray, ca: np.ndarray, b: np.ndarray, cb: np.ndarray) -> float:
    """Mahalanobis d² between two wall lines of the same frame (independent errors)."""
    d = np.array([wrap(float(a[0] - b[0])), float(a[1] - b[1])])
    return float(d @ np.linalg.solve(ca + cb, d))
