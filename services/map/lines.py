"""Walls as oriented 2D lines, seen from a planar pose: the measurement model of the map and its Jacobians.

A wall is the vertical plane ``n·p = ρ`` with ``n = (cos θ, sin θ, 0)``.  Its normal points from the
free space that saw it into the wall (the reconstruction's convention: away from the scanner), so the two
faces of a thin wall are two lines, and ``ρ`` is signed: a wall through the origin has no singularity.

A pose ``(x, y, ψ)`` maps its level sensor frame to the world: ``p_w = R(ψ) p_s + t``.  The same wall in the
sensor frame is ``(θ − ψ, ρ − n(θ)·t)``.
"""

from __future__ import annotations

import math

import numpy as np


def wrap(angle: float) -> float:
    """``angle`` brought into ``(−π, π]``, rad."""
    r = math.remainder(angle, 2.0 * math.pi)
    return math.pi if r <= -math.pi else r


def line_in_sensor(pose: np.ndarray, line: np.ndarray) -> np.ndarray:
    """The wall ``line = (θ, ρ)`` (world) as seen from ``pose = (x, y, ψ)``: ``(θ − ψ, ρ − n(θ)·t)``.

    Parameters
    ----------
    pose : array of 3
        ``x, y`` in m, heading ``ψ`` in rad.
    line : array of 2
        ``θ`` in rad, ``ρ`` in m, world frame.

    Returns
    -------
    array of 2
        ``(θ_s, ρ_s)`` in the pose's level sensor frame, ``θ_s`` wrapped into ``(−π, π]``.
    """
    x, y, psi = pose
    theta, rho = line
    return np.array([wrap(theta - psi), rho - (math.cos(theta) * x + math.sin(theta) * y)])


def line_in_world(pose: np.ndarray, observed: np.ndarray) -> np.ndarray:
    """The inverse of :func:`line_in_sensor`: a wall ``(θ_s, ρ_s)`` seen from ``pose``, in the world."""
    x, y, psi = pose
    theta = wrap(observed[0] + psi)
    return np.array([theta, observed[1] + math.cos(theta) * x + math.sin(theta) * y])


def measurement_jacobians(pose: np.ndarray, line: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Jacobians of :func:`line_in_sensor` with respect to the pose and the line.

    The pose's increment is GTSAM's ``Pose2`` tangent ``(δx, δy, δψ)`` in the body frame
    (``t ← t + R(ψ)(δx, δy)``, ``ψ ← ψ + δψ`` to first order); the line's is ``(δθ, δρ)``.

    Returns
    -------
    H_pose : (2, 3) array
        ``[[0, 0, −1], [−cos(θ−ψ), −sin(θ−ψ), 0]]``.
    H_line : (2, 2) array
        ``[[1, 0], [x sin θ − y cos θ, 1]]``.
    """
    x, y, psi = pose
    theta = line[0]
    a = theta - psi
    h_pose = np.array([[0.0, 0.0, -1.0], [-math.cos(a), -math.sin(a), 0.0]])
    h_line = np.array([[1.0, 0.0], [x * math.sin(theta) - y * math.cos(theta), 1.0]])
    return h_pose, h_line


def world_jacobians(pose: np.ndarray, observed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Jacobians of :func:`line_in_world` with respect to ``(x, y, ψ)`` (world increments) and ``(θ_s, ρ_s)``.

    Used to carry an observation's covariance and its pose's into the world frame (first order).
    """
    x, y, _ = pose
    theta = observed[0] + pose[2]
    c, s = math.cos(theta), math.sin(theta)
    d = -s * x + c * y  # ∂(n(θ)·t)/∂θ
    j_pose = np.array([[0.0, 0.0, 1.0], [c, s, d]])
    j_obs = np.array([[1.0, 0.0], [d, 1.0]])
    return j_pose, j_obs


def tangent(theta: float) -> np.ndarray:
    """The wall's direction ``(−sin θ, cos θ)``: along it the extent is measured."""
    return np.array([-math.sin(theta), math.cos(theta)])


def foot(line: np.ndarray) -> np.ndarray:
    """The point of the line nearest the origin, ``ρ n(θ)``."""
    return line[1] * np.array([math.cos(line[0]), math.sin(line[0])])


def interval_on_line(line: np.ndarray, points: np.ndarray) -> tuple[float, float]:
    """The span of ``points`` (k, 2) projected along the line's :func:`tangent`, from its :func:`foot`."""
    s = (np.asarray(points, float)[:, :2] - foot(line)) @ tangent(float(line[0]))
    return float(s.min()), float(s.max())


def segment(line: np.ndarray, interval: tuple[float, float]) -> np.ndarray:
    """The two end points (2, 2) of the line between the distances ``interval`` along it."""
    f, t = foot(line), tangent(float(line[0]))
    return np.array([f + interval[0] * t, f + interval[1] * t])


def mahalanobis2(residual: np.ndarray, covariance: np.ndarray) -> float:
    """``rᵀ C⁻¹ r`` (a χ² with ``len(r)`` degrees of freedom when ``r ~ N(0, C)``)."""
    return float(residual @ np.linalg.solve(covariance, residual))


def _rot(psi: float) -> np.ndarray:
    c, s = math.cos(psi), math.sin(psi)
    return np.array([[c, -s], [s, c]])


def pose_compose(a: np.ndarray, u: np.ndarray) -> np.ndarray:
    """``a ⊕ u``: the pose ``u`` (given in ``a``'s body frame) in ``a``'s frame; as GTSAM's ``Pose2.compose``."""
    t = np.asarray(a[:2], float) + _rot(float(a[2])) @ np.asarray(u[:2], float)
    return np.array([t[0], t[1], wrap(float(a[2]) + float(u[2]))])


def pose_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a⁻¹ ⊕ b``: the motion from ``a`` to ``b`` in ``a``'s body frame; as GTSAM's ``Pose2.between``."""
    t = _rot(float(a[2])).T @ (np.asarray(b[:2], float) - np.asarray(a[:2], float))
    return np.array([t[0], t[1], wrap(float(b[2]) - float(a[2]))])


def pose_inverse_adjoint(u: np.ndarray) -> np.ndarray:
    """The adjoint (3, 3) of ``u⁻¹`` on the tangent ``(δx, δy, δψ)``: carries a covariance of the pose before a
    motion ``u`` into the body frame after it (GTSAM's ``Pose2.inverse().AdjointMap()``)."""
    psi = float(u[2])
    t = -(_rot(psi).T @ np.asarray(u[:2], float))
    r = _rot(-psi)
    return np.array([[r[0, 0], r[0, 1], t[1]], [r[1, 0], r[1, 1], -t[0]], [0.0, 0.0, 1.0]])
