"""`lelsonar batch COMMAND FILES_OR_GLOBS… --out DIR`: one command over many recordings, in parallel.

Each file runs the command's own code (``lelsonar COMMAND … FILE``, in a worker process or a Ray task),
its stdout going to the file's output in DIR.  DIR mirrors the inputs' folders below their common parent,
so equal names in two folders never collide, and ``DIR/index.jsonl`` holds one line per input, sorted by
path: the input's size, mtime and hash, the command and its flags, the output's hash, the exit code and
the counts.  Nothing in it depends on the workers, the engine or the clock, so two runs over the same
files write the same index.

A file is done, and skipped by the next run, when its index line matches the input (size, mtime, hash),
the command and flags, and the output on disk still has the recorded hash.  A file that fails is
reported, counted and retried next time; it never stops the batch.

Everything per file happens in its worker: hashing the input, checking the previous run's output, running
the command.  This process only hands the files out, writes the index and shows the progress, so the
workers, not it, set the pace.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import glob
import io
import json
import os
import resource
import shutil
import sys
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lelsonar.cli.executor import (
    ExecutorConfig,
    Outcome,
    WorkerLoad,
    add_executor_arguments,
    config_from_args,
    helpers_cpu,
    run_each,
    tree_cpu,
    worker_loads,
)
from lelsonar.cli.main import COMMAND_MODULES, main
from lelsonar.cli.paths import output_dir, output_file
from lelsonar.cli.reconstruct import compared_methods
from lelsonar.errors import ConfigError

INDEX = "index.jsonl"
#: Fields of a `reconstruct --json` line that say when and how fast this run computed it, not what it
#: computed: left out of the batch's output, which must not depend on the run.
RUN_FIELDS = ("stamp_ns", "timings")
#: What a worker imports to run any command on a file, loaded once by a local pool before it forks its
#: workers.  Nothing that starts threads at import (a Rerun or Ray runtime): a forked worker would lack them.
WORKER_MODULES = (
    *COMMAND_MODULES,
    "lelsonar.log.recording",
    "lelsonar.reconstruct.stream.observers",
    "lelsonar.reconstruct.stream.service",
    "lelsonar.reconstruct.stream.sources",
    "lelsonar.view.present",
    "xxhash",
)
#: Exit codes of `lelsonar batch`.
EXIT_OK, EXIT_SOME_FAILED = 0, 1


@dataclass(frozen=True)
class Job:
    """How one command runs on one file, and what it leaves in DIR."""

    suffix: str  # of the output beside the input's relative path
    method_flags: tuple[str, ...]  # the estimation flags the command takes
    stdout_is_output: bool  # the command's stdout is the output (else it writes ``-o`` itself)
    module: str  # the module that registers the command


JOBS: dict[str, Job] = {
    "reconstruct": Job(".jsonl", ("--method", "--compare"), True, "lelsonar.cli.reconstruct"),
    "review": Job(".rrd", ("--method", "--compare"), False, "lelsonar.cli.review"),
    "info": Job(".json", (), True, "lelsonar.cli.recordings"),
    "export": Job(".rosbag2", ("--method", "--compare"), False, "lelsonar.cli.bridge"),
    "map": Job(".json", ("--method",), True, "lelsonar.cli.map"),  # one map per recording
}

EPILOG = (
    "Outputs in DIR, per input: reconstruct → .jsonl (the lines of `reconstruct --source F --json` without "
    "stamp_ns and timings, which say when and how fast, not what), "
    "review → .rrd, info → .json (`info --json`), export → .rosbag2/ (a bag directory), map → .json "
    "(`map --source F --json`: one map per recording); and DIR/index.jsonl. "
    "Exit status: 0 when every file's command exited 0, 1 when any file failed or its command reported no "
    "result (see the summary and the index), 2 on a usage error."
)


def register(sub: argparse._SubParsersAction) -> None:
    from lelsonar.cli.reconstruct import add_method_arguments

    p = sub.add_parser(
        "batch",
        help="run reconstruct, review, info, export or map over many recordings (process pool or Ray)",
        description="Run a command over every recording that FILES_OR_GLOBS names, each file in its own "
        "worker, with a progress bar, a summary table, and an index that makes the batch resumable.",
        epilog=EPILOG,
    )
    # Stored as `job`: `command` is the subcommand's own name (`batch`), which errors and --config use.
    p.add_argument("job", metavar="command", choices=sorted(JOBS), help="the command to run on each file")
    p.add_argument("inputs", nargs="+", metavar="FILES_OR_GLOBS", help="recordings, or quoted globs ('a/*.mcap')")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="where the outputs and the index go")
    p.add_argument("--force", action="store_true", help="redo every file, even one whose output is complete")
    p.add_argument(
        "--timings",
        type=Path,
        default=None,
        metavar="FILE",
        help="also write where the time went as JSON: the wall time, the CPU time of this process and its "
        "workers, and each worker's items, busy and CPU time and start-up",
    )
    add_executor_arguments(p)
    add_method_arguments(
        p.add_argument_group("estimation (reconstruct, review, export)"),
        "also run these methods, e.g. ls,paper (default: ls; '' for none)",
    )
    p.set_defaults(run=run_batch)


def expand_inputs(patterns: list[str]) -> list[Path]:
    """The files that ``patterns`` name (globs expanded, ``**`` recursive), deduplicated, sorted by path.

    Raises
    ------
    ConfigError
        A pattern that names nothing (a typo must not pass as an empty batch).
    """
    found: set[Path] = set()
    for pattern in patterns:
        hits = [Path(h) for h in glob.glob(pattern, recursive=True)] if glob.has_magic(pattern) else [Path(pattern)]
        hits = [h for h in hits if h.is_file()]
        if not hits:
            raise ConfigError(f"{pattern!r} names no file")
        found.update(h.resolve() for h in hits)
    return sorted(found)


def relative_names(paths: list[Path]) -> list[Path]:
    """Each path relative to the inputs' common parent folder (the layout mirrored in DIR)."""
    root = Path(os.path.commonpath([p.parent for p in paths]))
    return [p.relative_to(root) for p in paths]


