"""Critical step, split, baseline, registry and the top-level reconstruct() (paper §4-5)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lelsonar.errors import ConfigError
from lelsonar.geometry import ArrayGeometry
from lelsonar.reconstruct.estimate.baseline import fuzzy_c_means, ransac_plane
from lelsonar.reconstruct.estimate.pipeline import (
    DEFAULT_METHOD,
    METHODS,
    FitOptions,
    corner_edge,
    reconstruct,
)
from lelsonar.reconstruct.estimate.results import (
    EdgeLine,
    FailureReason,
    FitFailure,
    PlaneFit,
    ScanReconstruction,
)
from lelsonar.reconstruct.estimate.split import critical_step, split_subsets
from lelsonar.signal.energy import EnergyModel
from tests.synthetic import synthetic_corner_scan, tilted_normal

GEO = ArrayGeometry()
MODEL = EnergyModel(phi0=2.0, phi1=1.0, phi2=0.5)
FAST_METHODS = [m for m in METHODS if m not in ("paper", "lel-nm")]


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.rad2deg(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))


# ----------------------------------------------------------------------------- critical step and split


@settings(max_examples=100, deadline=None)
@given(st.integers(20, 300), st.floats(0.05, 0.95), st.integers(0, 2**32 - 1), st.floats(1.2, 5.0))
def test_critical_step_finds_the_peak_of_a_synthetic_r_curve(n: int, where: float, seed: int, height: float) -> None:
    rng = np.random.default_rng(seed)
    k = int(where * (n - 1))
    x = np.arange(n)
    r = 1.0 + 0.3 * np.sin(x / n * 6) + rng.uniform(0, 0.05, n)  # smooth background below the peak
    r += height * np.exp(-0.5 * ((x - k) / 1.5) ** 2)
    assert critical_step(r) == k
    assert abs(critical_step(r, 0.04) - k) <= 1


def test_critical_step_centroid_finds_the_middle_of_a_plateau() -> None:
    r = np.ones(100)
    r[40:50] = 3.0 + np.array([0.05, 0, 0.02, 0.01, 0, 0, 0.01, 0.03, 0, 0.0])  # flat top, argmax at 40
    assert critical_step(r) == 40
    assert critical_step(r, 0.04) in (44, 45)


def test_critical_step_ignores_invalid_steps() -> None:
    assert critical_step(np.array([np.nan, 0.0, -1.0])) is None
    assert critical_step(np.array([np.nan, 2.0, 1.0, np.inf])) == 1
    with pytest.raises(ConfigError):
        critical_step(np.ones((2, 2)))


def test_split_excludes_the_critical_step_and_labels_by_angle() -> None:
    g = np.linspace(-0.2, 1.9, 30)
    s = split_subsets(g, 12)
    np.testing.assert_array_equal(s.steps_a, np.arange(12))
    np.testing.assert_array_equal(s.steps_b, np.arange(13, 30))
    rev = split_subsets(g[::-1], 17)  # the same scan run the other way
    assert np.all(g[::-1][rev.steps_a] < g[::-1][17]) and np.all(g[::-1][rev.steps_b] > g[::-1][17])
    with pytest.raises(ConfigError):
        split_subsets(g, 30)


# ----------------------------------------------------------------------------- baseline


def test_fcm_separates_three_blobs_and_is_seeded() -> None:
    rng = np.random.default_rng(0)
    centers = np.array([[0, 0], [5, 0], [0, 5]])
    x = np.concatenate([c + rng.normal(0, 0.3, (50, 2)) for c in centers])
    a = fuzzy_c_means(x, 3, rng=np.random.default_rng(1))
    b = fuzzy_c_means(x, 3, rng=np.random.default_rng(1))
    np.testing.assert_array_equal(a.labels, b.labels)
    np.testing.assert_allclose(a.membership.sum(axis=0), 1.0)
    assert a.converged
    for k in range(3):  # each blob is one cluster
        assert len(set(a.labels[50 * k : 50 * (k + 1)])) == 1
    assert len(set(a.labels)) == 3


def test_ransac_survives_half_outliers() -> None:
    rng = np.random.default_rng(0)
    wall = np.c_[rng.uniform(-1, 1, 100), 1.5 + rng.normal(0, 0.002, 100), rng.uniform(-1, 1, 100)]
    junk = rng.uniform([-1, 0.5, -1], [1, 2.5, 1], (100, 3))
    res = ransac_plane(np.r_[wall, junk], threshold=0.01, rng=np.random.default_rng(3))
    assert res is not None
    assert angle_deg(res.normal, np.array([0, 1.0, 0])) < 0.5 and res.offset == pytest.approx(1.5, abs=0.003)
    assert res.inliers[:100].mean() > 0.95
    assert ransac_plane(np.zeros((2, 3)), threshold=0.01, rng=np.random.default_rng(0)) is None


# ----------------------------------------------------------------------------- reconstruct()


def _scan(seed: int = 0, noise: float = 0.002, **kw):  # noqa: ANN202
    return synthetic_corner_scan(GEO, rng=np.random.default_rng(seed), noise=noise, energy_model=MODEL, **kw)


def _run(s, method: str, **kw) -> ScanReconstruction:  # noqa: ANN001
    return reconstruct(s.gamma, s.distance, s.sensor_energy, GEO, MODEL, method=method, **kw)


def test_registry_has_the_paper_and_the_default() -> None:
    assert {"paper", "ls", "lel", "lel-refit-ls", "lel-refit-lel", "constant-depth", "fcm-ransac"} <= set(METHODS)
    assert DEFAULT_METHOD in METHODS
    with pytest.raises(TypeError):
        METHODS["x"] = METHODS["ls"]  # type: ignore[index]
    with pytest.raises(ConfigError, match="unknown reconstruction method"):
        _run(_scan(), "nope")


@pytest.fixture(scope="module")
def paper_scans():
    """The paper's corner from the physical simulator (waveforms, calibrated E0), two noise seeds."""
    from lelsonar.signal.energy import echo_amplitude, waveform_energy
    from lelsonar.sim import default_energy_model, preset, simulate_scan

    out = []
    for seed in (1, 2):
        scan = simulate_scan(preset("paper-test1"), seed=seed)
        out.append(
            (
                scan,
                dict(
                    gamma=scan.gamma_measured,
                    distance=scan.distance,
                    sensor_energy=waveform_energy(scan.waveforms, scan.sample_rate),
                    geometry=scan.geometry,
                    energy_model=default_energy_model(),
                    echo_amplitude=echo_amplitude(scan.waveforms, scan.sample_rate, scan.t0, scan.tof),
                ),
            )
        )
    return out


