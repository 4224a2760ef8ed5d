"""``lelsonar bench fleet``: N scanners, W reconstructors in one group, through a Zenoh router.

Processes, all ``python -m lelsonar ...`` children started and always reaped here:

- a router (``lelsonar router``) on a private unix socket;
- W workers, each wired as ``lelsonar reconstruct --group fleet`` wires itself
  (:class:`~lelsonar.reconstruct.stream.group.GroupMembership`,
  :class:`~lelsonar.reconstruct.stream.sources.LiveSource`,
  :class:`~lelsonar.reconstruct.stream.sources.PlanesServer`, the default
  :class:`~lelsonar.reconstruct.stream.config.ReconstructConfig`, provisional
  estimates on), plus a probe that timestamps what they process
  (:mod:`lelsonar.tools.bench_fleet_worker`);
- ``--publishers`` processes (default one per 25 scanners) sharing the N scanners
  (:mod:`lelsonar.tools.bench_fleet_publisher`): each scanner has a served
  :class:`~lelsonar.acquire.log_server.ScanLog` and its
  :class:`~lelsonar.acquire.log_server.LogServer`, and puts real simulated ``Sample``
  payloads (:mod:`lelsonar.sim`, encoded once, a header joined per put) at ``--rate`` Hz
  with congestion control BLOCK, the scanners' phases spread over the period, on one
  schedule for all the processes.  Each ``acquisition_time_ns`` is the wall clock just
  before its put;
- this process: subscribes to ``<prefix>/*/planes`` and counts terminal
  estimates per scan (duplicates, incomplete).

Reported: handled samples/s (live samples processed by all workers over the
time from the first put to the last processed), p50/p99 put → processed
(``handle`` returned) and put → provisional estimate published (of the sample
named by its ``last_step``), incomplete / duplicated / missing finals, CPU per
worker (user + system over its wall time), CPU of each process while busy (a worker from its first
live sample to its last, read at most every 10 ms, the publisher over its puts, the router
meanwhile), how far the publishers fell behind their schedule (a run where they fell behind on
their own is invalid: the offered rate was not offered; behind because BLOCK held their puts, the
workers did not keep up), and each worker's CPU per sample inside ``handle``, inside ``tick`` and
outside them, with the provisional refits' cost by the steps the scan held.  The offered rate is scanners ×
``--rate``: a run shows whether the workers keep up with it, not how far beyond it they could go;
``--capacity`` finds that (:mod:`lelsonar.tools.bench_fleet_capacity`).  ``--failover`` (default on
with W ≥ 2) runs the same again and SIGKILLs one worker in the middle of the first scans: every
scan must still get exactly one complete final.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

from lelsonar.tools.bench_fleet_capacity import CAPACITY_LADDER, run_capacity
from lelsonar.tools.bench_fleet_publisher import GO, READY, RESULT, check_encoding, combine, parts, publisher_main
from lelsonar.tools.bench_fleet_stages import STALL_MS, run_stages
from lelsonar.tools.bench_fleet_worker import PREFIX, client_settings, worker_main

_READY, _RESULT = READY, RESULT


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scanners", type=int, default=10, help="simulated scanners (default: %(default)s)")
    parser.add_argument("--workers", type=int, default=2, help="reconstructors in the group (default: %(default)s)")
    parser.add_argument("--rate", type=float, default=50.0, help="samples/s per scanner (default: %(default)s)")
    parser.add_argument("--scans", type=int, default=2, help="scans per scanner (default: %(default)s)")
    parser.add_argument(
        "--steps", type=int, default=0, help="steps per scan (default: the preset's, 184 for paper-test1)"
    )
    parser.add_argument("--preset", default="paper-test1", help="simulator preset (default: %(default)s)")
    parser.add_argument(
        "--failover",
        choices=("auto", "on", "off", "only"),
        default="auto",
        help="also run the case where one worker is SIGKILLed mid-scan (auto: when --workers >= 2; "
        "only: that case alone)",
    )
    parser.add_argument("--no-provisional", action="store_true", help="workers publish finals only")
    parser.add_argument(
        "--timeout",
        type=float,
        default=180.0,
        help="s to wait for the finals after the last put (default: %(default)s)",
    )
    parser.add_argument(
        "--repeat",
        type=int,
        default=1,
        help="runs per case; the table shows medians, and sums for incomplete and duplicated finals "
        "(default: %(default)s)",
    )
    parser.add_argument("--json", type=Path, metavar="OUT", help="also write the results as JSON (every run)")
    parser.add_argument(
        "--capacity",
        type=int,
        nargs="*",
        metavar="N",
        default=None,
        help="find one reconstructor's capacity instead: N scanners × --rate for each N, rising, until one does "
        f"not hold (no N given: {' '.join(str(n) for n in CAPACITY_LADDER)})",
    )
    parser.add_argument(
        "--stages",
        action="store_true",
        help="where one reconstructor's time goes instead: --scanners × --scans scans through one service in "
        "this process, without Zenoh, CPU per sample by stage (ingest, provisional update, exact fits, final)",
    )
    parser.add_argument("--markdown", type=Path, default=None, help="also write the tables to this Markdown file")
    parser.add_argument(
        "--publishers",
        type=int,
        default=0,
        help="publisher processes the scanners are spread over (default: one per 25 scanners)",
    )
    # Internal: the child processes.
    parser.add_argument("--role", choices=("worker", "publisher"), help=argparse.SUPPRESS)
    parser.add_argument("--part", type=int, default=0, help=argparse.SUPPRESS)
    parser.add_argument("--parts", type=int, default=1, help=argparse.SUPPRESS)
    parser.add_argument("--endpoint", help=argparse.SUPPRESS)
    parser.add_argument("--member", help=argparse.SUPPRESS)


def command_line(args: argparse.Namespace) -> str:
    # --capacity sets the scanners, one worker and no failover itself: only what it reads is shown.
    ladder = args.capacity is not None
    return (
        "lelsonar bench fleet "
        + ("" if ladder else f"--scanners {args.scanners} --workers {args.workers} ")
        + f"--rate {args.rate:g} --scans {args.scans}"
        + (f" --steps {args.steps}" if args.steps else "")
        + (f" --repeat {args.repeat}" if args.repeat > 1 else "")
        + (f" --publishers {args.publishers}" if args.publishers > 0 else "")
        + f" --preset {args.preset}"
        + ("" if ladder else f" --failover {args.failover}")
        + (" --no-provisional" if args.no_provisional else "")
        + (f" --capacity {' '.join(str(n) for n in args.capacity)}" if args.capacity else "")
        + (" --capacity" if args.capacity == [] else "")
    )


def _pct(values: list[float], q: float) -> float | None:
    if not values:
        return None
    v = sorted(values)
    return v[min(len(v) - 1, int(round(q / 100 * (len(v) - 1))))]


# --- the orchestration -----------------------------------------------------------------------
def _proc_cpu_s(pid: int) -> float | None:
    """CPU (user + system) a process has used so far, from /proc (None where there is no /proc)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None


