"""A final worker's side: the process it runs in, the protocol it speaks through its pipe, its loop.

- **Protocol**: the worker sends :data:`READY` once it has started, then reads jobs ``(ticket, fn, args)``
  (``fn`` a module-level function, pickled by reference) and sends back each one's :class:`Done`, until it
  reads ``None`` (stop) or its pipe closes (its caller is gone).
- **Process**: workers come from a fork server (:func:`worker_context`: a fresh single-threaded process that
  imported :data:`PRELOAD` once; spawn where there is none), never from a fork of the caller, which may hold
  a Zenoh session and its threads.  A worker ignores Ctrl-C (its caller ends it) and runs at a lower
  priority than its caller (:data:`WORKER_NICENESS`).
"""

from __future__ import annotations

import multiprocessing
import multiprocessing.connection
import multiprocessing.forkserver
import os
import signal
import threading
import traceback
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from lelsonar.errors import InternalError

__all__ = ["Done", "PRELOAD", "READY", "WORKER_NICENESS", "run_job", "worker_context", "worker_main"]

#: The modules a worker needs, imported once by the fork server (not once per worker): the worker's loop,
#: the final it runs, and the kernels that final loads.
PRELOAD = (
    "lelsonar.reconstruct.stream.final_worker",
    "lelsonar.reconstruct.stream.finals",
    "lelsonar.reconstruct.stream.finals_warm",
)
#: A worker's first message: it has started and takes jobs.
READY = "ready"
#: How much less CPU a worker gets than its caller when they contend for a core: the caller handles the
#: samples, and a final that waits costs no sample its latency.
WORKER_NICENESS = 5


@dataclass(frozen=True)
class Done:
    """One job's outcome: ``value``, or the ``error`` it raised (with the worker's ``trace``)."""

    ticket: int
    value: Any = None
    error: BaseException | None = None
    trace: str = ""


def worker_context(preload: Sequence[str]) -> multiprocessing.context.BaseContext:
    """The fork server (``preload`` imported once) where the platform has one, else spawn; never fork.

    The server is one per process; the first caller's preload holds for the others.  It starts with
    Ctrl-C ignored (inherited), so a Ctrl-C while it imports prints no traceback of its own, and without
    the command's stdout and stderr: it outlives the command by its imports when the command ends first,
    and a reader of the command's output must see its end when the command ends (the workers report
    through their pipes; the caller logs what they could not).
    """
    if "forkserver" not in multiprocessing.get_all_start_methods():
        return multiprocessing.get_context("spawn")
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload(list(preload))
    if threading.current_thread() is threading.main_thread():
        handler = signal.signal(signal.SIGINT, signal.SIG_IGN)
        kept = []
        for fd in (1, 2):
            try:
                if os.get_inheritable(fd):
                    os.set_inheritable(fd, False)  # closed in the server as it starts (exec)
                    kept.append(fd)
            except OSError:
                pass  # not open
        try:
            multiprocessing.forkserver.ensure_running()  # returns without waiting for its imports
        finally:
            for fd in kept:
                os.set_inheritable(fd, True)
            signal.signal(signal.SIGINT, handler)
    return context


def run_job(ticket: int, fn: Callable[..., Any], args: tuple) -> Done:
    """``fn(*args)``'s value, or the error it raised with its trace, as job ``ticket``'s :class:`Done`."""
    try:
        return Done(ticket, fn(*args))
    except Exception as exc:  # noqa: BLE001 - handed back with its job, raised or reported by the caller
        return Done(ticket, error=exc, trace=traceback.format_exc())


def worker_main(conn: multiprocessing.connection.Connection) -> None:
    """A worker: run each job it is sent and send back its :class:`Done`, until told to stop (None) or its
    caller is gone."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the caller's: it ends the workers
    try:
        os.nice(WORKER_NICENESS)
    except OSError:
        pass  # (a platform without priorities: the worker runs at its caller's)
    try:
        conn.send(READY)
        while True:
            job = conn.recv()
            if job is None:
                return
            result = run_job(*job)
            try:
                conn.send(result)
            except Exception as exc:  # noqa: BLE001 - an unpicklable result or error is reported, not lost
                conn.send(Done(result.ticket, error=InternalError(f"a final's result could not be sent back: {exc}")))
    except (EOFError, OSError, KeyboardInterrupt):
        return  # the caller is gone
