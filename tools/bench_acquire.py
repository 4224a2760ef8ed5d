"""``lelsonar bench acquire``: the wall time of a scan against the physical bound.

A scan cannot be faster than its physics: the servo must travel from step to
step, each shot must listen for its acoustic window, and every byte of every
command, status packet and frame must cross its serial link.  The bound is
:func:`lelsonar.acquire.scan_bound.scan_bound` for the emulated rig
(:func:`~lelsonar.acquire.scan_bound.emulated_scan_bound`):

    T_bound = Σ travel + steps × window + link time (AX-12 bus, sensor board) − overlap

with the links of the rig (default: the AX-12 bus at 1 Mbps, the board on USB
full speed, 1.216 MB/s), and as overlap only what the pipelined loop realises:
each move runs while the previous shot's frame crosses the link.  The emulators
pace their bytes at the same rates, so the emulated scan pays the line time a
real one would.  The target is a full scan with the emulated devices (the real
drivers talking byte for byte to the AX-12 and sensor-board emulators on ptys)
within 1.1 × T_bound.

Measured side by side, in one process, each ``--runs`` times (median shown):

* ``emulated`` — :func:`lelsonar.acquire.service.run_acquisition` with
  ``device="emulated"``, pipelined (the default), recording to MCAP, no Zenoh;
* ``emulated+zenoh`` — the same, also publishing as a Zenoh client to a hub on
  a private unix socket (a peer listening, with a counting subscriber, in this
  process);
* ``emulated, sequential`` — ``--no-pipeline``: move, fire, record, one after the
  other, against its own bound (no overlap);
* ``sim`` — the simulator backend (no serial, no waiting), for comparison.

Two wall times: the whole ``run_acquisition`` call (emulator start-up, servo
connect, the scan, finishing the MCAP file) and the scan alone (``ScanStart``
to ``ScanEnd`` stamps).  The verdict uses the whole call.

CPU per sample is ``time.process_time()`` over the call / samples: every thread
of the process, so with ``emulated`` it includes the emulators (they are threads
here, and the sensor-board emulator runs the acoustic simulator for each shot).
It is split into the calling thread (drivers, frame parsing, messages, MCAP;
``time.thread_time()``), the two emulator threads (``/proc/self/task/<tid>/schedstat``,
sampled every 10 ms) and the rest (Zenoh, the progress bar's refresh thread,
the sampler itself).
"""

from __future__ import annotations

import argparse
import io
import os
import statistics
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from lelsonar.errors import InternalError

if TYPE_CHECKING:
    from lelsonar.acquire.scan_bound import ScanBound

TARGET_RATIO = 1.1


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--preset", default="paper-test1", help="simulator preset: scene and schedule (default: %(default)s)"
    )
    parser.add_argument(
        "--runs", type=int, default=3, help="timed runs per backend; medians are reported (default: %(default)s)"
    )
    parser.add_argument("--steps", type=int, default=None, help="override the preset's number of steps")
    parser.add_argument("--seed", type=int, default=0, help="simulator seed (default: %(default)s)")
    parser.add_argument("--no-zenoh", action="store_true", help="skip the emulated+zenoh row")
    parser.add_argument("--no-sequential", action="store_true", help="skip the emulated, sequential row")


def command_line(args: argparse.Namespace) -> str:
    """The exact command that reproduces this run, every option spelled out."""
    parts = ["lelsonar bench acquire", f"--preset {args.preset}", f"--runs {args.runs}", f"--seed {args.seed}"]
    if args.steps is not None:
        parts.append(f"--steps {args.steps}")
    if args.no_zenoh:
        parts.append("--no-zenoh")
    if args.no_sequential:
        parts.append("--no-sequential")
    return " ".join(parts)


