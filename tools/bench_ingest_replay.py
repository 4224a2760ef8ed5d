"""``lelsonar bench ingest``, (a′) and (c): the ingest stage and the MCAP replay, in this process, beside their floors.

* the ingest stage (:meth:`~lelsonar.reconstruct.stream.ingest.Ingest.accept`) against a plain upb parse
  (``FromString``) of the same payloads;
* the replay (:func:`~lelsonar.reconstruct.stream.replay.replay_mcap`) against python ``mcap`` + upb reading
  the same file (:func:`lelsonar.tools.bench_replay.time_floor`);
* a cProfile breakdown of one replay (``--profile``).
"""

from __future__ import annotations

import statistics
import time
from pathlib import Path

from lelsonar.tools.bench_ingest_live import build_scan


# --- (c) replay --------------------------------------------------------------------------------
def record_scans(path: Path, preset_name: str, scans: int) -> int:
    """Record ``scans`` scans of one scanner to ``path``; return the number of samples."""
    from lelsonar.log.recording import McapRecorder

    start, samples, end = build_scan(preset_name)
    t = 1_700_000_000_000_000_000
    n = 0
    with McapRecorder(path, metadata={"bench": "ingest"}) as rec:
        for k in range(scans):
            start.scan_id, start.start_time_ns = k + 1, t
            rec.write(start)
            for sample in samples:
                t += 20_000_000  # 20 ms per step, as an emulated scan
                sample.scan_id, sample.acquisition_time_ns = k + 1, t
                rec.write(sample)
                n += 1
            t += 1_000_000
            end.scan_id, end.end_time_ns = k + 1, t
            rec.write(end)
            t += 1_000_000_000
    return n


def time_replay(path: Path, runs: int, plans: list | None = None, **config) -> tuple[float, int]:
    """Median wall time of replay_mcap through a fresh service, and the finals of the last run; each run's
    plan (:func:`~lelsonar.reconstruct.stream.replay.replay_plan`, decided as the replay decides it) is
    appended to ``plans``.

    Each run starts once the workers of the last have exited and this process's threads are idle
    (:func:`~lelsonar.tools.bench_replay.reap_workers`, :func:`~lelsonar.tools.bench_replay.settle`): a worker
    still exiting would take a core from the run, and make it decompress on fewer threads.
    """
    from lelsonar.log.recording import open_recording
    from lelsonar.reconstruct.stream.config import ReconstructConfig
    from lelsonar.reconstruct.stream.replay import replay_mcap, replay_plan
    from lelsonar.reconstruct.stream.service import ReconstructionService
    from lelsonar.tools.bench_replay import reap_workers, settle

    times, finals = [], 0
    for _ in range(runs):
        service = ReconstructionService(ReconstructConfig(**config))
        reap_workers()
        settle()
        t = time.perf_counter()
        rec = open_recording(path)
        plan = replay_plan(rec, service.config.final_workers)
        replay_mcap(rec, service, plan=plan)
        times.append(time.perf_counter() - t)
        finals = service.stats.finals
        if plans is not None:
            plans.append(plan)
    return statistics.median(times), finals


def time_ingest_only(path: Path, runs: int) -> float:
    """Median wall time to read, decode, validate and assemble the recording (no estimation)."""
    from lelsonar.log.recording import iter_payloads
    from lelsonar.reconstruct.stream.ingest import Ingest
    from lelsonar.tools.bench_replay import reap_workers, settle

    times = []
    for _ in range(runs):
        ingest = Ingest()
        reap_workers()
        settle()
        t = time.perf_counter()
        for rec in iter_payloads(path):
            ingest.accept(rec.type_name, rec.payload)
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def time_read_upb(path: Path, runs: int) -> float:
    """Median wall time of the tolerant reader and a upb parse of every payload: the replay's reading alone."""
    from lelsonar.tools.bench_replay import reap_workers, time_read

    reap_workers()
    return statistics.median(time_read(path, warm=False)[0] for _ in range(runs))  # (warm: the replays read it)


def time_floor(path: Path, runs: int) -> float:
    """Median wall time of the replay's floor: python ``mcap`` + upb reading the same file's contract messages."""
    from lelsonar.tools.bench_replay import reap_workers
    from lelsonar.tools.bench_replay import time_floor as floor

    reap_workers()
    return statistics.median(floor(path, warm=False)[0] for _ in range(runs))  # (warm: the replays read it)


