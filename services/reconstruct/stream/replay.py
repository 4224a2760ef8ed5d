"""Replaying a recording through the service: the file's payloads in log-time order, on the cores it finds.

:func:`replay_mcap` feeds a recording's contract messages to the same :meth:`ReconstructionService.handle`
a live source does (:mod:`lelsonar.reconstruct.stream.sources`), so a replay gives the estimates live data
gave.  How it shares the host is its :class:`ReplayPlan` (:func:`replay_plan`): threads that decompress the
file ahead (:func:`decompress_threads`) and worker processes for its finals (:func:`replay_workers`), as
many as the tasks running now leave cores idle.
"""

from __future__ import annotations

import logging
import math
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

from lelsonar import codec
from lelsonar.log.recording import Recording, open_recording
from lelsonar.reconstruct.stream.final_pool import FinalPool, workers_warm
from lelsonar.reconstruct.stream.finals import auto_workers
from lelsonar.reconstruct.stream.service import ReconstructionService

_log = logging.getLogger(__name__)

#: The contract messages a replay feeds the service: a scan's, not the estimates a file may also hold.
REPLAYED = (codec.ScanStart, codec.Sample, codec.ScanEnd)


def decompress_threads(cpus: int | None = None, runnable: int | None = None) -> int:
    """Threads to decompress a replayed file ahead of the service: the cores no task is running on now, up to two.

    ``runnable`` (default: the host's tasks running or ready to run now, this one included, from
    ``/proc/loadavg``; the load average instead where there is none).  Not the load average where the
    kernel gives the tasks of the moment: it lags the host by a minute, and a replay right after a busy one
    would get no thread.  The reading thread decompresses itself whatever chunk no thread has started yet
    (:meth:`~lelsonar.log.reader.McapSource.read`), so a thread that loses its core to a neighbour holds the
    read up by at most the one job it has started.
    """
    n = cpus if cpus is not None else (os.cpu_count() or 1)
    busy = runnable if runnable is not None else runnable_tasks()
    return max(0, min(2, n - busy))


def runnable_tasks() -> int:
    """Tasks running or ready to run on the host now, the caller's included (``/proc/loadavg``'s fourth field);
    the 1-minute load average, rounded up, where that is not readable."""
    try:
        with open("/proc/loadavg") as f:
            return int(f.read().split()[3].partition("/")[0])
    except (OSError, ValueError, IndexError):
        return math.ceil(os.getloadavg()[0])


class ReplayPlan(NamedTuple):
    """How a replay shares the host: worker processes for its finals, threads that decompress ahead."""

    workers: int
    decompress_threads: int


#: The interpreter's switch interval while threads decompress a replayed file, s: a thread back from a chunk's
#: decompression waits this long at most for the GIL while the caller runs Python (the ingest, the finals);
#: CPython's default interval lasts several chunks' decompression, lost to the read at every hand-over.
DECOMPRESSING_SWITCH_S = 1e-4
#: The chunks a replay reads (their median record, compressed) must be at least this large for threads to
#: decompress them ahead: a thread takes the GIL back after each chunk, and against a caller busy with Python
#: (the ingest, the finals) each hand-over waits, so small chunks (``acquire``'s, a chunk per step) read slower
#: with a thread than without.
THREADED_CHUNK_BYTES = 64 * 1024


def replay_plan(rec: Recording, configured_workers: int | None) -> ReplayPlan:
    """The plan :func:`replay_mcap` follows by default, from the host's load now: :func:`decompress_threads`
    where the file's chunks are large enough (:data:`THREADED_CHUNK_BYTES`, :func:`chunk_bytes`), and
    :func:`replay_workers`."""
    size = chunk_bytes(rec)
    threads = decompress_threads() if size is None or size >= THREADED_CHUNK_BYTES else 0
    return ReplayPlan(replay_workers(configured_workers, scans_in(rec), decompressing=threads > 0), threads)