# --- the physical bound ------------------------------------------------------------------
def bound_line(bound) -> str:
    """The bound's parts, as the report prints them."""
    b = bound
    return (
        f"{b.total_s:.3f} s = travel {b.travel_units} units (initial move {b.initial_units}) at "
        f"{b.speed_units_s:.0f} units/s (no-load 59 rpm) = {b.travel_s:.3f} s"
        f" + {b.steps} × {b.window_s * 1e3:.1f} ms windows = {b.windows_s:.3f} s"
        f" + sensor link {b.steps} × (FIRE {b.fire_bytes} B + ACQ {b.acq_bytes:,} B) on "
        f"{b.sensor_link.describe()} = {b.sensor_link_s:.3f} s"
        f" + AX-12 bus {b.steps} × {b.move_bus_bytes} B on {b.motor_link.describe()} = {b.motor_link_s:.3f} s"
        + (
            f" − overlap (each move while the previous frame crosses the link) {b.overlap_s:.3f} s"
            if b.pipelined
            else " (no overlap)"
        )
    )


# --- CPU of the emulator threads -----------------------------------------------------------
class ThreadCpuSampler:
    """Samples the on-CPU time of threads whose name ends with ``suffix`` (Linux schedstat, ns)."""

    def __init__(self, suffix: str = "-emulator", period_s: float = 0.01) -> None:
        self._suffix = suffix
        self._period = period_s
        self._stop = threading.Event()
        self._seen: dict[int, tuple[str, int]] = {}
        self._thread = threading.Thread(target=self._run, name="bench-cpu-sampler", daemon=True)
        self.available = Path("/proc/self/task").is_dir()

    def __enter__(self) -> ThreadCpuSampler:
        if self.available:
            self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        if self.available:
            self._thread.join(timeout=2)

    def _run(self) -> None:
        while True:
            self._sample()
            if self._stop.wait(self._period):
                self._sample()
                return

    def _sample(self) -> None:
        for t in threading.enumerate():
            if not t.name.endswith(self._suffix) or t.native_id is None:
                continue
            try:
                with open(f"/proc/self/task/{t.native_id}/schedstat") as f:
                    ns = int(f.read().split()[0])
            except (OSError, ValueError, IndexError):
                continue  # the thread just ended
            self._seen[t.native_id] = (t.name, max(ns, self._seen.get(t.native_id, ("", 0))[1]))

    @property
    def seconds(self) -> float:
        return sum(ns for _, ns in self._seen.values()) / 1e9


def host_busy(seconds: float = 0.5) -> float | None:
    """Fraction of the host's CPU time that was busy over ``seconds`` (from /proc/stat), before a bench starts.

    The load average lags by a minute; this says whether a neighbour is running now.
    """

    def snap() -> tuple[int, int]:
        with open("/proc/stat") as f:
            v = [int(x) for x in f.readline().split()[1:]]
        idle = v[3] + (v[4] if len(v) > 4 else 0)
        return sum(v[:8]), idle

    try:
        t0, i0 = snap()
        time.sleep(seconds)
        t1, i1 = snap()
    except (OSError, ValueError, IndexError):
        return None
    return 1.0 - (i1 - i0) / (t1 - t0) if t1 > t0 else None


def host_line(busy: float | None) -> str:
    if busy is None:
        return "host CPU busy before the run: unknown"
    warn = " [red](a neighbour is running: numbers are pessimistic)[/]" if busy > 0.15 else ""
    return f"host CPU busy before the run: {100 * busy:.0f} % of {os.cpu_count()} cores{warn}"


