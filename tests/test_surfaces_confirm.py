"""A plane claims good only where the sweep confirms it a plane and its σ places its trace within 2 cm.

Analytic sweeps built by hand (:class:`tests.test_surfaces.Echoes`): a lone retro-reflecting corner, an edge as
strong as a wall, a wall alone and two walls with their corner; the accuracy bound from the σ by hand; the
capsules' own beam-pattern peaks with one echo and with a second summed in.
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
