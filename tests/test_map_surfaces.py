"""A reconstruction's surfaces, corners and edges as the map's observation: frames, σ's shape, and the L
planes kept for recordings without surfaces."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lelsonar import codec
from lelsonar.geometry import array_pose
from lelsonar.map.from_reconstruction import fan_direction, observation_at, planar_pose
from lelsonar.map.lines import line_in_world
from lelsonar.reconstruct.estimate.surfaces import UNSETTLED
from lelsonar.reconstruct.estimate.surfaces.features import NOT_ITS_END
from lelsonar.v1 import reconstruction_pb2 as pb


def _surface(msg, n_array, offset, cov3, *, quality=pb.PLANE_QUALITY_GOOD, label="s1"):
    """A SurfaceEstimate as the extractor writes it: bearing atan2(n_z, n_y), tilt asin(n_x) in the array frame."""
    n = np.asarray(n_array, float)
    item = msg.surfaces.add(
        label=label, bearing=math.atan2(n[2], n[1]), tilt=math.asin(n[0]), bearing_source="amplitude peak"
    )
    p = item.plane
    p.label, p.method, p.offset, p.quality = label, "constant-depth", offset, quality
    p.normal.x, p.normal.y, p.normal.z = n
    foot = n * offset
    along = np.cross([1.0, 0.0, 0.0], n)
    for q in (foot - 0.2 * along, foot + 0.2 * along):
        p.patch.add(x=q[0], y=q[1], z=q[2])
    item.covariance.extend(np.asarray(cov3, float).ravel().tolist())
    msg.surface_echo_count += 40
    return item


def _placed(heading=0.7, xy=(1.5, -0.5), mount="fan"):
    rot, trans = array_pose(xy[0], xy[1], heading, mount, 0.3)
    return rot, trans, planar_pose(rot, trans, None)


@pytest.mark.parametrize("bearing_deg", [-60.0, 0.0, 35.0, 120.0])
def test_a_fan_surface_lands_on_its_world_line_with_its_sigma_s_shape(bearing_deg):
    rot, trans, pose = _placed()
    # A vertical wall seen at this bearing in the fan, tilt 0 (the stack is vertical).
    n_array = fan_direction(math.radians(bearing_deg), 0.0)
    n_world = rot @ n_array
    offset = 1.8
    rho_world = offset + float(n_world @ trans)
    sb, st, so = math.radians(3.0), math.radians(1.0), 0.004
    cov3 = np.diag([sb**2, st**2, so**2])
    msg = codec.Reconstruction(scanner_id="s1", scan_id=3)
    _surface(msg, n_array, offset, cov3)
    obs = observation_at(msg, rot, pose, "lel")
    [wall] = obs.walls
    theta_world = math.atan2(n_world[1], n_world[0])
    assert line_in_world(pose.vector, wall.line) == pytest.approx([theta_world, rho_world], abs=1e-9)
    # A wall poorly placed in bearing stays poorly placed in azimuth, and well placed in range.
    assert math.sqrt(wall.covariance[0, 0]) == pytest.approx(sb, rel=1e-4)
    assert math.sqrt(wall.covariance[1, 1]) == pytest.approx(so, rel=1e-4)
    assert wall.quality == "good" and wall.label == "s1"


def test_a_tilt_read_off_the_stack_does_not_move_a_wall_s_range():
    """The mirror's range is its perpendicular distance: a tilt error leans the plane, the wall stays at ρ."""
    rot, _, pose = _placed(heading=0.0, xy=(0.0, 0.0))
    n_array = fan_direction(0.3, math.radians(6.0))
    msg = codec.Reconstruction(scanner_id="s1", scan_id=1)
    _surface(msg, n_array, 2.0, np.diag([1e-4, 1e-3, 1e-6]))
    [wall] = observation_at(msg, rot, pose, "lel").walls
    assert wall.line[1] == pytest.approx(2.0, abs=1e-12)
    assert abs(wall.normal[2]) < 1e-12


def test_surfaces_replace_the_l_planes_and_carry_verdicts_corners_and_edges():
    rot, _, pose = _placed(heading=0.0, xy=(0.0, 0.0))
    msg = codec.Reconstruction(scanner_id="s1", scan_id=2)
    plane = msg.planes.add(label="a", method="lel", offset=1.0, normal_stderr=0.01, offset_stderr=0.01)
    plane.normal.y = 1.0
    plane.quality = pb.PLANE_QUALITY_GOOD
    plane.patch.add(x=0.0, y=1.0, z=0.0)
    _surface(msg, fan_direction(0.5, 0.0), 1.2, np.diag([1e-4, 1e-4, 1e-6]))
    flagged = _surface(
        msg, fan_direction(-1.0, 0.0), 2.2, np.diag([1e-4, 1e-4, 1e-6]), quality=pb.PLANE_QUALITY_DEGRADED, label="s2"
    )
    flagged.plane.quality_reasons.append("bearing from the amplitude peak alone")
    _surface(msg, rot.T @ np.array([0.0, 0.0, -1.0]), 0.3, np.eye(3) * 1e-4, label="s3")  # the floor
    corner = msg.corners.add(label="c1")
    corner.line.point.y, corner.line.direction.x, corner.line.point_stderr = 2.0, 1.0, 0.01
    edge = msg.edges.add(label="e1")
    edge.line.point.z, edge.line.direction.x, edge.line.point_stderr = 1.5, 1.0, 0.02
    obs = observation_at(msg, rot, pose, "lel")
    assert [w.label for w in obs.walls] == ["s1", "s2"]
    assert obs.walls[1].quality == "degraded" and obs.walls[1].reasons == ("bearing from the amplitude peak alone",)
    assert any("s3" in n and "horizontal" in n for n in obs.notes)
    kinds = sorted(f.kind for f in obs.features)
    assert kinds == ["concave", "edge"]
    for f in obs.features:
        # The stack (array x) is vertical on the fan mount: the features are vertical lines.
        assert abs(f.direction[2]) == pytest.approx(1.0)
    # Without surfaces, the L planes of record are the walls.
    msg.ClearField("surfaces")
    msg.ClearField("corners")
    msg.ClearField("edges")
    msg.surface_echo_count = 0
    assert [w.label for w in observation_at(msg, rot, pose, "lel").walls] == ["a"]


