"""The walls of the map while it grows, and the gate an observation passes to join one.

A :class:`Track` is one wall as fusion holds it (in the local frame of the first pose), with the
observations (:class:`Seen`) that made it; :func:`gate` measures a new observation against every track.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lelsonar.map.observation import QUALITIES, WallObservation


@dataclass
class Seen:
    """One observation of a wall: which scan, its pose's index, the observation."""

    scan_id: int
    pose_index: int
    obs: WallObservation


@dataclass
class Track:
    """A wall of the map while it grows.  ``index`` ≥ 0: in the graph (good evidence); −1: flagged only."""

    id: int
    index: int
    seen: list[Seen]
    flagged: list[Seen] = field(default_factory=list)
    conflicts: dict[int, str] = field(default_factory=dict)  # other wall id → what differs
    line: np.ndarray = field(default_factory=lambda: np.zeros(2))  # local frame
    covariance: np.ndarray = field(default_factory=lambda: np.eye(2))
    interval: tuple[float, float] = (0.0, 0.0)


def precision_rank(obs: WallObservation) -> tuple[int, float]:
    """How an observation ranks to place a flagged wall: the better verdict, then the smaller σ of its bearing."""
    return QUALITIES.index(obs.quality), float(obs.covariance[0, 0])


def best_seen(seen: list[Seen]) -> Seen:
    """The observation that places a flagged wall best (:func:`precision_rank`)."""
    return min(seen, key=lambda s: precision_rank(s.obs))


def gate(
    tracks: list[Track],
    measured: np.ndarray,
    meas_cov: np.ndarray,
    pose: np.ndarray,
    pose_cov: np.ndarray,
    points: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mahalanobis d², the gap between stretches (m), and the innovation, of one observation to each track.

    The innovation is taken in the sensor frame: ``ν = h(pose, wall) − z`` with
    ``S = H_p P H_pᵀ + H_l C H_lᵀ + R`` (the pose's, the wall's and the observation's covariances).
    """
    n = len(tracks)
    if n == 0:
        return np.zeros(0), np.zeros(0), np.zeros((0, 2))
    lines = np.array([t.line for t in tracks])
    covs = np.array([t.covariance for t in tracks])
    x, y, psi = pose
    theta = lines[:, 0]
    c, s = np.cos(theta), np.sin(theta)
    a = theta - psi
    nu = np.empty((n, 2))
    nu[:, 0] = np.remainder(a - measured[0] + np.pi, 2 * np.pi) - np.pi
    nu[:, 1] = lines[:, 1] - (c * x + s * y) - measured[1]
    h_pose = np.zeros((n, 2, 3))
    h_pose[:, 0, 2] = -1.0
    h_pose[:, 1, 0] = -np.cos(a)
    h_pose[:, 1, 1] = -np.sin(a)
    h_line = np.zeros((n, 2, 2))
    h_line[:, 0, 0] = 1.0
    h_line[:, 1, 0] = x * s - y * c
    h_line[:, 1, 1] = 1.0
    big_s = h_pose @ pose_cov @ h_pose.transpose(0, 2, 1) + h_line @ covs @ h_line.transpose(0, 2, 1) + meas_cov
    d2 = np.einsum("ni,ni->n", nu, np.linalg.solve(big_s, nu[..., None])[..., 0])
    # The observed stretch on each wall's line, against the wall's own stretch.
    tangents = np.stack([-s, c], axis=1)
    feet = lines[:, 1:2] * np.stack([c, s], axis=1)
    along = np.einsum("nkj,nj->nk", points[None, :, :] - feet[:, None, :], tangents)
    lo, hi = along.min(axis=1), along.max(axis=1)
    intervals = np.array([t.interval for t in tracks])
    gap = np.maximum(lo - intervals[:, 1], intervals[:, 0] - hi)
    return d2, gap, nu
