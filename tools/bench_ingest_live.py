"""``lelsonar bench ingest``, (a) and (b): the publisher and consumer processes, over Zenoh, and their runner.

The consumer runs :class:`~lelsonar.reconstruct.stream.sources.LiveSource` feeding a
:class:`~lelsonar.reconstruct.stream.service.ReconstructionService` that timestamps what it
processes; the publisher puts the simulated scans through the acquisition service's own
:class:`~lelsonar.acquire.scan_loop.ScanPublisher`.  Both are ``python -m lelsonar.tools.bench_ingest
--role ...`` on a private unix socket, started and always reaped by :func:`run_phase`.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

DONE_KEY = "lelsonar-bench/ingest/done"
SAMPLE_TYPE = "lelsonar.v1.Sample"
PREFIX = "lelsonar"
_RESULT = "RESULT "
_READY = "READY"


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
        # zenoh's stub types matching_status as bool; it is a MatchingStatus.
        while not all(p.matching_status.matching for p in probes):  # type: ignore[attr-defined]
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
        for pub in pubs.values():
            pub.close()

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
    from lelsonar.reconstruct.stream.config import ReconstructConfig
    from lelsonar.reconstruct.stream.ingest import Accepted, Ingest
    from lelsonar.reconstruct.stream.service import ReconstructionService

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
            config = config if config is not None else ReconstructConfig()
            super().__init__(config, publish=self._published)
            self.ingest = TimedIngest(limits=config.limits)
            self.forward = None  # e.g. PlanesServer.publish
            self.done_mono: list[float] = []  # per sample: when its handle returned (monotonic s)
            self.sample_latency_ns: list[int] = []  # per sample: handle returned − put
            self.estimate_latency: list[tuple[str, int]] = []
            self.busy: dict[str, list[float]] = {}  # bucket → handle durations, s
            # Each scan's ScanEnd time, kept from its arrival: a final made in a worker process is published
            # after the ingest has let its scan go.
            self.end_ns: dict[tuple[str, int], int] = {}
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
                if isinstance(ev, Accepted) and ev.kind == "end" and ev.scan.end is not None:
                    self.end_ns[(ev.scan.start.scanner_id, ev.scan.start.scan_id)] = ev.scan.end.end_time_ns
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
                ref = self.end_ns.pop((msg.scanner_id, msg.scan_id), None)
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