def _child(args: list[str], stdin=None) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "lelsonar", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        stdin=stdin,
        text=True,
    )


def _read_tagged(proc: subprocess.Popen, tag: str, timeout: float) -> dict | None:
    """The JSON after ``tag`` on the child's stdout (other lines skipped); None if it ends first."""
    result: list = []

    def read() -> None:
        assert proc.stdout is not None  # every child is started with stdout=PIPE
        for line in proc.stdout:
            if line.startswith(tag):
                result.append(json.loads(line[len(tag) :]))
                return

    t = threading.Thread(target=read, daemon=True)
    t.start()
    t.join(timeout)
    return result[0] if result else None


def run_case(args: argparse.Namespace, *, kill_one: bool, progress=None) -> dict[str, Any]:
    import zenoh

    from lelsonar import codec
    from lelsonar.net.transport import ZenohSettings, open_session
    from lelsonar.reconstruct.estimate import wire

    procs: list[subprocess.Popen] = []
    bench = [
        "bench",
        "fleet",
        "--scanners",
        str(args.scanners),
        "--workers",
        str(args.workers),
        "--rate",
        str(args.rate),
        "--scans",
        str(args.scans),
        "--steps",
        str(args.steps),
        "--preset",
        args.preset,
    ] + (["--no-provisional"] if args.no_provisional else [])
    finals: dict[tuple[str, int], list[str]] = {}
    lock = threading.Lock()
    got = threading.Condition(lock)
    with tempfile.TemporaryDirectory(prefix="lelsonar-fleet-") as tmp:
        endpoint = f"unixsock-stream/{tmp}/router.sock"
        try:
            router = _child(["router", "--listen", endpoint])
            procs.append(router)
            assert router.stdout is not None  # started with stdout=PIPE
            if "listening" not in (router.stdout.readline() or ""):
                raise SystemExit("bench fleet: the router did not start")
            with open_session(ZenohSettings(mode="client", connect=(endpoint,))) as session:

                def on_planes(sample: zenoh.Sample) -> None:
                    msg = codec.Reconstruction.FromString(sample.payload.to_bytes())
                    if wire.is_terminal(msg):
                        with got:
                            finals.setdefault((msg.scanner_id, msg.scan_id), []).append(
                                f"{wire.status_name(msg)}:{len(msg.missing_steps)}"
                            )
                            got.notify_all()

                sub = session.declare_subscriber(f"{PREFIX}/*/planes", on_planes)
                workers = [
                    _child(bench + ["--role", "worker", "--endpoint", endpoint, "--member", f"w{i}"])
                    for i in range(args.workers)
                ]
                procs += workers
                for w in workers:
                    if _read_tagged(w, _READY, 90) is None:
                        raise SystemExit("bench fleet: a worker did not come up")
                time.sleep(0.6)  # the group's settle time (0.5 s): every member takes part in the first scans
                n_pub = parts(args.scanners, args.publishers)
                publishers = [
                    _child(
                        bench
                        + ["--role", "publisher", "--endpoint", endpoint, "--part", str(i), "--parts", str(n_pub)],
                        stdin=subprocess.PIPE,
                    )
                    for i in range(n_pub)
                ]
                procs += publishers
                for p in publishers:
                    if _read_tagged(p, _READY, 120) is None:
                        raise SystemExit("bench fleet: a publisher did not come up")
                # One schedule for every publisher: a start just ahead, and the scans' ids.
                go = f"{GO}{time.time() + 0.2} {time.time_ns() // 1_000_000}\n"
                for p in publishers:
                    assert p.stdin is not None  # started with stdin=PIPE
                    p.stdin.write(go)
                    p.stdin.flush()
                t_start, router_cpu0 = time.monotonic(), _proc_cpu_s(router.pid)
                killed = None
                if kill_one:
                    steps = args.steps or 184
                    time.sleep(steps / 2 / args.rate)  # mid-way through the first scans
                    workers[0].send_signal(signal.SIGKILL)
                    killed = "w0"
                wait_s = args.scans * ((args.steps or 184) + 2) / args.rate * 20 + 120
                pub = combine([_read_tagged(p, _RESULT, wait_s) for p in publishers], n_pub)
                router_cpu1, router_wall = _proc_cpu_s(router.pid), time.monotonic() - t_start
                expected = args.scanners * args.scans
                deadline = time.monotonic() + args.timeout
                with got:
                    while len(finals) < expected and time.monotonic() < deadline:
                        got.wait(0.2)
                        if progress is not None:
                            progress(len(finals), expected)
                time.sleep(1.0)  # a duplicate would come late: give it a chance to show
                reports = []
                for w in workers:
                    if w.poll() is None:
                        w.send_signal(signal.SIGTERM)
                        reports.append(_read_tagged(w, _RESULT, 60))
                sub.undeclare()
                for p in publishers:
                    assert p.stdin is not None  # started with stdin=PIPE
                    p.stdin.close()
        finally:
            for p in procs:
                if p.poll() is None:
                    p.kill()
                p.wait()
    finished: list[dict] = [r for r in reports if r is not None]
    processed = [x / 1e6 for r in finished for x in r["processed_ns"]]
    provisional = [x / 1e6 for r in finished for x in r["provisional_ns"]]
    firsts = [r["first"] for r in finished if r["first"] is not None]
    lasts = [r["last"] for r in finished if r["last"] is not None]
    samples = sum(r["samples"] for r in finished)
    statuses = [s for v in finals.values() for s in v]
    return {
        "kill_one": killed,
        "expected_finals": expected,
        "scans_with_final": len(finals),
        "duplicated_finals": sum(len(v) - 1 for v in finals.values()),
        "incomplete_finals": sum(1 for s in statuses if not s.startswith("final:") or not s.endswith(":0"))
        + (expected - len(finals)),
        "handled_per_s": (samples - 1) / (max(lasts) - min(firsts))
        if len(firsts) and max(lasts) > min(firsts)
        else 0.0,
        "samples_processed": samples,
        "processed_ms": {"p50": _pct(processed, 50), "p99": _pct(processed, 99)},
        "provisional_ms": {"p50": _pct(provisional, 50), "p99": _pct(provisional, 99), "n": len(provisional)},
        "cpu_per_worker": {r["member"]: r["cpu_s"] / r["wall_s"] for r in finished},
        # Over the window each was busy: a worker from its first live sample handled to its last (read at
        # most every 10 ms), the
        # publisher over its puts, the router over the publisher's puts.
        "busy_cpu": {
            **{
                r["member"]: r["busy_cpu_s"] / r["busy_wall_s"]
                for r in finished
                if r.get("busy_cpu_s") is not None and r["busy_wall_s"] > 0
            },
            **({"publisher": pub["cpu_s"] / pub["wall_s"]} if pub and pub.get("wall_s") else {}),
            **(
                {"router": (router_cpu1 - router_cpu0) / router_wall}
                if router_cpu0 is not None and router_cpu1 is not None and router_wall > 0
                else {}
            ),
        },
        "adopted": {r["member"]: r["group"].get("scans adopted", 0) for r in finished},
        "dropped_other_member": {r["member"]: r["group"].get("dropped: other member", 0) for r in finished},
        "recovered": {r["member"]: r["service"]["samples"]["recovered"] for r in finished},
        "shed": {r["member"]: r["service"].get("provisionals_shed", 0) for r in finished},
        "statuses": dict(Counter(statuses)),
        "recovery": {r["member"]: r["service"]["recovery"] for r in finished},
        "rejected": {r["member"]: r["service"]["rejected"] for r in finished},
        "worker_errors": {r["member"]: r["errors"] for r in finished},
        "publisher": pub,
        "cpu_per_sample_us": {r["member"]: cpu_per_sample(r) for r in finished},
        "threads_cpu_s": {r["member"]: r.get("threads_cpu_s", {}) for r in finished},
        # The worst over the workers: the longest handle and tick, and the calls over STALL_MS.
        "longest_ms": {k: max((r["longest_call_ms"][k] for r in finished), default=None) for k in ("handle", "tick")},
        "stalls": {k: sum(r["stalls"][k] for r in finished) for k in ("handle", "tick")},
        "refit_us": refit_cost([x for r in finished for x in r["refits"]], args.steps or 184),
        "elapsed_s": time.monotonic() - t_start,
    }


