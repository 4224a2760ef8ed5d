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


#: Huber's threshold (in σ) for the observations that enter robustly: 95 % efficiency on Gaussian errors.
HUBER_K = 1.345


def wall_factor(
    pose_index: int, wall_index: int, measured: np.ndarray, covariance: np.ndarray, robust: bool = False
) -> gtsam.CustomFactor:
    """A factor tying a scan's pose to a wall line through one observation ``(θ_s, ρ_s)`` with its covariance;
    ``robust``: Huber's loss beyond :data:`HUBER_K` σ, so one wrong observation pulls linearly, not quadratically."""
    gaussian = gtsam.noiseModel.Gaussian.Covariance(np.asarray(covariance, float))
    noise = (
        gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(HUBER_K), gaussian)
        if robust
        else gaussian
    )
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
    previous: np.ndarray, current: np.ndarray, previous_cov: np.ndarray, current_cov: np.ndarray, floor: np.ndarray
) -> np.ndarray:
    """The covariance of one odometry step from the absolute poses' covariances, as the step's factor takes it.

    Odometry composes each step onto its estimate and propagates its covariance to first order,
    ``Σ_k = J Σ_{k−1} Jᵀ + Q`` with ``J = [[1, 0, −Δy], [0, 1, Δx], [0, 0, 1]]`` (world frame,
    ``Δ = t_k − t_{k−1}``); the step's own noise is what that leaves, ``Q = Σ_k − J Σ_{k−1} Jᵀ``.  It is turned
    into the body frame of the new pose (the tangent of GTSAM's ``Pose2`` between two poses), its negative part
    (a source whose covariance does not grow) dropped, and each σ kept above ``floor``.

    Parameters
    ----------
    previous, current : array of 3
        The two odometry poses ``(x, y, ψ)``.
    previous_cov, current_cov : (3, 3) arrays
        Their covariances over ``(x, y, ψ)``, world frame.
    floor : array of 3
        Smallest σ of ``(δx, δy, δψ)``.
    """
    dx, dy = float(current[0] - previous[0]), float(current[1] - previous[1])
    jac = np.array([[1.0, 0.0, -dy], [0.0, 1.0, dx], [0.0, 0.0, 1.0]])
    q_world = np.asarray(current_cov) - jac @ np.asarray(previous_cov) @ jac.T
    c, s = math.cos(current[2]), math.sin(current[2])
    rot = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])  # world → body of the new pose
    q = rot @ q_world @ rot.T
    w, v = np.linalg.eigh(0.5 * (q + q.T))
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


class MapGraph:
    """The map's factor graph behind one door: the fusion adds poses, walls and factors as NumPy arrays, one
    :meth:`update` (an ISAM2 step) a scan, and reads estimates and marginals back as arrays.

    Parameters
    ----------
    relinearize_threshold, relinearize_skip
        As :func:`isam2`.
    """

    def __init__(self, relinearize_threshold: float, relinearize_skip: int = 10) -> None:
        self._isam = isam2(relinearize_threshold, relinearize_skip)
        self._factors = gtsam.NonlinearFactorGraph()
        self._values = gtsam.Values()
        self._estimate = gtsam.Values()

    # ---------------------------------------------------------------- building (pending until update)
    def add_pose(self, index: int, guess: np.ndarray) -> None:
        """A new pose variable with its initial guess ``(x, y, ψ)``."""
        self._values.insert(pose_key(index), gtsam.Pose2(*(float(v) for v in guess)))

    def add_wall(self, index: int, guess: np.ndarray) -> None:
        """A new wall variable with its initial guess ``(θ, ρ)``."""
        self._values.insert(wall_key(index), np.asarray(guess, float).copy())

    def add_prior(self, index: int, pose: np.ndarray, covariance: np.ndarray) -> None:
        self._factors.add(prior_factor(index, gtsam.Pose2(*(float(v) for v in pose)), covariance))

    def add_odometry(self, previous: int, current: int, step: np.ndarray, covariance: np.ndarray) -> None:
        self._factors.add(odometry_factor(previous, current, gtsam.Pose2(*(float(v) for v in step)), covariance))

    def add_observation(
        self, pose_index: int, wall_index: int, measured: np.ndarray, covariance: np.ndarray, robust: bool = False
    ) -> None:
        self._factors.add(wall_factor(pose_index, wall_index, measured, covariance, robust))

    # ---------------------------------------------------------------- solving
    def update(self) -> None:
        """One ISAM2 update with everything added since the last one.

        Raises
        ------
        RuntimeError
            GTSAM's indeterminate or ill-conditioned system (the pending factors are dropped).
        """
        factors, values = self._factors, self._values
        self._factors, self._values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        self._isam.update(factors, values)
        self._estimate = self._isam.calculateEstimate()

    def pose(self, index: int) -> np.ndarray:
        """The current estimate of a pose, ``(x, y, ψ)``."""
        return pose_vector(self._estimate.atPose2(pose_key(index)))

    def wall(self, index: int) -> np.ndarray:
        """The current estimate of a wall, ``(θ, ρ)``."""
        return np.asarray(self._estimate.atPoint2(wall_key(index)), float)

    def pose_marginal(self, index: int) -> np.ndarray:
        """ISAM2's marginal covariance of a pose (body-frame tangent)."""
        return np.asarray(self._isam.marginalCovariance(pose_key(index)))

    def wall_marginal(self, index: int) -> np.ndarray:
        """ISAM2's marginal covariance of a wall's ``(θ, ρ)``."""
        return np.asarray(self._isam.marginalCovariance(wall_key(index)))

    def pose_wall_joint(self, pose_index: int, wall_index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The joint marginal of a pose and a wall: its blocks ``(P_pp, P_pw, P_ww)``."""
        p, w = pose_key(pose_index), wall_key(wall_index)
        joint = self._isam.jointMarginalCovariance(gtsam.KeyVector([p, w]))
        return np.asarray(joint.at(p, p)), np.asarray(joint.at(p, w)), np.asarray(joint.at(w, w))

    def solve(self, polished: bool) -> Solution:
        """The whole graph's estimate: ISAM2's (its marginals from the Bayes tree, on demand), or converged by
        Levenberg–Marquardt from it (``polished``, with the marginals of that estimate)."""
        if not polished:
            return Solution(self._estimate, None, self)
        factors = self._isam.getFactorsUnsafe()
        estimate = polish(factors, self._estimate)
        return Solution(estimate, gtsam.Marginals(factors, estimate), self)


class Solution:
    """An estimate of the whole graph (:meth:`MapGraph.solve`), its values and marginals as arrays."""

    def __init__(self, estimate: gtsam.Values, marginals: gtsam.Marginals | None, owner: MapGraph) -> None:
        self._estimate = estimate
        self._marginals = marginals
        self._owner = owner

    def pose(self, index: int) -> np.ndarray:
        return pose_vector(self._estimate.atPose2(pose_key(index)))

    def wall(self, index: int) -> np.ndarray:
        return np.asarray(self._estimate.atPoint2(wall_key(index)), float)

    def pose_marginal(self, index: int) -> np.ndarray:
        if self._marginals is None:
            return self._owner.pose_marginal(index)
        return np.asarray(self._marginals.marginalCovariance(pose_key(index)))

    def wall_marginal(self, index: int) -> np.ndarray:
        if self._marginals is None:
            return self._owner.wall_marginal(index)
        return np.asarray(self._marginals.marginalCovariance(wall_key(index)))
