"""``lelsonar bench ingest``: Zenoh ingest rate, update latency and MCAP replay speed.

Three measurements, side by side in one run and one table:

(a) **sustained ingest** through Zenoh with reconstruction on.  A publisher
    process puts ``Sample`` payloads (4 × 3500 float32 waveforms, 56 KB) of
    several scanners, interleaved, through the acquisition service's own
    :class:`~lelsonar.acquire.scan_loop.ScanPublisher` (congestion control
    BLOCK), as fast as BLOCK lets it, for ``--seconds``; a consumer process runs
    :class:`~lelsonar.reconstruct.stream.sources.LiveSource` feeding a
    :class:`~lelsonar.reconstruct.stream.service.ReconstructionService` (default
    configuration, estimates published by a
    :class:`~lelsonar.reconstruct.stream.sources.PlanesServer`).  The rate is the
    number of samples whose ``handle`` returned per second, between the 10th
    and the 90th percentile of the samples (the start-up and the final drain
    left out).  Target ≥ 1,000 samples/s and ≥ 0.8× the decode + validate
    floor: :func:`lelsonar.codec.decode` alone on the same payloads (whole
    scans, ScanStart to ScanEnd; samples counted), in the parent process,
    right after the run (printed beside the result).
(a′) the **ingest stage** alone — decode, validate, route, assemble
    (:meth:`~lelsonar.reconstruct.stream.ingest.Ingest.accept`: everything the
    service does before estimation — the samples' one compiled pass, which
    also works out each step's E^γ, E0 and R) — on the floor's payloads, one run of each
    per round, medians of 5; same target against the same floor.  The details
    give the time ``Ingest.accept`` took per sample inside (a)'s consumer.
(b) **latency** of ``--latency-scanners`` scanners (default 10) each putting
    ``--rate`` samples/s (default 50: one every 20 ms),
    ``--scans`` scans each, back to back; not synchronised (scanner j runs j/N
    of a scan behind the first, so their corners and finals do not all fall on
    the same instant).  Each ``Sample``'s ``acquisition_time_ns`` and
    each ``ScanEnd``'s ``end_time_ns`` is stamped with ``time.time_ns()`` just
    before its put.  The consumer reports, per sample, put → ``handle``
    returned ("processed"); per provisional estimate, put of the sample named
    by its ``last_step`` → the estimate published; per final estimate, put of
    the ``ScanEnd`` → published.  The publisher also subscribes to the planes
    key and reports put → estimate *received* (what a planner sees).  Target
    p99 ≤ 50 ms for the first two.
(c) **MCAP replay**: ``--scans`` scans recorded with
    :class:`~lelsonar.log.recording.McapRecorder` (zstd, /tf and points included),
    replayed with :func:`~lelsonar.reconstruct.stream.sources.replay_mcap` through a
    default ``ReconstructionService``; samples / wall time, median of
    ``--replay-runs``.  Target ≥ 3,000 samples/s and ≥ 0.8× the read + decode
    floor (the same file read and every payload decoded and validated, same run).  Two diagnostic rows
    bracket it: the replay without the comparison methods
    (``compare_methods=()``), and reading + decoding + assembling alone.

Processes: the consumer listens on a private unix socket
(``unixsock-stream/<tmpdir>/z.sock``, a peer); the publisher connects to it as
a client.  Both are ``python -m lelsonar.tools.bench_ingest --role ...``,
started and always reaped by the bench; every session is closed by a ``with``.
The messages come from the simulator (:class:`~lelsonar.acquire.backends.SimScanner`)
built once by :mod:`lelsonar.acquire.messages`, as the acquisition service builds them.

``--profile`` adds a cProfile breakdown of one replay (the same ``handle`` code
as the live path).
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from lelsonar.tools.bench_ingest_procs import READY, RESULT, run_phase
from lelsonar.tools.bench_ingest_stage import (
    build_scan,
    decoding_paths,
    ingest_stage_vs_floor,
    profile_replay,
    record_scans,
    time_ingest_only,
    time_read_decode,
    time_replay,
)

TARGET_RATE = 1000.0
TARGET_P99_MS = 50.0
TARGET_REPLAY = 3000.0
#: Ingest and replay within this share of their floors (decode + validate; read + decode),
#: each floor measured in the same run.
TARGET_FLOOR_RATIO = 0.8
DONE_KEY = "lelsonar-bench/ingest/done"
SAMPLE_TYPE = "lelsonar.v1.Sample"
PREFIX = "lelsonar"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--scans",
        type=int,
        default=3,
        help="scans in the latency run and in the replayed recording (default: %(default)s)",
    )
    parser.add_argument(
        "--seconds", type=float, default=8.0, help="publishing time of the ingest-rate run, s (default: %(default)s)"
    )
    parser.add_argument(
        "--rate",
        type=float,
        default=50.0,
        help="samples/s each scanner publishes in the latency run (default: %(default)s, a sample every 20 ms)",
    )
    parser.add_argument(
        "--latency-scanners",
        type=int,
        default=10,
        help="scanners publishing at --rate each in the latency run (default: %(default)s)",
    )
    parser.add_argument(
        "--scanners", type=int, default=2, help="scanners interleaved in the ingest-rate run (default: %(default)s)"
    )
    parser.add_argument("--preset", default="paper-test1", help="simulator preset of the scan (default: %(default)s)")
    parser.add_argument(
        "--fifo",
        type=int,
        default=256,
        help="LiveSource fifo_capacity in the consumer; bounds what is buffered when the "
        "publisher outruns it (default: %(default)s)",
    )
    parser.add_argument(
        "--replay-runs",
        type=int,
        default=5,
        help="timed rounds of the replay rows and their floor, interleaved; medians (default: %(default)s)",
    )
    parser.add_argument("--profile", action="store_true", help="also print a cProfile breakdown of one replay")
    # Internal: the child processes.
    parser.add_argument("--role", choices=("consumer", "publisher"), help=argparse.SUPPRESS)
    parser.add_argument("--socket", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--phase", choices=("rate", "latency"), help=argparse.SUPPRESS)
    parser.add_argument("--timeout", type=float, default=60.0, help=argparse.SUPPRESS)


def command_line(args: argparse.Namespace) -> str:
    return (
        f"lelsonar bench ingest --scans {args.scans} --seconds {args.seconds:g} --rate {args.rate:g} "
        f"--scanners {args.scanners} --latency-scanners {args.latency_scanners} --preset {args.preset} "
        f"--fifo {args.fifo} --replay-runs {args.replay_runs}" + (" --profile" if args.profile else "")
    )


def _stamp(message, scanner_id: str, scan_id: int, field: str | None = None) -> int:
    """Give a prebuilt message its identity and, if ``field``, the wall clock now; return that time."""
    message.scanner_id = scanner_id
    message.scan_id = scan_id
    now = time.time_ns()
    if field:
        setattr(message, field, now)
    return now


# --- the publisher process ---------------------------------------------------------------------
def publisher_main(args: argparse.Namespace) -> int:
    import zenoh

    from lelsonar import codec
    from lelsonar.acquire.scan_loop import ScanPublisher
    from lelsonar.keys import ScannerKeys
    from lelsonar.net.transport import hermetic_settings, open_session

    start, samples, end = build_scan(args.preset)
    n_scanners = args.scanners if args.phase == "rate" else args.latency_scanners
    scanners = [f"bench{i}" for i in range(n_scanners)]
    received: list[tuple[int, bytes]] = []
    put_ns: dict[tuple[str, int, int], int] = {}  # (scanner, scan, step) → put time
    end_ns: dict[tuple[str, int], int] = {}
    deadline = time.monotonic() + args.timeout
    with open_session(hermetic_settings(args.socket, listen=False)) as session:
        planes_sub = session.declare_subscriber(
            ScannerKeys(PREFIX, "*").planes, lambda s: received.append((time.time_ns(), s.payload.to_bytes()))
        )
        pubs = {sid: ScanPublisher(session, ScannerKeys(PREFIX, sid)) for sid in scanners}
        # Publish nothing before the consumer's subscriptions are known here (a put before would be lost).
        probes = [
            session.declare_publisher(k)
            for sid in scanners
            for k in (ScannerKeys(PREFIX, sid).sample, ScannerKeys(PREFIX, sid).scan, DONE_KEY)
        ]
        while not all(p.matching_status.matching for p in probes):
            if time.monotonic() > deadline:
                raise SystemExit("publisher: the consumer's subscriptions never matched")
            time.sleep(0.01)
        for p in probes:
            p.undeclare()

        puts = 0
        scans = 0
        scan_base = time.time_ns() // 1000
        t_first = time.monotonic()
        if args.phase == "rate":
            # Rounds of one scan per scanner, samples interleaved, as fast as BLOCK allows.
            rounds = 0
            while time.monotonic() - t_first < args.seconds and time.monotonic() < deadline:
                scan_id = scan_base + rounds
                for sid in scanners:
                    _stamp(start, sid, scan_id, "start_time_ns")
                    pubs[sid].publish(start)
                for sample in samples:
                    for sid in scanners:
                        _stamp(sample, sid, scan_id, "acquisition_time_ns")
                        pubs[sid].publish(sample)
                        puts += 1
                for sid in scanners:
                    _stamp(end, sid, scan_id, "end_time_ns")
                    pubs[sid].publish(end)
                    scans += 1
                rounds += 1
        else:
            # Every scanner puts one sample each 1/--rate s, its --scans scans back to back; the scanners
            # are not synchronised: scanner j runs j/N of a scan behind scanner 0 (staggered within the
            # period too), as independent robots would.  Scan ids differ per scanner.
            period = 1.0 / args.rate
            lag = period / n_scanners
            steps = len(samples)
            offset = [round(j * steps / n_scanners) for j in range(n_scanners)]
            total = args.scans * steps
            for i in range(total + max(offset)):
                for j, sid in enumerate(scanners):
                    k, step = divmod(i - offset[j], steps)
                    if not 0 <= k < args.scans:
                        continue
                    scan_id = scan_base + k
                    if step == 0:
                        _stamp(start, sid, scan_id, "start_time_ns")
                        pubs[sid].publish(start)
                    delay = t_first + i * period + j * lag - time.monotonic()
                    if delay > 0:
                        time.sleep(delay)
                    sample = samples[step]
                    put_ns[(sid, scan_id, sample.step)] = _stamp(sample, sid, scan_id, "acquisition_time_ns")
                    pubs[sid].publish(sample)
                    puts += 1
                    if step == steps - 1:
                        end_ns[(sid, scan_id)] = _stamp(end, sid, scan_id, "end_time_ns")
                        pubs[sid].publish(end)
                        scans += 1
        put_s = time.monotonic() - t_first
        session.put(
            DONE_KEY, json.dumps({"samples": puts, "scans": scans}), congestion_control=zenoh.CongestionControl.BLOCK
        )
        # Wait (bounded) for every final estimate to come back.
        finals = seen = 0
        while finals < scans and time.monotonic() < deadline:
            time.sleep(0.05)
            batch = received[seen:]
            seen += len(batch)
            finals += sum(1 for _, b in batch if codec.decode(b, codec.Reconstruction).status != 1)
        planes_sub.undeclare()
        for p in pubs.values():
            p.close()

    e2e = []
    for t, payload in received:
        msg = codec.decode(payload, codec.Reconstruction)
        if msg.status == 1:
            ref = put_ns.get((msg.scanner_id, msg.scan_id, msg.last_step))
        else:
            ref = end_ns.get((msg.scanner_id, msg.scan_id))
        if ref is not None:
            e2e.append(("provisional" if msg.status == 1 else "final", t - ref))
    print(
        RESULT
        + json.dumps({"puts": puts, "scans": scans, "put_s": put_s, "estimates_received": len(received), "e2e": e2e}),
        flush=True,
    )
    return 0


# --- the consumer process ----------------------------------------------------------------------
def _timed_service_class():
    """A ReconstructionService that timestamps what it processes (the bench's probe, not a change of it)."""
    from lelsonar.reconstruct.stream.ingest import Accepted, Ingest
    from lelsonar.reconstruct.stream.service import ReconstructConfig, ReconstructionService

    class TimedIngest(Ingest):
        last_events: list = []
        sample_accept_s: list = [0, 0.0]  # Sample payloads accepted, and the time spent in accept on them

        def accept(self, type_name, payload, **kwargs):
            t0 = time.perf_counter()
            events = super().accept(type_name, payload, **kwargs)
            if type_name == SAMPLE_TYPE:
                self.sample_accept_s = [self.sample_accept_s[0] + 1, self.sample_accept_s[1] + time.perf_counter() - t0]
            self.last_events = events
            return events

    class TimedService(ReconstructionService):
        def __init__(self, config: ReconstructConfig | None = None) -> None:
            config = ReconstructConfig() if config is None else config
            super().__init__(config, publish=self._published)
            self.ingest = TimedIngest(limits=config.limits)
            self.forward = None  # e.g. PlanesServer.publish
            self.done_mono: list[float] = []  # per sample: when its handle returned (monotonic s)
            self.sample_latency_ns: list[int] = []  # per sample: handle returned − put
            self.estimate_latency: list[tuple[str, int]] = []
            self.busy: dict[str, list[float]] = {}  # bucket → handle durations, s
            self._finals_made = False

        def handle(self, type_name, payload, **kwargs):
            self.ingest.last_events = []
            self._finals_made = False
            t0 = time.perf_counter()
            out = super().handle(type_name, payload, **kwargs)
            dt = time.perf_counter() - t0
            now_ns, now_mono = time.time_ns(), time.monotonic()
            kind = type_name.rsplit(".", 1)[-1]
            bucket = "final" if self._finals_made else ("provisional" if out else kind)
            self.busy.setdefault(bucket, []).append(dt)
            for ev in self.ingest.last_events:
                if isinstance(ev, Accepted) and ev.kind == "sample":
                    self.done_mono.append(now_mono)
                    self.sample_latency_ns.append(now_ns - int(ev.scan.time_ns[ev.step]))
            return out

        def tick(self, **kwargs):
            self._finals_made = False
            t0 = time.perf_counter()
            out = super().tick(**kwargs)
            if out:
                self.busy.setdefault("final (tick)", []).append(time.perf_counter() - t0)
            return out

        def _published(self, msg) -> None:
            if self.forward is not None:
                self.forward(msg)
            now = time.time_ns()
            scan = self.ingest.scans.get((msg.scanner_id, msg.scan_id))
            if msg.status == 1:
                ref = int(scan.time_ns[msg.last_step]) if scan is not None else None
                name = "provisional"
            else:
                self._finals_made = True
                ref = scan.end.end_time_ns if scan is not None and scan.end is not None else None
                name = "final"
            if ref is not None:
                self.estimate_latency.append((name, now - ref))

    return TimedService


def consumer_main(args: argparse.Namespace) -> int:
    from lelsonar.cli.warm_up import exercise_kernels
    from lelsonar.keys import ScannerKeys
    from lelsonar.net.transport import hermetic_settings, open_session
    from lelsonar.reconstruct.stream.sources import LiveSource, PlanesServer

    exercise_kernels()  # as `lelsonar reconstruct` does before it listens
    service = _timed_service_class()()
    keys = ScannerKeys(PREFIX, "*")
    stop = threading.Event()
    done: dict[str, Any] = {}
    got_done = threading.Event()
    timed_out = False

    def on_done(sample) -> None:
        done.update(json.loads(sample.payload.to_bytes()))
        got_done.set()

    deadline = time.monotonic() + args.timeout
    with open_session(hermetic_settings(args.socket, listen=True)) as session:
        planes = PlanesServer(session, keys, service.latest)
        service.forward = planes.publish
        ctl = session.declare_subscriber(DONE_KEY, on_done)
        source = LiveSource(session, keys, service, stop, fifo_capacity=args.fifo)
        with source:
            print(READY, flush=True)
            while True:
                if (
                    got_done.is_set()
                    and len(service.done_mono) >= done["samples"]
                    and service.stats.finals >= done["scans"]
                ):
                    break
                if time.monotonic() > deadline:
                    timed_out = True
                    break
                time.sleep(0.01)
        ctl.undeclare()
        planes.close()
    busy = {k: [len(v), sum(v), max(v)] for k, v in service.busy.items()}
    print(
        RESULT
        + json.dumps(
            {
                "samples": len(service.done_mono),
                "finals": service.stats.finals,
                "done": done,
                "timed_out": timed_out,
                "rejected": dict(service.ingest.rejected),
                "errors": source.errors,
                "done_mono": service.done_mono,
                "sample_latency_ns": service.sample_latency_ns,
                "estimate_latency": service.estimate_latency,
                "busy": busy,
                "sample_accept_s": service.ingest.sample_accept_s,
            }
        ),
        flush=True,
    )
    return 0


# --- the benchmark ---------------------------------------------------------------------------
def _pct(values: list[float], q: float) -> float:
    if not values:
        return float("nan")
    s = sorted(values)
    return s[min(len(s) - 1, max(0, round(q / 100 * (len(s) - 1))))]


def _lat_ms(pairs: list, name: str) -> list[float]:
    return [ns / 1e6 for n, ns in pairs if n == name]


def _verdict(ok: bool) -> str:
    return "[green]PASS[/]" if ok else "[red]MISS[/]"


def run(args: argparse.Namespace) -> int:
    if args.role == "consumer":
        return consumer_main(args)
    if args.role == "publisher":
        return publisher_main(args)

    from rich.console import Console
    from rich.table import Table

    from lelsonar.errors import ConfigError
    from lelsonar.reconstruct.stream.service import ReconstructConfig
    from lelsonar.tools.bench import machine, progress
    from lelsonar.tools.bench_acquire import host_busy, host_line

    defaults = ReconstructConfig()

    if (
        args.scans < 1
        or args.seconds <= 0
        or args.rate <= 0
        or args.scanners < 1
        or args.replay_runs < 1
        or args.latency_scanners < 1
    ):
        raise ConfigError("--scans, --scanners, --replay-runs must be >= 1; --seconds and --rate > 0")
    console = Console(width=max(Console().width, 160))
    busy = host_busy()
    t_bench = time.perf_counter()

    phases = iter(progress(["sustained ingest", "latency", "replay"], "phases"))
    # (a) sustained ingest
    next(phases)
    pub_a, con_a = run_phase(args, "rate")
    done = sorted(con_a["done_mono"])
    n = len(done)
    i10, i90 = n // 10, (9 * n) // 10
    rate = (i90 - i10) / (done[i90] - done[i10]) if n > 10 and done[i90] > done[i10] else float("nan")
    overall = (n - 1) / (done[-1] - done[0]) if n > 1 else float("nan")
    window = done[-1] - done[0] if n > 1 else float("nan")
    busy_s = sum(v[1] for v in con_a["busy"].values())
    b = con_a["busy"]

    # The floor and the ingest stage alone, the same run, right after (a), on the same payloads, interleaved.
    floor_a, stage_a = ingest_stage_vs_floor(args.preset, 5)
    decoding = decoding_paths(args.preset, 5)
    live_accepts, live_accept_s = con_a["sample_accept_s"]

    def mean_ms(bucket: str) -> str:
        return f"{1e3 * b[bucket][1] / b[bucket][0]:.1f}" if bucket in b else "—"

    # (b) latency
    next(phases)
    pub_b, con_b = run_phase(args, "latency")
    lat_sample = [ns / 1e6 for ns in con_b["sample_latency_ns"]]
    lat_prov = _lat_ms(con_b["estimate_latency"], "provisional")
    lat_final = _lat_ms(con_b["estimate_latency"], "final")
    e2e_prov = _lat_ms(pub_b["e2e"], "provisional")
    e2e_final = _lat_ms(pub_b["e2e"], "final")

    # (c) replay
    next(phases)
    with tempfile.TemporaryDirectory(prefix="lelsonar-bench-replay-") as tmp:
        path = Path(tmp) / "replay.mcap"
        n_replay = record_scans(path, args.preset, args.scans)
        time_replay(path, 1)  # warm-up
        # (c) is what `lelsonar reconstruct --source FILE.mcap` runs: finals only, no provisional estimates.
        # Interleaved, one run of each per round, so a neighbour's load hits the result and its floor alike.
        rounds: dict[str, list[float]] = {"replay": [], "prov": [], "ingest": [], "floor": []}
        for _ in range(args.replay_runs):
            t, replay_finals = time_replay(path, 1, provisional=False)
            rounds["replay"].append(t)
            rounds["prov"].append(time_replay(path, 1)[0])
            rounds["ingest"].append(time_ingest_only(path, 1))
            rounds["floor"].append(time_read_decode(path, 1))
        replay_s, replay_prov_s, ingest_s, read_decode_s = (
            statistics.median(rounds[k]) for k in ("replay", "prov", "ingest", "floor")
        )
        size_mb = path.stat().st_size / 1e6
        if args.profile:
            profile_stash = (path.read_bytes(), n_replay)
        else:
            profile_stash = None
    next(phases, None)  # the bar counts the last phase and goes
    wall = time.perf_counter() - t_bench

    console.print(
        f"[bold]lelsonar bench ingest[/] — preset {args.preset}, Sample = 4 × 3500 float32 "
        f"waveforms (56 KB); bench wall {wall:.0f} s"
    )
    console.print(f"machine: {machine()}; {host_line(busy)}")
    console.print(f"command: {command_line(args)}")
    console.print(
        f"service: ReconstructConfig() defaults — method {defaults.method}, compare_methods "
        f"{defaults.compare_methods}, refit_every {defaults.refit_every}"
    )
    table = Table(title="Ingest, latency and replay (one run, side by side)")
    for col in ("measurement", "result", "floor (same run)", "ratio", "target", "verdict", "details"):
        table.add_column(
            col,
            justify="right" if col in ("result", "target", "floor (same run)", "ratio") else "left",
            overflow="fold",
            max_width=70 if col == "details" else None,
        )
    ok_rate = rate >= TARGET_RATE and rate >= TARGET_FLOOR_RATIO * floor_a
    table.add_row(
        "(a) sustained ingest, Zenoh → LiveSource → service",
        f"{rate:,.0f} samples/s",
        f"{floor_a:,.0f}/s decode+validate",
        f"{rate / floor_a:.2f}×",
        f"≥ {TARGET_RATE:,.0f} and ≥ {TARGET_FLOOR_RATIO}× floor",
        _verdict(ok_rate),
        f"{n} samples of {args.scanners} scanners × {con_a['finals'] // max(1, args.scanners)} scans "
        f"in {window:.1f} s (overall {overall:,.0f}/s; 10–90 % window); "
        f"publisher {pub_a['puts'] / pub_a['put_s']:,.0f} puts/s "
        f"(BLOCK); consumer busy {100 * busy_s / window:.0f} % in handle; mean handle ms: sample "
        f"{mean_ms('Sample')}, with provisional refit {mean_ms('provisional')}, with final {mean_ms('final')}; "
        f"rejected {con_a['rejected'] or 0}, errors {con_a['errors']}"
        + ("; [red]consumer timed out[/]" if con_a["timed_out"] else ""),
    )
    ok_stage = stage_a >= TARGET_FLOOR_RATIO * floor_a
    table.add_row(
        "(a′) ingest stage alone: decode + validate + route + assemble (Ingest.accept)",
        f"{stage_a:,.0f} samples/s",
        f"{floor_a:,.0f}/s decode+validate",
        f"{stage_a / floor_a:.2f}×",
        f"≥ {TARGET_FLOOR_RATIO}× floor",
        _verdict(ok_stage),
        "everything before estimation, on the floor's payloads (whole scans), interleaved with it in this process; "
        f"in (a)'s consumer, Ingest.accept took {1e6 * live_accept_s / max(1, live_accepts):.0f} µs a sample "
        f"({live_accepts / live_accept_s if live_accept_s else float('nan'):,.0f}/s while in it)",
    )
    saved = decoding["parsed"] - decoding["fast"]
    table.add_row(
        "(a″) Sample decoding: the stage with the fast path, without it, and a plain upb parse",
        f"{decoding['fast']:.1f} µs/sample with, {decoding['parsed']:.1f} without",
        f"{decoding['parse']:.1f} µs upb parse",
        f"{decoding['fast'] / decoding['parsed']:.2f}×",
        "—",
        "",
        f"the fast path (fastwire: a Sample of an open scan read from its payload, never parsed) saves "
        f"{saved:.1f} µs a sample, {100 * saved / decoding['parsed']:.0f} % of the stage without it (every "
        "payload parsed by upb, the sample placed from the message); same payloads as (a′), medians of 5",
    )
    p50, p99 = _pct(lat_sample, 50), _pct(lat_sample, 99)
    ok_lat_s = p99 <= TARGET_P99_MS
    table.add_row(
        "(b1) latency put → sample processed (handle returned)",
        f"p50 {p50:.1f} / p99 {p99:.1f} ms",
        "",
        "",
        f"p99 ≤ {TARGET_P99_MS:.0f} ms",
        _verdict(ok_lat_s),
        f"{len(lat_sample)} samples: {args.latency_scanners} scanners at {args.rate:g}/s each, "
        f"{args.scans} scans back to back; max {max(lat_sample):.0f} ms",
    )
    q50, q99 = _pct(lat_prov, 50), _pct(lat_prov, 99)
    ok_lat_e = q99 <= TARGET_P99_MS
    table.add_row(
        "(b2) latency put of last_step → provisional estimate published",
        f"p50 {q50:.1f} / p99 {q99:.1f} ms",
        "",
        "",
        f"p99 ≤ {TARGET_P99_MS:.0f} ms",
        _verdict(ok_lat_e),
        f"{len(lat_prov)} estimates (every refit_every steps once the corner is confirmed); "
        f"received by a subscriber: p50 {_pct(e2e_prov, 50):.1f} / p99 {_pct(e2e_prov, 99):.1f} ms",
    )
    table.add_row(
        "(b3) latency put of ScanEnd → final estimate published",
        f"p50 {_pct(lat_final, 50):.0f} / max {max(lat_final, default=float('nan')):.0f} ms",
        "",
        "",
        "—",
        "",
        f"{len(lat_final)} finals ({', '.join((defaults.method, *defaults.compare_methods))}, from scratch); received: "
        f"max {max(e2e_final, default=float('nan')):.0f} ms",
    )
    replay_rate = n_replay / replay_s
    floor_c = n_replay / read_decode_s
    ok_replay = replay_rate >= TARGET_REPLAY and replay_rate >= TARGET_FLOOR_RATIO * floor_c
    table.add_row(
        "(c) MCAP replay, as `reconstruct --source` runs it",
        f"{replay_rate:,.0f} samples/s",
        f"{floor_c:,.0f}/s read+decode",
        f"{replay_rate / floor_c:.2f}×",
        f"≥ {TARGET_REPLAY:,.0f} and ≥ {TARGET_FLOOR_RATIO}× floor",
        _verdict(ok_replay),
        f"{n_replay} samples, {args.scans} scans, {size_mb:.1f} MB zstd; median of {args.replay_runs}; "
        f"{replay_finals} finals ({', '.join((defaults.method, *defaults.compare_methods))}); no provisional "
        "estimates, which the finals do not depend on",
    )
    table.add_row(
        "(c′) replay with provisional estimates (diagnostic)",
        f"{n_replay / replay_prov_s:,.0f} samples/s",
        "",
        f"{n_replay / replay_prov_s / floor_c:.2f}×",
        "—",
        "",
        f"a refit every {defaults.refit_every} steps, as live and `lelsonar review` do",
    )
    table.add_row(
        "(c″) MCAP read + decode + assemble only (diagnostic)",
        f"{n_replay / ingest_s:,.0f} samples/s",
        "",
        f"{n_replay / ingest_s / floor_c:.2f}×",
        "—",
        "",
        "Ingest.accept over iter_payloads: no estimation; the ceiling of (c)",
    )
    console.print(table)
    if profile_stash is not None:
        with tempfile.TemporaryDirectory(prefix="lelsonar-bench-profile-") as tmp:
            p = Path(tmp) / "replay.mcap"
            p.write_bytes(profile_stash[0])
            profile_replay(p, profile_stash[1], console)
    return 0 if (ok_rate and ok_stage and ok_lat_s and ok_lat_e and ok_replay) else 1


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="lelsonar bench ingest")
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    raise SystemExit(main())
