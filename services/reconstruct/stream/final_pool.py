"""The final pool: worker processes that run finals off the sample path, results in submission order.

A final (:func:`~lelsonar.reconstruct.stream.finals.estimate_final`: the reconstruction of record on a
whole scan) costs a scan's worth of CPU, most of it the surfaces' extraction.  Run where the samples are
handled, it holds the stream for that long (live: every scanner's samples wait; a replay: the reading
waits).  A :class:`FinalPool` runs it in worker processes instead, while the stream goes on:

- **Order**: :meth:`FinalPool.ready` and :meth:`FinalPool.drain` hand results back in the order the jobs
  were submitted (a replay prints and writes its finals in the file's order), whichever worker finished
  first.
- **Same answer**: a worker runs the same function on the same inputs, pickled exactly (NumPy arrays
  keep their bits), on the same machine code (the kernels' disk cache): the result is the one the
  caller would have computed.  Where no worker is ready yet (the pool is starting) or none is left,
  the caller computes the job itself.
- **Bounded**: at most ``capacity`` jobs wait or run; past that :meth:`FinalPool.submit` runs the job in
  the caller (the stream slows down to the estimation's pace instead of holding every scan), and
  :meth:`FinalPool.drain` runs what no worker has taken yet instead of waiting.  Results done but behind
  an older one still running are held too: at most ``capacity`` more.
- **A worker that dies** (killed, a crash in native code): its job runs again on a new worker, and if
  that one dies too, in the caller.  Never lost, never silent: logged and counted
  (:class:`PoolStats`).
- **Processes**: workers come from a fork server, never from a fork of the caller, and speak through
  their pipes (:mod:`.final_worker`).  Workers ignore Ctrl-C: the caller ends them
  (:meth:`FinalPool.close`); a worker whose caller died sees its pipe close and exits.

Results come back through one collector thread, which also feeds the next job to a freed worker at
once, so the workers never wait for the caller.  It also sends every job (pickling a job and writing it
through a worker's pipe waits for that worker to read it): the caller only hands a job to a worker, and
goes on.
"""

from __future__ import annotations

import logging
import multiprocessing
import multiprocessing.connection
import multiprocessing.forkserver
import os
import threading
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from lelsonar.errors import ConfigError, InternalError
from lelsonar.reconstruct.stream.final_worker import PRELOAD, READY, Done, run_job, worker_context, worker_main

__all__ = ["FinalPool", "PoolStats", "workers_warm"]

_log = logging.getLogger(__name__)

#: Worker starts that fail one after another before the pool gives up on workers (the caller then computes).
_MAX_FAILED_STARTS = 3
#: Set once a worker of this process has been ready: the fork server has loaded the kernels, so a new
#: pool's workers start in a fraction of a second rather than seconds.
_WARM = threading.Event()


def workers_warm() -> bool:
    """Whether a final worker of this process has started already (a new pool then starts at once)."""
    return _WARM.is_set()


@dataclass
class PoolStats:
    """What a pool did, for the service's counters."""

    submitted: int = 0
    #: Jobs run by the caller: no worker was ready (the pool starting, or none left), or a job's workers died.
    inline: int = 0
    #: Jobs run by a worker.
    pooled: int = 0
    workers_started: int = 0
    #: Workers that died while the pool was open (killed, a crash in native code), with or without a job.
    workers_lost: int = 0
    #: Jobs run again because their worker died.
    rerun: int = 0
    #: Jobs that raised (their error is handed back with them).
    errors: int = 0


@dataclass
class _Job:
    ticket: int
    fn: Callable[..., Any]
    args: tuple
    deaths: int = 0  # workers that died running it


@dataclass(eq=False)
class _Worker:
    process: Any  # multiprocessing.process.BaseProcess
    conn: multiprocessing.connection.Connection
    ready: bool = False
    job: _Job | None = None
    #: Held while writing to ``conn`` (the collector sends the jobs, close() the stop).
    sending: threading.Lock = field(default_factory=threading.Lock)


@dataclass
class _State:
    """Everything the caller and the collector thread share, behind ``lock``."""

    lock: threading.Lock = field(default_factory=threading.Lock)
    queue: deque = field(default_factory=deque)  # _Job waiting for a worker
    outbox: deque = field(default_factory=deque)  # (_Worker, _Job) given to a worker, for the collector to send
    orphans: deque = field(default_factory=deque)  # _Job whose workers died twice: the caller runs them
    workers: list = field(default_factory=list)  # _Worker
    done: dict = field(default_factory=dict)  # ticket -> Done, not yet handed back
    closing: bool = False
    gave_up: bool = False  # workers could not be started: the caller computes everything
    failed_starts: int = 0
    starting: bool = False  # the collector is starting a worker


