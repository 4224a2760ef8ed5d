"""``lelsonar bench recording``: what durable recording costs.

The acquisition recorder hands every step to the OS before the step is
published: one MCAP chunk per step (the Sample; its /tf and points are the next), flushed.  This
bench writes the same simulated scan, messages built beforehand, through
:class:`lelsonar.log.recording.McapRecorder` with

* ``1 MiB chunks`` — the floor, no durability (``durable=False``): chunks
  written when full, so a killed writer loses up to a whole chunk (≈10 samples);
* ``chunk per step`` — the default: a killed writer loses at most the step
  being written;
* ``chunk per step + fsync`` — ``lelsonar acquire --fsync``: each step also on
  the disk (survives a power cut).

and reads each file back with the tolerant reader.  Each row is the median of
``--runs`` runs, interleaved so a neighbour's load hits every row alike; the
ratio is against the first row of the same compression.

A second table replays ONE file of 1, 10 and 100 scans (``--rss-scans``) merged
by ``mcap``'s own writer, each measurement in a fresh process
(:mod:`lelsonar.tools.bench_replay`): the reading's speed against its floor,
python ``mcap`` + upb on the same file, and the peak resident set of the
replay, which must not grow with the file.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

from lelsonar import codec
from lelsonar.cli.paths import output_dir
from lelsonar.tools import bench_markdown

#: Each row: its label and the McapRecorder options it measures.
ROWS: tuple[tuple[str, dict[str, bool]], ...] = (
    ("1 MiB chunks, not durable", {"durable": False}),
    ("chunk per step", {}),
    ("chunk per step, fsync", {"fsync": True}),
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--preset", default="paper-test1", help="simulator preset (default: %(default)s)")
    parser.add_argument("--steps", type=int, default=None, help="override the preset's number of steps")
    parser.add_argument("--runs", type=int, default=7, help="runs per row; medians are reported (default: %(default)s)")
    parser.add_argument(
        "--compression",
        nargs="+",
        default=["zstd"],
        choices=("zstd", "lz4", "none"),
        help="chunk compressions to compare (default: zstd, the acquire default)",
    )
    parser.add_argument(
        "--dir",
        type=Path,
        default=None,
        help="where to write (default: a temporary directory; fsync cost depends on the disk)",
    )
    parser.add_argument("--seed", type=int, default=0, help="simulator seed (default: %(default)s)")
    parser.add_argument(
        "--rss-scans",
        type=int,
        nargs="*",
        default=[1, 10, 100],
        help="scans merged into one file for the replay speed and memory rows; none to skip (default: 1 10 100)",
    )
    parser.add_argument(
        "--rss-runs", type=int, default=1, help="runs of each replay row; medians (default: %(default)s)"
    )
    parser.add_argument("--markdown", type=Path, default=None, help="also write the tables to this Markdown file")


def command_line(args: argparse.Namespace) -> str:
    parts = [
        "lelsonar bench recording",
        f"--preset {args.preset}",
        f"--runs {args.runs}",
        f"--seed {args.seed}",
        f"--compression {' '.join(args.compression)}",
    ]
    if args.steps is not None:
        parts.append(f"--steps {args.steps}")
    if args.dir is not None:
        parts.append(f"--dir {args.dir}")
    parts.append(f"--rss-scans {' '.join(str(n) for n in args.rss_scans)} --rss-runs {args.rss_runs}")
    return " ".join(parts)


def scan_messages(preset_name: str, steps: int | None, seed: int) -> list:
    """ScanStart, one Sample per step and ScanEnd of a simulated scan, built as `acquire` builds them."""
    import dataclasses

    from lelsonar.acquire import messages
    from lelsonar.acquire.backends import SimScanner
    from lelsonar.acquire.scan_loop import gamma_schedule
    from lelsonar.sim import preset
    from lelsonar.sim.calibrate import default_energy_model

    sim = preset(preset_name)
    if steps is not None:
        sim = dataclasses.replace(sim, steps=steps)
    scanner = SimScanner(sim, seed)
    schedule = gamma_schedule(sim.gamma_start, sim.gamma_stop, sim.steps)
    t0 = time.time_ns()
    out: list[codec.ScanMessage] = [messages.scan_start("bench", 1, t0, scanner.info, schedule, default_energy_model())]
    for step, gamma in enumerate(schedule):
        out.append(messages.sample("bench", 1, step, float(gamma), scanner.measure(step, float(gamma)), scanner.info))
    out.append(
        messages.scan_end(
            "bench",
            1,
            time.time_ns(),
            complete=True,
            reason="",
            steps_planned=len(schedule),
            samples_sent=len(schedule),
            echoes_missing=0,
        )
    )
    return out


def write_once(path: Path, msgs: list, compression: str, options: dict) -> float:
    """Wall time to write the scan and finish the file, s."""
    from lelsonar.log.recording import McapRecorder

    t = time.perf_counter()
    with McapRecorder(path, compression=compression, **options) as rec:
        for m in msgs:
            rec.write(m)
    return time.perf_counter() - t


def read_once(path: Path) -> float:
    from lelsonar.log.recording import open_recording

    t = time.perf_counter()
    for _ in open_recording(path).payloads():
        pass
    return time.perf_counter() - t


def run(args: argparse.Namespace) -> int:
    from rich.console import Console

    from lelsonar.log.reader import salvage
    from lelsonar.tools.bench import machine
    from lelsonar.tools.bench_acquire import host_busy, host_line

    if args.dir is not None:
        output_dir(args.dir, what="--dir")
    console = Console(width=max(Console().width, 160))
    busy = host_busy()
    msgs = scan_messages(args.preset, args.steps, args.seed)
    steps = len(msgs) - 2
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        where = Path(tmp)
        times: dict[tuple[str, str], list[float]] = {}
        reads: dict[tuple[str, str], list[float]] = {}
        sizes: dict[tuple[str, str], int] = {}
        chunks: dict[tuple[str, str], int] = {}
        for _ in range(args.runs):  # interleaved: every row sees the same neighbours
            for comp in args.compression:
                for i, (name, options) in enumerate(ROWS):
                    path = where / f"{comp}-{i}.mcap"
                    times.setdefault((comp, name), []).append(write_once(path, msgs, comp, options))
                    reads.setdefault((comp, name), []).append(read_once(path))
                    sizes[(comp, name)] = path.stat().st_size
                    chunks[(comp, name)] = salvage(path).chunks_read
        fs = _filesystem(where)
    title = (
        f"writing one {args.preset} scan ({steps} steps, {len(msgs)} contract messages, "
        f"each Sample with /tf and points) — medians of {args.runs}"
    )
    headers = ("compression", "recorder", "chunks", "write ms", "µs/step", "× before", "MB", "read ms")
    rows = []
    for comp in args.compression:
        base = statistics.median(times[(comp, ROWS[0][0])])
        for name, _ in ROWS:
            med = statistics.median(times[(comp, name)])
            rows.append(
                (
                    comp,
                    name,
                    str(chunks[(comp, name)]),
                    f"{1e3 * med:.1f}",
                    f"{1e6 * med / steps:.0f}",
                    f"{med / base:.2f}",
                    f"{sizes[(comp, name)] / 1e6:.2f}",
                    f"{1e3 * statistics.median(reads[(comp, name)]):.1f}",
                )
            )
    notes = [
        f"machine: {machine()}; files on {fs}; {host_line(busy)}",
        "floor: the first row of each compression (1 MiB chunks, no durability)",
        "fsync's cost is the disk's: on a shared or loaded host it varies several-fold between runs",
        f"command: {command_line(args)}",
    ]
    _print(console, title, headers, rows, notes)
    sections = [bench_markdown.table(title, headers, rows, notes)]
    ok = True
    if args.rss_scans:
        replay_section, ok = replay_memory(console, args)
        sections.append(replay_section)
    bench_markdown.write(args.markdown, sections)
    return 0 if ok else 1


def _print(console, title: str, headers, rows, notes) -> None:
    from rich.table import Table

    table = Table(title=title, title_justify="left")
    for i, col in enumerate(headers):
        table.add_column(col, justify="left" if i < 2 else "right")
    for row in rows:
        table.add_row(*row)
    console.print(table)
    for note in notes:
        console.print(note, highlight=False)


#: Target: the replay's peak RSS on the largest file within this factor of the 1-scan file's.
TARGET_RSS_GROWTH = 1.25


def replay_memory(console, args: argparse.Namespace) -> tuple[str, bool]:
    """The replay rows: one merged file per ``--rss-scans``; speed against python mcap + upb, and peak RSS."""
    from lelsonar.tools import bench_replay
    from lelsonar.tools.bench_acquire import host_busy, host_line

    busy = host_busy()
    rows = bench_replay.memory_rows(args.rss_scans, args.preset, args.rss_runs)
    headers = (
        "scans in one file",
        "MB",
        "samples",
        "floor samples/s",
        "read × floor",
        "replay × floor",
        "replay, workers up × floor",
        "replay, finals inline × floor",
        "finals in workers (replay / up)",
        "peak RSS MiB replay / up / read / floor",
        "runs; replays' plans",
        "replay ≥ floor",
    )
    table_rows = []
    ok = True
    for r in rows:
        floor, read, replay, warm, inline = (
            r["samples"] / r[f"{m}_s"] for m in ("floor", "read", "replay", "warm", "inline")
        )
        ok &= read >= bench_replay.TARGET_RATIO * floor
        fast = replay >= bench_replay.TARGET_RATIO * floor
        ok &= fast
        table_rows.append(
            (
                str(r["scans"]),
                f"{r['mb']:.0f}",
                str(r["samples"]),
                f"{floor:,.0f}",
                f"{read / floor:.2f}×",
                f"{replay / floor:.2f}×",
                f"{warm / floor:.2f}×",
                f"{inline / floor:.2f}×",
                f"{r['replay_pooled']} / {r['warm_pooled']} of {r['scans']}",
                f"{r['replay_rss']:.0f} / {r['warm_rss']:.0f} / {r['read_rss']:.0f} / {r['floor_rss']:.0f}",
                f"{r['runs']}; {bench_replay.plans_text(r['plans'])}",
                "[green]PASS[/]" if fast else "[red]FAIL[/]",
            )
        )
    growth = rows[-1]["replay_rss"] / rows[0]["replay_rss"] if rows else float("nan")
    flat = growth <= TARGET_RSS_GROWTH
    ok &= flat
    title = "replay of ONE file of N scans merged by mcap's own writer — medians of the runs column, fresh process each"
    notes = [
        f"floor: {bench_replay.FLOOR}",
        f"runs: --rss-runs, and more on a short file (at least {bench_replay.SHORT_FILE_RUNS} scans replayed a "
        "mode); every child warms up before its clock: the replays load the kernels, the floor and the read "
        "read the file once untimed (each then reads into a heap already mapped, the file in the page cache)",
        "plans: each replay child's final workers (w) and decompressing threads (t), which the host's load at its "
        "start decides (× the children that had it)",
        "read: lelsonar's tolerant reader (iter_payloads, every chunk's CRC checked) + upb FromString; target "
        f"≥ {bench_replay.TARGET_RATIO:.1f}× floor",
        "replay: replay_mcap through ReconstructionService(provisional=False), as `reconstruct --source`: "
        "reading, decoding, validation, assembly and the final estimates (in worker processes where "
        "replay_workers starts them: on the cores the reading and its decompression leave idle, and in a process "
        "that has none yet not for a short file; the plans column says what each child had); target "
        f"≥ {bench_replay.TARGET_RATIO:.1f}× floor",
        "replay, workers up: the same in a process whose final workers' fork server was ready before the clock "
        "(a live reconstructor, a process that replayed a file already); workers as the host's load leaves "
        "cores idle, but the decompression's below a few hundred scans (on 2 cores: none, as replay)",
        "replay, finals inline: the same with every final estimated in the replaying process (--jobs 0), the "
        "file decompressed ahead on the idle cores",
        "a file's last final starts when its reading ends: it adds one final to a replay whatever the workers",
        f"peak RSS: VmHWM of the replaying process (a final worker holds one scan); replay's at "
        f"{rows[-1]['scans'] if rows else '?'} scans is {growth:.2f}× its 1st file's (target ≤ {TARGET_RSS_GROWTH}×: "
        "flat in the file's length) " + ("[green]PASS[/]" if flat else "[red]FAIL[/]"),
        f"{host_line(busy)}",
    ]
    _print(console, title, headers, table_rows, notes)
    work_title, work_headers, work_rows, work_notes = replay_work(rows)
    _print(console, work_title, work_headers, work_rows, work_notes)
    return (
        bench_markdown.table(title, headers, table_rows, notes)
        + "\n"
        + bench_markdown.table(work_title, work_headers, work_rows, work_notes)
    ), ok


def replay_work(rows: list[dict]) -> tuple[str, tuple[str, ...], list[tuple[str, ...]], list[str]]:
    """Where a replay's time goes: the CPU per scan of the floor, the reading, the ingest stage and the finals,
    from the same children as the speed rows, and the best a replay of that work can do on this host's cores."""
    import os

    cores = os.cpu_count() or 1
    headers: tuple[str, ...] = (
        "scans in one file",
        "floor",
        "read",
        "ingest stage",
        "finals",
        "replaying thread",
        "replay's work × floor's",
        f"best on {cores} cores: one scan / many",
    )
    out: list[tuple[str, ...]] = []
    for r in rows:
        n = r["scans"]
        floor, read = r["floor_cpu"] / n, r["read_cpu"] / n
        ingest = max(r["ingest_cpu"] / n - read, 0.0)
        finals = max(r["inline_cpu"] / n - r["ingest_cpu"] / n, 0.0)
        work = read + ingest + finals
        own = r.get("replay_thread_cpu", float("nan")) / n
        # One scan: its final reads the whole scan, so it starts when the reading ends; many: all of it shared.
        one = floor / ((read + ingest) / cores + finals) if work else float("nan")
        many = cores * floor / work if work else float("nan")
        out.append(
            (
                str(n),
                f"{1e3 * floor:.1f}",
                f"{1e3 * read:.1f}",
                f"{1e3 * ingest:.1f}",
                f"{1e3 * finals:.1f}",
                f"{1e3 * own:.1f}",
                f"{work / floor:.2f}×",
                f"{one:.2f}× / {many:.2f}×",
            )
        )
    notes = [
        "CPU ms per scan of each child's timed section (every thread of the replaying process), medians: "
        "floor = python mcap + upb; read = the tolerant reader + upb; ingest stage = decode, validate, assemble "
        "(ingest child − read); finals = the replay with every final in the process (inline child − ingest child); "
        "replaying thread = the replay child's CPU on its replaying thread alone (the reading there, the service, "
        "the finals it keeps): its wall clock cannot go under it, whatever the host",
        "best: the replay's work spread over the cores with nothing lost; a scan's final starts when its last "
        "sample is read, so a file of one scan overlaps only its reading",
    ]
    return "where a replay's time goes (CPU per scan)", headers, out, notes


def _filesystem(path: Path) -> str:
    """The filesystem type under ``path`` (fsync's cost depends on it), from /proc/mounts."""
    try:
        best, kind = "", "unknown filesystem"
        resolved = str(path.resolve())
        with open("/proc/mounts") as f:
            for line in f:
                _dev, mount, fstype, *_ = line.split()
                if resolved.startswith(mount) and len(mount) > len(best):
                    best, kind = mount, f"{fstype} ({mount})"
        return kind
    except OSError:
        return "unknown filesystem"