def file_hash(path: Path) -> str:
    """xxh3-128 of a file's bytes, or of a directory's files (names and bytes, sorted by name)."""
    import xxhash

    h = xxhash.xxh3_128()
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    for f in files:
        if path.is_dir():
            h.update(str(f.relative_to(path)).encode() + b"\0")
        with open(f, "rb") as fh:
            while chunk := fh.read(1 << 20):
                h.update(chunk)
    return h.hexdigest()


def fingerprint(path: Path) -> dict[str, Any]:
    st = path.stat()
    return {"size": st.st_size, "mtime_ns": st.st_mtime_ns, "hash": file_hash(path)}


def command_argv(command: str, source: Path, output: Path, flags: list[str]) -> list[str]:
    """The ``lelsonar`` argv that processes one file, as a user would type it.

    A file's finals are estimated in its own process (``--jobs 0``): the batch already spreads the files over
    the cores, and a pool of final workers per file would only compete with them.
    """
    if command == "reconstruct":
        return ["reconstruct", "--source", str(source), "--json", "--jobs", "0", *flags]
    if command == "info":
        return ["info", "--json", str(source), *flags]
    if command == "map":
        return ["map", "--source", str(source), "--json", "--jobs", "0", *flags]
    return [command, str(source), "-o", str(output), "--jobs", "0", *flags]


def process_input(
    command: str, source: str, out_dir: str, key: dict[str, Any], previous: dict[str, Any] | None
) -> dict[str, Any]:
    """One input's index line: the input fingerprinted, skipped when ``previous`` records it complete, else
    run by :func:`process_file`.

    ``key`` holds the input's name, the command, its flags and the output's name; the line adds the
    input's fingerprint and the run's fields.  Everything per file happens here, in the worker: hashing
    the input and checking the output take no time from the process that hands the files out.
    """
    key = {**key, **_prefixed(fingerprint(Path(source)))}
    if previous is not None and is_complete(previous, key, Path(out_dir)):
        return {**previous, "skipped": True}
    result = process_file(command, source, str(Path(out_dir) / key["output"]), key["flags"])
    return {**key, **result}


