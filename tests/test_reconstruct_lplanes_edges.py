"""An L plane of record on an edge's echoes is not good, by what its own echoes say of their target.

The scene is an analytic L (wall a at ``y = 1.57 m``, wall b at ``z = 1.8 m``, their corner) whose wall b is
never heard face-on: an edge 2 m away answers in its place, after the corner.  The L model fits plane b to the
edge's echoes with the normal its premise gives (``z``), so the plane lands on the edge's range, where no wall
is.  Two edges, each caught by its own reading:

* a line across the capsule stack (along ``y`` at ``z = 2 m``): its ranges curve along the stack by ``1/(2ρ)``,
  a plane's are straight;
* a line along the stack (a point in the scan plane, at 105°): its echoes' region is centred on the edge, not
  on the plane's foot (90°), and ends short of it on the side where nothing more is heard.

The same scene with wall b a true mirror keeps its plane good.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from lelsonar.geometry import ArrayGeometry, boresight
from lelsonar.reconstruct.estimate.quality import GOOD, UNRELIABLE
from lelsonar.reconstruct.estimate.record import RecordOptions, ScanInput, reconstruct_scan
from lelsonar.reconstruct.estimate.results import PlaneFit
from lelsonar.reconstruct.estimate.surface_check import foot_off_centre_finding, stack_curvature_finding
from lelsonar.sim import default_energy_model

from .synthetic import WALL_B, synthetic_corner_scan

#: Wall b's offset and the edge's range, m; the beam's half-width, rad; range noise, m.
_WALL_B, _EDGE, _BEAM, _NOISE = 1.8, 2.0, math.radians(26.0), 0.002


def _l_with_edge(edge: str | None, seed: int = 7):
    """The analytic L with wall b's mirror echoes replaced by an edge's after the corner (``edge``: ``"across"``
    the stack, ``"along"`` it, or None to keep wall b): the scan's γ and ranges, and its estimate of record."""
    geometry = ArrayGeometry()
    scan = synthetic_corner_scan(geometry, rng=np.random.default_rng(seed), offset_b=_WALL_B, noise=_NOISE)
    g, d = scan.gamma, scan.distance.copy()
    if edge is not None:
        pc = geometry.capsule_positions(g)
        axis = np.broadcast_to(boresight(g)[:, None, :], pc.shape)
        if edge == "across":  # the line {(0, s, 2 m)}: each capsule's nearest point has its own x
            rel = np.stack([-pc[..., 0], np.zeros(pc.shape[:2]), _EDGE - pc[..., 2]], axis=-1)
        else:  # the line {(s, 2 m cos 105°, 2 m sin 105°)}: a point in the scan plane
            rel = np.array([0.0, _EDGE * math.cos(math.radians(105.0)), _EDGE * math.sin(math.radians(105.0))]) - pc
            rel[..., 0] = 0.0
        dist = np.linalg.norm(rel, axis=-1)
        heard = np.einsum("nkj,nkj->nk", axis, rel) / dist >= math.cos(_BEAM)
        heard &= (np.arange(g.size) > scan.critical_step + 3)[:, None]
        d[scan.source == WALL_B] = np.nan
        take = heard & ~(d < dist)
        d[take] = dist[take] + np.random.default_rng(seed + 1).normal(0.0, _NOISE, dist.shape)[take]
    given = ScanInput.of_scan(g, d, scan.sensor_energy, geometry, default_energy_model())
    return g, d, reconstruct_scan(given, RecordOptions())


@pytest.mark.parametrize(("edge", "reading"), [("across", "capsule stack"), ("along", "its foot, with nothing heard")])
def test_an_l_plane_on_an_edges_echoes_is_not_good(edge: str, reading: str) -> None:
    _, _, est = _l_with_edge(edge)
    a, b = est.planes
    assert isinstance(a, PlaneFit) and a.quality == GOOD  # wall a is a wall
    assert isinstance(b, PlaneFit) and b.normal[2] > 0.99  # the premise's normal, the edge's range
    assert abs(b.offset - _WALL_B) > 0.1
    assert b.quality == UNRELIABLE
    assert any(reading in r for r in b.quality_reasons), b.quality_reasons


def test_the_same_l_with_wall_b_heard_keeps_both_planes_good() -> None:
    _, _, est = _l_with_edge(None)
    for plane in est.planes:
        assert isinstance(plane, PlaneFit) and plane.quality == GOOD, plane.quality_reasons
    assert abs(est.planes[1].offset - _WALL_B) < 0.01


def test_a_planes_straight_ranges_along_the_stack_are_no_edges() -> None:
    rng = np.random.default_rng(3)
    x = np.tile(np.array([-0.12, -0.04, 0.04, 0.12]), 40)
    steps = np.repeat(np.arange(40), 4)
    tilted = 2.0 - 0.1 * x + rng.normal(0.0, _NOISE, x.size)  # a plane tilted along the stack
    assert stack_curvature_finding(x, steps, tilted) == ()
    across = np.sqrt(2.0**2 + x**2) + rng.normal(0.0, _NOISE, x.size)
    ((level, reason),) = stack_curvature_finding(x, steps, across)
    assert level == UNRELIABLE and "capsule stack" in reason
    # One capsule a step says nothing of a curvature.
    assert stack_curvature_finding(x[::4], steps[::4], across[::4]) == ()


def test_a_mirrors_echoes_centred_on_its_foot_say_nothing() -> None:
    # A mirror heard ±26° about its foot at 90°, nothing past either end: centred, whatever the normal's σ.
    gamma = np.deg2rad(np.arange(40.0, 140.0, 0.5))
    beam = np.stack([np.zeros_like(gamma), np.cos(gamma), np.sin(gamma)], axis=1)
    heard = np.abs(gamma - math.pi / 2) <= _BEAM
    distance = np.where(heard, 2.0, np.nan)[:, None].repeat(2, axis=1)
    steps = np.repeat(np.flatnonzero(heard), 2)  # both capsules' echoes, each step
    ranges = np.full(steps.size, 2.0)
    normal = np.array([0.0, 0.0, 1.0])
    assert foot_off_centre_finding(normal, 0.002, beam[steps], steps, ranges, distance) == ()
    # The same echoes with a normal the premise turned by 8°: the foot is off their centre.
    turned = np.array([0.0, -math.sin(math.radians(8.0)), math.cos(math.radians(8.0))])
    ((level, reason),) = foot_off_centre_finding(turned, 0.002, beam[steps], steps, ranges, distance)
    assert level == UNRELIABLE and "its foot, with nothing heard" in reason
    # Past the short end something else is heard: that end may be cut, so nothing is said.
    masked = distance.copy()
    masked[steps.min() - 2] = 2.3
    masked[steps.max() + 2] = 2.3
    assert foot_off_centre_finding(turned, 0.002, beam[steps], steps, ranges, masked) == ()
