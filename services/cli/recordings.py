"""`lelsonar recover IN -o OUT` and `lelsonar info FILE... [--json]`."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    from lelsonar.cli.paths import add_overwrite_argument

    p = sub.add_parser(
        "recover",
        help="rewrite a cut, unfinished or corrupted recording as a valid, indexed MCAP",
        description="Salvage every intact message of IN (chunks that fail their CRC or decompression are skipped "
        "and counted) and write them, with their channels, schemas and metadata, to a new MCAP file "
        "with a summary and indexes. Like `mcap recover`.",
    )
    p.add_argument("source", type=Path, metavar="IN.mcap", help="the damaged or unfinished recording (left as is)")
    p.add_argument(
        "-o", "--output", type=Path, required=True, metavar="OUT.mcap", help="the repaired recording to write"
    )
    add_overwrite_argument(p)
    p.add_argument(
        "--compression",
        choices=("zstd", "lz4", "none"),
        default="zstd",
        help="chunk compression of the output (default: %(default)s)",
    )
    p.set_defaults(run=run_recover)

    p = sub.add_parser(
        "info",
        help="summarise recordings: scans, steps, channels, damage, estimates",
        description="Per file: scans and scanners, steps received against planned with the missing ones, duration, "
        "device, channels with message counts, damaged parts, and the final estimates if the file "
        "holds Reconstruction messages. Works on damaged and unfinished files.",
    )
    p.add_argument("files", type=Path, nargs="+", metavar="FILE.mcap", help="the recordings to summarise")
    p.add_argument("--json", action="store_true", help="one JSON object per file (SI units, times in Unix ns)")
    p.set_defaults(run=run_info)


def run_recover(args: argparse.Namespace) -> int:
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    from lelsonar import codec
    from lelsonar.cli.paths import input_file, output_file
    from lelsonar.errors import ConfigError, RecordingError
    from lelsonar.log.recording import Recording, describe_damage
    from lelsonar.log.recover import recover

    input_file(args.source)
    output_file(args.output, overwrite=args.overwrite, what="recovered file")
    if args.output.resolve() == args.source.resolve():
        raise ConfigError("recover writes a new file: give -o another name than the input")
    report = recover(args.source, args.output, compression=args.compression)
    s = report.source
    if report.messages_written == 0:
        args.output.unlink(missing_ok=True)
        raise RecordingError(
            f"nothing to recover in {args.source}: no intact message"
            + (f" ({describe_damage(s)})" if not s.intact else "")
        )
    try:  # the output must open in the indexed reader, message for message
        with open(args.output, "rb") as f:
            reader = make_reader(f)
            summary = reader.get_summary()
            indexed = sum(1 for _ in reader.iter_messages())
    except (McapError, ValueError, EOFError) as exc:
        raise RecordingError(f"the recovered {args.output} does not read back ({exc}); please report this") from None
    if summary is None or indexed != report.messages_written:
        raise RecordingError(
            f"the recovered {args.output} reads back {indexed} of {report.messages_written} "
            "messages; please report this"
        )
    samples = Recording(s).count(codec.Sample)
    state = "intact" if s.intact else describe_damage(s)
    print(
        f"recovered {report.messages_written} messages ({samples} samples) on {report.channels_written} channels "
        f"from {args.source} into {args.output}; the input {state}",
        file=sys.stderr,
    )
    return 0


def run_info(args: argparse.Namespace) -> int:
    """Each file in turn; one that cannot be read is one line on stderr, and the exit code is then 2.

    A closed stdout (``| head -1``) ends the command with 141, as for every command.
    """
    from lelsonar.cli.paths import input_file
    from lelsonar.errors import RecordingError
    from lelsonar.log.summary import summarize

    status = 0
    for path in args.files:
        try:
            info = summarize(input_file(path))
        except RecordingError as exc:
            print(f"lelsonar info: error: {exc}", file=sys.stderr, flush=True)
            status = 2
            continue
        if args.json:
            print(json.dumps(info.as_dict(), separators=(",", ":"), sort_keys=True), flush=True)
        else:
            _print_info(info)
    return status


def _ns(t: int | None) -> str:
    if t is None:
        return "—"
    import datetime as dt

    return dt.datetime.fromtimestamp(t / 1e9, dt.UTC).strftime("%Y-%m-%d %H:%M:%S.%f")[:-3] + " UTC"


def _print_info(info) -> None:
    from rich.table import Table

    from lelsonar.log.summary import step_ranges
    from lelsonar.view import present

    c = present.console()
    state = "finished, intact" if info.intact else f"[yellow]{info.damage_text}[/]"
    c.print(f"[bold]{info.path}[/]  {info.size:,} bytes — {state}", highlight=False)
    dur = f"{info.duration_s:.2f} s" if info.duration_s is not None else "—"
    c.print(f"  time      {_ns(info.start_ns)} → {_ns(info.end_ns)} ({dur})", highlight=False)
    c.print(f"  device    {info.device or '—'}    scanners: {', '.join(info.scanners) or '—'}", highlight=False)
    lost = f"{'' if info.messages_lost_exact else '≈'}{info.messages_lost}"
    c.print(f"  messages  {info.messages} intact, {lost} lost", highlight=False)

    t = Table(title="channels", title_justify="left")
    for col in ("topic", "schema", "messages", "lost"):
        t.add_column(col, justify="right" if col in ("messages", "lost") else "left")
    for ch in info.channels:
        t.add_row(ch.topic, ch.schema, str(ch.messages), "?" if ch.lost is None else str(ch.lost))
    c.print(t)

    if info.scans:
        t = Table(title="scans", title_justify="left")
        for col in ("scanner", "scan", "device", "status", "steps", "missing steps", "duration"):
            t.add_column(col, justify="right" if col in ("steps", "duration") else "left")
        for sc in info.scans:
            planned = "?" if sc.steps_planned is None else str(sc.steps_planned)
            status = sc.status + (f" ({sc.reason})" if sc.reason else "") + "".join(f"; {u}" for u in sc.unreadable)
            dur = f"{sc.duration_s:.2f} s" if sc.duration_s is not None else "—"
            t.add_row(
                sc.scanner_id,
                str(sc.scan_id),
                sc.device or "—",
                status,
                f"{sc.steps_received}/{planned}",
                step_ranges(sc.missing_steps) or "none",
                dur,
            )
        c.print(t)
    else:
        c.print("  no lelsonar scans in this file")

    for d in info.damage:
        n = f"{'' if d['exact'] else '≈'}{d['messages_lost']} messages"
        c.print(
            f"  [yellow]damaged[/] {d['kind']} at byte {d['offset']} ({d['length']} bytes, {n}): {d['reason']}",
            highlight=False,
        )

    for est in info.estimates:
        crit = f"critical step {est.critical_step}" if est.critical_step is not None else "no corner"
        t = Table(
            title=f"estimate: {est.scanner_id} scan {est.scan_id} — {est.status}, {est.samples_used} samples, {crit}",
            title_justify="left",
        )
        for col in ("plane", "method", "normal n", "h (cm)", "σ (mm)", "inliers", "quality"):
            t.add_column(col, justify="right" if col in ("h (cm)", "σ (mm)", "inliers") else "left")
        for p in est.planes:
            n = p["normal"]
            t.add_row(
                p["label"],
                p["method"],
                f"{n[0]:+.3f} {n[1]:+.3f} {n[2]:+.3f}",
                f"{p['offset'] * 100:.2f}",
                f"{p['sigma'] * 1000:.1f}",
                f"{p['inliers']}/{p['points']}",
                p["quality"],
            )
        c.print(t)
