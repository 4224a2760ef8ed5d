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
