"""A region's centre is its target's bearing only while its two flanks are one beam pattern's, mirror images.

* a lone wall's flanks cross every level symmetrically about its foot (the midpoints within their noise of it),
  so its centre's σ takes nothing from them;
* a flank whose outer part is another target's weaker echo (a wall that ends at its foot, an edge's diffraction
  beside it) puts the midpoints where that echo leaves it, off the centre by what the centre's σ must hold;
* in a sweep, an edge at the wall's range beside its foot whose diffraction runs the region on past the wall's own
  end: the wall's centre is off its foot, and its σ says by how much.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from lelsonar.reconstruct.estimate.surfaces import extract_surfaces
from lelsonar.reconstruct.estimate.surfaces.symmetry import flank_asymmetry, level_midpoints
from lelsonar.signal.directivity import piston_directivity
from tests.piston_sweep import GAMMA, GEOMETRY, KA, PistonSweep, wrap

STEP = float(GAMMA[1] - GAMMA[0])
#: The region's ends uniform within a step each: the centre's σ from them alone.
ENDS = math.sqrt(2.0 * STEP * STEP / 48.0)


def _lone_wall(seed: int, bearing: float) -> tuple[np.ndarray, np.ndarray]:
    sweep = PistonSweep(seed)
    sweep.wall(bearing, 1.0)
    _, amp = sweep.readings()
    held = np.flatnonzero(np.isfinite(amp).all(axis=1))
    return GAMMA[held], np.median(amp[held], axis=1)


@pytest.mark.parametrize("seed", range(6))
def test_lone_wall_flanks_cross_every_level_about_its_foot(seed):
    foot = math.radians(float(np.random.default_rng(seed).uniform(-20.0, 20.0)))
    g, a = _lone_wall(seed, foot)
    found = level_midpoints(g, a)
    assert found is not None
    mids, sds = found
    assert np.all(np.abs(mids - foot) <= 4.0 * np.hypot(sds, STEP / 8.0)), np.degrees(mids - foot)
    # The excess over the noise is the noise's own scatter: a fraction of a step, not the several steps a second
    # echo moves an end by.
    centre = 0.5 * (float(g[0]) + float(g[-1]))
    assert flank_asymmetry(g, a, centre, ENDS) <= STEP / 4.0


def test_a_flank_another_echo_continues_moves_the_midpoints_off_the_centre():
    """One flank of a piston's profile about β, the other a weaker echo's about β + δ from the level where it
    takes over: the midpoints of the crossings under that level sit off β by what the weaker echo shifts them,
    those over it at β; the centre (the threshold's midpoint) is off β, and the asymmetry covers its error."""
    beta, delta, weak = 0.0, math.radians(8.0), 0.5
    psi = GAMMA - beta
    main = np.where(KA * np.abs(np.sin(psi)) < 3.8317, piston_directivity(psi, KA) ** 2, 0.0)
    psi_w = GAMMA - beta - delta
    other = weak * np.where(KA * np.abs(np.sin(psi_w)) < 3.8317, piston_directivity(psi_w, KA) ** 2, 0.0)
    # Past β the weaker echo takes over where it is the stronger one (the first echo over the threshold).
    amp = np.where((GAMMA > beta) & (other > main), other, main)
    # The region: the steps over the threshold about the peak, up to the first under it on either side.
    over = amp > 0.02
    top = int(np.argmax(amp))
    first = top - int(np.argmin(over[top::-1]))
    last = top + int(np.argmin(over[top:]))
    held = np.arange(first + 1, last)
    g, a = GAMMA[held], amp[held]
    centre = 0.5 * (float(g[0]) + float(g[-1]))
    assert abs(centre - beta) > 3.0 * ENDS  # the centre's own σ does not hold its error
    mids, _ = level_midpoints(g, a)
    assert abs(float(mids[-1]) - beta) < STEP  # the top levels are the one beam pattern's
    asym = flank_asymmetry(g, a, centre, ENDS)
    assert abs(centre - beta) <= 3.0 * math.hypot(ENDS, asym)


@pytest.mark.parametrize("seed", range(3))
def test_an_edge_running_a_wall_region_on_leaves_its_bearing_within_its_sigma(seed):
    """A wall at 1 m with its foot at γ = 0, and a vertical edge 11° off its foot 4 mm farther (a like range):
    past the wall's own threshold crossing the edge's diffraction carries the region on, so its centre lies off
    the foot by degrees.  The wall's bearing, whatever its verdict, is within 3 σ of its foot."""
    sweep = PistonSweep(seed)
    sweep.wall(0.0, 1.0)
    sweep.corner(0.2, 1.004, gain=1.0)
    distance, amp = sweep.readings()
    result = extract_surfaces(GAMMA, distance, GEOMETRY, amplitude=amp)
    (wall,) = [w for w in result.surfaces if abs(w.offset - 1.0) < 0.02]
    sigma = math.sqrt(float(wall.covariance[0, 0]))
    assert abs(wrap(wall.bearing)) <= 3.0 * sigma, (math.degrees(wall.bearing), math.degrees(sigma))


@pytest.mark.parametrize("seed", range(3))
def test_a_lone_wall_keeps_its_sigma(seed):
    """The same wall alone: its centre is its foot, its σ the ends' and the noise's (no asymmetry added)."""
    sweep = PistonSweep(seed)
    sweep.wall(0.0, 1.0)
    distance, amp = sweep.readings()
    (wall,) = extract_surfaces(GAMMA, distance, GEOMETRY, amplitude=amp).surfaces
    sigma = math.sqrt(float(wall.covariance[0, 0]))
    assert abs(wrap(wall.bearing)) <= 3.0 * sigma
    assert sigma < 2.0 * ENDS
