"""``lelsonar bench estimators --families …``: every estimator on seeded scene families.

For each family of :mod:`lelsonar.sim.scenes` and each seed, the
scene is drawn (``draw_scene(family, seed)``), simulated
(``simulate_scan(cfg, seed)``), and reconstructed by each method through
:func:`lelsonar.reconstruct.estimate.pipeline.reconstruct` with the energy model a user
of that rig would have: the paper's six-shot calibration of the draw's rig
(``calibrated_energy_model``; cached per rig, as a real rig is calibrated once).

Per plane (a and b pooled):

* **angle**: between the fitted and true normals, °;
* **offset**: fitted minus true ``h``, cm (medians of |·|);
* **patch**: largest distance between the fitted and true planes over the
  observed patch (the true foot points of that plane's mirror echoes), cm;
* **oracle**: LS on the true mirror-echo points ``p_c + d·n_true`` (the
  project's existing definition, :mod:`lelsonar.tools.bench_estimators`);
* **failure**: patch error > 2 cm **and** > 3× the oracle's on that plane; a
  failure *the oracle avoids* is one where the oracle's own patch error is ≤ 2 cm;
* **missing**: the method returned no plane (not counted as a failure);
* **z**: error / reported standard error, for the normal (angle /
  ``PlaneFit.normal_stderr``, the RMS tilt: E[z²] = 1, median ≈ 0.83 when
  calibrated) and the offset (``(h − h_true)/offset_stderr``: median |z| ≈ 0.67);
* **good-but-failed**: failures whose plane claims ``quality`` GOOD (read with
  ``getattr``; "n/a" while no plane of that method carries an assessed quality);
* **time**: per plane (the solver's ``diagnostics.time_s``) and per scan
  (wall time of ``reconstruct``), measured inside the worker processes, and
  ``serial``: the best of repeated ``reconstruct`` calls on each family's first
  scene, run alone after the accuracy runs (the number for a time budget);
* **edge** (per scan): direction error (°) and the distance across the true
  edge line of the estimated edge's point (cm), with z-scores against
  ``EdgeLine.direction_stderr`` and ``point_stderr``.

The external anchor ``open3d`` is Open3D's ``segment_plane`` (seeded, 1 cm,
3 points, all 1000 iterations — its early stop is not deterministic across
threads) followed by an LS refit of its inliers, on the same
corrected subsets as the project's pipeline (split at the default method's
critical step); it needs the ``bench`` extra and is skipped with a note if
Open3D cannot be imported.  With it and ``--timing-repeats``, a speed table
holds the default method per plane against Open3D with its default early stop
(what a user of ``segment_plane`` gets) and with all 1000 iterations, on the
same points in the same process, medians of interleaved repeats
(:func:`speed_vs_open3d`).

Planes with fewer than 3 true mirror echoes have no oracle and no patch; they
are counted ("unobserved") and left out of the statistics.

``--json OUT`` writes strict JSON (NaN → null): the command, machine, scenes
(description, true critical step, echo counts, energy model), the summary and
one row per family, seed, method and plane (errors, standard errors,
z-scores, quality, oracle errors, critical step, corner-echo shares of the
subset and of the inliers, solver notes, failure flags).
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing
import os
import shlex
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lelsonar.tools.bench import machine

#: Name of the external anchor in the tables and the JSON.
ANCHOR = "open3d"
#: Failure thresholds: patch error above this (cm) …
FAIL_PATCH_CM = 2.0
#: … and above this multiple of the oracle's patch error.
FAIL_ORACLE_RATIO = 3.0
#: A critical step further than this from the true one (steps) is "wrong" in the failure patterns.
CRIT_TOLERANCE = 2
#: Failures whose inliers are at least this share of corner echoes are "corner cluster captured".
CORNER_SHARE = 0.3


# ---------------------------------------------------------------------------- pure helpers
def is_failure(patch_cm: float, oracle_patch_cm: float) -> bool:
    """Whether a plane failed: patch error > 2 cm and > 3× the oracle's (NaN → False).

    Parameters
    ----------
    patch_cm : float
        The method's patch error, cm.
    oracle_patch_cm : float
        The oracle's patch error on the same plane, cm.
    """
    if not (math.isfinite(patch_cm) and math.isfinite(oracle_patch_cm)):
        return False
    return patch_cm > FAIL_PATCH_CM and patch_cm > FAIL_ORACLE_RATIO * oracle_patch_cm


def z_score(error: float, stderr: float) -> float:
    """``error / stderr``; NaN if either is not finite or the standard error is not > 0."""
    if not (math.isfinite(error) and math.isfinite(stderr) and stderr > 0):
        return float("nan")
    return error / stderr


def plane_errors(
    normal: np.ndarray, offset: float, n_true: np.ndarray, h_true: float, patch: np.ndarray
) -> tuple[float, float, float]:
    """Angle (°), signed offset error (cm) and patch error (cm) of a plane ``n·x = h``.

    The patch error is the largest ``|n·p − h|`` over the true patch points
    ``patch`` (k, 3), m → cm; NaN for an empty patch.
    """
    ang = math.degrees(math.acos(float(np.clip(np.dot(normal, n_true), -1.0, 1.0))))
    off = 100.0 * (offset - h_true)
    pe = 100.0 * float(np.max(np.abs(patch @ normal - offset))) if len(patch) else float("nan")
    return ang, off, pe


def quality_name(quality: object) -> str | None:
    """``"good"``, ``"degraded"``, ``"unreliable"`` … from an enum, a string or a wire name; None if absent."""
    if quality is None or (isinstance(quality, str) and not quality):  # "": not assessed
        return None
    if isinstance(quality, (int, np.integer)) and not hasattr(quality, "name"):  # the wire's PlaneQuality number
        return {0: "unspecified", 1: "good", 2: "degraded", 3: "unreliable"}.get(int(quality), str(quality))
    value = getattr(quality, "value", quality)
    if not isinstance(value, str):
        value = getattr(quality, "name", str(quality))
    name = str(value).lower()
    for prefix in ("planequality.", "plane_quality_", "quality_"):
        if name.startswith(prefix):
            name = name[len(prefix) :]
    return name


def percentile(values: list[float] | np.ndarray, q: float) -> float:
    """``q``-th percentile of the finite values; NaN if there are none."""
    a = np.asarray(values, dtype=float)
    a = a[np.isfinite(a)]
    return float(np.percentile(a, q)) if a.size else float("nan")


def frac_above(z: np.ndarray, k: float) -> float:
    """Share of the finite values of ``z`` above ``k``; NaN if there are none."""
    z = np.asarray(z, dtype=float)
    z = z[np.isfinite(z)]
    return float(np.mean(z > k)) if z.size else float("nan")


def summarize(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Statistics of per-plane rows of one family and method (see the module docstring).

    Rows of unobserved planes (``observed`` False) only count in ``unobserved``.
    """
    obs = [r for r in rows if r["observed"]]
    fitted = [r for r in obs if r["ok"]]
    fails = [r for r in fitted if r["failure"]]
    zn = np.abs([r["z_angle"] for r in fitted], dtype=float)
    zh = np.abs([r["z_offset"] for r in fitted], dtype=float)
    ratios = [r["patch_cm"] / r["oracle_patch_cm"] for r in fitted if r["oracle_patch_cm"] > 0]
    quality = [r["quality"] for r in fails]
    has_quality = any(r["quality"] is not None for r in fitted)
    scans = {(r["family"], r["seed"]): r["time_scan_ms"] for r in rows}
    crit = [
        abs(r["crit"] - r["crit_true"]) <= CRIT_TOLERANCE
        for r in rows
        if r["label"] == "a" and r.get("crit") is not None and r["crit_true"] >= 0
    ]

    return {
        "planes": len(obs),
        "unobserved": len(rows) - len(obs),
        "missing": len(obs) - len(fitted),
        "angle_med": percentile([r["angle_deg"] for r in fitted], 50),
        "angle_p95": percentile([r["angle_deg"] for r in fitted], 95),
        "offset_med": percentile([abs(r["offset_cm"]) for r in fitted], 50),
        "offset_p95": percentile([abs(r["offset_cm"]) for r in fitted], 95),
        "patch_med": percentile([r["patch_cm"] for r in fitted], 50),
        "patch_p95": percentile([r["patch_cm"] for r in fitted], 95),
        "oracle_patch_med": percentile([r["oracle_patch_cm"] for r in obs], 50),
        "oracle_patch_p95": percentile([r["oracle_patch_cm"] for r in obs], 95),
        "ratio_med": percentile(ratios, 50),
        "ratio_p95": percentile(ratios, 95),
        "failures": len(fails),
        "failures_oracle_avoids": sum(not r["oracle_fails"] for r in fails),
        "z_angle_med": percentile(zn, 50),
        "z_angle_gt3": frac_above(zn, 3.0),
        "z_offset_med": percentile(zh, 50),
        "z_offset_gt3": frac_above(zh, 3.0),
        "failures_good": sum(q == "good" for q in quality) if has_quality else None,
        "failures_good_service": (sum(r.get("quality_service") == "good" for r in fails) if has_quality else None),
        "crit_ok": float(np.mean(crit)) if crit else float("nan"),
        **_edge_summary([r for r in rows if r["label"] == "a" and r.get("edge_ok")]),
        "ms_plane": percentile([r["time_plane_ms"] for r in fitted], 50),
        "ms_scan": percentile(list(scans.values()), 50),
        "ms_scan_p95": percentile(list(scans.values()), 95),
    }


