"""A region on a plane's trace by its depth alone: that plane's end, or a wall of its own, weighed by its beam flank.

Either echo follows the beam pattern across γ about its source (a mirror's foot, a corner's retro-reflecting
line), so the flank a region cut by the sweep's end shows places its peak:

* a wall whose foot lies past the sweep's end, at a depth that puts its region on a seen plane's trace, is a
  wall (placed by its flank, not good), not that plane's end;
* a corner on that trace past the sweep's end stays that plane's end: its flank agrees;
* of two placements on two planes' traces, the one the flank agrees with is taken;
* seeded worlds (dev seeds) where a wall was claimed as a corner.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from lelsonar.reconstruct.estimate.surfaces.flank_bearing import FLANK_SOURCE
from lelsonar.sim.world_geometry import ElementKind
from lelsonar.sim.world_render import pose_frame
from lelsonar.tools.surface_oracle import bearing_tilt, trace_error, true_plane
from lelsonar.tools.surface_scores import majority, score_scan, world_sweep
from tests.piston_sweep import PistonSweep, assert_flank_placed_wall, assert_plane_end, wrap


def _bearing_sigma(f) -> float:
    """A feature's σ across its bearing in the fan, rad: its point's σ along the fan's tangent over its range."""
    t = np.array([0.0, -math.sin(f.bearing), math.cos(f.bearing)])
    return math.sqrt(float(t @ f.covariance @ t)) / f.depth


#: A wall seen whole (its region gives the sweep's beam), and the bearing on its trace past the sweep's start.
PLANE = (math.radians(-100.0), 1.0)
PAST_START = math.radians(-165.0)
#: The range of that trace there.
ON_TRACE = PLANE[1] / math.cos(PAST_START - PLANE[0])


def test_a_wall_past_the_sweeps_start_at_a_depth_on_a_planes_trace_is_a_wall_placed_by_its_flank():
    # Its foot 20° from the trace's point at its depth (farther than a corner's aperture moves a flank's peak,
    # 1/(2k) ≈ 4° on this beam, by over 3 σ), 5° past the sweep's start.
    foot, end = math.radians(-155.0), math.radians(-175.0)
    depth = PLANE[1] / math.cos(end - PLANE[0])
    s = PistonSweep(seed=3)
    s.wall(*PLANE)
    s.wall(foot, depth)
    result = s.surfaces()
    # The premise: its depth alone put it on the plane's trace as its end; the flank says it is not.
    assert_flank_placed_wall(result, depth, foot, "a wall of its own")


def test_a_corner_past_the_sweeps_start_on_a_planes_trace_stays_that_planes_end():
    s = PistonSweep(seed=4)
    s.wall(*PLANE)
    s.corner(PAST_START, ON_TRACE)
    result = s.surfaces()
    corner = assert_plane_end(result, ON_TRACE, PLANE[1])
    # Placed on the trace where the flank agrees: within 3 σ of its true bearing.
    assert abs(wrap(corner.bearing - PAST_START)) <= 3 * _bearing_sigma(corner), math.degrees(corner.bearing)


def test_of_two_placements_on_two_traces_the_one_the_flank_agrees_with_is_taken():
    # Two planes whose traces both reach the corner's depth within its region's reach (cut by the second
    # plane's nearer echo, its peak may lie up to a beam's half-width before it): the first plane's 29° short
    # of the corner, the second's where the corner is.
    near_foot = math.radians(1.5)
    far_foot = math.radians(86.0)
    corner = math.radians(108.6)
    rho = 3.33 / math.cos(corner - far_foot)
    s = PistonSweep(seed=5)
    s.wall(near_foot, 0.72)
    s.wall(far_foot, 3.33)
    s.corner(corner, rho, gain=3.0)
    result = s.surfaces()
    (far,) = [w for w in result.surfaces if abs(w.offset - 3.33) < 0.02]
    (found,) = [f for f in result.corners if abs(f.depth - rho) < 0.02]
    assert found.surfaces == (far.label,)
    assert abs(wrap(found.bearing - corner)) <= 3 * _bearing_sigma(found), math.degrees(found.bearing)


def _scan(family: str, seed: int, pose: int):
    _, scan, amp, result = world_sweep(family, seed, pose)
    return scan, amp, result


@pytest.mark.slow
@pytest.mark.parametrize(("family", "seed", "pose"), [("room", 24, 0), ("l_room", 27, 1), ("boxes", 26, 0)])
def test_a_wall_past_the_sweeps_end_once_claimed_as_a_corner_is_found_within_its_sigma_not_good(family, seed, pose):
    # Its foot past the sweep's end, the wall's region lies on another plane's trace: as that plane's end it would
    # lie farther than the beam's half-width from its far end, or its flank disputes it; it is a wall of its own,
    # placed by its flank.
    scan, amp, result = _scan(family, seed, pose)
    record = score_scan(family, scan, result, seed=seed, amplitude=amp)
    assert not record.missed, record.missed
    disputed = [
        s
        for s in result.surfaces
        if s.bearing_source == FLANK_SOURCE or any("a wall of its own" in r for r in s.reasons)
    ]
    assert disputed
    for s in disputed:
        element, _ = majority(scan, s.steps, s)
        assert scan.model.elements[element].kind == ElementKind.MIRROR
        n_true, h_true = true_plane(scan, element)
        db = wrap(s.bearing - bearing_tilt(n_true)[0])
        assert abs(db) <= 3 * math.sqrt(s.covariance[0, 0]), math.degrees(db)
        assert trace_error(s.normal, s.offset, n_true, h_true) < 0.05
        assert s.quality != "good"


@pytest.mark.slow
def test_a_corner_placed_on_the_wrong_planes_trace_is_placed_where_its_flank_agrees():
    scan, _amp, result = _scan("l_room", 36, 2)
    rot, tr = pose_frame(scan.rig, scan.pose)
    for f in result.corners:
        element, _ = majority(scan, f.steps, f)
        el = scan.model.elements[element]
        if el.kind != ElementKind.DIHEDRAL or len(f.surfaces) != 1:
            continue
        p = rot.T @ (el.p0 - tr)
        truth = math.atan2(p[2], p[1])
        assert abs(wrap(f.bearing - truth)) <= 3 * _bearing_sigma(f), (f.label, math.degrees(f.bearing))
