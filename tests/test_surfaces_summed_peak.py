"""A second echo summed into part of the capsule stack bends the amplitude peak; the bearing's σ says so.

One target's echo peaks at one γ in every capsule (their beams are parallel), so the capsules' own peaks
spread only by their noise.  Another echo at a like range summing into the amplitude window of some capsules
only (its path differs from capsule to capsule) moves their peaks and the summed peak with them, which the
parabola through the steps' medians does not show.  The surface's σ holds that spread through the peak's share
of the bearing, for a whole region and for a core trimmed of another target's steps, whose trimmed centre is
weighed with its peak anew (:func:`~lelsonar.reconstruct.estimate.surfaces.flanks.trimmed_centre`).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from lelsonar.reconstruct.estimate.surfaces import SurfaceOptions
from lelsonar.reconstruct.estimate.surfaces.beam_pattern import (
    bearing_from_amplitude,
    capsule_peak_spread,
    unfaded_ends,
)
from lelsonar.reconstruct.estimate.surfaces.flanks import trimmed_centre
from lelsonar.reconstruct.estimate.surfaces.measurement import centre_with_peak, measure_region, step_table
from lelsonar.reconstruct.estimate.surfaces.regions import find_regions, subregion
from lelsonar.reconstruct.estimate.surfaces.symmetry import flank_asymmetry
from tests.test_surfaces import BEAM, GAMMA, GEOMETRY, Echoes

#: The second echo's share of the wall's at its own peak, and how far its peak lies from the wall's (rad).
SECOND_WEIGHT = 0.25
SECOND_OFFSET = math.radians(10.0)


def _wall_with_a_second_echo(seed: int, bearing: float, offset: float, bent: tuple[int, ...]):
    """A plane's sweep whose capsules ``bent`` also hear a second echo's amplitude summed into the plane's, peaking
    :data:`SECOND_OFFSET` past the plane's bearing: the ranges stay the plane's (the first echo sets them)."""
    e = Echoes(seed=seed)
    e.plane(bearing, offset)
    d = e.ranges()
    amp = e.amp.copy()
    second = SECOND_WEIGHT * np.exp(-(((GAMMA - bearing - SECOND_OFFSET) / BEAM) ** 2)) / (2 * offset)
    heard = np.isfinite(amp)
    for c in bent:
        amp[:, c] = np.where(heard[:, c], amp[:, c] + second, amp[:, c])
    return d, amp


@pytest.mark.parametrize(("seed", "bearing_deg"), [(61, 30.0), (62, -75.0), (63, 115.0)])
def test_a_peak_bent_in_half_the_stack_widens_the_bearing_it_weighs_in(seed, bearing_deg):
    bearing, offset = math.radians(bearing_deg), 2.0
    d, amp = _wall_with_a_second_echo(seed, bearing, offset, bent=(2, 3))
    (region,) = find_regions(d)
    steps = region.steps
    core = subregion(region, steps[3:-3], False, False)
    m = measure_region(core, GAMMA, d, amp, GEOMETRY, SurfaceOptions())
    g = GAMMA[core.steps]
    peak = bearing_from_amplitude(g, m.step_amplitude)
    assert peak is not None
    # The summed peak is bent far beyond its parabola's σ: the case this is about.
    assert abs(peak[0] - bearing) > 10 * peak[1]
    assert m.peak_spread == pytest.approx(capsule_peak_spread(g, step_table(core, amp)))
    assert m.peak_spread > 0.5 * abs(peak[0] - bearing)
    nearest = (int(steps[2]), int(steps[-3]))
    t = trimmed_centre(m, GAMMA, nearest)
    # The trimmed centre's σ lets the bent peak in: the peak's share of the bearing brings the spread with it.
    centre = trimmed_centre(measure_region(core, GAMMA, d, None, GEOMETRY, SurfaceOptions()), GAMMA, nearest)
    _, _, weight = centre_with_peak(centre.bearing, centre.bearing_stderr, peak, True)
    assert weight > 0.5
    # (with how far the core's flanks are from mirror images about that bearing, where both its ends fade alike)
    fades = not any(unfaded_ends(g, m.step_amplitude) or (False, False))
    asymmetry = flank_asymmetry(g, m.step_amplitude, t.bearing, t.bearing_stderr) if fades else 0.0
    assert t.summed_spread == pytest.approx(math.hypot(weight * m.peak_spread, asymmetry))
    assert abs(t.bearing - bearing) <= 3 * t.surface_bearing_stderr
    # The whole region (whose bent end may stop stronger than a fade: its peak alone) says so too.
    whole = measure_region(region, GAMMA, d, amp, GEOMETRY, SurfaceOptions())
    assert abs(whole.bearing - bearing) <= 3 * whole.surface_bearing_stderr


@pytest.mark.parametrize("seed", [64, 65])
def test_a_second_echo_every_capsule_shares_adds_no_spread(seed):
    # The second echo summed into every capsule alike bends the summed peak, but no capsule's peak from the
    # others': the spread stays within their noise (a sum that is one beam pattern in every capsule cannot be
    # told from one echo by them).
    bearing, offset = math.radians(20.0), 2.0
    d, amp = _wall_with_a_second_echo(seed, bearing, offset, bent=(0, 1, 2, 3))
    (region,) = find_regions(d)
    m = measure_region(region, GAMMA, d, amp, GEOMETRY, SurfaceOptions())
    peak = bearing_from_amplitude(GAMMA[region.steps], m.step_amplitude)
    assert peak is not None
    assert abs(peak[0] - bearing) > 3 * peak[1]
    assert m.peak_spread < 3 * peak[1] * math.sqrt(2.0)
