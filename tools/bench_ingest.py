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
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

TARGET_RATE = 1000.0
TARGET_P99_MS = 50.0
TARGET_REPLAY = 3000.0
#: Target: ingest and replay within this share of their floors (decode + validate; read + decode),
#: each floor measured in the same run.
TARGET_FLOOR_RATIO = 0.8
DONE_KEY = "lelsonar-bench/ingest/done"
SAMPLE_TYPE = "lelsonar.v1.Sample"
PREFIX = "lelsonar"
_RESULT = "RESULT "
_READY = "READY"


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
        f"--scanners {args.scanners} --latency-scanners {args.latency_scanners} --preset {args.preset} --fifo {args.fifo} --replay-runs {args.replay_runs}"
        + (" --profile" if args.profile else "")
    )


# --- messages --------------------------------------------------------------------------------
def build_scan(preset_name: str, seed: int = 0):
    """ScanStart, Samples and ScanEnd of one simulated scan, as the acquisition service builds them."""
    from lelsonar.acquire import messages
    from lelsonar.acquire.backends import SimScanner
    from lelsonar.acquire.scan_loop import gamma_schedule
    from lelsonar.sim import preset
    from lelsonar.sim.calibrate import default_energy_model

    sim = preset(preset_name)
    scanner = SimScanner(sim, seed)
    schedule = gamma_schedule(sim.gamma_start, sim.gamma_stop, sim.steps)
    start = messages.scan_start("s0", 1, time.time_ns(), scanner.info, schedule, default_energy_model())
    samples = [
        messages.sample("s0", 1, step, float(g), scanner.measure(step, float(g)), scanner.info)
        for step, g in enumerate(schedule)
    ]
    end = messages.scan_end(
        "s0",
        1,
        time.time_ns(),
        complete=True,
        reason="",
        steps_planned=len(schedule),
        samples_sent=len(schedule),
        echoes_missing=0,
    )
    return start, samples, end


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
        _RESULT
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
        def __init__(self, config: ReconstructConfig = ReconstructConfig()) -> None:
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
            print(_READY, flush=True)
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
        _RESULT
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


# --- the parent: run a phase with two processes ------------------------------------------------
def _child(
    role: str, args: argparse.Namespace, sock: Path, phase: str, timeout: float, stderr_path: Path
) -> subprocess.Popen:
    cmd = [
        sys.executable,
        "-m",
        "lelsonar.tools.bench_ingest",
        "--role",
        role,
        "--socket",
        str(sock),
        "--phase",
        phase,
        "--timeout",
        str(timeout),
        "--preset",
        args.preset,
        "--scans",
        str(args.scans),
        "--seconds",
        str(args.seconds),
        "--rate",
        str(args.rate),
        "--scanners",
        str(args.scanners),
        "--latency-scanners",
        str(args.latency_scanners),
        "--fifo",
        str(args.fifo),
    ]
    with open(stderr_path, "w") as err:
        return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=err, text=True)


class _Lines:
    """Reads a child's stdout lines on a thread, so waits for a line are bounded."""

    def __init__(self, name: str, proc: subprocess.Popen) -> None:
        import queue

        self.name = name
        self.proc = proc
        self._lines: queue.Queue[str | None] = queue.Queue()
        self._thread = threading.Thread(target=self._read, name=f"{name}-stdout", daemon=True)
        self._thread.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self._lines.put(line)
        self._lines.put(None)

    def wait_for(self, prefix: str, deadline: float) -> str:
        """The first line starting with ``prefix``; raises if the child ends or the deadline passes first."""
        import queue

        while True:
            remaining = deadline - time.monotonic()
            try:
                line = self._lines.get(timeout=remaining) if remaining > 0 else None
            except queue.Empty:
                line = None
            if line is None:
                raise RuntimeError(f"no {prefix.strip()!r} line from the {self.name} (exit code {self.proc.poll()})")
            if line.startswith(prefix):
                return line[len(prefix) :]


def run_phase(args: argparse.Namespace, phase: str) -> tuple[dict, dict]:
    """Start a consumer and a publisher on a private socket; return their results."""
    budget = args.seconds + 40.0 if phase == "rate" else (args.scans + 1) * 256 / args.rate + 40.0
    procs: list[subprocess.Popen] = []
    with tempfile.TemporaryDirectory(prefix="lelsonar-bench-ingest-") as tmp:
        tmpdir = Path(tmp)
        sock = tmpdir / "z.sock"
        try:
            consumer = _child("consumer", args, sock, phase, budget, tmpdir / "consumer.err")
            procs.append(consumer)
            consumer_out = _Lines("consumer", consumer)
            consumer_out.wait_for(_READY, time.monotonic() + 60)
            publisher = _child("publisher", args, sock, phase, budget, tmpdir / "publisher.err")
            procs.append(publisher)
            publisher_out = _Lines("publisher", publisher)
            end = time.monotonic() + budget + 20
            pub = json.loads(publisher_out.wait_for(_RESULT, end))
            con = json.loads(consumer_out.wait_for(_RESULT, end))
            for p, name in zip(procs, ("consumer", "publisher")):
                if p.wait(timeout=max(1.0, end - time.monotonic())) != 0:
                    raise RuntimeError(f"the {name} process exited with {p.returncode}")
            return pub, con
        except BaseException:
            for name in ("consumer.err", "publisher.err"):
                text = (tmpdir / name).read_text() if (tmpdir / name).exists() else ""
                if text.strip():
                    print(f"--- {name} ---\n{text[-3000:]}", file=sys.stderr)
            raise
        finally:
            for p in procs:
                if p.poll() is None:
                    p.kill()
                p.wait(timeout=10)
                if p.stdout:
                    p.stdout.close()


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


