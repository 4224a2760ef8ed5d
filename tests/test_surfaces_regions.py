"""The regions of constant depth and their steps' medians: compiled and vectorised, against plain references.

The reference below is the rule written out step by step, kept here (and only here) as the independent
statement of what :func:`~lelsonar.reconstruct.estimate.surfaces.regions.find_regions` computes; the two
must agree exactly (steps, readings, cuts) on world sweeps and on synthetic sweeps with missing echoes,
NaN rows, infinities, cut regions and every option varied.
"""

from __future__ import annotations

import math
import statistics
import warnings

import numpy as np
import pytest

from lelsonar.errors import ConfigError
from lelsonar.reconstruct.estimate.surfaces.measurement import step_medians
from lelsonar.reconstruct.estimate.surfaces.regions import Region, find_regions
from lelsonar.sim.world_geometry import build_model
from lelsonar.sim.world_render import simulate_world_scan
from lelsonar.sim.worlds import WORLD_FAMILIES, draw_world
from lelsonar.tools.stress_world_score import score_world
from lelsonar.tools.stress_worlds import draw_stress_world


def _reference(
    distance: np.ndarray, *, tolerance: float = 0.015, max_gap: int = 2, min_steps: int = 3
) -> list[tuple[list[int], list[int], list[int], bool, bool]]:
    """The rule step by step: (steps, rows, capsules, cut before, cut after) of each region."""
    d = np.asarray(distance, dtype=np.float64)
    n, m = d.shape
    rs = np.full(n, np.nan)
    have = np.isfinite(d).any(axis=1)
    if have.any():
        rs[have] = np.nanmedian(d[have], axis=1)

    def steady(row: np.ndarray, step_range: float, seen: list[list[float]], run_ranges: np.ndarray) -> float:
        devs = [abs(float(row[c]) - statistics.median(v)) for c, v in enumerate(seen) if v and math.isfinite(row[c])]
        if devs:
            return statistics.median(devs)
        return abs(float(step_range) - float(np.median(run_ranges)))

    def cut(end: int, direction: int, ref: float) -> bool:
        if not 0 <= end + direction < n:
            return True
        for k in range(1, max_gap + 3):
            s = end + direction * k
            if 0 <= s < n and math.isfinite(rs[s]) and rs[s] < ref - tolerance:
                return True
        return False

    runs: list[list[int]] = []
    run: list[int] = []
    seen: list[list[float]] = [[] for _ in range(m)]
    gap = 0
    for s in range(n):
        if not math.isfinite(rs[s]):
            gap += 1
            if run and gap > max_gap:
                runs.append(run)
                run = []
            continue
        if not (run and steady(d[s], rs[s], seen, rs[run]) <= tolerance):
            if run:
                runs.append(run)
            run = []
            seen = [[] for _ in range(m)]
        run.append(s)
        for c in range(m):
            if math.isfinite(d[s, c]):
                seen[c].append(float(d[s, c]))
        gap = 0
    if run:
        runs.append(run)
    out = []
    for r in runs:
        if len(r) < min_steps:
            continue
        steps = np.asarray(r, dtype=np.intp)
        ref = float(np.median(rs[steps]))
        block = d[steps]
        med = np.full(m, np.nan)
        col = np.isfinite(block).any(axis=0)
        if col.any():
            med[col] = np.nanmedian(block[:, col], axis=0)
        with np.errstate(invalid="ignore"):  # an infinite reading against an infinite median
            keep = np.isfinite(block) & (np.abs(block - med) <= 2 * tolerance)
        rows, caps = np.nonzero(keep)
        out.append((r, steps[rows].tolist(), caps.tolist(), cut(r[0], -1, ref), cut(r[-1], 1, ref)))
    return out


def _as_tuples(regions: list[Region]) -> list[tuple[list[int], list[int], list[int], bool, bool]]:
    for r in regions:
        assert r.steps.dtype == r.rows.dtype == r.capsules.dtype == np.intp
    return [(r.steps.tolist(), r.rows.tolist(), r.capsules.tolist(), r.cut_before, r.cut_after) for r in regions]


@pytest.fixture(scope="module")
def world_sweeps() -> list[np.ndarray]:
    out = []
    for family in WORLD_FAMILIES:
        model = build_model(draw_world(family, 0))
        out.append(np.asarray(simulate_world_scan(model, 0, seed=0).distance))
    return out