@pytest.mark.slow
def test_a_room_toured_through_the_simulator_and_the_extractor_is_mapped_within_a_centimetre():
    """A world drawn for the test, simulated pose by pose, its surfaces extracted: the walls seen twice lie on the
    true faces, the poses beat odometry, and no wall claims good while off."""
    from lelsonar.tools.bench_map import false_good
    from lelsonar.tools.map_worlds import tour

    result = tour("room", 7)
    twice = [w for w in result.walls if w.scans >= 2]
    assert twice and all(w.face >= 0 for w in twice)
    assert np.median([w.offset for w in twice]) < 0.01
    assert np.median([w.angle for w in twice]) < math.radians(1.0)
    assert not false_good(result) and result.unmatched_good == 0
    fused = np.mean([p[0] for p in result.pose_fused])
    odometry = np.mean([p[0] for p in result.pose_odometry])
    assert fused < odometry


@pytest.mark.slow
def test_demo_world_maze_prints_a_route_out_that_crosses_no_true_wall(capsys, tmp_path):
    import re

    from shapely.geometry import LineString

    from lelsonar.cli.main import main
    from lelsonar.sim.world import load_world

    assert main(["demo", "--world", "maze", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    text = " ".join(out[out.index("route out") : out.index("the exit")].split())
    route = [(float(x), float(y)) for x, y in re.findall(r"\((-?\d+\.\d+), (-?\d+\.\d+)\)", text.split(": ", 1)[1])]
    world = load_world("examples/worlds/maze.toml")
    # The route's points are printed to the cm: a true wall is crossed only if the route comes nearer than that.
    line = LineString(route)
    for w in world.walls:
        assert line.distance(LineString([w.start, w.end])) > 0.15 - 0.01
    x0, y0, x1, y1 = world.bounds()
    end = route[-1]
    assert not (x0 < end[0] < x1 and y0 < end[1] < y1)


def test_an_l_plane_of_record_stands_for_a_surface_it_vouches_for_and_no_other():
    rot, _, pose = _placed(heading=0.0, xy=(0.0, 0.0))
    msg = codec.Reconstruction(scanner_id="s1", scan_id=5)
    n = fan_direction(0.2, 0.0)
    flagged = _surface(msg, n, 1.5, np.diag([1e-4, 1e-4, 1e-6]), quality=pb.PLANE_QUALITY_DEGRADED, label="s1")
    flagged.plane.quality_reasons.append("bearing from the amplitude peak alone")
    _surface(msg, fan_direction(1.4, 0.0), 2.0, np.diag([1e-4, 1e-4, 1e-6]), label="s2")
    for label, normal, offset in (("a", fan_direction(0.2 + 0.01, 0.0), 1.51), ("b", fan_direction(1.4, 0.0), 2.0)):
        plane = msg.planes.add(label=label, method="lel", offset=offset, normal_stderr=0.002, offset_stderr=0.001)
        plane.normal.x, plane.normal.y, plane.normal.z = normal
        plane.quality = pb.PLANE_QUALITY_GOOD if label == "a" else pb.PLANE_QUALITY_DEGRADED
        plane.patch.add(x=normal[0] * offset, y=normal[1] * offset, z=normal[2] * offset)
    walls = observation_at(msg, rot, pose, "lel").walls
    # s1 (degraded) is plane a's wall, which a vouches for; s2 is good on its own and b is not better.
    assert [(w.label, w.quality) for w in walls] == [("a", "good"), ("s2", "good")]
    assert walls[0].line[1] == pytest.approx(1.51)


def test_a_corner_whose_kind_or_line_its_sweep_left_open_ties_nothing_in_the_map():
    rot, _, pose = _placed(heading=0.0, xy=(0.0, 0.0))
    msg = codec.Reconstruction(scanner_id="s1", scan_id=3)
    _surface(msg, fan_direction(0.5, 0.0), 1.2, np.diag([1e-4, 1e-4, 1e-6]))
    for label, why in (
        ("c1", ""),
        ("c2", f"{UNSETTLED}; its echo's source is not at its plane's end"),
        ("c3", f"{NOT_ITS_END}: its echo fades toward where that plane's trace reaches its range"),
    ):
        corner = msg.corners.add(label=label)
        corner.line.point.y, corner.line.direction.x, corner.line.point_stderr = 2.0, 1.0, 0.01
        if why:
            corner.reasons.append(why)
    obs = observation_at(msg, rot, pose, "lel")
    # Only the corner whose kind and line its sweep settled is a corner of the map.
    assert len(obs.features) == 1 and obs.features[0].kind == "concave"
