"""The factor graph of the map: Pose2 scan poses and (θ, ρ) wall lines in GTSAM, solved incrementally by ISAM2.

The graph lives in a local frame whose origin is the first pose's position (far-away origins make the
system ill-conditioned), with a prior on the first pose; odometry between consecutive poses enters as
``BetweenFactorPose2``; each wall observation is a :func:`wall_factor` between its pose and its wall.
"""

from __future__ import annotations

import math
from functools import partial

import gtsam
import numpy as np

from lelsonar.map.lines import line_in_sensor, measurement_jacobians, wrap


def pose_key(index: int) -> int:
    """The graph key of the ``index``-th scan pose."""
    return gtsam.symbol("x", index)


def wall_key(index: int) -> int:
    """The graph key of the ``index``-th wall line."""
    return gtsam.symbol("l", index)


def pose_vector(pose: gtsam.Pose2) -> np.ndarray:
    """``(x, y, ψ)`` of a GTSAM pose."""
    return np.array([pose.x(), pose.y(), pose.theta()])


def wall_error(measured: np.ndarray, pose: np.ndarray, line: np.ndarray) -> np.ndarray:
    """The residual of one wall observation: predicted minus measured ``(θ_s, ρ_s)``, the angle wrapped."""
    predicted = line_in_sensor(pose, line)
    return np.array([wrap(predicted[0] - measured[0]), predicted[1] - measured[1]])


def _evaluate(measured: np.ndarray, this: gtsam.CustomFactor, values: gtsam.Values, jacobians) -> np.ndarray:
    keys = this.keys()
    pose = pose_vector(values.atPose2(keys[0]))
    line = values.atPoint2(keys[1])
    if jacobians is not None:
        h_pose, h_line = measurement_jacobians(pose, line)
        jacobians[0] = h_pose
        jacobians[1] = h_line
    return wall_error(measured, pose, line)


def wall_factor(pose_index: int, wall_index: int, measured: np.ndarray, covariance: np.ndarray) -> gtsam.CustomFactor:
    """A factor tying a scan's pose to a wall line through one observation ``(θ_s, ρ_s)`` with its covariance."""
    noise = gtsam.noiseModel.Gaussian.Covariance(np.asarray(covariance, float))
    return gtsam.CustomFactor(
        noise, [pose_key(pose_index), wall_key(wall_index)], partial(_evaluate, np.asarray(measured, float).copy())
    )


def odometry_factor(previous: int, current: int, step: gtsam.Pose2, covariance: np.ndarray) -> gtsam.BetweenFactorPose2:
    """The odometry's motion between two consecutive scans, with its covariance (body frame of ``previous``)."""
    return gtsam.BetweenFactorPose2(
        pose_key(previous), pose_key(current), step, gtsam.noiseModel.Gaussian.Covariance(covariance)
    )


def prior_factor(index: int, pose: gtsam.Pose2, covariance: np.ndarray) -> gtsam.PriorFactorPose2:
    """The prior that anchors the map's frame at the first pose."""
    return gtsam.PriorFactorPose2(pose_key(index), pose, gtsam.noiseModel.Gaussian.Covariance(covariance))


def step_covariance_from_poses(
    previous: np.ndarray, previous_cov: np.ndarray, current_cov: np.ndarray, floor: np.ndarray
) -> np.ndarray:
    """The covariance of one odometry step from the growth of the absolute poses' covariances.

    Odometry reports ``Σ_k`` growing with the distance travelled; the step adds ``Σ_k − Σ_{k−1}``
    (world frame), turned into the previous pose's body frame.  Its negative part (a source whose
    covariance does not grow) is dropped, and each σ is kept above ``floor``.

    Parameters
    ----------
    previous : array of 3
        The previous odometry pose ``(x, y, ψ)``.
    previous_cov, current_cov : (3, 3) arrays
        The two poses' covariances over ``(x, y, ψ)``, world frame.
    floor : array of 3
        Smallest σ of ``(δx, δy, δψ)``.
    """
    c, s = math.cos(previous[2]), math.sin(previous[2])
    rot = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])  # world → body of the previous pose
    grown = rot @ (np.asarray(current_cov) - np.asarray(previous_cov)) @ rot.T
    w, v = np.linalg.eigh(0.5 * (grown + grown.T))
    psd = (v * np.clip(w, 0.0, None)) @ v.T
    return psd + np.diag(np.asarray(floor, float) ** 2)


def isam2(relinearize_threshold: float, relinearize_skip: int = 10) -> gtsam.ISAM2:
    """An ISAM2 solver: Gauss–Newton steps on the Bayes tree, relinearized where a variable moved more than
    ``relinearize_threshold``, checked every ``relinearize_skip`` updates.

    Not the dogleg variant: it evaluates every factor's error at each update, and with Python factors
    that cost grows with the map.
    """
    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(relinearize_threshold)
    params.relinearizeSkip = relinearize_skip
    return gtsam.ISAM2(params)


def polish(factors: gtsam.NonlinearFactorGraph, initial: gtsam.Values) -> gtsam.Values:
    """Levenberg–Marquardt over the whole graph from ISAM2's estimate: the map as read is converged, whatever
    the incremental solver's relinearization left pending (its state is not touched)."""
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-6)
    params.setMaxIterations(20)
    return gtsam.LevenbergMarquardtOptimizer(factors, initial, params).optimize()