def process_file(command: str, source: str, output: str, flags: list[str]) -> dict[str, Any]:
    """Run ``lelsonar COMMAND`` on one file in this process; write its output atomically.

    Returns the index fields of the run: ``rc``, ``output_hash`` (None when nothing was written),
    ``error`` (the command's last stderr line when it failed), the counts of :func:`count_results`, and
    ``seconds`` (for the summary only: the index holds nothing that varies between runs).  An exception
    in the command propagates (the executor reports it).
    """
    job = JOBS[command]
    out = Path(output)
    # Written in a folder of its own, then moved: a bag's files are named after its final directory, and a
    # worker that dies leaves no output the index could take for complete.
    staging = out.parent / f".{out.name}.partial"
    _remove(staging)
    staging.mkdir(parents=True)
    partial = staging / out.name
    stdout, stderr = io.StringIO(), io.StringIO()
    t0 = time.perf_counter()
    try:
        with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
            rc = main(command_argv(command, Path(source), partial, flags))
        text = stdout.getvalue()
        if command == "reconstruct":
            text = without_run_fields(text)
        if job.stdout_is_output and rc in (0, 1):
            partial.write_text(text)
        result: dict[str, Any] = {"rc": rc, "output_hash": None, "error": None, "seconds": time.perf_counter() - t0}
        if rc not in (0, 1):
            lines = [line for line in stderr.getvalue().splitlines() if line.strip()]
            result["error"] = lines[-1] if lines else f"exit code {rc}"
        if partial.exists():
            _remove(out)
            os.replace(partial, out)
            result["output_hash"] = file_hash(out)
    finally:
        _remove(staging)
    result.update(count_results(command, text))
    return result


def without_run_fields(text: str) -> str:
    """`reconstruct --json` lines without :data:`RUN_FIELDS`, written as the command writes them."""
    out = []
    for line in text.splitlines():
        if line.strip():
            d = json.loads(line)
            for key in RUN_FIELDS:
                d.pop(key, None)
            out.append(json.dumps(d, separators=(",", ":"), sort_keys=True) + "\n")
    return "".join(out)


def count_results(command: str, text: str) -> dict[str, Any]:
    """``scans``, ``statuses`` and ``verdicts`` (plane qualities) from a command's stdout, where it says them."""
    if command == "reconstruct":
        msgs = [json.loads(line) for line in text.splitlines() if line.strip()]
        return {
            "scans": len(msgs),
            "statuses": dict(sorted(Counter(m.get("status", "?") for m in msgs).items())),
            "verdicts": dict(sorted(Counter(p.get("quality", "?") for m in msgs for p in m.get("planes", [])).items())),
        }
    if command == "info" and text.strip():
        d = json.loads(text)
        return {
            "scans": len(d.get("scans", [])),
            "statuses": dict(sorted(Counter(s.get("status", "?") for s in d.get("scans", [])).items())),
            "verdicts": dict(
                sorted(Counter(p.get("quality", "?") for e in d.get("estimates", []) for p in e["planes"]).items())
            ),
        }
    if command == "export":  # `export` prints "<count>  <topic>" per topic: one estimate per scan
        for line in text.splitlines():
            count, _, topic = line.strip().partition(" ")
            if topic.strip() == "/lelsonar/estimate" and count.isdigit():
                return {"scans": int(count), "statuses": {}, "verdicts": {}}
    return {"scans": None, "statuses": {}, "verdicts": {}}


def _remove(path: Path) -> None:
    if path.is_dir():
        shutil.rmtree(path)
    else:
        path.unlink(missing_ok=True)


def read_index(path: Path) -> dict[str, dict[str, Any]]:
    """The index's lines by input (the last line of an input wins; a torn last line is ignored)."""
    lines: dict[str, dict[str, Any]] = {}
    if not path.is_file():
        return lines
    for line in path.read_text().splitlines():
        try:
            d = json.loads(line)
            lines[d["input"]] = d
        except (ValueError, KeyError, TypeError):
            continue
    return lines


