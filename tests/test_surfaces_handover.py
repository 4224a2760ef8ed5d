"""Two targets at one range in one region, and a wall separated from its corner by its own line with the floor.

* a region cut by a nearer echo whose amplitude hands over from a face's flank to its own edge splits at the
  jump, each piece keeping the region's cut on its outer side and the hand-over on the jump's; one flank alone
  never splits;
* a piece whose end another echo took over at a like range does not calibrate the sweep's beam: that echo sums
  into its profile there;
* a wall's mirror and its corner with a seen plane stay beside each other across a region at a depth between
  theirs (on the wall's trace), not across a nearer one nor across a plane's own foot;
* seeded dev worlds: a box's face ending at its own edge, cut by a nearer edge, is found; the beam the split
  pieces leave uncalibrated still places a far wall beside its unseen corner by its flank, past a cut by a much
  nearer echo; a far wall beside its corner across the wall's line with the floor is found.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from lelsonar.reconstruct.estimate.surfaces import SurfaceOptions
from lelsonar.reconstruct.estimate.surfaces.evidence import on_the_way, walls_of_unseen_corners
from lelsonar.reconstruct.estimate.surfaces.jump_split import split_jump
from lelsonar.reconstruct.estimate.surfaces.measurement import measure_region
from lelsonar.reconstruct.estimate.surfaces.piston_beam import sweep_beam
from lelsonar.reconstruct.estimate.surfaces.regions import find_regions
from lelsonar.signal.directivity import piston_directivity
from lelsonar.tools.surface_scores import score_scan, world_sweep
from tests.test_surfaces_flank_bearing import GAMMA, GEOMETRY, KA, RANGE_NOISE
from tests.test_surfaces_recall import _measured


def _face_then_edge(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A nearer post over steps 90–99, then at 1.5 m a face's rising flank (its foot at step 140, past the face's
    end) over steps 100–119 and its own edge's weak diffraction (peak at step 128) over steps 120–139."""
    rng = np.random.default_rng(seed)
    d = np.full((GAMMA.size, 4), np.nan)
    a = np.full((GAMMA.size, 4), np.nan)
    post, face, edge = np.arange(90, 100), np.arange(100, 120), np.arange(120, 140)
    d[post] = 0.6 + rng.normal(0.0, RANGE_NOISE, (post.size, 4))
    a[post] = 0.3
    d[face] = 1.5 + rng.normal(0.0, RANGE_NOISE, (face.size, 4))
    d[edge] = 1.5 + rng.normal(0.0, RANGE_NOISE, (edge.size, 4))
    a[face] = (1.2 * piston_directivity(GAMMA[face] - GAMMA[140], KA) ** 2)[:, None] * np.ones(4)
    a[edge] = (0.08 * piston_directivity(GAMMA[edge] - GAMMA[128], KA) ** 2)[:, None] * np.ones(4)
    a *= np.exp(0.01 * rng.normal(size=a.shape))
    return d, a


def test_a_cut_region_whose_amplitude_hands_over_from_a_face_to_its_edge_splits_there():
    d, a = _face_then_edge(seed=3)
    opts = SurfaceOptions()
    (region,) = [r for r in find_regions(d) if r.steps[0] == 100]
    m = measure_region(region, GAMMA, d, a, GEOMETRY, opts)
    assert m.region.cut_before  # the nearer post cuts it
    first, second = split_jump(m, GAMMA, d, a, GEOMETRY, opts)
    assert np.array_equal(first.region.steps, np.arange(100, 120))
    assert np.array_equal(second.region.steps, np.arange(120, 140))
    assert first.region.cut_before and first.region.cut_after and second.region.cut_before
    assert first.handed_over == (False, True) and second.handed_over == (True, False)
    # The face's flank alone, its peak past the cut: one beam pattern, nothing to split.
    a[120:140] = (1.2 * piston_directivity(GAMMA[120:140] - GAMMA[140], KA) ** 2)[:, None] * np.ones(4)
    m = measure_region(region, GAMMA, d, a, GEOMETRY, opts)
    assert split_jump(m, GAMMA, d, a, GEOMETRY, opts) is None


