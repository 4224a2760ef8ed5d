"""One scene of the scene-family bench: draw, simulate, reconstruct with every method, score against the truth
(the speed of the methods: :mod:`lelsonar.tools.family_speed`).

Definitions: :mod:`lelsonar.tools.bench_families`.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lelsonar.tools.family_metrics import (
    ANCHOR,
    FAIL_PATCH_CM,
    failure_flags,
    is_failure,
    ls_plane,
    plane_errors,
    quality_name,
    z_score,
)


def open3d_plane(points: np.ndarray, *, early_stop: bool = False) -> tuple[np.ndarray, float, float, float, int] | None:
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


def open3d_anchor(points: np.ndarray) -> Estimate | None:
    """The deterministic anchor (:func:`open3d_plane`, all 1000 iterations) as an Estimate; None if too few points."""
    t0 = time.perf_counter()
    fit = open3d_plane(points)
    if fit is None:
        return None
    normal, h, se_n, se_h, n_in = fit
    return Estimate(normal, h, se_n, se_h, time.perf_counter() - t0, extra={"n_points": len(points), "n_inliers": n_in})


def _subset_sources(scan: Any, steps: np.ndarray, label: str) -> np.ndarray:
    """EchoSource of each point of ``plane_data(…, steps, …)``, in its order (the same validity mask)."""
    from lelsonar.reconstruct.estimate.correct import AXIS_Y, AXIS_Z, corrected_points

    d = scan.distance[steps]
    v = corrected_points(scan.geometry, scan.gamma_measured[steps], d, AXIS_Y if label == "a" else AXIS_Z)
    ok = np.isfinite(d) & (d > 0) & np.all(np.isfinite(v), axis=-1)
    return scan.truth.echo_source[steps][ok]


def anchor_available() -> str | None:
    """None if Open3D imports, else why not."""
    try:
        import open3d  # noqa: F401
    except Exception as exc:  # noqa: BLE001 — ImportError, or OSError for a missing libusb
        return f"{type(exc).__name__}: {exc}"
    return None


_WARM: set[str] = set()


def _warm_up(methods: list[str]) -> None:
    """Run each method once per process on a paper scan, so first-call costs (imports, caches) stay out of the times."""
    from lelsonar.reconstruct.estimate.record import RecordOptions, reconstruct_scan
    from lelsonar.reconstruct.estimate.waveform_input import scan_input_of_waveforms
    from lelsonar.sim import default_energy_model, preset, simulate_scan

    todo = [m for m in methods if m not in _WARM]
    if not todo:
        return
    given = scan_input_of_waveforms(simulate_scan(preset("paper-test1"), seed=12345), default_energy_model())
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
    from lelsonar.reconstruct.estimate.waveform_input import scan_input_of_waveforms
    from lelsonar.sim import EchoSource
    from lelsonar.sim.scenes import simulate_family_scene

    fs = simulate_family_scene(family, seed, wide_calibration=calibration == "wide")
    draw, scan, model = fs.draw, fs.scan, fs.energy_model
    cfg = draw.config
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
    runs = _reconstruct_all(scan_input_of_waveforms(scan, model), methods, DEFAULT_METHOD)
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
        split = critical_split(scan, rec.critical_step)
        edge = _edge_fields(rec.edge, truth)
        for label, res in (("a", rec.plane_a), ("b", rec.plane_b)):
            fitted = hasattr(res, "normal") and hasattr(res, "offset")
            data = getattr(rec, f"data_{label}", None)
            est = _from_plane_fit(res, scan, data, split.get(label)) if fitted else str(res)
            uses_split = isinstance(est, Estimate) and est.extra["fitted_on_split"]
            row = plane_row(base, truth, method, label, est, rec.critical_step, dt, uses_split)
            rows.append({**row, **edge, "quality_service": quality_service.get(label)})

    default_crit = crits.get(DEFAULT_METHOD, next(iter(crits.values()), None))
    split = critical_split(scan, default_crit) if anchor else {}
    if split:
        from lelsonar.reconstruct.estimate import fit as F
        from lelsonar.reconstruct.estimate.correct import AXIS_Y, AXIS_Z

        ests: dict[str, Estimate | str] = {}
        for label, axis in (("a", AXIS_Y), ("b", AXIS_Z)):
            data = F.plane_data(scan.geometry, scan.gamma_measured, scan.distance, split[label], label, axis)
            ests[label] = open3d_anchor(data.points) or "too few points"
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


def critical_split(scan: Any, crit: int | None) -> dict[str, np.ndarray]:
    """The pipeline's subsets at ``crit`` ({} if the split cannot be made or imported)."""
    try:
        from lelsonar.reconstruct.estimate.split import split_subsets

        if crit is None:
            return {}
        s = split_subsets(scan.gamma_measured, crit)
    except Exception:  # noqa: BLE001 — diagnostics and the anchor only; the estimators may move
        return {}
    return {"a": np.asarray(s.steps_a), "b": np.asarray(s.steps_b)}
