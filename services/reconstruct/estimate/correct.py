"""Data points and the paper's reflection-direction correction (§3–4, eq. 9, Fig. 7).

A mirror echo from a flat wall travels along the wall's normal, not along the
boresight, and its range is the perpendicular distance from the capsule to the
wall.  Plotting it along the boresight (eq. 9) bends the wall
into an arc (the paper's "curvature", Fig. 3).  The paper corrects the ranges
assuming the subset lies on an axis-aligned plane — ``y = const`` before the
corner, ``z = const`` after — and places each point where its beam meets that
plane, at range ``d / cos α`` with α the angle between the boresight and the
plane's normal.  On an axis-aligned wall this puts every mirror echo exactly on
the wall; on a tilted wall it is biased (the tilt is lost), which is what
:func:`lelsonar.reconstruct.estimate.fit.constant_depth_fit` fixes.
"""

from __future__ import annotations

import numpy as np

from lelsonar.errors import ConfigError
from lelsonar.geometry import ArrayGeometry, beam_points, boresight
from lelsonar.signal.compiled import kernel

__all__ = [
    "AXIS_Y",
    "AXIS_Z",
    "MAX_CORRECTION_ANGLE",
    "COS_MAX_CORRECTION",
    "corrected_points",
    "corrected_from",
    "mirror_points",
    "beam_points",
]

#: Normal of plane ``a`` assumed by the paper's correction (plane y = const).
AXIS_Y = np.array([0.0, 1.0, 0.0])
#: Normal of plane ``b`` assumed by the paper's correction (plane z = const).
AXIS_Z = np.array([0.0, 0.0, 1.0])
#: The largest angle between a beam and the assumed normal that is corrected (rad; ``1/cos α`` explodes beyond).
MAX_CORRECTION_ANGLE = float(np.deg2rad(80.0))
#: Its cosine, as the fits pass it to :func:`corrected_point`.
COS_MAX_CORRECTION = float(np.cos(MAX_CORRECTION_ANGLE))


def corrected_points(
    geometry: ArrayGeometry,
    gamma: np.ndarray,
    distance: np.ndarray,
    axis: np.ndarray,
    *,
    max_angle: float = MAX_CORRECTION_ANGLE,
) -> np.ndarray:
    """The paper's corrected data points (§4, Fig. 7).

    ``v = p_c + (d / cos α) · b(γ)`` with ``b = (0, cos γ, sin γ)`` the
    boresight and ``cos α = b · axis``.  Equivalently, the component of ``v``
    along ``axis`` is ``axis · p_c + d``, the wall position implied by a mirror
    echo from a wall with that normal.

    Parameters
    ----------
    geometry : ArrayGeometry
    gamma : (n_steps,) array, rad
    distance : (n_steps, n_capsules) array, m (NaN = no echo)
    axis : (3,) array
        The assumed normal (``AXIS_Y`` for plane ``a``, ``AXIS_Z`` for ``b``).
    max_angle : float
        Beams more than this far from ``axis`` (rad) give NaN: ``1/cos α``
        explodes there and no mirror echo can come from such a wall anyway.

    Returns
    -------
    (n_steps, n_capsules, 3) array
        NaN where there is no echo or the beam is too oblique.
    """
    g = np.asarray(gamma, dtype=np.float64)
    d = np.asarray(distance, dtype=np.float64)
    if d.shape != g.shape + (geometry.n_capsules,):
        raise ConfigError(f"distance must have shape {g.shape + (geometry.n_capsules,)}, got {d.shape}")
    return corrected_from(geometry.capsule_positions(g), boresight(g), d, axis, max_angle=max_angle)


def corrected_from(
    capsules: np.ndarray,
    beam: np.ndarray,
    distance: np.ndarray,
    axis: np.ndarray,
    *,
    max_angle: float = MAX_CORRECTION_ANGLE,
) -> np.ndarray:
    """:func:`corrected_points` from the capsule positions and boresights the caller has already computed.

    Parameters
    ----------
    capsules : (n_steps, n_capsules, 3) array
        ``p_c`` (:meth:`lelsonar.geometry.ArrayGeometry.capsule_positions`), m.
    beam : (n_steps, 3) array
        ``b(γ)`` (:func:`lelsonar.geometry.boresight`).
    distance : (n_steps, n_capsules) array, m (NaN = no echo)
    axis : (3,) array
    max_angle : float, rad

    Returns
    -------
    (n_steps, n_capsules, 3) array
    """
    ax = np.asarray(axis, dtype=np.float64)
    ax = ax / np.linalg.norm(ax)
    p = np.asarray(capsules, dtype=np.float64)
    b = np.asarray(beam, dtype=np.float64)
    d = np.asarray(distance, dtype=np.float64)
    n_caps = p.shape[-2]
    out = _corrected(
        np.ascontiguousarray(p.reshape(-1, n_caps, 3)),
        np.ascontiguousarray(b.reshape(-1, 3)),
        np.ascontiguousarray(d.reshape(-1, n_caps)),
        ax,
        float(np.cos(max_angle)),
    )
    return out.reshape(p.shape)


@kernel
def corrected_point(
    capsule: np.ndarray, beam: np.ndarray, distance: float, axis: np.ndarray, cos_max: float, out: np.ndarray
) -> None:
    """The paper's corrected point (§4, Fig. 7) of one echo, into ``out``: ``p_c + (d / cos α) b``.

    ``cos α = b · axis`` (``axis`` a unit vector); NaN where ``cos α ≤ cos_max`` (too oblique) or ``d`` is NaN.
    """
    cos_a = beam[0] * axis[0] + beam[1] * axis[1] + beam[2] * axis[2]
    if cos_a > cos_max:
        s = distance * (1.0 / cos_a)
        for u in range(3):
            out[u] = capsule[u] + s * beam[u]
    else:
        out[:] = np.nan


@kernel
def _corrected(
    capsules: np.ndarray, beam: np.ndarray, distance: np.ndarray, axis: np.ndarray, cos_max: float
) -> np.ndarray:
    """:func:`corrected_point` of every slot of (k, c) ranges (``capsules`` (k, c, 3), ``beam`` (k, 3))."""
    k, c = distance.shape
    out = np.empty((k, c, 3))
    for i in range(k):
        for j in range(c):
            corrected_point(capsules[i, j], beam[i], distance[i, j], axis, cos_max, out[i, j])
    return out


def mirror_points(geometry: ArrayGeometry, gamma: np.ndarray, distance: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Foot points of mirror echoes on a wall with unit ``normal``: ``p_c + d · n``.

    The mirror-echo condition ``n · p_c + d = h`` puts these
    points exactly on the wall ``n · x = h``.  Used by the constant-depth model
    and as the benchmark's oracle points.

    Returns
    -------
    (n_steps, n_capsules, 3) array
    """
    g = np.asarray(gamma, dtype=np.float64)
    d = np.asarray(distance, dtype=np.float64)
    n = np.asarray(normal, dtype=np.float64)
    return geometry.capsule_positions(g) + d[..., None] * (n / np.linalg.norm(n))