# --- where the time over the bound goes --------------------------------------------------
def component_run(args: argparse.Namespace) -> tuple[float, float, int]:
    """The two devices alone, through the same drivers and emulators as a scan: every move of the
    schedule back to back, then every FIRE back to back.  Returns (moves s, fires s, steps)."""
    from lelsonar.acquire.backends import DeviceScanner, open_scanner
    from lelsonar.acquire.config import AcquireConfig
    from lelsonar.acquire.scan_loop import gamma_schedule
    from lelsonar.acquire.service import sim_config

    cfg = AcquireConfig(device="emulated", preset=args.preset, steps=args.steps, seed=args.seed, record=False)
    sim = sim_config(cfg)
    schedule = gamma_schedule(sim.gamma_start, sim.gamma_stop, sim.steps)
    with open_scanner(cfg, sim) as scanner:
        if not isinstance(scanner, DeviceScanner):
            raise InternalError(f"--device {cfg.device} opened no drivers to time apart")
        t = time.perf_counter()
        for gamma in schedule:
            scanner.motor.move_to(float(gamma))
        moves = time.perf_counter() - t
        t = time.perf_counter()
        for step in range(len(schedule)):
            scanner.board.fire(step)
        fires = time.perf_counter() - t
    return moves, fires, len(schedule)


# --- one run -------------------------------------------------------------------------------
@dataclass
class RunResult:
    call_s: float
    scan_s: float
    samples: int
    cpu_s: float
    main_cpu_s: float
    emulator_cpu_s: float
    delivered: int | None = None


@dataclass
class Row:
    label: str
    bound: ScanBound | None
    pipeline: bool = True
    zenoh: bool = False
    results: list[RunResult] = field(default_factory=list)

    def median(self, name: str) -> float:
        return statistics.median(getattr(r, name) for r in self.results)


def _scan_start_ns(path: Path) -> int:
    from lelsonar import codec
    from lelsonar.log.recording import iter_payloads

    payloads = iter_payloads(path)
    try:
        for rec in payloads:
            if rec.type_name == codec.ScanStart.DESCRIPTOR.full_name:
                return codec.decode(rec.payload, codec.ScanStart).start_time_ns
    finally:
        payloads.close()
    raise RuntimeError(f"no ScanStart in {path}")


def one_run(
    device: str, args: argparse.Namespace, *, zenoh_pub: bool = False, steps: int | None = None, pipeline: bool = True
) -> RunResult:
    """One full scan through run_acquisition, recorded to a temporary MCAP file."""
    from contextlib import ExitStack

    from rich.console import Console

    from lelsonar.acquire.config import AcquireConfig
    from lelsonar.acquire.service import run_acquisition
    from lelsonar.keys import ScannerKeys
    from lelsonar.net.transport import hermetic_settings, open_session

    with tempfile.TemporaryDirectory(prefix="lelsonar-bench-acquire-") as tmp, ExitStack() as stack:
        cfg = AcquireConfig(
            device=device,
            preset=args.preset,
            steps=steps if steps is not None else args.steps,
            serve_log_for=0.0,
            pipeline=pipeline,
            seed=args.seed,
            record=True,
            out_dir=Path(tmp),
        )
        quiet = Console(file=io.StringIO(), width=120)
        delivered = [0]
        settings = None
        if zenoh_pub:
            # The hub: a peer listening on a private unix socket, with a counting subscriber;
            # the acquisition connects to it as a client, as it would to a router.
            sock = Path(tmp) / "z.sock"
            hub = stack.enter_context(open_session(hermetic_settings(sock, listen=True)))
            sub = hub.declare_subscriber(
                ScannerKeys(cfg.prefix, "*").sample, lambda _s: delivered.__setitem__(0, delivered[0] + 1)
            )
            stack.callback(sub.undeclare)
            settings = hermetic_settings(sock, listen=False)
        with ThreadCpuSampler() as sampler:
            t_wall = time.perf_counter()
            c_proc = time.process_time()
            c_main = time.thread_time()
            report = run_acquisition(cfg, settings, threading.Event(), console=quiet)
            call_s = time.perf_counter() - t_wall
            cpu = time.process_time() - c_proc
            main_cpu = time.thread_time() - c_main
        if not report.ok:
            raise RuntimeError(f"{device} scan failed: {[e.reason for e in report.ends]}")
        end = report.ends[-1]
        if zenoh_pub:  # let the last samples land before the hub closes (bounded)
            deadline = time.monotonic() + 2.0
            while delivered[0] < end.samples_sent and time.monotonic() < deadline:
                time.sleep(0.005)
        scan_s = (end.end_time_ns - _scan_start_ns(report.paths[-1])) / 1e9
        return RunResult(
            call_s=call_s,
            scan_s=scan_s,
            samples=end.samples_sent,
            cpu_s=cpu,
            main_cpu_s=main_cpu,
            emulator_cpu_s=sampler.seconds,
            delivered=delivered[0] if zenoh_pub else None,
        )


