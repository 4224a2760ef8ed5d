"""Every wall a sweep sees makes its own plane, and the rules that keep its echoes its own.

* an end whose amplitude a later echo inside the amplitude window lifts is no end of the mirror: the
  window's reach in range, not the range tolerance, bounds the echoes that sum into it;
* a target's echo is strongest at its own bearing: a region weaker at a bearing inside it than elsewhere
  (beyond one beam pattern's change over a step and the amplitude noise) holds no target there, so no
  plane's end is placed there;
* two regions without a bearing on one plane's trace cannot both be its end: the nearer is a wall whose
  corner with the plane the deeper one is, where some bearing it leaves open puts that corner there;
* seeded worlds: walls whose echoes were taken for another item's are found as planes.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from lelsonar.reconstruct.estimate.corner.wall import ECHO_WINDOW_RANGE
from lelsonar.reconstruct.estimate.surfaces import SurfaceOptions
from lelsonar.reconstruct.estimate.surfaces.beam_pattern import weaker_at
from lelsonar.reconstruct.estimate.surfaces.evidence import unseen_corner
from lelsonar.reconstruct.estimate.surfaces.measurement import Measured, handed_over
from lelsonar.reconstruct.estimate.surfaces.regions import Region
from lelsonar.signal.directivity import piston_directivity
from lelsonar.tools.surface_scores import score_scan, world_sweep
from tests.measured_regions import hand_measured

RANGE = 1.8


def _region_after(past: float) -> tuple[Region, np.ndarray]:
    """A region at ``RANGE`` over steps 10–20 of four capsules, the step just before it at ``past``."""
    d = np.full((30, 4), np.nan)
    d[10:21] = RANGE
    d[9] = past
    steps = np.arange(10, 21)
    rows, caps = np.repeat(steps, 4), np.tile(np.arange(4), steps.size)
    return Region(steps=steps, rows=rows, capsules=caps, cut_before=False, cut_after=False), d


@pytest.mark.parametrize(
    ("gap", "sums"),
    [
        (-0.02, True),  # within the region's own band
        (0.05, True),  # later, rising inside the amplitude window
        (2 * SurfaceOptions().range_tolerance + ECHO_WINDOW_RANGE - 0.002, True),
        (2 * SurfaceOptions().range_tolerance + ECHO_WINDOW_RANGE + 0.002, False),  # past the window
        (-0.05, False),  # nearer than the band: it would have set the range itself (a cut)
    ],
)
def test_a_later_echo_inside_the_amplitude_window_sums_into_the_end_it_follows(gap, sums):
    region, d = _region_after(RANGE + gap)
    opts = SurfaceOptions()
    assert handed_over(region, d, (True, False), opts) is sums
    # Only the flagged end is looked past.
    assert handed_over(region, d, (False, True), opts) is False


def _missed(mount: str, family: str, seed: int, pose: int) -> tuple[str, ...]:
    _, scan, _, result = world_sweep(family, seed, pose, mount)
    return score_scan(family, scan, result, seed=seed).missed


@pytest.mark.parametrize(("family", "seed", "pose"), [("room", 4, 0), ("corridor", 7, 1)])
def test_the_wall_ahead_of_a_vertical_fan_is_a_plane_though_its_corner_with_the_floor_lifts_its_end(family, seed, pose):
    # The paper mount: the wall-floor corner answers a few cm behind the wall's mirror at the region's lower
    # end, inside the amplitude window, so that end is strong though the beam fades the mirror there; the
    # region's centre stays the wall's bearing and the wall is no end of the floor.
    assert _missed("paper", family, seed, pose) == ()


KA = 7.0  # a 40 kHz capsule of a few mm: main lobe ±33°
STEP = math.radians(1.0)


def _flank(beta: float, lo: float, hi: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Steps' γ from ``lo`` to ``hi`` (rad) and a mirror's amplitudes at ``beta``, 2 % log-normal noise."""
    gamma = np.arange(lo, hi + 0.5 * STEP, STEP)
    amp = piston_directivity(gamma - beta, KA) ** 2 * np.exp(0.02 * rng.standard_normal(gamma.size))
    return gamma, amp


