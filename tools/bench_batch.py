"""``lelsonar bench batch``: how ``lelsonar batch reconstruct`` scales with its workers on one archive.

The archive: ``--distinct`` simulated recordings (``lelsonar simulate --mcap``, one scan each, seeded),
linked under ``--files`` names (a file's work does not depend on its name; links keep the disk free).
Each run is the whole command as a user types it, in a new process: ``lelsonar batch reconstruct`` with
``--workers 1`` (the files in that process: the fastest one process does it, its start-up included) and
with ``--workers N`` (a process pool, whose start-up counts), alternated so a shared host's load falls on
both alike.  The row is the ratio of the medians, against its floor (85 % of N×: 1.7× for 2 workers).
Each row also says where the time went (the command's ``--timings``): the cores it used, how busy its
workers were and what CPU they got, their start-up and the CPU of the process that hands the files out.
``--ray`` adds a row on Ray, its start-up included.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from lelsonar.cli.executor import RAY_AUTO
from lelsonar.cli.values import positive_count
from lelsonar.tools.bench import machine

#: Speedup floor per worker: N workers must reach this share of N×.
EFFICIENCY_FLOOR = 0.85


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--files", type=positive_count, default=480, help="recordings in the archive (default 480)")
    parser.add_argument(
        "--distinct", type=positive_count, default=8, help="distinct simulated scans among them (default 8)"
    )
    parser.add_argument("--preset", default="paper-test1", help="simulator preset of every scan (default paper-test1)")
    parser.add_argument("--workers", type=positive_count, default=2, help="workers of the parallel runs (default 2)")
    parser.add_argument("--repeats", type=positive_count, default=3, help="runs of each configuration (default 3)")
    parser.add_argument(
        "--ray", nargs="?", const=RAY_AUTO, default=None, metavar="ADDRESS", help="also time the batch on Ray"
    )


def _quiet_main(argv: list[str]) -> int:
    from lelsonar.cli.main import main

    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        return main(argv)


def make_archive(folder: Path, files: int, distinct: int, preset: str) -> list[Path]:
    """``files`` recordings of ``preset``: seeds 0…distinct-1 simulated, each linked under several names."""
    sources = folder / "distinct"
    sources.mkdir(parents=True, exist_ok=True)
    seeds = []
    for seed in range(max(1, min(distinct, files))):
        path = sources / f"seed-{seed:04d}.mcap"
        rc = _quiet_main(["simulate", "--preset", preset, "--seed", str(seed), "--mcap", str(path)])
        if rc != 0:
            raise SystemExit(f"lelsonar simulate --seed {seed} failed ({rc})")
        seeds.append(path)
    paths = []
    for k in range(files):
        path = folder / f"scan-{k:05d}.mcap"
        os.link(seeds[k % len(seeds)], path)
        paths.append(path)
    return paths


@dataclass(frozen=True)
class Run:
    """One ``lelsonar batch reconstruct`` run, whole command: wall time, and where the time went (from its
    ``--timings``).

    Attributes
    ----------
    wall : float
        The command's wall time, from its start to its exit, s.
    cpu_all, cpu_parent, cpu_workers : float
        CPU time (user + system) of the command and every process below it; of the command's own
        process; of its workers from their start to their last file (in-process: the files' CPU), s.
    busy : float
        Wall time the workers spent inside files, summed over them, s.
    start_up : float
        From the batch's first hand-out to the slowest worker's first file, s: a pool's start-up.
    cpu_path : float
        The run's critical path in CPU time: what its wall time would be on free cores, s.  In one process,
        all its CPU time; with a pool, the command's start-up, the fork server's imports, the busiest
        worker's CPU time, its share of handing the files out, and the command's end.
    load : float
        The host's 1-minute load average just before the run.
    """

    wall: float
    cpu_all: float
    cpu_parent: float
    cpu_workers: float
    busy: float
    start_up: float
    cpu_path: float
    load: float


def time_batch(archive: Path, out: Path, engine_flags: list[str]) -> Run:
    """Run ``lelsonar batch reconstruct`` over the archive into a fresh ``out``, in a new process."""
    shutil.rmtree(out, ignore_errors=True)
    timings = out.with_name(out.name + "-timings.json")
    argv = [sys.executable, "-m", "lelsonar", "batch", "reconstruct", str(archive / "*.mcap"), "--out", str(out)]
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    done = subprocess.run([*argv, "--timings", str(timings), *engine_flags], capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        tail = (done.stderr.strip().splitlines() or ["no output"])[-1]
        raise SystemExit(f"lelsonar batch reconstruct {' '.join(engine_flags)} failed ({done.returncode}): {tail}")
    t = json.loads(timings.read_text())
    workers = t["per_worker"]
    inline = t["engine"] == "inline"
    slowest = max((w["process_cpu"] for w in workers), default=0.0)
    path = t["cpu_before_files_s"] + t["cpu_helpers_s"] + slowest + t["cpu_after_files_s"]
    path += t["cpu_hand_out_s"] / max(1, len(workers))
    return Run(
        wall=wall,
        cpu_all=t["cpu_all_s"],
        cpu_parent=t["cpu_this_process_s"] - (sum(w["cpu"] for w in workers) if inline else 0.0),
        cpu_workers=sum(w["cpu" if inline else "process_cpu"] for w in workers),
        busy=sum(w["busy"] for w in workers),
        start_up=max((w["first_start"] for w in workers), default=0.0),
        cpu_path=t["cpu_this_process_s"] if inline else path,
        load=load,
    )


def run(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.table import Table

    from lelsonar.tools.bench import progress

    console = Console(width=max(Console().width, 180))
    with tempfile.TemporaryDirectory(prefix="lelsonar-bench-batch-") as tmp:
        root = Path(tmp)
        make_archive(root / "archive", args.files, args.distinct, args.preset)
        configs = {"1 worker": ["--workers", "1"], f"{args.workers} workers": ["--workers", str(args.workers)]}
        if args.ray is not None:
            configs["ray"] = ["--ray"] + ([] if args.ray == RAY_AUTO else [args.ray])
        runs = [(name, k) for k in range(args.repeats) for name in configs]
        results: dict[str, list[Run]] = {name: [] for name in configs}
        for name, k in progress(runs, "batch runs"):
            results[name].append(time_batch(root / "archive", root / f"out-{k}", configs[name]))
    base = statistics.median(r.wall for r in results["1 worker"])
    base_path = statistics.median(r.cpu_path for r in results["1 worker"])
    table = Table(
        title=f"lelsonar batch reconstruct: {args.files} recordings of {args.preset} ({args.distinct} distinct), "
        f"whole command, runs alternated, medians of {args.repeats}"
    )
    columns = ("engine", "wall s", "min s", "files/s", "load", "cores used", "busy", "efficiency", "start-up s")
    for col in (*columns, "parent CPU s", "free-core est.", "speedup", "floor", ""):
        table.add_column(col, justify="left" if col in ("engine", "") else "right")
    status = 0
    for name, rs in results.items():
        n = 1 if name == "1 worker" else args.workers if name != "ray" else (os.cpu_count() or 1)
        floor = 1.0 if n == 1 else EFFICIENCY_FLOOR * n
        wall = statistics.median(r.wall for r in rs)
        speedup = base / wall
        ok = speedup >= floor or n == 1
        if name != "ray":
            status |= 0 if ok else 1
        table.add_row(
            name,
            f"{wall:.2f}",
            f"{min(r.wall for r in rs):.2f}",
            f"{args.files / wall:.1f}",
            f"{statistics.median(r.load for r in rs):.1f}",
            f"{statistics.median(r.cpu_all / r.wall for r in rs):.2f}",
            f"{statistics.median(r.busy / (r.wall * n) for r in rs):.0%}",
            f"{statistics.median(r.cpu_workers / (r.wall * n) for r in rs):.0%}",
            f"{statistics.median(r.start_up for r in rs):.2f}",
            f"{statistics.median(r.cpu_parent for r in rs):.2f}",
            "—" if name == "ray" else f"{base_path / statistics.median(r.cpu_path for r in rs):.2f}×",
            f"{speedup:.2f}×",
            f"{floor:.2f}×",
            "" if n == 1 else ("ok" if ok else "[red]below the floor[/]"),
        )
    console.print(table)
    load = os.getloadavg()
    console.print(
        f"{machine()}; load average now {load[0]:.1f} {load[1]:.1f} {load[2]:.1f} (load: the 1-minute average "
        "before each run). cores used: CPU time of the command and every process below it over its wall time. "
        "busy: the workers' time inside files over wall × workers. efficiency: the workers' CPU time over wall × "
        "workers (where it is far below 100 % the host, not the batch, held them back). start-up: from the "
        "first hand-out to the slowest worker's first file. parent CPU: the command's own process, files "
        "excluded. free-core est.: the speedup the runs' CPU critical paths predict on free cores (an "
        "estimate that ignores contention for memory and caches, for a loaded host; the row's verdict is the "
        f"measured speedup). The ratio needs {args.workers} free cores.",
        highlight=False,
    )
    return status
