"""`lelsonar bench sim`: how long a simulated scan takes (target: 220 steps with waveforms ≤ 0.5 s, one core).

A module with ``add_arguments(parser)`` and ``run(args) -> int``.
"""

from __future__ import annotations

import argparse
import statistics
import time


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--preset", default="paper-test2", help="simulator preset (default: %(default)s)")
    parser.add_argument("--runs", type=int, default=7, help="timed runs; the median is reported (default: %(default)s)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the first run; run i uses seed + i")
    parser.add_argument("--budget", type=float, default=0.5, help="target seconds per scan (default: %(default)s)")


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from lelsonar.errors import ConfigError
    from lelsonar.sim import preset, simulate_scan
    from lelsonar.tools.bench import machine, progress

    if args.runs < 1:
        raise ConfigError(f"--runs must be ≥ 1, got {args.runs}")
    cfg = preset(args.preset)
    simulate_scan(cfg, seed=args.seed)  # warm-up: imports, first-touch allocations
    rows = []
    for with_waveforms in (True, False):
        times = []
        for i in progress(range(args.runs), f"scans {'with' if with_waveforms else 'without'} waveforms"):
            t = time.perf_counter()
            simulate_scan(cfg, seed=args.seed + i, with_waveforms=with_waveforms)
            times.append(time.perf_counter() - t)
        rows.append((with_waveforms, statistics.median(times), min(times), max(times)))

    n_samples = cfg.steps * cfg.geometry.n_capsules * cfg.window_samples
    print(f"machine: {machine()}, numpy {np.__version__}")
    print(
        f"preset {args.preset}: {cfg.steps} steps × {cfg.geometry.n_capsules} capsules × "
        f"{cfg.window_samples} samples ({n_samples / 1e6:.2f} M samples), {args.runs} runs"
    )
    print(f"{'waveforms':>10} {'median s':>10} {'min s':>8} {'max s':>8}")
    for with_waveforms, med, lo, hi in rows:
        print(f"{'yes' if with_waveforms else 'no':>10} {med:10.4f} {lo:8.4f} {hi:8.4f}")
    ok = rows[0][1] <= args.budget
    print(f"{'within' if ok else 'OVER'} the {args.budget:.2f} s budget for a full scan with waveforms")
    return 0 if ok else 1