def _edge_summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Edge statistics over one row per scan that has an edge."""
    zd = np.abs([r["z_edge_dir"] for r in rows], dtype=float)
    zp = np.abs([r["z_edge_point"] for r in rows], dtype=float)
    return {
        "edges": len(rows),
        "edge_dir_med": percentile([r["edge_dir_deg"] for r in rows], 50),
        "edge_dir_p95": percentile([r["edge_dir_deg"] for r in rows], 95),
        "edge_point_med": percentile([r["edge_point_cm"] for r in rows], 50),
        "edge_point_p95": percentile([r["edge_point_cm"] for r in rows], 95),
        "z_edge_dir_med": percentile(zd, 50),
        "z_edge_point_med": percentile(zp, 50),
        "z_edge_gt3": float(np.mean(np.concatenate([zd[np.isfinite(zd)], zp[np.isfinite(zp)]]) > 3))
        if np.isfinite(zd).any() or np.isfinite(zp).any()
        else float("nan"),
    }


#: Failure flags, in the order the patterns table shows them.
FLAGS = ("critical step", "corner cluster", "planes swapped", "tilted wall", "few mirror echoes", "unexplained")


def failure_flags(row: dict[str, Any]) -> list[str]:
    """Why a failing row may have failed (several can hold); ``["unexplained"]`` if none does.

    * ``critical step``: a method that fits the critical-step subsets split
      more than :data:`CRIT_TOLERANCE` steps from the true critical step;
    * ``corner cluster``: corner echoes are ≥ :data:`CORNER_SHARE` of the
      inliers, or the fitted offset is nearer the edge's range from the
      rotation axis than the true offset (the corner echoes all sit there);
    * ``planes swapped``: the fitted normal is nearer the other plane's;
    * ``tilted wall``: the true wall is > 1° off the paper's axis (y for a,
      z for b), which the paper's correction assumes;
    * ``few mirror echoes``: fewer than 12 true mirror echoes of the plane.
    """
    flags = []
    crit, true = row.get("crit"), row.get("crit_true")
    if (
        row.get("uses_split")
        and crit is not None
        and true is not None
        and true >= 0
        and abs(crit - true) > CRIT_TOLERANCE
    ):
        flags.append("critical step")
    share = row.get("inlier_corner_share")
    h, h_true, edge = row.get("offset"), row.get("true_offset"), row.get("edge_range")
    near_edge = h is not None and h_true is not None and edge is not None and abs(h - edge) < abs(h - h_true)
    if (share is not None and math.isfinite(share) and share >= CORNER_SHARE) or near_edge:
        flags.append("corner cluster")
    n, other = row.get("normal"), row.get("other_normal")
    if n is not None and other is not None and np.dot(n, other) > np.dot(n, row["true_normal"]):
        flags.append("planes swapped")
    axis = (0.0, 1.0, 0.0) if row.get("label") == "a" else (0.0, 0.0, 1.0)
    if math.degrees(math.acos(min(1.0, abs(float(np.dot(row["true_normal"], axis)))))) > 1.0:
        flags.append("tilted wall")
    if row.get("n_mirror", 0) < 12:
        flags.append("few mirror echoes")
    return flags or ["unexplained"]


def ls_plane(points: np.ndarray) -> tuple[np.ndarray, float, float, float]:
    """Least-squares plane ``θ·x = 1`` (the paper's eq. 15) with textbook standard errors.

    Kept here, independent of the estimators, so the oracle and the anchor do
    not move when the estimators do.

    Parameters
    ----------
    points : (k, 3) array
        m; at least 3, not collinear.

    Returns
    -------
    normal : (3,) array
        ``θ/|θ|``.
    offset : float
        ``h = 1/|θ|``, m.
    normal_stderr : float
        RMS tilt of the normal, rad: root of the trace of ``cov(n)``, with
        ``cov(θ) = σ²(JᵀJ)⁻¹`` from the metric residuals ``(θ·x − 1)/|θ|``
        and ``σ² = Σr²/(k − 3)``; inf with 3 points or fewer.
    offset_stderr : float
        m; inf likewise.
    """
    x = np.asarray(points, dtype=np.float64)
    theta, *_ = np.linalg.lstsq(x, np.ones(x.shape[0]), rcond=None)
    nt = float(np.linalg.norm(theta))
    n, h = theta / nt, 1.0 / nt
    if x.shape[0] <= 3:
        return n, h, float("inf"), float("inf")
    q = x @ theta - 1.0
    r = q / nt
    jac = x / nt - np.outer(q, theta) / nt**3
    jtj = jac.T @ jac
    if np.linalg.cond(jtj) > 1e15:
        return n, h, float("inf"), float("inf")
    cov = float(r @ r) / (x.shape[0] - 3) * np.linalg.inv(jtj)
    jn = (np.eye(3) - np.outer(n, n)) / nt
    var_n = float(np.trace(jn @ cov @ jn.T))
    var_h = float(h**4 * (n @ cov @ n))
    return n, h, math.sqrt(max(var_n, 0.0)), math.sqrt(max(var_h, 0.0))


# ---------------------------------------------------------------------------- one scan
def _open3d_plane(
    points: np.ndarray, *, early_stop: bool = False
) -> tuple[np.ndarray, float, float, float, int] | None:
    """Open3D RANSAC (seeded, 1 cm, 3 points, up to 1000 iterations), then LS on its inliers.

    ``early_stop=False`` runs all 1000 iterations (``probability=1``): Open3D's early stop depends on
    its threads' timing, so seeded runs differ with it (isl-org/Open3D#7270); without it the seeded
    result is the same every run.  ``early_stop=True`` is Open3D's default (``probability`` 0.99999999),
    what a user of ``segment_plane`` gets: the speed reference.

    Returns ``(normal, h, se_n, se_h, n_inliers)`` of :func:`ls_plane` on the inliers, or None if
    fewer than 8 points or 3 inliers.
    """
    import open3d as o3d

    if len(points) < 8:
        return None
    o3d.utility.random.seed(0)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.array(points, dtype=np.float64, order="C")))
    kw = {} if early_stop else {"probability": 1.0}
    _model, inliers = cloud.segment_plane(distance_threshold=0.01, ransac_n=3, num_iterations=1000, **kw)
    kept = points[np.asarray(inliers, dtype=np.intp)]
    if len(kept) < 3:
        return None
    return (*ls_plane(kept), len(kept))


def _open3d_anchor(points: np.ndarray) -> Estimate | None:
    """The deterministic anchor (:func:`_open3d_plane`, all 1000 iterations) as an Estimate; None if too few points."""
    t0 = time.perf_counter()
    fit = _open3d_plane(points)
    if fit is None:
        return None
    normal, h, se_n, se_h, n_in = fit
    return Estimate(normal, h, se_n, se_h, time.perf_counter() - t0, extra={"n_points": len(points), "n_inliers": n_in})


def speed_vs_open3d(family: str, seed: int, repeats: int, calibration: str = "paper") -> dict[str, Any]:
    """The default fit per plane against Open3D ``segment_plane`` + LS refit on the same points, ms.

    One scene of ``family``, in this process.  Each repeat runs, back to back, the default
    method's :func:`lelsonar.reconstruct.estimate.record.reconstruct_scan` (with the echoes' amplitudes, as
    the service runs it; both planes, so per plane is half the scan) and Open3D with its default
    early stop and with all 1000 iterations (the deterministic anchor of the accuracy rows) on
    the two corrected subsets at the default method's critical step (the anchor's points).
    Interleaving puts the same load of a shared host on all three; the medians over ``repeats``
    (after one warm-up) are reported, and their ratios.

    Returns
    -------
    dict with ``default_ms``, ``open3d_ms`` (early stop), ``open3d_1000_ms`` (per plane),
    ``ratio`` and ``ratio_1000`` (default over Open3D), ``repeats`` and ``points`` (a, b);
    the Open3D fields are NaN if a subset has too few points.
    """
    from lelsonar.reconstruct.estimate import fit as F
    from lelsonar.reconstruct.estimate.correct import AXIS_Y, AXIS_Z
    from lelsonar.reconstruct.estimate.pipeline import DEFAULT_METHOD
    from lelsonar.reconstruct.estimate.record import RecordOptions, ScanInput, reconstruct_scan
    from lelsonar.signal.energy import echo_amplitude, waveform_energy
    from lelsonar.sim.scenes import simulate_family_scene

    fs = simulate_family_scene(family, seed, wide_calibration=calibration == "wide")
    scan, model = fs.scan, fs.energy_model
    energy = waveform_energy(scan.waveforms, scan.sample_rate)
    amplitude = echo_amplitude(scan.waveforms, scan.sample_rate, scan.t0, scan.tof)
    given = ScanInput.of_scan(
        scan.gamma_measured, scan.distance, energy, scan.geometry, model, echo_amplitude=amplitude
    )
    record = RecordOptions(method=DEFAULT_METHOD)

    def default() -> Any:
        return reconstruct_scan(given, record)

    split = _split(scan, default().critical_step)
    subsets = (
        [
            F.plane_data(scan.geometry, scan.gamma_measured, scan.distance, split[label], label, axis).points
            for label, axis in (("a", AXIS_Y), ("b", AXIS_Z))
        ]
        if split
        else []
    )
    usable = len(subsets) == 2 and all(len(p) >= 8 for p in subsets)
    t_def, t_o3d, t_1000 = [], [], []
    for k in range(repeats + 1):
        t0 = time.perf_counter()
        default()
        t1 = time.perf_counter()
        if usable:
            for pts in subsets:
                _open3d_plane(pts, early_stop=True)
            t2 = time.perf_counter()
            for pts in subsets:
                _open3d_plane(pts)
            t3 = time.perf_counter()
        if k:  # the first round warms caches up
            t_def.append((t1 - t0) / 2)
            if usable:
                t_o3d.append((t2 - t1) / len(subsets))
                t_1000.append((t3 - t2) / len(subsets))
    med = {
        name: 1e3 * float(np.median(ts)) if ts else float("nan")
        for name, ts in (("default_ms", t_def), ("open3d_ms", t_o3d), ("open3d_1000_ms", t_1000))
    }
    return {
        **med,
        "ratio": med["default_ms"] / med["open3d_ms"],
        "ratio_1000": med["default_ms"] / med["open3d_1000_ms"],
        "repeats": repeats,
        "points": [len(p) for p in subsets],
    }


def _subset_sources(scan: Any, steps: np.ndarray, label: str) -> np.ndarray:
    """EchoSource of each point of ``plane_data(…, steps, …)``, in its order (the same validity mask)."""
    from lelsonar.reconstruct.estimate.correct import AXIS_Y, AXIS_Z, corrected_points

    d = scan.distance[steps]
    v = corrected_points(scan.geometry, scan.gamma_measured[steps], d, AXIS_Y if label == "a" else AXIS_Z)
    ok = np.isfinite(d) & (d > 0) & np.all(np.isfinite(v), axis=-1)
    return scan.truth.echo_source[steps][ok]


def _anchor_available() -> str | None:
    """None if Open3D imports, else why not."""
    try:
        import open3d  # noqa: F401
    except Exception as exc:  # noqa: BLE001 — ImportError, or OSError for a missing libusb
        return f"{type(exc).__name__}: {exc}"
    return None


_WARM: set[str] = set()


def _warm_up(methods: list[str]) -> None:
    """Run each method once per process on a paper scan, so first-call costs (imports, caches) stay out of the times."""
    from lelsonar.reconstruct.estimate.record import RecordOptions, ScanInput, reconstruct_scan
    from lelsonar.signal.energy import echo_amplitude, waveform_energy
    from lelsonar.sim import default_energy_model, preset, simulate_scan

    todo = [m for m in methods if m not in _WARM]
    if not todo:
        return
    scan = simulate_scan(preset("paper-test1"), seed=12345)
    energy = waveform_energy(scan.waveforms, scan.sample_rate)
    amplitude = echo_amplitude(scan.waveforms, scan.sample_rate, scan.t0, scan.tof)
    given = ScanInput.of_scan(
        scan.gamma_measured, scan.distance, energy, scan.geometry, default_energy_model(), echo_amplitude=amplitude
    )
    for m in todo:
        try:
            reconstruct_scan(given, RecordOptions(method=m))
        except Exception:  # noqa: BLE001 — the measured run reports it
            pass
        _WARM.add(m)


@dataclass(frozen=True, eq=False)
class SceneTruth:
    """What the bench compares a scan's planes with.

    Attributes
    ----------
    planes : dict
        Label → :class:`lelsonar.sim.TruePlane`.
    patch : dict
        Label → (k, 3) true foot points of that plane's mirror echoes, m.
    oracle : dict
        Label → (angle °, offset cm, patch cm) of the oracle, or None with
        fewer than 3 mirror echoes (the plane is then "unobserved").
    n_mirror : dict
        Label → number of true mirror echoes.
    edge_range : float
        Distance of the edge from the rotation axis at x = 0, m (where the
        corner echoes put a plane).
    edge_point, edge_direction : (3,) arrays
        The true edge line (a point on it, m; its unit direction).
    """

    planes: dict[str, Any]
    patch: dict[str, np.ndarray]
    oracle: dict[str, tuple[float, float, float] | None]
    n_mirror: dict[str, int]
    edge_range: float
    edge_point: np.ndarray
    edge_direction: np.ndarray


def scene_truth(scan: Any) -> SceneTruth:
    """Patches, oracle errors and mirror-echo counts of a :class:`SimulatedScan` (planes a and b)."""
    from lelsonar.sim import EchoSource

    truth = scan.truth
    planes = {p.label: p for p in truth.planes}
    pc = scan.geometry.capsule_positions(scan.gamma_measured)
    patch: dict[str, np.ndarray] = {}
    oracle: dict[str, tuple[float, float, float] | None] = {}
    n_mirror: dict[str, int] = {}
    for label, src in (("a", EchoSource.PLANE_A), ("b", EchoSource.PLANE_B)):
        tp = planes[label]
        m = (truth.echo_source == src) & np.isfinite(scan.distance)
        n_mirror[label] = int(m.sum())
        patch[label] = pc[m] + (tp.offset - pc[m] @ tp.normal)[:, None] * tp.normal
        oracle[label] = None
        if m.sum() >= 3:
            n_o, h_o, _, _ = ls_plane(pc[m] + scan.distance[m][:, None] * tp.normal)
            oracle[label] = plane_errors(n_o, h_o, tp.normal, tp.offset, patch[label])
    edge = scan.config.scene.edges[0]
    at_x0 = edge.point - edge.direction * (edge.point[0] / edge.direction[0])
    return SceneTruth(
        planes,
        patch,
        oracle,
        n_mirror,
        float(np.hypot(at_x0[1], at_x0[2])),
        at_x0,
        np.asarray(edge.direction, dtype=float),
    )


def edge_errors(
    point: np.ndarray, direction: np.ndarray, true_point: np.ndarray, true_direction: np.ndarray
) -> tuple[float, float]:
    """Errors of an estimated edge line: direction (°, sign-free) and position (cm).

    The position error is the distance of the estimated line's point from the
    true line, i.e. the error across the line where the estimate puts it.
    """
    c = abs(float(np.dot(direction, true_direction)))
    ang = math.degrees(math.acos(min(1.0, c)))
    rel = np.asarray(point, dtype=float) - true_point
    across = rel - np.dot(rel, true_direction) * true_direction
    return ang, 100.0 * float(np.linalg.norm(across))


@dataclass(frozen=True, eq=False)
class Estimate:
    """One method's plane, reduced to what the bench scores (a PlaneFit or the anchor's fit)."""

    normal: np.ndarray
    offset: float
    normal_stderr: float
    offset_stderr: float
    time_s: float
    quality: str | None = None
    reasons: tuple[str, ...] = ()
    extra: dict[str, Any] = field(default_factory=dict)


def _point_sources(scan: Any, data: Any) -> np.ndarray | None:
    """EchoSource of each point of a ``PlaneData`` (matched by step and range), or None if they do not match."""
    steps = np.asarray(getattr(data, "step", ()), dtype=np.intp)
    d = np.asarray(getattr(data, "distance", ()), dtype=np.float64)
    if steps.shape != d.shape or steps.ndim != 1 or (steps.size and steps.max() >= scan.n_steps):
        return None
    match = scan.distance[steps] == d[:, None]
    if not match.any(axis=1).all():
        return None
    return scan.truth.echo_source[steps, match.argmax(axis=1)]


def _from_plane_fit(res: Any, scan: Any, data: Any, steps: np.ndarray | None) -> Estimate:
    """An :class:`Estimate` of a ``PlaneFit`` (read with ``getattr`` where the contract is still moving).

    The true source of each point the plane was fitted on comes from the
    reconstruction's ``data_a``/``data_b`` when present, else from the
    critical-step subset ``steps`` rebuilt here; ``extra["fitted_on_split"]``
    says whether those points are that subset (so the critical step decided them).
    """
    from lelsonar.sim import EchoSource

    diag = getattr(res, "diagnostics", None)
    mask = np.asarray(getattr(res, "inlier_mask", np.zeros(0, dtype=bool)), dtype=bool)
    extra: dict[str, Any] = {
        "n_points": int(getattr(res, "n_points", mask.size)),
        "n_inliers": int(np.count_nonzero(mask)),
        "sigma_mm": 1e3 * float(getattr(res, "sigma", float("nan"))),
        "notes": [str(n) for n in getattr(diag, "notes", ())],
    }
    try:  # diagnostics only: the reconstruct internals may move
        split_src = _subset_sources(scan, steps, res.label) if steps is not None and len(steps) else None
    except Exception:  # noqa: BLE001
        split_src = None
    src = _point_sources(scan, data) if data is not None else None
    if src is not None and src.shape == mask.shape:
        on_split = (
            steps is not None
            and split_src is not None
            and split_src.shape == src.shape
            and np.array_equal(np.unique(np.asarray(data.step)), np.unique(_valid_steps(scan, steps)))
        )
    else:
        src, on_split = split_src, split_src is not None and split_src.shape == mask.shape
    extra["fitted_on_split"] = bool(on_split)
    if src is not None and src.shape == mask.shape:
        inl = src[mask]
        extra["subset_corner_share"] = float(np.mean(src == EchoSource.CORNER)) if src.size else 0.0
        extra["inlier_corner_share"] = float(np.mean(inl == EchoSource.CORNER)) if inl.size else float("nan")
    reasons = getattr(res, "quality_reasons", None) or getattr(res, "reasons", None) or ()
    return Estimate(
        normal=np.asarray(res.normal, dtype=float),
        offset=float(res.offset),
        normal_stderr=float(res.normal_stderr),
        offset_stderr=float(res.offset_stderr),
        time_s=float(getattr(diag, "time_s", float("nan"))),
        quality=quality_name(getattr(res, "quality", None)),
        reasons=tuple(str(r) for r in reasons),
        extra=extra,
    )


def _reconstruct_all(given: Any, methods: list[str], default: str) -> dict[str, Any]:
    """Each method's reconstruction of one scan, through the reconstruction of record.

    Returns method → ``(ScanReconstruction, seconds, quality_service)`` or the text of the exception a
    method raised (a crashing method is a result).  ``quality_service`` maps a label to the verdict
    ``reconstruct --compare`` shows: the default method is the method of record and the others are
    compared with it, so theirs are cross-checked; without the default, each method's own.
    """
    from lelsonar.reconstruct.estimate.record import RecordOptions, reconstruct_scan

    def one(method: str, compare: tuple[str, ...] = ()) -> dict[str, Any]:
        est = reconstruct_scan(given, RecordOptions(method=method, compare_methods=compare))
        return {
            m: (
                est.results[m],
                est.results[m].timings.total,
                {pl.label: quality_name(getattr(pl, "quality", None)) for pl in est.planes_of(m)},
            )
            for m in (method, *compare)
        }

    if default in methods:
        try:
            return one(default, tuple(m for m in methods if m != default))
        except Exception:  # noqa: BLE001 — one method crashed: run each alone to say which
            pass
    out: dict[str, Any] = {}
    for method in methods:
        try:
            out.update(one(method))
        except Exception as exc:  # noqa: BLE001 — a crashing method is a result, not the end of the bench
            out[method] = f"{type(exc).__name__}: {exc}"
    return out


def _edge_fields(edge: Any, truth: SceneTruth) -> dict[str, Any]:
    """The scan's edge errors and z-scores as row fields (NaN when the method has no edge)."""
    nan = float("nan")
    if not (hasattr(edge, "point") and hasattr(edge, "direction")):
        return {"edge_ok": False, "edge_dir_deg": nan, "edge_point_cm": nan, "z_edge_dir": nan, "z_edge_point": nan}
    ang, dist = edge_errors(np.asarray(edge.point), np.asarray(edge.direction), truth.edge_point, truth.edge_direction)
    se_d = float(getattr(edge, "direction_stderr", nan))
    se_p = float(getattr(edge, "point_stderr", nan))
    return {
        "edge_ok": True,
        "edge_dir_deg": ang,
        "edge_point_cm": dist,
        "z_edge_dir": z_score(math.radians(ang), se_d),
        "z_edge_point": z_score(dist / 100.0, se_p),
    }


