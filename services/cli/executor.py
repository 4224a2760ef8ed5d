"""Run one function over many argument tuples: a local process pool by default, Ray tasks where asked.

The one place work fans out over processes or machines: ``lelsonar batch`` and the benchmarks use it, so
``--workers`` and ``--ray`` mean the same everywhere.  It lives with the commands because only the edge
decides how a process spends its cores; the services below scale live work through Zenoh groups and never
fan out over files, and ``tools`` may import any layer.

The local pool's workers are forked from a fork server that has imported the work's modules: imported
once, not once per worker.  Each outcome says which worker ran it and
what wall and CPU time it took, so a run can say where its time went.

``ray`` is an optional extra (``pip install -e '.[ray]'``) imported in this module only.  Ray is asked for
one CPU per task, so a cluster runs as many tasks at once as it has cores; ``--ray`` without an address
joins ``RAY_ADDRESS`` when it is set, else starts a local head.
"""

from __future__ import annotations

import argparse
import multiprocessing
import multiprocessing.forkserver
import os
import resource
import signal
import socket
import threading
import time
import traceback
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from typing import Any

from lelsonar.errors import ConfigError

#: ``--ray`` given without an address: join RAY_ADDRESS if set, else start a local head.
RAY_AUTO = "auto-or-local"
RAY_EXTRA_HINT = "Ray is not installed; install the extra: pip install -e '.[ray]'"


@dataclass(frozen=True)
class ExecutorConfig:
    """Where the work runs.

    Attributes
    ----------
    workers : int or None
        Local processes; None is one per core.  1 runs in this process (no pool).
    ray : str or None
        None: the local pool.  :data:`RAY_AUTO`: Ray at ``RAY_ADDRESS`` or a new local head.  Any other
        string: the Ray address (``auto``, ``host:6379``, ``ray://host:10001``).
    """

    workers: int | None = None
    ray: str | None = None

    @property
    def engine(self) -> str:
        """``"ray"``, ``"pool"`` or ``"inline"``, for the tables."""
        if self.ray is not None:
            return "ray"
        return "inline" if self.worker_count == 1 else "pool"

    @property
    def worker_count(self) -> int:
        return max(1, self.workers if self.workers is not None else (os.cpu_count() or 1))


@dataclass(frozen=True)
class Outcome:
    """One item's result: ``value``, or ``error`` (one line) with the ``trace`` for a report.

    ``worker`` names the process that ran it (``host:pid``), ``started`` is its start (``time.time()``,
    s), ``seconds`` its wall time, ``cpu`` the CPU time its process spent on it and ``process_cpu`` the
    CPU time of that process since it began, at the item's end: where a run's time went, never part of a
    result.
    """

    value: Any = None
    error: str | None = None
    trace: str = ""
    worker: str = ""
    started: float = 0.0
    seconds: float = 0.0
    cpu: float = 0.0
    process_cpu: float = 0.0

    @property
    def ok(self) -> bool:
        return self.error is None


@dataclass(frozen=True)
class WorkerLoad:
    """What one worker process did in a run.

    Attributes
    ----------
    worker : str
        ``host:pid``.
    items : int
        Items it ran.
    busy, cpu : float
        Wall and CPU time inside those items, s.
    process_cpu : float
        CPU time of the process from its start to its last item's end (its start-up included), s.
    first_start, last_end : float
        When its first item began and its last ended, s after the run's start: the first is the worker's
        start-up as the run saw it.
    """

    worker: str
    items: int
    busy: float
    cpu: float
    process_cpu: float
    first_start: float
    last_end: float


def worker_loads(outcomes: Iterable[Outcome], since: float) -> list[WorkerLoad]:
    """Each worker's :class:`WorkerLoad` over ``outcomes``, ``since`` being the run's ``time.time()``."""
    by_worker: dict[str, list[Outcome]] = {}
    for o in outcomes:
        if o.worker:
            by_worker.setdefault(o.worker, []).append(o)
    return [
        WorkerLoad(
            worker=w,
            items=len(os_),
            busy=sum(o.seconds for o in os_),
            cpu=sum(o.cpu for o in os_),
            process_cpu=max(o.process_cpu for o in os_),
            first_start=min(o.started for o in os_) - since,
            last_end=max(o.started + o.seconds for o in os_) - since,
        )
        for w, os_ in sorted(by_worker.items())
    ]


def add_executor_arguments(parser: argparse.ArgumentParser) -> None:
    """``--workers N`` and ``--ray [ADDRESS]``."""
    parser.add_argument(
        "--workers",
        type=int,
        default=None,
        metavar="N",
        help="local worker processes (default: one per core; 1 runs in this process)",
    )
    add_ray_argument(parser)


