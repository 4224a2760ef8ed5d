"""The robot's odometry between the poses of a world: noisy, drifting, with an honest covariance.

The odometry frame starts at the first pose (``odom`` = ``map`` there); each
move from one pose to the next is the classic turn–drive–turn of a
differential robot (Thrun, Burgard & Fox, *Probabilistic Robotics*, §5.4):
turn ``δ1`` towards the next point, drive ``d``, turn ``δ2`` to the new
heading.  The odometry measures

* ``δ1' = δ1·(1 + σ_r·N)``, ``d' = d·(1 + σ_t·N)``,
* ``δ2' = δ2·(1 + σ_r·N)``, plus a heading error ``drift·d + σ_h·√d·N`` built
  up along the drive, half of it before the drive and half after,

and its covariance over (x, y, heading) is propagated to first order through
the same composition, with the drift's square added to the heading variance
(a bias the robot does not know is part of its error, not a shift of its
estimate it could undo).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lelsonar.sim.world import Odometry, Pose2


@dataclass(frozen=True, eq=False)
class OdometryPose:
    """One pose as the odometry has it.

    Attributes
    ----------
    x, y, heading : float
        m, m, rad in the odometry frame.
    covariance : (3, 3) array
        Over (x, y, heading), m² and rad².
    """

    x: float
    y: float
    heading: float
    covariance: np.ndarray


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def simulate_odometry(poses: tuple[Pose2, ...], model: Odometry) -> list[OdometryPose]:
    """The odometry's estimate of every pose (the first is exact), seeded by ``model.seed``."""
    rng = np.random.default_rng(model.seed)
    if not poses:
        return []
    first = poses[0]
    x, y, th = first.x, first.y, first.heading
    cov = np.zeros((3, 3))
    out = [OdometryPose(x, y, th, cov.copy())]
    for prev, cur in zip(poses[:-1], poses[1:]):
        dx, dy = cur.x - prev.x, cur.y - prev.y
        d = math.hypot(dx, dy)
        d1 = _wrap(math.atan2(dy, dx) - prev.heading) if d > 1e-9 else 0.0
        d2 = _wrap(cur.heading - prev.heading - d1)
        n = rng.standard_normal(5)
        # The heading error of the drive builds up along it: half before (it bends the drive), half after.
        half_drift = [0.5 * model.heading_drift * d + model.heading_noise * math.sqrt(d / 2) * n[k] for k in (3, 4)]
        drift_var = 0.5 * model.heading_noise**2 * d + 0.5 * (model.heading_drift * d) ** 2
        m1 = d1 * (1 + model.rotation_noise * n[0]) + half_drift[0]
        md = d * (1 + model.translation_noise * n[1])
        m2 = d2 * (1 + model.rotation_noise * n[2]) + half_drift[1]
        # First turn.
        th += m1
        cov[2, 2] += (model.rotation_noise * d1) ** 2 + drift_var
        # Drive: x += d cos th, y += d sin th.
        jac = np.array([[1.0, 0.0, -md * math.sin(th)], [0.0, 1.0, md * math.cos(th)], [0.0, 0.0, 1.0]])
        u = np.array([math.cos(th), math.sin(th), 0.0])
        cov = jac @ cov @ jac.T + (model.translation_noise * d) ** 2 * np.outer(u, u)
        x += md * math.cos(th)
        y += md * math.sin(th)
        # Second turn.
        th = _wrap(th + m2)
        cov[2, 2] += (model.rotation_noise * d2) ** 2 + drift_var
        out.append(OdometryPose(x, y, th, 0.5 * (cov + cov.T)))
    return out


def array_covariance(odometry_covariance: np.ndarray) -> np.ndarray:
    """6 × 6 covariance (x, y, z, rotation about x, y, z) of the array frame from a base's (x, y, heading) one.

    The array sits above the base on its vertical axis, so it shares the base's position error in x and y and
    its heading error (a rotation about the world's z); height, roll and pitch are the mount's, known.
    """
    out = np.zeros((6, 6))
    idx = [0, 1, 5]
    out[np.ix_(idx, idx)] = odometry_covariance
    return out
