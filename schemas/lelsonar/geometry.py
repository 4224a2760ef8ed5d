"""Frames of the scanner, shared by the simulator, the acquisition and the reconstruction.

Conventions (the paper's Fig. 1 and eq. 9):

* World frame: x is the rotation axis; at γ = 0 the beams point along +y; at
  γ = 90° they point along +z.  Units are metres and radians.
* Array frame: the world frame rotated by γ about x.  Capsule ``i`` sits at
  ``(x_i, r, 0)`` in the array frame, where ``r`` is the radial offset of the
  capsule faces from the axis, and its boresight is ``(0, 1, 0)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lelsonar.errors import ConfigError

#: Capsule pitch along the axis (paper §3: 8 cm).
CAPSULE_PITCH_M = 0.08


def rotation_x(gamma: np.ndarray | float) -> np.ndarray:
    """Rotation matrices about x by ``gamma`` (rad); shape ``(..., 3, 3)``."""
    g = np.asarray(gamma, dtype=float)
    if g.ndim == 0:
        # One angle (a turn of the corner model's axes): the same matrix without the four stacks.
        c, s = np.cos(g), np.sin(g)
        return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    c, s = np.cos(g), np.sin(g)
    one, zero = np.ones_like(g), np.zeros_like(g)
    return np.stack(
        [
            np.stack([one, zero, zero], axis=-1),
            np.stack([zero, c, -s], axis=-1),
            np.stack([zero, s, c], axis=-1),
        ],
        axis=-2,
    )


def boresight(gamma: np.ndarray | float) -> np.ndarray:
    """Unit beam directions ``(0, cos γ, sin γ)`` for each γ; shape ``(..., 3)``."""
    g = np.asarray(gamma, dtype=float)
    # Written in place: the same numbers as stacking zeros, cos γ and sin γ, without the stack's copies
    # (every scan's fit builds these).
    out = np.empty(g.shape + (3,))
    out[..., 0] = 0.0
    np.cos(g, out=out[..., 1])
    np.sin(g, out=out[..., 2])
    return out


@dataclass(frozen=True)
class ArrayGeometry:
    """Where the capsules are on the rotating array.

    Parameters
    ----------
    capsule_x : tuple of float
        Position of each capsule along the rotation axis, m.
    radial_offset : float
        Distance of the capsule faces from the rotation axis, m.
    """

    capsule_x: tuple[float, ...] = (
        -1.5 * CAPSULE_PITCH_M,
        -0.5 * CAPSULE_PITCH_M,
        0.5 * CAPSULE_PITCH_M,
        1.5 * CAPSULE_PITCH_M,
    )
    radial_offset: float = 0.03

    def __post_init__(self) -> None:
        if not 1 <= len(self.capsule_x) <= 16:
            raise ConfigError(f"an array needs 1 to 16 capsules, got {len(self.capsule_x)}")
        if not all(np.isfinite(self.capsule_x)):
            raise ConfigError("capsule positions must be finite numbers (m)")
        if not (np.isfinite(self.radial_offset) and 0.0 <= self.radial_offset < 0.5):
            raise ConfigError(f"radial_offset must be in [0, 0.5) m, got {self.radial_offset!r}")

    @property
    def n_capsules(self) -> int:
        return len(self.capsule_x)

    def capsules_in_array_frame(self) -> np.ndarray:
        """Capsule positions in the array frame, shape ``(n_capsules, 3)``."""
        x = np.asarray(self.capsule_x, dtype=float)
        return np.stack([x, np.full_like(x, self.radial_offset), np.zeros_like(x)], axis=-1)

    def capsule_positions(self, gamma: np.ndarray | float, beam: np.ndarray | None = None) -> np.ndarray:
        """World positions ``(x^c, y^c, z^c)`` of every capsule at each γ (eq. 9).

        Returns shape ``(..., n_capsules, 3)`` for ``gamma`` of shape ``(...)``.  ``beam``: the
        :func:`boresight` of ``gamma``, if the caller has it (its cos γ and sin γ are used, not
        computed again: the same numbers).
        """
        # R·c for a capsule c = (x, r, 0) of the array frame is (x, r cos γ, r sin γ): the products the matmul
        # c·Rᵀ forms, without its zero terms (the same numbers, bit for bit; on every fit's path).
        g = np.asarray(gamma, dtype=float)
        if beam is None:
            cos_g, sin_g = np.cos(g), np.sin(g)
        else:
            cos_g, sin_g = beam[..., 1], beam[..., 2]
        x = np.asarray(self.capsule_x, dtype=float)
        out = np.empty(g.shape + (x.size, 3))
        out[..., 0] = x
        out[..., 1] = self.radial_offset * cos_g[..., None]
        out[..., 2] = self.radial_offset * sin_g[..., None]
        return out


def beam_points(geometry: ArrayGeometry, gamma: np.ndarray, distance: np.ndarray) -> np.ndarray:
    """Raw data points along each beam, the paper's eq. (9).

    Parameters
    ----------
    geometry : ArrayGeometry
    gamma : (n_steps,) array
        Measured rotation per step, rad.
    distance : (n_steps, n_capsules) array
        Range of each capsule, m (NaN where no echo).

    Returns
    -------
    (n_steps, n_capsules, 3) array
        ``v = p_c(γ) + d · (0, cos γ, sin γ)``.
    """
    gamma = np.asarray(gamma, dtype=float)
    distance = np.asarray(distance, dtype=float)
    origins = geometry.capsule_positions(gamma)
    return origins + distance[..., None] * boresight(gamma)[..., None, :]


def beam_points_from_capsules(
    positions: np.ndarray, boresights: np.ndarray, gamma: np.ndarray, distance: np.ndarray
) -> np.ndarray:
    """Eq. (9) for capsules given in the array frame, as a ``ScanStart`` lists them.

    Parameters
    ----------
    positions, boresights : (n_capsules, 3) arrays
        Capsule positions (m) and unit beam directions in the array frame.
    gamma : (...) array
        Rotation about x, rad.
    distance : (..., n_capsules) array
        Ranges, m.

    Returns
    -------
    (..., n_capsules, 3) array
    """
    rot = rotation_x(gamma)
    origins = np.einsum("...ij,kj->...ki", rot, np.asarray(positions, dtype=float))
    beams = np.einsum("...ij,kj->...ki", rot, np.asarray(boresights, dtype=float))
    return origins + np.asarray(distance, dtype=float)[..., None] * beams


# ---------------------------------------------------------------------------- frames of a moving robot
#: Mounts of the array on a robot: ``fan`` (rotation axis vertical) and ``paper`` (axis horizontal).
MOUNTS = ("fan", "paper")


def mount_rotation(mount: str) -> np.ndarray:
    """Rotation base ← array of a mount: its columns are the array frame's axes in the robot's base frame.

    The base frame is the robot's (x ahead, y to the left, z up, as ROS's ``base_link``); the array
    frame is the one above at γ = 0.

    * ``paper``: the rotation axis x points to the robot's right, the beams look ahead at γ = 0 and
      straight up at γ = 90° (the paper's rig, seeing a wall ahead and the ceiling).
    * ``fan``: the rotation axis x points up, the beams look ahead at γ = 0 and to the left at
      γ = 90°: a horizontal fan turning counter-clockwise seen from above, the capsules stacked
      vertically.

    Raises
    ------
    ConfigError
        For an unknown mount.
    """
    if mount == "fan":
        return np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    if mount == "paper":
        return np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    raise ConfigError(f"unknown mount {mount!r}; choose one of {', '.join(MOUNTS)}")


def rotation_z(angle: float) -> np.ndarray:
    """Rotation about z by ``angle`` (rad), 3×3."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def quaternion_from_matrix(rot: np.ndarray) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation matrix, with w ≥ 0 (Shepperd's method, stable for every rotation)."""
    m = np.asarray(rot, dtype=float)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = ((m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s)
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = (0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s)
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = ((m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s)
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = ((m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s)
    arr = np.array(q, dtype=float)
    arr /= np.linalg.norm(arr)
    if arr[3] < 0:
        arr = -arr
    return float(arr[0]), float(arr[1]), float(arr[2]), float(arr[3])


def matrix_from_quaternion(q) -> np.ndarray:
    """Rotation matrix of a unit quaternion (x, y, z, w)."""
    x, y, z, w = (float(v) for v in q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def tilt_rotation(tilt: float) -> np.ndarray:
    """Rotation of a mount tilted by ``tilt`` (rad) about the robot's lateral axis (base y), 3×3: the robot's
    ahead (base x) turns up by ``tilt`` (down for a negative tilt), its up (base z) leans back."""
    c, s = np.cos(tilt), np.sin(tilt)
    return np.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]])


def array_pose(
    x: float, y: float, heading: float, mount: str, height: float, tilt: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Pose of the array frame (γ = 0) in a world frame, for a robot at floor point (x, y) with ``heading``,
    the mount tilted by ``tilt`` (rad, :func:`tilt_rotation`) about the robot's lateral axis.

    Returns
    -------
    rotation : (3, 3) array
        world ← array; a point ``p`` of the array frame is at ``rotation @ p + translation``.
    translation : (3,) array
        The array frame's origin (on the rotation axis, ``height`` above the floor), m.
    """
    if tilt == 0.0:
        return rotation_z(heading) @ mount_rotation(mount), np.array([x, y, height], dtype=float)
    return rotation_z(heading) @ tilt_rotation(tilt) @ mount_rotation(mount), np.array([x, y, height], dtype=float)


def beam_heading(orientation) -> float:
    """Heading (rad, counter-clockwise from +x) of an array's γ = 0 beam, the frame's +y, projected on the floor.

    ``orientation`` is the array frame's (x, y, z, w) in a z-up world frame.
    """
    beam = matrix_from_quaternion(orientation)[:, 1]
    return float(np.arctan2(beam[1], beam[0]))
