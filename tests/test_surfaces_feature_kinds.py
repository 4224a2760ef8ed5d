"""A corner's or an edge's kind stands only where its own echoes admit what gave it: an end whose echo fades toward
its placement, a pair corner whose own bearing is elsewhere, a double bounce no farther than its plane's mirror
each say their kind is not settled (never a false corner), and the map leaves them out."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lelsonar.reconstruct.estimate.surfaces import SurfaceOptions
from lelsonar.reconstruct.estimate.surfaces.features import (
    ALIKE,
    NOT_ITS_END,
    NOT_THEIR_LINE,
    falls_toward,
    like_its_mirror,
    pair_denied,
    placement_caveats,
)
from lelsonar.reconstruct.estimate.surfaces.measurement import Measured
from lelsonar.reconstruct.estimate.surfaces.regions import Region
from lelsonar.reconstruct.estimate.surfaces.strength import EchoScale
from lelsonar.sim.world_geometry import ElementKind
from lelsonar.tools.surface_scores import majority, world_sweep
from tests.measured_regions import hand_measured

#: The beam's curvature in log amplitude (1/rad²): a piston of ka ≈ 6.6, two-way.
BEAM_K = 6.0
STEP = math.radians(0.88)


def _flank(source: float, lo: float, hi: float, rng: np.random.Generator, noise: float = 0.02):
    """Steps from ``lo`` to ``hi`` (rad) hearing one target at ``source``: ``log A = −k (γ − β)²`` plus noise."""
    g = np.arange(lo, hi + STEP / 2, STEP)
    return g, np.exp(-BEAM_K * (g - source) ** 2 + noise * rng.standard_normal(g.size))


def test_an_echo_rises_toward_its_source_past_its_span_and_falls_away_from_it():
    rng = np.random.default_rng(5)
    # The target 12° before the region: the region is its flank, rising toward the target.
    g, a = _flank(math.radians(-12.0), 0.0, math.radians(15.0), rng)
    assert falls_toward(g, a, math.radians(-12.0)) == 0.0
    assert falls_toward(g, a, math.radians(-30.0)) == 0.0  # farther the same way: still rising toward it
    # Past the other end the echo fades toward the bearing: no one target there.
    assert falls_toward(g, a, math.radians(25.0)) > 0.0
    # Inside the span the test says nothing.
    assert falls_toward(g, a, math.radians(5.0)) == 0.0


def test_a_flat_echo_falls_toward_neither_side():
    # A clipped top or a target far off the beam's axis on both sides alike: no slope beyond the noise.
    rng = np.random.default_rng(6)
    g = np.arange(0.0, math.radians(10.0), STEP)
    a = np.exp(0.02 * rng.standard_normal(g.size))
    assert falls_toward(g, a, math.radians(-10.0)) == 0.0
    assert falls_toward(g, a, math.radians(20.0)) == 0.0


def _measured(
    bearing: float, depth: float, *, source: str = "region centre", cut: tuple[bool, bool] = (False, False)
) -> Measured:
    """A region at ``bearing`` (deg) and ``depth`` seen by one capsule on the fan's axis, 11 steps either side."""
    steps = np.arange(23)
    region = Region(steps=steps, rows=steps, capsules=np.zeros(23, dtype=np.intp), cut_before=cut[0], cut_after=cut[1])
    b = math.radians(bearing)
    return hand_measured(
        region, bearing=b, depth=depth, span=(b - 11 * STEP, b + 11 * STEP), step=STEP, bearing_source=source
    )


def _scale() -> EchoScale:
    nan = float("nan")
    return EchoScale(gamma=np.zeros(23), opts=SurfaceOptions(), mirror=nan, beam_k=nan, beam_low=nan, full_scale=nan)


@pytest.mark.parametrize("apart_deg", [0.0, 1.0])
def test_a_corner_whose_own_bearing_is_its_planes_lines_is_theirs(apart_deg):
    # Their line's point 2.5 m away at 30°, known to 0.1°: a region centred within its own σ (0.5°) of it.
    own = _measured(30.0 + apart_deg, 2.5)
    b = math.radians(30.0)
    point = 2.5 * np.array([0.0, math.cos(b), math.sin(b)])
    cov = np.diag([1e-6, 1e-6, 1e-6])
    assert pair_denied(own, point, cov, _scale()) == ""


