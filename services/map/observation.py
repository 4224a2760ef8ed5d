"""What the map takes in: one scan's pose and the walls, corners and edges it saw, in its own frame.

Frames
------
* **World**: the map's frame, z up; headings counter-clockwise from +x.
* **Sensor** (of one scan): the level frame at the scanner: origin at the pose's ``(x, y)``, x along the
  heading, z up.  A scanner mounted with a tilt has its observations turned into this frame by the
  adapter that builds them (see :mod:`lelsonar.map.from_reconstruction`).

Every length is in m, every angle in rad.  Arrays are validated on construction: a wrong observation is
an :class:`~lelsonar.errors.InvalidMessageError` naming the field, never a wall in the map.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from lelsonar.errors import InvalidMessageError

#: The verdicts a wall observation can carry, best first (the reconstruction's PlaneQuality names).
QUALITIES = ("good", "degraded", "unreliable")

#: A wall is vertical: its sensor-frame normal may lean at most this far out of the floor plane.
MAX_WALL_TILT = math.radians(30.0)


def _matrix(value, shape: tuple[int, int], name: str) -> np.ndarray:
    m = np.array(value, dtype=float)
    if m.shape != shape:
        raise InvalidMessageError(f"{name} must be a {shape[0]}×{shape[1]} matrix, got shape {m.shape}")
    if not np.all(np.isfinite(m)):
        raise InvalidMessageError(f"{name} holds a non-finite number")
    if not np.allclose(m, m.T, atol=1e-12 + 1e-9 * np.abs(m).max()):
        raise InvalidMessageError(f"{name} must be symmetric")
    if np.linalg.eigvalsh(m).min() < -1e-12 * max(1.0, np.abs(m).max()):
        raise InvalidMessageError(f"{name} must be positive semi-definite")
    m.setflags(write=False)
    return m


def _points(value, name: str) -> np.ndarray:
    p = np.array(value, dtype=float).reshape(-1, 3) if np.size(value) else np.zeros((0, 3))
    if not np.all(np.isfinite(p)):
        raise InvalidMessageError(f"{name} holds a non-finite coordinate")
    p.setflags(write=False)
    return p


def _vector(value, name: str, *, unit: bool = False) -> np.ndarray:
    v = np.array(value, dtype=float)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise InvalidMessageError(f"{name} must be 3 finite numbers, got {value!r}")
    if unit:
        norm = float(np.linalg.norm(v))
        if abs(norm - 1.0) > 1e-6:
            raise InvalidMessageError(f"{name} must be a unit vector, its norm is {norm:.6g}")
    v.setflags(write=False)
    return v


@dataclass(frozen=True, eq=False)
class Pose2D:
    """Where the scanner was, as odometry says (world frame).

    Parameters
    ----------
    x, y : float
        Position of the sensor frame's origin, m.
    heading : float
        Yaw of the sensor frame, rad, counter-clockwise from +x.
    z : float
        Height of the sensor frame's origin, m (carried to the walls' extents; not estimated).
    covariance : (3, 3) array or None
        Covariance of ``(x, y, heading)`` as odometry reports it: growing with the distance travelled.
        None when the source gives none (then the map assumes the pose exact and says so).
    """

    x: float
    y: float
    heading: float
    z: float = 0.0
    covariance: np.ndarray | None = None

    def __post_init__(self) -> None:
        for name in ("x", "y", "heading", "z"):
            if not math.isfinite(getattr(self, name)):
                raise InvalidMessageError(f"pose {name} must be finite, got {getattr(self, name)!r}")
        if self.covariance is not None:
            object.__setattr__(self, "covariance", _matrix(self.covariance, (3, 3), "pose covariance"))

    @property
    def vector(self) -> np.ndarray:
        """``(x, y, heading)``."""
        return np.array([self.x, self.y, self.heading])


@dataclass(frozen=True, eq=False)
class WallObservation:
    """One planar surface a scan saw, in the scan's sensor frame.

    Parameters
    ----------
    normal : array of 3
        Unit normal, pointing away from the scanner (into the wall).
    offset : float
        ``normal · p = offset`` for the points ``p`` of the wall, m.
    covariance : (2, 2) array
        Covariance of ``(θ, ρ)``: ``θ`` the normal's azimuth ``atan2(n_y, n_x)`` (rad), ``ρ`` the
        offset of the wall's trace on the floor plane (m).  A wall well placed in range can be poorly
        placed in bearing: give the σ its true shape.
    extent : (k, 3) array
        Points of the observed patch (its corners), m; ``k ≥ 1``.
    quality : str
        ``"good"``, ``"degraded"`` or ``"unreliable"``: the extractor's verdict.
    reasons : tuple of str
        Why the verdict is not good.
    label : str
        The extractor's name for the surface (for messages).
    """

    normal: np.ndarray
    offset: float
    covariance: np.ndarray
    extent: np.ndarray
    quality: str = "good"
    reasons: tuple[str, ...] = ()
    label: str = ""

    def __post_init__(self) -> None:
        object.__setattr__(self, "normal", _vector(self.normal, f"wall {self.label!r} normal", unit=True))
        if not math.isfinite(self.offset):
            raise InvalidMessageError(f"wall {self.label!r} offset must be finite, got {self.offset!r}")
        object.__setattr__(self, "covariance", _matrix(self.covariance, (2, 2), f"wall {self.label!r} covariance"))
        if np.linalg.eigvalsh(self.covariance).min() <= 0.0:
            raise InvalidMessageError(f"wall {self.label!r} covariance must be positive definite (give its σ)")
        object.__setattr__(self, "extent", _points(self.extent, f"wall {self.label!r} extent"))
        if len(self.extent) == 0:
            raise InvalidMessageError(f"wall {self.label!r} needs at least one extent point (its observed patch)")
        if self.quality not in QUALITIES:
            raise InvalidMessageError(f"wall {self.label!r} quality must be one of {QUALITIES}, got {self.quality!r}")
        if math.asin(min(1.0, abs(float(self.normal[2])))) > MAX_WALL_TILT:
            raise InvalidMessageError(
                f"wall {self.label!r} is not vertical (normal z = {self.normal[2]:.3f}): "
                "pass floors and ceilings elsewhere"
            )
        object.__setattr__(self, "reasons", tuple(self.reasons))

    @property
    def line(self) -> np.ndarray:
        """``(θ, ρ)`` of the wall's trace on the floor plane, sensor frame."""
        h = math.hypot(self.normal[0], self.normal[1])
        return np.array([math.atan2(self.normal[1], self.normal[0]), self.offset / h])


