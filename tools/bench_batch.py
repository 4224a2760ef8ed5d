"""``lelsonar bench batch``: how ``lelsonar batch reconstruct`` scales with its workers on one archive.

An archive of simulated recordings (``lelsonar simulate --mcap``, one scan each, seeded) is reconstructed
by ``lelsonar batch reconstruct`` with 1 worker (in the process) and with N workers (a process pool,
worker start-up included), interleaved so a shared host's load falls on both alike.  The row is the ratio
of the medians, against its floor (1.7× for 2 workers: 85 % of the ideal).  ``--ray`` adds a row on Ray.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import shutil
import statistics
import tempfile
import time
from pathlib import Path

from lelsonar.cli.executor import RAY_AUTO
from lelsonar.tools.bench import machine

#: Speedup floor per worker: N workers must reach this share of N×.
EFFICIENCY_FLOOR = 0.85


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--files", type=int, default=12, help="recordings in the archive (default 12)")
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


def make_archive(folder: Path, files: int, preset: str) -> list[Path]:
    """``files`` recordings of ``preset``, seeds 0…files-1."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for seed in range(files):
        path = folder / f"scan-{seed:04d}.mcap"
        rc = _quiet_main(["simulate", "--preset", preset, "--seed", str(seed), "--mcap", str(path)])
        if rc != 0:
            raise SystemExit(f"lelsonar simulate --seed {seed} failed ({rc})")
        paths.append(path)
    return paths


def time_batch(archive: Path, out: Path, engine_flags: list[str]) -> float:
    """Wall time of one ``lelsonar batch reconstruct`` over the archive into a fresh ``out``, s."""
    shutil.rmtree(out, ignore_errors=True)
    t0 = time.perf_counter()
    rc = _quiet_main(["batch", "reconstruct", str(archive / "*.mcap"), "--out", str(out), *engine_flags])
    wall = time.perf_counter() - t0
    if rc != 0:
        raise SystemExit(f"lelsonar batch reconstruct {' '.join(engine_flags)} failed ({rc})")
    return wall


def run(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.table import Table

    from lelsonar.cli.warm_up import exercise_kernels
    from lelsonar.tools.bench import progress

    console = Console()
    with tempfile.TemporaryDirectory(prefix="lelsonar-bench-batch-") as tmp:
        root = Path(tmp)
        make_archive(root / "archive", args.files, args.preset)
        exercise_kernels()  # the in-process run starts warm, as the pool's workers start cold: the ratio is a floor
        configs = {"1 worker": ["--workers", "1"], f"{args.workers} workers": ["--workers", str(args.workers)]}
        if args.ray is not None:
            configs["ray"] = ["--ray"] + ([] if args.ray == RAY_AUTO else [args.ray])
        runs = [(name, k) for k in range(args.repeats) for name in configs]
        times: dict[str, list[float]] = {name: [] for name in configs}
        for name, k in progress(runs, "batch runs"):
            times[name].append(time_batch(root / "archive", root / f"out-{k}", configs[name]))
    med = {name: statistics.median(ts) for name, ts in times.items()}
    base = med["1 worker"]
    table = Table(
        title=f"lelsonar batch reconstruct: {args.files} recordings of {args.preset}, medians of {args.repeats}"
    )
    for col in ("engine", "median s", "min s", "files/s", "speedup", "floor", ""):
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
            f"{speedup:.2f}×",
            f"{floor:.2f}×",
            "" if n == 1 else ("ok" if ok else "[red]below the floor[/]"),
        )
    console.print(table)
    load = os.getloadavg()
    console.print(
        f"{machine()}; load average {load[0]:.1f} {load[1]:.1f} {load[2]:.1f} (the ratio needs {args.workers} free "
        "cores: on a loaded host it measures the host)",
        highlight=False,
    )
    return status