OPTIONS = [
    {},
    {"tolerance": 0.005},
    {"tolerance": 0.04, "max_gap": 0, "min_steps": 1},
    {"tolerance": 0.01, "max_gap": 5, "min_steps": 6},
]


@pytest.mark.parametrize("options", OPTIONS)
def test_world_sweeps_split_as_the_rule_says(world_sweeps, options):
    rng = np.random.default_rng(7)
    for d in world_sweeps:
        assert _as_tuples(find_regions(d, **options)) == _reference(d, **options)
        # The same sweep with a fifth of its echoes lost and a run of steps with none.
        lossy = d.copy()
        lossy[rng.random(d.shape) < 0.2] = np.nan
        start = int(rng.integers(0, d.shape[0] - 10))
        lossy[start : start + int(rng.integers(1, 8))] = np.nan
        assert _as_tuples(find_regions(lossy, **options)) == _reference(lossy, **options)


def _synthetic(rng: np.random.Generator, n: int, m: int) -> np.ndarray:
    """Piecewise targets: steady runs, ramps, one capsule on another target, gaps, ties, infinities."""
    d = np.empty((n, m))
    s = 0
    while s < n:
        k = min(int(rng.integers(1, 25)), n - s)
        base = rng.uniform(0.3, 3.0)
        spread = rng.choice([0.0, 0.003, 0.02]) * np.arange(m)  # a tilt or a line across the stack
        drift = rng.choice([0.0, 0.0, 0.004]) * np.arange(k)[:, None]
        d[s : s + k] = base + spread + drift + rng.normal(0, rng.choice([0.0005, 0.004, 0.01]), (k, m))
        s += k
    d = np.round(d, int(rng.choice([3, 6, 12])))  # coarse ranges make equal values and even-count medians
    d[rng.random(d.shape) < rng.uniform(0.0, 0.5)] = np.nan
    d[rng.random(n) < 0.05] = np.nan
    hit = rng.random(d.shape) < 0.03
    d[hit] = rng.uniform(0.3, 3.0, np.count_nonzero(hit))
    if rng.random() < 0.3:
        d[rng.random(d.shape) < 0.01] = np.inf
    return d


def test_synthetic_sweeps_split_as_the_rule_says():
    rng = np.random.default_rng(20261128)
    for _ in range(300):
        n = int(rng.integers(0, 120))
        m = int(rng.integers(1, 6))
        d = _synthetic(rng, n, m) if n else np.empty((0, m))
        options = {
            "tolerance": float(rng.choice([0.003, 0.015, 0.05])),
            "max_gap": int(rng.integers(0, 4)),
            "min_steps": int(rng.integers(1, 5)),
        }
        assert _as_tuples(find_regions(d, **options)) == _reference(d, **options), options


def test_bad_arguments_are_config_errors():
    with pytest.raises(ConfigError):
        find_regions(np.zeros(5))
    with pytest.raises(ConfigError):
        find_regions(np.zeros((5, 4)), tolerance=0.0)
    with pytest.raises(ConfigError):
        find_regions(np.zeros((5, 4)), max_gap=-1)
    with pytest.raises(ConfigError):
        find_regions(np.zeros((5, 4)), min_steps=0)


def test_step_medians_are_each_steps_median(world_sweeps):
    """Each step's median over its readings' finite values, as ``np.median`` of them, bit for bit."""
    rng = np.random.default_rng(11)
    for d in world_sweeps:
        values = np.round(rng.uniform(0.0, 2.0, d.shape), int(rng.choice([2, 12])))  # ties and even counts
        values[rng.random(d.shape) < 0.3] = np.nan
        values[rng.random(d.shape) < 0.02] = np.inf
        for region in find_regions(d, tolerance=0.04, min_steps=1):
            got = step_medians(region, values)
            v = values[region.rows, region.capsules]
            pos = np.searchsorted(region.steps, region.rows)
            for k in range(region.steps.size):
                mine = v[(pos == k) & np.isfinite(v)]
                want = float(np.median(mine)) if mine.size else float("nan")
                assert np.float64(got[k]).tobytes() == np.float64(want).tobytes()