def cpu_per_sample(report: dict) -> dict[str, float] | None:
    """A worker's CPU per live sample, µs: all its threads over the window it was busy ("total"), its
    processing thread inside ``handle`` and inside ``tick``, and the rest ("outside": Zenoh's receive, the
    channel, the doorbell, the group's filter, the planes server)."""
    n, total = report["samples"], report.get("busy_cpu_s")
    if not n or total is None:
        return None
    inside = report["thread_cpu_s"]
    out = {"total": total * 1e6 / n, "handle": inside["handle"] * 1e6 / n, "tick": inside["tick"] * 1e6 / n}
    out["outside"] = out["total"] - out["handle"] - out["tick"]
    return out


#: A worker's CPU per sample: all its threads, inside handle, inside tick, the rest.
CPU_PARTS = ("total", "handle", "tick", "outside")

#: Provisional refits' cost is shown by the quarter of the scan its steps reach.
REFIT_BINS = 4


def refit_cost(refits: list[tuple[int, float]], steps: int) -> dict[str, float | None]:
    """Median µs of CPU per provisional refit (the call that made it), by the quarter of the scan held then:
    flat when a refit costs O(new samples), rising when it costs O(steps so far)."""
    out: dict[str, float | None] = {}
    for b in range(REFIT_BINS):
        lo, hi = b * steps // REFIT_BINS + 1, (b + 1) * steps // REFIT_BINS
        cost = [us for held, us in refits if lo <= held <= hi]
        out[f"{lo}-{hi}"] = statistics.median(cost) if cost else None
    return out