#: Methods whose reported standard errors are calibrated on the paper's scenes (lelsonar bench estimators:
#: median |error/σ| 0.6-0.8, none beyond 2.1 in 16 planes).  The LEL refits after the §5.3 pre-filter
#: (``paper``, ``lel-refit-lel``) compute σ from the truncated residuals and overclaim 3-7x; LS is biased.
CALIBRATED = ("corner", "adaptive", "lel-refit-ls", "lel", "constant-depth", "fcm-ransac")


@pytest.mark.parametrize("method", FAST_METHODS)
def test_every_method_against_the_paper_corner(method: str, paper_scans) -> None:
    for scan, inputs in paper_scans:
        rec = reconstruct(method=method, **inputs)
        truth = {p.label: p for p in scan.truth.planes}
        for p in rec.planes:
            assert isinstance(p, PlaneFit), str(p)
            assert p.method == method and p.diagnostics.time_s > 0
            t = truth[p.label]
            angle = np.deg2rad(angle_deg(p.normal, t.normal))
            if method == "ls":
                continue
            # The observed patch spans ~24 cm × 6 cm; σ_r = 2 mm over ≥ 200 echoes puts a robust fit within
            # 5σ_r/√n < 1 mm of it; 1 cm (5σ_r) leaves room for the inefficient refits.
            assert abs(p.offset - t.offset) < 0.01, (method, p.label)
            if method in CALIBRATED:
                assert angle <= 5 * p.normal_stderr and abs(p.offset - t.offset) <= 5 * p.offset_stderr, (
                    method,
                    p.label,
                    np.rad2deg(angle),
                    np.rad2deg(p.normal_stderr),
                )
        if method == "ls":
            # LS on the paper's subsets runs through the multipath cluster: 17° on plane b in the paper's
            # eq. 16 — and the verdict says so.
            b = rec.plane_b
            assert angle_deg(b.normal, truth["b"].normal) > 10 and b.quality == "unreliable"
        assert isinstance(rec.edge, EdgeLine)


