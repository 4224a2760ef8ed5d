"""``lelsonar bench acquire``: the wall time of a scan against the physical bound (issue 5).

A scan cannot be faster than its physics: the servo must travel from step to
step and each shot must listen for its acoustic window.  The bound is

    T_bound = Σ |Δraw| / v  +  steps × window_samples / sample_rate

with ``Δraw`` the position units between consecutive goals (plus the move from
the power-on position to the first goal), ``v`` the AX-12 speed at the
configured Moving Speed (0 = the no-load 59 rpm, :mod:`lelsonar.acquire.devices.ax12`,
the emulator's motion model), and the window of the preset.  The target is a
full scan with the emulated devices (the real drivers talking byte for byte
to the AX-12 and sensor-board emulators on ptys) within 1.25 × T_bound.

Measured side by side, in one process, each ``--runs`` times (median shown):

* ``emulated`` — :func:`lelsonar.acquire.service.run_acquisition` with
  ``device="emulated"``, recording to MCAP, no Zenoh;
* ``emulated+zenoh`` — the same, also publishing as a Zenoh client to a hub on
  a private unix socket (a peer listening, with a counting subscriber, in this
  process);
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

TARGET_RATIO = 1.25


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--preset", default="paper-test1", help="simulator preset: scene and schedule (default: %(default)s)")
    parser.add_argument("--runs", type=int, default=3, help="timed runs per backend; medians are reported (default: %(default)s)")
    parser.add_argument("--steps", type=int, default=None, help="override the preset's number of steps")
    parser.add_argument("--seed", type=int, default=0, help="simulator seed (default: %(default)s)")
    parser.add_argument("--no-zenoh", action="store_true", help="skip the emulated+zenoh row")


def command_line(args: argparse.Namespace) -> str:
    """The exact command that reproduces this run, every option spelled out."""
    parts = ["lelsonar bench acquire", f"--preset {args.preset}", f"--runs {args.runs}", f"--seed {args.seed}"]
    if args.steps is not None:
        parts.append(f"--steps {args.steps}")
    if args.no_zenoh:
        parts.append("--no-zenoh")
    return " ".join(parts)


# --- the physical bound ------------------------------------------------------------------
@dataclass(frozen=True)
class Bound:
    steps: int
    travel_units: int
    initial_units: int
    speed_units_s: float
    window_s: float

    @property
    def travel_s(self) -> float:
        return self.travel_units / self.speed_units_s

    @property
    def windows_s(self) -> float:
        return self.steps * self.window_s

    @property
    def total_s(self) -> float:
        return self.travel_s + self.windows_s


def physical_bound(cfg) -> Bound:
    """Motor travel at the configured speed plus every step's acoustic window, for ``cfg`` (an AcquireConfig)."""
    from lelsonar.acquire.devices import ax12
    from lelsonar.acquire.emulate.ax12_emulator import AX12EmulatorConfig
    from lelsonar.acquire.scan_loop import gamma_schedule
    from lelsonar.acquire.service import sim_config

    sim = sim_config(cfg)
    schedule = gamma_schedule(sim.gamma_start, sim.gamma_stop, sim.steps)
    # As open_scanner sets them up: the driver's zero and the emulator's power-on position.
    zero_raw = int(sim.servo.to_raw(0.0))
    initial = int(sim.servo.to_raw(sim.gamma_start))
    goals = [min(ax12.POSITION_MAX, max(0, ax12.raw_from_gamma(float(g), zero_raw))) for g in schedule]
    first = abs(goals[0] - initial)
    units = first + sum(abs(b - a) for a, b in zip(goals, goals[1:]))
    # AcquireConfig.motor_speed is rad/s with 0 = maximum; the driver writes Moving Speed 0 (no-load speed).
    speed = ax12.speed_units_per_s(0, AX12EmulatorConfig().no_load_rpm)
    return Bound(steps=len(schedule), travel_units=units, initial_units=first, speed_units_s=speed,
                 window_s=sim.window_samples / sim.sample_rate)


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
    from lelsonar.acquire.backends import open_scanner
    from lelsonar.acquire.config import AcquireConfig
    from lelsonar.acquire.scan_loop import gamma_schedule
    from lelsonar.acquire.service import sim_config

    cfg = AcquireConfig(device="emulated", preset=args.preset, steps=args.steps, seed=args.seed, record=False)
    sim = sim_config(cfg)
    schedule = gamma_schedule(sim.gamma_start, sim.gamma_stop, sim.steps)
    with open_scanner(cfg, sim) as scanner:
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
    results: list[RunResult] = field(default_factory=list)

    def median(self, name: str) -> float:
        return statistics.median(getattr(r, name) for r in self.results)


