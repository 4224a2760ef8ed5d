"""A plane's region without a bearing of its own, at another plane's depth and tilt within reach of its foot, is
that plane's own mirror past a nearer echo: it is placed at that plane's bearing."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from lelsonar.reconstruct.estimate.surfaces import SurfaceOptions
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


@pytest.mark.parametrize(("depth", "placed"), [(2.483, True), (2.52, False)])
def test_a_planes_own_mirror_past_a_nearer_echo_takes_its_planes_bearing(depth, placed):
    # A vertical fan: a wall 2.48 m ahead leaning 9.7° along the stack, its bearing from its region's centre; past
    # the nearer target that cut it, 21–25° up, a region without a bearing of its own at the wall's depth and tilt
    # (3 mm off), or 4 cm deeper.
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
