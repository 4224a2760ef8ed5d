"""A corner's or an edge's σ covers what its evidence leaves open.

* a plane's line with a surface across the fan placed at the plane's foot: the line's turn in the plane is
  known only through its cosine, so the bearing's σ holds the turn the tilt's σ leaves open (analytic, and a
  seeded stress world where the line lies 5.7° off the foot);
* an edge's amplitude peak farther from where its echo fades than one beam pattern's fall allows is another
  echo's too (analytic);
* an end where the echo goes on in another region is no fade (analytic);
* a corner on two planes' line whose own range the line misses past both σ: the line's σ grows by χ²;
* seeded stress worlds, one per cause: each feature's point within 3 σ (or 2 cm) of its true line.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from lelsonar.reconstruct.estimate.surfaces.beam_pattern import bearing_from_amplitude
from lelsonar.reconstruct.estimate.surfaces.measurement import Measured
from lelsonar.reconstruct.estimate.surfaces.own_bearing import CONTINUED, continued_ends, peak_past_fade
from lelsonar.reconstruct.estimate.surfaces.placement import line_yaw_stderr
from lelsonar.reconstruct.estimate.surfaces.regions import Region
from lelsonar.signal.directivity import piston_directivity
from lelsonar.sim.world_geometry import ElementKind
from lelsonar.tools.map_worlds import sweep
from lelsonar.tools.stress_world_score import ERROR_FLOOR, _majority, estimate_of, world_run
from lelsonar.tools.stress_worlds import draw_stress_world
from lelsonar.tools.surface_scores import feature_offset
from tests.measured_regions import hand_measured

CLASSES = {"corner": (ElementKind.DIHEDRAL, ElementKind.TRIHEDRAL), "edge": (ElementKind.EDGE,)}


def _line_echo(h: float, q: float, phi: float) -> tuple[float, float, float]:
    """Range, tilt and bearing off the foot of the point nearest the array of a line in plane ``n·X = h``, ``q``
    from the foot in the plane, turned by ``phi`` from square to the stack."""
    x = np.array([q * math.cos(phi) ** 2, h, -q * math.cos(phi) * math.sin(phi)])  # (stack, along n, along e)
    rho = float(np.linalg.norm(x))
    return rho, math.asin(x[0] / rho), math.atan2(-x[2], x[1])


@pytest.mark.parametrize("phi_deg", [0.0, 10.0, 20.0, 30.0])
def test_the_foots_bearing_sigma_holds_the_turn_a_tilt_within_its_sigma_leaves_open(phi_deg):
    # A floor corner 0.5 m off a wall 2 m away: the tilt's σ of 0.5° leaves the line's turn open by ~15° about
    # square, so the point may lie ~4° off the foot however square the line truly is.
    h, q, sigma_t = 2.0, 0.5, math.radians(0.5)
    rho, tilt, off = _line_echo(h, q, math.radians(phi_deg))
    square_tilt = math.asin(q / math.hypot(h, q))
    within = abs(tilt - square_tilt) <= 3 * sigma_t  # the foot is where a tilt within 3 σ of square places it
    se = line_yaw_stderr(rho, 0.001, tilt, sigma_t, h, 0.001)
    assert se > 0
    if within:
        assert abs(off) <= 3 * se, (math.degrees(off), math.degrees(se))
    # A sharper tilt narrows it; the turn is bounded by a line at right angles to the stack's square.
    assert line_yaw_stderr(rho, 0.001, tilt, sigma_t / 4, h, 0.001) < se
    assert se <= math.atan2(q, h) + 1e-12


def test_no_turn_where_the_range_does_not_reach_past_the_plane():
    assert line_yaw_stderr(1.0, 0.001, 0.1, 0.01, 1.2, 0.001) == 0.0
    assert line_yaw_stderr(float("nan"), 0.001, 0.1, 0.01, 1.0, 0.001) == 0.0


def _beyond_3_sigma(cls: str, seed: int, mount: str, pose: int) -> list[tuple[str, float, float]]:
    """Each feature of the stress world's sweep off its true line by > 3 σ and > 2 cm: label, m off, σ."""
    world = draw_stress_world(cls, seed, mount)
    scan = sweep(world_run(world, seed), pose)
    surfaces = estimate_of(scan).surfaces
    out = []
    for f in (*surfaces.corners, *surfaces.edges):
        k = _majority(scan, f.steps, f.rows, f.capsules)
        if k < 0 or scan.model.elements[k].kind not in CLASSES[f.kind]:
            continue
        dist, sigma = feature_offset(scan, f, k)
        if dist > ERROR_FLOOR and dist > 3 * sigma:
            out.append((f.label, dist, sigma))
    return out


@pytest.mark.slow
@pytest.mark.parametrize(
    ("cls", "seed", "mount", "pose"),
    [
        # A wall's corner with the floor in the horizontal fan, 5.7° off the wall's foot: its tilt is within 3 σ
        # of a square line's.
        ("odometry", 41, "fan", 1),
        # A one-capsule fragment of a box edge's echo, split off where the other capsules' echo changes.
        ("clutter", 43, "fan", 1),
        # A tiny box's edge whose amplitudes sum a stronger echo at a like range: the peak lies past its fade.
        ("boxes_tiny", 41, "fan", 0),
        ("boxes_tiny", 42, "fan", 0),
        # Corners on two fitted planes' line whose own double-bounce range the line misses by ~1 cm, past
        # both σ: the planes' bearings are off by what their σ does not say.
        ("touching", 42, "paper", 0),
        ("strong_edges", 40, "paper", 1),
        # A plane's end whose capsules go on hearing its range past its first step (the whole stack there):
        # its reach runs past that end too.
        ("strong_edges", 43, "paper", 1),
        # One capsule's edge echo, split off the rest of it where the other capsules start hearing a wall.
        ("touching", 46, "fan", 1),
        # A region denied its pair's line whose ranges scatter along the stack past one target's: its tilt is
        # anywhere within the beam.
        ("strong_edges", 45, "paper", 0),
    ],
)
def test_seeded_features_lie_within_3_sigma_of_their_lines(cls, seed, mount, pose):
    assert _beyond_3_sigma(cls, seed, mount, pose) == []


