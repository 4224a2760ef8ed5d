"""`lelsonar bench NAME`: the benchmarks, each a module with ``add_arguments(parser)`` and ``run(args)``.

Benchmarks measure; tests assert.  Each prints its table with the machine it
ran on, and ratios are measured side by side in one run.
"""

from __future__ import annotations

import argparse
import importlib
import platform
from collections.abc import Callable, Iterable, Iterator
from typing import TypeVar

from lelsonar.cli.warm_up import ensure_compiled

T = TypeVar("T")

BENCHES = {
    "sim": ("lelsonar.tools.bench_sim", "simulating a full scan with waveforms"),
    "estimators": ("lelsonar.tools.bench_estimators", "accuracy and speed of every estimator against the oracle"),
    "acquire": ("lelsonar.tools.bench_acquire", "emulated scan wall time against the physical bound"),
    "ingest": ("lelsonar.tools.bench_ingest", "Zenoh ingest rate, update latency and MCAP replay speed"),
    "recording": (
        "lelsonar.tools.bench_recording",
        "cost of durable recording: chunk per step, fsync, vs 1 MiB chunks",
    ),
    "surfaces": ("lelsonar.tools.bench_surfaces", "every surface of a sweep against the world simulator's truth"),
    "fleet": ("lelsonar.tools.bench_fleet", "N scanners, W reconstructors in one group: rate, latency, failover"),
    "map": ("lelsonar.tools.bench_map", "map update time per scan vs map size, walls vs truth, poses vs odometry"),
    "batch": ("lelsonar.tools.bench_batch", "lelsonar batch over an archive: N workers against 1"),
    "stress-worlds": (
        "lelsonar.tools.bench_stress_worlds",
        "surfaces and the map on worlds outside the families: good-but-wrong claims and crashes",
    ),
}


def machine() -> str:
    """One line naming the machine, for every benchmark table."""
    import os

    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return f"{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}, {platform.system()}"


def progress(items: Iterable[T], label: str, total: int | None = None) -> Iterator[T]:
    """Yield ``items`` while a progress bar on stderr counts them (transient: the tables stay clean)."""
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    if total is None and hasattr(items, "__len__"):
        total = len(items)  # type: ignore[arg-type]
    with Progress(
        TextColumn(label),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=Console(stderr=True),
        transient=True,
    ) as bar:
        task = bar.add_task(label, total=total)
        for item in items:
            yield item
            bar.advance(task)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help=f"run a benchmark ({', '.join(BENCHES)}, or all)")
    names = p.add_subparsers(dest="bench", required=True, metavar="NAME")
    for name, (module, summary) in BENCHES.items():
        mod = importlib.import_module(module)
        q = names.add_parser(name, help=summary, description=summary)
        mod.add_arguments(q)
        q.set_defaults(run=_compiled_first(mod.run))
    q = names.add_parser("all", help="every benchmark with its defaults")
    q.set_defaults(run=_compiled_first(run_all))


def _compiled_first(run: Callable[[argparse.Namespace], int]) -> Callable[[argparse.Namespace], int]:
    """``run`` once the numeric kernels are compiled (with a progress bar if the cache is cold): a bench's
    children would otherwise each compile them, and time out waiting for one another."""

    def compiled_then_run(args: argparse.Namespace) -> int:
        ensure_compiled()
        return run(args)

    return compiled_then_run


def run_all(args: argparse.Namespace) -> int:
    status = 0
    for name, (module, _summary) in BENCHES.items():  # each benchmark shows its own progress
        mod = importlib.import_module(module)
        parser = argparse.ArgumentParser(prog=f"lelsonar bench {name}")
        mod.add_arguments(parser)
        print(f"\n=== lelsonar bench {name} ===", flush=True)
        status |= int(mod.run(parser.parse_args([])) or 0)
    return status
