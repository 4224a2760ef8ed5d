"""A region on a plane's trace as that plane's end or a wall of its own: the physics each hypothesis predicts.

* an end (a corner, an edge) is a point seen in the fan: its echo leaves toward it from a capsule that sits
  ``r`` out along its own axis, so its flank is steeper than a mirror's, whose echo leaves along its normal;
  fitted as a mirror's, a near point's flank puts its peak too far out, fitted in the point's own angles it
  does not (:func:`point_angles`);
* a cut by an echo much nearer than the region's range is as clean as the sweep's end: that echo answers wholly
  before the region's amplitude window (:func:`clean_cuts`);
* a wall's foot beside its unseen corner may lie inside its region's span, where no peak shows near a cut end;
* seeded dev worlds, one per cause: a wall once claimed as a corner found (flagged, not good), a near
  corner whose flank a mirror's fit disputes kept as its plane's end, and an edge whose flank disputes every
  placement on a trace an edge still (its echo weak at its own peak).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from lelsonar.reconstruct.estimate.surfaces import SurfaceOptions
from lelsonar.reconstruct.estimate.surfaces.evidence import unseen_corner
from lelsonar.reconstruct.estimate.surfaces.flank_bearing import bearing_from_flank, point_angles
from lelsonar.reconstruct.estimate.surfaces.measurement import clean_cuts
from lelsonar.reconstruct.estimate.surfaces.piston_beam import SweepBeam
from lelsonar.reconstruct.estimate.surfaces.regions import Region
from lelsonar.signal.directivity import piston_directivity
from lelsonar.sim.world_geometry import ElementKind
from lelsonar.tools.surface_scores import majority, score_scan, world_sweep
from tests.test_surfaces_recall import _measured

KA = 5.13  # a 7 mm piston at 40 kHz
RADIAL = 0.03  # m, the capsules' distance from the rotation axis


def _point_profile(gamma: np.ndarray, bearing: float, rho: float, noise: float, seed: int) -> np.ndarray:
    """A point's two-way echo amplitude across γ from a capsule ``RADIAL`` out along its axis, log-normal noise."""
    d = gamma - bearing
    psi = np.abs(np.arctan2(rho * np.sin(d), rho * np.cos(d) - RADIAL))
    amp = piston_directivity(psi, KA) ** 2 / (2 * rho)
    return amp * np.exp(noise * np.random.default_rng(seed).normal(size=gamma.size))


def test_a_near_points_flank_fitted_in_its_own_angles_peaks_at_it_and_as_a_mirrors_too_far_out():
    # A corner 0.75 m away at 0°, seen on its flank from 18° to 28° (its peak past the sweep's start there).
    bearing, rho = 0.0, 0.75
    gamma = np.radians(np.arange(18.0, 28.01, 0.9))
    amp = _point_profile(gamma, bearing, rho, noise=0.005, seed=1)
    beam = SweepBeam(ka=KA, ka_stderr=0.005, n_regions=3)
    reach = math.radians(40.0)
    mirror = bearing_from_flank(gamma, amp, beam, before=reach, after=0.0)
    point = bearing_from_flank(point_angles(gamma, bearing, rho, RADIAL), amp, beam, before=reach, after=0.0)
    assert mirror is not None and point is not None
    assert abs(point[0] - bearing) <= 3 * point[1], (math.degrees(point[0]), math.degrees(point[1]))
    # As a mirror's, too far out by about 2 (r/ρ) u, u the flank's distance from the peak: beyond its own σ.
    u = float(np.mean(gamma)) - bearing
    shift = bearing - mirror[0]
    assert shift > 3 * mirror[1], (math.degrees(shift), math.degrees(mirror[1]))
    assert 0.5 < shift / (2 * RADIAL / rho * u) < 1.5, math.degrees(shift)


def test_a_mirrors_angles_are_the_points_at_infinity():
    gamma = np.radians(np.linspace(-40.0, 40.0, 9))
    far = point_angles(gamma, 0.1, 1e9, RADIAL)
    assert np.allclose(far, gamma, atol=1e-9)
    # Nearer, steeper: farther off the axis than γ − β, and symmetric about the bearing.
    near = point_angles(gamma, 0.0, 0.5, RADIAL)
    assert np.all(np.abs(near[gamma != 0]) > np.abs(gamma[gamma != 0]))
    assert np.allclose(near, -near[::-1])


def _region(first: int, last: int, cut: tuple[bool, bool]) -> Region:
    steps = np.arange(first, last + 1)
    rows = np.repeat(steps, 4)
    capsules = np.tile(np.arange(4), steps.size)
    return Region(steps=steps, rows=rows, capsules=capsules, cut_before=cut[0], cut_after=cut[1])


