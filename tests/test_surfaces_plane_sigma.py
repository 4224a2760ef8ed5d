"""A plane's bearing and its σ where a region's ends are another target's: analytic sweeps and seeded worlds.

* a region that holds its wall's double bounce with the floor past one end only (the other side's made a
  region of its own) is lopsided: the wall's bearing is the centre of its own steps, not of the region;
* a centred region's bearing weighs its centre with its beam pattern's peak where the two agree;
* the beam pattern's peak wanders as its own fit's σ says, wherever the sweep's steps fall;
* amplitude noise moves where a region's echo crosses the threshold: the centre's σ holds it;
* a plane whose end steps were trimmed off as another target's may have faded on the one next to its core
  (its echo summed into it): its centre puts that end between them, and its σ spans them; an end step with
  too few readings for a slope is trimmed by its depth alone.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import special

from lelsonar.reconstruct.estimate.surfaces import SurfaceOptions, extract_surfaces
from lelsonar.reconstruct.estimate.surfaces.beam_pattern import bearing_from_amplitude, end_crossing_stderr
from lelsonar.reconstruct.estimate.surfaces.flanks import trimmed_centre
from lelsonar.reconstruct.estimate.surfaces.measurement import measure_region
from lelsonar.reconstruct.estimate.surfaces.regions import find_regions, subregion
from lelsonar.tools.surface_scores import world_sweep
from tests.test_surfaces import GAMMA, GEOMETRY, THRESHOLD, Echoes
from tests.test_surfaces_wall_end import bearing_errors


def test_a_wall_whose_floor_corner_flanks_its_region_on_one_side_only_takes_its_own_steps_centre():
    bearing, offset = math.radians(-30.0), 4.0
    alone = Echoes(seed=21)
    alone.plane(bearing, offset)
    own = np.flatnonzero(np.isfinite(alone.range).any(axis=1))
    e = Echoes(seed=21)
    e.plane(bearing, offset)
    n = np.array([0.0, math.cos(bearing), math.sin(bearing)])
    e.across_line(offset * n + np.array([-0.24, 0.0, 0.0]), np.cross([1.0, 0.0, 0.0], n), gain=2.0)
    d = e.ranges()
    # The corner's steps past the wall's last step are gone (on that side they made a region of their own).
    d[own[-1] + 1 :] = np.nan
    (region,) = [r for r in find_regions(d) if np.isin(own, r.steps).all()]
    head = int(np.count_nonzero(region.steps < own[0]))
    assert head >= 3 and region.steps[-1] == own[-1]  # the premise: one flank, in the region
    result = extract_surfaces(GAMMA, d, GEOMETRY, amplitude=e.amp)
    (wall,) = [s for s in result.surfaces if abs(s.offset - offset) < 0.01]
    sd = math.sqrt(wall.covariance[0, 0])
    # The whole region's centre is half the flank's width off: the wall's own steps' is not.
    whole = 0.5 * (GAMMA[region.steps[0]] + GAMMA[region.steps[-1]])
    assert abs(whole - bearing) > 3 * sd
    assert abs(wall.bearing - bearing) <= 3 * sd, (math.degrees(wall.bearing - bearing), math.degrees(sd))


@pytest.mark.parametrize(("seed", "bearing_deg"), [(31, 25.0), (32, -70.0), (33, 110.0)])
def test_a_plane_trimmed_at_one_end_puts_that_end_between_its_core_and_the_trimmed_step(seed, bearing_deg):
    bearing, offset = math.radians(bearing_deg), 2.0
    e = Echoes(seed=seed)
    e.plane(bearing, offset)
    d = e.ranges()
    (region,) = find_regions(d)
    steps = region.steps
    # The plane's last step trimmed off (its echo summed with another's there).
    core = subregion(region, steps[:-1], False, False)
    m = measure_region(core, GAMMA, d, None, GEOMETRY, SurfaceOptions())
    assert m.bearing_source == "region centre"
    t = trimmed_centre(m, GAMMA, (None, int(steps[-1])))
    step = float(GAMMA[1] - GAMMA[0])
    assert t.bearing == pytest.approx(0.5 * (GAMMA[steps[0]] + 0.5 * (GAMMA[steps[-2]] + GAMMA[steps[-1]])))
    # One end over its gap (step²/12), the other over the step to the trimmed one and the gap past it.
    var = (step**2 / 12 + (2 * step) ** 2 / 12) / 4
    assert t.bearing_stderr == pytest.approx(math.sqrt(var))
    assert abs(t.bearing - bearing) <= 3 * t.bearing_stderr
    assert abs(t.bearing - bearing) < abs(m.bearing - bearing)
    assert trimmed_centre(m, GAMMA, (None, None)) is m


@pytest.mark.slow
@pytest.mark.parametrize(
    ("family", "seed", "pose", "at_least"),
    [
        # The wall 4.2 m away meets the floor; that corner's echoes join the wall's region on one side only
        # (four steps), the other side's stay apart.
        ("corridor", 11, 1, 1),
        # Two walls' regions end on a step of their corner with the floor whose echo sums with the wall's;
        # trimmed, each core is lopsided by that step.
        ("boxes", 16, 0, 2),
    ],
)
def test_in_simulated_worlds_walls_flanked_or_trimmed_on_one_side_keep_their_bearing_within_sigma(
    family, seed, pose, at_least
):
    _, scan, _, result = world_sweep(family, seed, pose)
    checked = bearing_errors(scan, result.surfaces)
    assert len(checked) >= at_least
    for label, error, sd in checked:
        assert abs(error) <= 3 * sd, f"{label}: {math.degrees(error):.2f}° with σ {math.degrees(sd):.2f}°"


@pytest.mark.parametrize(("seed", "bearing_deg"), [(41, 15.0), (42, -50.0), (43, 95.0)])
def test_a_centred_regions_bearing_weighs_its_centre_and_its_beam_patterns_peak(seed, bearing_deg):
    bearing, offset = math.radians(bearing_deg), 2.5
    e = Echoes(seed=seed)
    e.plane(bearing, offset)
    d = e.ranges()
    (region,) = find_regions(d)
    opts = SurfaceOptions()
    centre = measure_region(region, GAMMA, d, None, GEOMETRY, opts)
    both = measure_region(region, GAMMA, d, e.amp, GEOMETRY, opts)
    assert centre.bearing_source == both.bearing_source == "region centre"
    g = GAMMA[region.steps]
    peak, peak_sd = bearing_from_amplitude(g, both.step_amplitude)
    # The peak's σ is its parabola fit's; two that differ by more than their σ say scale it (the Birge ratio).
    apart = abs(peak - centre.bearing) / math.hypot(peak_sd, centre.bearing_stderr)
    wc, wp = centre.bearing_stderr**-2, peak_sd**-2
    assert both.bearing == pytest.approx((wc * centre.bearing + wp * peak) / (wc + wp))
    assert both.bearing_stderr == pytest.approx(max(1.0, apart) * (wc + wp) ** -0.5)
    assert both.bearing_stderr < centre.bearing_stderr
    assert abs(both.bearing - bearing) <= 3 * both.bearing_stderr


def _piston_beam(psi: np.ndarray, ka: float = 6.6) -> np.ndarray:
    """A transceiver's two-way piston directivity ``D(ψ)²``, ``D = 2 J1(ka sin ψ)/(ka sin ψ)``."""
    x = ka * np.sin(psi)
    x = np.where(np.abs(x) < 1e-9, 1e-9, x)
    return (2 * special.j1(x) / x) ** 2


