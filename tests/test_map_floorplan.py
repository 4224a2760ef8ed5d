"""The floor plan against independent truth: the route out of a maze keeps the robot's radius from every
wall and crosses none of the true walls; the free space stays inside the true room."""

from __future__ import annotations

import json

import numpy as np
import pytest
from shapely.geometry import LineString, Point, Polygon

from lelsonar.errors import ConfigError
from lelsonar.map import floorplan as fp
from lelsonar.map.fusion import WallMapper
from lelsonar.map.synthetic import NoiseModel, maze, observe_world, room


def _fused(world, seed):
    scans, _, _ = observe_world(world, NoiseModel(), np.random.default_rng(seed))
    mapper = WallMapper()
    for s in scans:
        mapper.add_scan(s)
    return mapper.snapshot()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_route_out_of_a_maze_keeps_the_radius_and_crosses_no_true_wall(seed):
    world = maze(5, np.random.default_rng(seed))
    m = _fused(world, seed)
    cfg = fp.PlanConfig(robot_radius=0.15)
    start = (m.poses[0].x, m.poses[0].y)
    path = fp.route(m, start, tuple(world.exit), cfg)
    assert path is not None
    assert path[0] == pytest.approx(start) and Point(path[-1]).distance(Point(world.exit)) < cfg.resolution
    # Out: the end is beyond every true wall.
    assert path[-1][0] > world.segments[:, :, 0].max()
    line = LineString(path)
    for w in fp.wall_segments(m):
        assert line.distance(w) >= cfg.robot_radius - 1e-9
    for seg in world.segments:
        assert not line.intersects(LineString(seg))
    # Only the last stretch, out of the exit the scans looked through, may leave the space seen free.
    assert fp.unseen_length(m, path, cfg) < 1.0


def test_no_route_from_a_start_off_the_grid_or_into_a_wall():
    m = _fused(room(), 3)
    cfg = fp.PlanConfig(robot_radius=0.15)
    assert fp.route(m, (-5.0, -5.0), None, cfg) is None
    assert fp.route(m, (m.poses[0].x, m.poses[0].y), (2.0, 0.0), cfg) is None  # the goal is on a wall


def test_free_space_grid_geojson_and_markers_of_a_room():
    world = room()
    m = _fused(world, 1)
    truth = Polygon(world.segments[:, 0])
    space = fp.free_space(m)
    assert space.area > 0.5 * truth.area
    assert space.difference(truth.buffer(0.05)).area < 0.01
    grid = fp.occupancy_grid(m, fp.PlanConfig(resolution=0.05))
    r, c = grid.cell(m.poses[0].x, m.poses[0].y)
    assert grid.data[r, c] == fp.FREE
    r, c = grid.cell(2.0, 0.0)  # on the true south wall
    assert grid.data[r, c] == fp.OCCUPIED or grid.data[r + 1, c] == fp.OCCUPIED or grid.data[r - 1, c] == fp.OCCUPIED
    r, c = grid.cell(-0.5, -0.5)  # outside: never seen
    assert grid.data[r, c] == fp.UNKNOWN
    msg = grid.to_message()
    assert len(msg["data"]) == msg["info"]["width"] * msg["info"]["height"]
    gj = json.loads(json.dumps(fp.to_geojson(m)))
    kinds = [f["properties"]["kind"] for f in gj["features"]]
    assert kinds.count("wall") == len(m.walls) and "free_space" in kinds and kinds.count("pose") == len(m.poses)
    markers = fp.wall_markers(m)
    assert len(markers) == sum(len(w.pieces) for w in m.walls)
    assert {mk["text"] for mk in markers} == {f"wall {w.id}: {w.quality}" for w in m.walls}
    assert all(mk["scale"]["y"] >= 0.01 for mk in markers)


def test_plan_config_is_checked():
    with pytest.raises(ConfigError, match="resolution"):
        fp.PlanConfig(resolution=0.0)
    with pytest.raises(ConfigError, match="unknown_cost"):
        fp.PlanConfig(unknown_cost=0.5)


