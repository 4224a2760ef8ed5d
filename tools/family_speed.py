"""The speed of the scene-family bench: the default method against Open3D ``segment_plane`` on the same points,
and each method's serial wall time on one scene.

Definitions: :mod:`lelsonar.tools.bench_families`.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from lelsonar.tools.family_metrics import percentile
from lelsonar.tools.family_scan import critical_split, open3d_plane


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
    from lelsonar.reconstruct.estimate.record import RecordOptions, reconstruct_scan
    from lelsonar.reconstruct.estimate.waveform_input import scan_input_of_waveforms
    from lelsonar.sim.scenes import simulate_family_scene

    fs = simulate_family_scene(family, seed, wide_calibration=calibration == "wide")
    scan = fs.scan
    given = scan_input_of_waveforms(scan, fs.energy_model)
    record = RecordOptions(method=DEFAULT_METHOD)

    def default() -> Any:
        return reconstruct_scan(given, record)

    split = critical_split(scan, default().critical_step)
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
                open3d_plane(pts, early_stop=True)
            t2 = time.perf_counter()
            for pts in subsets:
                open3d_plane(pts)
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
