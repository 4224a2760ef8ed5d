"""Seeded world families: valid, reproducible, and a maze's poses lead out of it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lelsonar.errors import ConfigError
from lelsonar.sim.world_render import simulate_world_scan, world_rig
from lelsonar.sim.worlds import WORLD_FAMILIES, draw_world


def _crosses(p, q, a, b) -> bool:
    """Whether the open segments p–q and a–b cross (orientation test)."""

    def orient(u, v, w):
        return (v[0] - u[0]) * (w[1] - u[1]) - (v[1] - u[1]) * (w[0] - u[0])

    return orient(p, q, a) * orient(p, q, b) < 0 and orient(a, b, p) * orient(a, b, q) < 0


@pytest.mark.parametrize("family", WORLD_FAMILIES)
def test_every_family_draws_valid_reproducible_worlds_whose_sweeps_find_walls(family):
    for seed in range(3):
        world = draw_world(family, seed)
        assert world == draw_world(family, seed)
        assert world.walls and world.poses
        rig = world_rig(world, steps=60)
        scan = simulate_world_scan(world, 0, rig=rig, seed=seed, with_waveforms=False)
        assert np.isfinite(scan.distance).mean() > 0.5, (family, seed)
    assert draw_world(family, 0) != draw_world(family, 1)


def test_a_maze_s_poses_walk_out_through_its_exit_without_crossing_a_wall():
    for seed in range(5):
        world = draw_world("maze", seed)
        walls = [(w.start, w.end) for w in world.walls]
        poses = world.poses
        for p, q in zip(poses[:-1], poses[1:]):
            assert not any(_crosses((p.x, p.y), (q.x, q.y), a, b) for a, b in walls), seed
        # One cell further along the last heading is outside every wall: the exit.
        last = poses[-1]
        step = math.dist((poses[0].x, poses[0].y), (poses[1].x, poses[1].y)) if len(poses) > 1 else 1.0
        out = (last.x + 2 * step * math.cos(last.heading), last.y + 2 * step * math.sin(last.heading))
        assert not any(_crosses((last.x, last.y), out, a, b) for a, b in walls), seed
        x0, y0, x1, y1 = world.bounds()
        assert not (x0 <= out[0] <= x1 and y0 <= out[1] <= y1), seed


def test_an_unknown_family_is_a_one_line_error():
    with pytest.raises(ConfigError, match="unknown world family 'cave'"):
        draw_world("cave", 0)


@pytest.mark.parametrize("family", WORLD_FAMILIES)
def test_the_paper_mount_sees_the_same_world_facing_a_wall_with_the_floor_and_ceiling_in_its_sweep(family):
    for seed in range(3):
        fan, paper = draw_world(family, seed), draw_world(family, seed, mount="paper")
        assert draw_world(family, seed, mount="fan") == fan
        assert paper.scanner.mount == "paper" and fan.scanner.mount == "fan"
        assert (paper.walls, paper.boxes, paper.room) == (fan.walls, fan.boxes, fan.room)
        assert [(p.x, p.y) for p in paper.poses] == [(p.x, p.y) for p in fan.poses]
        assert paper.scanner.height == fan.scanner.height
        # Past straight down and straight up: the floor's and the ceiling's feet are in the sweep.
        assert paper.scanner.sweep_start < -math.pi / 2 and paper.scanner.sweep_stop > math.pi / 2
        # Each pose faces a wall (the foot of its perpendicular on it, within 3 m) at most 12° off square.
        for p in paper.poses:
            ahead = (math.cos(p.heading), math.sin(p.heading))
            faced = False
            for w in paper.walls:
                d = np.subtract(w.end, w.start)
                t = float(np.dot(np.subtract((p.x, p.y), w.start), d) / np.dot(d, d))
                foot = np.add(w.start, t * d)
                to = foot - (p.x, p.y)
                dist = float(np.hypot(*to))
                if 0 < t < 1 and dist <= 3.0:
                    faced |= float(np.dot(to / dist, ahead)) >= math.cos(math.radians(12.0)) - 1e-9
            assert faced, (family, seed, p)


def test_an_unknown_mount_is_a_one_line_error():
    with pytest.raises(ConfigError, match="unknown scanner mount 'side'"):
        draw_world("room", 0, mount="side")
