"""Replay speed and peak memory against their floor: python ``mcap`` + upb reading the same file.

Used by ``lelsonar bench recording`` (the memory rows) and ``lelsonar bench ingest`` (the replay
row's floor).  A file of N scans is made the way other programs make one: N copies of a
recorded scan (each its own scan id and times, viewer channels included) merged into ONE file
by ``mcap``'s own writer (1 MiB chunks that mix channels).  Each measurement runs in a fresh
child process (``python -m lelsonar.tools.bench_replay --child MODE FILE``), which reports its
peak resident set (``VmHWM``): replay's memory must not grow with the file.

Each child also reports the CPU seconds of its timed section (every thread of the process; not the
final workers').  The CPU of ``read``, ``ingest`` and ``inline`` against ``floor``'s says where a
replay's time goes: the reading, the ingest stage and the finals.  A replay child also reports those of its
replaying thread alone: what no other thread can take from it, under which its wall clock cannot go.

Modes:

* ``replay`` — :func:`~lelsonar.reconstruct.stream.replay.replay_mcap` through a
  ``ReconstructionService`` without provisional estimates, as ``reconstruct --source`` runs it
  (the kernels loaded first), estimation included (on a host of several cores, the next chunks
  decompressed on other threads while the service estimates; the finals in worker processes as
  :func:`~lelsonar.reconstruct.stream.replay.replay_workers` decides);
* ``warm`` — the same replay in a process whose final workers have started before (their fork
  server's imports and kernels loaded before the clock, as in a live reconstructor or a process
  that replayed a file already): the finals in workers from the first scan, where the host's load
  leaves a core idle beside the decompression's;
* ``read`` — :func:`~lelsonar.log.recording.iter_payloads` and a upb parse of each payload
  (the reading alone);
* ``ingest`` — the reading and :meth:`~lelsonar.reconstruct.stream.ingest.Ingest.accept` (decode, validate,
  assemble): the replay without its estimation;
* ``inline`` — ``replay`` with every final estimated in the replaying process (``final_workers=0``): its CPU
  seconds are the whole replay's work, where ``replay`` and ``warm`` do part of it in worker processes;
* ``floor`` — ``mcap.reader.make_reader(f).iter_messages(topics=…, log_time_order=True)`` and a
  upb parse (``FromString``) of each contract message: the reading any program can do.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path

CONTRACT_TOPICS = ("/lelsonar/scan_start", "/lelsonar/sample", "/lelsonar/scan_end")
FLOOR = (
    "python mcap make_reader + upb FromString of the contract messages, same file, log-time order, warm (after a "
    "pass over the file)"
)
TARGET_RATIO = 1.0


def peak_rss_mib() -> float:
    """This process's peak resident set, MiB (VmHWM)."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def _other_threads_ticks() -> int:
    """CPU ticks used so far by this process's threads other than the caller's (from ``/proc/self/task``)."""
    me = threading.get_native_id()
    total = 0
    for task in os.listdir("/proc/self/task"):
        if int(task) == me:
            continue
        try:
            with open(f"/proc/self/task/{task}/stat") as f:
                fields = f.read().rpartition(")")[2].split()
        except OSError:
            continue  # ended meanwhile
        total += int(fields[11]) + int(fields[12])
    return total


def settle(quiet_s: float = 0.05, limit_s: float = 2.0) -> None:
    """Wait, before a child's clock starts, until the other threads of the process have stopped using CPU.

    OpenBLAS's threads spin for a while after numpy is loaded; a child's CPU seconds count every thread, so a
    child whose clock starts right after its imports (the floor, the read) would be charged that spin and a
    replay child (whose kernels load first) would not.  Every child settles the same way.  Waits at most
    ``limit_s``; a host without ``/proc`` does not wait.
    """
    if not os.path.isdir("/proc/self/task"):
        return
    wake = threading.Event()
    deadline = time.monotonic() + limit_s
    last, since = _other_threads_ticks(), time.monotonic()
    while time.monotonic() < deadline:
        wake.wait(0.01)
        now = _other_threads_ticks()
        if now != last:
            last, since = now, time.monotonic()
        elif time.monotonic() - since >= quiet_s:
            return