def _valid_steps(scan: Any, steps: np.ndarray) -> np.ndarray:
    """The steps of ``steps`` with at least one valid range."""
    steps = np.asarray(steps, dtype=np.intp)
    d = scan.distance[steps]
    return steps[np.any(np.isfinite(d) & (d > 0), axis=1)]


def plane_row(
    base: dict[str, Any],
    truth: SceneTruth,
    method: str,
    label: str,
    est: Estimate | str,
    crit: int | None,
    time_scan_s: float,
    uses_split: bool,
) -> dict[str, Any]:
    """One JSON row: the plane's errors, standard errors, z-scores, quality and oracle (``est`` a str: no plane)."""
    tp = truth.planes[label]
    orc = truth.oracle[label]
    nan = float("nan")
    row = {
        **base,
        "method": method,
        "label": label,
        "crit": crit,
        "n_mirror": truth.n_mirror[label],
        "uses_split": uses_split,
        "observed": orc is not None,
        "true_normal": [float(v) for v in tp.normal],
        "true_offset": float(tp.offset),
        "other_normal": [float(v) for v in truth.planes["b" if label == "a" else "a"].normal],
        "time_scan_ms": 1e3 * time_scan_s,
        "oracle_angle_deg": orc[0] if orc else nan,
        "oracle_offset_cm": orc[1] if orc else nan,
        "oracle_patch_cm": orc[2] if orc else nan,
        "oracle_fails": bool(orc is not None and orc[2] > FAIL_PATCH_CM),
        "ok": not isinstance(est, str),
    }
    if isinstance(est, str):
        row.update(
            angle_deg=nan,
            offset_cm=nan,
            patch_cm=nan,
            failure=False,
            z_angle=nan,
            z_offset=nan,
            quality=None,
            quality_reasons=[],
            normal_stderr_deg=nan,
            offset_stderr_cm=nan,
            time_plane_ms=nan,
            why=est,
            flags=[],
        )
        return row
    ang, off, pe = plane_errors(est.normal, est.offset, tp.normal, tp.offset, truth.patch[label])
    se_n, se_h = est.normal_stderr, est.offset_stderr
    row.update(est.extra)
    row.update(
        angle_deg=ang,
        offset_cm=off,
        patch_cm=pe,
        failure=is_failure(pe, row["oracle_patch_cm"]),
        normal_stderr_deg=math.degrees(se_n) if math.isfinite(se_n) else nan,
        offset_stderr_cm=100.0 * se_h if math.isfinite(se_h) else nan,
        z_angle=z_score(math.radians(ang), se_n),
        z_offset=z_score(off / 100.0, se_h),
        quality=est.quality,
        quality_reasons=list(est.reasons),
        time_plane_ms=1e3 * est.time_s,
        normal=[float(v) for v in est.normal],
        offset=float(est.offset),
    )
    row["flags"] = failure_flags(row) if row["failure"] else []
    return row


