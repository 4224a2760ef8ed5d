"""A corner or an edge is on its true line, or its σ covers how far it is, or it says why it is not placed there.

Analytic sweeps (:class:`tests.test_surfaces.Echoes`) for each rule, and the stress worlds' sweeps where a
feature was placed far off its line with a σ of millimetres.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from lelsonar import codec
from lelsonar.reconstruct.estimate import wire
from lelsonar.reconstruct.estimate.surfaces import Feature, extract_surfaces
from lelsonar.reconstruct.estimate.surfaces.features import MIXED, NOT_THEIR_LINE, OPENING_OPEN, TRACE_ONLY
from lelsonar.reconstruct.estimate.surfaces.results import SurfaceOptions
from lelsonar.signal.energy import echo_amplitude
from lelsonar.sim.world_geometry import ElementKind, build_model
from lelsonar.sim.world_render import simulate_world_scan
from lelsonar.sim.worlds import draw_world
from lelsonar.tools.map_worlds import sweep
from lelsonar.tools.stress_world_score import estimate_of, world_run
from lelsonar.tools.stress_worlds import draw_stress_world
from lelsonar.tools.surface_scores import feature_offset, majority
from lelsonar.view import present
from tests.test_surfaces import GAMMA, GEOMETRY, Echoes


def _off_line(f: Feature, point: np.ndarray, direction: np.ndarray) -> tuple[float, float]:
    """The feature point's distance from the line through ``point`` along ``direction`` and its σ that way."""
    d = direction / np.linalg.norm(direction)
    off = (f.point - point) - ((f.point - point) @ d) * d
    dist = float(np.linalg.norm(off))
    if not dist > 0:
        return 0.0, 0.0
    r = off / dist
    return dist, math.sqrt(float(r @ f.covariance @ r))


def test_a_corner_at_two_planes_range_off_their_line_is_not_placed_on_it():
    # Walls y = 1 and z = 1.5 meet at range 1.80 m, but their corner does not echo (rounded, or absorbent): a
    # line across the stack at the same range, 0.6 m along the stack, does.  The pair's range matches; the
    # ranges' slope along the stack (19° off the fan) does not match their line's (in the fan).
    rho = math.hypot(1.0, 1.5)
    b = math.atan2(1.5, 1.0)
    x0 = 0.6
    r_fan = math.sqrt(rho * rho - x0 * x0)
    point = np.array([x0, r_fan * math.cos(b), r_fan * math.sin(b)])
    direction = np.array([0.0, -math.sin(b), math.cos(b)])
    e = Echoes(seed=7)
    e.plane(0.0, 1.0)
    e.plane(math.pi / 2, 1.5)
    e.across_line(point, direction, gain=1.5)
    result = extract_surfaces(GAMMA, e.ranges(), GEOMETRY, amplitude=e.amp)
    assert sorted(round(s.offset, 2) for s in result.surfaces) == pytest.approx([1.0, 1.5], abs=0.01)
    assert len(result.corners) == 1
    c = result.corners[0]
    # The premise: classified at the two planes' double-bounce range.
    assert any("double-bounce range of the two planes" in r for r in c.reasons)
    # Not on their line (60 cm from the echo's): where its own echo is, within 3 σ, and it joins no plane.
    assert any(NOT_THEIR_LINE in r for r in c.reasons) and c.surfaces == ()
    dist, sigma = _off_line(c, point, direction)
    assert dist <= 3 * sigma
    # Their line's point, where it would have been set, is 60 cm off the echo's line.
    assert np.linalg.norm(c.point - [0.0, 1.0, 1.5]) > 0.3


def test_the_planners_table_and_the_json_show_why_a_corner_is_not_on_their_line():
    e = Echoes(seed=7)
    e.plane(0.0, 1.0)
    e.plane(math.pi / 2, 1.5)
    b = math.atan2(1.5, 1.0)
    r_fan = math.sqrt(1.5**2 + 1.0 - 0.36)
    e.across_line(
        np.array([0.6, r_fan * math.cos(b), r_fan * math.sin(b)]), np.array([0.0, -math.sin(b), math.cos(b)]), 1.5
    )
    result = extract_surfaces(GAMMA, e.ranges(), GEOMETRY, amplitude=e.amp)
    msg = wire.add_surfaces(codec.Reconstruction(scanner_id="t", scan_id=1), result)
    caption = str(present.surfaces_table(msg).caption)
    assert f"* c1: {NOT_THEIR_LINE}" in caption
    assert any(NOT_THEIR_LINE in r for r in json.loads(present.to_json(msg))["corners"][0]["reasons"])