def _floor_pass(path: Path) -> int:
    """Python mcap + upb over the contract messages of ``path`` in log-time order; the samples read."""
    from mcap.reader import make_reader

    from lelsonar import codec

    types = codec.MESSAGE_TYPES
    samples = 0
    with open(path, "rb") as f:
        for schema, _channel, message in make_reader(f).iter_messages(topics=CONTRACT_TOPICS, log_time_order=True):
            msg = types[schema.name if schema is not None else ""].FromString(message.data)
            samples += isinstance(msg, codec.Sample)
    return samples


def _read_pass(path: Path) -> int:
    """The tolerant reader and a upb parse of every contract payload of ``path``; the samples read."""
    from lelsonar import codec
    from lelsonar.log.recording import iter_payloads

    types = codec.MESSAGE_TYPES
    samples = 0
    for rec in iter_payloads(path):
        msg = types[rec.type_name].FromString(rec.payload)
        samples += isinstance(msg, codec.Sample)
    return samples


def reap_workers(timeout: float = 5.0) -> None:
    """Wait until the final workers a replay of this process left exiting (each exits on its own once its pool
    is closed) are gone, so that the next measurement does not share the cores with their exit."""
    import multiprocessing

    for p in multiprocessing.active_children():
        p.join(timeout)


def time_floor(path: Path, warm: bool = True) -> tuple[float, int]:
    """(seconds, samples) of python mcap + upb reading the contract messages of ``path`` in log-time order
    (``warm``: as :func:`_timed_pass`)."""
    import mcap.reader  # noqa: F401 - imported before the clock, warm or not

    from lelsonar import codec  # noqa: F401

    return _timed_pass(_floor_pass, path, warm)


def time_read(path: Path, warm: bool = True) -> tuple[float, int]:
    """(seconds, samples) of the tolerant reader and a upb parse of every contract payload (``warm``: as
    :func:`_timed_pass`)."""
    import lelsonar.log.recording  # noqa: F401 - imported before the clock, warm or not
    from lelsonar import codec  # noqa: F401

    return _timed_pass(_read_pass, path, warm)


def _timed_pass(reading: Callable[[Path], int], path: Path, warm: bool) -> tuple[float, int]:
    """(seconds, samples) of one timed pass of ``reading`` over ``path``; ``warm``: after one untimed pass.

    A replay child loads the kernels before its clock (as ``reconstruct --source`` does), which leaves its
    process a heap of freed memory: the chunks it decompresses land in pages already mapped.  A child that
    starts reading cold maps fresh pages for them instead (a page fault each, a few ms of system time a
    scan), which the replay is spared.  The untimed pass gives every child a warm heap and the file's pages
    alike, so that the ratios compare the readings, not the processes' histories.
    """
    if warm:
        reading(path)
    settle()
    cpu, t = time.process_time(), time.perf_counter()
    samples = reading(path)
    return _timed(t, cpu), samples


def time_replay(path: Path) -> tuple[float, int]:
    """(seconds, finals) of replay_mcap through a service without provisional estimates."""
    return _replay(path, warm=False)


def time_replay_warm(path: Path) -> tuple[float, int]:
    """(seconds, finals) of :func:`time_replay` with the final workers' fork server ready before the clock."""
    return _replay(path, warm=True)


#: The replay child's finals estimated in worker processes (reported beside its seconds).
_POOLED: list[int] = []
#: The child's CPU seconds (every thread of the process, not its workers) over the timed section.
_CPU: list[float] = []
#: The replay child's plan: its final workers and decompressing threads (the host's load decides them).
_PLAN: list = []
#: The replay child's CPU seconds on the replaying thread alone over the timed section: the part of its work no
#: other thread can take, which its wall clock cannot go under whatever the host.
_THREAD_CPU: list[float] = []


def _timed(t: float, cpu: float) -> float:
    """Wall seconds since ``t``; the CPU seconds since ``cpu`` go to :data:`_CPU`."""
    _CPU.append(time.process_time() - cpu)
    return time.perf_counter() - t


