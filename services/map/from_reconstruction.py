"""A ``Reconstruction`` as the map's observation of one scan, at the pose of its ``ScanStart``: a thin adapter,
kept apart from the fusion.

What it takes: the sweep's surfaces, corners and edges where the reconstruction extracted them
(``surface_echo_count > 0``); the two planes of record of the L model otherwise (recordings made before
surfaces were extracted).  Where both came, a plane of record that vouches for a wall a surface alone
cannot (a better verdict on the same wall) stands for that surface.

A surface's σ keeps its shape: its covariance over (bearing, tilt, offset) is carried to the wall's
``(θ, ρ)`` to first order.  A wall is vertical, so its ``ρ`` is the surface's offset (a mirror's range is
its perpendicular distance whatever the tilt the stack read), and the tilt enters ``θ`` only through a
tilted mount.

Frames: a ``Reconstruction``'s planes are in the scan's array frame at γ = 0.  ``ScanStart.pose``, where
the recording has one, places that frame in the odometry's world frame (rotation and position, with the
6 × 6 covariance over ``(x, y, z, roll, pitch, yaw)``).  The robot's heading is the azimuth of the beams
at γ = 0 (the array frame's +y, ahead for every mount); the observation frame is the level frame turned
by that heading, so a tilted mount's planes are levelled before they become walls.
"""

from __future__ import annotations

import math

import numpy as np

from lelsonar import codec
from lelsonar.map.observation import (
    MAX_WALL_TILT,
    QUALITIES,
    FeatureObservation,
    Pose2D,
    ScanObservation,
    WallObservation,
)
from lelsonar.reconstruct.estimate.surfaces.features import kind_unsettled, placement_caveats

#: Smallest variance given to an observation's (θ, ρ), so a plane that claims none still has a σ (rad², m²).
MIN_VARIANCE = (1e-10, 1e-10)


def _vec(v) -> np.ndarray:
    return np.array([v.x, v.y, v.z], dtype=float)


def _quaternion_matrix(x: float, y: float, z: float, w: float) -> np.ndarray:
    n = math.sqrt(x * x + y * y + z * z + w * w)
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def level_heading(rotation: np.ndarray) -> float:
    """The heading of an array frame placed by ``rotation`` (world ← array): the azimuth of its +y."""
    ahead = rotation[:, 1]
    return math.atan2(ahead[1], ahead[0])


def planar_pose(rotation: np.ndarray, position: np.ndarray, covariance: np.ndarray | None) -> Pose2D:
    """The planar pose of an array frame placed by ``rotation`` (world ← array) at ``position``.

    Parameters
    ----------
    covariance : (6, 6) array or None
        Over ``(x, y, z, rotation about x, y, z)`` in the world frame (ROS's order); its ``(x, y, yaw)``
        block is the pose's.  None, or all zeros: unknown.
    """
    cov = None
    if covariance is not None and np.any(covariance):
        cov = np.asarray(covariance, dtype=float)[np.ix_([0, 1, 5], [0, 1, 5])]
    return Pose2D(float(position[0]), float(position[1]), level_heading(rotation), float(position[2]), cov)


def scan_pose(start: codec.ScanStart) -> tuple[np.ndarray, Pose2D, str | None]:
    """The array frame's rotation (world ← array), the scan's planar pose, and a note when the start has no pose.

    A ``ScanStart`` without a pose (older recordings) is taken at the origin of the world, the array frame
    unturned, and the note says so.
    """
    if not start.HasField("pose"):
        rot = np.eye(3)
        note = f"scan {start.scan_id} has no pose in its ScanStart: taken at the origin"
        return rot, planar_pose(rot, np.zeros(3), None), note
    pose = start.pose
    q = pose.orientation
    rot = _quaternion_matrix(q.x, q.y, q.z, q.w)
    cov6 = np.array(pose.covariance, dtype=float)
    return rot, planar_pose(rot, _vec(pose.position), cov6.reshape(6, 6) if cov6.size == 36 else None), None


