"""A region at a plane's own depth, within reach of its foot, is that plane's mirror and not its double bounce with
another plane whose line passes near that foot: the region's depth says which of the two it misses less.  Without a
bearing of its own, it is placed at its plane's."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from lelsonar.reconstruct.estimate.surfaces import SurfaceOptions
from lelsonar.reconstruct.estimate.surfaces.evidence import pair_corner, plane_line
from lelsonar.reconstruct.estimate.surfaces.fitting import place_own_mirrors
from lelsonar.reconstruct.estimate.surfaces.regions import Region
from tests.measured_regions import hand_measured


def _region(lo_deg: float, hi_deg: float, depth: float, cut: tuple[bool, bool], tilt: float = 0.0):
    steps = np.arange(int(round(hi_deg - lo_deg)) + 1)
    region = Region(
        steps=steps, rows=steps, capsules=np.zeros(steps.size, dtype=np.intp), cut_before=cut[0], cut_after=cut[1]
    )
    lo, hi = math.radians(lo_deg), math.radians(hi_deg)
    return hand_measured(region, bearing=0.5 * (lo + hi), depth=depth, span=(lo, hi), step=math.radians(1.0), tilt=tilt)


@pytest.mark.parametrize(("at_line", "theirs"), [(False, False), (True, True)])
def test_a_region_at_a_planes_own_depth_is_its_mirror_not_its_corner(at_line, theirs):
    # A vertical fan: the floor 0.26 m below the array, a wall 2.48 m ahead leaning 9.7° along the stack.  Their
    # line passes 6° below the wall's foot, 2.494 m away: 14 mm past the wall's own depth.  A region cut before (by
    # a nearer target), 21–25° up, within reach of the wall's foot.
    opts = SurfaceOptions()
    tilt = math.radians(9.7)
    floor = _region(-110.0, -70.0, 0.26, (False, False))
    wall = _region(-20.0, 20.0, 2.48, (False, False), tilt=tilt)
    line = plane_line(floor, wall)
    assert line is not None
    rho = float(np.linalg.norm(line[0]))
    assert rho - wall.depth == pytest.approx(0.014, abs=0.002)
    depth = rho if at_line else wall.depth + 0.003
    region = _region(21.0, 25.0, depth, (True, False), tilt=tilt)
    found = pair_corner(region, [floor, wall], opts)
    assert (found is not None) == theirs


@pytest.mark.parametrize(("depth", "placed"), [(2.483, True), (2.52, False)])
def test_a_planes_own_mirror_past_a_nearer_echo_takes_its_planes_bearing(depth, placed):
    # The wall of the case above, its bearing from its region's centre; past the nearer target that cut it, 21–25°
    # up, a region without a bearing of its own at the wall's depth and tilt (3 mm off), or 4 cm deeper.
    tilt = math.radians(9.7)
    wall = _region(-20.0, 20.0, 2.48, (False, False), tilt=tilt)
    region = _region(21.0, 25.0, depth, (True, False), tilt=tilt)
    region = replace(region, bearing_source="undetermined", bearing_stderr=math.radians(3.0))
    measured = [wall, region]
    place_own_mirrors(measured, set(), SurfaceOptions().beyond_cut)
    assert measured[0] is wall
    if placed:
        assert measured[1].bearing == pytest.approx(wall.bearing)
        assert measured[1].bearing_source == wall.bearing_source
        assert measured[1].bearing_stderr == pytest.approx(wall.bearing_stderr)
    else:
        assert measured[1] is region