def _wide_wall(rng: np.random.Generator, *, far_after: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A wall 0.385 m from the axis at bearing 13.8°, heard from −68.6° to 96.7° (a 58° beam), its ranges
    ``ρ − r·cos(γ − β)`` (r = 3 cm) plus 2 mm of noise; past ``far_after`` (rad) a target at another depth."""
    gamma = np.arange(math.radians(-100.0), math.radians(130.0), math.radians(0.879))
    rho, beta, r = 0.385, math.radians(13.8), 0.03
    d = rho - r * np.cos(gamma - beta)[:, None] + rng.normal(0.0, 0.002, (gamma.size, 4))
    d[(gamma < math.radians(-68.6)) | (gamma > math.radians(96.7))] = np.nan  # the echo fades there
    if far_after is not None:
        d[gamma > far_after] += 0.04
    return gamma, d


def test_a_wide_walls_drift_with_the_radial_offset_is_one_region():
    """The radial offset drifts a wide beam's wall by ``r·(1 − cos Δγ)``, more than the tolerance from the run's
    median; with the sweep's γ and the offset the run is one region, both ends faded (not cut)."""
    gamma, d = _wide_wall(np.random.default_rng(26))
    assert len(find_regions(d)) > 1  # the drift alone splits it
    regions = find_regions(d, gamma=gamma, radial_offset=0.03)
    assert len(regions) == 1
    (region,) = regions
    heard = np.flatnonzero(np.isfinite(d).any(axis=1))
    assert region.steps.tolist() == heard.tolist()
    assert region.n_echoes == np.count_nonzero(np.isfinite(d))
    assert not region.cut_before and not region.cut_after


def test_a_target_at_another_depth_past_the_drift_still_cuts():
    """4 cm deeper past 87.6°: not the wall's drift, two regions."""
    gamma, d = _wide_wall(np.random.default_rng(26), far_after=math.radians(87.6))
    regions = find_regions(d, gamma=gamma, radial_offset=0.03)
    assert len(regions) >= 2
    assert all(
        not (gamma[r.steps] > math.radians(87.6)).any() or (gamma[r.steps] > math.radians(87.6)).all() for r in regions
    )


def test_no_drift_join_without_gamma_or_offset():
    gamma, d = _wide_wall(np.random.default_rng(26))
    plain = _as_tuples(find_regions(d))
    assert _as_tuples(find_regions(d, gamma=gamma, radial_offset=0.0)) == plain
    with pytest.raises(ConfigError):
        find_regions(d, gamma=gamma[:-1], radial_offset=0.03)


@pytest.mark.slow
def test_a_wide_beams_wall_is_not_good_off_its_bearing():
    """Stress world ``beam`` seed 0, fan mount, first pose: a 58° beam hears a wall 0.385 m away over 165°;
    its region is the whole run, centred on the wall's bearing (a part the radial offset's drift split off
    would be centred degrees away from it)."""
    score = score_world("beam", 0, "fan", draw_stress_world("beam", 0, "fan"), max_poses=1)
    assert score.counts["crash"] == 0, score.failures
    assert score.counts["surface good-but-failed"] == 0, score.failures
    assert score.counts["bearing > 3σ"] == 0, score.failures


def test_a_step_that_holds_none_of_its_regions_readings_is_no_step_of_it():
    """A step joins its run near the capsules' medians as they stand then: step 0 (capsules 2 and 3 at 1.000 m)
    opens the run, and the run settles at 0.960 m.  Against the whole run's medians step 0 holds no reading of
    the region (4 cm off, over twice the tolerance): with a spread bound it is no step of the region, quietly
    (no median of nothing); without one the rule keeps it, as the reference says."""
    d = np.full((12, 4), 0.960)
    d[0] = [np.nan, np.nan, 1.000, 1.000]
    d[1] = [0.960, 0.960, 0.988, 0.988]
    d[2, 2:] = 0.975
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        (region,) = find_regions(d, max_spread=0.255)
    assert region.steps.tolist() == list(range(1, 12))
    assert np.unique(region.rows).tolist() == region.steps.tolist()  # every step holds one of its readings
    assert (d[region.rows, region.capsules] < 0.99).all()
    assert _as_tuples(find_regions(d)) == _reference(d)
    assert _reference(d)[0][0][0] == 0