@pytest.mark.parametrize("noise", [0.0, 0.02])
def test_the_beam_patterns_peak_wanders_as_its_fit_says_wherever_the_steps_fall(noise):
    # A piston's D² over 1° steps whose grid falls anywhere against the target, its log amplitude noisy:
    # the vertex's error against its own fit's σ, with no quantisation of the steps in it.
    step = math.radians(1.0)
    rng = np.random.default_rng(81)
    errors, sds = [], []
    for _ in range(300):
        target = rng.uniform(-step, step)
        g = np.arange(-40.0, 40.5, 1.0) * step + rng.uniform(0.0, step)
        clean = _piston_beam(g - target)
        heard = clean > 0.05
        fit = bearing_from_amplitude(g[heard], clean[heard] * np.exp(noise * rng.standard_normal(heard.sum())))
        assert fit is not None
        errors.append(fit[0] - target)
        sds.append(fit[1])
    err, sd = np.abs(np.asarray(errors)), np.asarray(sds)
    if noise > 0:
        # A Gaussian's 95 / 99.7 % within 2 / 3 σ (a few of 300 either way).
        assert np.mean(err <= 2 * sd) >= 0.92 and np.mean(err <= 3 * sd) >= 0.98
    else:
        # Without noise, a tenth of one step's quantisation (step/√24) at most: where the steps fall does not
        # move the vertex, and its fit's residuals (the beam's departure from a parabola) cover what does.
        assert float(np.max(err)) < 0.1 * step / math.sqrt(24.0)
        assert np.all(err <= 3 * sd)