def test_the_corner_two_planes_meet_at_is_still_placed_on_their_line():
    # The control: the walls' own corner echoes, tilt and range agree with their line.
    e = Echoes(seed=7)
    e.plane(0.0, 1.0)
    e.plane(math.pi / 2, 1.5)
    e.vertical_line(1.0, 1.5, gain=1.5)
    result = extract_surfaces(GAMMA, e.ranges(), GEOMETRY, amplitude=e.amp)
    (c,) = result.corners
    assert not any(NOT_THEIR_LINE in r for r in c.reasons) and len(c.surfaces) == 2
    assert np.linalg.norm(c.point[1:] - [1.0, 1.5]) < 0.01
    assert math.sqrt(max(np.linalg.eigvalsh(c.covariance))) < 0.01


@pytest.mark.parametrize("bearing_deg,occluder", [(44.4, None), (62.0, (80.0, 0.7))])
def test_an_end_seen_from_one_trace_only_has_no_bearing_of_its_own(bearing_deg, occluder):
    # A wall y = 1 and a target 1.4 m away, without amplitudes: its region is cut (by the wall's nearer echo, or
    # by a nearer edge past it), so its bearing is undetermined, and it is set where the wall's trace reaches
    # 1.4 m (44.4°).  Whether the target is that end (44.4°) or elsewhere in the region's reach (62°, 43 cm
    # away), it lies within 3 σ: its σ across the ray spans the reach, at least a beam's half-width past a cut
    # end.
    rho = 1.4
    b = math.radians(bearing_deg)
    truth = np.array([0.0, rho * math.cos(b), rho * math.sin(b)])
    e = Echoes(seed=8)
    e.plane(0.0, 1.0)
    e.vertical_line(float(truth[1]), float(truth[2]), gain=1.0)
    if occluder is not None:
        at, r = math.radians(occluder[0]), occluder[1]
        e.vertical_line(r * math.cos(at), r * math.sin(at), gain=0.3)
    result = extract_surfaces(GAMMA, e.ranges(), GEOMETRY)
    (f,) = [f for f in (*result.corners, *result.edges) if abs(f.depth - rho) < 0.02]
    assert f.surfaces == ("s1",) and any(TRACE_ONLY in r for r in f.reasons)
    assert f.bearing == pytest.approx(math.acos(1.0 / rho), abs=math.radians(1.0))
    e_b = np.array([0.0, -math.sin(f.bearing), math.cos(f.bearing)])
    assert math.sqrt(float(e_b @ f.covariance @ e_b)) >= rho * SurfaceOptions().beyond_cut / math.sqrt(12.0)
    dist, sigma = _off_line(f, truth, np.array([1.0, 0.0, 0.0]))
    assert dist <= 3 * sigma


def _stress_feature(
    cls: str, seed: int, mount: str, pose: int, element: int
) -> tuple[ElementKind, list[tuple[Feature, float, float]]]:
    """The element's kind, and the features of one stress-world sweep (as of record) whose readings are mostly
    ``element``'s, each with its distance from the element's true line and its σ that way."""
    run = world_run(draw_stress_world(cls, seed, mount), seed)
    scan = sweep(run, pose)
    surfaces = estimate_of(scan).surfaces
    out = []
    for f in (*surfaces.corners, *surfaces.edges):
        if majority(scan, f.steps, f)[0] == element:
            out.append((f, *feature_offset(scan, f, element)))
    return scan.model.elements[element].kind, out


@pytest.mark.parametrize(
    "case,kind,rule",
    [
        # A room corner heard past a box's face, set on that face's trace 1.3 m off: its bearing is the reach's.
        (("boxes_large", 0, "fan", 1, 19), ElementKind.DIHEDRAL, TRACE_ONLY),
        # Two walls' corner in a vertical fan at the floor–wall corner's range, its stack slope 10° off theirs.
        (("acute", 0, "paper", 0, 10), ElementKind.DIHEDRAL, NOT_THEIR_LINE),
        # A region holding two ceiling corners, their ranges scattered 4 cm: no one line across the fan.
        (("narrow", 0, "paper", 2, 25), ElementKind.DIHEDRAL, MIXED.split(":")[0]),
        # A trihedral's echo, a point on the arc a bearing unsure by 15° spans: off the tangent by the sagitta.
        (("mixed", 0, "fan", 1, 40), ElementKind.TRIHEDRAL, ""),
        # An edge whose readings mix with a wall's slope along the stack as no target within the beam does.
        (("boxes_large", 1, "fan", 0, 46), ElementKind.EDGE, ""),
        # A room corner whose region's amplitude top a wall's nearer echo cuts, 2° off its wall's trace.
        (("heights", 1, "fan", 0, 22), ElementKind.DIHEDRAL, "its bearing weighs its own"),
    ],
)
def test_a_stress_worlds_feature_lies_within_three_sigma_of_its_line(case, kind, rule):
    cls, seed, mount, pose, element = case
    true_kind, found = _stress_feature(cls, seed, mount, pose, element)
    assert true_kind == kind and found
    for f, dist, sigma in found:
        assert dist <= max(3 * sigma, 0.02), (f.label, dist, sigma, f.reasons)
        if rule and dist > 0.02:
            assert any(rule in r for r in f.reasons)


