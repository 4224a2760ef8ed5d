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
workers did not keep up), and each worker's CPU per sample inside ``handle``, ``tick`` and ``catch_up`` and
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
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from lelsonar.errors import ConfigError
from lelsonar.tools.bench_fleet_capacity import CAPACITY_LADDER, run_capacity
from lelsonar.tools.bench_fleet_publisher import GO, READY, RESULT, check_encoding, combine, parts, publisher_main
from lelsonar.tools.bench_fleet_results import CPU_PARTS, case_result, refit_cost, summarise
from lelsonar.tools.bench_fleet_results import behind as behind_text
from lelsonar.tools.bench_fleet_stages import STALL_MS, run_stages
from lelsonar.tools.bench_fleet_worker import PREFIX, TIMED_CALLS, client_settings, service_config, worker_main

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
        "--service",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="a field of the workers' ReconstructConfig (repeatable; e.g. provisional_backlog=0 for an A/B)",
    )
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
        + "".join(f" --service {s}" for s in args.service)
        + (f" --capacity {' '.join(str(n) for n in args.capacity)}" if args.capacity else "")
        + (" --capacity" if args.capacity == [] else "")
    )


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
    bench = (
        [
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
        ]
        + (["--no-provisional"] if args.no_provisional else [])
        + [f"--service={s}" for s in args.service]
    )
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
    return case_result(
        reports,
        finals,
        pub,
        expected=expected,
        killed=killed,
        router_cpu=(router_cpu0, router_cpu1, router_wall),
        steps=args.steps or 184,
        t_start=t_start,
    )


def run(args: argparse.Namespace) -> int:
    if args.role == "worker":
        return worker_main(args)
    if args.role == "publisher":
        return publisher_main(args, PREFIX, client_settings(args.endpoint))
    check_encoding(args.preset)
    service_config(args.service)  # a field or value the workers would refuse, refused here
    if args.stages:
        return run_stages(args, refit_cost)
    if args.capacity is not None:
        return run_capacity(args, run_case, summarise, command_line)
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
    from rich.table import Table

    from lelsonar.tools.bench import machine

    if args.scanners < 1 or args.workers < 1 or not args.rate > 0 or args.scans < 1 or args.repeat < 1:
        raise ConfigError("--scanners, --workers, --scans and --repeat must be >= 1 and --rate > 0")
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
                + behind_text(r["publisher"])
            ),
        ),
        (
            "worker CPU µs/sample: all / handle / tick / catch_up / outside",
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
            f"longest handle / tick / catch_up, ms CPU (calls over {STALL_MS:g} ms)",
            lambda r: " / ".join(
                "—" if r["longest_ms"][k] is None else f"{r['longest_ms'][k]:.1f} ({r['stalls'][k]})"
                for k in TIMED_CALLS
            ),
        ),
        (
            "samples that woke an idle worker (doorbell)",
            lambda r: "—" if r["doorbell_per_sample"] is None else f"{100 * r['doorbell_per_sample']:.0f} %",
        ),
        (
            "provisionals shed (of which stale)",
            lambda r: f"{sum(r['shed'].values()):g} ({sum(r['stale'].values()):g})",
        ),
        (
            "provisional exact fits made in the final pool",
            lambda r: f"{sum(r.get('fits_from_pool', {}).values()):g}",
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
