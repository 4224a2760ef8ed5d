"""The family benchmark's definitions (failure, z-score) and the MCAP path that reproduces its scenes."""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lelsonar.acquire.simulated import record_scan
from lelsonar.log.recording import read_metadata
from lelsonar.reconstruct.estimate.pipeline import DEFAULT_METHOD, reconstruct
from lelsonar.signal.energy import echo_amplitude, waveform_energy
from lelsonar.sim import simulate_scan
from lelsonar.sim.scenes import calibrated_energy_model, draw_scene, simulate_family_scene
from lelsonar.tools import bench_families as B

LELSONAR = [sys.executable, "-m", "lelsonar"]


@pytest.mark.parametrize(
    ("patch", "oracle", "fails"),
    [
        (2.5, 0.5, True),  # > 2 cm and > 3×
        (2.5, 1.0, False),  # > 2 cm but only 2.5× the oracle
        (1.9, 0.01, False),  # 190× the oracle but under 2 cm
        (6.1, 2.0, True),
        (6.0, 2.0, False),  # exactly 3×: not above
        (float("nan"), 0.1, False),
        (3.0, float("nan"), False),
    ],
)
def test_failure_needs_both_thresholds(patch, oracle, fails):
    assert B.is_failure(patch, oracle) is fails


def test_z_score_and_quality_names():
    assert B.z_score(0.02, 0.01) == pytest.approx(2.0)
    assert B.z_score(-0.03, 0.01) == pytest.approx(-3.0)
    assert math.isnan(B.z_score(0.01, 0.0)) and math.isnan(B.z_score(float("nan"), 1.0))
    assert B.quality_name(None) is None and B.quality_name("") is None  # "": not assessed
    assert B.quality_name("GOOD") == "good"
    assert B.quality_name("PLANE_QUALITY_DEGRADED") == "degraded"

    class Q:  # an enum-like with a string value
        value = "unreliable"

    assert B.quality_name(Q()) == "unreliable"


def test_plane_errors_patch_is_the_largest_distance_over_the_true_patch():
    n = np.array([0.0, 1.0, 0.0])
    tilted = np.array([0.0, math.cos(0.01), math.sin(0.01)])
    patch = np.array([[0, 1.0, -0.5], [0, 1.0, 0.5]])
    ang, off, pe = B.plane_errors(tilted, 1.0, n, 1.0, patch)
    assert ang == pytest.approx(math.degrees(0.01))
    assert off == 0.0
    assert pe == pytest.approx(100 * max(abs(math.cos(0.01) + z * math.sin(0.01) - 1.0) for z in (-0.5, 0.5)))


def _row(**kw):
    base = {
        "family": "f",
        "seed": 0,
        "method": "m",
        "label": "a",
        "observed": True,
        "ok": True,
        "failure": False,
        "oracle_fails": False,
        "angle_deg": 0.1,
        "offset_cm": 0.1,
        "patch_cm": 0.2,
        "oracle_patch_cm": 0.1,
        "z_angle": 0.5,
        "z_offset": -0.5,
        "quality": None,
        "time_plane_ms": 1.0,
        "time_scan_ms": 2.0,
    }
    return {**base, **kw}


def test_summary_counts_failures_z_and_quality():
    rows = [_row(seed=i, z_angle=z, z_offset=-z) for i, z in enumerate((0.2, 0.5, 0.8, 4.0))]
    rows += [
        _row(seed=9, failure=True, patch_cm=5.0, z_angle=10.0, z_offset=10.0, quality="good"),
        _row(seed=10, failure=True, oracle_fails=True, patch_cm=5.0, oracle_patch_cm=2.5, quality="degraded"),
        _row(seed=11, ok=False, patch_cm=float("nan")),
        _row(seed=12, observed=False),
    ]
    s = B.summarize(rows)
    assert (s["planes"], s["unobserved"], s["missing"]) == (7, 1, 1)
    assert s["failures"] == 2 and s["failures_oracle_avoids"] == 1 and s["failures_good"] == 1
    assert s["z_angle_med"] == pytest.approx(0.65) and s["z_angle_gt3"] == pytest.approx(2 / 6)
    assert s["z_offset_gt3"] == pytest.approx(2 / 6)
    assert B.summarize([_row()])["failures_good"] is None  # no quality attribute yet: n/a


def test_family_scan_rows_follow_the_definitions():
    scene, rows = B.family_scan("paper", 0, [DEFAULT_METHOD], anchor=False, dump_dir=None)
    assert scene["family"] == "paper" and scene["crit_true"] > 0
    assert {r["label"] for r in rows} == {"a", "b"}
    for r in rows:
        assert r["observed"] and r["ok"]
        assert r["failure"] == B.is_failure(r["patch_cm"], r["oracle_patch_cm"])
        assert r["z_angle"] == pytest.approx(math.radians(r["angle_deg"]) / math.radians(r["normal_stderr_deg"]))
        assert r["z_offset"] == pytest.approx(r["offset_cm"] / r["offset_stderr_cm"])
        assert r["oracle_patch_cm"] < 0.5 and r["patch_cm"] < 2.0  # the paper's L is easy
        assert 0 <= r["inlier_corner_share"] <= 1 and 0 <= r["subset_corner_share"] <= 1