def time_ingest(path: Path) -> tuple[float, int]:
    """(seconds, samples) of the reading and the ingest stage (decode, validate, assemble): no estimation."""
    from lelsonar import codec
    from lelsonar.cli.warm_up import exercise_kernels
    from lelsonar.log.recording import iter_payloads
    from lelsonar.reconstruct.stream.ingest import Ingest
    from lelsonar.reconstruct.stream.replay import REPLAYED

    exercise_kernels()  # as the replay children: the kernels loaded before the clock
    ingest = Ingest()
    sample = codec.Sample.DESCRIPTOR.full_name
    samples = 0
    settle()
    cpu, t = time.process_time(), time.perf_counter()
    for rec in iter_payloads(path, REPLAYED):
        ingest.accept(rec.type_name, rec.payload)
        samples += rec.type_name == sample
    return _timed(t, cpu), samples


def time_inline(path: Path) -> tuple[float, int]:
    """(seconds, finals) of :func:`time_replay` with every final estimated in the replaying process."""
    return _replay(path, warm=False, workers=0)


def _replay(path: Path, *, warm: bool, workers: int | None = None) -> tuple[float, int]:
    from lelsonar.cli.warm_up import exercise_kernels
    from lelsonar.log.recording import open_recording
    from lelsonar.reconstruct.stream.config import ReconstructConfig
    from lelsonar.reconstruct.stream.final_pool import FinalPool
    from lelsonar.reconstruct.stream.finals import auto_workers
    from lelsonar.reconstruct.stream.replay import replay_mcap, replay_plan
    from lelsonar.reconstruct.stream.service import ReconstructionService

    if warm:
        with FinalPool(max(auto_workers(), 1)) as pool:  # the fork server's imports and kernels: once a process
            pool.wait_ready(600)
    exercise_kernels()  # loaded from the cache before the clock starts, as a live reconstructor does
    service = ReconstructionService(ReconstructConfig(provisional=False, final_workers=workers))
    settle()
    cpu, t, own = time.process_time(), time.perf_counter(), time.thread_time()
    rec = open_recording(path)
    plan = replay_plan(rec, service.config.final_workers)  # as replay_mcap decides it, reported
    replay_mcap(rec, service, plan=plan)
    _THREAD_CPU.append(time.thread_time() - own)
    seconds = _timed(t, cpu)
    _POOLED.append(int(service.stats_dict().get("finals_pool", {}).get("in_workers", 0)))
    _PLAN.append(plan)
    return seconds, service.stats.finals


_MODES = {
    "floor": time_floor,
    "read": time_read,
    "ingest": time_ingest,
    "inline": time_inline,
    "replay": time_replay,
    "warm": time_replay_warm,
}