def is_complete(line: dict[str, Any] | None, key: dict[str, Any], out_dir: Path) -> bool:
    """Whether an index line records this very input and flags, run to its end, with its output intact."""
    if line is None or line.get("rc") not in (0, 1) or line.get("output_hash") is None:
        return False
    if any(line.get(k) != v for k, v in key.items()):
        return False
    output = out_dir / line["output"]
    return output.exists() and file_hash(output) == line["output_hash"]


def run_batch(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    job = JOBS[args.job]
    if job.module not in COMMAND_MODULES:
        raise ConfigError(f"`lelsonar {args.job}` does not exist in this version; batch runs it where it does")
    config = config_from_args(args)
    inputs = expand_inputs(args.inputs)
    names = relative_names(inputs)
    values = {"--method": args.method, "--compare": args.compare}
    flags = [part for flag in job.method_flags for part in (flag, values[flag])]
    if "--compare" in job.method_flags:
        compared_methods(args)  # a name that is no method fails here, not in every file's worker
    if args.timings is not None:  # a file of each run, replaced by the next
        output_file(args.timings, overwrite=True, what="--timings file")
    out_dir = output_dir(args.out, what="--out")
    index_path = out_dir / INDEX
    recorded = read_index(index_path)
    previous = {} if args.force else recorded

    # Bound to this stderr: a command running in this process (--workers 1) has its own redirected.
    console = Console(file=sys.stderr)
    console = console if console.is_terminal else Console(file=sys.stderr, width=120)
    keys = []
    for name in names:
        output = name.with_name(name.name.removesuffix(".mcap") + job.suffix)
        keys.append({"input": str(name), "command": args.job, "flags": flags, "output": str(output)})
    items = [(args.job, str(path), str(out_dir), key, previous.get(key["input"])) for path, key in zip(inputs, keys)]
    lines: dict[str, dict[str, Any]] = {}
    times: dict[str, float] = {}
    outcomes: list[Outcome] = []
    started, since, cpu_start = time.perf_counter(), time.time(), time.process_time()
    with (
        open(index_path, "a") as log,
        Progress(
            TextColumn(f"batch {args.job}"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("{task.fields[failed]} failed"),
            TimeElapsedColumn(),
            console=console,
            transient=True,
            refresh_per_second=2,  # its thread renders the bar: kept light beside the workers
        ) as bar,
    ):
        task = bar.add_task("files", total=len(items), failed=0)
        failed = 0
        for i, outcome in run_each(process_input, items, config, preload=WORKER_MODULES):
            outcomes.append(outcome)
            key = keys[i]
            if outcome.ok:
                line = outcome.value
                if not line.get("skipped"):
                    times[key["input"]] = line.pop("seconds")
            else:
                line = {**key, **_prefixed(_fingerprint_or_none(inputs[i]))}
                line.update(rc=None, output_hash=None, error=outcome.error, **count_results("", ""))
            lines[key["input"]] = line
            if not line.get("skipped"):
                log.write(json.dumps(line, sort_keys=True) + "\n")  # kept as it comes: a killed batch resumes
                log.flush()
            if line["rc"] != 0 and not line.get("skipped"):
                failed += 1
            bar.update(task, advance=1, failed=failed)
    wall = time.perf_counter() - started
    cpu_end = time.process_time()
    ordered = [lines[k] for k in sorted(lines)]
    # The lines of inputs outside this run stay: a batch over part of an archive keeps the rest resumable.
    index = {**recorded, **lines}
    tmp = index_path.with_name(INDEX + ".partial")
    tmp.write_text("".join(json.dumps(_clean(index[k]), sort_keys=True) + "\n" for k in sorted(index)))
    os.replace(tmp, index_path)
    loads = worker_loads(outcomes, since)
    _print_summary(console, args.job, ordered, times, wall, config)
    _print_workers(console, loads, wall, config)
    if args.timings is not None:
        write_timings(args.timings, wall, config, loads, (cpu_start, cpu_end))
    return EXIT_OK if all(line["rc"] == 0 for line in ordered) else EXIT_SOME_FAILED


def _fingerprint_or_none(path: Path) -> dict[str, Any]:
    try:
        return fingerprint(path)
    except OSError:
        return {"size": None, "mtime_ns": None, "hash": None}


def _prefixed(fp: dict[str, Any]) -> dict[str, Any]:
    return {f"input_{k}": v for k, v in fp.items()}


def _clean(line: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in line.items() if k != "skipped"}


def _print_summary(console, command: str, lines: list[dict[str, Any]], times, wall: float, config) -> None:
    from rich.table import Table

    table = Table(title=f"lelsonar batch {command}: {len(lines)} files", title_justify="left")
    for col in ("file", "status", "scans", "scan status", "verdicts", "time"):
        table.add_column(col, justify="right" if col in ("scans", "time") else "left")
    for line in lines:
        if line.get("skipped"):
            status = "[dim]done before[/]"
        elif line["rc"] == 0:
            status = "ok"
        elif line["rc"] == 1:
            status = "[yellow]no result[/]"
        else:
            status = f"[red]failed[/]: {line.get('error') or 'exit ' + str(line['rc'])}"
        t = times.get(line["input"])
        table.add_row(
            line["input"],
            status,
            "—" if line.get("scans") is None else str(line["scans"]),
            ", ".join(f"{k} {v}" for k, v in line.get("statuses", {}).items()) or "—",
            ", ".join(f"{k} {v}" for k, v in line.get("verdicts", {}).items()) or "—",
            "—" if t is None else f"{t:.1f} s",
        )
    console.print(table)
    n_failed = sum(1 for line in lines if line["rc"] not in (0, 1))
    n_empty = sum(1 for line in lines if line["rc"] == 1)
    n_skipped = sum(1 for line in lines if line.get("skipped"))
    where = {
        "ray": "on Ray",
        "inline": "in this process",
        "pool": f"on {config.worker_count} worker processes",
    }[config.engine]
    console.print(
        f"batch {command}: {len(lines) - n_failed - n_empty} ok, {n_empty} without result, {n_failed} failed, "
        f"{n_skipped} done before; {wall:.1f} s {where}",
        highlight=False,
    )


def _print_workers(console, loads: list[WorkerLoad], wall: float, config: ExecutorConfig) -> None:
    """One line: how busy the workers were, how long the slowest took to start, and the CPU time spent
    (on this machine: Ray's workers are not this process's children)."""
    if not loads or wall <= 0:
        return
    busy = sum(load.busy for load in loads) / (wall * len(loads))
    start = max(load.first_start for load in loads)
    cpu = "" if config.engine == "ray" else f"; CPU {tree_cpu():.1f} s in all"
    console.print(
        f"{len(loads)} worker{'s' if len(loads) > 1 else ''} busy {busy:.0%} of the time, the last one's first "
        f"file after {start:.1f} s{cpu}",
        highlight=False,
    )


def write_timings(
    path: Path, wall: float, config: ExecutorConfig, loads: list[WorkerLoad], loop_cpu: tuple[float, float]
) -> None:
    """The run's timings as JSON (see ``--timings``): never part of the index, which must not vary.

    ``loop_cpu`` is this process's CPU time when the first file was handed out and when the last came back.
    The document splits this process's CPU into before the files (its start-up), while they ran (handing
    them out and collecting their results; files that ran in this process excluded) and after (the index,
    the summary); ``cpu_helpers_s`` is the fork server's and the resource tracker's own.
    """
    own = resource.getrusage(resource.RUSAGE_SELF)
    this = own.ru_utime + own.ru_stime
    inline = sum(load.cpu for load in loads) if config.engine == "inline" else 0.0
    start, end = loop_cpu
    doc = {
        "engine": config.engine,
        "workers": config.worker_count,
        "wall_s": wall,
        "cpu_this_process_s": this,
        "cpu_before_files_s": start,
        "cpu_hand_out_s": max(0.0, end - start - inline),
        "cpu_after_files_s": max(0.0, this - end),
        "cpu_helpers_s": helpers_cpu(),
        "cpu_all_s": tree_cpu(),
        "per_worker": [dataclasses.asdict(load) for load in loads],
    }
    path.write_text(json.dumps(doc, indent=1) + "\n")