def _wall(plane, to_level: np.ndarray) -> WallObservation | None:
    """One plane of record as a wall in the level frame, or None for a horizontal plane (floor, ceiling)."""
    n = to_level @ _vec(plane.normal)
    n /= np.linalg.norm(n)
    if math.asin(min(1.0, abs(float(n[2])))) > MAX_WALL_TILT:
        return None
    h2 = float(n[0] ** 2 + n[1] ** 2)
    cov = np.diag([plane.normal_stderr**2, (plane.offset_stderr / math.sqrt(h2)) ** 2])
    if len(plane.theta_covariance) == 9 and plane.offset > 0:
        # θ = n / d (the paper's parameter vector); φ = atan2(θ_y, θ_x), ρ = 1 / |θ_xy| in the level frame.
        c_theta = to_level @ np.array(plane.theta_covariance, dtype=float).reshape(3, 3) @ to_level.T
        a, b = n[0] / plane.offset, n[1] / plane.offset
        r2 = a * a + b * b
        jac = np.array([[-b / r2, a / r2, 0.0], [-a / r2**1.5, -b / r2**1.5, 0.0]])
        full = jac @ c_theta @ jac.T
        if np.all(np.isfinite(full)) and np.linalg.eigvalsh(full).min() > 0:
            cov = full
    cov = cov + np.diag(MIN_VARIANCE)
    return _wall_observation(plane, n, 0.5 * (cov + cov.T), to_level, plane.label)


def _wall_observation(plane, normal: np.ndarray, cov: np.ndarray, to_level: np.ndarray, label: str) -> WallObservation:
    """A plane message as a wall: its patch levelled (its foot at ``offset`` along ``normal`` without one), and
    its verdict (none given: degraded, saying so)."""
    patch = np.array([to_level @ _vec(p) for p in plane.patch]).reshape(-1, 3)
    if len(patch) == 0:
        patch = (plane.offset * normal)[None, :]
    quality = codec.QUALITY_NAME.get(plane.quality, "unassessed")
    reasons = tuple(plane.quality_reasons)
    if quality == "unassessed":
        quality, reasons = "degraded", reasons + ("the reconstruction gave no verdict",)
    return WallObservation(
        normal=normal,
        offset=float(plane.offset),
        covariance=cov,
        extent=patch,
        quality=quality,
        reasons=reasons,
        label=label,
    )


def fan_direction(bearing: float, tilt: float) -> np.ndarray:
    """A surface's unit normal in the array frame from its bearing in the fan and its tilt along the stack (x).

    ``(sin τ, cos τ cos β, cos τ sin β)``: the ``SurfaceEstimate`` convention (β = 0 along +y, γ = 0).
    """
    c = math.cos(tilt)
    return np.array([math.sin(tilt), c * math.cos(bearing), c * math.sin(bearing)])


def _azimuth(normal_array: np.ndarray, to_level: np.ndarray) -> float:
    n = to_level @ normal_array
    return math.atan2(float(n[1]), float(n[0]))


def surface_line_covariance(bearing: float, tilt: float, covariance: np.ndarray, to_level: np.ndarray) -> np.ndarray:
    """Covariance of a vertical wall's ``(θ, ρ)`` from its surface's over (bearing, tilt, offset), first order.

    ``θ`` is the azimuth of ``to_level · n(β, τ)`` (:func:`fan_direction`), differentiated by central
    differences; ``ρ`` is the offset.
    """
    eps = 1e-6
    jac = np.zeros((2, 3))
    for k, (db, dt) in enumerate(((eps, 0.0), (0.0, eps))):
        hi = _azimuth(fan_direction(bearing + db, tilt + dt), to_level)
        lo = _azimuth(fan_direction(bearing - db, tilt - dt), to_level)
        jac[0, k] = math.remainder(hi - lo, 2 * math.pi) / (2 * eps)
    jac[1, 2] = 1.0
    return jac @ covariance @ jac.T


def _surface_wall(item, to_level: np.ndarray) -> WallObservation | None:
    """One extracted surface as a wall in the level frame, or None for a horizontal one (floor, ceiling)."""
    plane = item.plane
    n_array = _vec(plane.normal)
    n = to_level @ n_array
    n /= np.linalg.norm(n)
    if math.asin(min(1.0, abs(float(n[2])))) > MAX_WALL_TILT:
        return None
    cov3 = np.array(item.covariance, dtype=float).reshape(3, 3) if len(item.covariance) == 9 else None
    matches = np.linalg.norm(fan_direction(item.bearing, item.tilt) - n_array / np.linalg.norm(n_array)) < 1e-6
    if cov3 is not None and np.all(np.isfinite(cov3)) and matches:
        cov = surface_line_covariance(item.bearing, item.tilt, cov3, to_level)
    else:
        cov = np.diag([plane.normal_stderr**2, plane.offset_stderr**2])
    if not np.all(np.isfinite(cov)):
        cov = np.diag([(math.pi / 2) ** 2, max(plane.offset_stderr, 0.1) ** 2])
    cov = 0.5 * (cov + cov.T) + np.diag(MIN_VARIANCE)
    # Level the normal: the wall is vertical, its trace is at the range the mirror gave.
    h = math.hypot(float(n[0]), float(n[1]))
    vertical = np.array([n[0] / h, n[1] / h, 0.0])
    return _wall_observation(plane, vertical, cov, to_level, item.label or plane.label)


