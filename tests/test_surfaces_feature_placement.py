"""Corners and edges placed where their evidence puts them: a yawed wall's floor corner in the vertical fan, and
no end on a plane's trace past what the sweep saw of it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lelsonar.reconstruct.estimate.surfaces import extract_surfaces
from lelsonar.sim.world_geometry import ElementKind
from lelsonar.sim.world_render import pose_frame
from lelsonar.tools.map_worlds import sweep
from lelsonar.tools.stress_world_score import estimate_of, world_run
from lelsonar.tools.stress_worlds import draw_stress_world

from .test_surfaces import GAMMA_PAPER, GEOMETRY, Echoes, _line_distance, _unit


@pytest.mark.parametrize("yaw_deg", [10.0, 12.0, 14.0])
def test_a_yawed_walls_floor_corner_in_the_vertical_fan_runs_along_the_stack_not_across_the_fan(yaw_deg):
    # The paper's mount 0.3 m above the floor, a wall 1.2 m ahead turned by the yaw about the vertical.  Its
    # corner with the floor is a line in both planes: along the stack, leaning with the yaw.  The yaw slopes the
    # corner's ranges along the stack as a line across the fan off the axis by ~0.3 m would (the floor's distance):
    # the ranges alone do not tell the two apart, the floor (seen, in the fan) and the corner's bearing do.
    yaw = math.radians(yaw_deg)
    wall, floor = (0.0, 1.2, yaw), (-math.pi / 2, 0.3, 0.0)
    e = Echoes(seed=31, gamma=GAMMA_PAPER)
    for bearing, offset, tilt in (wall, floor):
        e.plane(bearing, offset, tilt)
    n = np.stack([_unit(wall[0], wall[2]), _unit(floor[0], floor[2])])
    on = np.linalg.pinv(n) @ np.array([wall[1], floor[1]])
    direction = np.cross(n[0], n[1])
    direction /= np.linalg.norm(direction)
    e.across_line(on, direction, gain=1.5)
    result = extract_surfaces(GAMMA_PAPER, e.ranges(), GEOMETRY, amplitude=e.amp)
    features = [*result.corners, *result.edges]
    assert features, [(s.bearing, s.offset) for s in result.surfaces]
    for f in features:
        sigma = math.sqrt(float(np.max(np.linalg.eigvalsh(f.covariance))))
        off = _line_distance(f.point, on, direction)
        assert off <= 3 * sigma, (f.kind, off, sigma, f.reasons)
        assert abs(float(f.direction @ direction)) == pytest.approx(1.0, abs=0.02), (f.direction, f.reasons)


def _line_offset(scan, f) -> tuple[int, float]:
    """The element most of the feature's echoes came from, and the feature's distance from it (the world frame)."""
    k = scan.echo_index[f.steps]
    k = k[k >= 0]
    el_index = int(np.bincount(k).argmax())
    el = scan.model.elements[el_index]
    rot, tr = pose_frame(scan.rig, scan.pose)
    p = rot @ f.point + tr
    d = (el.p1 - el.p0) / np.linalg.norm(el.p1 - el.p0)
    return el_index, float(np.linalg.norm((p - el.p0) - ((p - el.p0) @ d) * d))


@pytest.mark.slow
def test_a_room_corner_past_a_box_faces_end_is_not_placed_on_the_faces_extended_trace():
    # A cluttered room (stress class clutter, seed 0, fan mount), its third pose: a box face 0.8 m away whose
    # edges the sweep hears on its trace, and beyond them, behind, room corners and edges whose regions are
    # cut by the box.  The face's trace extended runs within a few cm of a room corner 2 m off, which a
    # trace alone would call the face's end.  The face ends at its edges; nothing past them is its end.
    world = draw_stress_world("clutter", 0, "fan")
    scan = sweep(world_run(world, 0), 2)
    surfaces = estimate_of(scan).surfaces
    features = [*surfaces.corners, *surfaces.edges]
    assert features
    for f in features:
        el_index, off = _line_offset(scan, f)
        el = scan.model.elements[el_index]
        if el.kind not in (ElementKind.DIHEDRAL, ElementKind.TRIHEDRAL, ElementKind.EDGE) or off <= 0.02:
            continue
        # Off by more than the floor: its σ across the line must say so.
        sigma = math.sqrt(float(np.max(np.linalg.eigvalsh(f.covariance))))
        assert off <= 3 * sigma, (f.kind, f.label, el_index, off, sigma, f.reasons)
