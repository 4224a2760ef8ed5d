"""A hand-built fan sweep: mirrors and vertical lines (a fan mount's corners) seen through a piston ``D(ψ)²``."""

from __future__ import annotations

import math

import numpy as np

from lelsonar.geometry import ArrayGeometry
from lelsonar.reconstruct.estimate.surfaces import SurfaceSet, extract_surfaces
from lelsonar.reconstruct.estimate.surfaces.flank_bearing import FLANK_SOURCE
from lelsonar.signal.directivity import piston_directivity

GEOMETRY = ArrayGeometry(radial_offset=0.03)
GAMMA = np.linspace(math.radians(-149.7), math.radians(149.7), 300)
KA = 5.13  # a 7 mm piston at 40 kHz
THRESHOLD = 0.05  # V
RANGE_NOISE = 0.002  # m
FIRST_NULL = 3.8317  # ka·sin ψ of the piston's first null


class PistonSweep:
    """Mirrors and vertical lines seen through a piston ``D(ψ)²``: the first echo over the threshold sets each
    reading; amplitudes log-normal about the beam, ranges Gaussian."""

    def __init__(self, seed: int, amp_noise: float = 0.01) -> None:
        self.rng = np.random.default_rng(seed)
        self.caps = GEOMETRY.capsule_positions(GAMMA)
        self.beam = np.stack([np.zeros_like(GAMMA), np.cos(GAMMA), np.sin(GAMMA)], axis=1)
        self.range = np.full(self.caps.shape[:2], np.nan)
        self.amp = np.full(self.caps.shape[:2], np.nan)
        self.amp_noise = amp_noise

    def _add(self, r: np.ndarray, toward: np.ndarray, gain: float) -> None:
        psi = np.arccos(np.clip(np.einsum("nk,nmk->nm", self.beam, toward), -1.0, 1.0))
        main = (psi < 0.5 * math.pi) & (KA * np.sin(psi) < FIRST_NULL)
        a = gain * piston_directivity(psi, KA) ** 2 / (2 * r)
        a = a * np.exp(self.amp_noise * self.rng.normal(size=a.shape))
        first = main & (a > THRESHOLD) & (r > 0) & ~(self.range <= r)
        self.range[first] = r[first]
        self.amp[first] = a[first]

    def wall(self, bearing: float, offset: float, gain: float = 2.5) -> None:
        n = np.array([0.0, math.cos(bearing), math.sin(bearing)])
        self._add(offset - self.caps @ n, np.broadcast_to(n, self.caps.shape), gain)

    def corner(self, bearing: float, rho: float, gain: float = 2.5) -> None:
        """A vertical line at ``rho`` in the fan: its echo retro-reflects from the point nearest each capsule."""
        rel = rho * np.array([0.0, math.cos(bearing), math.sin(bearing)]) - self.caps
        rel[..., 0] = 0.0
        r = np.linalg.norm(rel, axis=-1)
        self._add(r, rel / r[..., None], gain)

    def readings(self) -> tuple[np.ndarray, np.ndarray]:
        return self.range + self.rng.normal(0.0, RANGE_NOISE, self.range.shape), self.amp

    def surfaces(self) -> SurfaceSet:
        """The surfaces the extractor finds in these :meth:`readings`."""
        d, a = self.readings()
        return extract_surfaces(GAMMA, d, GEOMETRY, amplitude=a)


def wrap(a: float) -> float:
    """An angle in [−π, π)."""
    return (a + math.pi) % (2 * math.pi) - math.pi


def assert_flank_placed_wall(result, depth: float, foot: float, reason: str) -> None:
    """``result`` holds one surface at ``depth``: placed by its beam flank within 3 σ of ``foot``, a reason naming
    ``reason``, not good, and no corner or edge takes its echoes."""
    (wall,) = [w for w in result.surfaces if abs(w.offset - depth) < 0.02]
    assert wall.bearing_source == FLANK_SOURCE
    assert any(reason in r for r in wall.reasons), wall.reasons
    assert abs(wrap(wall.bearing - foot)) <= 3 * math.sqrt(wall.covariance[0, 0]), math.degrees(wall.bearing)
    assert wall.quality != "good"
    assert not [f for f in (*result.corners, *result.edges) if abs(f.depth - depth) < 0.02]


def assert_plane_end(result, depth: float, plane_offset: float):
    """``result`` holds no surface at ``depth`` but one corner there, the end of the plane at ``plane_offset``
    alone; that corner."""
    assert not [w for w in result.surfaces if abs(w.offset - depth) < 0.05]
    (corner,) = [f for f in result.corners if abs(f.depth - depth) < 0.02]
    (plane,) = [w for w in result.surfaces if abs(w.offset - plane_offset) < 0.02]
    assert corner.surfaces == (plane.label,)
    return corner
