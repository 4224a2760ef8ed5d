"""The pose a scan announces: ``PoseWithCovariance`` checked, read into :class:`ScanPose`, and built.

A scan's ``ScanStart.pose`` and an ``Odometry`` message carry the array frame's pose in a named frame;
:func:`validate_pose` is their check (:func:`lelsonar.codec.decode` runs it), :func:`scan_pose` reads one
(the origin, with a note, for a scan that carries none), :func:`pose_message` writes one.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np

from lelsonar.checks import finite, finite_vector
from lelsonar.errors import InvalidMessageError, NonFiniteValueError
from lelsonar.v1 import scan_pb2

ScanStart = scan_pb2.ScanStart
PoseWithCovariance = scan_pb2.PoseWithCovariance

#: A pose's quaternion may be off unit norm by this much (float32 round trips, hand-typed poses).
QUATERNION_NORM_TOLERANCE = 1e-3
#: The frame a scan without a pose is taken to be in.
DEFAULT_POSE_FRAME = "odom"
_FRAME_ID = re.compile(r"[A-Za-z0-9_.\-]{1,64}")


def validate_pose(where: str, pose: PoseWithCovariance) -> None:
    """Check a pose: a bounded frame id, a finite position, a unit quaternion, a symmetric PSD covariance.

    Raises
    ------
    DecodeError
        A subclass naming the field and what was wrong.
    """
    if not _FRAME_ID.fullmatch(pose.frame_id):
        raise InvalidMessageError(
            f"{where}.frame_id {pose.frame_id[:80]!r} must be 1 to 64 of [A-Za-z0-9_.-] (e.g. 'odom' or 'map')"
        )
    finite_vector(f"{where}.position", pose.position)
    q = pose.orientation
    finite(f"{where}.orientation", q.x, q.y, q.z, q.w)
    norm = math.sqrt(q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w)
    if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
        raise InvalidMessageError(f"{where}.orientation has norm {norm:.6g}; a rotation needs a unit quaternion")
    n = len(pose.covariance)
    if n == 0:
        return
    if n != 36:
        raise InvalidMessageError(f"{where}.covariance holds {n} numbers; expected 36 (6 x 6, row-major) or none")
    cov = np.asarray(pose.covariance, dtype=float).reshape(6, 6)
    if not np.all(np.isfinite(cov)):
        raise NonFiniteValueError(f"{where}.covariance must be finite")
    scale = max(float(np.max(np.abs(cov))), 1e-300)
    if np.max(np.abs(cov - cov.T)) > 1e-9 * scale:
        raise InvalidMessageError(f"{where}.covariance is not symmetric")
    if np.min(np.diag(cov)) < 0 or np.min(np.linalg.eigvalsh(cov)) < -1e-9 * scale:
        raise InvalidMessageError(f"{where}.covariance is not positive semi-definite (a negative variance)")


@dataclass(frozen=True)
class ScanPose:
    """The pose a scan announces, or the origin for a scan that carries none.

    Attributes
    ----------
    frame_id : str
    position : (3,) array, m
    orientation : (x, y, z, w)
    covariance : (6, 6) array or None
        None when the scan gave none.
    known : bool
        False: the scan carried no pose and this is the origin of :data:`DEFAULT_POSE_FRAME`.
    note : str
        Empty, or why the pose is the origin.
    """

    frame_id: str
    position: np.ndarray
    orientation: tuple[float, float, float, float]
    covariance: np.ndarray | None
    known: bool
    note: str = ""


def scan_pose(start: ScanStart) -> ScanPose:
    """The array frame's pose of a (validated) ``ScanStart``; the origin, with a note, when it has none."""
    if not start.HasField("pose"):
        return ScanPose(
            DEFAULT_POSE_FRAME,
            np.zeros(3),
            (0.0, 0.0, 0.0, 1.0),
            None,
            False,
            "the scan carries no pose (recorded before scans did): taken as the origin",
        )
    p = start.pose
    q = np.array([p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w])
    q /= np.linalg.norm(q)
    cov = np.asarray(p.covariance, dtype=float).reshape(6, 6) if len(p.covariance) == 36 else None
    return ScanPose(
        p.frame_id,
        np.array([p.position.x, p.position.y, p.position.z]),
        (float(q[0]), float(q[1]), float(q[2]), float(q[3])),
        cov,
        True,
    )


def pose_message(frame_id: str, position, orientation, covariance: np.ndarray | None = None) -> PoseWithCovariance:
    """A validated ``PoseWithCovariance``: ``orientation`` (x, y, z, w), ``covariance`` 6 × 6 or None."""
    msg = PoseWithCovariance(frame_id=frame_id)
    msg.position.x, msg.position.y, msg.position.z = (float(v) for v in position)
    o = msg.orientation
    o.x, o.y, o.z, o.w = (float(v) for v in orientation)
    if covariance is not None:
        msg.covariance.extend(float(v) for v in np.asarray(covariance, dtype=float).reshape(36))
    validate_pose("pose", msg)
    return msg
