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
