"""The stress worlds: valid world files outside the families, and the bench's scoring of one of them."""

from __future__ import annotations

import math
import tomllib

import numpy as np
import pytest

from lelsonar.sim.world import MOUNTS, parse_world
from lelsonar.tools.stress_world_score import COUNTS, score_world
from lelsonar.tools.stress_worlds import STRESS_CLASSES, draw_stress_world, stress_world_data, world_toml


def _corners_deg(world) -> list[float]:
    """Interior angles where two walls share an endpoint, degrees."""
    out = []
    for i, a in enumerate(world.walls):
        for b in world.walls[i + 1 :]:
            for p, q in ((a.start, a.end), (a.end, a.start)):
                for r, s in ((b.start, b.end), (b.end, b.start)):
                    if math.dist(p, r) < 1e-9:
                        u, v = np.subtract(q, p), np.subtract(s, r)
                        out.append(math.degrees(math.acos(u @ v / (np.linalg.norm(u) * np.linalg.norm(v)))))
    return out


@pytest.mark.parametrize("mount", MOUNTS)
@pytest.mark.parametrize("cls", STRESS_CLASSES)
def test_each_class_draws_a_world_file_that_reads_back_the_same(cls: str, mount: str) -> None:
    for seed in (0, 1):
        data = stress_world_data(cls, seed, mount)
        world = draw_stress_world(cls, seed, mount)
        assert world == draw_stress_world(cls, seed, mount)  # seeded: the same triple, the same world
        again = parse_world(tomllib.loads(world_toml(data)), f"stress-{cls}-{seed}-{mount}")
        assert again == world
        assert world.scanner.mount == mount and world.poses


def test_the_corner_classes_leave_the_right_angle() -> None:
    for seed in range(4):
        assert all(abs(a - 90.0) > 8.0 for a in _corners_deg(draw_stress_world("oblique", seed)))
        assert min(_corners_deg(draw_stress_world("acute", seed))) < 60.0 + 1e-6
        assert min(_corners_deg(draw_stress_world("obtuse", seed))) > 100.0


def test_thin_walls_have_free_ends() -> None:
    """A thin wall has at least one end no other wall meets: a convex edge the families never draw."""
    world = draw_stress_world("thin", 0)
    ends = [p for w in world.walls for p in (w.start, w.end)]
    lonely = [p for p in ends if sum(math.dist(p, q) < 1e-9 for q in ends) == 1]
    assert lonely


def test_a_stress_world_is_scored_without_a_crash() -> None:
    score = score_world("boxes_turned", 0, "fan", draw_stress_world("boxes_turned", 0), max_poses=1)
    assert set(score.counts) == set(COUNTS)
    assert score.counts["sweeps"] == 1 and score.counts["crash"] == 0, score.failures


def test_an_l_plane_its_own_surface_contradicts_is_not_good() -> None:
    """Acute room, seed 1, fan mount, first pose: the L model can land plane a on a wall's range with its normal far
    off (a wall's bearing from ranges alone is ill-posed); the surface of the same echoes, its bearing from the beam
    pattern, says so, and the plane is degraded with that reason."""
    score = score_world("acute", 1, "fan", draw_stress_world("acute", 1), max_poses=1)
    assert score.counts["crash"] == 0, score.failures
    assert score.counts["L good-but-wrong"] == 0, score.failures


def test_the_beam_and_tilt_classes_leave_the_default_rig() -> None:
    """``beam``: the echo beam 20–60° wide on a level mount; ``tilt``: the mount ±10° off level, the default beam."""
    widths, tilts = [], []
    for seed in range(4):
        for mount in MOUNTS:
            beam = draw_stress_world("beam", seed, mount).scanner
            tilt = draw_stress_world("tilt", seed, mount).scanner
            assert beam.tilt == 0.0 and beam.beam_width is not None
            assert tilt.beam_width is None
            widths.append(math.degrees(beam.beam_width))
            tilts.append(math.degrees(tilt.tilt))
    assert all(20.0 <= w <= 60.0 for w in widths) and max(widths) - min(widths) > 10.0
    assert all(-10.0 <= t <= 10.0 for t in tilts) and min(tilts) < 0.0 < max(tilts)
