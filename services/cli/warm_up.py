"""lelsonar warm-up: compile the numeric kernels once, so the first reconstruction does not.

Numba compiles a kernel on its first call and keeps the machine code on disk
(lelsonar.signal.compiled).  Compiling all of them takes a while,
once per install or edit; make runs this right after installing.  It
replays a short simulated recording through the service twice (the finals of
"reconstruct --source" with the compared methods, then the live path's
provisional estimates) so every kernel meets the argument types it meets in use.

A command that computes finds the cache cold at start: it says so, then
compiles in a child process behind a progress bar, so Ctrl-C stops it at once.
"""

from __future__ import annotations

import argparse
import logging
import subprocess
import sys
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
    p.add_argument(
        "--in-process",
        action="store_true",
        help="compile in this process (Ctrl-C then waits for the kernel being compiled)",
    )
    p.set_defaults(run=run_warm_up)


def exercise_kernels() -> None:
    """Call every kernel once, as a scan does: compiled if need be, else loaded from the cache.

    A live reconstructor does this before it listens, so its first scan does not wait for the loading
    (which would otherwise delay the first scan's samples).
    The service's own log is held back meanwhile: these scans are not the user's.
    """
    import numpy as np

    from lelsonar.acquire.simulated import record_scan
    from lelsonar.reconstruct.estimate.surfaces.piston import Profiles, piston_lm
    from lelsonar.reconstruct.stream.config import ReconstructConfig
    from lelsonar.reconstruct.stream.replay import replay_mcap
    from lelsonar.reconstruct.stream.service import ReconstructionService
    from lelsonar.sim import default_energy_model, preset, simulate_scan

    logging.disable(logging.WARNING)  # at start-up, before any thread of ours logs
    try:
        with tempfile.TemporaryDirectory(prefix="lelsonar-warm-up-") as tmp:
            path = Path(tmp) / "warm-up.mcap"
            record_scan(simulate_scan(preset("paper-test1"), seed=0), path, default_energy_model())
            for provisional in (False, True):
                replay_mcap(path, ReconstructionService(ReconstructConfig(provisional=provisional)))
        # A fan sweep's beam-pattern fits run only where a wall lies past the sweep's end, which no L scan has.
        g = np.linspace(-0.3, 0.3, 13)
        piston_lm(Profiles.pack([(g, -7.0 * g * g)]), np.zeros(1), np.full(1, 5.3), free_ka=True)
    finally:
        logging.disable(logging.NOTSET)


def run_warm_up(args: argparse.Namespace) -> int:
    from lelsonar.signal.compiled import cache_dir, kernels
    from lelsonar.view import present

    console = present.console(stderr=True)
    t0 = time.perf_counter()
    in_child = None  # s spent compiling in a child process
    if not args.in_process and cache_is_cold():
        compile_in_child(console, WARM_UP_NOTICE)
        in_child = time.perf_counter() - t0
    with console.status("loading the numeric kernels…"):
        exercise_kernels()
    found = kernels()
    # A kernel has a variant per argument types it is called with from Python (one called only from other
    # kernels is compiled into them and has none), so variants outnumber kernels.
    compiled = sum(sum(k.stats.cache_misses.values()) for k in found.values())
    loaded = sum(sum(k.stats.cache_hits.values()) for k in found.values())
    done = (
        f"compiled in {in_child:.1f} s (in a child process), then {loaded} variants loaded from the cache"
        if in_child is not None
        else f"{compiled} variants compiled now and {loaded} loaded from the cache"
    )
    console.print(
        f"warm-up: {len(found)} kernels ready: {done} (a variant per argument types a kernel is called with), "
        f"in {time.perf_counter() - t0:.1f} s; cache {cache_dir() or 'of Numba'}",
        highlight=False,
    )
    return 0


def cache_is_cold() -> bool:
    """No kernel of this build has been compiled yet (its cache holds no index)."""
    from lelsonar.signal.compiled import cache_dir

    where = cache_dir()
    return where is not None and not any(where.rglob("*.nbi"))


#: What a command that computes says before it compiles a cold cache.
FIRST_RUN_NOTICE = (
    "first run of this build: compiling the numeric kernels once (about 40 s on 2 idle cores; Ctrl-C stops, "
    "`lelsonar warm-up` does it ahead)"
)
#: What `lelsonar warm-up` says before it compiles a cold cache.
WARM_UP_NOTICE = "compiling the numeric kernels of this build once (about 40 s on 2 idle cores; Ctrl-C stops)"


def compile_in_child(console, notice: str = FIRST_RUN_NOTICE) -> None:
    """Compile every kernel in a child process, with a progress bar; Ctrl-C ends it at once.

    Numba's compiler holds the interpreter for seconds at a time, which would hold a Ctrl-C as long;
    this process only waits and draws.

    Raises
    ------
    KeyboardInterrupt
        Ctrl-C (the child is stopped first).
    RuntimeError
        The child failed (its last line of stderr says why).
    """
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from lelsonar.signal.compiled import cache_dir, kernels

    where = cache_dir()
    total = len(kernels())
    console.print(notice, highlight=False)
    child = subprocess.Popen(
        [sys.executable, "-m", "lelsonar", "warm-up", "--in-process"],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # Ctrl-C reaches this process only, which stops the child
    )
    try:
        with Progress(
            TextColumn("compiling"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("kernels"),
            TimeElapsedColumn(),
            console=console,
            transient=True,
        ) as progress:
            task = progress.add_task("compile", total=total)
            while True:
                try:
                    child.wait(timeout=0.25)
                    break
                except subprocess.TimeoutExpired:
                    done = len(list(where.rglob("*.nbi"))) if where is not None else 0
                    progress.update(task, completed=min(done, total))
    except BaseException:
        child.kill()
        child.wait()
        raise
    err = child.stderr.read() if child.stderr is not None else ""
    if child.returncode != 0:
        last = (err.strip().splitlines() or ["no message"])[-1]
        raise RuntimeError(f"compiling the numeric kernels failed (exit {child.returncode}): {last}")


def ensure_compiled(console=None) -> None:
    """Before a command that computes: compile in a child, with a progress bar, if the cache is cold."""
    if not cache_is_cold():
        return
    from lelsonar.view import present

    compile_in_child(console or present.console(stderr=True))
