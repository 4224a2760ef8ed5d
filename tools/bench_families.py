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
import os
import shlex
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from lelsonar.cli.executor import add_ray_argument, config_from_args, map_values
from lelsonar.tools.bench import machine
from lelsonar.tools.family_metrics import (
    ANCHOR,
    CORNER_SHARE,
    CRIT_TOLERANCE,
    FAIL_ORACLE_RATIO,
    FAIL_PATCH_CM,
    FLAGS,
    failure_flags,
    finite_json,
    frac_above,
    is_failure,
    json_default,
    ls_plane,
    percentile,
    plane_errors,
    quality_name,
    summarize,
    z_score,
)
from lelsonar.tools.family_scan import (
    Estimate,
    SceneTruth,
    anchor_available,
    edge_errors,
    family_scan,
    open3d_anchor,
    open3d_plane,
    plane_row,
    scene_truth,
)
from lelsonar.tools.family_speed import serial_scan_times, speed_summary, speed_vs_open3d

#: The measures and the scene runner are re-exported: the tests and the stress sweep import them from here.
__all__ = [
    "ANCHOR",
    "CORNER_SHARE",
    "CRIT_TOLERANCE",
    "Estimate",
    "FAIL_ORACLE_RATIO",
    "FAIL_PATCH_CM",
    "FLAGS",
    "SceneTruth",
    "add_family_arguments",
    "anchor_available",
    "default_methods",
    "edge_errors",
    "failure_flags",
    "family_scan",
    "finite_json",
    "frac_above",
    "is_failure",
    "json_default",
    "ls_plane",
    "markdown_table",
    "open3d_anchor",
    "open3d_plane",
    "percentile",
    "plane_errors",
    "plane_row",
    "quality_name",
    "run_families",
    "scene_truth",
    "serial_scan_times",
    "speed_summary",
    "speed_vs_open3d",
    "summarize",
    "z_score",
]


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
    anchor_note = None if args.no_anchor else anchor_available()
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

        def advance(done):
            for item in done:
                yield item
                progress.advance(task)

        items = [(f, s, methods, anchor, args.dump_failures, args.calibration) for f, s in jobs]
        # Spawned workers: the parent has imported Open3D (OpenMP), which a forked child may deadlock on.
        for scene, r in map_values(family_scan, items, config_from_args(args, "jobs"), wrap=advance):
            scenes.append(scene)
            rows.extend(r)
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
                finite_json(
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
    add_ray_argument(p)
    add_family_arguments(p)
    raise SystemExit(run_families(p.parse_args()))