def family_scan(
    family: str, seed: int, methods: list[str], anchor: bool, dump_dir: str | None, calibration: str = "paper"
) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """Draw, simulate and reconstruct one scene; the scene's summary and one row per method and plane.

    ``calibration``: ``"paper"`` (six shots, 0.9–1.8 m, as ``lelsonar calibrate``) or ``"wide"``
    (0.6–2.7 m, the families' span) — see :func:`lelsonar.sim.scenes.calibrated_energy_model`.
    """
    _warm_up(methods)
    from lelsonar.reconstruct.estimate.pipeline import DEFAULT_METHOD
    from lelsonar.reconstruct.estimate.record import ScanInput
    from lelsonar.signal.energy import echo_amplitude, waveform_energy
    from lelsonar.sim import EchoSource
    from lelsonar.sim.scenes import simulate_family_scene

    fs = simulate_family_scene(family, seed, wide_calibration=calibration == "wide")
    draw, scan, model = fs.draw, fs.scan, fs.energy_model
    cfg = draw.config
    energy = waveform_energy(scan.waveforms, scan.sample_rate)
    # The first echoes' own amplitudes, as the reconstruction service computes them from each Sample.
    amplitude = echo_amplitude(scan.waveforms, scan.sample_rate, scan.t0, scan.tof)
    truth = scene_truth(scan)
    counts = np.bincount(scan.truth.echo_source.ravel().astype(int), minlength=len(EchoSource))
    scene = {
        "family": family,
        "seed": seed,
        "description": draw.description,
        "crit_true": int(scan.truth.critical_step),
        "n_steps": int(scan.n_steps),
        "window_samples": int(cfg.window_samples),
        "edge_range": truth.edge_range,
        "echoes": {s.name.lower(): int(counts[s]) for s in EchoSource},
        "energy_model": [model.phi0, model.phi1, model.phi2, model.d_min, model.d_max],
    }
    base = {"family": family, "seed": seed, "crit_true": scene["crit_true"], "edge_range": truth.edge_range}
    rows: list[dict[str, Any]] = []

    crits: dict[str, int | None] = {}
    given = ScanInput.of_scan(
        scan.gamma_measured, scan.distance, energy, scan.geometry, model, echo_amplitude=amplitude
    )
    runs = _reconstruct_all(given, methods, DEFAULT_METHOD)
    for method in methods:
        run = runs[method]
        if isinstance(run, str):
            rows += [
                {**plane_row(base, truth, method, label, run, None, 0.0, False), "quality_service": None}
                for label in ("a", "b")
            ]
            continue
        rec, dt, quality_service = run
        crits[method] = rec.critical_step
        split = _split(scan, rec.critical_step)
        edge = _edge_fields(rec.edge, truth)
        for label, res in (("a", rec.plane_a), ("b", rec.plane_b)):
            fitted = hasattr(res, "normal") and hasattr(res, "offset")
            data = getattr(rec, f"data_{label}", None)
            est = _from_plane_fit(res, scan, data, split.get(label)) if fitted else str(res)
            uses_split = isinstance(est, Estimate) and est.extra["fitted_on_split"]
            row = plane_row(base, truth, method, label, est, rec.critical_step, dt, uses_split)
            rows.append({**row, **edge, "quality_service": quality_service.get(label)})

    default_crit = crits.get(DEFAULT_METHOD, next(iter(crits.values()), None))
    split = _split(scan, default_crit) if anchor else {}
    if split:
        from lelsonar.reconstruct.estimate import fit as F
        from lelsonar.reconstruct.estimate.correct import AXIS_Y, AXIS_Z

        ests: dict[str, Estimate | str] = {}
        for label, axis in (("a", AXIS_Y), ("b", AXIS_Z)):
            data = F.plane_data(scan.geometry, scan.gamma_measured, scan.distance, split[label], label, axis)
            ests[label] = _open3d_anchor(data.points) or "too few points"
        t_scan = sum(e.time_s for e in ests.values() if isinstance(e, Estimate))
        rows += [plane_row(base, truth, ANCHOR, label, e, default_crit, t_scan, True) for label, e in ests.items()]

    if dump_dir and any(r["failure"] for r in rows):
        from lelsonar.acquire.simulated import record_scan

        path = Path(dump_dir) / f"{family}-{seed}.mcap"
        failing = sorted({f"{r['method']}:{r['label']}" for r in rows if r["failure"]})
        record_scan(
            scan,
            path,
            model,
            scan_id=seed + 1,
            metadata={
                "family": family,
                "seed": str(seed),
                "description": draw.description,
                "failures": ",".join(failing),
            },
        )
        scene["dump"] = str(path)
    return scene, rows