@dataclass(frozen=True, eq=False)
class FeatureObservation:
    """A corner (two or three surfaces meeting) or a convex edge, in the scan's sensor frame.

    Parameters
    ----------
    point : array of 3
        A point of the feature's line, m.
    direction : array of 3
        Unit direction of the line.
    kind : str
        ``"concave"`` or ``"convex"`` for corners; ``"edge"`` for a convex (diffracting) edge.
    point_stderr : float
        Standard error of the point across the line, m.
    """

    point: np.ndarray
    direction: np.ndarray
    kind: str = "concave"
    point_stderr: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "point", _vector(self.point, "feature point"))
        object.__setattr__(self, "direction", _vector(self.direction, "feature direction", unit=True))
        if self.kind not in ("concave", "convex", "edge"):
            raise InvalidMessageError(f"feature kind must be concave, convex or edge, got {self.kind!r}")
        if not (math.isfinite(self.point_stderr) and self.point_stderr >= 0.0):
            raise InvalidMessageError(f"feature point_stderr must be ≥ 0 m, got {self.point_stderr!r}")


@dataclass(frozen=True, eq=False)
class ScanObservation:
    """One scan, as the map takes it.

    Parameters
    ----------
    scan_id : int
        The scan's id (unique in one map).
    pose : Pose2D
        The scanner's pose from odometry.
    walls : tuple of WallObservation
        Every vertical surface the scan saw.
    features : tuple of FeatureObservation
        Corners and edges the scan saw.
    step_covariance : (3, 3) array or None
        Covariance of the motion since the previous scan ``(δx, δy, δψ)``, in this pose's body frame (the
        tangent of the relative pose).  None: derived from the poses' covariances.
    notes : tuple of str
        What the source could not give (e.g. no pose recorded), carried into the map's notes.
    """

    scan_id: int
    pose: Pose2D
    walls: tuple[WallObservation, ...] = ()
    features: tuple[FeatureObservation, ...] = ()
    step_covariance: np.ndarray | None = None
    notes: tuple[str, ...] = field(default=())

    def __post_init__(self) -> None:
        if self.scan_id < 0:
            raise InvalidMessageError(f"scan_id must be ≥ 0, got {self.scan_id}")
        object.__setattr__(self, "walls", tuple(self.walls))
        object.__setattr__(self, "features", tuple(self.features))
        object.__setattr__(self, "notes", tuple(self.notes))
        if self.step_covariance is not None:
            object.__setattr__(self, "step_covariance", _matrix(self.step_covariance, (3, 3), "step covariance"))