def test_a_deeper_end_step_in_one_or_two_capsules_is_trimmed_by_its_depth_alone():
    bearing, offset = math.radians(-40.0), 2.0
    e = Echoes(seed=51)
    e.plane(bearing, offset)
    d = e.ranges()
    own = np.flatnonzero(np.isfinite(d).any(axis=1))
    # A corner's echo 1 cm deeper in the two lower capsules just before the wall's first step, and in the
    # lowest one a step earlier (the beam's edge): no slope to judge those steps by, only their depth.
    wall_range = float(np.nanmedian(d[own[:5]]))
    d[own[0] - 1, :2] = wall_range + 0.010 + np.array([0.0, 0.004])
    d[own[0] - 2, 0] = wall_range + 0.012
    (region,) = [r for r in find_regions(d) if np.isin(own, r.steps).all()]
    assert region.steps[0] == own[0] - 2  # the premise: the two steps join the wall's region
    result = extract_surfaces(GAMMA, d, GEOMETRY, amplitude=e.amp)
    (wall,) = [s for s in result.surfaces if abs(s.offset - offset) < 0.01]
    assert wall.steps[0] == own[0]
    assert abs(wall.bearing - bearing) <= 3 * math.sqrt(wall.covariance[0, 0])


def test_noise_free_amplitudes_move_no_threshold_crossing():
    e = Echoes(seed=61)
    e.plane(math.radians(10.0), 2.0)
    (region,) = find_regions(e.ranges())
    per_step = np.nanmedian(e.amp[region.steps], axis=1)
    step = float(GAMMA[1] - GAMMA[0])
    assert max(end_crossing_stderr(GAMMA[region.steps], per_step)) < 0.05 * step


def test_the_threshold_crossings_wander_as_the_noise_over_the_beams_log_slope_says():
    # A beam exp(−(γ/B)²) over a threshold, its log amplitude noisy by 0.2: where the first and last steps over
    # the threshold fall, over many draws, against the σ the rule gives from each draw's own steps.
    gamma = np.radians(np.arange(-60.0, 60.0, 0.88))
    beam = 1.0 * np.exp(-((gamma / math.radians(15.0)) ** 2))
    rng = np.random.default_rng(71)
    firsts, lasts, claimed = [], [], []
    for _ in range(300):
        amp = beam * np.exp(0.2 * rng.standard_normal(gamma.size))
        over = np.flatnonzero(amp > 0.2)
        steps = np.arange(over[0], over[-1] + 1)
        firsts.append(gamma[steps[0]])
        lasts.append(gamma[steps[-1]])
        claimed.append(end_crossing_stderr(gamma[steps], amp[steps]))
    rule = np.median(np.asarray(claimed), axis=0)
    seen = np.array([np.std(firsts), np.std(lasts)])
    # An upper bound (several noisy steps near the threshold: the first over it wanders less), within 2×.
    assert np.all(rule >= seen) and np.all(rule < 2.0 * seen), (np.degrees(rule), np.degrees(seen))


def test_with_noisy_amplitudes_the_centres_sigma_covers_where_the_threshold_crossings_fall():
    # Each echo's amplitude 20 % off at random (log-normal): its threshold crossings wander by steps.
    bearing, offset, inside = math.radians(35.0), 2.0, 0
    runs = 40
    for seed in range(runs):
        e = Echoes(seed=100 + seed)
        e.plane(bearing, offset)
        rng = np.random.default_rng(seed)
        amp = e.amp * np.exp(0.2 * rng.standard_normal(e.amp.shape))
        heard = amp > THRESHOLD
        d = np.where(heard, e.ranges(), np.nan)
        result = extract_surfaces(GAMMA, d, GEOMETRY, amplitude=np.where(heard, amp, np.nan))
        (wall,) = [s for s in result.surfaces if abs(s.offset - offset) < 0.01]
        inside += abs(wall.bearing - bearing) <= 3 * math.sqrt(wall.covariance[0, 0])
    # A Gaussian's 99.7 % within 3 σ: at most a few of 40 outside.
    assert inside >= runs - 3, f"{inside} of {runs} within 3 σ"