def test_paper_method_runs_the_six_start_nelder_mead(paper_scans) -> None:
    scan, inputs = paper_scans[0]
    rec = reconstruct(method="paper", **inputs)
    truth = {p.label: p for p in scan.truth.planes}
    for p in rec.planes:
        assert isinstance(p, PlaneFit) and p.diagnostics.starts == 12  # six before and six after the pre-filter
        # The corrected points pin an axis-aligned wall's normal to ~0.02° (σ_r/(spread·√n)); the paper's
        # LEL refit on the 10 % pre-filtered points drifts along the weakly constrained direction by up to
        # ~0.4° (the README's p95): 0.5° catches a broken refit, not that known drift.
        assert angle_deg(p.normal, truth[p.label].normal) < 0.5
        assert abs(p.offset - truth[p.label].offset) < 0.01


def test_noise_free_scan_is_recovered_exactly_and_the_edge_is_the_true_one() -> None:
    s = _scan(0, noise=0.0)
    rec = _run(s, DEFAULT_METHOD)
    for p, n, h in zip(rec.planes, s.normals, s.offsets):
        assert angle_deg(p.normal, n) < 1e-6 and p.offset == pytest.approx(h, abs=1e-9)
    e = rec.edge
    assert isinstance(e, EdgeLine)
    np.testing.assert_allclose(e.point, [0, 1.57, 1.06], atol=1e-8)
    assert abs(e.direction[0]) == pytest.approx(1.0) and e.angle == pytest.approx(np.pi / 2)


def test_constant_depth_fixes_a_tilted_wall_that_biases_the_paper_correction() -> None:
    tilt = np.deg2rad(8.0)
    errs = {m: [] for m in ("lel-refit-ls", "constant-depth", "adaptive")}
    for seed in range(3):
        s = _scan(seed, noise=0.001, normal_a=tilted_normal((0, 1, 0), tilt), n_steps=300)
        for m in errs:
            errs[m].append(angle_deg(_run(s, m).plane_a.normal, s.normals[0]))
    assert min(errs["lel-refit-ls"]) > 6.0  # the axis-aligned correction loses the tilt
    # The mirror-echo model's normal rests on the capsules' 3 cm lever arm: with σ_r = 1 mm over ~300
    # echoes its RMS tilt error is ~0.3°, so 1.5° is 5σ (test_reconstruct_fit checks the calibration).
    assert max(errs["constant-depth"]) < 1.5
    assert max(errs["adaptive"]) < 1.5  # the tilt test switches to the mirror-echo model


def test_guard_recovers_from_the_outlier_cluster() -> None:
    """Plane b of this scan has ~37 % corner echoes: LEL from θ_LS locks on the cluster."""
    s = _scan(1)
    free = _run(s, "lel", options=FitOptions(guard=False)).plane_b
    guarded = _run(s, "lel").plane_b
    assert angle_deg(free.normal, s.normals[1]) > 5.0
    assert angle_deg(guarded.normal, s.normals[1]) < 0.5
    assert any("guard: switched" in n for n in guarded.diagnostics.notes)


def test_degenerate_inputs_give_typed_failures_never_nans() -> None:
    g = np.linspace(-0.17, 1.9, 40)
    empty = reconstruct(g, np.full((40, 4), np.nan), np.zeros((40, 4)), GEO, MODEL)
    assert empty.critical_step is None and isinstance(empty.plane_a, FitFailure)
    assert empty.plane_a.reason is FailureReason.TOO_FEW_POINTS and isinstance(empty.edge, FitFailure)
    assert len(empty.failures) == 3
    # One step of echoes: four collinear points per subset at most.
    d = np.full((40, 4), np.nan)
    d[10] = d[30] = 1.5
    d[20] = 1.9
    e = np.where(np.isfinite(d), 1.0, 0.0)
    e[20] = 10.0
    rec = reconstruct(g, d, e, GEO, MODEL)
    assert rec.critical_step == 20
    for p in rec.planes:
        assert isinstance(p, FitFailure) and p.reason is FailureReason.TOO_FEW_POINTS
    # A wall seen from a single angle: a line of points -> degenerate geometry.
    d = np.full((40, 4), np.nan)
    d[:, :] = 1.5
    geo1 = ArrayGeometry(capsule_x=(0.0,), radial_offset=0.0)
    e = np.ones((40, 1))
    e[-1] = 10.0
    rec = reconstruct(np.zeros(40), d[:, :1], e, geo1, MODEL)
    assert rec.critical_step == 39
    assert isinstance(rec.plane_a, FitFailure) and rec.plane_a.reason is FailureReason.DEGENERATE_GEOMETRY