class FinalPool:
    """Runs jobs — ``fn(*args)``, ``fn`` a module-level function — in worker processes, results in order.

    Parameters
    ----------
    workers : int
        Worker processes; 0 runs every job in the caller, at :meth:`submit` (no process, no thread).
    capacity : int, optional
        Jobs waiting or running at most (default: two per worker, and two more).
    on_ready : callable, optional
        Called (on the collector thread, without arguments) when a result arrives, or a worker becomes
        ready: the caller's loop may wake up and take results with :meth:`ready`.  Must not block.
    preload : sequence of str
        Modules the fork server imports once, before it forks the workers.

    Use :meth:`close` (or the pool as a context manager) to end the workers; a pool that is garbage
    collected, and the interpreter at exit, end them too.
    """

    def __init__(
        self,
        workers: int,
        *,
        capacity: int | None = None,
        on_ready: Callable[[], None] | None = None,
        preload: Sequence[str] = PRELOAD,
    ) -> None:
        if workers < 0:
            raise ConfigError(f"final workers must be >= 0, got {workers} (reconstruct --jobs)")
        self.workers = workers
        self.capacity = capacity if capacity is not None else 2 * workers + 2
        if self.capacity < 1:
            raise ConfigError(f"the final pool's capacity must be >= 1, got {self.capacity}")
        self.on_ready = on_ready
        self.stats = PoolStats()
        self._next_ticket = 0  # the next submitted job's
        self._next_out = 0  # the next result handed back
        self._s = _State()
        self._changed = threading.Condition(self._s.lock)
        self._thread: threading.Thread | None = None
        self._wake_r = self._wake_w = -1
        if workers:
            self._context = worker_context(preload)
            self._wake_r, self._wake_w = os.pipe()
            self._thread = threading.Thread(target=self._collect, name="final-pool", daemon=True)
            self._thread.start()

    # --- the caller's side ---------------------------------------------------------------
    @property
    def in_flight(self) -> int:
        """Jobs submitted whose results have not been handed back."""
        return self._next_ticket - self._next_out

    @property
    def unfinished(self) -> int:
        """Jobs waiting for a worker or running (at most ``capacity``, and one more while a job's workers died)."""
        with self._s.lock:
            return self._unfinished()

    @property
    def busy_pids(self) -> list[int]:
        """Process ids of the workers running a job now."""
        with self._s.lock:
            return [w.process.pid for w in self._s.workers if w.job is not None]

    @property
    def ready_workers(self) -> int:
        with self._s.lock:
            return sum(w.ready for w in self._s.workers)

    def wait_ready(self, timeout: float | None = None) -> bool:
        """Wait until every worker is ready (the fork server's first start loads the kernels: seconds); False
        if ``timeout`` s passed first, or the pool gave up on workers."""
        s = self._s
        with self._changed:
            self._changed.wait_for(lambda: s.gave_up or sum(w.ready for w in s.workers) >= self.workers, timeout)
            return not s.gave_up and sum(w.ready for w in s.workers) >= self.workers

    def submit(self, fn: Callable[..., Any], *args: Any) -> int:
        """Queue ``fn(*args)``; return its ticket.  Runs it here when no worker is ready, or when ``capacity``
        jobs already wait or run (the caller then does a job's work instead of waiting for a worker's)."""
        ticket = self._next_ticket
        self._next_ticket += 1
        self.stats.submitted += 1
        job = _Job(ticket, fn, args)
        s = self._s
        with self._changed:
            queued = (
                self.workers > 0
                and not s.gave_up
                and any(w.ready for w in s.workers)
                and self._unfinished() < self.capacity
            )
            if queued:
                s.queue.append(job)
                self._feed()
        if not queued:
            self._run_here(job)
        self._run_orphans()
        return ticket

    def ready(self) -> list[Done]:
        """The results done so far that follow the last one handed back, in submission order; never waits."""
        s = self._s
        if not s.orphans and self._next_out not in s.done:
            # (read without the lock, as the caller asks after every sample: what comes meanwhile is taken next)
            return []
        self._run_orphans()
        return self._take()

    def drain(self) -> list[Done]:
        """Every outstanding result, in submission order: waits for the running jobs (and runs here what no
        worker can)."""
        out: list[Done] = []
        while True:
            self._run_orphans()
            out += self._take()
            if self.in_flight == 0:
                return out
            s = self._s
            with self._changed:
                here = []
                if s.queue and (s.gave_up or not any(w.ready and w.process.is_alive() for w in s.workers)):
                    here = list(s.queue)  # no worker to run what waits (all died, a new one not ready): here
                    s.queue.clear()
                elif s.queue:
                    here = [s.queue.pop()]  # the newest job no worker has taken: here, instead of waiting
                elif self._next_out not in s.done and not s.orphans:
                    self._changed.wait(1.0)  # a result or a death (the timeout only guards a lost wake)
            for job in here:
                self._run_here(job)

    def close(self, wait: float | None = 5.0) -> None:
        """End the workers (a job still running is abandoned: :meth:`drain` first to keep it); idempotent.

        ``wait``: s to wait for each worker to exit before it is killed; None: do not wait (each exits once
        it reads the stop, and is reaped by the next process start or at exit).
        """
        if self._thread is None:
            return
        s = self._s
        with self._changed:
            abandoned = len(s.queue) + sum(w.job is not None for w in s.workers)
        if abandoned:
            _log.warning("final pool closed with %d jobs unfinished; their results are dropped", abandoned)
        _shutdown(s, self._wake_w, self._changed)
        thread, self._thread = self._thread, None
        if wait is None:
            return
        with self._changed:
            starting = s.starting
        if not starting:  # (a worker still starting waits for the fork server's imports: it is killed once started)
            thread.join(wait)
        with self._changed:
            workers = list(s.workers)
        for w in workers:
            w.process.join(wait)
            if w.process.is_alive():
                w.process.kill()
                w.process.join(wait)

    def __enter__(self) -> FinalPool:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def _unfinished(self) -> int:
        s = self._s
        return len(s.queue) + len(s.orphans) + sum(w.job is not None for w in s.workers)

    def _take(self) -> list[Done]:
        out = []
        with self._changed:
            done = self._s.done
            while self._next_out in done:
                out.append(done.pop(self._next_out))
                self._next_out += 1
        return out

    def _run_here(self, job: _Job) -> None:
        self.stats.inline += 1
        result = run_job(job.ticket, job.fn, job.args)
        with self._changed:
            self._record(result)

    def _run_orphans(self) -> None:
        while True:
            with self._changed:
                if not self._s.orphans:
                    return
                job = self._s.orphans.popleft()
            self._run_here(job)

    def _record(self, result: Done) -> None:
        """(lock held) A job's result."""
        if result.error is not None:
            self.stats.errors += 1
        self._s.done[result.ticket] = result
        self._changed.notify_all()

    def _feed(self) -> None:
        """(lock held) Give waiting jobs to idle ready workers; the collector sends them (:meth:`_send_given`)."""
        s = self._s
        given = False
        for w in s.workers:
            if not s.queue:
                break
            if w.ready and w.job is None:
                w.job = job = s.queue.popleft()
                s.outbox.append((w, job))
                given = True
        if given and not s.closing and threading.current_thread() is not self._thread:
            # (the pipe is open until the pool is closing, which is set under the lock held here)
            os.write(self._wake_w, b"j")

    def _send_given(self) -> None:
        """(collector) Send the jobs given to workers, outside the lock: a worker reads a job as it is written,
        and the caller meanwhile goes on (its results, the next job)."""
        s = self._s
        while True:
            with self._changed:
                if not s.outbox:
                    return
                w, job = s.outbox.popleft()
                if w.job is not job or w not in s.workers or s.closing:
                    continue  # its worker died meanwhile (the job waits again) or the pool is closing
            try:
                with w.sending:
                    w.conn.send((job.ticket, job.fn, job.args))
            except (OSError, ValueError):  # the worker died: its sentinel says so (_lost runs its job again)
                with self._changed:
                    w.ready = False

    # --- the collector thread --------------------------------------------------------------
    def _collect(self) -> None:
        s = self._s
        try:
            self._start_workers()
            while True:
                with self._changed:
                    if s.closing:
                        return
                    workers = list(s.workers)
                waits: dict[Any, tuple[str, _Worker | None]] = {self._wake_r: ("wake", None)}
                for w in workers:
                    waits[w.conn] = ("conn", w)
                    waits[w.process.sentinel] = ("died", w)
                for obj in multiprocessing.connection.wait(list(waits)):
                    what, w = waits[obj]
                    if what == "wake":
                        os.read(self._wake_r, 4096)
                    elif what == "conn" and w is not None:
                        self._receive(w)
                    elif w is not None and w.process.exitcode is not None:
                        self._lost(w)
                    self._send_given()
        except Exception:  # noqa: BLE001 - the pool must not die silently: the caller computes from here on
            _log.exception("the final pool's collector failed; finals are computed in the caller from now on")
            with self._changed:
                s.gave_up = True
                s.orphans.extend(s.queue)
                s.queue.clear()
                for w in s.workers:
                    if w.job is not None:
                        s.orphans.append(w.job)
                        w.job = None
                self._changed.notify_all()
            self._wake_caller()
        finally:
            os.close(self._wake_r)

    def _start_workers(self) -> None:
        for _ in range(self.workers):
            self._start_one()

    def _start_one(self) -> None:
        """Start a worker (on the collector thread: the fork server's first start waits for its imports)."""
        s = self._s
        parent, child = multiprocessing.Pipe()
        process = self._context.Process(  # type: ignore[attr-defined]  # every concrete context has Process
            target=worker_main, args=(child,), name="lelsonar-final", daemon=True
        )
        with self._changed:
            if s.closing:
                return
            s.starting = True
        try:
            process.start()
        except Exception:  # noqa: BLE001 - a worker that cannot start is counted; the caller computes meanwhile
            _log.exception("could not start a final worker")
            parent.close()
            with self._changed:
                s.starting = False
                s.failed_starts += 1
                if s.failed_starts >= _MAX_FAILED_STARTS:
                    self._give_up("final workers could not be started")
            return
        finally:
            child.close()
        with self._changed:
            s.starting = False
            if s.closing:
                process.kill()
                parent.close()
                return
            s.workers.append(_Worker(process, parent))
            self.stats.workers_started += 1

    def _receive(self, w: _Worker) -> None:
        try:
            message = w.conn.recv()
        except (EOFError, OSError):
            w.process.join(1.0)  # it is ending: its sentinel follows
            if w.process.exitcode is not None:
                self._lost(w)
            return
        with self._changed:
            if message == READY:
                w.ready = True
                _WARM.set()
                self._s.failed_starts = 0
                self._feed()
                self._changed.notify_all()
            else:
                self._finished(w, message)
        self._wake_caller()

    def _finished(self, w: _Worker, message: Done) -> None:
        """(lock held) A worker's result: recorded; the worker takes the next job."""
        job, w.job = w.job, None
        if job is None or message.ticket != job.ticket:
            raise InternalError(f"a final worker answered ticket {message.ticket}, not the job it was given")
        self.stats.pooled += 1
        self._record(message)
        self._feed()

    def _lost(self, w: _Worker) -> None:
        """A worker ended on its own: its job runs again (a second death: in the caller); a new worker starts."""
        s = self._s
        with self._changed:
            if w not in s.workers:
                return
            s.workers.remove(w)
            if s.closing:
                return
            self.stats.workers_lost += 1
            job, w.job = w.job, None
            if not w.ready:
                s.failed_starts += 1
            if job is not None:
                job.deaths += 1
                self.stats.rerun += 1
                if job.deaths >= 2:
                    s.orphans.append(job)
                else:
                    s.queue.appendleft(job)
                    self._feed()  # an idle worker takes it at once
            _log.error(
                "a final worker (pid %s) died with exit code %s%s; %s",
                w.process.pid,
                w.process.exitcode,
                f" while estimating job {job.ticket}" if job is not None else "",
                (
                    "its job runs in the caller (a second worker died on it)"
                    if job is not None and job.deaths >= 2
                    else "its job runs again on a new worker"
                    if job is not None
                    else "a new worker starts"
                ),
            )
            give_up = s.failed_starts >= _MAX_FAILED_STARTS
            if give_up:
                self._give_up("final workers keep dying before they are ready")
            self._changed.notify_all()
        w.conn.close()
        if not give_up:
            self._start_one()
        self._wake_caller()

    def _give_up(self, why: str) -> None:
        """(lock held) No more workers: what waits runs in the caller."""
        s = self._s
        if not s.gave_up:
            _log.error("%s; finals are computed in the caller from now on", why)
        s.gave_up = True
        s.orphans.extend(s.queue)
        s.queue.clear()
        self._changed.notify_all()

    def _wake_caller(self) -> None:
        if self.on_ready is not None:
            try:
                self.on_ready()
            except Exception:  # noqa: BLE001 - the caller's hook failing must not stop the collector
                _log.exception("the final pool's on_ready hook failed")


def _shutdown(s: _State, wake_w: int, changed: threading.Condition) -> None:
    """Tell the collector and the workers to stop (from close() or the pool's finalizer)."""
    with changed:
        if s.closing:
            return
        s.closing = True
        workers = list(s.workers)
        changed.notify_all()
    for w in workers:
        try:
            with w.sending:
                w.conn.send(None)
        except (OSError, ValueError):
            pass  # already gone
    try:
        os.write(wake_w, b"x")
        os.close(wake_w)
    except OSError:
        pass