@pytest.mark.parametrize(
    "case,kind,rule",
    [
        # A box's top edge across the stack 0.4 m away, its ranges a hyperbola along the stack, the farthest
        # capsule hearing another edge: a straight fit put it 6° off the fan from where it is.
        (("boxes_tiny", 1, "paper", 2, 47), ElementKind.EDGE, ""),
        (("mixed", 0, "paper", 2, 92), ElementKind.EDGE, ""),
        # Two capsules on one side of the stack hear a box's edge 1.3 m off: a point or a plane, nothing says.
        (("boxes_turned", 0, "paper", 2, 40), ElementKind.EDGE, ""),
        (("heights", 1, "fan", 1, 57), ElementKind.EDGE, ""),
        # An edge at the sweep's end, its amplitude still at its top there: its peak may lie up to the cut.
        (("touching", 0, "fan", 1, 69), ElementKind.EDGE, "its amplitude peak is at a cut end's top"),
        # A wall's corner with a wall across a vertical fan that is not square to the stack: not at the foot.
        (("acute", 1, "paper", 2, 22), ElementKind.DIHEDRAL, "not the"),
        # A wall–floor corner on a wall whose fitted bearing is unsure by 2°: the corner is as unsure.
        (("boxes_large", 0, "fan", 2, 39), ElementKind.DIHEDRAL, ""),
    ],
)
def test_a_feature_placed_by_its_own_echo_lies_within_three_sigma_of_its_line(case, kind, rule):
    test_a_stress_worlds_feature_lies_within_three_sigma_of_its_line(case, kind, rule)


def test_a_corridors_end_corner_weighs_its_own_bearing_with_its_walls_trace():
    # Corridor world 9, pose 0, horizontal fan: the corner of the corridor's end wall (element 10) is heard only
    # past the side wall's nearer echo, its amplitude's top cut there, 3° off its bearing with a σ of 0.6°; the
    # side wall's trace crosses its range at its bearing.  Weighed together, their disagreement grows the σ.
    model = build_model(draw_world("corridor", 9, mount="fan"))
    scan = simulate_world_scan(model, 0, seed=9 * 1000)
    amp = echo_amplitude(scan.waveforms, scan.sample_rate, scan.t0, scan.tof)
    result = extract_surfaces(scan.gamma_measured, scan.distance, scan.geometry, amplitude=amp)
    mine = [f for f in result.corners if majority(scan, f.steps, f)[0] == 10]
    assert mine and model.elements[10].kind == ElementKind.DIHEDRAL
    for f in mine:
        assert any("its bearing weighs its own" in r for r in f.reasons)
        dist, sigma = feature_offset(scan, f, 10)
        assert dist <= max(3 * sigma, 0.02)


@pytest.mark.parametrize("opening_deg", [90.0, 100.0, 80.0])
def test_a_corner_tied_to_one_wall_covers_the_opening_its_other_wall_makes(opening_deg):
    # A wall y = 1.2 and a concave corner on its trace at 50°, its other wall absorbent (unseen): the double
    # bounce turns the capsule's image by twice the opening α about the line, so it answers from |X| sin α, short
    # of the line by 2.8 cm at 80° or 100°.  Placed on the wall's trace at that range, the corner's σ along the
    # trace covers where the line is; at a right angle its own bearing agrees and it is placed on the line.
    alpha = math.radians(opening_deg)
    x_line = np.array([0.0, 1.2, 1.2 * math.tan(math.radians(50.0))])
    e = Echoes(seed=11)
    e.plane(0.0, 1.2)
    # A line at sin α of the corner's distance, in its direction: its ranges are |X − p| sin α to 0.5 mm.
    e.vertical_line(math.sin(alpha) * x_line[1], math.sin(alpha) * x_line[2], gain=1.0)
    result = extract_surfaces(GAMMA, e.ranges(), GEOMETRY, amplitude=e.amp)
    assert [round(s.offset, 2) for s in result.surfaces] == [1.2]
    assert len(result.corners) == 1 and not result.edges
    c = result.corners[0]
    assert c.surfaces == (result.surfaces[0].label,)
    dist, sigma = _off_line(c, x_line, np.array([1.0, 0.0, 0.0]))
    assert dist <= 3 * sigma, (dist, sigma)
    # Off a right angle its own bearing and its range disagree on the trace: it says what its σ spans.
    assert any(r.startswith(OPENING_OPEN) for r in c.reasons) == (opening_deg != 90.0)
    if opening_deg == 90.0:
        assert dist < 0.01