def test_a_cut_by_a_much_nearer_echo_is_clean_one_at_a_like_range_is_not():
    opts = SurfaceOptions()
    distance = np.full((40, 4), np.nan)
    distance[10:30] = 3.0
    distance[30:33] = 1.2  # much nearer: answers wholly before the region's amplitude window
    distance[7:10] = 3.03  # a like range: rings into (or rises inside) the window
    region = _region(10, 29, (True, True))
    assert clean_cuts(region, distance, opts) == (False, True)
    # An end the region's own echo faded at is no cut at all.
    assert clean_cuts(_region(10, 29, (False, True)), distance, opts) == (False, True)
    distance[7:10] = np.nan
    assert clean_cuts(region, distance, opts) == (True, True)


def test_a_walls_foot_inside_its_cut_region_beside_its_unseen_corner_explains_both():
    # Plane j at its foot (−90°, 0.548 m); a wall at right angles 2.741 m away, its foot at 0°, its region
    # (−24.6° to 2.6°) cut after by a nearer target, no peak showing 2.6° from that cut end; their corner at
    # √(0.548² + 2.741²) = 2.795 m and −11.3°, a region before it cut by the wall's nearer mirror.
    j = _measured(-90.0, 0.548, (-128.6, -51.6), (False, False))
    wall = _measured(-11.0, 2.741, (-24.6, 2.6), (False, True))
    corner = _measured(-32.1, 2.795, (-38.7, -25.5), (False, True))
    opts = SurfaceOptions()
    beta = unseen_corner(wall, corner, j, opts)
    assert beta is not None
    assert abs(math.degrees(beta)) < 6.0, math.degrees(beta)  # within what 3 cm of the corner's depth allows
    # A corner beside the wall that nothing masked on the wall's side (it faded there) is no corner it hides.
    faded = _measured(-32.1, 2.795, (-38.7, -25.5), (False, False))
    assert unseen_corner(wall, faded, j, opts) is None


def _sweep(mount: str, family: str, seed: int, pose: int):
    _, scan, amp, result = world_sweep(family, seed, pose, mount)
    return scan, result, score_scan(family, scan, result, seed=seed, amplitude=amp)


@pytest.mark.slow
@pytest.mark.parametrize(
    ("family", "seed", "pose", "element"),
    [
        ("maze", 26, 0, 4),  # its foot inside its span, beside its corner with a near wall: an unseen corner
        ("boxes", 29, 2, 0),  # the same, at the sweep's end
        ("boxes", 31, 1, 0),  # cut by a much nearer wall: its flank as clean as at the sweep's end
        ("boxes", 0, 1, 3),  # cut on both sides by much nearer targets
        ("boxes", 35, 2, 3),  # at the sweep's start, its flank 4 σ from the corner a point's flank would make
    ],
)
def test_a_wall_on_a_planes_trace_once_claimed_as_its_corner_is_found_and_flagged(family, seed, pose, element):
    _scan, _result, record = _sweep("fan", family, seed, pose)
    assert not any(f" element {element} " in line for line in record.missed), record.missed
    walls = [p for p in record.planes if p.element == element]
    assert walls and all(p.flagged for p in walls)


@pytest.mark.slow
def test_a_near_corner_whose_flank_a_mirrors_fit_puts_too_far_out_stays_its_planes_end():
    # The paper mount: a wall's corner with the floor 0.77 m away, seen on its flank past the sweep's start; as
    # a mirror's its flank peaks 2° past the corner (5 σ), as a point's at it.
    scan, result, record = _sweep("paper", "maze", 8, 0)
    mine = [
        f
        for f in result.corners
        if scan.model.elements[majority(scan, f.steps, f)[0]].kind == ElementKind.DIHEDRAL and f.depth < 0.8
    ]
    assert mine
    assert not [
        s for s in result.surfaces if scan.model.elements[majority(scan, s.steps, s)[0]].kind != ElementKind.MIRROR
    ]
    assert record.false["plane"] == 0


@pytest.mark.slow
@pytest.mark.parametrize(("seed", "pose"), [(4, 1), (33, 0)])
def test_an_edge_whose_flank_no_trace_placement_explains_is_an_edge_at_its_flank_not_a_wall(seed, pose):
    # A box's edge cut on both sides by much nearer targets, its depth on a wall's trace far from its flank's
    # peak: no end there, and at its own peak its echo is a diffraction's, so an edge, not a wall.
    scan, result, _record = _sweep("fan", "boxes", seed, pose)
    overruled = [s for s in result.surfaces if any("a wall of its own" in r for r in s.reasons)]
    for s in overruled:
        element, _ = majority(scan, s.steps, s)
        assert scan.model.elements[element].kind == ElementKind.MIRROR, (s.label, s.reasons)
    edges = [f for f in result.edges if scan.model.elements[majority(scan, f.steps, f)[0]].kind == ElementKind.EDGE]
    assert edges
