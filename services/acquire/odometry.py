"""A real robot's odometry as each scan's pose: follow ``<prefix>/<scanner>/odom``, compose with the mount.

The robot (or the ROS 2 bridge) publishes ``lelsonar.v1.Odometry``: its base
frame (x ahead, y left, z up) in ``odom``, with covariance.  The rig file's
``[mount]`` table says where the array sits on the base
(:func:`lelsonar.geometry.mount_rotation`, ``height`` above the base's origin
on its vertical axis); :func:`array_pose` composes the two into the pose each
``ScanStart`` carries.  A scan that starts with no odometry, or only with an
estimate older than ``max_age``, carries no pose, and the acquisition says why.
"""

from __future__ import annotations

import logging
import threading
import time

import numpy as np

from lelsonar import codec, poses
from lelsonar.errors import DecodeError
from lelsonar.geometry import matrix_from_quaternion, mount_rotation, quaternion_from_matrix
from lelsonar.keys import ScannerKeys

_log = logging.getLogger(__name__)


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def array_pose(base: poses.PoseWithCovariance, mount: str, height: float) -> poses.PoseWithCovariance:
    """The array frame (γ = 0) of a base pose: ``R_a = R_b·M``, ``t_a = t_b + R_b·(0, 0, height)``.

    The covariance (rotation errors as small rotations about the parent's axes) goes through the
    composition's Jacobian: the array shares the base's rotation error, and its position error
    adds ``δθ × R_b·m`` (the lever arm ``m`` of the mount turned with the base).

    Parameters
    ----------
    base : PoseWithCovariance
        The base frame in ``base.frame_id`` (validated).
    mount : {"fan", "paper"}
    height : float
        m, the array's rotation axis above the base's origin.
    """
    q = (base.orientation.x, base.orientation.y, base.orientation.z, base.orientation.w)
    rot_b = matrix_from_quaternion(q)
    t_b = np.array([base.position.x, base.position.y, base.position.z])
    lever = rot_b @ np.array([0.0, 0.0, float(height)])
    rot_a = rot_b @ mount_rotation(mount)
    cov = None
    if len(base.covariance) == 36:
        jac = np.eye(6)
        jac[:3, 3:] = -_skew(lever)
        c = jac @ np.asarray(base.covariance, dtype=float).reshape(6, 6) @ jac.T
        cov = 0.5 * (c + c.T)
    return poses.pose_message(base.frame_id, t_b + lever, quaternion_from_matrix(rot_a), cov)


class OdometryFollower:
    """The latest odometry of one scanner's robot, from its Zenoh key (thread-safe).

    Parameters
    ----------
    session : zenoh.Session or None
        None: nothing is subscribed (fed with :meth:`offer`, as in tests).
    keys : ScannerKeys
        Of one scanner (its ``odom`` key).
    max_age : float
        s; an estimate older than this at a scan's start is not used.
    """

    def __init__(self, session, keys: ScannerKeys, max_age: float = 1.0) -> None:
        self.keys = keys
        self.max_age = float(max_age)
        self.rejected = 0
        self._lock = threading.Lock()
        self._latest: tuple[int, codec.Odometry] | None = None
        self._sub = session.declare_subscriber(keys.odom, self._on_sample) if session is not None else None

    def _on_sample(self, sample) -> None:
        try:
            self.offer(sample.payload.to_bytes(), time.time_ns())
        except Exception:  # a Zenoh callback must not die silently: count and log it
            self.rejected += 1
            _log.exception("odometry sample on %s could not be taken", self.keys.odom)

    def offer(self, payload: bytes, received_ns: int) -> bool:
        """Take one ``Odometry`` payload; False (counted, logged once) if it is invalid or another scanner's."""
        try:
            msg = codec.decode(payload, codec.Odometry)
            if msg.scanner_id != self.keys.scanner_id:
                raise DecodeError(f"odometry of scanner {msg.scanner_id!r} on {self.keys.odom}")
        except DecodeError as exc:
            self.rejected += 1
            if self.rejected == 1:
                _log.warning("odometry on %s rejected (further rejections are counted): %s", self.keys.odom, exc)
            return False
        with self._lock:
            self._latest = (int(received_ns), msg)
        return True

    def pose_for_scan(
        self, mount: str, height: float, now_ns: int | None = None
    ) -> tuple[poses.PoseWithCovariance | None, str]:
        """The array's pose for a scan starting now, or None and why not."""
        now = time.time_ns() if now_ns is None else now_ns
        with self._lock:
            latest = self._latest
        if latest is None:
            return None, f"no odometry received on {self.keys.odom}: the scan carries no pose"
        age = (now - latest[0]) / 1e9
        if age > self.max_age:
            return None, f"the odometry on {self.keys.odom} is {age:.1f} s old: the scan carries no pose"
        return array_pose(latest[1].pose, mount, height), ""

    def close(self) -> None:
        if self._sub is not None:
            self._sub.undeclare()
            self._sub = None
