"""A tiny geometric L-corner scan generator for the tests (no waveforms).

Not a simulator (that is :mod:`lelsonar.sim`): just the mirror-echo and
corner-echo geometry of the design notes §8, so the reconstruction math can be
tested on its own.

* A wall ``n · x = h`` echoes a capsule at ``p_c`` only if ``n`` is within
  ``beam_half_angle`` of the boresight; the range is ``h − n · p_c``.
* The corner (two bounces) echoes if the perpendicular from the capsule to
  the edge is within the beam; the range is the distance to the edge.
* The first (shortest) echo wins; Gaussian range noise is added.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lelsonar.energy_model import EnergyModel
from lelsonar.geometry import ArrayGeometry, boresight

__all__ = ["WALL_A", "WALL_B", "CORNER", "NONE", "SyntheticScan", "synthetic_corner_scan", "tilted_normal"]

WALL_A, WALL_B, CORNER, NONE = 0, 1, 2, 3


def tilted_normal(base: np.ndarray, tilt_yz: float = 0.0, tilt_x: float = 0.0) -> np.ndarray:
    """Rotate ``base`` by ``tilt_yz`` about x, then lean it by ``tilt_x`` towards +x (rad)."""
    b = np.asarray(base, dtype=np.float64)
    c, s = np.cos(tilt_yz), np.sin(tilt_yz)
    n = np.array([b[0], c * b[1] - s * b[2], s * b[1] + c * b[2]])
    n = np.cos(tilt_x) * n + np.sin(tilt_x) * np.array([1.0, 0.0, 0.0])
    return n / np.linalg.norm(n)


@dataclass(frozen=True)
class SyntheticScan:
    gamma: np.ndarray
    distance: np.ndarray  # (n, k), NaN = no echo
    source: np.ndarray  # (n, k) WALL_A / WALL_B / CORNER / NONE
    sensor_energy: np.ndarray  # (n, k)
    normals: tuple[np.ndarray, np.ndarray]
    offsets: tuple[float, float]
    critical_step: int


def synthetic_corner_scan(
    geometry: ArrayGeometry,
    *,
    rng: np.random.Generator,
    n_steps: int = 184,
    gamma_range: tuple[float, float] = (np.deg2rad(-10), np.deg2rad(110)),
    normal_a: np.ndarray = (0.0, 1.0, 0.0),
    offset_a: float = 1.57,
    normal_b: np.ndarray = (0.0, 0.0, 1.0),
    offset_b: float = 1.06,
    beam_half_angle: float = np.deg2rad(26.0),
    noise: float = 0.002,
    energy_model: EnergyModel | None = None,
) -> SyntheticScan:
    """Ranges of a rotating scan in front of an L corner (see the module doc).

    The synthetic energy is ``E0(d) · g`` per capsule with ``g = 4 cos⁴⁰(angle to the edge)`` for
    corner echoes and ``g = cos²(off-axis angle)`` for walls, so ``R`` peaks at the
    corner step nearest the edge direction.
    """
    g = np.linspace(gamma_range[0], gamma_range[1], n_steps)
    na = np.asarray(normal_a, dtype=np.float64) / np.linalg.norm(normal_a)
    nb = np.asarray(normal_b, dtype=np.float64) / np.linalg.norm(normal_b)
    pc = geometry.capsule_positions(g)  # (n, k, 3)
    b = boresight(g)[:, None, :]
    cos_w = np.cos(beam_half_angle)
    ranges = np.full(pc.shape[:2] + (3,), np.inf)
    for j, (n, h) in enumerate(((na, offset_a), (nb, offset_b))):
        ca = np.einsum("nkj,j->nk", np.broadcast_to(b, pc.shape), n)
        ranges[..., j] = np.where(ca >= cos_w, h - pc @ n, np.inf)
    # Edge line: intersection of the planes.
    e_dir = np.cross(na, nb)
    e_dir /= np.linalg.norm(e_dir)
    e_pt = np.linalg.solve(np.stack([na, nb, e_dir]), np.array([offset_a, offset_b, 0.0]))
    rel = e_pt - pc
    perp = rel - (rel @ e_dir)[..., None] * e_dir
    dist_edge = np.linalg.norm(perp, axis=-1)
    ca = np.einsum("nkj,nkj->nk", np.broadcast_to(b, pc.shape), perp) / dist_edge
    ranges[..., 2] = np.where(ca >= cos_w, dist_edge, np.inf)
    src = np.argmin(ranges, axis=-1)
    d = np.take_along_axis(ranges, src[..., None], axis=-1)[..., 0]
    none = ~np.isfinite(d)
    src = np.where(none, NONE, src)
    d = np.where(none, np.nan, d + rng.normal(0.0, noise, d.shape))
    model = energy_model or EnergyModel(phi0=2.0, phi1=1.0, phi2=0.5)
    # The corner returns most when the beam points straight at the edge.
    gain = np.where(src == CORNER, 4.0 * ca**40, 1.0)
    for j, n in enumerate((na, nb)):
        cosang = np.einsum("nkj,j->nk", np.broadcast_to(b, pc.shape), n)
        gain = np.where(src == j, np.clip(cosang, 0, 1) ** 2, gain)
    energy = np.where(none, 1e-6, model.expected_energy(np.where(none, 1.0, d)) * gain)
    edge_dir_gamma = np.arctan2(e_pt[2], e_pt[1])
    crit = int(np.argmin(np.abs(g - edge_dir_gamma)))
    return SyntheticScan(g, d, src, energy, (na, nb), (float(offset_a), float(offset_b)), crit)
