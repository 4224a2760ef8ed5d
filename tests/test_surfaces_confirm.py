"""A plane claims good only where the sweep confirms it a plane and its σ places its trace within 2 cm.

Analytic sweeps built by hand (:class:`tests.test_surfaces.Echoes`): a lone retro-reflecting corner, an edge as
strong as a wall, a wall alone and two walls with their corner; the accuracy bound from the σ by hand; the
capsules' own beam-pattern peaks with one echo and with a second summed in; seeded stress worlds (strong box
edges, a wide beam) against the simulator's truth.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from lelsonar.reconstruct.estimate.quality import DEGRADED, GOOD
from lelsonar.reconstruct.estimate.surfaces import extract_surfaces
from lelsonar.reconstruct.estimate.surfaces.beam_pattern import capsule_peak_spread
from lelsonar.reconstruct.estimate.surfaces.confirm import ACCURACY, LONE, TRACE_REACH, confirm_surfaces, trace_stderr
from lelsonar.signal.energy import echo_amplitude
from lelsonar.sim.world_geometry import ElementKind
from lelsonar.tools.map_worlds import sweep
from lelsonar.tools.stress_world_score import world_run
from lelsonar.tools.stress_worlds import draw_stress_world
from lelsonar.tools.surface_oracle import true_plane
from lelsonar.tools.surface_scores import majority
from tests.test_surfaces import GAMMA, GEOMETRY, Echoes


@pytest.mark.parametrize("gain", [1.0, 1.5])
def test_a_lone_vertical_corner_or_strong_edge_is_never_a_good_plane(gain):
    # A vertical line in the fan (a concave corner's double bounce, or an edge as strong as a wall): one range
    # over the beam's width, amplitudes of the beam pattern, as a wall facing the array would give.
    e = Echoes(seed=11)
    e.vertical_line(1.2, 0.9, gain=gain)
    result = extract_surfaces(GAMMA, e.ranges(), GEOMETRY, amplitude=e.amp)
    assert all(s.quality != GOOD for s in result.surfaces)
    assert all(LONE in s.reasons for s in result.surfaces if s.own_quality == GOOD)


def test_walls_that_share_a_corner_confirm_each_other_and_stay_good():
    e = Echoes(seed=3)
    e.plane(0.0, 1.0)
    e.plane(math.pi / 2, 1.5)
    e.vertical_line(1.0, 1.5, gain=1.5)
    result = extract_surfaces(GAMMA, e.ranges(), GEOMETRY, amplitude=e.amp)
    assert len(result.surfaces) == 2
    assert all(s.quality == GOOD and s.own_quality == GOOD for s in result.surfaces)
    assert {label for c in result.corners for label in c.surfaces} == {s.label for s in result.surfaces}


def test_a_surface_whose_sigma_does_not_place_its_trace_within_the_accuracy_is_degraded():
    e = Echoes(seed=3)
    e.plane(0.0, 1.0)
    e.plane(math.pi / 2, 1.5)
    e.vertical_line(1.0, 1.5, gain=1.5)
    result = extract_surfaces(GAMMA, e.ranges(), GEOMETRY, amplitude=e.amp)
    s = result.surfaces[0]
    # By hand: the trace 0.5 m from the foot moves by 0.5 tan σ_n, beside the offset's σ.
    sh = s.plane.offset_stderr
    edge = math.atan(math.sqrt((0.5 * ACCURACY) ** 2 - sh * sh) / TRACE_REACH)
    wide = s.plane.replace_scalars(normal_stderr=1.05 * edge)
    narrow = s.plane.replace_scalars(normal_stderr=0.95 * edge)
    assert trace_stderr(replace(s, plane=wide)) > 0.5 * ACCURACY
    out = confirm_surfaces([replace(s, plane=p) for p in (wide, narrow)], {s.label})
    assert out[0].quality == DEGRADED and "2 σ" in out[0].reasons[-1]
    assert out[1].quality == GOOD
    assert all(o.own_quality == GOOD for o in out)


def test_capsules_peaks_agree_on_one_echo_and_spread_where_a_second_sums_in_with_their_own_phases():
    # Four capsules, one beam pattern D(γ − β)² with 1 % amplitude noise: their own peaks agree within the noise.
    rng = np.random.default_rng(7)
    gamma = np.radians(np.arange(-30.0, 30.0, 0.6))
    beta, width = math.radians(4.0), math.radians(15.0)
    one = np.exp(-(((gamma - beta) / width) ** 2))[:, None] * np.exp(rng.normal(0.0, 0.01, (gamma.size, 4)))
    alone = capsule_peak_spread(gamma, one)
    assert alone < math.radians(0.2)
    # A second echo 12° away, a third as strong, summed in with a phase of its own per capsule (paths differing
    # by wavelengths): each capsule's peak moves its own way, by up to the weight times the separation.
    other = np.exp(-(((gamma - beta - math.radians(12.0)) / width) ** 2))
    phases = np.array([0.0, 0.5 * math.pi, math.pi, 1.5 * math.pi])
    summed = np.abs(one + (1.0 / 3.0) * other[:, None] * np.exp(1j * phases)[None, :])
    spread = capsule_peak_spread(gamma, summed)
    assert spread > 5 * alone and spread < math.radians(12.0) / 3.0
    # Fewer than two capsules with a peak: nothing to compare.
    assert capsule_peak_spread(gamma, one[:, :1]) == 0.0


def _stress_sweep(cls: str, seed: int, pose: int):
    world = draw_stress_world(cls, seed, "fan")
    scan = sweep(world_run(world, seed), pose)
    amp = echo_amplitude(scan.waveforms, scan.sample_rate, scan.t0, scan.tof)
    return scan, extract_surfaces(scan.gamma_measured, scan.distance, scan.geometry, amplitude=amp)


def test_a_box_edge_as_strong_as_a_wall_is_no_good_plane_though_its_far_edges_sit_on_its_trace():
    # Seeded: a box whose edges diffract as strongly as a wall; its near edge's region looks like a wall facing
    # the array, and its two far edges, their bearings undetermined, are set on that "wall's" trace.
    scan, result = _stress_sweep("strong_edges", 5, 2)
    for s in result.surfaces:
        k, _ = majority(scan, s.steps, s)
        if s.quality == GOOD:
            assert k >= 0 and scan.model.elements[k].kind == ElementKind.MIRROR, (s.label, s.reasons)
    edge_planes = [
        s for s in result.surfaces if scan.model.elements[majority(scan, s.steps, s)[0]].kind == ElementKind.EDGE
    ]
    assert edge_planes and all(LONE in s.reasons for s in edge_planes if s.own_quality == GOOD)


def test_a_peak_bearing_an_echo_summed_into_moves_each_capsules_own_way_says_so_in_its_sigma():
    # Seeded: a wide beam (about 52°), a wall's region cut by a nearer echo, its bearing from the amplitude peak,
    # which a second echo in the window pulls by several degrees, differently in each capsule.
    scan, result = _stress_sweep("beam", 6, 0)
    checked = 0
    for s in result.surfaces:
        k, _ = majority(scan, s.steps, s)
        if s.bearing_source != "amplitude peak" or scan.model.elements[k].kind != ElementKind.MIRROR:
            continue
        n_true, _ = true_plane(scan, k)
        err = abs((s.bearing - math.atan2(n_true[2], n_true[1]) + math.pi / 2) % math.pi - math.pi / 2)
        assert err <= 3 * math.sqrt(s.covariance[0, 0]), (s.label, math.degrees(err))
        checked += 1
    assert checked >= 1