def test_tiny_run_writes_json(tmp_path):
    from lelsonar.tools.bench_estimators import add_arguments

    p = argparse.ArgumentParser()
    add_arguments(p)
    out = tmp_path / "b.json"
    md = tmp_path / "b.md"
    args = p.parse_args(
        [
            "--families",
            "paper",
            "--seeds",
            "1",
            "--jobs",
            "1",
            "--no-anchor",
            "--timing-repeats",
            "1",
            "--methods",
            DEFAULT_METHOD,
            "--json",
            str(out),
            "--markdown",
            str(md),
        ]
    )
    B.run_families(args)
    table = md.read_text().splitlines()
    assert table[0].startswith("`") and table[2].startswith("| family |")
    assert [line.split(" | ")[:2] for line in table[4:]] == [
        ["| paper", f"**`{DEFAULT_METHOD}`**"],
        ["| all", f"**`{DEFAULT_METHOD}`**"],
    ]
    data = json.loads(out.read_text())
    assert data["families"] == ["paper"] and len(data["rows"]) == 2 and len(data["scenes"]) == 1
    assert {s["method"] for s in data["summary"]} == {DEFAULT_METHOD}


def _final(stdout: str) -> dict:
    return json.loads([line for line in stdout.splitlines() if line.startswith("{")][-1])