def _split(scan: Any, crit: int | None) -> dict[str, np.ndarray]:
    """The pipeline's subsets at ``crit`` ({} if the split cannot be made or imported)."""
    try:
        from lelsonar.reconstruct.estimate.split import split_subsets

        if crit is None:
            return {}
        s = split_subsets(scan.gamma_measured, crit)
    except Exception:  # noqa: BLE001 — diagnostics and the anchor only; the estimators may move
        return {}
    return {"a": np.asarray(s.steps_a), "b": np.asarray(s.steps_b)}


def serial_scan_times(
    family: str, seed: int, methods: list[str], repeats: int, calibration: str = "paper"
) -> dict[str, float]:
    """Best wall time of ``reconstruct_scan`` per method on one scene of ``family``, ms, run serially.

    The worker times of the accuracy runs share the cores with each other (and
    with anything else on the host); these are the numbers to hold against a
    time budget.  Each method runs once to warm up, then ``repeats`` times
    (fewer once a method has taken 1 s); the minimum is the least disturbed by
    other load on a shared host.
    """
    from lelsonar.reconstruct.estimate.record import RecordOptions, ScanInput, reconstruct_scan
    from lelsonar.signal.energy import waveform_energy
    from lelsonar.sim.scenes import simulate_family_scene

    fs = simulate_family_scene(family, seed, wide_calibration=calibration == "wide")
    scan, model = fs.scan, fs.energy_model
    energy = waveform_energy(scan.waveforms, scan.sample_rate)
    given = ScanInput.of_scan(scan.gamma_measured, scan.distance, energy, scan.geometry, model)
    out = {}
    for method in methods:
        ts: list[float] = []
        for _ in range(repeats + 1):
            t0 = time.perf_counter()
            try:
                reconstruct_scan(given, RecordOptions(method=method))
            except Exception:  # noqa: BLE001 — reported by the accuracy run
                break
            ts.append(time.perf_counter() - t0)
            if len(ts) >= 3 and sum(ts) > 1.0:  # a slow method (paper) gets two measured runs
                break
        out[method] = 1e3 * float(np.min(ts[1:])) if len(ts) > 1 else float("nan")
    return out


