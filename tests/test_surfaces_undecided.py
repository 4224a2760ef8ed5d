"""What a region's evidence cannot decide, it says so.

* an end placed on a plane's trace whose beam flank is flat across the region (its σ wider than the region's
  span) agrees with that end only as it would with a wall whose foot lies just past the cut end: its kind is
  not settled; a flank that resolves the region, or whose peak lies far from every cut end, decides;
* a region whose echo ends stronger on one side than the beam fades it, with another echo at a like range
  beyond, is not centred on its target: where its amplitude peak disagrees with its centre, the bearing's σ
  covers their difference;
* seeded dev worlds, one per cause.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from lelsonar.reconstruct.estimate.surfaces import extract_surfaces
from lelsonar.reconstruct.estimate.surfaces.classify import end_undecided
from lelsonar.reconstruct.estimate.surfaces.features import centre_off_peak, kind_unsettled
from lelsonar.reconstruct.estimate.surfaces.regions import Region
from lelsonar.signal.directivity import piston_directivity
from lelsonar.signal.energy import echo_amplitude
from lelsonar.sim.world_geometry import ElementKind, build_model
from lelsonar.sim.world_render import simulate_world_scan
from lelsonar.sim.worlds import draw_world
from lelsonar.tools.stress_world_score import score_world
from lelsonar.tools.stress_worlds import draw_stress_world
from lelsonar.tools.surface_scores import majority, score_scan
from tests.test_surfaces_recall import _measured

REACH = math.radians(40.0)


def _flank(m, peak_deg: float, sigma_deg: float):
    return replace(m, bearing=math.radians(peak_deg), bearing_stderr=math.radians(sigma_deg))


def test_a_flank_flat_across_its_region_cannot_tell_an_end_from_a_wall_past_the_cut():
    # A region from −150° to −145°, cut on both sides by nothing that bends its flank.
    m = _measured(-147.5, 2.1, (-150.0, -145.0), (True, True))
    flat = _flank(m, -147.8, 9.0)
    why = end_undecided(m, flat, (REACH, REACH), math.radians(-149.1))
    assert why and kind_unsettled([why])
    # Resolved within the span, the flank decides, whatever lies past the cut ends.
    assert end_undecided(m, _flank(m, -147.8, 1.5), (REACH, REACH), math.radians(-149.1)) == ""
    # No stretch past a cut end where a wall's foot may lie: nothing else to agree with.
    assert end_undecided(m, flat, (0.0, 0.0), math.radians(-149.1)) == ""


def test_a_flat_flank_far_from_the_cut_end_excludes_a_wall_past_it():
    # Cut after only: a wall's foot would lie in (−145°, −105°]; a flank peaking at −190° ± 9° is 45° short of it,
    # beyond 3 σ.
    m = _measured(-147.5, 2.1, (-150.0, -145.0), (False, True))
    assert end_undecided(m, _flank(m, -190.0, 9.0), (0.0, REACH), math.radians(-149.1)) == ""
    assert end_undecided(m, _flank(m, -160.0, 9.0), (0.0, REACH), math.radians(-149.1)) != ""


def test_a_wall_whose_flat_flank_agrees_with_a_planes_end_is_no_settled_corner():
    # boxes seed 5, pose 1: a wall heard over 6 steps at the sweep's start, on a nearer wall's trace.
    family, seed, pose = "boxes", 5, 1
    model = build_model(draw_world(family, seed, mount="fan"))
    scan = simulate_world_scan(model, pose, seed=seed * 1000 + pose)
    amp = echo_amplitude(scan.waveforms, scan.sample_rate, scan.t0, scan.tof)
    result = extract_surfaces(scan.gamma_measured, scan.distance, scan.geometry, amplitude=amp)
    record = score_scan(family, scan, result, seed=seed)
    assert record.false_features == ()
    on_mirrors = [
        f
        for f in (*result.corners, *result.edges)
        if model.elements[majority(scan, f.steps, f)[0]].kind == ElementKind.MIRROR
    ]
    # The wall is claimed by a feature that says its kind is not settled, and by no settled one.
    assert on_mirrors
    assert not any(f.settled for f in on_mirrors)


KA = 5.13  # a 7 mm piston at 40 kHz


def _centred(peak_deg: float, lo_deg: float, hi_deg: float, sigma_deg: float):
    """A region centred on its span, its amplitudes a mirror's two-way beam about ``peak_deg`` (1 % noise)."""
    gamma = np.radians(np.arange(-120.0, 0.01, 1.0))
    steps = np.flatnonzero((gamma >= math.radians(lo_deg) - 1e-9) & (gamma <= math.radians(hi_deg) + 1e-9))
    g = gamma[steps]
    noise = np.exp(0.01 * np.random.default_rng(3).standard_normal(g.size))
    amp = piston_directivity(g - math.radians(peak_deg), KA) ** 2 * noise
    m = _measured(0.5 * (lo_deg + hi_deg), 1.0, (lo_deg, hi_deg), (False, False))
    region = Region(
        steps=steps, rows=steps, capsules=np.zeros(steps.size, dtype=np.intp), cut_before=False, cut_after=False
    )
    m = replace(m, region=region, step_amplitude=amp, bearing_stderr=math.radians(sigma_deg), clipped=False)
    return gamma, m


def test_a_centre_its_own_amplitude_peak_disputes_has_a_sigma_that_covers_them():
    # Heard from −95° to −59° (centre −77°), its echo peaking at −72°: one end left while still strong.
    gamma, m = _centred(-72.0, -95.0, -59.0, 0.4)
    placed, why = centre_off_peak(m, gamma)
    assert why
    assert placed.bearing == m.bearing
    # The true bearing within 3 σ of the centre the region keeps.
    assert abs(placed.bearing - math.radians(-72.0)) <= 3 * placed.bearing_stderr
    # A centre its peak agrees with keeps its own σ.
    gamma, m = _centred(-77.0, -95.0, -59.0, 0.4)
    assert centre_off_peak(m, gamma) == (m, "")


@pytest.mark.slow
def test_a_one_capsule_edge_off_its_own_centre_claims_no_sigma_it_lacks():
    # clutter stress world, seed 1, fan mount: on pose 2 an edge one capsule hears over 36°, its echo peaking 5°
    # from its region's centre.
    score = score_world("clutter", 1, "fan", draw_stress_world("clutter", 1, "fan"), max_poses=3)
    assert score.counts["features"] > 0
    assert not [line for line in score.failures if "feature > 3σ" in line or "crash" in line]
