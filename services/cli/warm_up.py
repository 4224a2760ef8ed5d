"""`lelsonar warm-up`: compile the numeric kernels once, so the first `reconstruct` does not.

Numba compiles a kernel on its first call and keeps the machine code on disk
(:mod:`lelsonar.signal.compiled`).  Compiling all of them takes a while,
once per install or edit; `make` runs this right after installing.
It replays a short simulated recording through the service twice — the finals
of `reconstruct --source` (with the compared methods), then the live path's
provisional estimates — so every kernel meets the argument types it meets in
use, and says how many it compiled and how many it found compiled.
"""

from __future__ import annotations

import argparse
import logging
import tempfile
import time
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "warm-up",
        help="compile the numeric kernels ahead (once after an install or an edit)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.set_defaults(run=run_warm_up)


def exercise_kernels() -> None:
    """Call every kernel once, as a scan does: compiled if need be, else loaded from the cache.

    A live reconstructor does this before it listens, so its first scan does not wait for the loading
    (which would otherwise delay the first scan's samples).
    The service's own log is held back meanwhile: these scans are not the user's.
    """
    from lelsonar.acquire.simulated import record_scan
    from lelsonar.reconstruct.stream.service import ReconstructConfig, ReconstructionService
    from lelsonar.reconstruct.stream.sources import replay_mcap
    from lelsonar.sim import default_energy_model, preset, simulate_scan

    logging.disable(logging.WARNING)  # at start-up, before any thread of ours logs
    try:
        with tempfile.TemporaryDirectory(prefix="lelsonar-warm-up-") as tmp:
            path = Path(tmp) / "warm-up.mcap"
            record_scan(simulate_scan(preset("paper-test1"), seed=0), path, default_energy_model())
            for provisional in (False, True):
                replay_mcap(path, ReconstructionService(ReconstructConfig(provisional=provisional)))
    finally:
        logging.disable(logging.NOTSET)


def run_warm_up(args: argparse.Namespace) -> int:
    from lelsonar.signal.compiled import cache_dir, kernels
    from lelsonar.view import present

    console = present.console(stderr=True)
    t0 = time.perf_counter()
    with console.status("compiling the numeric kernels (~40 s the first time after an install or an edit)…"):
        exercise_kernels()
    found = kernels()
    # Counts of the kernels Python calls (by argument types); a kernel called only from kernels is compiled
    # into its callers.
    compiled = sum(sum(k.stats.cache_misses.values()) for k in found.values())
    loaded = sum(sum(k.stats.cache_hits.values()) for k in found.values())
    console.print(
        f"warm-up: {len(found)} kernels, {compiled} compiled and {loaded} loaded from the cache in "
        f"{time.perf_counter() - t0:.1f} s ({cache_dir() or 'Numba default cache'}); the others are "
        "compiled into the kernels that call them"
    )
    return 0
