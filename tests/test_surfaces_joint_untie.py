"""The joint corner fit unties what the walls' own echoes dispute, and a trimmed plane keeps its beam pattern's peak.

* :func:`~lelsonar.reconstruct.estimate.surfaces.fitting.joint_fit`: a corner whose double bounce pulls a wall off
  its own bearing by more than 3 σ pulls the walls tied to it too; those are fitted again without it.
* :func:`~lelsonar.reconstruct.estimate.surfaces.flanks.trimmed_centre`: the trimmed core's centre and its own
  amplitude peak are two measurements of one bearing, weighed together as any region's
  (:func:`~lelsonar.reconstruct.estimate.surfaces.measurement.centre_with_peak`).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from lelsonar.reconstruct.estimate.surfaces import SurfaceOptions
from lelsonar.reconstruct.estimate.surfaces.beam_pattern import bearing_from_amplitude
from lelsonar.reconstruct.estimate.surfaces.fitting import joint_fit
from lelsonar.reconstruct.estimate.surfaces.flanks import trimmed_centre
from lelsonar.reconstruct.estimate.surfaces.measurement import Measured, centre_with_peak, measure_region
from lelsonar.reconstruct.estimate.surfaces.regions import Region, find_regions, subregion
from lelsonar.signal.energy import echo_amplitude
from lelsonar.tools.map_worlds import sweep
from lelsonar.tools.stress_world_score import estimate_of, world_run
from lelsonar.tools.stress_worlds import draw_stress_world
from lelsonar.tools.surface_scores import score_scan, world_sweep
from tests.measured_regions import hand_measured
from tests.test_surfaces import GAMMA, GEOMETRY, Echoes

RADIAL = 0.03
CAPSULE_X = np.array([-0.12, -0.04, 0.04, 0.12])
NOISE = 0.002


def _normal(bearing: float) -> np.ndarray:
    return np.array([0.0, math.cos(bearing), math.sin(bearing)])


def _capsules(gamma: np.ndarray) -> np.ndarray:
    g = np.repeat(gamma, CAPSULE_X.size)
    return np.stack([np.tile(CAPSULE_X, gamma.size), RADIAL * np.cos(g), RADIAL * np.sin(g)], axis=1)


def _measured(positions: np.ndarray, ranges: np.ndarray, bearing: float, stderr: float, depth: float) -> Measured:
    """A region with these readings, measured at ``bearing`` ± ``stderr`` and ``depth`` (no tilt)."""
    n = ranges.size
    steps = np.arange(n // CAPSULE_X.size)
    region = Region(
        steps=steps,
        rows=np.repeat(steps, CAPSULE_X.size),
        capsules=np.tile(np.arange(CAPSULE_X.size), steps.size),
        cut_before=False,
        cut_after=False,
    )
    return hand_measured(
        region,
        bearing=bearing,
        depth=depth,
        span=(bearing - 0.1, bearing + 0.1),
        step=0.02,
        bearing_stderr=stderr,
        depth_stderr=NOISE / math.sqrt(n),
        peak_inside=True,
        positions=positions,
        ranges=ranges,
        stack_sigma=NOISE,
    )


def _room(rng: np.random.Generator, biased: int, bias: float) -> tuple[list[Measured], list[tuple[int, list[int]]]]:
    """Four walls of a rectangle around the array, each measured within its σ, and the three corners between
    neighbours; corner ``biased`` reads ``bias`` m long (another echo ahead of its double bounce)."""
    bearings = [0.1, 0.1 + math.pi / 2, 0.1 + math.pi, 0.1 + 3 * math.pi / 2]
    offsets = [1.6, 1.1, 1.9, 1.3]
    stderr = math.radians(0.3)
    measured: list[Measured] = []
    for b, h in zip(bearings, offsets, strict=True):
        p = _capsules(b + np.linspace(-0.3, 0.3, 31))
        d = h - p @ _normal(b) + rng.normal(0.0, NOISE, len(p))
        measured.append(_measured(p, d, b + rng.normal(0.0, stderr), stderr, h))
    pairs = []
    for k in range(3):
        na, nb = _normal(bearings[k]), _normal(bearings[k + 1])
        ha, hb = offsets[k], offsets[k + 1]
        x = np.linalg.solve(np.array([na[1:], nb[1:]]), np.array([ha, hb]))
        edge = math.atan2(x[1], x[0])
        p = _capsules(edge + np.linspace(-0.1, 0.1, 11))
        d = np.hypot(ha - p @ na, hb - p @ nb) + rng.normal(0.0, NOISE, len(p)) + (bias if k == biased else 0.0)
        measured.append(_measured(p, d, edge, math.radians(3.0), float(np.linalg.norm(x))))
        pairs.append((4 + k, [k, k + 1]))
    return measured, pairs


@pytest.mark.parametrize("seed", range(4))
def test_a_corner_that_pulls_a_wall_off_its_own_bearing_unties_it_and_the_rest_are_fitted_without_it(seed):
    measured, pairs = _room(np.random.default_rng(seed), biased=1, bias=0.025)
    joint, disputed = joint_fit(pairs, measured, SurfaceOptions())
    assert disputed, "the biased corner must pull a wall beyond 3 σ of its own bearing"
    # Every wall still tied is the joint fit of the corners that tie no disputed wall, and agrees with its own
    # bearing: nothing the disputed corner pulled is left in it.
    left = [(i, ties) for i, ties in pairs if not set(ties) & set(disputed)]
    again, none = joint_fit(left, measured, SurfaceOptions())
    assert not none
    assert set(joint) == set(again)
    for j, jw in joint.items():
        assert jw.bearing == again[j].bearing
        assert abs(jw.bearing - measured[j].bearing) <= 3 * measured[j].surface_bearing_stderr
    for text in disputed.values():
        assert "fitted on its own echoes" in text


@pytest.mark.parametrize("seed", range(3))
def test_corners_true_to_their_walls_tie_every_wall(seed):
    measured, pairs = _room(np.random.default_rng(seed), biased=-1, bias=0.0)
    joint, disputed = joint_fit(pairs, measured, SurfaceOptions())
    assert not disputed
    assert set(joint) == {0, 1, 2, 3}


@pytest.mark.parametrize("off_deg", [-30.0, 30.0])
def test_a_corner_whose_far_steps_could_not_hear_the_walls_line_ties_nothing(off_deg):
    measured, pairs = _room(np.random.default_rng(7), biased=-1, bias=0.0)
    reach = SurfaceOptions().beyond_cut
    # The first corner's region moved off its line: its near end within the beam's reach, its far end past it.
    c = measured[4]
    near = c.bearing + math.radians(off_deg)
    far = near + math.copysign(0.8 * reach, off_deg)
    measured[4] = replace(c, span=(min(near, far), max(near, far)))
    assert abs(near - c.bearing) < reach < abs(far - c.bearing)
    joint, disputed = joint_fit(pairs, measured, SurfaceOptions())
    assert not disputed
    assert set(joint) == {1, 2, 3}  # wall 0 meets the others only at that corner
    # Within reach of both ends, it ties them.
    measured[4] = replace(c, span=(c.bearing - 0.5 * reach, c.bearing + 0.5 * reach))
    joint, _ = joint_fit(pairs, measured, SurfaceOptions())
    assert set(joint) == {0, 1, 2, 3}


def test_a_centre_and_a_peak_that_agree_are_weighed_and_a_clipped_or_distant_peak_leaves_the_centre():
    c, sc = 0.30, math.radians(0.4)
    p, sp = 0.30 + math.radians(0.5), math.radians(0.1)
    b, s, w = centre_with_peak(c, sc, (p, sp), True)
    wc, wp = sc**-2, sp**-2
    apart = abs(p - c) / math.hypot(sc, sp)
    assert b == pytest.approx((wc * c + wp * p) / (wc + wp))
    assert s == pytest.approx(max(1.0, apart) / math.sqrt(wc + wp))
    assert w == pytest.approx(wp / (wc + wp))
    assert centre_with_peak(c, sc, (p, sp), False) == (c, sc, 0.0)
    assert centre_with_peak(c, sc, None, True) == (c, sc, 0.0)
    assert centre_with_peak(c, sc, (c + 4 * math.hypot(sc, sp), sp), True) == (c, sc, 0.0)


@pytest.mark.parametrize(("seed", "bearing_deg"), [(51, 25.0), (52, -70.0), (53, 110.0)])
def test_a_trimmed_core_weighs_its_trimmed_centre_with_its_own_amplitude_peak(seed, bearing_deg):
    bearing, offset = math.radians(bearing_deg), 2.0
    e = Echoes(seed=seed)
    e.plane(bearing, offset)
    d = e.ranges()
    (region,) = find_regions(d)
    steps = region.steps
    core = subregion(region, steps[:-1], False, False)
    m = measure_region(core, GAMMA, d, e.amp, GEOMETRY, SurfaceOptions())
    bare = measure_region(core, GAMMA, d, None, GEOMETRY, SurfaceOptions())
    centre = trimmed_centre(bare, GAMMA, (None, int(steps[-1])))
    t = trimmed_centre(m, GAMMA, (None, int(steps[-1])))
    peak = bearing_from_amplitude(GAMMA[core.steps], m.step_amplitude)
    assert peak is not None
    expected = centre_with_peak(centre.bearing, centre.bearing_stderr, peak, True)
    assert t.bearing == pytest.approx(expected[0])
    assert t.bearing_stderr == pytest.approx(expected[1])
    assert t.bearing_stderr < centre.bearing_stderr
    assert abs(t.bearing - bearing) <= 3 * t.bearing_stderr


def _wall(family: str, seed: int, pose: int, element: int, mount: str = "fan"):
    ws = world_sweep(family, seed, pose, mount)
    rec = score_scan(family, ws.scan, ws.result, seed=seed, amplitude=ws.amplitude)
    (plane,) = [p for p in rec.planes if p.element == element]
    return plane


@pytest.mark.slow
@pytest.mark.parametrize(
    ("family", "seed", "pose", "element"),
    [
        # A wall's region trimmed of its corner with the floor at both ends: its centre 0.7° off, its peak on it.
        ("l_room", 22, 2, 1),
        # A wall trimmed so, tied at a corner to a wall whose own centre and peak agree: the joint fit, told only
        # the trimmed centre, spread the first wall's error over both.
        ("boxes", 24, 0, 1),
        # In a corridor's middle: a corner of the far wall with the wall behind, tied to the far wall and the wall
        # ahead (their line the same distance away, mirrored across the array, out of its steps' beams).
        ("corridor", 34, 0, 3),
        ("maze", 37, 2, 5),
    ],
)
def test_in_simulated_worlds_a_wall_is_good_within_three_times_its_oracle(family, seed, pose, element):
    plane = _wall(family, seed, pose, element)
    assert plane.quality == "good"
    assert plane.within_oracle, f"{100 * plane.error:.2f} cm, oracle {100 * plane.oracle:.2f} cm"


@pytest.mark.slow
def test_in_a_stress_world_a_ceiling_tied_to_a_disputed_wall_keeps_its_own_bearing():
    # Paper mount, two large boxes: a wall's own mirror echoes cut into pieces that pass for its corners pull it
    # 2° off its beam pattern (disputed); the ceiling tied to it at their true corner was left with the pull.
    world = draw_stress_world("boxes_large", 5, "paper")
    run = world_run(world, 5)
    scan = sweep(run, 0)
    amplitude = echo_amplitude(scan.waveforms, scan.sample_rate, scan.t0, scan.tof)
    rec = score_scan("boxes_large", scan, estimate_of(scan).surfaces, seed=5, amplitude=amplitude)
    (ceiling,) = [p for p in rec.planes if p.element == 10]
    assert ceiling.kind == "ceiling"
    assert ceiling.quality == "good"
    assert ceiling.within_oracle, f"{100 * ceiling.error:.2f} cm, oracle {100 * ceiling.oracle:.2f} cm"