def _behind(pub: dict | None) -> str:
    """What the publishers' schedule says of a run: nothing (kept), held back by BLOCK, or invalid."""
    pub = pub or {}
    if pub.get("kept_up"):
        return ""
    if pub.get("held_back"):
        return f" behind: held back inside put {pub['blocked_s']:.1f} s (BLOCK: the workers did not keep up)"
    return " BEHIND on their own: run invalid"


def summarise(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """One case over its runs: medians of the figures, sums of the failures (every run kept in "runs")."""

    def med(values):
        values = [v for v in values if v is not None]
        return statistics.median(values) if values else None

    out: dict[str, Any] = {"runs": runs, "kill_one": runs[0]["kill_one"], "expected_finals": runs[0]["expected_finals"]}
    out["handled_per_s"] = med([r["handled_per_s"] for r in runs])
    for key in ("processed_ms", "provisional_ms"):
        out[key] = {q: med([r[key][q] for r in runs]) for q in ("p50", "p99")}
    out["scans_with_final"] = min(r["scans_with_final"] for r in runs)
    out["incomplete_finals"] = sum(r["incomplete_finals"] for r in runs)
    out["duplicated_finals"] = sum(r["duplicated_finals"] for r in runs)
    members = sorted({m for r in runs for m in r["cpu_per_worker"]})
    out["cpu_per_worker"] = {m: med([r["cpu_per_worker"].get(m) for r in runs]) for m in members}
    procs = sorted({m for r in runs for m in r["busy_cpu"]})
    out["busy_cpu"] = {m: med([r["busy_cpu"].get(m) for r in runs]) for m in procs}
    pubs = [r["publisher"] for r in runs if r["publisher"]]
    out["publisher"] = {
        k: med([p[k] for p in pubs]) for k in (pubs[0] if pubs else {}) if k not in ("kept_up", "held_back", "valid")
    }
    if pubs:
        for flag in ("kept_up", "held_back", "valid"):
            out["publisher"][flag] = len(pubs) == len(runs) and all(p[flag] for p in pubs)
    out["cpu_per_sample_us"] = {
        m: {k: med([(r["cpu_per_sample_us"].get(m) or {}).get(k) for r in runs]) for k in CPU_PARTS} for m in members
    }
    out["threads_cpu_s"] = {
        m: {k: med([r["threads_cpu_s"].get(m, {}).get(k) for r in runs]) for k in runs[0]["threads_cpu_s"].get(m, {})}
        for m in members
    }
    bins = runs[0]["refit_us"]
    out["refit_us"] = {b: med([r["refit_us"].get(b) for r in runs]) for b in bins}
    out["longest_ms"] = {
        k: max((r["longest_ms"][k] for r in runs if r["longest_ms"][k] is not None), default=None)
        for k in ("handle", "tick")
    }
    out["stalls"] = {k: sum(r["stalls"][k] for r in runs) for k in ("handle", "tick")}
    out["adopted"] = {m: med([r["adopted"].get(m, 0) for r in runs]) for m in members}
    out["statuses"] = dict(sum((Counter(r["statuses"]) for r in runs), Counter()))
    for key in ("recovered", "dropped_other_member", "shed"):
        out[key] = {m: med([r[key].get(m, 0) for r in runs]) for m in members}
    return out


def run(args: argparse.Namespace) -> int:
    if args.role == "worker":
        return worker_main(args)
    if args.role == "publisher":
        return publisher_main(args, PREFIX, client_settings(args.endpoint))
    check_encoding(args.preset)
    if args.stages:
        return run_stages(args, refit_cost)
    if args.capacity is not None:
        return run_capacity(args, run_case, summarise, command_line)
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
    from rich.table import Table

    from lelsonar.tools.bench import machine

    if args.scanners < 1 or args.workers < 1 or not args.rate > 0 or args.scans < 1 or args.repeat < 1:
        raise SystemExit("bench fleet: --scanners, --workers, --scans and --repeat must be >= 1 and --rate > 0")
    cases = ([] if args.failover == "only" else [False]) + (
        [True] if args.failover in ("on", "only") or (args.failover == "auto" and args.workers >= 2) else []
    )
    console = Console()
    load = os.getloadavg()
    console.print(
        f"command: {command_line(args)}\nmachine: {machine()}\nload average before: "
        f"{load[0]:.2f} {load[1]:.2f} {load[2]:.2f}",
        highlight=False,
    )
    results = []
    for kill in cases:
        label = "failover (one worker SIGKILLed mid-scan)" if kill else "steady"
        runs = []
        for k in range(args.repeat):
            with Progress(
                TextColumn(f"{label}, run {k + 1}/{args.repeat}"),
                BarColumn(),
                MofNCompleteColumn(),
                TextColumn("finals"),
                TimeElapsedColumn(),
                console=Console(stderr=True),
                transient=True,
            ) as bar:
                task = bar.add_task(label, total=args.scanners * args.scans)

                def show(done: int, total: int, task=task, bar=bar) -> None:
                    bar.update(task, completed=done)

                runs.append(run_case(args, kill_one=kill, progress=show))
        res = summarise(runs)
        res["case"] = label
        results.append(res)
    table = Table(
        title=f"bench fleet: {args.scanners} scanners × {args.rate:g} Hz, {args.workers} workers"
        + (f" (medians of {args.repeat} runs)" if args.repeat > 1 else "")
    )
    table.add_column("")
    for r in results:
        table.add_column("failover" if r["kill_one"] else "steady", justify="right")

    def ms(d):
        return " / ".join("—" if d[k] is None else f"{d[k]:.0f}" for k in ("p50", "p99"))

    def pub(r, key):
        return (r["publisher"] or {}).get(key, float("nan"))

    offered = args.scanners * args.rate
    rows = [
        ("offered samples/s (scanners × rate)", lambda r: f"{offered:.0f}"),
        ("handled samples/s", lambda r: f"{r['handled_per_s']:.0f}"),
        ("handled / offered", lambda r: f"{r['handled_per_s'] / offered:.2f}"),
        ("put→processed p50 / p99, ms", lambda r: ms(r["processed_ms"])),
        ("put→provisional p50 / p99, ms", lambda r: ms(r["provisional_ms"])),
        ("scans with a final", lambda r: f"{r['scans_with_final']} / {r['expected_finals']}"),
        ("incomplete finals (must be 0)", lambda r: str(r["incomplete_finals"])),
        ("duplicated finals (must be 0)", lambda r: str(r["duplicated_finals"])),
        (
            "CPU per worker (of one core)",
            lambda r: " ".join(f"{v * 100:.0f}%" for v in r["cpu_per_worker"].values() if v is not None),
        ),
        (
            "CPU while busy (of one core)",
            lambda r: " ".join(f"{m} {v * 100:.0f}%" for m, v in r["busy_cpu"].items() if v is not None),
        ),
        (
            "publisher lag p50 / p99 / max, s",
            lambda r: f"{pub(r, 'lag_p50'):.2f} / {pub(r, 'lag_p99'):.2f} / {pub(r, 'lag_max'):.2f}",
        ),
        (
            "publishing took / schedule, s",
            lambda r: (
                f"{pub(r, 'wall_s'):.1f} / {pub(r, 'schedule_s'):.1f} ({pub(r, 'processes'):.0f} processes)"
                + _behind(r["publisher"])
            ),
        ),
        (
            "worker CPU µs/sample: all / handle / tick / outside",
            lambda r: "; ".join(
                f"{m} " + " / ".join("—" if v[k] is None else f"{v[k]:.0f}" for k in CPU_PARTS)
                for m, v in r["cpu_per_sample_us"].items()
            ),
        ),
        (
            "provisional refit µs by steps held",
            lambda r: " ".join(f"{b}: {'—' if v is None else f'{v:.0f}'}" for b, v in r["refit_us"].items()),
        ),
        (
            f"longest handle / tick, ms CPU (calls over {STALL_MS:g} ms)",
            lambda r: " / ".join(
                "—" if r["longest_ms"][k] is None else f"{r['longest_ms'][k]:.1f} ({r['stalls'][k]})"
                for k in ("handle", "tick")
            ),
        ),
        (
            "provisionals shed",
            lambda r: f"{sum(r['shed'].values()):g}",
        ),
        ("scans adopted (failover)", lambda r: f"{sum(r['adopted'].values()):g}"),
    ]
    table_rows = [(name, *(fn(r) for r in results)) for name, fn in rows]
    for row in table_rows:
        table.add_row(*row)
    console.print(table)
    from lelsonar.tools import bench_markdown

    bench_markdown.write(
        args.markdown,
        [
            bench_markdown.table(
                str(table.title),
                ["", *("failover" if r["kill_one"] else "steady" for r in results)],
                table_rows,
                [f"command: {command_line(args)}", f"machine: {machine()}"],
            )
        ],
    )
    for r in results:
        console.print(
            f"{r['case']}: terminal statuses (status:missing steps) {r['statuses']}; adopted "
            f"{r['adopted']}; recovered samples {r['recovered']}; dropped as other member "
            f"{r['dropped_other_member']}",
            highlight=False,
        )
        for m, threads in r["threads_cpu_s"].items():
            console.print(
                f"{r['case']}: {m}'s CPU by thread, s: " + ", ".join(f"{k} {v:.2f}" for k, v in threads.items()),
                highlight=False,
            )
    load = os.getloadavg()
    console.print(
        f"load average after: {load[0]:.2f} {load[1]:.2f} {load[2]:.2f} (2 cores shared with other work "
        "here: figures are of this run only)",
        highlight=False,
    )
    if args.json:
        args.json.write_text(
            json.dumps({"command": command_line(args), "machine": machine(), "cases": results}, indent=1)
        )
    behind = [r["case"] for r in results if not (r["publisher"] or {}).get("valid")]
    if behind:
        console.print(
            f"[red]invalid[/]: the publishers fell behind their schedule ({', '.join(behind)}): the offered rate "
            "was not offered, so these figures are of the publishers, not the reconstructors; rerun with more "
            "--publishers or on a quieter host"
        )
    bad = any(r["incomplete_finals"] or r["duplicated_finals"] for r in results) or bool(behind)
    return 1 if bad else 0


if __name__ == "__main__":
    p = argparse.ArgumentParser()
    add_arguments(p)
    sys.exit(run(p.parse_args()))