def time_replay(path: Path, runs: int, **config) -> tuple[float, int]:
    """Median wall time of replay_mcap through a fresh service, and the finals of the last run."""
    from lelsonar.reconstruct.stream.service import ReconstructConfig, ReconstructionService
    from lelsonar.reconstruct.stream.sources import replay_mcap

    times, finals = [], 0
    for _ in range(runs):
        service = ReconstructionService(ReconstructConfig(**config))
        t = time.perf_counter()
        replay_mcap(path, service)
        times.append(time.perf_counter() - t)
        finals = service.stats.finals
    return statistics.median(times), finals


def time_ingest_only(path: Path, runs: int) -> float:
    """Median wall time to read, decode, validate and assemble the recording (no estimation)."""
    from lelsonar.log.recording import iter_payloads
    from lelsonar.reconstruct.stream.ingest import Ingest

    times = []
    for _ in range(runs):
        ingest = Ingest()
        t = time.perf_counter()
        for rec in iter_payloads(path):
            ingest.accept(rec.type_name, rec.payload)
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def time_read_decode(path: Path, runs: int) -> float:
    """Median wall time to read the recording and decode + validate every payload: the replay's floor."""
    from lelsonar import codec
    from lelsonar.log.recording import iter_payloads

    times = []
    for _ in range(runs):
        t = time.perf_counter()
        for rec in iter_payloads(path):
            cls = codec.MESSAGE_TYPES.get(rec.type_name)
            if cls is not None and cls is not codec.Reconstruction:
                codec.decode(rec.payload, cls)
        times.append(time.perf_counter() - t)
    return statistics.median(times)


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


def ingest_stage_vs_floor(preset_name: str, runs: int, n: int = 400) -> tuple[float, float]:
    """Samples/s of (floor) :func:`lelsonar.codec.decode` (parse + every validation) and of (stage)
    :meth:`~lelsonar.reconstruct.stream.ingest.Ingest.accept` — decode, validate, route, assemble: everything the
    service does before estimation — over the same payloads (whole scans, ScanStart to ScanEnd), in this
    process, one run of each per round (medians of ``runs``)."""
    from lelsonar import codec
    from lelsonar.reconstruct.stream.ingest import Ingest

    payloads = ingest_stage_payloads(preset_name, n)
    classes = [codec.MESSAGE_TYPES[name] for name, _ in payloads]
    samples = sum(1 for cls in classes if cls is codec.Sample)
    floor, stage = [], []
    for _ in range(runs):
        t = time.perf_counter()
        for cls, (_, b) in zip(classes, payloads):
            codec.decode(b, cls)
        floor.append(samples / (time.perf_counter() - t))
        ingest = Ingest()
        t = time.perf_counter()
        for name, b in payloads:
            ingest.accept(name, b)
        stage.append(samples / (time.perf_counter() - t))
        if ingest.rejected or ingest.accepted != len(payloads):
            raise RuntimeError(f"the ingest stage refused bench payloads: {dict(ingest.rejected)}")
    return statistics.median(floor), statistics.median(stage)


def profile_replay(path: Path, samples: int, console) -> None:
    """cProfile one replay (the live path's ``handle`` code), then time each final method without the profiler."""
    import cProfile
    import pstats

    from rich.table import Table

    from lelsonar.reconstruct.estimate.pipeline import reconstruct
    from lelsonar.reconstruct.stream.service import ReconstructionService
    from lelsonar.reconstruct.stream.sources import replay_mcap

    prof = cProfile.Profile()
    service = ReconstructionService()
    prof.enable()
    replay_mcap(path, service)
    prof.disable()
    stats = pstats.Stats(prof).stats  # (file, line, func) → (cc, nc, tt, ct, callers)

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

    upd = ("reconstruct/service.py", "_provisional")
    parts = [
        ("replay_mcap (everything)", "reconstruct/sources.py", "replay_mcap", None),
        ("  MCAP read (iter_payloads, zstd)", "lelsonar/recording.py", "iter_payloads", None),
        ("  ingest.accept: decode + assemble", "reconstruct/ingest.py", "accept", None),
        ("    codec.decode (parse + validate)", "lelsonar/codec.py", "decode", None),
        (
            "    ScanAssembly.add (carried energies checked, echo windows cut out)",
            "reconstruct/assembly.py",
            "add",
            None,
        ),
        ("  _provisional (corner check, provisional refit)", *upd, None),
        ("    ScanAssembly.arrays", "reconstruct/assembly.py", "arrays", upd),
        ("    IncrementalPlane.update (provisional planes)", "reconstruct/incremental.py", "update", upd),
        ("  _finalise (after ScanEnd: main + compare methods)", "reconstruct/service.py", "_finalise", None),
        ("    reconstruct (each method, from scratch)", "reconstruct/pipeline.py", "reconstruct", None),
    ]
    whole = cum("reconstruct/sources.py", "replay_mcap")[1] or 1.0
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
        f"in {window:.1f} s (overall {overall:,.0f}/s; 10–90 % window); publisher {pub_a['puts'] / pub_a['put_s']:,.0f} puts/s "
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
    p50, p99 = _pct(lat_sample, 50), _pct(lat_sample, 99)
    ok_lat_s = p99 <= TARGET_P99_MS
    table.add_row(
        "(b1) latency put → sample processed (handle returned)",
        f"p50 {p50:.1f} / p99 {p99:.1f} ms",
        "",
        "",
        f"p99 ≤ {TARGET_P99_MS:.0f} ms",
        _verdict(ok_lat_s),
        f"{len(lat_sample)} samples: {args.latency_scanners} scanners at {args.rate:g}/s each, {args.scans} scans back to back; max {max(lat_sample):.0f} ms",
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