def _scan_start_ns(path: Path) -> int:
    from lelsonar import codec
    from lelsonar.recording import iter_payloads

    payloads = iter_payloads(path)
    try:
        for rec in payloads:
            if rec.type_name == codec.ScanStart.DESCRIPTOR.full_name:
                return codec.decode(rec.payload, codec.ScanStart).start_time_ns
    finally:
        payloads.close()
    raise RuntimeError(f"no ScanStart in {path}")


def one_run(device: str, args: argparse.Namespace, *, zenoh_pub: bool = False, steps: int | None = None) -> RunResult:
    """One full scan through run_acquisition, recorded to a temporary MCAP file."""
    from contextlib import ExitStack

    from rich.console import Console

    from lelsonar.acquire.config import AcquireConfig
    from lelsonar.acquire.service import run_acquisition
    from lelsonar.keys import ScannerKeys
    from lelsonar.transport import hermetic_settings, open_session

    with tempfile.TemporaryDirectory(prefix="lelsonar-bench-acquire-") as tmp, ExitStack() as stack:
        cfg = AcquireConfig(device=device, preset=args.preset, steps=steps if steps is not None else args.steps,
                            serve_log_for=0.0,
                            seed=args.seed, record=True, out_dir=Path(tmp))
        quiet = Console(file=io.StringIO(), width=120)
        delivered = [0]
        settings = None
        if zenoh_pub:
            # The hub: a peer listening on a private unix socket, with a counting subscriber;
            # the acquisition connects to it as a client, as it would to a router.
            sock = Path(tmp) / "z.sock"
            hub = stack.enter_context(open_session(hermetic_settings(sock, listen=True)))
            sub = hub.declare_subscriber(ScannerKeys(cfg.prefix, "*").sample,
                                         lambda _s: delivered.__setitem__(0, delivered[0] + 1))
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
        return RunResult(call_s=call_s, scan_s=scan_s, samples=end.samples_sent, cpu_s=cpu, main_cpu_s=main_cpu,
                         emulator_cpu_s=sampler.seconds, delivered=delivered[0] if zenoh_pub else None)