def ingest_stage_payloads(preset_name: str, n: int = 400) -> list[tuple[str, bytes]]:
    """(type name, payload) of whole scans of one scanner, ScanStart … ScanEnd, ``n`` samples or a little more."""
    from lelsonar import codec

    start, samples, end = build_scan(preset_name)
    out: list[tuple[str, bytes]] = []
    scan_id = 0
    while sum(1 for name, _ in out if name == codec.Sample.DESCRIPTOR.full_name) < n:
        scan_id += 1
        for m in (start, *samples, end):
            m.scan_id = scan_id
            out.append((m.DESCRIPTOR.full_name, m.SerializeToString()))
    return out


#: The ingest stage's floor, printed beside its ratio.
STAGE_FLOOR = (
    "plain upb parse (FromString) of the same payloads, no validation; upb copies each waveform's bytes into its "
    "arena (python protobuf does not alias the input), so the floor reads and writes every payload once; "
    "(a′) and the floor in thread CPU time"
)


def ingest_stage_vs_floor(preset_name: str, runs: int, n: int = 400) -> tuple[float, float]:
    """Samples/s of (floor) a plain upb parse, ``cls.FromString``, and of (stage)
    :meth:`~lelsonar.reconstruct.stream.ingest.Ingest.accept` — decode, validate, route, assemble: everything the
    service does before estimation — over the same payloads (whole scans, ScanStart to ScanEnd), in this
    process, one run of each per round (medians of ``runs``); this thread's CPU time, so that a neighbour's load
    on a shared host slows neither side."""
    from lelsonar import codec
    from lelsonar.reconstruct.stream.ingest import Ingest

    payloads = ingest_stage_payloads(preset_name, n)
    parsers = [(codec.MESSAGE_TYPES[name].FromString, b) for name, b in payloads]
    samples = sum(1 for name, _ in payloads if name == codec.Sample.DESCRIPTOR.full_name)
    floor, stage = [], []
    for _ in range(runs):
        t = time.thread_time()
        for parse, b in parsers:
            parse(b)
        floor.append(samples / (time.thread_time() - t))
        ingest = Ingest()
        t = time.thread_time()
        for name, b in payloads:
            ingest.accept(name, b)
        stage.append(samples / (time.thread_time() - t))
        if ingest.rejected or ingest.accepted != len(payloads):
            raise RuntimeError(f"the ingest stage refused bench payloads: {dict(ingest.rejected)}")
    return statistics.median(floor), statistics.median(stage)


def decoding_paths(preset_name: str, runs: int, n: int = 400) -> dict[str, float]:
    """µs a sample, over the same payloads (whole scans, ScanStart to ScanEnd), one run of each per round,
    medians of ``runs``: ``parse`` a plain upb parse of every payload (``ParseFromString``, no check), ``fast``
    the ingest stage as it runs (:class:`~lelsonar.reconstruct.stream.ingest.Ingest`: a Sample of an open
    scan read straight from its payload, :mod:`~lelsonar.reconstruct.stream.fastwire`), ``parsed`` the stage
    without that (``Ingest(fast_path=False)``: every payload parsed by upb, the sample placed from the
    message).  This thread's CPU time, as :func:`ingest_stage_vs_floor`."""
    from lelsonar import codec
    from lelsonar.reconstruct.stream.ingest import Ingest

    payloads = ingest_stage_payloads(preset_name, n)
    classes = [codec.MESSAGE_TYPES[name] for name, _ in payloads]
    samples = sum(1 for cls in classes if cls is codec.Sample)
    times: dict[str, list[float]] = {"parse": [], "fast": [], "parsed": []}
    for _ in range(runs):
        t = time.thread_time()
        for cls, (_, b) in zip(classes, payloads):
            cls().ParseFromString(b)
        times["parse"].append(time.thread_time() - t)
        for name, fast in (("fast", True), ("parsed", False)):
            ingest = Ingest(fast_path=fast)
            t = time.thread_time()
            for type_name, b in payloads:
                ingest.accept(type_name, b)
            times[name].append(time.thread_time() - t)
            if ingest.rejected or ingest.accepted != len(payloads):
                raise RuntimeError(f"the ingest stage refused bench payloads: {dict(ingest.rejected)}")
    return {name: 1e6 * statistics.median(v) / samples for name, v in times.items()}


