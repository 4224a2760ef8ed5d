"""The Rerun timeline logging of the reconstruction, read back from the .rrd it writes."""

from __future__ import annotations

import math
import shutil
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest
import rerun as rr
from rerun.chunk import RrdReader

from lelsonar.errors import ConfigError
from lelsonar.geometry import ArrayGeometry, beam_points
from lelsonar.reconstruct.estimate.results import (
    EdgeLine,
    FailureReason,
    FitFailure,
    PlaneFit,
    SolverDiagnostics,
)
from lelsonar.view.rerun_log import ScanLogger, SubsetView, default_blueprint, make_recording

T_START_NS = 1_700_000_000_000_000_000
STEP_NS = 50_000_000
N_STEPS = 20
N_SAMPLES = 400
SAMPLE_RATE = 200_000.0
T0 = 1e-3
H_A, H_B = 1.57, 1.06
N_A, N_B = np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0])


# -- helpers ----------------------------------------------------------------------------------------


def _rerun_cli() -> str:
    exe = Path(sys.executable).with_name("rerun")
    return str(exe) if exe.exists() else (shutil.which("rerun") or "rerun")


def read_rrd(path: Path) -> dict[str, list[pa.RecordBatch]]:
    """Record batches of the recording, by entity path."""
    out: dict[str, list[pa.RecordBatch]] = defaultdict(list)
    for chunk in RrdReader(path).store().stream().to_chunks():
        out[str(chunk.entity_path)].append(chunk.to_record_batch())
    return out


def column(batches: list[pa.RecordBatch], name: str) -> list:
    """One column over all batches of an entity, rows sorted by the ``step`` timeline when present."""
    rows = []
    for b in batches:
        if name not in b.schema.names:
            continue
        steps = b.column("step").to_pylist() if "step" in b.schema.names else [None] * b.num_rows
        rows += [(s if s is not None else -1, v) for s, v in zip(steps, b.column(name).to_pylist())]
    return [v for _, v in sorted(rows, key=lambda r: r[0])]


def mono(batches: list[pa.RecordBatch], name: str) -> list:
    """Like :func:`column`, for a component with one instance per row (text, level, ...)."""
    return [v[0] if v else None for v in column(batches, name)]


def names(batches: list[pa.RecordBatch]) -> set[str]:
    return {n for b in batches for n in b.schema.names}


def corner_ranges(geometry: ArrayGeometry, gamma: float) -> np.ndarray:
    """Ranges of each capsule to the nearer wall of an L corner (walls y = H_A, z = H_B)."""
    caps = geometry.capsule_positions(gamma)
    c, s = math.cos(gamma), math.sin(gamma)
    d_a = (H_A - caps[:, 1]) / c if c > 1e-6 else np.full(len(caps), np.inf)
    d_b = (H_B - caps[:, 2]) / s if s > 1e-6 else np.full(len(caps), np.inf)
    return np.minimum(d_a, d_b)


def plane_fit(
    method: str,
    label: str,
    rng: np.random.Generator,
    n_points: int = 40,
    tilt: float = 0.0,
    points_out: dict | None = None,
) -> PlaneFit:
    base, h = (N_A, H_A) if label == "a" else (N_B, H_B)
    normal = base + np.array([0.0, 0.0, tilt]) if label == "a" else base + np.array([0.0, tilt, 0.0])
    normal /= np.linalg.norm(normal)
    u = np.array([1.0, 0.0, 0.0])
    w = np.cross(normal, u)
    o = h * normal
    patch = np.array([o + a * u + b * w for a, b in ((-0.15, -0.4), (0.15, -0.4), (0.15, 0.4), (-0.15, 0.4))])
    mask = rng.random(n_points) > 0.15
    # Points scattered about the true wall; the fit's residuals are theirs against the fitted plane.
    points = (
        rng.uniform(-0.4, 0.4, (n_points, 1)) * w
        + rng.uniform(-0.15, 0.15, (n_points, 1)) * u
        + (h + rng.normal(0, 0.01, (n_points, 1))) * (N_A if label == "a" else N_B)
    )
    if points_out is not None:
        points_out[(method, label)] = points
    residuals = points @ normal - h
    return PlaneFit(
        label=label,
        method=method,
        normal=normal,
        offset=h,
        entropy=0.4,
        sigma_relative=0.002,
        sigma=0.002 * h,
        inlier_mask=mask,
        sorted_residuals=np.sort(residuals),
        theta_covariance=np.eye(3) * 1e-8,
        normal_stderr=1e-3,
        offset_stderr=1e-3,
        patch=patch,
        diagnostics=SolverDiagnostics("lstsq"),
    )