def add_ray_argument(parser: argparse.ArgumentParser) -> None:
    """``--ray [ADDRESS]`` alone (the benchmarks keep their ``--jobs``)."""
    parser.add_argument(
        "--ray",
        nargs="?",
        const=RAY_AUTO,
        default=None,
        metavar="ADDRESS",
        help="run on Ray instead: ADDRESS (auto, host:6379, ray://host:10001), else $RAY_ADDRESS, else a local "
        "head; needs the extra: pip install -e '.[ray]'",
    )


def config_from_args(args: argparse.Namespace, workers_dest: str = "workers") -> ExecutorConfig:
    """The executor of ``--workers`` (or the flag stored in ``workers_dest``) and ``--ray``."""
    workers = getattr(args, workers_dest, None)
    if workers is not None and workers < 1:
        raise ConfigError(f"--workers must be at least 1, not {workers}")
    return ExecutorConfig(workers=workers, ray=getattr(args, "ray", None))


def tree_cpu() -> float:
    """CPU time (user + system) of this process and of every process below it, ended or running, s.

    A fork server's workers are its children, not ours: on Linux each running child is read from
    ``/proc`` with the children it has reaped.  Elsewhere only this process and its reaped children count.
    """
    own = resource.getrusage(resource.RUSAGE_SELF)
    reaped = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + reaped.ru_utime + reaped.ru_stime + _running_children_cpu(reaped=True)


def helpers_cpu() -> float:
    """CPU time of this process's running children themselves, without theirs, s: after a pool has ended,
    the fork server's (its imports) and the resource tracker's.  0 where ``/proc`` is not."""
    return _running_children_cpu(reaped=False)


def _running_children_cpu(reaped: bool) -> float:
    tick = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
    total = 0.0
    for pid in _running_children():
        try:
            with open(f"/proc/{pid}/stat") as fh:
                fields = fh.read().rpartition(")")[2].split()
        except OSError:
            continue  # ended meanwhile: counted once reaped
        # utime, stime, cutime, cstime: fields 14-17 of proc(5), 12-15 after the name.
        total += sum(int(f) for f in fields[11 : 15 if reaped else 13]) / tick
    return total


def _running_children() -> list[int]:
    pids: list[int] = []
    try:
        for tid in os.listdir("/proc/self/task"):
            with open(f"/proc/self/task/{tid}/children") as fh:
                pids.extend(int(p) for p in fh.read().split())
    except OSError:
        return []
    return pids


_WORKER = f"{socket.gethostname()}:{{pid}}"


def _call(fn: Callable[..., Any], args: tuple) -> Outcome:
    started, t0, c0 = time.time(), time.perf_counter(), time.process_time()

    def timed(**fields: Any) -> Outcome:
        return Outcome(
            **fields,
            worker=_WORKER.format(pid=os.getpid()),
            started=started,
            seconds=time.perf_counter() - t0,
            cpu=time.process_time() - c0,
            process_cpu=time.process_time(),
        )

    try:
        return timed(value=fn(*args))
    except (Exception, SystemExit) as exc:  # noqa: BLE001 - every failure is reported with its item, never lost
        return timed(error=f"{type(exc).__name__}: {exc}".splitlines()[0], trace=traceback.format_exc())


def run_each(
    fn: Callable[..., Any], items: Sequence[tuple], config: ExecutorConfig, preload: Sequence[str] = ()
) -> Iterator[tuple[int, Outcome]]:
    """Yield ``(index, outcome)`` of ``fn(*items[index])`` for every item, in completion order.

    An exception in ``fn`` (or a worker process that dies) becomes that item's ``Outcome.error``; the other
    items run on.  ``fn`` must be a module-level function and the items picklable.  ``preload`` names the
    modules a local pool imports once and forks its workers from (``fn``'s module is always one): what
    every worker would otherwise import at its start.
    """
    if not items:
        return
    if config.ray is not None:
        yield from _run_ray(fn, items, config.ray)
    elif config.worker_count == 1:
        for i, args in enumerate(items):
            yield i, _call(fn, args)
    else:
        modules = [fn.__module__, *(m for m in preload if m != fn.__module__)]
        yield from _run_pool(fn, items, min(config.worker_count, len(items)), modules)


def map_values(
    fn: Callable[..., Any],
    items: Sequence[tuple],
    config: ExecutorConfig,
    wrap: Callable[[Iterator[tuple[int, Outcome]]], Iterator[tuple[int, Outcome]]] | None = None,
    preload: Sequence[str] = (),
) -> list[Any]:
    """``[fn(*item) for item in items]`` in input order, on the executor; the first failure is raised.

    ``wrap`` wraps the stream of completions (a progress bar).

    Raises
    ------
    RuntimeError
        An item failed (its error line, and its traceback as the message's tail).
    """
    out: list[Any] = [None] * len(items)
    stream = run_each(fn, items, config, preload)
    for i, outcome in wrap(stream) if wrap is not None else stream:
        if not outcome.ok:
            raise RuntimeError(f"item {i} {items[i]!r} failed: {outcome.error}\n{outcome.trace}")
        out[i] = outcome.value
    return out


