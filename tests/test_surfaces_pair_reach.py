"""A region is two planes' double bounce, or one plane's end, only where every one of its steps could hear that
line: within the beam's half-width of both ends of its span, as the joint fit ties a corner's walls."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lelsonar.reconstruct.estimate.surfaces import SurfaceOptions
from lelsonar.reconstruct.estimate.surfaces.evidence import pair_corner, plane_ends
from lelsonar.reconstruct.estimate.surfaces.regions import Region
from tests.measured_regions import hand_measured

STEP = math.radians(1.0)


def _region(lo_deg: float, hi_deg: float, depth: float, cut: tuple[bool, bool]):
    steps = np.arange(int(round(hi_deg - lo_deg)) + 1)
    region = Region(
        steps=steps, rows=steps, capsules=np.zeros(steps.size, dtype=np.intp), cut_before=cut[0], cut_after=cut[1]
    )
    lo, hi = math.radians(lo_deg), math.radians(hi_deg)
    return hand_measured(region, bearing=0.5 * (lo + hi), depth=depth, span=(lo, hi), step=STEP)


@pytest.mark.parametrize(
    ("span_deg", "theirs"),
    [
        ((55.0, 75.0), True),  # the line 10° before the cut end, 30° from the far end
        ((65.0, 95.0), False),  # 20° before the cut end, but 50° from the far end: its far steps cannot hear it
    ],
)
def test_a_region_past_a_cut_end_is_their_double_bounce_only_where_every_step_hears_their_line(span_deg, theirs):
    # Walls x·ŷ = 1 and x·ẑ = 1 meet at (1, 1): 1.414 m away at 45°.  A region at that range, cut before (a nearer
    # echo hides the line's own bearing), its span starting past the line.
    opts = SurfaceOptions()
    assert opts.beyond_cut == pytest.approx(math.radians(40.0))
    wall_y = _region(-20.0, 20.0, 1.0, (False, False))
    wall_z = _region(70.0, 110.0, 1.0, (False, False))
    corner = _region(*span_deg, math.sqrt(2.0), (True, False))
    found = pair_corner(corner, [wall_y, wall_z], opts)
    assert (found is not None) == theirs
    if theirs:
        assert found is not None and found[0] == [0, 1] and found[1] == pytest.approx(math.pi / 4)


@pytest.mark.parametrize(("span_deg", "its_end"), [((55.0, 75.0), True), ((65.0, 95.0), False)])
def test_a_region_past_a_cut_end_is_a_planes_end_only_where_every_step_hears_it(span_deg, its_end):
    # The wall x·ŷ = 1 reaches 1.414 m at ±45° along its trace: a region at that range, cut before, its span starting
    # past 45°.
    wall_y = _region(-20.0, 20.0, 1.0, (False, False))
    region = _region(*span_deg, math.sqrt(2.0), (True, False))
    ends = list(plane_ends(region, [wall_y], SurfaceOptions()))
    assert bool(ends) == its_end
    if its_end:
        assert ends[0][0] == [0] and ends[0][1] == pytest.approx(math.pi / 4)
