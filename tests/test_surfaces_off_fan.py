"""A target only part of the capsule stack hears, off the fan on the beam's flank, and a line across the stack:
their kind from the echo taken back to the beam's axis, their place from their exact ranges."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lelsonar.reconstruct.estimate.surfaces import extract_surfaces
from lelsonar.reconstruct.estimate.surfaces.beam_pattern import piston_power
from lelsonar.reconstruct.estimate.surfaces.results import OFF_FAN
from lelsonar.signal.directivity import piston_directivity

from .test_surfaces import GAMMA, GEOMETRY, Echoes

VERTICAL = np.array([0.0, 0.0, 1.0])


@pytest.mark.parametrize("ka", [4.0, 5.13, 6.6])
def test_the_piston_taken_from_the_beams_curvature_is_the_simulators_piston(ka):
    # Near the axis log D² = −(ka)²ψ²/4: the sweep's curvature k gives ka = 2√k, and from it the whole pattern.
    k = ka * ka / 4.0
    for deg in (0.0, 5.0, 15.0, 25.0, 35.0):
        psi = math.radians(deg)
        want = float(piston_directivity(np.array([psi]), ka)[0] ** 2)
        assert piston_power(psi, k) == pytest.approx(want, rel=1e-9, abs=1e-12)
    assert piston_power(math.asin(3.9 / ka), k) == 0.0  # past the first null nothing says how strong it was


def _two_capsule_target(x0: float, gain: float, seed: int):
    """A wall 2.5 m ahead and a vertical line 0.6 m ahead, ``x0`` along the stack; its features nearer than 1 m."""
    e = Echoes(seed=seed)
    e.plane(0.0, 2.5)
    e.across_line(np.array([x0, 0.6, 0.0]), VERTICAL, gain=gain)
    ranges = e.ranges()
    heard = np.nanmin(ranges, axis=0) < 1.0
    result = extract_surfaces(GAMMA, ranges, GEOMETRY, amplitude=e.amp)
    return heard, [f for f in (*result.edges, *result.corners) if f.depth < 1.0]


def test_a_weak_edge_two_capsules_hear_off_the_fan_is_an_edge_once_its_echo_is_taken_back():
    # A diffracting edge (0.15 of a mirror's echo) beside the stack, over the threshold in the two capsules nearest
    # it.  Its ranges' slope along the stack puts it ~10° off the fan from them: taken back through the beam
    # pattern from there (3 σ farther out), its echo is still far under a mirror's.
    heard, found = _two_capsule_target(0.18, 0.15, seed=7)
    assert heard.sum() == 2  # the premise: part of the stack hears it
    assert len(found) == 1
    f = found[0]
    assert f.kind == "edge" and f.settled, f.reasons
    assert any("taken back" in r for r in f.reasons)
    off = f.point - np.array([0.18, 0.6, 0.0])
    off[2] = 0.0
    dist = float(np.linalg.norm(off))
    assert dist <= 3 * math.sqrt(float(off @ f.covariance @ off)) / dist


def test_a_strong_target_two_capsules_hear_far_off_the_fan_is_not_called_an_edge():
    # A concave corner's echo (1.5 of a mirror's) far out on the beam's flank is as weak there as an edge's near
    # the axis; its slope puts it far enough off the fan that, taken back, it could be a mirror's: kind left open.
    heard, found = _two_capsule_target(0.32, 1.5, seed=7)
    assert heard.sum() == 2
    assert found
    for f in found:
        assert not (f.kind == "edge" and f.settled), f.reasons
        assert f.kind == "corner" or any(OFF_FAN in r for r in f.reasons)


@pytest.mark.parametrize("seed", range(6))
def test_a_line_across_the_stack_heard_unevenly_is_placed_by_its_exact_ranges_within_its_sigma(seed):
    # A vertical edge 0.9 m ahead, 0.15 m along the stack: every capsule hears it, the farthest only on some steps.
    # Its ranges are a hyperbola along the stack; a straight or quadratic fit over unevenly heard capsules turns its
    # higher terms into a slope, which moves the point along the stack by more than its σ.
    x0, y0 = 0.15, 0.9
    e = Echoes(seed=100 + seed)
    e.plane(0.0, 2.5)
    e.across_line(np.array([x0, y0, 0.0]), VERTICAL, gain=0.3)
    ranges = e.ranges()
    far = int(np.argmin(GEOMETRY.capsule_x))
    drop = np.random.default_rng(seed).random(ranges.shape[0]) < 0.6
    ranges[drop & (ranges[:, far] < 1.5), far] = np.nan
    result = extract_surfaces(GAMMA, ranges, GEOMETRY, amplitude=e.amp)
    found = [f for f in (*result.edges, *result.corners) if abs(f.depth - math.hypot(x0, y0)) < 0.05]
    assert len(found) == 1, [(f.kind, f.depth, f.reasons) for f in (*result.edges, *result.corners)]
    f = found[0]
    assert any("curve along the capsule stack" in r for r in f.reasons)
    off = f.point - np.array([x0, y0, 0.0])
    off[2] = 0.0
    dist = float(np.linalg.norm(off))
    assert dist <= 3 * math.sqrt(float(off @ f.covariance @ off)) / dist
    assert dist < 0.005
