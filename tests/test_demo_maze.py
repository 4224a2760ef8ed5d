"""The maze demo's tour and its run on a maze it was not written for: against the world's own walls."""

from __future__ import annotations

import math
import re

import pytest
from shapely.geometry import LineString, MultiPoint, Point

from lelsonar.cli.maze_tour import load_tour_world, tour_poses
from lelsonar.errors import ConfigError
from lelsonar.sim.world import Pose2, World, parse_world
from lelsonar.sim.worlds import POSE_CLEARANCE, draw_world


def _corridor_world(poses: list[tuple[float, float, float]]) -> World:
    return parse_world(
        {
            "world": {"name": "corridor"},
            "room": {"ceiling": 2.5},
            "wall": [{"from": [0.0, 0.0], "to": [4.0, 0.0]}, {"from": [0.0, 1.5], "to": [4.0, 1.5]}],
            "pose": [{"x": x, "y": y, "heading": h} for x, y, h in poses],
        },
        "corridor",
    )


def test_the_tour_stops_every_spacing_along_each_drive_heading_the_way_it_drives():
    world = _corridor_world([(0.5, 0.75, 90.0), (3.5, 0.75, 0.0), (3.5, 0.75, 180.0)])
    stops = tour_poses(world, 0.5)
    # First the start turned about; 3 m at most 0.5 m apart: 5 stops between the first two waypoints; none
    # between two at one place.
    assert len(stops) == 1 + 3 + 5
    back = stops[0]
    assert (back.x, back.y) == (0.5, 0.75) and back.heading == pytest.approx(-math.pi / 2)
    stops = stops[1:]
    assert stops[0] == world.poses[0] and stops[6] == world.poses[1] and stops[-1] == world.poses[2]
    xs = [p.x for p in stops[:7]]
    assert all(b - a == pytest.approx(0.5) for a, b in zip(xs, xs[1:]))
    assert all(p.heading == pytest.approx(0.0) and p.y == pytest.approx(0.75) for p in stops[1:6])
    assert tour_poses(world, 0.0) == world.poses


def test_the_tour_does_not_stop_near_a_wall_it_drives_past():
    # The drive hugs the south wall at 0.2 m: stops there would stand nearer a wall than a drawn world's poses.
    world = _corridor_world([(0.5, 0.75, 0.0), (0.5, 0.2, 0.0), (3.5, 0.2, 0.0)])
    stops = tour_poses(world, 0.5)
    assert all(p in world.poses or min(abs(p.y - 0.0), abs(p.y - 1.5)) >= POSE_CLEARANCE - 1e-9 for p in stops)
    assert Pose2(0.5, 0.2, 0.0) in stops and len(stops) > len(world.poses)


def test_world_names_files_and_families_and_one_line_errors():
    world, source = load_tour_world("maze:3")
    assert world.name == "maze-3" and "seed 3" in source
    assert world.walls == draw_world("maze", 3).walls
    world, source = load_tour_world("maze")
    assert world.name == "maze" and source.endswith("maze.toml")
    for bad in ("maze:x", "castle:1", "no-such-world"):
        with pytest.raises(ConfigError, match="--world"):
            load_tour_world(bad)
    with pytest.raises(ConfigError, match="scan-every"):
        tour_poses(world, -1.0)


@pytest.mark.slow
def test_demo_finds_the_way_out_of_a_drawn_maze_and_draws_it(capsys, tmp_path):
    """A maze of the family (not the example the demo was written with): the route printed crosses no true
    wall and keeps the robot's radius from each, ends outside the maze, and the pictures are written."""
    from lelsonar.cli.main import main

    assert main(["demo", "--world", "maze:1", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    text = " ".join(out[out.index("route out") : out.index("it runs")].split())
    route = [(float(x), float(y)) for x, y in re.findall(r"\((-?\d+\.\d+), (-?\d+\.\d+)\)", text.split(": ", 1)[1])]
    world = draw_world("maze", 1)
    line = LineString(route)
    # The route's points are printed to the cm: a true wall is crossed only if the route comes nearer than that.
    for w in world.walls:
        assert line.distance(LineString([w.start, w.end])) > 0.15 - 0.01
    hull = MultiPoint([p for w in world.walls for p in (w.start, w.end)]).convex_hull
    assert not hull.contains(Point(route[-1]))
    assert math.dist(route[0], (world.poses[0].x, world.poses[0].y)) < 0.05
    assert (tmp_path / "maze-1.rrd").stat().st_size > 0 and (tmp_path / "maze-1.png").stat().st_size > 0
    assert "rerun " + str(tmp_path / "maze-1.rrd") in " ".join(out.split())


def test_the_planner_gets_the_map_and_prints_the_route_out_of_it(tmp_path, capsys):
    """``planner --map`` against a mapper's map on Zenoh (a synthetic maze fused by the library): the route it
    prints keeps the robot's radius from the map's walls, crosses no true wall and ends beyond them."""
    import numpy as np

    from lelsonar.cli.main import main
    from lelsonar.map.fusion import WallMapper
    from lelsonar.map.synthetic import NoiseModel, maze, observe_world
    from lelsonar.map.wire import map_message
    from lelsonar.net.transport import hermetic_settings, open_session

    world = maze(5, np.random.default_rng(4))
    scans, _, _ = observe_world(world, NoiseModel(), np.random.default_rng(4))
    mapper = WallMapper()
    for s in scans:
        mapper.add_scan(s)
    fused = mapper.snapshot()
    payload = map_message(fused, "rover").SerializeToString()
    sock = tmp_path / "z.sock"
    with open_session(hermetic_settings(sock, listen=True)) as session:
        queryable = session.declare_queryable("lelsonar/map", lambda q: q.reply("lelsonar/map", payload))
        start = f"{fused.poses[0].x},{fused.poses[0].y}"
        argv = ["planner", "--map", "--mode", "client", "--connect", f"unixsock-stream/{sock}", "--timeout", "30"]
        assert main([*argv, "--start", start]) == 0
        queryable.undeclare()
    out = " ".join(capsys.readouterr().out.split())
    assert "walls of good evidence" in out
    text = out[out.index("route out") : out.index("it runs")]
    route = [(float(x), float(y)) for x, y in re.findall(r"\((-?\d+\.\d+), (-?\d+\.\d+)\)", text.split(": ", 1)[1])]
    line = LineString(route)
    # It keeps the radius from every wall piece of the map (printed to the cm) and crosses no true wall; a true
    # wall's end beyond the stretch the scans saw of it is not in the map.
    from lelsonar.map.floorplan import wall_segments

    for piece in wall_segments(fused):
        assert line.distance(piece) > 0.15 - 0.01
    for seg in world.segments:
        assert not line.intersects(LineString(seg))
    assert route[-1][0] > world.segments[:, :, 0].max()


@pytest.mark.slow
def test_demo_says_why_when_a_maze_has_no_way_out(capsys, tmp_path):
    """The example maze with its exit walled up: no route is printed, but one line says why, and the exit code
    says it failed."""
    from lelsonar.cli.main import main

    assert main(["demo", "--world", "maze_closed", "--out", str(tmp_path)]) == 1
    out = " ".join(capsys.readouterr().out.split())
    assert "route out (" not in out
    assert "no route out of the map from (0.75, 0.75): every way out" in out
    assert (tmp_path / "maze_closed.png").stat().st_size > 0
