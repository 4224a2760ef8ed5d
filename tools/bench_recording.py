"""``lelsonar bench recording``: what durable recording costs.

The acquisition recorder hands every step to the OS before the step is
published: one MCAP chunk per step (Sample, /tf and points), flushed.  This
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
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

from lelsonar import codec

#: Each row: its label and the McapRecorder options it measures.
ROWS: tuple[tuple[str, dict[str, bool]], ...] = (
    ("before: 1 MiB chunks", {"durable": False}),
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
    open_recording(path).payloads()
    return time.perf_counter() - t


def run(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.table import Table

    from lelsonar.log.reader import salvage
    from lelsonar.tools.bench import machine
    from lelsonar.tools.bench_acquire import host_busy, host_line

    console = Console()
    console = console if console.is_terminal else Console(width=120)
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
    table = Table(
        title=f"writing one {args.preset} scan ({steps} steps, {len(msgs)} contract messages, "
        f"each Sample with /tf and points) — medians of {args.runs}",
        title_justify="left",
    )
    for col in ("compression", "recorder", "chunks", "write ms", "µs/step", "× before", "MB", "read ms"):
        table.add_column(col, justify="left" if col in ("compression", "recorder") else "right")
    for comp in args.compression:
        base = statistics.median(times[(comp, ROWS[0][0])])
        for name, _ in ROWS:
            med = statistics.median(times[(comp, name)])
            table.add_row(
                comp,
                name,
                str(chunks[(comp, name)]),
                f"{1e3 * med:.1f}",
                f"{1e6 * med / steps:.0f}",
                f"{med / base:.2f}",
                f"{sizes[(comp, name)] / 1e6:.2f}",
                f"{1e3 * statistics.median(reads[(comp, name)]):.1f}",
            )
    console.print(table)
    console.print(f"machine: {machine()}; files on {fs}; {host_line(busy)}")
    console.print("fsync's cost is the disk's: on a shared or loaded host it varies several-fold between runs")
    console.print(f"command: {command_line(args)}")
    return 0


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