def log_scan(
    rec: rr.RecordingStream, scanner_id: str = "s1", scan_id: int = 7, seed: int = 0, t_start_ns: int = T_START_NS
) -> dict:
    """Log a synthetic 20-step scan with one partial and one final estimate; return what was sent."""
    rng = np.random.default_rng(seed)
    geometry = ArrayGeometry()
    logger = ScanLogger(rec, scanner_id, scan_id)
    gamma = np.deg2rad(np.linspace(-10.0, 110.0, N_STEPS))
    logger.scan_started(
        t_start_ns, gamma[0], gamma[-1], N_STEPS, geometry.capsules_in_array_frame(), "synthetic corner"
    )
    sent = {"n_points": [], "waveforms": [], "ratio": [], "gamma": gamma}
    for k, g in enumerate(gamma):
        d = corner_ranges(geometry, g) + rng.normal(0.0, 0.003, 4)
        d[rng.random(4) < 0.2] = np.nan  # no echo on some capsules
        points = beam_points(geometry, np.array([g]), d[None])[0]
        waves = rng.normal(0.0, 0.05, (4, N_SAMPLES))
        energy = float(rng.uniform(1e-4, 1e-3))
        expected = float(rng.uniform(1e-4, 1e-3))
        ratio = energy / expected
        logger.step(
            k,
            t_start_ns + k * STEP_NS,
            g,
            points,
            geometry.capsule_positions(g),
            waves,
            SAMPLE_RATE,
            T0,
            energy,
            expected,
            ratio,
        )
        sent["n_points"].append(int(np.isfinite(d).sum()))
        sent["waveforms"].append(waves)
        sent["ratio"].append(ratio)
        if k == 9:  # a partial estimate: ls already fits plane b, another method fails on it
            logger.estimate(
                k,
                t_start_ns + k * STEP_NS,
                [
                    plane_fit("ls", "a", rng),
                    plane_fit("lel", "a", rng),
                    plane_fit("ls", "b", rng),
                    FitFailure(FailureReason.TOO_FEW_POINTS, "3 < 8 points", "b", 3),
                ],
                None,
                [SubsetView("a", rng.normal([0, H_A, 0.3], 0.05, (40, 3)), rng.random(40) > 0.2)],
                critical_step=None,
                critical_gamma=None,
                final=False,
            )
    last = N_STEPS - 1
    sent["fit_points"] = {}
    fits = [
        plane_fit(m, lab, rng, tilt=t, points_out=sent["fit_points"])
        for m, t in (("ls", 0.05), ("lel", 0.0))
        for lab in ("a", "b")
    ]
    subsets = [
        SubsetView(lab, rng.normal(o, 0.05, (40, 3)), rng.random(40) > 0.2)
        for lab, o in (("a", [0, H_A, 0.3]), ("b", [0, 0.6, H_B]))
    ]
    edge = EdgeLine(point=np.array([0.0, H_A, H_B]), direction=np.array([1.0, 0.0, 0.0]), angle=math.pi / 2)
    sent["critical"] = 6
    logger.estimate(
        last,
        t_start_ns + last * STEP_NS,
        fits,
        edge,
        subsets,
        critical_step=6,
        critical_gamma=float(gamma[6]),
        final=True,
    )
    lel = {f.label: f for f in fits if f.method == "lel"}  # untilted: their patches lie on the true walls
    logger.truth([("a", N_A, H_A, lel["a"].patch), ("b", N_B, H_B, lel["b"].patch)])
    logger.event("warning", "synthetic scan done")
    sent["fits"] = fits
    return sent


@pytest.fixture(scope="module")
def scan_rrd(tmp_path_factory) -> tuple[Path, dict]:
    path = tmp_path_factory.mktemp("rerun") / "scan.rrd"
    rec = make_recording(recording_id="test-scan")
    rec.save(path, default_blueprint=default_blueprint())
    sent = log_scan(rec)
    rec.flush()
    rec.disconnect()
    return path, sent


