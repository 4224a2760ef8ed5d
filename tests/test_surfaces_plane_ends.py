"""A plane's region of constant depth and what sits at its ends: analytic sweeps and one seeded world.

* the steps of a line across the stack at a like range (a wall's corner with the floor) that extend a
  wall's region are not the wall's, and do not move its bearing;
* a capsule that sees a farther target past a nearer one's edge holds no reading of the nearer one's region;
* the centre's σ is the quantisation of its two ends, each over its own gap;
* an amplitude peak's σ covers another echo summing into its flank, bounded by how much it widens the top.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from lelsonar.reconstruct.estimate.surfaces import extract_surfaces
from lelsonar.reconstruct.estimate.surfaces.beam_pattern import bearing_from_amplitude, log_amplitude_curvature
from lelsonar.reconstruct.estimate.surfaces.measurement import summed_width_stderr
from lelsonar.reconstruct.estimate.surfaces.regions import find_regions
from lelsonar.reconstruct.estimate.surfaces.stack import capsule_x
from lelsonar.signal.directivity import piston_directivity
from lelsonar.signal.energy import echo_amplitude
from lelsonar.sim.world_geometry import build_model
from lelsonar.sim.world_render import simulate_world_scan
from lelsonar.sim.worlds import draw_world
from lelsonar.tools.surface_oracle import true_plane
from lelsonar.tools.surface_scores import majority
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
    # Its own steps only: at most each end's step, where some capsules hear the corner already, goes with it.
    assert set(wall.steps) <= set(own) and own.size - wall.steps.size <= 2
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
    # The fourth capsule hears the farther wall where the others hear the nearer target first: the wall's own
    # region, its plane fitted with the tilt left open, and none of those readings unexplained.
    assert result.unexplained["off their step's range (another target in the same beam)"] == 0
    (behind,) = [s for s in result.surfaces if abs(s.offset - 3.0) < 0.05]
    assert behind.capsules is not None and set(behind.capsules.tolist()) == {3}
    assert np.count_nonzero(seen_far[behind.rows]) == np.count_nonzero(seen_far)
    assert any("tilt not determined" in r for r in behind.reasons)


def test_the_centres_sigma_is_the_quantisation_of_its_ends_over_their_own_gaps():
    # A servo's quantised positions: steps of 2 and 3 units of 0.293° in turn.
    unit = math.radians(300.0 / 1023.0)
    gamma = math.radians(-150.0) + unit * np.cumsum(np.tile([2, 3], 205))[:410]
    e = Echoes(seed=5, gamma=gamma)
    bearing, offset = math.radians(20.0), 1.5
    e.plane(bearing, offset)
    # The centre alone (no amplitudes: no beam-pattern peak to weigh with it).
    result = extract_surfaces(gamma, e.ranges(), GEOMETRY)
    (s,) = result.surfaces
    assert s.bearing_source == "region centre"
    first, last = int(s.steps[0]), int(s.steps[-1])
    before, after = gamma[first] - gamma[first - 1], gamma[last + 1] - gamma[last]
    assert math.sqrt(s.covariance[0, 0]) == pytest.approx(math.sqrt((before**2 + after**2) / 48))


@pytest.mark.slow
def test_in_a_simulated_corridor_the_far_walls_floor_corner_does_not_move_its_bearing():
    # The corridor world of seed 10, its second pose: the far wall's corner with the floor answers on both
    # sides of the wall's own echo at a like range, four steps on one side and one on the other.
    world = draw_world("corridor", 10)
    scan = simulate_world_scan(build_model(world), 1, seed=10 * 1000 + 1)
    amp = echo_amplitude(scan.waveforms, scan.sample_rate, scan.t0, scan.tof)
    result = extract_surfaces(scan.gamma_measured, scan.distance, scan.geometry, amplitude=amp)
    for s in result.surfaces:
        if s.quality != "good":
            continue
        k, _ = majority(scan, s.steps, s)
        n_true, _h = true_plane(scan, k)
        error = math.remainder(s.bearing - math.atan2(n_true[2], n_true[1]), 2 * math.pi)
        assert abs(error) <= 3 * math.sqrt(s.covariance[0, 0]), f"{s.label}: {math.degrees(error):.2f}°"
    # The corner's steps on either side are the wall's corner with the floor, not the wall.
    far = max(result.surfaces, key=lambda s: s.offset)
    ends = [c for c in result.corners if far.label in c.surfaces and abs(c.depth - far.offset) < 0.03]
    assert len(ends) == 2


@pytest.mark.parametrize(("weight", "apart"), [(0.2, 10.0), (0.4, 15.0), (0.3, 20.0)])
def test_the_bound_on_a_summed_echo_covers_how_far_it_moved_the_amplitude_peak(weight, apart):
    ka = 3.66  # a 5 mm piston at 40 kHz
    beta = math.radians(20.0)
    whole = beta + np.radians(np.arange(-40.0, 40.0, 0.88))
    beam = log_amplitude_curvature(whole, piston_directivity(whole - beta, ka) ** 2)
    # A region cut 10° before the peak, a weaker echo summing into its far flank.
    g = beta + np.radians(np.arange(-10.0, 40.0, 0.88))
    alone = piston_directivity(g - beta, ka) ** 2
    summed = alone + weight * piston_directivity(g - beta - math.radians(apart), ka) ** 2
    bearing, _ = bearing_from_amplitude(g, summed)
    # The flattest top one echo shows: the same beam over windows cut anywhere from 20° to 2° before its peak.
    windows = (beta + np.radians(np.arange(-cut, 40.0, 0.88)) for cut in np.arange(2.0, 21.0))
    flattest = min(
        c for w in windows if (c := log_amplitude_curvature(w, piston_directivity(w - beta, ka) ** 2)) is not None
    )
    bound = summed_width_stderr(log_amplitude_curvature(g, summed, plateau=True), beam, flattest)
    assert abs(bearing - beta) <= bound
    # One echo alone: its top is no flatter than one echo's, and the bound adds nothing.
    assert summed_width_stderr(log_amplitude_curvature(g, alone, plateau=True), beam, flattest) == 0.0