def _feature(f, kind: str, to_level: np.ndarray) -> FeatureObservation | None:
    # A corner or an edge its sweep did not place on its own line, or whose kind it did not settle (its reasons say
    # so), ties no walls and ends none.
    if placement_caveats(f.reasons) or kind_unsettled(f.reasons):
        return None
    d = to_level @ _vec(f.line.direction)
    if not np.linalg.norm(d) > 0:
        return None
    return FeatureObservation(
        point=to_level @ _vec(f.line.point),
        direction=d / np.linalg.norm(d),
        kind=kind,
        point_stderr=max(float(f.line.point_stderr), 0.0),
    )


#: An L plane of record is the same wall as a surface when their normals and offsets agree this well (rad, m).
SAME_WALL = (math.radians(3.0), 0.03)


def _better_of(surface: WallObservation, planes: list[WallObservation]) -> WallObservation:
    """The surface, or the L plane of record on the same wall where that one has the better verdict (the
    joint corner model of an L scan fits both walls at once: where it vouches for a wall and the surface
    alone cannot, its fit is the scan's)."""
    rank = QUALITIES.index(surface.quality)
    for plane in planes:
        d_theta = abs(math.remainder(float(plane.line[0] - surface.line[0]), 2 * math.pi))
        if d_theta <= SAME_WALL[0] and abs(float(plane.line[1] - surface.line[1])) <= SAME_WALL[1]:
            if QUALITIES.index(plane.quality) < rank:
                return plane
    return surface


def has_surfaces(msg: codec.Reconstruction) -> bool:
    """Whether the reconstruction extracted the sweep's surfaces (then they, not the L planes, are its walls)."""
    return msg.surface_echo_count > 0 or len(msg.surfaces) > 0


def scan_from_reconstruction(
    msg: codec.Reconstruction, start: codec.ScanStart | None, method: str, scan_id: int | None = None
) -> ScanObservation:
    """A scan's surfaces (or planes of record of ``method``) as the map's observation, at its start's pose."""
    if start is None:
        rot = np.eye(3)
        pose = planar_pose(rot, np.zeros(3), None)
        note: str | None = f"scan {msg.scan_id}: no ScanStart came with it: taken at the origin"
    else:
        rot, pose, note = scan_pose(start)
    return observation_at(msg, rot, pose, method, (note,) if note else (), scan_id)


def observation_at(
    msg: codec.Reconstruction,
    rotation: np.ndarray,
    pose: Pose2D,
    method: str,
    notes: tuple[str, ...] = (),
    scan_id: int | None = None,
) -> ScanObservation:
    """A scan's surfaces, corners and edges (or, without them, its planes of record of ``method`` and their
    corner edge), seen from an array frame placed by ``rotation`` (world ← array) at ``pose``, as the map's
    observation.

    Horizontal planes (a floor, a ceiling) are not walls of a floor plan: they are left out, and named in
    the observation's notes.
    """
    notes_out = list(notes)
    c, s = math.cos(pose.heading), math.sin(pose.heading)
    to_level = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]]) @ rotation
    walls, horizontal = [], []
    features: list[FeatureObservation] = []
    if has_surfaces(msg):
        for item in msg.surfaces:
            wall = _surface_wall(item, to_level)
            if wall is None:
                horizontal.append(item.label)
            else:
                walls.append(wall)
        for group, kind in ((msg.corners, "concave"), (msg.edges, "edge")):
            features.extend(f for f in (_feature(x, kind, to_level) for x in group) if f is not None)
        planes = [w for w in (_wall(p, to_level) for p in msg.planes if p.method == method) if w is not None]
        walls = [_better_of(w, planes) for w in walls]
    else:
        for plane in msg.planes:
            if plane.method != method:
                continue
            wall = _wall(plane, to_level)
            if wall is None:
                horizontal.append(plane.label)
            else:
                walls.append(wall)
        if msg.HasField("corner_edge") and walls:
            e = msg.corner_edge
            d = to_level @ _vec(e.direction)
            if np.linalg.norm(d) > 0:
                features.append(
                    FeatureObservation(
                        point=to_level @ _vec(e.point),
                        direction=d / np.linalg.norm(d),
                        kind="concave",
                        point_stderr=max(float(e.point_stderr), 0.0),
                    )
                )
    if horizontal:
        notes_out.append(f"scan {msg.scan_id}: plane {', '.join(horizontal)} horizontal (floor or ceiling), not a wall")
    return ScanObservation(
        scan_id=int(msg.scan_id if scan_id is None else scan_id),
        pose=pose,
        walls=tuple(walls),
        features=tuple(features),
        notes=tuple(notes_out),
    )
