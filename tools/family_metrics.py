"""The pure measures of the scene-family bench: plane errors, failures, z-scores, summaries, strict JSON.

Definitions: :mod:`lelsonar.tools.bench_families`.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

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


def finite_json(o: Any) -> Any:
    """``o`` with every NaN or infinity replaced by None (strict JSON: jq and browsers read it)."""
    if isinstance(o, float):
        return o if math.isfinite(o) else None
    if isinstance(o, np.floating):
        return float(o) if np.isfinite(o) else None
    if isinstance(o, dict):
        return {k: finite_json(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [finite_json(v) for v in o]
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
