"""``lelsonar bench batch``: how ``lelsonar batch reconstruct`` scales with its workers on one archive.

The archive: ``--distinct`` simulated recordings (``lelsonar simulate --mcap``, one scan each, seeded),
linked under ``--files`` names (a file's work does not depend on its name; links keep the disk free).
Each run is the whole command as a user types it, in a new process: ``lelsonar batch reconstruct`` with
``--workers 1`` (the files in that process) and with ``--workers N`` (a process pool, whose start-up
counts), interleaved so a shared host's load falls on both alike.  The row is the ratio of the medians,
against its floor (85 % of N×: 1.7× for 2 workers).  ``--ray`` adds a row on Ray, its start-up included.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from lelsonar.cli.executor import RAY_AUTO
from lelsonar.tools.bench import machine

#: Speedup floor per worker: N workers must reach this share of N×.
EFFICIENCY_FLOOR = 0.85


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--files", type=int, default=480, help="recordings in the archive (default 480)")
    parser.add_argument("--distinct", type=int, default=8, help="distinct simulated scans among them (default 8)")
    parser.add_argument("--preset", default="paper-test1", help="simulator preset of every scan (default paper-test1)")
    parser.add_argument("--workers", type=int, default=2, help="workers of the parallel runs (default 2)")
    parser.add_argument("--repeats", type=int, default=3, help="runs of each configuration (default 3)")
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


def time_batch(archive: Path, out: Path, engine_flags: list[str]) -> tuple[float, float]:
    """Wall and CPU time (the command and its workers: user + system) of one ``lelsonar batch reconstruct``
    over the archive into a fresh ``out``, in a new process, s.

    CPU over wall is the cores the run got: a host that gives 2 workers less than 2 cores caps the ratio.
    """
    shutil.rmtree(out, ignore_errors=True)
    argv = [sys.executable, "-m", "lelsonar", "batch", "reconstruct", str(archive / "*.mcap"), "--out", str(out)]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    done = subprocess.run([*argv, *engine_flags], capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    if done.returncode != 0:
        tail = (done.stderr.strip().splitlines() or ["no output"])[-1]
        raise SystemExit(f"lelsonar batch reconstruct {' '.join(engine_flags)} failed ({done.returncode}): {tail}")
    return wall, cpu


def run(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.table import Table

    from lelsonar.tools.bench import progress

    console = Console()
    with tempfile.TemporaryDirectory(prefix="lelsonar-bench-batch-") as tmp:
        root = Path(tmp)
        make_archive(root / "archive", args.files, args.distinct, args.preset)
        configs = {"1 worker": ["--workers", "1"], f"{args.workers} workers": ["--workers", str(args.workers)]}
        if args.ray is not None:
            configs["ray"] = ["--ray"] + ([] if args.ray == RAY_AUTO else [args.ray])
        runs = [(name, k) for k in range(args.repeats) for name in configs]
        times: dict[str, list[float]] = {name: [] for name in configs}
        cores: dict[str, list[float]] = {name: [] for name in configs}
        for name, k in progress(runs, "batch runs"):
            wall, cpu = time_batch(root / "archive", root / f"out-{k}", configs[name])
            times[name].append(wall)
            cores[name].append(cpu / wall)
    med = {name: statistics.median(ts) for name, ts in times.items()}
    base = med["1 worker"]
    table = Table(
        title=f"lelsonar batch reconstruct: {args.files} recordings of {args.preset} ({args.distinct} distinct), "
        f"whole command, medians of {args.repeats}"
    )
    for col in ("engine", "median s", "min s", "files/s", "cores used", "speedup", "floor", ""):
        table.add_column(col, justify="left" if col in ("engine", "") else "right")
    status = 0
    for name, ts in times.items():
        n = 1 if name == "1 worker" else args.workers if name != "ray" else (os.cpu_count() or 1)
        floor = 1.0 if n == 1 else EFFICIENCY_FLOOR * n
        speedup = base / med[name]
        ok = speedup >= floor or n == 1
        if name != "ray":
            status |= 0 if ok else 1
        table.add_row(
            name,
            f"{med[name]:.2f}",
            f"{min(ts):.2f}",
            f"{args.files / med[name]:.1f}",
            f"{statistics.median(cores[name]):.2f}",
            f"{speedup:.2f}×",
            f"{floor:.2f}×",
            "" if n == 1 else ("ok" if ok else "[red]below the floor[/]"),
        )
    console.print(table)
    load = os.getloadavg()
    console.print(
        f"{machine()}; load average {load[0]:.1f} {load[1]:.1f} {load[2]:.1f}. cores used: CPU (user + system of "
        f"the command and its workers) over wall time; the ratio needs {args.workers} free cores, and where the "
        "workers got fewer it measures the host",
        highlight=False,
    )
    return status