def test_simulate_family_mcap_round_trips_through_reconstruct(tmp_path):
    path = tmp_path / "scene.mcap"
    sim = subprocess.run(
        [*LELSONAR, "simulate", "--family", "partial", "--seed", "3", "--mcap", str(path)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert sim.returncode == 0, sim.stderr
    assert "partial #3" in sim.stdout
    rec = subprocess.run(
        [*LELSONAR, "reconstruct", "--source", str(path), "--json", "--compare", ""],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert rec.returncode == 0, rec.stderr
    final = _final(rec.stdout)

    fs = simulate_family_scene("partial", 3)
    scan = fs.scan
    # As the service computes them from each recorded Sample: energies and the first echoes' amplitudes.
    want = reconstruct(
        scan.gamma_measured,
        scan.distance,
        waveform_energy(scan.waveforms, scan.sample_rate),
        scan.geometry,
        fs.energy_model,
        echo_amplitude=echo_amplitude(scan.waveforms, scan.sample_rate, scan.t0, scan.tof),
    )
    assert final["critical_step"] == want.critical_step
    got = {p["label"]: p for p in final["planes"]}
    for label, plane in (("a", want.plane_a), ("b", want.plane_b)):
        n = got[label]["normal"]
        assert np.allclose([n["x"], n["y"], n["z"]], plane.normal, atol=1e-9)
        assert got[label]["offset"] == pytest.approx(plane.offset, abs=1e-9)
    meta = read_metadata(path)["lelsonar.config"]
    assert meta["family"] == "partial" and meta["seed"] == "3"
    truth = json.loads(meta["truth_planes"])
    assert truth["a"]["offset"] == pytest.approx(1.57)


def test_record_scan_is_what_dump_failures_writes(tmp_path):
    draw = draw_scene("noise", 1)
    scan = simulate_scan(draw.config, seed=1)
    end = record_scan(
        scan, tmp_path / "d" / "noise-1.mcap", calibrated_energy_model(draw.config), metadata={"family": "noise"}
    )
    assert end.samples_sent == scan.n_steps and Path(tmp_path / "d" / "noise-1.mcap").stat().st_size > 0


def test_dump_failures_writes_the_failing_scene_that_reconstruct_replays(tmp_path, monkeypatch):
    # Every fitted plane "fails" (patched where the scene runner looks it up).
    monkeypatch.setattr("lelsonar.tools.family_scan.is_failure", lambda patch, oracle: math.isfinite(patch))
    scene, rows = B.family_scan("corner", 2, [DEFAULT_METHOD], anchor=False, dump_dir=str(tmp_path))
    path = Path(scene["dump"])
    assert path == tmp_path / "corner-2.mcap" and path.exists()
    meta = read_metadata(path)["lelsonar.config"]
    assert meta["failures"] == f"{DEFAULT_METHOD}:a,{DEFAULT_METHOD}:b" and meta["description"].startswith("corner #2")
    rec = subprocess.run(
        [*LELSONAR, "reconstruct", "--source", str(path), "--json", "--compare", ""],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert rec.returncode == 0, rec.stderr
    got = {p["label"]: p["offset"] for p in _final(rec.stdout)["planes"]}
    assert got == {r["label"]: pytest.approx(r["offset"], abs=1e-12) for r in rows}


def test_failure_flags_name_the_patterns():
    base = {
        "label": "a",
        "true_normal": [0.0, 1.0, 0.0],
        "other_normal": [0.0, 0.0, 1.0],
        "true_offset": 1.57,
        "edge_range": 1.89,
        "n_mirror": 300,
        "crit": 50,
        "crit_true": 50,
        "uses_split": True,
        "normal": [0.0, 1.0, 0.0],
        "offset": 1.60,
        "inlier_corner_share": 0.0,
    }
    assert B.failure_flags(base) == ["unexplained"]
    assert B.failure_flags({**base, "crit": 10}) == ["critical step"]
    assert B.failure_flags({**base, "crit": 10, "uses_split": False}) == ["unexplained"]
    assert B.failure_flags({**base, "offset": 1.85}) == ["corner cluster"]
    assert B.failure_flags({**base, "inlier_corner_share": 0.5}) == ["corner cluster"]
    assert B.failure_flags({**base, "normal": [0.0, 0.6, 0.8]}) == ["planes swapped"]
    assert B.failure_flags({**base, "true_normal": [0.0, math.cos(0.05), math.sin(0.05)]}) == ["tilted wall"]
    assert B.failure_flags({**base, "n_mirror": 5, "crit": 0}) == ["critical step", "few mirror echoes"]
    assert B.quality_name(1) == "good" and B.quality_name(3) == "unreliable"


def test_open3d_anchor_is_deterministic_and_refits_the_wall():
    pytest.importorskip("open3d")
    rng = np.random.default_rng(0)
    wall = np.c_[
        rng.uniform(-0.5, 0.5, 300), np.full(300, 1.5) + 0.002 * rng.standard_normal(300), rng.uniform(-0.5, 0.5, 300)
    ]
    cluster = np.c_[rng.uniform(-0.1, 0.1, 150), rng.uniform(1.6, 1.9, 150), rng.uniform(0.4, 0.6, 150)]
    pts = np.vstack([wall, cluster])
    first = [B.open3d_anchor(pts) for _ in range(3)]
    assert all(np.array_equal(e.normal, first[0].normal) for e in first)
    assert first[0].offset == pytest.approx(1.5, abs=0.002) and abs(first[0].normal[1]) > 0.9999
    assert first[0].extra["n_inliers"] >= 290


def test_ls_plane_standard_errors_match_the_scatter():
    rng = np.random.default_rng(3)
    errs, ses = [], []
    for _ in range(200):
        pts = np.c_[rng.uniform(-0.3, 0.3, 60), 1.2 + 0.003 * rng.standard_normal(60), rng.uniform(-0.3, 0.3, 60)]
        n, h, se_n, se_h = B.ls_plane(pts)
        errs.append(h - 1.2 if n[1] > 0 else -h - 1.2)
        ses.append(se_h)
    z = np.asarray(errs) / np.asarray(ses)
    assert 0.8 < np.std(z) < 1.2


def test_edge_errors_direction_and_across_the_line():
    d = np.array([1.0, 0.0, 0.0])
    tilted = np.array([math.cos(0.02), math.sin(0.02), 0.0])
    ang, across = B.edge_errors(np.array([0.3, 1.57, 1.10]), -tilted, np.array([0.0, 1.57, 1.06]), d)
    assert ang == pytest.approx(math.degrees(0.02))  # sign-free
    assert across == pytest.approx(4.0)  # 4 cm across; the 30 cm along the line do not count


def test_speed_vs_open3d_times_the_default_fit_and_open3d_on_the_same_points():
    pytest.importorskip("open3d")
    v = B.speed_vs_open3d("paper", 0, repeats=2)
    assert v["repeats"] == 2 and len(v["points"]) == 2 and min(v["points"]) >= 8
    assert all(v[k] > 0 for k in ("default_ms", "open3d_ms", "open3d_1000_ms"))
    assert v["ratio"] == pytest.approx(v["default_ms"] / v["open3d_ms"])
    # Both Open3D runs fit the same wall: the early stop changes the time, not which plane it finds.
    pts = np.random.default_rng(0).uniform(-0.5, 0.5, (200, 3)) * [1, 0, 1] + [0, 1.5, 0]
    early, full = B.open3d_plane(pts, early_stop=True), B.open3d_plane(pts)
    assert early[1] == pytest.approx(1.5, abs=1e-9) and full[1] == pytest.approx(1.5, abs=1e-9)
    s = B.speed_summary([v, {**v, "default_ms": 3 * v["default_ms"]}])
    assert s["default_ms"] == pytest.approx(2 * v["default_ms"]) and s["open3d_ms"] == pytest.approx(v["open3d_ms"])
