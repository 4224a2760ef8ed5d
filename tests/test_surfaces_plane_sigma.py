"""A plane's bearing and its σ where a region's ends are another target's: analytic sweeps and seeded worlds.

* a region that holds its wall's double bounce with the floor past one end only (the other side's made a
  region of its own) is lopsided: the wall's bearing is the centre of its own steps, not of the region;
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from lelsonar.reconstruct.estimate.surfaces import extract_surfaces
from lelsonar.reconstruct.estimate.surfaces.regions import find_regions
from lelsonar.signal.energy import echo_amplitude
from lelsonar.sim.world_geometry import build_model
from lelsonar.sim.world_render import simulate_world_scan
from lelsonar.sim.worlds import draw_world
from lelsonar.tools.bench_surfaces import majority, true_plane
from tests.test_surfaces import GAMMA, GEOMETRY, Echoes


def _bearing_z(scan, surfaces) -> list[tuple[str, float, float]]:
    """Each good surface's bearing error against its majority element's truth: (label, error rad, σ rad)."""
    out = []
    for s in surfaces:
        if s.quality != "good":
            continue
        k, _ = majority(scan, s.steps, s)
        n_true, _h = true_plane(scan, k)
        error = math.remainder(s.bearing - math.atan2(n_true[2], n_true[1]), 2 * math.pi)
        out.append((s.label, error, math.sqrt(s.covariance[0, 0])))
    return out


def test_a_wall_whose_floor_corner_flanks_its_region_on_one_side_only_takes_its_own_steps_centre():
    bearing, offset = math.radians(-30.0), 4.0
    alone = Echoes(seed=21)
    alone.plane(bearing, offset)
    own = np.flatnonzero(np.isfinite(alone.range).any(axis=1))
    e = Echoes(seed=21)
    e.plane(bearing, offset)
    n = np.array([0.0, math.cos(bearing), math.sin(bearing)])
    e.across_line(offset * n + np.array([-0.24, 0.0, 0.0]), np.cross([1.0, 0.0, 0.0], n), gain=2.0)
    d = e.ranges()
    # The corner's steps past the wall's last step are gone (on that side they made a region of their own).
    d[own[-1] + 1 :] = np.nan
    (region,) = [r for r in find_regions(d) if np.isin(own, r.steps).all()]
    head = int(np.count_nonzero(region.steps < own[0]))
    assert head >= 3 and region.steps[-1] == own[-1]  # the premise: one flank, in the region
    result = extract_surfaces(GAMMA, d, GEOMETRY, amplitude=e.amp)
    (wall,) = [s for s in result.surfaces if abs(s.offset - offset) < 0.01]
    sd = math.sqrt(wall.covariance[0, 0])
    # The whole region's centre is half the flank's width off: the wall's own steps' is not.
    whole = 0.5 * (GAMMA[region.steps[0]] + GAMMA[region.steps[-1]])
    assert abs(whole - bearing) > 3 * sd
    assert abs(wall.bearing - bearing) <= 3 * sd, (math.degrees(wall.bearing - bearing), math.degrees(sd))


@pytest.mark.slow
def test_in_a_simulated_corridor_a_one_sided_floor_corner_flank_does_not_move_the_walls_bearing():
    # The corridor world of seed 11, its second pose (fan mount): the wall 4.2 m away meets the floor; that
    # corner's echoes join the wall's region on one side only (four steps), the other side's stay apart.
    scan = simulate_world_scan(build_model(draw_world("corridor", 11)), 1, seed=11 * 1000 + 1)
    amp = echo_amplitude(scan.waveforms, scan.sample_rate, scan.t0, scan.tof)
    result = extract_surfaces(scan.gamma_measured, scan.distance, scan.geometry, amplitude=amp)
    checked = _bearing_z(scan, result.surfaces)
    assert checked
    for label, error, sd in checked:
        assert abs(error) <= 3 * sd, f"{label}: {math.degrees(error):.2f}° with σ {math.degrees(sd):.2f}°"