def speed_summary(per_family: list[dict[str, Any]]) -> dict[str, Any]:
    """Medians over families of :func:`speed_vs_open3d`'s times, and the ratios of those medians."""
    med = {k: percentile([v[k] for v in per_family], 50) for k in ("default_ms", "open3d_ms", "open3d_1000_ms")}
    return {
        **med,
        "ratio": med["default_ms"] / med["open3d_ms"],
        "ratio_1000": med["default_ms"] / med["open3d_1000_ms"],
        "repeats": per_family[0]["repeats"] if per_family else 0,
        "points": [],
    }


# ---------------------------------------------------------------------------- run
def default_methods(with_paper: bool) -> list[str]:
    """The project's default method, ``fcm-ransac``, ``lel-refit-ls`` (and ``paper``), as registered."""
    from lelsonar.reconstruct.estimate.pipeline import DEFAULT_METHOD, METHODS

    out = []
    for m in (DEFAULT_METHOD, "fcm-ransac", "lel-refit-ls", *(("paper",) if with_paper else ())):
        if m in METHODS and m not in out:
            out.append(m)
    return out


def _fmt(x: float | None, digits: int = 2) -> str:
    """``digits`` decimals below 10, fewer above (3 significant figures at most)."""
    if x is None:
        return "n/a"
    if not math.isfinite(x):
        return "—"
    return f"{x:.{digits if abs(x) < 10 else 1 if abs(x) < 100 else 0}f}"


def _good(s: dict[str, Any]) -> str:
    """Failures claiming good: the method's own verdict, and in brackets after the service's cross-check if fewer."""
    own, svc = s["failures_good"], s.get("failures_good_service")
    if own is None:
        return "n/a"
    return f"{own}" if svc is None or svc == own else f"{own} ({svc})"


def _pct(x: float) -> str:
    return "—" if not math.isfinite(x) else f"{100 * x:.0f}%"


def _pair(a: float, b: float, digits: int = 2) -> str:
    return f"{_fmt(a, digits)}/{_fmt(b, digits)}"


def _scan_ms(s: dict[str, Any]) -> float:
    """The serial scan time if measured, else the workers' median, ms."""
    t = s.get("ms_scan_serial", float("nan"))
    return t if math.isfinite(t) else s["ms_scan"]


def _targets(
    summary: dict[tuple[str, str], dict[str, Any]], families: tuple[str, ...], default: str
) -> list[tuple[str, dict[str, bool]]]:
    """The default method's targets, checked per family."""
    out = []
    for fam in families:
        s = summary.get((fam, default))
        f = summary.get((fam, "fcm-ransac"))
        if s is None:
            continue
        out.append(
            (
                fam,
                {
                    "median ≤ 1.2× oracle": s["ratio_med"] <= 1.2,
                    "p95 ≤ 2× oracle": s["patch_p95"] <= 2.0 * s["oracle_patch_p95"],
                    "no failure the oracle avoids": s["failures_oracle_avoids"] == 0,
                    "failures ≤ fcm-ransac": f is None or s["failures"] <= f["failures"],
                    "z calibrated": all(0.5 <= s[k] <= 1.0 for k in ("z_angle_med", "z_offset_med"))
                    and all(s[k] <= 0.05 for k in ("z_angle_gt3", "z_offset_gt3")),
                    "scan ≤ 10 ms": _scan_ms(s) <= 10.0,
                },
            )
        )
    return out