KA = 5.13  # a 7 mm piston at 40 kHz
STEP = math.radians(0.88)


def _region(gamma_deg: np.ndarray, amplitude: np.ndarray, cut: tuple[bool, bool], **kw) -> Measured:
    """A region over the given steps (one per γ, capsule 0, 1.5 m), as the own-bearing tests read it."""
    n = gamma_deg.size
    steps = np.arange(n) + kw.pop("first", 0)
    caps = kw.pop("capsules", np.zeros(n, dtype=np.intp))
    region = Region(steps=steps, rows=steps, capsules=caps, cut_before=cut[0], cut_after=cut[1])
    g = np.radians(gamma_deg)
    peak = bearing_from_amplitude(g, amplitude)
    fields = dict(
        bearing_stderr=peak[1] if peak else 0.1,
        bearing_source="amplitude peak" if peak else "undetermined",
        tilt_stderr=0.001,
        peak=float(np.max(amplitude)),
        peak_inside=True,
        exact=True,
        step_amplitude=amplitude,
    )
    fields.update(kw)
    return hand_measured(
        region,
        bearing=peak[0] if peak else float(np.mean(g)),
        depth=1.5,
        span=(float(g[0]), float(g[-1])),
        step=STEP,
        **fields,
    )


def _beam(gamma_deg: np.ndarray, bearing_deg: float) -> np.ndarray:
    return piston_directivity(np.radians(np.abs(gamma_deg - bearing_deg)), KA) ** 2


# The piston's log amplitude near its top: −(ka)² ψ²/4.
BEAM_K = KA * KA / 4.0


def test_a_peak_one_beam_pattern_reaches_from_its_fading_end_stands():
    # One edge at +10°, heard from −5° (a nearer echo cuts it there) to where it fades on the other side.
    g = np.arange(-5.0, 40.0, math.degrees(STEP))
    amp = _beam(g, 10.0)
    heard = amp >= amp.max() * 10 ** (-20 / 10)  # 20 dB under the peak
    g, amp = g[heard], amp[heard]
    m = _region(g, amp, (True, False))
    assert abs(math.degrees(m.bearing) - 10.0) < 1.0
    assert peak_past_fade(m, np.radians(g), BEAM_K) == (m, "")


def test_a_peak_bent_by_a_stronger_echo_summing_in_is_past_what_its_fading_end_allows():
    # A weak edge at +20° fades at the far end; a stronger echo at 0°, at a like range, sums into the window
    # and pulls the amplitude peak to it.
    g = np.arange(-5.0, 70.0, math.degrees(STEP))
    amp = 0.3 * _beam(g, 20.0) + _beam(g, 0.0)
    weak = 0.3 * _beam(g, 20.0)
    heard = weak >= weak.max() * 10 ** (-20 / 10)  # where the edge's own echo is over the threshold
    g, amp = g[heard], amp[heard]
    m = _region(g, amp, (True, False))
    assert abs(math.degrees(m.bearing) - 20.0) > 3 * math.degrees(m.bearing_stderr)  # the peak is bent
    placed, why = peak_past_fade(m, np.radians(g), BEAM_K)
    assert why
    assert abs(placed.bearing - math.radians(20.0)) > 0
    assert placed.bearing_stderr > m.bearing_stderr


def test_an_end_where_the_echo_goes_on_in_another_region_is_no_fade():
    # One capsule hears an edge at 0.636 m over three steps; the whole stack goes on hearing it from the next.
    g = np.array([-45.7, -44.5, -43.7])
    fragment = _region(g, np.full(3, 0.05), (False, False), capsules=np.full(3, 3, dtype=np.intp), first=104)
    fragment = replace(fragment, ranges=np.full(3, 0.636), depth=0.667)
    rows = np.repeat(np.arange(107, 111), 4)
    caps = np.tile(np.arange(4), 4)
    rest = replace(
        fragment,
        region=Region(steps=np.arange(107, 111), rows=rows, capsules=caps, cut_before=False, cut_after=False),
        ranges=np.full(rows.size, 0.637),
        depth=0.66,
    )
    placed, why = continued_ends(fragment, [fragment, rest], 0.015)
    assert why.startswith(CONTINUED)
    assert placed.region.cut_after and not placed.region.cut_before
    # The same steps at another range: another target, the end stands.
    other = replace(rest, ranges=np.full(rows.size, 0.70))
    assert continued_ends(fragment, [fragment, other], 0.015) == (fragment, "")


def test_the_sweeps_own_ranges_say_where_an_echo_goes_on_past_its_region():
    # The same fragment, the rest of its echo in no region: capsule 3 hears 0.637 m on the step before it.
    g = np.array([-45.7, -44.5, -43.7])
    fragment = _region(g, np.full(3, 0.05), (False, False), capsules=np.full(3, 3, dtype=np.intp), first=104)
    fragment = replace(fragment, ranges=np.full(3, 0.636))
    distance = np.full((120, 4), 1.9)
    distance[104:107, 3] = 0.636
    assert continued_ends(fragment, [fragment], 0.015, distance) == (fragment, "")
    distance[103, 3] = 0.637
    placed, why = continued_ends(fragment, [fragment], 0.015, distance)
    assert why.startswith(CONTINUED) and placed.region.cut_before and not placed.region.cut_after
