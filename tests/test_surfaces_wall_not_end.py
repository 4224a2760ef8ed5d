"""A strong region whose depth alone puts it on a nearer plane's trace, past a cut by that plane at a like range:
that plane's end (a concave corner) only if its own echo's flank does not refute it.

The nearer plane answers inside the region's amplitude window where the two meet, so the region's flank is not
trusted there; its steps away from that cut are its own echo alone:

* a wall whose foot lies 12° from where the plane's trace reaches its depth (just inside the cut) is a wall,
  placed by its flank away from the cut, not good, and no corner takes its echoes (whether or not the trace first
  claims it as the plane's end);
* a corner at that point of the trace stays the plane's end: its flank agrees.
"""

from __future__ import annotations

import math

from tests.piston_sweep import PistonSweep, assert_flank_placed_wall, assert_plane_end

#: The nearer plane (bearing, offset) and the bearing on its trace where it reaches the region's depth, inside
#: its own region (its nearer echo masks the target from there on).
PLANE = (math.radians(-60.0), 0.9)
END = math.radians(-85.0)
#: The trace's range there: within the amplitude window's reach of the plane's depth (a like range).
ON_TRACE = PLANE[1] / math.cos(END - PLANE[0])


def test_the_premise_the_region_is_cut_by_the_plane_at_a_like_range():
    assert ON_TRACE - PLANE[1] < 0.1


def test_a_wall_behind_a_nearer_plane_at_a_depth_on_its_trace_is_a_wall_not_its_end():
    foot = END - math.radians(12.0)
    s = PistonSweep(seed=11)
    s.wall(*PLANE)
    s.wall(foot, ON_TRACE)
    result = s.surfaces()
    walls = [w for w in result.surfaces if abs(w.offset - ON_TRACE) < 0.02]
    assert len(walls) == 1, [(c.label, c.reasons) for c in result.corners]
    assert_flank_placed_wall(result, ON_TRACE, foot, "flank")


def test_a_corner_where_the_nearer_planes_trace_reaches_its_depth_stays_that_planes_end():
    s = PistonSweep(seed=12)
    s.wall(*PLANE)
    s.corner(END, ON_TRACE)
    result = s.surfaces()
    assert_plane_end(result, ON_TRACE, PLANE[1])