@pytest.mark.parametrize(("source", "cut"), [("region centre", (False, False)), ("amplitude peak", (True, False))])
def test_a_region_whose_own_bearing_is_off_its_planes_line_is_not_their_double_bounce(source, cut):
    # The same line, the region's own bearing 9° away: 3 σ of both is 1.5°.  A region centre (uncut) or an
    # amplitude peak on an uncut side points the beam at its echo's source: not their line's.
    own = _measured(39.0, 2.5, source=source, cut=cut)
    b = math.radians(30.0)
    point = 2.5 * np.array([0.0, math.cos(b), math.sin(b)])
    why = pair_denied(own, point, np.diag([1e-6, 1e-6, 1e-6]), _scale())
    assert why.startswith(NOT_THEIR_LINE) and "39.0°" in why, why


def test_a_peak_between_two_nearer_echoes_does_not_deny_the_line():
    # Cut on both sides, a nearer echo bends each flank where it cuts: no stretch of the echo's own places its peak.
    own = _measured(39.0, 2.5, source="amplitude peak", cut=(True, True))
    b = math.radians(30.0)
    point = 2.5 * np.array([0.0, math.cos(b), math.sin(b)])
    assert pair_denied(own, point, np.diag([1e-6, 1e-6, 1e-6]), _scale()) == ""


@pytest.mark.parametrize(("z", "alike"), [(0.07, True), (0.30, False)])
def test_a_double_bounce_with_a_surface_across_the_fan_is_told_from_its_planes_mirror_by_its_extra_range(z, alike):
    # A plane 1.77 m deep, both depths known to 0.7 mm (3 σ of their difference: 3 mm).  A surface 7 cm off the
    # fan puts the double bounce z²/(2h) = 1.4 mm behind the mirror (a plane leaning 2.3° along the stack echoes
    # alike); 30 cm off, 25 mm behind.
    pj = _measured(0.0, 1.77)
    own = _measured(25.0, 1.77 + math.hypot(1.77, z) - 1.77)
    pj = Measured(**{**pj.__dict__, "depth_stderr": 0.0005})
    own = Measured(**{**own.__dict__, "depth_stderr": 0.0005})
    placed = Measured(**{**own.__dict__, "tilt": math.atan2(z, 1.77)})
    why = like_its_mirror(placed, own, pj)
    assert bool(why) == alike, why
    if alike:
        assert why.startswith(ALIKE) and placement_caveats([why])


def _features_of(mount: str, family: str, seed: int, pose: int, element: int):
    model, scan, _, result = world_sweep(family, seed, pose, mount)
    mine = [f for f in (*result.corners, *result.edges) if majority(scan, f.steps, f)[0] == element]
    return model, mine


@pytest.mark.parametrize(
    ("family", "seed", "pose", "element", "truth"),
    [("boxes", 4, 1, 53, ElementKind.EDGE), ("boxes", 6, 2, 0, ElementKind.MIRROR)],
)
def test_an_end_whose_echo_fades_toward_its_placement_claims_no_kind(family, seed, pose, element, truth):
    # Fan mount: a box's edge (and a wall's flank) at the range where a plane's trace reaches it, placed there
    # because its own bearing is undetermined, while its echo fades toward that placement: no corner there.
    model, mine = _features_of("fan", family, seed, pose, element)
    assert model.elements[element].kind == truth
    assert mine
    for f in mine:
        assert not (f.kind == "corner" and f.settled), f.reasons
        # Its own kind, settled by its own echo's strength, or the end's placement denied (and its kind left open).
        right = truth == ElementKind.EDGE and f.kind == "edge" and f.settled
        assert right or (any(r.startswith(NOT_ITS_END) for r in f.reasons) and placement_caveats(f.reasons))


def test_a_walls_flank_off_two_planes_line_by_its_own_bearing_is_no_corner():
    # Vertical fan, corridor world 3, pose 2: the end wall's middle region (its own centre at 1.2°) at the range of
    # the floor's line with a piece of the same wall measured 15° off: their line's point is 9° from its centre.
    # (Its flank past the nearer echo that cuts it has no bearing of its own: nothing there denies the line.)
    model, mine = _features_of("paper", "corridor", 3, 2, 0)
    assert model.elements[0].kind == ElementKind.MIRROR
    centred = [f for f in mine if any("region centre puts its echo's source" in r for r in f.reasons)]
    assert len(centred) == 1
    assert not centred[0].settled and placement_caveats(centred[0].reasons)


def test_a_leaning_walls_flank_is_not_its_double_bounce_with_the_floor():
    # Vertical fan, boxes world 2, pose 1: a wall's flanks either side of a box edge slope along the stack with the
    # wall's lean, 5 mm deeper than its foot; the floor 7 cm off the fan would put its double bounce 1.4 mm behind.
    model, mine = _features_of("paper", "boxes", 2, 1, 4)
    assert model.elements[4].kind == ElementKind.MIRROR
    assert mine
    for f in mine:
        assert not (f.kind == "corner" and f.settled), f.reasons
        assert any(r.startswith(ALIKE) for r in f.reasons)