def test_a_region_whose_end_another_echo_took_over_does_not_calibrate_the_beam():
    rng = np.random.default_rng(8)
    d = np.full((GAMMA.size, 4), np.nan)
    a = np.full((GAMMA.size, 4), np.nan)
    steps = np.arange(100, 160)
    d[steps] = 1.5 + rng.normal(0.0, RANGE_NOISE, (steps.size, 4))
    a[steps] = (1.2 * piston_directivity(GAMMA[steps] - GAMMA[130], KA) ** 2)[:, None] * np.exp(
        0.01 * rng.normal(size=(steps.size, 4))
    )
    (region,) = find_regions(d)
    m = measure_region(region, GAMMA, d, a, GEOMETRY, SurfaceOptions())
    beam = sweep_beam([m], GAMMA, a, KA)
    assert beam is not None and abs(beam.ka - KA) < 3 * beam.ka_stderr + 0.05
    assert sweep_beam([replace(m, handed_over=(False, True))], GAMMA, a, KA) is None


def test_a_wall_and_its_corner_stay_beside_each_other_across_a_line_on_the_walls_trace():
    # Plane j at its foot (90°, 0.41 m); a wall 3.505 m away, its region cut before; their corner 3.53 m away;
    # between them in the sweep the wall's own line with the floor, 3.52 m away.
    opts = SurfaceOptions()
    j = replace(_measured(90.0, 0.41, (60.0, 120.0), (False, False)), bearing=math.radians(52.6))
    wall = _measured(-22.0, 3.505, (-27.5, -17.6), (True, False))
    line = _measured(-15.5, 3.520, (-16.4, -14.6), (True, False))
    corner = _measured(-10.0, 3.530, (-13.5, -7.6), (True, False))
    assert on_the_way(line, wall, corner, opts)
    regions = [j, wall, line, corner]
    found = walls_of_unseen_corners(regions, [0], [False] * 4, set(), GAMMA, opts)
    assert 1 in found
    # A nearer target between them would hide the corner: they are not one wall and its corner.
    post = replace(line, depth=1.9, ranges=np.full(3, 1.9))
    assert not on_the_way(post, wall, corner, opts)
    assert 1 not in walls_of_unseen_corners([j, wall, post, corner], [0], [False] * 4, set(), GAMMA, opts)
    # Nor is a plane's own foot between them, at whatever depth: a wall of its own answers there.
    foot = replace(line, bearing_source="region centre", region=replace(line.region, cut_before=False))
    assert 1 not in walls_of_unseen_corners([j, wall, foot, corner], [0, 2], [False] * 4, set(), GAMMA, opts)


def _fan_record(family: str, seed: int, pose: int):
    _, scan, amp, result = world_sweep(family, seed, pose)
    return score_scan(family, scan, result, seed=seed, amplitude=amp), result, scan


def test_a_box_face_ending_at_its_own_edge_past_a_nearer_edge_is_found_and_the_edge_too():
    record, result, scan = _fan_record("boxes", 7, 1)
    assert not any(" element 14 " in line for line in record.missed)  # the face
    edges = [f for f in result.edges if np.mean(scan.echo_index[f.rows, f.capsules] == 68) > 0.5]
    assert edges  # its own edge, a feature apart from the face's region


def test_the_split_pieces_leave_a_far_walls_flank_its_beam_and_it_stays_a_plane_placed_by_it():
    record, result, scan = _fan_record("boxes", 31, 1)
    assert not any(" element 0 " in line for line in record.missed)
    assert not any(np.mean(scan.echo_index[f.rows, f.capsules] == 0) > 0.5 for f in result.corners)
    # A wall beside its unseen corner, cut by a much nearer echo: its flank places it, within its σ.
    (s,) = [s for s in result.surfaces if np.mean(scan.echo_index[s.rows, s.capsules] == 0) > 0.5]
    assert any("flank" in r for r in s.reasons) and s.quality != "good"
    (p,) = [p for p in record.planes if p.element == 0]
    assert abs(p.bearing_z) <= 3.0, p.bearing_z


def test_a_far_wall_beside_its_corner_across_its_line_with_the_floor_is_found():
    record, _result, _scan = _fan_record("boxes", 34, 0)
    assert not any(" element 3 " in line for line in record.missed)
    walls = [p for p in record.planes if p.element == 3]
    assert walls and all(p.flagged for p in walls)
