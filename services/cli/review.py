"""`lelsonar review`: a recording reconstructed offline into a Rerun .rrd with the default layout."""

from __future__ import annotations

import argparse
from pathlib import Path

from lelsonar.cli.reconstruct import (
    add_estimator_arguments,
    add_truth_preset_argument,
    open_source,
    report_replay,
    service_config,
)


def register(sub: argparse._SubParsersAction) -> None:
    from lelsonar.cli.paths import add_overwrite_argument

    p = sub.add_parser(
        "review",
        help="reconstruct a recording offline into a Rerun .rrd with the default layout",
        description="Replay a recording through the reconstruction, step by step as it was acquired, into a "
        "Rerun recording (.rrd) with the default layout; print the final planes on stdout.",
    )
    p.add_argument("source", type=Path, metavar="FILE.mcap", help="the recording to review")
    p.add_argument(
        "-o", "--output", type=Path, metavar="FILE.rrd", help="the Rerun recording to write (default: FILE.rrd)"
    )
    p.add_argument(
        "--screenshot",
        type=Path,
        metavar="FILE.png",
        help="also draw the final step (points, final planes, R) with matplotlib into an image, from the data "
        "the .rrd gets (the README's docs/review.png is made so)",
    )
    add_truth_preset_argument(p, "draw the true planes of a simulator preset")
    add_overwrite_argument(p)
    add_estimator_arguments(p, scan_timeout=False)
    p.set_defaults(run=run_review)


def run_review(args: argparse.Namespace) -> int:
    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

    from lelsonar.cli.paths import output_file
    from lelsonar.errors import ConfigError
    from lelsonar.log.recording import read_metadata, truth_world
    from lelsonar.reconstruct.stream.observers import combine
    from lelsonar.reconstruct.stream.replay import replay_mcap
    from lelsonar.reconstruct.stream.service import ReconstructionService
    from lelsonar.view import present
    from lelsonar.view.rerun_observer import open_rerun

    source = open_source(args.source)
    out = output_file(args.output or args.source.with_suffix(".rrd"), overwrite=args.overwrite, what="review file")
    shot = None
    if args.screenshot is not None:
        from lelsonar.view.snapshot import SnapshotObserver, check_image_path

        shot = SnapshotObserver(main_method=args.method, truth_preset=args.truth_preset)
        check_image_path(output_file(args.screenshot, overwrite=args.overwrite, what="screenshot"))
    files = [Path(f).resolve() for f in (args.source, out, args.screenshot) if f is not None]
    if len(set(files)) < len(files):
        raise ConfigError("the recording, the review file and the screenshot must be three different files")
    config = service_config(args)  # its flags refused before the review file is made
    total = source.expected_payloads()
    console = present.console(stderr=True)
    from lelsonar.cli.warm_up import ensure_compiled

    ensure_compiled(console)
    world = truth_world(read_metadata(source).get("lelsonar.config"))  # a simulated world, drawn as truth
    with (
        open_rerun(
            rrd=out,
            application_id="lelsonar",
            truth_preset=args.truth_preset,
            main_method=args.method,
            truth_world=world,
        ) as observer,
        Progress(
            TextColumn("review"),
            BarColumn(),
            TextColumn("{task.completed}/{task.total} messages"),
            TimeRemainingColumn(),
            console=console,
            transient=True,
        ) as progress,
    ):
        task = progress.add_task("replay", total=total)
        service = ReconstructionService(config, observer=combine(observer, shot))
        replay_mcap(source, service, on_payload=lambda _t: progress.advance(task))
    report_replay(source)
    tables = present.console()
    for msg in service.finals.values():
        tables.print(present.planes_table(msg))
        surfaces = present.surfaces_table(msg)
        if surfaces is not None:
            tables.print(surfaces)
    console.print(f"wrote {out} — open it with: rerun {out}", highlight=False)
    if shot is not None:
        console.print(f"wrote {shot.save(args.screenshot)}", highlight=False)
    return 0 if service.finals else 1
