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
    left out).  Target ≥ 1,000 samples/s and ≥ 0.6× the floor: a plain upb
    parse (``FromString``, no validation) of the same payloads (whole scans,
    ScanStart to ScanEnd; samples counted), in the parent process, right
    after the run (printed beside the result).
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
    replayed with :func:`~lelsonar.reconstruct.stream.replay.replay_mcap` through a
    default ``ReconstructionService``; samples / wall time, median of
    ``--replay-runs``.  Target ≥ 3,000 samples/s and ≥ 1.0× the floor: python
    ``mcap``'s reader + a upb parse of the contract messages of the same file
    (same run).  Diagnostic rows bracket it: the replay with provisional
    estimates, reading + decoding + assembling alone, and the tolerant reader +
    upb alone (the floor's own work).  The replay of ONE file of 1, 10 and 100
    scans merged by ``mcap``'s own writer, with its peak memory, is
    ``lelsonar bench recording``'s second table.

Processes: the consumer listens on a private unix socket
(``unixsock-stream/<tmpdir>/z.sock``, a peer); the publisher connects to it as
a client.  Both are ``python -m lelsonar.tools.bench_ingest --role ...``,
started and always reaped by the bench; every session is closed by a ``with``.
The messages come from the simulator (:class:`~lelsonar.acquire.backends.SimScanner`)
built once by :mod:`lelsonar.acquire.messages`, as the acquisition service builds them.

``--profile`` adds a cProfile breakdown of one replay (the same ``handle`` code
as the live path); ``--markdown OUT.md`` writes the table.  The processes of (a)
and (b) are in :mod:`lelsonar.tools.bench_ingest_live`, the in-process
measurements in :mod:`lelsonar.tools.bench_ingest_replay`.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

from lelsonar.tools import bench_markdown
from lelsonar.tools.bench_ingest_live import consumer_main, publisher_main, run_phase
from lelsonar.tools.bench_ingest_replay import (
    STAGE_FLOOR,
    decoding_paths,
    ingest_stage_vs_floor,
    profile_replay,
    record_scans,
    time_floor,
    time_ingest_only,
    time_read_upb,
    time_replay,
)
from lelsonar.tools.bench_replay import plans_text

TARGET_RATE = 1000.0
TARGET_P99_MS = 50.0
TARGET_REPLAY = 3000.0
#: Targets against the floors, each measured in the same run: the ingest stage against a plain upb parse of
#: the same payloads, the replay against python mcap + upb reading the same file.
TARGET_STAGE_RATIO = 0.6
TARGET_REPLAY_RATIO = 1.0


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
    parser.add_argument("--markdown", type=Path, default=None, help="also write the table to this Markdown file")
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

    from lelsonar.errors import ConfigError
    from lelsonar.reconstruct.stream.config import ReconstructConfig
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
    next(phases)
    live = measure_live_rate(args)
    next(phases)
    lat = measure_latency(args)
    next(phases)
    rep = measure_replay(args)
    next(phases, None)  # the bar counts the last phase and goes
    wall = time.perf_counter() - t_bench

    rows: list[tuple] = []
    ok: list[bool] = []
    for part_rows, part_ok in (
        ingest_rows(args, live),
        latency_rows(args, lat, defaults),
        replay_rows(args, rep, defaults),
    ):
        rows += part_rows
        ok += part_ok
    title = "Ingest, latency and replay (one run, side by side)"
    notes = [
        f"lelsonar bench ingest — preset {args.preset}, Sample = 4 × 3500 float32 waveforms (56 KB); "
        f"bench wall {wall:.0f} s",
        f"machine: {machine()}; {host_line(busy)}",
        f"command: {command_line(args)}",
        f"service: ReconstructConfig() defaults — method {defaults.method}, compare_methods "
        f"{defaults.compare_methods}, refit_every {defaults.refit_every}",
        f"floor of (a), (a′): {STAGE_FLOOR}",
        f"floor of (c): {REPLAY_FLOOR}",
    ]
    _print_table(console, title, rows, notes)
    bench_markdown.write(args.markdown, [bench_markdown.table(title, HEADERS, rows, notes)])
    if rep.profile_stash is not None:
        with tempfile.TemporaryDirectory(prefix="lelsonar-bench-profile-") as tmp:
            p = Path(tmp) / "replay.mcap"
            p.write_bytes(rep.profile_stash[0])
            profile_replay(p, rep.profile_stash[1], console)
    return 0 if all(ok) else 1


HEADERS = ("measurement", "result", "floor (same run)", "ratio", "target", "verdict", "details")
REPLAY_FLOOR = "python mcap make_reader + upb FromString of the contract messages, same file, log-time order"


def _print_table(console, title: str, rows: list[tuple], notes: list[str]) -> None:
    from rich.table import Table

    table = Table(title=title)
    for col in HEADERS:
        table.add_column(
            col,
            justify="right" if col in ("result", "target", "floor (same run)", "ratio") else "left",
            overflow="fold",
            max_width=70 if col == "details" else None,
        )
    for row in rows:
        table.add_row(*row)
    for note in notes[:4]:
        console.print(note, highlight=False)
    console.print(table)
    for note in notes[4:]:
        console.print(note, highlight=False)


# --- (a) sustained ingest and (a′) the stage alone ---------------------------------------------------
@dataclass
class LiveRate:
    pub: dict
    con: dict
    floor: float  # plain upb parse, samples/s
    stage: float  # Ingest.accept, samples/s
    paths: dict[str, float]  # µs a sample: plain parse, the stage with and without the fast path


def measure_live_rate(args: argparse.Namespace) -> LiveRate:
    """(a) through Zenoh, then the floor and the stage alone on the same payloads, interleaved, right after."""
    pub, con = run_phase(args, "rate")
    floor, stage = ingest_stage_vs_floor(args.preset, 5)
    return LiveRate(pub, con, floor, stage, decoding_paths(args.preset, 5))


def ingest_rows(args: argparse.Namespace, live: LiveRate) -> tuple[list[tuple], list[bool]]:
    con_a, pub_a, floor_a, stage_a = live.con, live.pub, live.floor, live.stage
    done = sorted(con_a["done_mono"])
    n = len(done)
    i10, i90 = n // 10, (9 * n) // 10
    rate = (i90 - i10) / (done[i90] - done[i10]) if n > 10 and done[i90] > done[i10] else float("nan")
    overall = (n - 1) / (done[-1] - done[0]) if n > 1 else float("nan")
    window = done[-1] - done[0] if n > 1 else float("nan")
    b = con_a["busy"]
    busy_s = sum(v[1] for v in b.values())
    live_accepts, live_accept_s = con_a["sample_accept_s"]

    def mean_ms(bucket: str) -> str:
        return f"{1e3 * b[bucket][1] / b[bucket][0]:.1f}" if bucket in b else "—"

    ok_rate = rate >= TARGET_RATE and rate >= TARGET_STAGE_RATIO * floor_a
    ok_stage = stage_a >= TARGET_STAGE_RATIO * floor_a
    rows = [
        (
            "(a) sustained ingest, Zenoh → LiveSource → service",
            f"{rate:,.0f} samples/s",
            f"{floor_a:,.0f}/s plain upb parse",
            f"{rate / floor_a:.2f}×",
            f"≥ {TARGET_RATE:,.0f} and ≥ {TARGET_STAGE_RATIO}× floor",
            _verdict(ok_rate),
            f"{n} samples of {args.scanners} scanners × {con_a['finals'] // max(1, args.scanners)} scans "
            f"in {window:.1f} s (overall {overall:,.0f}/s; 10–90 % window); publisher "
            f"{pub_a['puts'] / pub_a['put_s']:,.0f} puts/s (BLOCK); consumer busy {100 * busy_s / window:.0f} % in "
            f"handle; mean handle ms: sample {mean_ms('Sample')}, with provisional refit {mean_ms('provisional')}, "
            f"with final {mean_ms('final')}; rejected {con_a['rejected'] or 0}, errors {con_a['errors']}"
            + ("; [red]consumer timed out[/]" if con_a["timed_out"] else ""),
        ),
        (
            "(a′) ingest stage alone: decode + validate + route + assemble (Ingest.accept)",
            f"{stage_a:,.0f} samples/s",
            f"{floor_a:,.0f}/s plain upb parse",
            f"{stage_a / floor_a:.2f}×",
            f"≥ {TARGET_STAGE_RATIO}× floor",
            _verdict(ok_stage),
            "everything before estimation, on the floor's payloads (whole scans), interleaved with it in this "
            f"process; in (a)'s consumer, Ingest.accept took {1e6 * live_accept_s / max(1, live_accepts):.0f} µs "
            f"a sample ({live_accepts / live_accept_s if live_accept_s else float('nan'):,.0f}/s while in it)",
        ),
        (
            "(a″) the stage with the Sample fast path, against the stage parsing every payload with upb",
            f"{live.paths['fast']:.1f} µs a sample",
            f"{live.paths['parsed']:.1f} µs parsed",
            f"{live.paths['parsed'] / live.paths['fast']:.2f}×",
            "what the fast path buys",
            "",
            f"same payloads, medians of 5; a plain upb parse alone takes {live.paths['parse']:.1f} µs a sample",
        ),
    ]
    return rows, [ok_rate, ok_stage]


# --- (b) latency ---------------------------------------------------------------------------------------
def measure_latency(args: argparse.Namespace) -> tuple[dict, dict]:
    return run_phase(args, "latency")


def latency_rows(args: argparse.Namespace, lat: tuple[dict, dict], defaults) -> tuple[list[tuple], list[bool]]:
    pub_b, con_b = lat
    lat_sample = [ns / 1e6 for ns in con_b["sample_latency_ns"]]
    lat_prov = _lat_ms(con_b["estimate_latency"], "provisional")
    lat_final = _lat_ms(con_b["estimate_latency"], "final")
    e2e_prov = _lat_ms(pub_b["e2e"], "provisional")
    e2e_final = _lat_ms(pub_b["e2e"], "final")
    p50, p99 = _pct(lat_sample, 50), _pct(lat_sample, 99)
    q50, q99 = _pct(lat_prov, 50), _pct(lat_prov, 99)
    ok_lat_s, ok_lat_e = p99 <= TARGET_P99_MS, q99 <= TARGET_P99_MS
    rows = [
        (
            "(b1) latency put → sample processed (handle returned)",
            f"p50 {p50:.1f} / p99 {p99:.1f} ms",
            "",
            "",
            f"p99 ≤ {TARGET_P99_MS:.0f} ms",
            _verdict(ok_lat_s),
            f"{len(lat_sample)} samples: {args.latency_scanners} scanners at {args.rate:g}/s each, {args.scans} "
            f"scans back to back; max {max(lat_sample, default=float('nan')):.0f} ms",
        ),
        (
            "(b2) latency put of last_step → provisional estimate published",
            f"p50 {q50:.1f} / p99 {q99:.1f} ms",
            "",
            "",
            f"p99 ≤ {TARGET_P99_MS:.0f} ms",
            _verdict(ok_lat_e),
            f"{len(lat_prov)} estimates (every refit_every steps once the corner is confirmed); "
            f"received by a subscriber: p50 {_pct(e2e_prov, 50):.1f} / p99 {_pct(e2e_prov, 99):.1f} ms",
        ),
        (
            "(b3) latency put of ScanEnd → final estimate published",
            f"p50 {_pct(lat_final, 50):.0f} / max {max(lat_final, default=float('nan')):.0f} ms",
            "",
            "",
            "—",
            "",
            f"{len(lat_final)} finals ({', '.join((defaults.method, *defaults.compare_methods))}, from scratch); "
            f"received: max {max(e2e_final, default=float('nan')):.0f} ms",
        ),
    ]
    return rows, [ok_lat_s, ok_lat_e]


# --- (c) replay -------------------------------------------------------------------------------------------
@dataclass
class Replay:
    samples: int
    finals: int
    size_mb: float
    seconds: dict[str, float]  # median wall time per row
    profile_stash: tuple[bytes, int] | None
    #: Each round's replay ÷ floor samples/s, in round order (the spread of the median (c) prints).
    ratios: list[float] = field(default_factory=list)
    #: The (c) replays' plans: (final workers, decompressing threads) → rounds.
    plans: dict[tuple[int, int], int] = field(default_factory=dict)


def measure_replay(args: argparse.Namespace) -> Replay:
    """(c): one recorded file; the replay, its diagnostics and its floor, interleaved, one run of each per round."""
    from lelsonar.reconstruct.stream.final_pool import FinalPool
    from lelsonar.reconstruct.stream.finals import auto_workers

    with tempfile.TemporaryDirectory(prefix="lelsonar-bench-replay-") as tmp:
        path = Path(tmp) / "replay.mcap"
        n_replay = record_scans(path, args.preset, args.scans)
        time_replay(path, 1)  # warm-up
        with FinalPool(auto_workers()) as pool:  # the fork server's start (its imports, the kernels): once a process
            pool.wait_ready(120)
        # (c) is what `lelsonar reconstruct --source FILE.mcap` runs: finals only, no provisional estimates.
        # Interleaved, so a neighbour's load hits the result and its floor alike.
        rounds: dict[str, list[float]] = {"replay": [], "inline": [], "prov": [], "ingest": [], "read": [], "floor": []}
        finals = 0
        plans: list = []
        for _ in range(args.replay_runs):
            t, finals = time_replay(path, 1, plans, provisional=False)
            rounds["replay"].append(t)
            rounds["inline"].append(time_replay(path, 1, provisional=False, final_workers=0)[0])
            rounds["prov"].append(time_replay(path, 1)[0])
            rounds["ingest"].append(time_ingest_only(path, 1))
            rounds["read"].append(time_read_upb(path, 1))
            rounds["floor"].append(time_floor(path, 1))
        stash = (path.read_bytes(), n_replay) if args.profile else None
        return Replay(
            n_replay,
            finals,
            path.stat().st_size / 1e6,
            {k: statistics.median(v) for k, v in rounds.items()},
            stash,
            [f / r for r, f in zip(rounds["replay"], rounds["floor"], strict=True)],
            dict(Counter((p.workers, p.decompress_threads) for p in plans)),
        )


def replay_rows(args: argparse.Namespace, rep: Replay, defaults) -> tuple[list[tuple], list[bool]]:
    from lelsonar.reconstruct.stream.finals import auto_workers

    n, sec = rep.samples, rep.seconds
    replay_rate, floor_c = n / sec["replay"], n / sec["floor"]
    ok_replay = replay_rate >= TARGET_REPLAY and replay_rate >= TARGET_REPLAY_RATIO * floor_c
    rows = [
        (
            "(c) MCAP replay, as `reconstruct --source` runs it",
            f"{replay_rate:,.0f} samples/s",
            f"{floor_c:,.0f}/s python mcap + upb",
            f"{replay_rate / floor_c:.2f}×",
            f"≥ {TARGET_REPLAY:,.0f} and ≥ {TARGET_REPLAY_RATIO}× floor",
            _verdict(ok_replay),
            f"{n} samples, {args.scans} scans, {rep.size_mb:.1f} MB zstd; median of {args.replay_runs} "
            f"(rounds {min(rep.ratios):.2f}–{max(rep.ratios):.2f}×; plans {plans_text(rep.plans)}: final workers "
            "+ decompressing threads, as the host's load at each start decides them); "
            f"{rep.finals} finals ({', '.join((defaults.method, *defaults.compare_methods))}); no provisional "
            "estimates, which the finals do not depend on",
        ),
        (
            "(c⁰) replay, the finals in the replaying process (diagnostic)",
            f"{n / sec['inline']:,.0f} samples/s",
            "",
            f"{n / sec['inline'] / floor_c:.2f}×",
            "—",
            "",
            "--jobs 0: each final estimated where the file is read; (c) estimates them in worker processes "
            f"while the reading goes on where its plan starts any (up to {auto_workers()}, as the host's load "
            "leaves cores idle, and none for a short file without threads decompressing: see its plans)",
        ),
        (
            "(c′) replay with provisional estimates (diagnostic)",
            f"{n / sec['prov']:,.0f} samples/s",
            "",
            f"{n / sec['prov'] / floor_c:.2f}×",
            "—",
            "",
            f"a refit every {defaults.refit_every} steps, as live and `lelsonar review` do",
        ),
        (
            "(c″) MCAP read + decode + assemble only (diagnostic)",
            f"{n / sec['ingest']:,.0f} samples/s",
            "",
            f"{n / sec['ingest'] / floor_c:.2f}×",
            "—",
            "",
            "Ingest.accept over iter_payloads: no estimation; the ceiling of (c)",
        ),
        (
            "(c‴) MCAP read + upb parse only (diagnostic)",
            f"{n / sec['read']:,.0f} samples/s",
            "",
            f"{n / sec['read'] / floor_c:.2f}×",
            "≥ 1.0× floor",
            _verdict(sec["read"] <= sec["floor"]),
            "iter_payloads (every chunk's CRC checked) + FromString: the floor's work, by the tolerant reader",
        ),
    ]
    return rows, [ok_replay]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="lelsonar bench ingest")
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    raise SystemExit(main())