def profile_replay(path: Path, samples: int, console) -> None:
    """cProfile one replay (the live path's ``handle`` code), then time each final method without the profiler."""
    import cProfile
    import pstats

    from rich.table import Table

    from lelsonar.reconstruct.estimate.pipeline import reconstruct
    from lelsonar.reconstruct.stream.replay import replay_mcap
    from lelsonar.reconstruct.stream.service import ReconstructionService

    prof = cProfile.Profile()
    service = ReconstructionService()
    prof.enable()
    replay_mcap(path, service)
    prof.disable()
    stats = pstats.Stats(prof).stats  # type: ignore[attr-defined]  # typeshed omits .stats; (file, line, func) → (cc, nc, tt, ct, callers)

    def keys(file_end: str, func: str) -> list:
        return [k for k in stats if k[0].endswith(file_end) and k[2] == func]

    def cum(file_end: str, func: str, caller: tuple[str, str] | None = None) -> tuple[int, float]:
        calls = ct = 0.0
        for k in keys(file_end, func):
            if caller is None:
                calls, ct = calls + stats[k][1], ct + stats[k][3]
                continue
            for ck, (_cc, nc, _tt, cct) in stats[k][4].items():
                if ck[0].endswith(caller[0]) and ck[2] == caller[1]:
                    calls, ct = calls + nc, ct + cct
        return int(calls), ct

    upd = ("stream/service.py", "_provisional")
    parts = [
        ("replay_mcap (everything)", "stream/sources.py", "replay_mcap", None),
        ("  MCAP read (Recording.payloads: zstd, CRC)", "log/recording.py", "payloads", None),
        ("  ingest.accept: decode + assemble", "stream/ingest.py", "accept", None),
        ("    codec.decode (parse + validate)", "lelsonar/codec.py", "decode", None),
        (
            "    ScanAssembly.add (carried energies checked, echo windows cut out)",
            "stream/assembly.py",
            "add",
            None,
        ),
        ("  _provisional (corner check, provisional refit)", *upd, None),
        ("    ScanAssembly.arrays", "stream/assembly.py", "arrays", upd),
        ("    IncrementalPlane.update (provisional planes)", "estimate/incremental.py", "update", upd),
        ("  _finalise (after ScanEnd: main + compare methods)", "stream/service.py", "_finalise", None),
        ("    reconstruct (each method, from scratch)", "estimate/pipeline.py", "reconstruct", None),
    ]
    whole = cum("stream/sources.py", "replay_mcap")[1] or 1.0
    table = Table(
        title=f"cProfile of one replay: {samples} samples, {service.stats.finals} finals "
        f"(cumulative; the profiler inflates Python-heavy code)"
    )
    for col in ("where", "calls", "cumulative s", "ms / sample", "share"):
        table.add_column(col, justify="left" if col == "where" else "right")
    for label, file_end, func, caller in parts:
        calls, ct = cum(file_end, func, caller)
        table.add_row(label, str(calls), f"{ct:.3f}", f"{1e3 * ct / samples:.2f}", f"{100 * ct / whole:.0f} %")
    console.print(table)

    top = sorted(stats.items(), key=lambda kv: kv[1][2], reverse=True)[:10]
    tt = Table(title="Top functions by own time (same profile)")
    for col in ("function", "calls", "own s"):
        tt.add_column(col, justify="left" if col == "function" else "right")
    for (f, line, fn), v in top:
        tt.add_row(f"{fn}  ({'/'.join(Path(f).parts[-2:])}:{line})", str(v[1]), f"{v[2]:.3f}")
    console.print(tt)

    # What one final costs per method, without the profiler (as _finalise calls them), on the first scan of the
    # file assembled again (the service forgets each scan once it is final).
    from lelsonar.log.recording import iter_payloads
    from lelsonar.reconstruct.stream.ingest import Ingest

    kept = Ingest()
    for rec in iter_payloads(path):
        kept.accept(rec.type_name, rec.payload)
    scan = next(iter(kept.scans.values()))
    steps, gamma, distance, _ = scan.arrays()
    cfg = service.config
    ft = Table(title=f"One final estimate per method, wall (median of 3, no profiler; {len(steps)} steps)")
    for col in ("method", "role", "ms"):
        ft.add_column(col, justify="right" if col == "ms" else "left")
    for i, method in enumerate((cfg.method, *cfg.compare_methods)):
        times = []
        for _ in range(3):
            t = time.perf_counter()
            reconstruct(gamma, distance, scan.sensor_energy[steps], scan.geometry, scan.energy_model, method)
            times.append(time.perf_counter() - t)
        ft.add_row(method, "main" if i == 0 else "compare", f"{1e3 * statistics.median(times):.1f}")
    console.print(ft)