# --- the benchmark -------------------------------------------------------------------------
def run(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.table import Table

    from lelsonar.acquire.config import AcquireConfig
    from lelsonar.errors import ConfigError
    from lelsonar.tools.bench import machine, progress

    if args.runs < 1:
        raise ConfigError(f"--runs must be >= 1, got {args.runs}")
    console = Console(width=max(Console().width, 170))
    cfg = AcquireConfig(device="emulated", preset=args.preset, steps=args.steps, seed=args.seed)
    bound = physical_bound(cfg)
    busy = host_busy()

    # Warm-up: imports, first-touch allocations, the simulator's caches (a short emulated scan).
    one_run("emulated", args, steps=4)
    one_run("sim", args, steps=4)

    rows = [Row("emulated")] + ([] if args.no_zenoh else [Row("emulated+zenoh")]) + [Row("sim")]
    components = []
    for _ in progress(range(args.runs), "runs"):  # interleaved, so drift hits every backend alike
        for row in rows:
            device = "sim" if row.label == "sim" else "emulated"
            row.results.append(one_run(device, args, zenoh_pub=row.label.endswith("zenoh")))
        components.append(component_run(args))

    console.print(f"[bold]lelsonar bench acquire[/] — preset {args.preset}, {bound.steps} steps, "
                  f"{args.runs} runs per backend (median; min–max)")
    console.print(f"machine: {machine()}; {host_line(busy)}")
    console.print(f"command: {command_line(args)}")
    console.print(
        f"physical bound {bound.total_s:.3f} s = travel {bound.travel_units} units "
        f"(initial move {bound.initial_units}) at {bound.speed_units_s:.0f} units/s (no-load 59 rpm) "
        f"= {bound.travel_s:.3f} s + {bound.steps} × {bound.window_s * 1e3:.1f} ms windows = {bound.windows_s:.3f} s")

    table = Table(title=f"Scan wall time vs the physical bound {bound.total_s:.3f} s (target ≤ {TARGET_RATIO:.2f}×); "
                        f"CPU per sample by thread")
    cols = ("backend", "call s", "min–max s", "scan s", "call/bound", "scan/bound", "verdict", "ms/step over",
            "CPU ms/smp", "calling thr.", "emulators", "other", "delivered")
    for col in cols:
        table.add_column(col, justify="left" if col in ("backend", "verdict") else "right", no_wrap=True)
    status = 0
    for row in rows:
        call, scan = row.median("call_s"), row.median("scan_s")
        samples = row.results[0].samples
        lo, hi = min(r.call_s for r in row.results), max(r.call_s for r in row.results)
        per = lambda name: 1e3 * row.median(name) / samples  # noqa: E731
        other = [1e3 * (r.cpu_s - r.main_cpu_s - r.emulator_cpu_s) / samples for r in row.results]
        if row.label == "sim":
            ratio_call = ratio_scan = verdict = over = "—"
        else:
            ok = call / bound.total_s <= TARGET_RATIO
            status |= 0 if ok or row.label != "emulated" else 1
            ratio_call, ratio_scan = f"{call / bound.total_s:.3f}", f"{scan / bound.total_s:.3f}"
            verdict = "[green]PASS[/]" if ok else "[red]MISS[/]"
            over = f"{1e3 * (scan - bound.total_s) / samples:.2f}"
        delivered = "—" if row.results[0].delivered is None else \
            f"{min(r.delivered for r in row.results)}/{samples}"
        table.add_row(
            row.label, f"{call:.3f}", f"{lo:.2f}–{hi:.2f}", f"{scan:.3f}", ratio_call, ratio_scan, verdict, over,
            f"{per('cpu_s'):.2f}", f"{per('main_cpu_s'):.2f}",
            "—" if row.label == "sim" else f"{per('emulator_cpu_s'):.2f}", f"{statistics.median(other):.2f}",
            delivered)
    console.print(table)

    # Where the scan's time over the bound goes, per step (medians).
    moves = statistics.median(c[0] for c in components)
    fires = statistics.median(c[1] for c in components)
    n = components[0][2]
    scan = rows[0].median("scan_s")
    over_total = scan - bound.total_s
    over_move = moves - bound.travel_s
    over_fire = fires - bound.windows_s
    parts = Table(title="Where the emulated scan's time over the bound goes (per step; the devices alone, "
                        "same drivers and emulators)")
    for col in ("part", "measured s", "bound s", "ratio", "over, ms/step"):
        parts.add_column(col, justify="left" if col == "part" else "right", no_wrap=True)
    parts.add_row(f"{n} × move_to, back to back (travel)", f"{moves:.3f}", f"{bound.travel_s:.3f}",
                  f"{moves / bound.travel_s:.2f}", f"{1e3 * over_move / n:.2f}")
    parts.add_row(f"{n} × fire, back to back (acoustic windows)", f"{fires:.3f}", f"{bound.windows_s:.3f}",
                  f"{fires / bound.windows_s:.2f}", f"{1e3 * over_fire / n:.2f}")
    parts.add_row("rest of the scan loop (messages, MCAP, progress; by difference)", "", "", "",
                  f"{1e3 * (over_total - over_move - over_fire) / n:.2f}")
    parts.add_row("whole scan (emulated, ScanStart → ScanEnd)", f"{scan:.3f}", f"{bound.total_s:.3f}",
                  f"{scan / bound.total_s:.2f}", f"{1e3 * over_total / n:.2f}")
    console.print(parts)
    console.print(
        "call s: the whole run_acquisition call (emulator start-up, servo connect, scan, MCAP finish); "
        "scan s: ScanStart → ScanEnd stamps; verdict on call/bound for the emulated rows. "
        "CPU ms/sample = process_time / samples, all threads: calling thread (drivers, frame parsing, messages, "
        "MCAP zstd) + emulator threads (AX-12 and sensor board, incl. the acoustic simulator per shot; "
        "schedstat, 10 ms sampling) + other (Zenoh, progress refresh, sampler). "
        f"sim: {row_summary(rows[-1])}.")
    return status


def row_summary(row: Row) -> str:
    scan = row.median("scan_s")
    return f"{scan:.3f} s per scan ({1e3 * scan / row.results[0].samples:.2f} ms/step), no serial and no waiting"


if __name__ == "__main__":  # pragma: no cover - `lelsonar bench acquire` is the entry point
    p = argparse.ArgumentParser(prog="lelsonar bench acquire")
    add_arguments(p)
    raise SystemExit(run(p.parse_args()))