def _wall(wid, theta, rho, pieces, quality="good"):
    from lelsonar.map.result import FusedWall

    return FusedWall(
        id=wid,
        line=np.array([theta, rho]),
        covariance=np.diag([1e-6, 1e-6]),
        interval=(pieces[0][0], pieces[-1][1]),
        pieces=tuple(pieces),
        z_range=(0.3, 0.3),
        quality=quality,
        reasons=(),
        scans=(1,),
        good_observations=1,
        flagged_observations=0,
    )


def _feature(x, y, kind="concave", vertical=True):
    from lelsonar.map.result import FusedFeature

    return FusedFeature(
        point=np.array([x, y, 0.3]),
        direction=np.array([0.0, 0.0, 1.0]) if vertical else np.array([1.0, 0.0, 0.0]),
        kind=kind,
        point_stderr=0.005,
        source="observed",
        observations=1,
    )


def test_a_wall_seen_at_its_foot_likely_runs_on_to_the_corner_or_edge_that_ends_it():
    from lelsonar.map.result import FusedMap

    # The wall y = 2 (normal +y, its foot at the origin's x), seen only over x ∈ [0.9, 1.0] and [2.0, 2.1].
    wall = _wall(0, np.pi / 2, 2.0, [(-1.0, -0.9), (-2.1, -2.0)])  # along (−sin θ, cos θ) = (−1, 0)
    flagged = _wall(1, 0.0, 5.0, [(0.0, 0.05)], quality="unreliable")
    features = (
        _feature(0.0, 2.0),  # a concave corner where the wall meets another at x = 0
        _feature(3.0, 2.0, kind="edge"),  # the wall's free end at x = 3
        _feature(0.95, 2.0),  # on the piece itself: its own echo read as a corner
        _feature(-5.0, 2.0),  # beyond reach
        _feature(2.5, 2.0, vertical=False),  # the wall's foot on the floor: ends nothing along it
    )
    m = FusedMap(walls=(wall, flagged), features=features, poses=())
    cfg = fp.PlanConfig(likely_wall_reach=2.0, likely_wall_span=0.5)
    segments = {tuple(sorted(round(float(v), 6) for v in s[:, 0])) for s in fp.likely_walls(m, cfg)}
    # From the right piece to the edge at x = 3, from the left one to the corner at x = 0.
    assert segments == {(2.1, 3.0), (0.0, 0.9)}
    # Between the pieces, and on to the corner and the edge: closed, as no scan saw through them.
    gaps = {tuple(sorted(round(float(v), 6) for v in s[:, 0])) for s in fp.closed_gaps(m, cfg)}
    assert gaps == {(1.0, 2.0), (2.1, 3.0), (0.0, 0.9)}


def test_a_gap_between_pieces_is_closed_to_a_route_unless_a_scan_saw_through_it():
    from lelsonar.map.result import FusedMap, FusedPose

    # The wall x = 1 seen at y ∈ [−1.5, −0.5] and [0.5, 1.5]: a 1 m gap, the robot at the origin, the goal beyond.
    wall = _wall(0, 0.0, 1.0, [(-1.5, -0.5), (0.5, 1.5)])
    pose = FusedPose(scan_id=1, x=0.0, y=0.0, z=0.3, heading=0.0, covariance=np.eye(3) * 1e-6, odometry=(0.0, 0.0, 0.0))
    cfg = fp.PlanConfig(robot_radius=0.15, margin=1.0, likely_wall_span=0.0)
    unseen = FusedMap(walls=(wall,), features=(), poses=(pose,))
    assert len(fp.closed_gaps(unseen, cfg)) == 1
    path = fp.route(unseen, (0.0, 0.0), (2.0, 0.0), cfg)
    assert path is not None
    crossing = LineString(path).intersection(LineString([(1.0, -10.0), (1.0, 10.0)]))
    assert abs(crossing.coords[0][1]) > 1.5 + cfg.robot_radius  # round the wall's ends, not through the gap
    # An echo's path through the gap to a wall beyond (x = 3): the scans saw the gap open.
    beyond = _wall(1, 0.0, 3.0, [(-0.02, 0.02)])
    view = np.array([[0.0, 0.0], [3.0, -0.02], [3.0, 0.02]])
    seen = FusedMap(walls=(wall, beyond), features=(), poses=(pose,), views=(view,), view_scans=(1,))
    assert len(fp.closed_gaps(seen, cfg)) == 0
    path = fp.route(seen, (0.0, 0.0), (2.0, 0.0), cfg)
    assert path is not None
    crossing = LineString(path).intersection(LineString([(1.0, -10.0), (1.0, 10.0)]))
    assert abs(crossing.coords[0][1]) < 0.5 - cfg.robot_radius