# -- tests ------------------------------------------------------------------------------------------


def test_the_file_verifies(scan_rrd):
    path, _ = scan_rrd
    done = subprocess.run([_rerun_cli(), "rrd", "verify", str(path)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr


def test_every_view_has_its_entities(scan_rrd):
    path, _ = scan_rrd
    ents = read_rrd(path)
    scan = "/world/s1/scans/scan_7"
    expected = {
        "/world": "ViewCoordinates:xyz",
        "/world/s1/array": "Transform3D:quaternion",
        "/world/s1/array/capsules": "Points3D:positions",
        f"{scan}/raw": "Points3D:positions",
        f"{scan}/beams": "Arrows3D:vectors",
        f"{scan}/corrected/a": "Points3D:positions",
        f"{scan}/corrected/b": "Points3D:positions",
        f"{scan}/planes/ls/a": "Mesh3D:vertex_positions",
        f"{scan}/planes/lel/b": "Mesh3D:vertex_positions",
        f"{scan}/planes/lel/b/normal": "Arrows3D:vectors",
        f"{scan}/edge": "LineStrips3D:strips",
        f"{scan}/critical": "LineStrips3D:strips",
        "/world/s1/truth/a": "Mesh3D:vertex_positions",
        "/plots/energy/s1/scan_7": "Scalars:scalars",
        "/plots/ratio/s1/scan_7/R": "Scalars:scalars",
        "/plots/ratio/s1/scan_7/critical": "Scalars:scalars",
        "/plots/waveforms/s1/scan_7": "LineStrips2D:strips",
        "/plots/errors/a/s1/scan_7/lel": "BarChart:values",
        "/plots/errors/b/s1/scan_7/ls": "BarChart:values",
        "/log/s1/scan_7": "TextLog:text",
    }
    missing = {e: c for e, c in expected.items() if e not in ents or c not in names(ents[e])}
    assert not missing, f"missing: {missing}; have {sorted(ents)}"
    for e in ("/world/s1/scans/scan_7/raw", "/world/s1/array", "/plots/ratio/s1/scan_7/R"):
        assert {"step", "gamma_cdeg", "acq_time"} <= names(ents[e])


def test_steps_carry_pose_points_and_scalars(scan_rrd):
    path, sent = scan_rrd
    ents = read_rrd(path)
    gamma = sent["gamma"]

    assert column(ents["/world/s1/array"], "step") == list(range(N_STEPS))
    assert column(ents["/world/s1/array"], "gamma_cdeg") == [round(math.degrees(g) * 100) for g in gamma]
    quats = np.array([q[0] for q in column(ents["/world/s1/array"], "Transform3D:quaternion")])
    np.testing.assert_allclose(quats[:, 0], np.sin(gamma / 2), atol=1e-6)  # rotation about x by γ
    np.testing.assert_allclose(quats[:, 3], np.cos(gamma / 2), atol=1e-6)

    # The raw cloud grows by this step's echoes only: NaN rows (no echo) are dropped.
    clouds = column(ents["/world/s1/scans/scan_7/raw"], "Points3D:positions")
    assert [len(c) for c in clouds] == list(np.cumsum(sent["n_points"]))
    assert np.isfinite(np.array(clouds[-1], dtype=float)).all()
    beams = column(ents["/world/s1/scans/scan_7/beams"], "Arrows3D:vectors")
    assert [len(b) for b in beams] == sent["n_points"]

    ratio = [r[0] for r in column(ents["/plots/ratio/s1/scan_7/R"], "Scalars:scalars")]
    np.testing.assert_allclose(ratio, sent["ratio"])
    energy = column(ents["/plots/energy/s1/scan_7"], "Scalars:scalars")
    assert all(len(e) == 2 for e in energy) and len(energy) == N_STEPS

    # The critical marker sits on R at the critical step itself.
    crit = ents["/plots/ratio/s1/scan_7/critical"]
    assert column(crit, "step") == [sent["critical"]]
    np.testing.assert_allclose(column(crit, "Scalars:scalars")[0], [sent["ratio"][sent["critical"]]])


def test_waveforms_are_not_overwritten_by_later_steps(scan_rrd):
    # Rerun keeps zero-copy views of logged arrays until it flushes; each step must own its strips.
    path, sent = scan_rrd
    strips = column(read_rrd(path)["/plots/waveforms/s1/scan_7"], "LineStrips2D:strips")
    assert len(strips) == N_STEPS
    for k in (0, N_STEPS // 2, N_STEPS - 1):
        s = np.array(strips[k], dtype=float)  # (capsules, samples, 2)
        assert s.shape == (4, N_SAMPLES, 2)
        np.testing.assert_allclose(s[0, :, 0], (T0 + np.arange(N_SAMPLES) / SAMPLE_RATE) * 1e3, rtol=1e-6)
        volts = np.arange(4)[:, None] * 1.0 - s[:, :, 1]  # undo the stacking and the y-down flip
        np.testing.assert_allclose(volts, sent["waveforms"][k], atol=1e-6)


def test_estimates_draw_planes_edge_and_flag_outliers(scan_rrd):
    path, sent = scan_rrd
    ents = read_rrd(path)
    scan = "/world/s1/scans/scan_7"

    fit = next(f for f in sent["fits"] if (f.method, f.label) == ("lel", "a"))
    mesh = ents[f"{scan}/planes/lel/a"]
    np.testing.assert_allclose(np.array(column(mesh, "Mesh3D:vertex_positions")[-1]), fit.patch, atol=1e-6)
    assert len(column(mesh, "Mesh3D:triangle_indices")[-1]) == 2
    ls_rgba = column(ents[f"{scan}/planes/ls/a"], "Mesh3D:albedo_factor")[-1]
    lel_rgba = column(mesh, "Mesh3D:albedo_factor")[-1]
    assert ls_rgba != lel_rgba  # methods are told apart by colour

    # The bar charts are each final fit's sorted errors e_i, recomputed here from its points.
    for method, label in (("lel", "a"), ("lel", "b"), ("ls", "a"), ("ls", "b")):
        f = next(f for f in sent["fits"] if (f.method, f.label) == (method, label))
        (bars,) = column(ents[f"/plots/errors/{label}/s1/scan_7/{method}"], "BarChart:values")[-1]
        expected = np.sort(sent["fit_points"][(method, label)] @ f.normal - f.offset)
        assert bars["shape"] == [len(expected)]
        np.testing.assert_allclose(bars["buffer"], expected, rtol=0, atol=1e-12)

    seg = np.array(column(ents[f"{scan}/edge"], "LineStrips3D:strips")[-1][0])
    assert seg.shape == (2, 3)
    np.testing.assert_allclose(seg[:, 1:], [[H_A, H_B], [H_A, H_B]], atol=1e-9)
    assert -0.5 <= seg[0, 0] < seg[1, 0] <= 0.5  # clipped to the patches, ±0.5 m at most
    np.testing.assert_allclose(seg[:, 0], [-0.15, 0.15], atol=1e-9)

    # Outliers are drawn bigger than inliers.
    radii = np.array(column(ents[f"{scan}/corrected/b"], "Points3D:radii")[-1])
    assert len(set(np.round(radii, 6))) == 2


def test_a_failure_is_reported_and_takes_down_the_stale_patch(scan_rrd):
    path, _ = scan_rrd
    ents = read_rrd(path)
    log = ents["/log/s1/scan_7"]
    rows = list(zip(mono(log, "TextLog:level"), mono(log, "TextLog:text")))
    # Before the final, a plane not fitted yet is an expected state (the beams have not reached wall b):
    # not a warning.
    said = [(lvl, txt) for lvl, txt in rows if "plane b" in txt and "too few points" in txt]
    assert said and all(lvl == "DEBUG" for lvl, _ in said)
    assert not any(lvl == "WARN" and "not fitted" in txt for lvl, txt in rows)
    assert any(lvl == "INFO" and txt.startswith("final estimate") for lvl, txt in rows)
    assert any("critical step 6" in txt for _, txt in rows)
    assert any(lvl == "WARN" and txt == "synthetic scan done" for lvl, txt in rows)
    # At step 9 ls fitted plane b while another method failed on it: the fresh ls patch stays.
    assert "Clear:is_recursive" not in names(ents["/world/s1/scans/scan_7/planes/ls/b"])


def test_a_method_that_fails_later_is_cleared(tmp_path):
    path = tmp_path / "clear.rrd"
    rec = make_recording(recording_id="clear")
    rec.save(path)
    rng = np.random.default_rng(3)
    logger = ScanLogger(rec, "s1", 1)
    logger.estimate(5, T_START_NS, [plane_fit("lel", "b", rng)], None, [], None, None, final=False)
    logger.estimate(
        6,
        T_START_NS + STEP_NS,
        [FitFailure(FailureReason.SOLVER_FAILED, "diverged", "b", 20)],
        None,
        [],
        None,
        None,
        final=False,
    )
    logger.estimate(
        7,
        T_START_NS + 2 * STEP_NS,
        [FitFailure(FailureReason.SOLVER_FAILED, "diverged", "b", 20)],
        None,
        [],
        None,
        None,
        final=False,
    )
    rec.flush()
    rec.disconnect()
    ents = read_rrd(path)
    plane = ents["/world/s1/scans/scan_1/planes/lel/b"]
    assert mono(plane, "Clear:is_recursive") == [True]
    assert column(plane, "step")[-1] == 6
    warnings = [t for t in mono(ents["/log/s1/scan_1"], "TextLog:text") if "solver failed" in t]
    assert len(warnings) == 1  # the same failure is said once


def test_two_scans_in_one_recording_do_not_collide(tmp_path):
    path = tmp_path / "two.rrd"
    rec = make_recording(recording_id="two")
    rec.save(path, default_blueprint=default_blueprint())
    log_scan(rec, "s1", 7, seed=1)
    log_scan(rec, "s1", 8, seed=2, t_start_ns=T_START_NS + 10**10)
    rec.flush()
    rec.disconnect()
    ents = read_rrd(path)
    for scan in ("scan_7", "scan_8"):
        assert len(column(ents[f"/world/s1/scans/{scan}/raw"], "Points3D:positions")) == N_STEPS
        assert len(column(ents[f"/plots/ratio/s1/{scan}/R"], "Scalars:scalars")) == N_STEPS
    # The scanner's pose is one entity, logged by both scans.
    assert len(column(ents["/world/s1/array"], "Transform3D:quaternion")) == 2 * N_STEPS


def read_blueprint(path: Path) -> dict:
    """Views (class → sorted origins), panel states, the time panel's timeline and the column shares."""
    reader = RrdReader(path)
    entries = reader.blueprints()
    assert len(entries) == 1
    out: dict = {"views": defaultdict(list), "panels": {}, "timeline": None, "col_shares": None}
    for chunk in reader.store(store=entries[0]).stream().to_chunks():
        b = chunk.to_record_batch()
        cols = set(b.schema.names)
        if "ViewBlueprint:class_identifier" in cols:
            for cls, origin in zip(
                b.column("ViewBlueprint:class_identifier").to_pylist(),
                b.column("ViewBlueprint:space_origin").to_pylist(),
            ):
                out["views"][cls[0]].append(origin[0])
        if "PanelBlueprint:state" in cols:
            out["panels"][str(chunk.entity_path)] = b.column("PanelBlueprint:state").to_pylist()[0][0]
        if "TimePanelBlueprint:timeline" in cols:
            out["timeline"] = b.column("TimePanelBlueprint:timeline").to_pylist()[0][0]
        if "ContainerBlueprint:col_shares" in cols:
            out["col_shares"] = b.column("ContainerBlueprint:col_shares").to_pylist()[0]
    out["views"] = {k: sorted(v) for k, v in out["views"].items()}
    return out


def test_the_blueprint_lays_out_world_plots_and_log(scan_rrd):
    bp = read_blueprint(scan_rrd[0])
    assert bp["views"] == {
        "3D": ["/world"],
        "TimeSeries": ["/plots/energy", "/plots/ratio"],
        "2D": ["/plots/waveforms"],
        "BarChart": ["/plots/errors/a", "/plots/errors/b"],
        "TextLog": ["/log"],
    }
    collapsed = 2  # rrb.PanelState.Collapsed
    assert bp["panels"] == {"/blueprint_panel": collapsed, "/selection_panel": collapsed}
    assert bp["timeline"] == "step"
    assert bp["col_shares"] == [3.0, 2.0]  # the world takes 3/5 of the width


def test_default_blueprint_and_logger_follow_the_root(tmp_path):
    path = tmp_path / "root.rrd"
    rec = make_recording(recording_id="root")
    rec.save(path, default_blueprint=default_blueprint("/review/"))
    logger = ScanLogger(rec, "s 1", 2, root="/review")
    logger.event("info", "hello", t_ns=T_START_NS)
    rec.flush()
    rec.disconnect()
    assert read_blueprint(path)["views"]["3D"] == ["/review/world"]
    assert read_blueprint(path)["views"]["TextLog"] == ["/review/log"]
    ents = read_rrd(path)
    assert "/review/world" in ents
    assert mono(ents["/review/log/s\\ 1/scan_2"], "TextLog:level") == ["INFO"]


def test_subset_view_checks_its_shapes():
    with pytest.raises(ConfigError):
        SubsetView("a", np.zeros((5, 2)), np.ones(5, bool))
    with pytest.raises(ConfigError):
        SubsetView("a", np.zeros((5, 3)), np.ones(4, bool))
    points = np.zeros((3, 3))
    view = SubsetView("a", points, [True, False, True])
    points[0, 0] = 1.0
    assert view.points[0, 0] == 0.0 and not view.points.flags.writeable


def test_long_waveforms_are_drawn_as_their_envelope(tmp_path):
    path = tmp_path / "envelope.rrd"
    rec = make_recording(recording_id="envelope")
    rec.save(path)
    rng = np.random.default_rng(5)
    geometry = ArrayGeometry()
    logger = ScanLogger(rec, "s1", 1, waveform_points=1000)
    n = 3500
    waves = rng.normal(0.0, 0.05, (4, n))
    waves[2, 1234] = 0.9  # one sharp peak must survive
    logger.step(
        0,
        T_START_NS,
        0.0,
        np.full((4, 3), np.nan),
        geometry.capsule_positions(0.0),
        waves,
        SAMPLE_RATE,
        T0,
        1.0,
        1.0,
        1.0,
    )
    rec.flush()
    rec.disconnect()
    s = np.array(column(read_rrd(path)["/plots/waveforms/s1/scan_1"], "LineStrips2D:strips")[0], dtype=float)
    assert s.shape == (4, 1000, 2)
    volts = np.arange(4)[:, None] - s[:, :, 1]
    np.testing.assert_allclose(volts.max(axis=1), waves.max(axis=1), atol=1e-6)
    np.testing.assert_allclose(volts.min(axis=1), waves.min(axis=1), atol=1e-6)
    assert np.all(np.diff(s[0, :, 0]) >= 0)  # time still runs forward
    assert s[0, 0, 0] == pytest.approx(T0 * 1e3) and s[0, -1, 0] == pytest.approx((T0 + (n - 1) / SAMPLE_RATE) * 1e3)


def test_the_final_step_draws_only_the_final_planes(tmp_path):
    path = tmp_path / "final.rrd"
    rec = make_recording(recording_id="final")
    rec.save(path)
    rng = np.random.default_rng(4)
    logger = ScanLogger(rec, "s1", 1, main_method="corner")
    provisional = [plane_fit("adaptive", "a", rng), plane_fit("adaptive", "b", rng)]
    logger.estimate(5, T_START_NS, provisional, None, [], None, None, final=False)
    final = [plane_fit(m, lab, rng) for m in ("corner", "ls") for lab in ("a", "b")]
    logger.estimate(9, T_START_NS + 4 * STEP_NS, final, None, [], None, None, final=True)
    rec.flush()
    rec.disconnect()
    ents = read_rrd(path)
    for label in ("a", "b"):
        gone = ents[f"/world/s1/scans/scan_1/planes/adaptive/{label}"]
        assert mono(gone, "Clear:is_recursive") == [True] and column(gone, "step")[-1] == 9
        assert "Clear:is_recursive" not in names(ents[f"/world/s1/scans/scan_1/planes/corner/{label}"])
        # One label per plane: the method of record's.
        corner = column(ents[f"/world/s1/scans/scan_1/planes/corner/{label}/normal"], "Arrows3D:labels")[-1]
        assert corner == [f"{label}: corner, unassessed"] or corner[0].startswith(f"{label}: corner")
        assert not column(ents[f"/world/s1/scans/scan_1/planes/ls/{label}/normal"], "Arrows3D:labels")
