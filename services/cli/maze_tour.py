"""The rover's tour of a world for ``lelsonar demo --world``: which world, and where it stops to scan.

A world's poses are the rover's waypoints.  A sonar sees a wall only near the foot of its perpendicular, so
one sweep per waypoint leaves most of each wall unseen and the poses far apart, tied by odometry alone.  The
rover therefore scans as it goes: every ``spacing`` metres along the straight drive between two waypoints
(the drive the odometry models), heading the way it drives.  Consecutive sweeps then see the same walls,
which tie the poses to each other, and the walls are seen along their length, not at one point.
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

from shapely.geometry import LineString, Point, Polygon
from shapely.ops import unary_union

from lelsonar.acquire.world_scans import WorldRun
from lelsonar.errors import ConfigError
from lelsonar.sim.odometry import simulate_odometry
from lelsonar.sim.world import Pose2, World, load_world
from lelsonar.sim.world_geometry import build_model
from lelsonar.sim.world_render import world_rig
from lelsonar.sim.worlds import POSE_CLEARANCE, WORLD_FAMILIES, draw_world

#: Where the example worlds live (a name given to ``--world`` is looked up there).
EXAMPLE_WORLDS = Path(__file__).resolve().parents[2] / "examples" / "worlds"


def resolve_world(text: str) -> Path:
    """``--world``'s file: a path to a world file, or the name of an example world (``maze``)."""
    path = Path(text)
    if path.is_file():
        return path
    named = EXAMPLE_WORLDS / f"{text}.toml"
    if named.is_file():
        return named
    known = ", ".join(sorted(p.stem for p in EXAMPLE_WORLDS.glob("*.toml"))) or "none found"
    raise ConfigError(
        f"--world {text!r} is neither a world file, an example world ({known}), nor FAMILY:SEED "
        f"({', '.join(WORLD_FAMILIES)})"
    )


def load_tour_world(text: str) -> tuple[World, str]:
    """``--world``'s world and where it comes from: a world file, an example's name, or ``FAMILY:SEED`` (a
    world drawn from a family of :mod:`lelsonar.sim.worlds`, ``maze:3``)."""
    if not Path(text).is_file() and ":" in text:
        family, _, seed = text.partition(":")
        if family not in WORLD_FAMILIES or not seed.isdigit():
            raise ConfigError(
                f"--world {text!r}: FAMILY:SEED takes a family ({', '.join(WORLD_FAMILIES)}) and a seed ≥ 0, as maze:3"
            )
        return draw_world(family, int(seed)), f"the {family} family, seed {seed}"
    path = resolve_world(text)
    return load_world(path), str(path)


def tour_poses(world: World, spacing: float) -> tuple[Pose2, ...]:
    """The waypoints with a stop every ``spacing`` m (at most) along each drive between two of them.

    A stop is evenly spaced on the drive and heads along it.  One nearer a wall or box than a drawn world's
    poses may be (:data:`~lelsonar.sim.worlds.POSE_CLEARANCE`) is left out: the rover drives past there without
    stopping.  The tour begins with a sweep turned about at the first waypoint: a sweep leaves the directions
    behind the rover unseen, and nothing else looks back at where it starts.  ``spacing`` 0: the waypoints
    alone.
    """
    if not (math.isfinite(spacing) and spacing >= 0):
        raise ConfigError(f"--scan-every must be a distance ≥ 0 m, got {spacing!r}")
    poses = world.poses
    if spacing == 0 or len(poses) < 2:
        return poses
    obstacles = unary_union(
        [LineString([w.start, w.end]) for w in world.walls] + [Polygon(b.footprint()) for b in world.boxes]
    )
    first = poses[0]
    out = [Pose2(first.x, first.y, math.remainder(first.heading + math.pi, 2 * math.pi)), first]
    for a, b in zip(poses, poses[1:]):
        d = math.hypot(b.x - a.x, b.y - a.y)
        n = math.ceil(d / spacing - 1e-9)
        heading = math.atan2(b.y - a.y, b.x - a.x)
        for k in range(1, n):
            p = Pose2(a.x + (b.x - a.x) * k / n, a.y + (b.y - a.y) * k / n, heading)
            if obstacles.is_empty or obstacles.distance(Point(p.x, p.y)) >= POSE_CLEARANCE:
                out.append(p)
        out.append(b)
    return tuple(out)


def tour_run(world: World, source: str, *, seed: int, spacing: float) -> WorldRun:
    """The world ready to be scanned at every stop of its tour (:func:`tour_poses`), with the odometry's
    estimate of each stop (seeded by the world's odometry seed) and the sweeps seeded by ``seed``."""
    toured = replace(world, poses=tour_poses(world, spacing))
    return WorldRun(
        path=Path(source),
        world=toured,
        model=build_model(toured),
        rig=world_rig(toured),
        odometry=simulate_odometry(toured.poses, toured.odometry),
        seed=int(seed),
    )