def child(mode: str, path: Path) -> dict:
    """Run one measurement in a fresh interpreter; its seconds, samples and peak RSS."""
    done = subprocess.run(
        [sys.executable, "-m", "lelsonar.tools.bench_replay", "--child", mode, str(path)],
        capture_output=True,
        text=True,
        timeout=1800,
    )
    if done.returncode != 0:
        raise RuntimeError(f"bench_replay child {mode} failed: {done.stderr.strip().splitlines()[-1:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def merged_file(path: Path, scans: int, preset_name: str, seed: int = 0) -> int:
    """Write ``scans`` copies of one recorded scan into ONE file with ``mcap``'s own writer; return the samples."""
    from mcap.writer import CompressionType
    from mcap.writer import Writer as McapWriter

    from lelsonar import codec
    from lelsonar.log.reader import salvage
    from lelsonar.tools.bench_recording import scan_messages, write_once

    with tempfile.TemporaryDirectory(prefix="lelsonar-bench-merge-") as tmp:
        one = Path(tmp) / "one.mcap"
        write_once(one, scan_messages(preset_name, None, seed), "zstd", {})
        s = salvage(one)  # one scan: small
        ordered = s.in_log_time_order()
    t_first, t_last = ordered[0].log_time, ordered[-1].log_time
    period = t_last - t_first + 1_000_000_000
    types = {cid: codec.MESSAGE_TYPES.get(s.schema_name(cid)) for cid in s.channels}
    samples = 0
    with open(path, "wb") as f:
        w = McapWriter(f, compression=CompressionType.ZSTD)
        w.start(profile="", library="lelsonar bench (merged)")
        schema_ids = {sid: w.register_schema(sc.name, sc.encoding, sc.data) for sid, sc in s.schemas.items()}
        channel_ids = {
            cid: w.register_channel(ch.topic, ch.message_encoding, schema_ids.get(ch.schema_id, 0), dict(ch.metadata))
            for cid, ch in s.channels.items()
        }
        for k in range(scans):
            shift = k * period
            for m in ordered:
                data = m.data
                cls = types.get(m.channel_id)
                if cls in (codec.ScanStart, codec.Sample, codec.ScanEnd):
                    msg = cls.FromString(data)
                    msg.scan_id = k + 1
                    for name in ("start_time_ns", "acquisition_time_ns", "end_time_ns"):
                        if name in cls.DESCRIPTOR.fields_by_name:
                            setattr(msg, name, getattr(msg, name) + shift)
                    data = msg.SerializeToString()
                    samples += cls is codec.Sample
                t = m.log_time + shift
                w.add_message(channel_ids[m.channel_id], log_time=t, data=data, publish_time=t)
        w.finish()
    return samples


#: Runs of each mode on a file of one scan, at least: its replay takes tens of ms, a scheduling hiccup's size.
SHORT_FILE_RUNS = 9


def runs_for(scans: int, runs: int) -> int:
    """Runs of each mode on a file of ``scans`` scans: ``runs``, and more for a short file, so that every row's
    median stands on about as much replaying (:data:`SHORT_FILE_RUNS` scans' worth)."""
    return max(runs, -(-SHORT_FILE_RUNS // max(scans, 1)))


def memory_rows(scans_list: list[int], preset_name: str, runs: int = 1) -> list[dict]:
    """Per file of N scans: size, samples, and (median over :func:`runs_for` runs) seconds and peak RSS of each
    mode; ``runs`` and ``plans`` (the replay children's: final workers, decompressing threads → runs)."""
    import statistics
    from collections import Counter

    rows = []
    with tempfile.TemporaryDirectory(prefix="lelsonar-bench-replay-") as tmp:
        for n in scans_list:
            path = Path(tmp) / f"merged-{n}.mcap"
            samples = merged_file(path, n, preset_name)
            got: dict[str, list[dict]] = {mode: [] for mode in _MODES}
            k = runs_for(n, runs)
            for _ in range(k):  # interleaved: a neighbour's load hits every mode alike
                for mode in _MODES:
                    got[mode].append(child(mode, path))
            row: dict = {"scans": n, "samples": samples, "mb": path.stat().st_size / 1e6, "runs": k}
            for mode, results in got.items():
                row[f"{mode}_s"] = statistics.median(r["seconds"] for r in results)
                row[f"{mode}_cpu"] = statistics.median(r["cpu_s"] for r in results)
                row[f"{mode}_rss"] = max(r["rss_mib"] for r in results)
                row[f"{mode}_pooled"] = min(r.get("pooled", 0) for r in results)
                row[f"{mode}_thread_cpu"] = statistics.median(r.get("thread_cpu_s", math.nan) for r in results)
            row["plans"] = Counter(
                (r["workers"], r["threads"]) for mode in ("replay", "warm") for r in got[mode] if "threads" in r
            )
            rows.append(row)
            path.unlink()
    return rows


def plans_text(plans: dict[tuple[int, int], int]) -> str:
    """The replay children's plans, e.g. ``0 w + 1 t ×8, 0 w + 0 t ×1`` (final workers + decompressing threads)."""
    return ", ".join(f"{w} w + {t} t ×{k}" for (w, t), k in sorted(plans.items(), key=lambda kv: -kv[1]))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m lelsonar.tools.bench_replay")
    parser.add_argument("--child", choices=sorted(_MODES), required=True)
    parser.add_argument("path", type=Path)
    args = parser.parse_args(argv)
    seconds, samples = _MODES[args.child](args.path)
    out = {"seconds": seconds, "samples": samples, "rss_mib": peak_rss_mib(), "cpu_s": _CPU[-1]}
    if _POOLED:
        out["pooled"] = _POOLED[-1]
    if _PLAN:
        out["workers"], out["threads"] = _PLAN[-1]
    if _THREAD_CPU:
        out["thread_cpu_s"] = _THREAD_CPU[-1]
    print(json.dumps(out), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
