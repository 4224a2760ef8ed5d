"""A corner's or an edge's σ covers what its evidence leaves open.

* a plane's line with a surface across the fan placed at the plane's foot: the line's turn in the plane is
  known only through its cosine, so the bearing's σ holds the turn the tilt's σ leaves open (analytic, and a
  seeded stress world where the line lies 5.7° off the foot);
* seeded stress worlds, one per cause: each feature's point within 3 σ (or 2 cm) of its true line.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from lelsonar.reconstruct.estimate.surfaces.placement import line_yaw_stderr
from lelsonar.sim.world_geometry import ElementKind
from lelsonar.tools.map_worlds import sweep
from lelsonar.tools.stress_world_score import ERROR_FLOOR, _majority, estimate_of, world_run
from lelsonar.tools.stress_worlds import draw_stress_world
from lelsonar.tools.surface_scores import feature_offset

CLASSES = {"corner": (ElementKind.DIHEDRAL, ElementKind.TRIHEDRAL), "edge": (ElementKind.EDGE,)}


def _line_echo(h: float, q: float, phi: float) -> tuple[float, float, float]:
    """Range, tilt and bearing off the foot of the point nearest the array of a line in plane ``n·X = h``, ``q``
    from the foot in the plane, turned by ``phi`` from square to the stack."""
    x = np.array([q * math.cos(phi) ** 2, h, -q * math.cos(phi) * math.sin(phi)])  # (stack, along n, along e)
    rho = float(np.linalg.norm(x))
    return rho, math.asin(x[0] / rho), math.atan2(-x[2], x[1])


@pytest.mark.parametrize("phi_deg", [0.0, 10.0, 20.0, 30.0])
def test_the_foots_bearing_sigma_holds_the_turn_a_tilt_within_its_sigma_leaves_open(phi_deg):
    # A floor corner 0.5 m off a wall 2 m away: the tilt's σ of 0.5° leaves the line's turn open by ~15° about
    # square, so the point may lie ~4° off the foot however square the line truly is.
    h, q, sigma_t = 2.0, 0.5, math.radians(0.5)
    rho, tilt, off = _line_echo(h, q, math.radians(phi_deg))
    square_tilt = math.asin(q / math.hypot(h, q))
    within = abs(tilt - square_tilt) <= 3 * sigma_t  # the foot is where a tilt within 3 σ of square places it
    se = line_yaw_stderr(rho, 0.001, tilt, sigma_t, h, 0.001)
    assert se > 0
    if within:
        assert abs(off) <= 3 * se, (math.degrees(off), math.degrees(se))
    # A sharper tilt narrows it; the turn is bounded by a line at right angles to the stack's square.
    assert line_yaw_stderr(rho, 0.001, tilt, sigma_t / 4, h, 0.001) < se
    assert se <= math.atan2(q, h) + 1e-12


def test_no_turn_where_the_range_does_not_reach_past_the_plane():
    assert line_yaw_stderr(1.0, 0.001, 0.1, 0.01, 1.2, 0.001) == 0.0
    assert line_yaw_stderr(float("nan"), 0.001, 0.1, 0.01, 1.0, 0.001) == 0.0


def _beyond_3_sigma(cls: str, seed: int, mount: str, pose: int) -> list[tuple[str, float, float]]:
    """Each feature of the stress world's sweep off its true line by > 3 σ and > 2 cm: label, m off, σ."""
    world = draw_stress_world(cls, seed, mount)
    scan = sweep(world_run(world, seed), pose)
    surfaces = estimate_of(scan).surfaces
    out = []
    for f in (*surfaces.corners, *surfaces.edges):
        k = _majority(scan, f.steps, f.rows, f.capsules)
        if k < 0 or scan.model.elements[k].kind not in CLASSES[f.kind]:
            continue
        dist, sigma = feature_offset(scan, f, k)
        if dist > ERROR_FLOOR and dist > 3 * sigma:
            out.append((f.label, dist, sigma))
    return out


@pytest.mark.slow
@pytest.mark.parametrize(
    ("cls", "seed", "mount", "pose"),
    [
        # A wall's corner with the floor in the horizontal fan, 5.7° off the wall's foot: its tilt is within 3 σ
        # of a square line's.
        ("odometry", 41, "fan", 1),
    ],
)
def test_seeded_features_lie_within_3_sigma_of_their_lines(cls, seed, mount, pose):
    assert _beyond_3_sigma(cls, seed, mount, pose) == []