def run_families(args: argparse.Namespace) -> int:
    """Run the family benchmark, print the tables; 0 if the default method meets its targets."""
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )
    from rich.table import Table

    from lelsonar.reconstruct.estimate.pipeline import DEFAULT_METHOD
    from lelsonar.sim.scenes import parse_families

    families = parse_families(args.families)
    methods = list(args.methods) if args.methods else default_methods(args.with_paper)
    console = Console(width=max(Console().width, 200))
    command = (
        shlex.join(["lelsonar", *sys.argv[1:]])
        if sys.argv and sys.argv[0].endswith("lelsonar")
        else shlex.join(sys.argv)
    )
    anchor_note = None if args.no_anchor else _anchor_available()
    anchor = not args.no_anchor and anchor_note is None
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    jobs = [(f, s) for f in families for s in seeds]
    if args.dump_failures:
        Path(args.dump_failures).mkdir(parents=True, exist_ok=True)
    console.print(f"[bold]{command}[/]")
    console.print(
        f"{machine()}, numpy {np.__version__}; {len(seeds)} seeds × {len(families)} families, "
        f"methods {', '.join(methods)}"
        + (f", anchor {ANCHOR}" if anchor else "")
        + f"; {args.jobs} workers; energy model: {args.calibration} calibration of each rig"
    )
    if anchor_note is not None:
        console.print(
            f"[yellow]note: the Open3D anchor is skipped ({anchor_note}); install the bench extra "
            "(pip install -e '.[bench]') and libusb-1.0-0[/]"
        )
    t_start = time.perf_counter()
    scenes: list[dict[str, Any]] = []
    rows: list[dict[str, Any]] = []
    progress = Progress(
        TextColumn("scenes"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TextColumn("ETA"),
        TimeRemainingColumn(),
        console=console,
        transient=True,
    )
    with progress:
        task = progress.add_task("scenes", total=len(jobs))
        if args.jobs > 1:
            # spawn, not fork: the parent has imported Open3D (OpenMP), which a forked child may deadlock on.
            with ProcessPoolExecutor(args.jobs, mp_context=multiprocessing.get_context("spawn")) as ex:
                futures = [
                    ex.submit(family_scan, fam, seed, methods, anchor, args.dump_failures, args.calibration)
                    for fam, seed in jobs
                ]
                for fut in as_completed(futures):
                    scene, scene_rows = fut.result()
                    scenes.append(scene)
                    rows.extend(scene_rows)
                    progress.advance(task)
        else:
            for fam, seed in jobs:
                scene, scene_rows = family_scan(fam, seed, methods, anchor, args.dump_failures, args.calibration)
                scenes.append(scene)
                rows.extend(scene_rows)
                progress.advance(task)
    wall = time.perf_counter() - t_start
    order = {f: i for i, f in enumerate(families)}
    scenes.sort(key=lambda s: (order[s["family"]], s["seed"]))
    rows.sort(key=lambda r: (order[r["family"]], r["seed"], r["method"], r["label"]))
    all_methods = [*methods, *((ANCHOR,) if anchor else ())]

    serial: dict[str, dict[str, float]] = {}
    if args.timing_repeats > 0:
        with console.status("serial timings …"):
            for fam in families:
                serial[fam] = serial_scan_times(
                    fam, args.first_seed, methods, min(args.timing_repeats, 20), args.calibration
                )
    speed: dict[str, dict[str, Any]] = {}
    if anchor and args.timing_repeats > 0:
        with console.status("default fit vs Open3D …"):
            for fam in families:
                speed[fam] = speed_vs_open3d(fam, args.first_seed, min(args.timing_repeats, 20), args.calibration)
        speed["all"] = speed_summary(list(speed.values()))
    summary: dict[tuple[str, str], dict[str, Any]] = {}
    for fam in (*families, "all"):
        for method in all_methods:
            mr = [r for r in rows if r["method"] == method and (fam == "all" or r["family"] == fam)]
            if mr:
                summary[(fam, method)] = summarize(mr)
                times = [
                    serial[f].get(method, float("nan")) for f in (families if fam == "all" else (fam,)) if f in serial
                ]
                summary[(fam, method)]["ms_scan_serial"] = (
                    percentile(times, 50)
                    if fam != "all"
                    else max((t for t in times if math.isfinite(t)), default=float("nan"))
                )

    table = Table(
        title=f"Plane errors per scene family and method (planes a and b pooled; median / p95; "
        f"{len(seeds)} seeds, {wall:.0f} s)",
        title_justify="left",
    )
    cols = (
        "family",
        "method",
        "planes",
        "angle °",
        "|Δh| cm",
        "patch cm",
        "oracle cm",
        "ratio",
        "fail",
        "¬orc",
        "miss",
        "|z_n|, >3",
        "|z_h|, >3",
        "f&good",
        "crit±2",
        "ms/pl",
        "ms/scan",
        "serial",
    )
    for c in cols:
        table.add_column(c, justify="left" if c in ("family", "method") else "right")
    for fam in (*families, "all"):
        for method in all_methods:
            s = summary.get((fam, method))
            if s is None:
                continue
            style = "bold" if method == DEFAULT_METHOD else None
            table.add_row(
                fam,
                method,
                f"{s['planes']}" + (f" (+{s['unobserved']})" if s["unobserved"] else ""),
                _pair(s["angle_med"], s["angle_p95"]),
                _pair(s["offset_med"], s["offset_p95"]),
                _pair(s["patch_med"], s["patch_p95"]),
                _pair(s["oracle_patch_med"], s["oracle_patch_p95"]),
                _fmt(s["ratio_med"]),
                str(s["failures"]),
                str(s["failures_oracle_avoids"]),
                str(s["missing"]),
                f"{_fmt(s['z_angle_med'])}, {_pct(s['z_angle_gt3'])}",
                f"{_fmt(s['z_offset_med'])}, {_pct(s['z_offset_gt3'])}",
                _good(s),
                _pct(s["crit_ok"]),
                _fmt(s["ms_plane"]),
                _fmt(s["ms_scan"], 1),
                _fmt(s["ms_scan_serial"], 1),
                style=style,
            )
        table.add_section()
    console.print(table)
    console.print(
        "planes: observed planes (+ planes with < 3 true mirror echoes, left out); ratio: median of the "
        "per-plane patch/oracle ratios; fail: patch > 2 cm and > 3× the oracle's; ¬orc: failures where "
        "the oracle's patch ≤ 2 cm; miss: no plane returned; |z|: median |error / reported standard "
        "error| and the share > 3 (normal angle, offset); f&good: failures whose own quality says good (in brackets: "
        "after reconstruct --compare's cross-check against the method of record); crit±2: scans "
        "whose critical step is within 2 steps of the true one (only meaningful for methods that split there); "
        "times: median per plane (solver) and per scan (reconstruct) in the workers; serial: "
        "reconstruct of the family's first scene run alone (best of repeats; 'all': the slowest family)."
    )

    patterns: dict[str, dict[str, int]] = {}
    for r in rows:
        if r.get("failure"):
            for flag in r["flags"]:
                patterns.setdefault(r["method"], {}).setdefault(flag, 0)
                patterns[r["method"]][flag] += 1
    if patterns:
        kinds = FLAGS
        pt = Table(
            title="Failure patterns (a failure can have several): critical step > 2 steps off (split "
            "methods); corner cluster (≥ 30 % corner inliers, or the plane at the edge's range); "
            "planes swapped; tilted wall (> 1° off the paper's axis); < 12 mirror echoes",
            title_justify="left",
        )
        pt.add_column("method")
        pt.add_column("failures", justify="right")
        for k in kinds:
            pt.add_column(k, justify="right")
        pt.add_column("worst families", justify="left")
        for method in all_methods:
            p = patterns.get(method)
            if not p:
                continue
            by_fam: dict[str, int] = {}
            for r in rows:
                if r["method"] == method and r.get("failure"):
                    by_fam[r["family"]] = by_fam.get(r["family"], 0) + 1
            worst = ", ".join(f"{f} {n}" for f, n in sorted(by_fam.items(), key=lambda kv: -kv[1])[:4])
            pt.add_row(method, str(sum(by_fam.values())), *(str(p.get(k, 0)) for k in kinds), worst)
        console.print(pt)

    et = Table(
        title="Corner edge per family and method (median / p95; |z| = error / reported standard error)",
        title_justify="left",
    )
    for c in ("family", "method", "scans", "direction °", "across cm", "|z| dir", "|z| across", "|z|>3"):
        et.add_column(c, justify="left" if c in ("family", "method") else "right")
    for fam in (*families, "all"):
        for method in methods:
            s = summary.get((fam, method))
            if s is None or not s["edges"]:
                continue
            et.add_row(
                fam,
                method,
                str(s["edges"]),
                _pair(s["edge_dir_med"], s["edge_dir_p95"]),
                _pair(s["edge_point_med"], s["edge_point_p95"]),
                _fmt(s["z_edge_dir_med"]),
                _fmt(s["z_edge_point_med"]),
                _pct(s["z_edge_gt3"]),
                style="bold" if method == DEFAULT_METHOD else None,
            )
        et.add_section()
    console.print(et)

    if speed:
        st = Table(
            title=f"Default fit {DEFAULT_METHOD!r} per plane vs Open3D segment_plane + LS refit on the same "
            f"points (serial, medians of {min(args.timing_repeats, 20)} interleaved repeats, first scene "
            "of each family)",
            title_justify="left",
        )
        for c in ("family", "points a/b", f"{DEFAULT_METHOD} ms", "open3d ms", "ratio", "open3d 1000 ms", "ratio 1000"):
            st.add_column(c, justify="left" if c == "family" else "right")
        for fam, v in speed.items():
            st.add_row(
                fam,
                "/".join(str(n) for n in v["points"]) if v.get("points") else "",
                _fmt(v["default_ms"]),
                _fmt(v["open3d_ms"]),
                _fmt(v["ratio"]),
                _fmt(v["open3d_1000_ms"]),
                _fmt(v["ratio_1000"]),
            )
        console.print(st)
        console.print(
            "open3d: segment_plane with its default early stop (what a user of it gets); open3d 1000: all "
            "1000 iterations (the deterministic anchor of the accuracy rows); the default fit's time is its "
            "reconstruct (both planes, with the echo amplitudes) over 2; 'all': medians over the families."
        )
    targets = _targets(summary, families, DEFAULT_METHOD)
    misses = [f"{fam}: {k}" for fam, checks in targets for k, ok in checks.items() if not ok]
    if targets:
        tt = Table(title=f"Targets for the default method {DEFAULT_METHOD!r}", title_justify="left")
        tt.add_column("family")
        names = list(targets[0][1])
        for n in names:
            tt.add_column(n, justify="center")
        for fam, checks in targets:
            tt.add_row(fam, *("[green]✓[/]" if checks[n] else "[red]✗[/]" for n in names))
        console.print(tt)
        console.print(
            "median: median of the per-plane patch/oracle ratios; p95: the p95 of the patch error over "
            "the oracle's p95; z calibrated: median |z| in [0.5, 1] and ≤ 5 % beyond 3, normal and offset; "
            "scan: the serial time if measured."
        )
    dumps = [s["dump"] for s in scenes if "dump" in s]
    if dumps:
        console.print(
            f"dumped {len(dumps)} failing scenes to {args.dump_failures}; reproduce one with: "
            f"lelsonar reconstruct --source {dumps[0]} --json --compare {','.join(methods)}"
        )
    if getattr(args, "markdown", None):
        out = Path(args.markdown)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(
            markdown_table(summary, families, all_methods, DEFAULT_METHOD, command, machine()), encoding="utf-8"
        )
        console.print(f"wrote {out} (Markdown)")
    if args.json:
        out = Path(args.json)
        out.parent.mkdir(parents=True, exist_ok=True)
        with open(out, "w", encoding="utf-8") as fh:
            json.dump(
                _finite(
                    {
                        "command": command,
                        "machine": machine(),
                        "families": list(families),
                        "seeds": [seeds.start, seeds.stop],
                        "methods": all_methods,
                        "default_method": DEFAULT_METHOD,
                        "wall_s": wall,
                        "jobs": args.jobs,
                        "serial_ms": serial,
                        "speed_vs_open3d": speed,
                        "calibration": args.calibration,
                        "scenes": scenes,
                        "summary": [{"family": k[0], "method": k[1], **v} for k, v in summary.items()],
                        "targets": [{"family": fam, **checks} for fam, checks in targets],
                        "rows": rows,
                    }
                ),
                fh,
                default=json_default,
                allow_nan=False,
            )
        console.print(f"wrote {out} ({len(rows)} plane rows)")
    console.print(
        f"default method {DEFAULT_METHOD!r}: "
        + ("[green]meets its targets on every family[/]" if not misses else f"[red]misses {len(misses)} targets[/]")
    )
    return 0 if not misses else 1


def markdown_table(
    summary: dict[tuple[str, str], dict[str, Any]],
    families: tuple[str, ...],
    methods: list[str],
    default: str,
    command: str,
    machine_line: str,
) -> str:
    """The summary as a Markdown table with the command and machine it came from."""
    lines = [
        f"`{command}` ({machine_line}). Medians / p95 over planes a and b; failure: patch > 2 cm and "
        "> 3× the oracle's (LS on the true mirror echoes); |z|: median |error / reported standard error| "
        "and the share > 3.",
        "",
        r"| family | method | angle ° | \|Δh\| cm | patch cm | patch / oracle | failures (oracle avoids) "
        r"| no plane | \|z\| normal | \|z\| offset | failures claiming good (after cross-check) | ms / scan |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for fam in (*families, "all"):
        for method in methods:
            s = summary.get((fam, method))
            if s is None:
                continue
            name = f"**`{method}`**" if method == default else f"`{method}`"
            lines.append(
                f"| {fam} | {name} | {_pair(s['angle_med'], s['angle_p95'])} | "
                f"{_pair(s['offset_med'], s['offset_p95'])} | {_pair(s['patch_med'], s['patch_p95'])} | "
                f"{_fmt(s['ratio_med'])} | {s['failures']} ({s['failures_oracle_avoids']}) | {s['missing']} | "
                f"{_fmt(s['z_angle_med'])}, {_pct(s['z_angle_gt3'])} | {_fmt(s['z_offset_med'])}, "
                f"{_pct(s['z_offset_gt3'])} | {_good(s)} | "
                f"{_fmt(_scan_ms(s), 1)} |"
            )
    return "\n".join(lines) + "\n"


def _finite(o: Any) -> Any:
    """``o`` with every NaN or infinity replaced by None (strict JSON: jq and browsers read it)."""
    if isinstance(o, float):
        return o if math.isfinite(o) else None
    if isinstance(o, np.floating):
        return float(o) if np.isfinite(o) else None
    if isinstance(o, dict):
        return {k: _finite(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_finite(v) for v in o]
    return o


def json_default(o: Any) -> Any:
    """NumPy scalars and arrays as JSON values (json.dumps default=); anything else as its str."""
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def add_family_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``--families`` mode's own flags (``--seeds``, ``--methods``, ``--jobs``, ``--json`` are shared)."""
    g = parser.add_argument_group("scene families")
    g.add_argument(
        "--families",
        nargs="+",
        metavar="NAME",
        help="run on seeded scene families instead of presets: 'all' or names from "
        "paper, distance, tilted, partial, steps, beam, corner, noise, mixed",
    )
    g.add_argument("--with-paper", action="store_true", help="also run the slow 'paper' method (Nelder-Mead)")
    g.add_argument("--no-anchor", action="store_true", help="skip the Open3D segment_plane anchor")
    g.add_argument(
        "--calibration",
        choices=("paper", "wide"),
        default="paper",
        help="energy model of each rig: the paper's six shots at 0.9-1.8 m, as `lelsonar calibrate` "
        "(default), or eight at 0.6-2.7 m covering the families' walls",
    )
    g.add_argument("--markdown", metavar="OUT.md", help="also write the summary as a Markdown table")
    g.add_argument(
        "--dump-failures",
        metavar="DIR",
        help="write every scene with a failing plane as DIR/<family>-<seed>.mcap "
        "(replay with lelsonar reconstruct --source FILE --json)",
    )


if __name__ == "__main__":  # pragma: no cover
    p = argparse.ArgumentParser(prog="bench_families")
    p.add_argument("--seeds", type=int, default=10)
    p.add_argument("--first-seed", type=int, default=0)
    p.add_argument("--methods", nargs="+")
    p.add_argument("--jobs", type=int, default=os.cpu_count() or 1)
    p.add_argument("--json")
    add_family_arguments(p)
    raise SystemExit(run_families(p.parse_args()))