def test_a_region_is_never_weaker_at_its_own_targets_bearing():
    rng = np.random.default_rng(21)
    for _ in range(200):
        beta = rng.uniform(-0.3, 0.3)
        # Cut anywhere around its target, on either side.
        lo, hi = beta - rng.uniform(0.05, 0.5), beta + rng.uniform(0.05, 0.5)
        g, a = _flank(beta, lo, hi, rng)
        assert not weaker_at(g, a, beta)


def test_a_region_cut_before_its_peak_is_weaker_inside_it_than_at_its_cut_end():
    rng = np.random.default_rng(22)
    # The target 10° before the region's first step: the region is its flank, rising toward the cut end.
    g, a = _flank(math.radians(-10.0), 0.0, math.radians(30.0), rng)
    assert weaker_at(g, a, math.radians(20.0))
    assert not weaker_at(g, a, math.radians(0.4))  # within a step of the strongest end
    assert not weaker_at(g, a, math.radians(-3.0))  # past the span: the test says nothing there


@pytest.mark.parametrize(("family", "seed", "pose"), [("l_room", 9, 0), ("boxes", 2, 1)])
def test_a_wall_cut_by_a_nearer_echo_is_no_end_placed_where_its_echo_is_weaker(family, seed, pose):
    # The fan mount: a wall's region cut on one side holds its foot, or its flank; the trace of a plane
    # crosses its depth inside it where its echo is far under its strongest step, so it is no end there.
    assert _missed("fan", family, seed, pose) == ()


def _measured(bearing: float, depth: float, span: tuple[float, float], cut: tuple[bool, bool]) -> Measured:
    """What a region says, as far as the placement tests read it (angles in degrees)."""
    steps = np.arange(3)
    region = Region(steps=steps, rows=steps, capsules=np.zeros(3, dtype=np.intp), cut_before=cut[0], cut_after=cut[1])
    return hand_measured(
        region,
        bearing=math.radians(bearing),
        depth=depth,
        span=(math.radians(span[0]), math.radians(span[1])),
        step=STEP,
        bearing_stderr=0.003,
        bearing_source="undetermined" if any(cut) else "region centre",
        tilt_stderr=0.001,
    )


def test_a_wall_past_the_sweeps_start_and_its_corner_with_a_seen_wall_explain_two_regions_together():
    # Plane j seen at its foot (−80°, 0.65 m); a wall at right angles 2.85 m away, its foot at −170°, past the
    # sweep's start at −150°: its flank is a region at 2.85 m cut by the sweep's start, and their corner, at
    # √(0.65² + 2.85²) = 2.923 m and −157.2°, a region cut by that nearer one.
    j = _measured(-80.0, 0.65, (-117.0, -43.0), (False, False))
    wall = _measured(-147.0, 2.85, (-150.0, -145.0), (True, False))
    corner = _measured(-136.0, 2.923, (-142.0, -131.0), (True, False))
    opts = SurfaceOptions()
    beta = unseen_corner(wall, corner, j, opts)
    assert beta is not None
    # The bearing that puts the corner at its depth is the wall's, within what 3 cm of depth allows.
    assert abs(math.degrees(beta) + 170.0) < 3.0, math.degrees(beta)
    # Not the other way round: a wall at the corner's depth meets j deeper still.
    assert unseen_corner(corner, wall, j, opts) is None
    # A deeper region out of the corner's reach (faded, not cut, short of it) is no corner of that wall.
    far = _measured(-100.0, 2.923, (-104.0, -96.0), (False, False))
    assert unseen_corner(wall, far, j, opts) is None


@pytest.mark.parametrize(("family", "seed", "pose"), [("room", 8, 0), ("l_room", 5, 1)])
def test_a_wall_past_the_sweeps_start_beside_its_corner_is_a_plane_not_the_end_of_another(family, seed, pose):
    # The fan mount: a wall's foot lies past the sweep's start, its flank a region cut there; beside it, its
    # corner with a wall seen at its foot, masked on that side by the wall's nearer mirror.  Both fit the seen
    # wall's trace; the nearer is the wall, the deeper its corner.
    assert _missed("fan", family, seed, pose) == ()