def test_malformed_inputs_raise_config_errors() -> None:
    g = np.zeros(10)
    with pytest.raises(ConfigError):
        reconstruct(g, np.ones((10, 3)), np.ones((10, 4)), GEO, MODEL)
    with pytest.raises(ConfigError):
        reconstruct(g, -np.ones((10, 4)), np.ones((10, 4)), GEO, MODEL)
    with pytest.raises(ConfigError):
        reconstruct(g + np.nan, np.ones((10, 4)), np.ones((10, 4)), GEO, MODEL)
    with pytest.raises(ConfigError):
        FitOptions(prefilter_fraction=0)


def test_partial_scans_and_warm_starts() -> None:
    s = _scan(3)
    half = slice(0, 50)  # before the corner: only plane a can be estimated
    part = reconstruct(s.gamma[half], s.distance[half], s.sensor_energy[half], GEO, MODEL)
    # The best R so far is not the corner; the "b" subset holds wall-a echoes seen at
    # γ < 30°, which no plane facing +z can have returned: the mirror-echo check says so.
    assert isinstance(part.plane_b, FitFailure) and part.plane_b.reason is FailureReason.DEGENERATE_GEOMETRY
    assert isinstance(part.plane_a, PlaneFit)
    # Warm starts are extra LEL starts of the per-subset methods (the live service's provisional refits).
    full = _run(s, "adaptive")
    warm = _run(s, "adaptive", warm_start=(full.plane_a.theta, None))
    assert warm.plane_a.diagnostics.starts == full.plane_a.diagnostics.starts + 1
    assert angle_deg(warm.plane_a.normal, full.plane_a.normal) < 1e-6
    junk = _run(s, "adaptive", warm_start=(np.array([5.0, -3.0, 0.1]), None))  # a stale, bad warm start
    assert angle_deg(junk.plane_a.normal, s.normals[0]) < 0.5


def test_results_are_frozen() -> None:
    rec = _run(_scan(4), DEFAULT_METHOD)
    with pytest.raises(dataclasses.FrozenInstanceError):
        rec.method = "x"  # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        rec.timings.total = 0.0  # type: ignore[misc]
    assert rec.timings.total >= rec.timings.fit > 0


def test_edge_needs_two_non_parallel_planes() -> None:
    rec = _run(_scan(5), DEFAULT_METHOD)
    assert isinstance(corner_edge(rec.plane_a, rec.plane_a), FitFailure)
    assert isinstance(corner_edge(rec.plane_a, FitFailure(FailureReason.TOO_FEW_POINTS, "x", "b")), FitFailure)


def test_adaptive_removes_the_correction_offset_bias_on_a_yawed_wall() -> None:
    """Wall a leaning 5° towards +x: the corrected points get its direction right but sit
    h·(1 − cos 5°) ≈ 6 mm too near; the mirror-echo offset does not."""
    off = {"lel-refit-ls": [], "adaptive": []}
    for seed in range(3):
        s = _scan(seed, noise=0.001, normal_a=tilted_normal((0, 1, 0), 0.0, np.deg2rad(5.0)), n_steps=300)
        for m in off:
            p = _run(s, m).plane_a
            off[m].append(abs(p.offset - s.offsets[0]))
            assert angle_deg(p.normal, s.normals[0]) < 0.3
    assert min(off["lel-refit-ls"]) > 0.004
    assert max(off["adaptive"]) < 0.001


@settings(max_examples=200, deadline=None)
@given(st.lists(st.one_of(st.just(float("nan")), st.floats(-3.0, 3.0)), min_size=3, max_size=40), st.integers(0, 39))
def test_split_labels_by_the_nan_median_angle(g: list[float], crit: int) -> None:
    """Plane a is the subset of smaller median γ (NaN ignored), as np.nanmedian decides it."""
    import warnings

    g_arr = np.asarray(g)
    crit = crit % len(g)
    s = split_subsets(g_arr, crit)
    before, after = g_arr[:crit], g_arr[crit + 1 :]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN subsets
        mb = np.nanmedian(before) if before.size else np.nan
        ma = np.nanmedian(after) if after.size else np.nan
    if before.size and after.size:
        swap = mb > ma
    elif before.size:
        swap = mb > g_arr[crit]
    else:
        swap = ma < g_arr[crit]
    np.testing.assert_array_equal(s.steps_a, np.arange(crit + 1, len(g)) if swap else np.arange(crit))
    assert crit not in s.steps_a and crit not in s.steps_b