# --- the benchmark -------------------------------------------------------------------------
def run(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.table import Table

    from lelsonar.acquire.config import AcquireConfig
    from lelsonar.acquire.scan_bound import emulated_scan_bound
    from lelsonar.errors import ConfigError
    from lelsonar.tools.bench import machine, progress

    if args.runs < 1:
        raise ConfigError(f"--runs must be >= 1, got {args.runs}")
    console = Console(width=max(Console().width, 170))
    cfg = AcquireConfig(device="emulated", preset=args.preset, steps=args.steps, seed=args.seed)
    bound = emulated_scan_bound(cfg, pipelined=True)
    sequential = emulated_scan_bound(cfg, pipelined=False)
    busy = host_busy()

    # Warm-up: imports, first-touch allocations, the simulator's caches (a short emulated scan).
    one_run("emulated", args, steps=4)
    one_run("sim", args, steps=4)

    rows = (
        [Row("emulated", bound)]
        + ([] if args.no_zenoh else [Row("emulated+zenoh", bound, zenoh=True)])
        + ([] if args.no_sequential else [Row("emulated, sequential", sequential, pipeline=False)])
        + [Row("sim", None)]
    )
    components = []
    for _ in progress(range(args.runs), "runs"):  # interleaved, so drift hits every backend alike
        for row in rows:
            device = "sim" if row.label == "sim" else "emulated"
            row.results.append(one_run(device, args, zenoh_pub=row.zenoh, pipeline=row.pipeline))
        components.append(component_run(args))

    console.print(
        f"[bold]lelsonar bench acquire[/] — preset {args.preset}, {bound.steps} steps, "
        f"{args.runs} runs per backend (median; min–max)"
    )
    console.print(f"machine: {machine()}; {host_line(busy)}")
    console.print(f"command: {command_line(args)}")
    console.print(f"physical bound, pipelined: {bound_line(bound)}", highlight=False)
    console.print(f"physical bound, sequential: {bound_line(sequential)}", highlight=False)

    table = Table(
        title=f"Scan wall time vs the physical bound {bound.total_s:.3f} s (target ≤ {TARGET_RATIO:.2f}×; "
        f"sequential: vs {sequential.total_s:.3f} s); CPU per sample by thread"
    )
    cols = (
        "backend",
        "call s",
        "min–max s",
        "scan s",
        "call/bound",
        "scan/bound",
        "verdict",
        "ms/step over",
        "CPU ms/smp",
        "calling thr.",
        "emulators",
        "other",
        "delivered",
    )
    for col in cols:
        table.add_column(col, justify="left" if col in ("backend", "verdict") else "right", no_wrap=True)
    status = 0
    for row in rows:
        call, scan = row.median("call_s"), row.median("scan_s")
        samples = row.results[0].samples
        lo, hi = min(r.call_s for r in row.results), max(r.call_s for r in row.results)
        per = lambda name, row=row, samples=samples: 1e3 * row.median(name) / samples  # noqa: E731
        other = [1e3 * (r.cpu_s - r.main_cpu_s - r.emulator_cpu_s) / samples for r in row.results]
        if row.bound is None:
            ratio_call = ratio_scan = verdict = over = "—"
        else:
            total = row.bound.total_s
            ok = call / total <= TARGET_RATIO
            status |= 0 if ok or row.label != "emulated" else 1
            ratio_call, ratio_scan = f"{call / total:.3f}", f"{scan / total:.3f}"
            verdict = "[green]PASS[/]" if ok else "[red]MISS[/]"
            over = f"{1e3 * (scan - total) / samples:.2f}"
        counts = [r.delivered for r in row.results if r.delivered is not None]
        delivered = f"{min(counts)}/{samples}" if counts else "—"
        table.add_row(
            row.label,
            f"{call:.3f}",
            f"{lo:.2f}–{hi:.2f}",
            f"{scan:.3f}",
            ratio_call,
            ratio_scan,
            verdict,
            over,
            f"{per('cpu_s'):.2f}",
            f"{per('main_cpu_s'):.2f}",
            "—" if row.label == "sim" else f"{per('emulator_cpu_s'):.2f}",
            f"{statistics.median(other):.2f}",
            delivered,
        )
    console.print(table)

    # Where the scan's time over the bound goes, per step (medians).
    moves = statistics.median(c[0] for c in components)
    fires = statistics.median(c[1] for c in components)
    n = components[0][2]
    scan = rows[0].median("scan_s")
    moves_bound = bound.travel_s + bound.motor_link_s
    fires_bound = bound.windows_s + bound.sensor_link_s
    over_total = scan - bound.total_s
    over_fire = fires - fires_bound
    parts = Table(
        title="Where the emulated scan's time over the bound goes (per step; the devices alone, "
        "same drivers and emulators)"
    )
    for col in ("part", "measured s", "bound s", "ratio", "over, ms/step"):
        parts.add_column(col, justify="left" if col == "part" else "right", no_wrap=True)
    parts.add_row(
        f"{n} × fire (FIRE, window, ACQ over the link), back to back",
        f"{fires:.3f}",
        f"{fires_bound:.3f}",
        f"{fires / fires_bound:.2f}",
        f"{1e3 * over_fire / n:.2f}",
    )
    parts.add_row(
        f"{n} × move_to (bus, travel), back to back; pipelined, each but the first is under a frame",
        f"{moves:.3f}",
        f"{moves_bound:.3f}",
        f"{moves / moves_bound:.2f}",
        f"{1e3 * (moves - moves_bound) / n:.2f}",
    )
    parts.add_row(
        "rest of the pipelined scan (loop, moves the frames did not hide; by difference)",
        "",
        "",
        "",
        f"{1e3 * (over_total - over_fire) / n:.2f}",
    )
    parts.add_row(
        "whole scan (emulated, ScanStart → ScanEnd)",
        f"{scan:.3f}",
        f"{bound.total_s:.3f}",
        f"{scan / bound.total_s:.2f}",
        f"{1e3 * over_total / n:.2f}",
    )
    console.print(parts)
    console.print(
        "call s: the whole run_acquisition call (emulator start-up, servo connect, scan, MCAP finish); "
        "scan s: ScanStart → ScanEnd stamps; verdict on call/bound for the emulated rows, each against its own bound. "
        "CPU ms/sample = process_time / samples, all threads: calling thread (drivers, frame parsing, messages, "
        "MCAP zstd) + emulator threads (AX-12 and sensor board, incl. the acoustic simulator per shot; "
        "schedstat, 10 ms sampling) + other (Zenoh, progress refresh, sampler). "
        f"sim: {row_summary(rows[-1])}."
    )
    return status


def row_summary(row: Row) -> str:
    scan = row.median("scan_s")
    return f"{scan:.3f} s per scan ({1e3 * scan / row.results[0].samples:.2f} ms/step), no serial and no waiting"


if __name__ == "__main__":  # pragma: no cover - `lelsonar bench acquire` is the entry point
    p = argparse.ArgumentParser(prog="lelsonar bench acquire")
    add_arguments(p)
    raise SystemExit(run(p.parse_args()))