def chunk_bytes(rec: Recording) -> int | None:
    """The median length of the chunk records a replay reads (those whose index names a contract channel, or
    that have none), compressed; None where the file has none, or was not opened from a file."""
    if rec.source is None:
        return None
    contract = set(rec.contract_channels())
    sizes = sorted(
        u.length
        for u in rec.source.units
        if u.chunk and (u.index is None or any(cid in contract for cid, _n in u.index))
    )
    return sizes[len(sizes) // 2] if sizes else None


def replay_mcap(
    path: Path | str | Recording,
    service: ReconstructionService,
    on_payload: Callable[[int], None] | None = None,
    *,
    plan: ReplayPlan | None = None,
) -> int:
    """Feed a recording through the service in log-time order, then finalise open scans.

    On a host of several cores, the next chunks of the file are decompressed and checked on
    other threads while the service handles a payload (:func:`decompress_threads`,
    :meth:`~lelsonar.log.reader.McapSource.read`): decompression releases the GIL, so it overlaps
    the estimation.  The finals are estimated in worker processes while the file is read
    (:func:`replay_workers`, :class:`~lelsonar.reconstruct.stream.final_pool.FinalPool`), and handed back in
    the file's order.  The payloads are handled in the file's order, on the caller's thread, and the
    estimates are the same either way.

    ``plan``: the workers and threads to use (default: :func:`replay_plan`'s, decided now).  While threads
    decompress, the interpreter's switch interval is :data:`DECOMPRESSING_SWITCH_S` at most (restored after).

    Returns the number of payloads read.
    """
    rec = open_recording(path)
    n = 0
    if plan is None:
        plan = replay_plan(rec, service.config.final_workers)
    pool = FinalPool(plan.workers) if plan.workers else None
    switch = sys.getswitchinterval()
    if plan.decompress_threads:
        sys.setswitchinterval(min(switch, DECOMPRESSING_SWITCH_S))
    try:
        service.use_pool(pool)
        # Earlier outputs in the file (Reconstruction) are not inputs: their chunks are not even decompressed.
        for r in rec.payloads(REPLAYED, decompress_threads=plan.decompress_threads):
            service.handle(r.type_name, r.payload)
            n += 1
            if on_payload is not None:
                on_payload(r.log_time_ns)
        service.finish()  # (waits for every final)
    finally:
        sys.setswitchinterval(switch)
        if pool is not None:
            service.use_pool(None, drain=False)  # after finish(), none is left; on an error, they are dropped (logged)
            pool.close(wait=None)  # each worker exits on its own: the replay does not wait for it
    if not isinstance(path, Recording) and (line := rec.damage_warning()):
        _log.warning("%s", line.removeprefix("warning: "))
    return n


#: Scans a replay must hold to start the final workers in a process that has none yet (their fork server
#: imports the estimate and loads its kernels first: seconds of CPU, and a shorter replay ends before it is
#: ready), or, with no thread decompressing, in any process (a worker's start and the pickling cost a short
#: file more than its finals).
COLD_START_SCANS = 50
#: Scans a replay must hold to start its workers on the core its decompression takes: a worker there shares
#: that core with the decompressing thread, which a worker repays (its fork server's start, a final pickled
#: each way) only over a long file, if at all.
COLD_START_SHARED_SCANS = 500


def replay_workers(
    configured: int | None,
    scans: int | None,
    *,
    cpus: int | None = None,
    runnable: int | None = None,
    decompressing: bool = True,
) -> int:
    """Worker processes for a replay's finals: ``configured``, else :func:`auto_workers` as far as the tasks
    running now leave cores idle (``runnable`` as :func:`decompress_threads`': the caller's thread is one of
    them, and its core is the reading's; a worker that finds no core only competes with the reading).
    None for a file of one scan, whose final can overlap nothing.

    ``decompressing`` (threads decompress the file ahead, :func:`replay_plan`): below
    :data:`COLD_START_SHARED_SCANS` scans, one core fewer, the decompression's, whose thread would share it
    with a worker.  On two cores (the reading's and the decompression's) the finals of such a file stay in
    the caller while the file is decompressed ahead on the other core: a worker there would run at a lower
    priority than the decompressing thread
    (:data:`~lelsonar.reconstruct.stream.final_worker.WORKER_NICENESS`), fall behind, and leave the finals
    queued at the end of the file to the caller, after its start and the pickling had taken their CPU.

    None for a file of fewer than :data:`COLD_START_SCANS` scans in a process with no worker started yet
    (the fork server's start, its imports and kernels, takes a core for seconds), nor, without threads
    decompressing, in one with: a worker's start and the pickling cost a short file more than its finals.
    """
    if scans is not None and scans < 2:
        return 0
    if configured is not None:
        return configured
    n = cpus if cpus is not None else (os.cpu_count() or 1)
    busy = runnable if runnable is not None else runnable_tasks()
    if (not workers_warm() or not decompressing) and (scans is None or scans < COLD_START_SCANS):
        return 0
    if decompressing and (scans is None or scans < COLD_START_SHARED_SCANS):
        busy += 1  # the decompression's core
    return max(0, min(auto_workers(n), n - busy))


def scans_in(rec: Recording) -> int | None:
    """Scans a recording holds, from its summary or its chunks' indexes (None when neither says)."""
    s = rec.salvage
    counts = s.statistics_counts if s.statistics_counts is not None else s.indexed_counts
    starts = [cid for cid, cls in rec.contract_channels().items() if cls is codec.ScanStart]
    n = max([counts.get(cid, 0) for cid in starts] + [len(rec.start_copies())])
    return n if n or counts else None