def pool_context(preload: Sequence[str]) -> multiprocessing.context.BaseContext:
    """The start method of the local pool: a fork server where the platform has one, else spawn.

    Never a fork of this process: its threads (a progress bar, BLAS, a Rust runtime) could hold a lock the
    child would inherit held.  The fork server is a fresh single-threaded process that imports ``preload``
    once, then forks each worker with those modules loaded; spawn makes every worker import them anew.
    The server is one per process: the preload of the first pool holds for the others.

    The server starts with Ctrl-C ignored, so a Ctrl-C while it imports leaves no traceback: it ends with
    this process.  Its workers take Ctrl-C back (:func:`_worker_start`).
    """
    if "forkserver" not in multiprocessing.get_all_start_methods():
        return multiprocessing.get_context("spawn")
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload(list(preload))
    if threading.current_thread() is threading.main_thread():
        handler = signal.signal(signal.SIGINT, signal.SIG_IGN)  # inherited by the server's interpreter
        try:
            multiprocessing.forkserver.ensure_running()  # starts it, without waiting for its imports
        finally:
            signal.signal(signal.SIGINT, handler)
    return context


def _worker_start() -> None:
    """In each worker: Ctrl-C interrupts the item, as in the command itself."""
    signal.signal(signal.SIGINT, signal.default_int_handler)


def _run_pool(
    fn: Callable[..., Any], items: Sequence[tuple], workers: int, preload: Sequence[str]
) -> Iterator[tuple[int, Outcome]]:
    context = pool_context(preload)
    queue = list(range(len(items)))[::-1]  # popped from the end: input order
    while queue:
        lost: list[int] = []
        with ProcessPoolExecutor(workers, mp_context=context, initializer=_worker_start) as pool:
            # Two items per worker in flight: a worker never waits for this loop, and a dying worker loses
            # only a few items.
            running: dict[Future, int] = {}
            while (queue or running) and not lost:
                while queue and len(running) < 2 * workers:
                    i = queue.pop()
                    running[pool.submit(_call, fn, items[i])] = i
                done, _ = wait(running, return_when=FIRST_COMPLETED)
                for fut in sorted(done, key=running.__getitem__):
                    i = running.pop(fut)
                    try:
                        outcome = fut.result()
                    except BrokenProcessPool:
                        lost.append(i)
                        continue
                    yield i, outcome
            lost.extend(running.values())
        # Each item in flight when a worker died runs again alone: the one that kills its own pool is
        # reported, the others complete.
        for i in sorted(lost):
            with ProcessPoolExecutor(1, mp_context=context, initializer=_worker_start) as alone:
                try:
                    yield i, alone.submit(_call, fn, items[i]).result()
                except BrokenProcessPool:
                    yield i, Outcome(error="the worker process died (killed, or a crash in native code)")


def _ray_module():
    try:
        import ray
    except ModuleNotFoundError:
        raise ConfigError(RAY_EXTRA_HINT) from None
    return ray


def _run_ray(fn: Callable[..., Any], items: Sequence[tuple], address: str) -> Iterator[tuple[int, Outcome]]:
    ray = _ray_module()
    started = False
    # ray.init installs its own SIGINT/SIGTERM handlers in this process; the command's are put back after.
    handlers = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    if not ray.is_initialized():
        target = os.environ.get("RAY_ADDRESS") if address == RAY_AUTO else address
        try:
            ray.init(address=target or None, include_dashboard=False, log_to_driver=False, logging_level="WARNING")
        except ConnectionError as exc:
            raise ConfigError(f"cannot reach Ray at {target}: {exc}; start it with `ray start --head`") from None
        started = True
    try:
        task = ray.remote(num_cpus=1, max_retries=0)(_call)
        refs = {task.remote(fn, args): i for i, args in enumerate(items)}
        while refs:
            done, _ = ray.wait(list(refs), num_returns=1)
            for ref in done:
                i = refs.pop(ref)
                try:
                    yield i, ray.get(ref)
                except ray.exceptions.RayError as exc:
                    yield i, Outcome(error=f"{type(exc).__name__}: {exc}".splitlines()[0])
    finally:
        if started:
            ray.shutdown()
            if threading.current_thread() is threading.main_thread():
                for sig, handler in handlers.items():
                    signal.signal(sig, handler)