def test_a_route_goes_round_where_a_wall_likely_runs_rather_than_through_it():
    from lelsonar.map.result import FusedMap, FusedPose

    # A wall x = 1 seen at y ∈ [−0.02, 0.02] only, ended by corners at y = ±1.5; the robot at the origin.
    wall = _wall(0, 0.0, 1.0, [(-0.02, 0.02)])
    corners = (_feature(1.0, -1.5), _feature(1.0, 1.5))
    pose = FusedPose(scan_id=1, x=0.0, y=0.0, z=0.3, heading=0.0, covariance=np.eye(3) * 1e-6, odometry=(0.0, 0.0, 0.0))
    m = FusedMap(walls=(wall,), features=corners, poses=(pose,))
    cfg = fp.PlanConfig(robot_radius=0.15, margin=2.5)
    path = fp.route(m, (0.0, 0.0), (2.0, 0.0), cfg)
    assert path is not None
    line = LineString(path)
    # It passes the wall's line x = 1 beyond the corners, not through the stretch between them.
    crossing = line.intersection(LineString([(1.0, -10.0), (1.0, 10.0)]))
    assert abs(crossing.coords[0][1]) > 1.5 + cfg.robot_radius


def test_the_map_read_back_from_its_message_plans_as_the_library_does():
    from lelsonar.map.wire import map_from_message, map_message

    m = _fused(room(), 2)
    back = map_from_message(map_message(m, "s1"))
    assert len(back.walls) == len(m.walls) and len(back.poses) == len(m.poses)
    for a, b in zip(m.walls, back.walls):
        np.testing.assert_allclose(b.line, a.line, atol=1e-12)
        np.testing.assert_allclose(b.covariance, a.covariance, atol=1e-15)
        np.testing.assert_allclose(b.pieces, a.pieces, atol=1e-9)
        assert (b.quality, b.scans) == (a.quality, a.scans)
    assert len(back.views) == len(m.views) and back.view_scans == m.view_scans
    assert fp.free_space(back).symmetric_difference(fp.free_space(m)).area < 1e-9
    start = (m.poses[0].x, m.poses[0].y)
    assert fp.route(back, start) == fp.route(m, start)


def test_an_echo_path_to_an_unreliable_wall_is_no_evidence_of_free_space():
    from lelsonar.map.result import FusedMap

    # The robot at the origin; a good wall x = 1 seen at its foot; an "echo" read as a wall at x = 3 behind it.
    near = _wall(0, 0.0, 1.0, [(-0.02, 0.02)])
    ghost = _wall(1, 0.0, 3.0, [(-0.02, 0.02)], quality="unreliable")
    to_near = np.array([[0.0, 0.0], [1.0, -0.02], [1.0, 0.02]])
    to_ghost = np.array([[0.0, 0.0], [3.0, -0.02], [3.0, 0.02]])
    m = FusedMap(walls=(near, ghost), features=(), poses=(), views=(to_near, to_ghost), view_scans=(1, 1))
    assert [v.tolist() for v in fp.trusted_views(m)] == [to_near.tolist()]
    space = fp.free_space(m)
    assert space.contains(Point(0.5, 0.0)) and not space.intersects(Point(2.0, 0.0))
