"""A plane's region of constant depth and what sits at its ends: analytic sweeps and one seeded world.

* the steps of a line across the stack at a like range (a wall's corner with the floor) that extend a
  wall's region are not the wall's, and do not move its bearing;
* a capsule that sees a farther target past a nearer one's edge holds no reading of the nearer one's region;
* the centre's σ is the quantisation of its two ends, each over its own gap.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from lelsonar.reconstruct.estimate.surfaces import extract_surfaces
from lelsonar.reconstruct.estimate.surfaces.regions import capsule_x, find_regions
from tests.test_surfaces import GAMMA, GEOMETRY, Echoes, _unit


def _wall_and_floor_corner(seed: int, bearing: float, offset: float, below: float) -> tuple[Echoes, np.ndarray]:
    """A wall and its corner with a floor ``below`` along the stack; returns the sweep and the wall's own steps."""
    alone = Echoes(seed=seed)
    alone.plane(bearing, offset)
    own = np.flatnonzero(np.isfinite(alone.range).any(axis=1))
    e = Echoes(seed=seed)
    e.plane(bearing, offset)
    n = _unit(bearing)
    # The double bounce of the wall with the floor retro-reflects from their line: stronger than the mirror,
    # so it answers past the wall's own echo on both sides, a little deeper.
    e.across_line(offset * n + np.array([below, 0.0, 0.0]), np.cross([1.0, 0.0, 0.0], n), gain=3.0)
    return e, own


@pytest.mark.parametrize("bearing", [-90.0, -37.3, 12.9])
def test_a_walls_region_is_its_own_steps_not_its_corner_with_the_floor_past_its_ends(bearing):
    beta, offset = math.radians(bearing), 3.0
    e, own = _wall_and_floor_corner(7, beta, offset, below=-0.25)
    d = e.ranges()
    # The premise: the corner's steps past the wall's join its region of constant depth.
    (region,) = [r for r in find_regions(d) if np.isin(own, r.steps).all()]
    assert region.steps.size > own.size
    result = extract_surfaces(GAMMA, d, GEOMETRY, amplitude=e.amp)
    (wall,) = [s for s in result.surfaces if abs(s.offset - offset) < 0.01]
    assert set(wall.steps) == set(own)
    sd = math.sqrt(wall.covariance[0, 0])
    assert abs(wall.bearing - beta) <= 3 * sd
    assert wall.quality == "good", wall.reasons


def test_a_capsule_seeing_a_farther_wall_past_a_nearer_target_leaves_the_nearer_ones_region():
    bearing = math.radians(-30.0)
    far, near = Echoes(seed=11), Echoes(seed=12)
    far.plane(bearing, 3.0)
    near.plane(bearing, 1.0, gain=0.5)
    d, amp = far.ranges(), far.amp.copy()
    # A nearer target masks three capsules of the four (a box's edge beside the stack).
    masked = np.isfinite(near.range[:, :3])
    d[:, :3] = np.where(masked, near.ranges()[:, :3], d[:, :3])
    amp[:, :3] = np.where(masked, near.amp[:, :3], amp[:, :3])
    seen_far = np.isfinite(far.range[:, 3]) & masked.any(axis=1)
    # Without a bound, the fourth capsule's own median over the region keeps its 3 m readings in the 1 m region.
    (kept,) = [r for r in find_regions(d) if np.nanmedian(d[r.rows, r.capsules]) < 2]
    assert np.any(d[kept.rows, kept.capsules] > 2)
    # One target's ranges differ between capsules by no more than their distance apart.
    x = capsule_x(GEOMETRY)
    (near_region,) = [
        r for r in find_regions(d, max_spread=float(np.ptp(x)) + 0.015) if np.nanmedian(d[r.rows, r.capsules]) < 2
    ]
    assert not np.any(d[near_region.rows, near_region.capsules] > 2)
    result = extract_surfaces(GAMMA, d, GEOMETRY, amplitude=amp)
    assert result.unexplained["off their step's range (another target in the same beam)"] == np.count_nonzero(seen_far)


def test_the_centres_sigma_is_the_quantisation_of_its_ends_over_their_own_gaps():
    # A servo's quantised positions: steps of 2 and 3 units of 0.293° in turn.
    unit = math.radians(300.0 / 1023.0)
    gamma = math.radians(-150.0) + unit * np.cumsum(np.tile([2, 3], 205))[:410]
    e = Echoes(seed=5, gamma=gamma)
    bearing, offset = math.radians(20.0), 1.5
    e.plane(bearing, offset)
    result = extract_surfaces(gamma, e.ranges(), GEOMETRY, amplitude=e.amp)
    (s,) = result.surfaces
    assert s.bearing_source == "region centre"
    first, last = int(s.steps[0]), int(s.steps[-1])
    before, after = gamma[first] - gamma[first - 1], gamma[last + 1] - gamma[last]
    assert math.sqrt(s.covariance[0, 0]) == pytest.approx(math.sqrt((before**2 + after**2) / 48))
