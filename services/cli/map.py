"""`lelsonar map`: walls fused across the scans of recordings into one map (JSON, GeoJSON, a route)."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from lelsonar.cli.values import count


def register(sub: argparse._SubParsersAction) -> None:
    from lelsonar.cli.map_views import add_mapper_view_arguments, add_view_arguments
    from lelsonar.cli.reconstruct import add_jobs_argument
    from lelsonar.reconstruct.estimate.pipeline import DEFAULT_METHOD, METHODS

    p = sub.add_parser(
        "map",
        help="fuse the walls of several scans (recordings) into one map",
        description="Replay each recording through the reconstruction, take each scan's surfaces, corners and "
        "edges (its two planes of record where the reconstruction extracted no surfaces) as observations at the "
        "scan's pose (ScanStart; the origin where a recording has none), fuse them across scans (GTSAM factor "
        "graph) and print the map: walls with σ and verdict, corners, edges, corrected poses (world frame, m "
        "and rad).",
    )
    p.add_argument(
        "--source",
        type=Path,
        nargs="+",
        required=True,
        metavar="FILE.mcap",
        help="recordings, in any order: the scans are fused in the order they started",
    )
    p.add_argument("--scanner", help="only this scanner's scans (needed when the recordings hold several)")
    p.add_argument("--json", action="store_true", help="print the map as one JSON object")
    p.add_argument("--geojson", type=Path, metavar="FILE", help="also write the floor plan as GeoJSON")
    p.add_argument(
        "--grid", type=Path, metavar="FILE", help="also write the occupancy grid (nav_msgs/OccupancyGrid fields, JSON)"
    )
    p.add_argument(
        "--route",
        action="store_true",
        help="plan a route from the first pose out of the map (or to --goal) and print it",
    )
    p.add_argument("--goal", metavar="X,Y", help="the route's goal in the map frame, m (default: out of the map)")
    p.add_argument(
        "--robot-radius", type=float, default=0.15, metavar="M", help="the route keeps this from walls (default 0.15)"
    )
    p.add_argument("--resolution", type=float, default=0.05, metavar="M", help="grid cell size (default 0.05)")
    p.add_argument(
        "--method",
        default=DEFAULT_METHOD,
        choices=sorted(METHODS),
        help=f"estimator of record (default: {DEFAULT_METHOD})",
    )
    add_jobs_argument(p)
    _add_fusion_arguments(p)
    add_view_arguments(p)
    p.set_defaults(run=run_map_with_views)

    from lelsonar.cli.paths import add_overwrite_argument
    from lelsonar.cli.secure import add_secure_argument
    from lelsonar.net.transport import add_zenoh_arguments

    p = sub.add_parser(
        "mapper",
        help="keep one scanner's map live from its scans and estimates, published on <prefix>/map",
        description="Listen to <prefix>/<scanner>/scan (poses) and <prefix>/<scanner>/planes (final estimates), "
        "fuse each scan into the map (one update per scan) and publish it as a Map on <prefix>/map (a get there "
        "returns the latest).",
    )
    p.add_argument("--scanner", required=True, help="the scanner (one robot) whose scans make the map")
    p.add_argument(
        "--method",
        default=DEFAULT_METHOD,
        choices=sorted(METHODS),
        help=f"estimator of record (default: {DEFAULT_METHOD})",
    )
    p.add_argument("--record", type=Path, metavar="FILE.mcap", help="record every map to an MCAP file")
    add_overwrite_argument(p)
    p.add_argument("--until-scans", type=count, default=0, metavar="N", help="exit after N scans are mapped")
    p.add_argument("--json", action="store_true", help="print each map as one JSON line (as map --json)")
    _add_fusion_arguments(p)
    add_zenoh_arguments(p, default_mode="client")
    add_secure_argument(p)
    add_mapper_view_arguments(p)
    p.set_defaults(run=run_mapper)


def _add_fusion_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("fusion", "map and mapper give the same map from the same scans with the same flags")
    g.add_argument(
        "--gate",
        type=float,
        default=None,
        metavar="CHI2",
        help="association gate, χ² with 2 dof (default 13.8: p = 0.999)",
    )
    g.add_argument(
        "--no-polish",
        action="store_true",
        help="read the map as ISAM2 leaves it, without a final Levenberg–Marquardt pass (cheaper on large maps)",
    )


def _fusion_config(args: argparse.Namespace):
    from lelsonar.map.fusion import FusionConfig

    extra = {} if args.gate is None else {"gate_chi2": args.gate}
    return FusionConfig(polish=not args.no_polish, **extra)


def _goal(text: str | None) -> tuple[float, float] | None:
    from lelsonar.errors import ConfigError

    if text is None:
        return None
    try:
        x, y = (float(v) for v in text.split(","))
    except ValueError:
        raise ConfigError(f"--goal takes X,Y in metres (e.g. 5.6,3.5), got {text!r}") from None
    return x, y


def scans_of(path: Path, method: str, jobs: int | None = None) -> list:
    """Each final scan of one recording: ``(start time ns, scanner id, the map's observation)``.

    The recording is replayed through the reconstruction (as ``reconstruct --source`` does) and each
    scan's ``ScanStart`` gives its pose.
    """
    from lelsonar import codec
    from lelsonar.log.recording import iter_payloads, open_recording
    from lelsonar.map.from_reconstruction import scan_from_reconstruction
    from lelsonar.reconstruct.stream.config import ReconstructConfig
    from lelsonar.reconstruct.stream.replay import replay_mcap
    from lelsonar.reconstruct.stream.service import ReconstructionService

    source = open_recording(path).require_scans()
    if (line := source.damage_warning()) is not None:
        print(line, file=sys.stderr, flush=True)
    starts = {}
    for rec in iter_payloads(source):
        if rec.type_name == codec.ScanStart.DESCRIPTOR.full_name:
            start = codec.decode(rec.payload, codec.ScanStart)
            starts[(start.scanner_id, start.scan_id)] = start
    config = ReconstructConfig(method=method, compare_methods=(), provisional=False, final_workers=jobs)
    service = ReconstructionService(config)
    replay_mcap(source, service)
    out = []
    for m in service.finals.values():
        its_start = starts.get((m.scanner_id, m.scan_id))
        t = its_start.start_time_ns if its_start is not None else 0
        out.append((t, m.scanner_id, scan_from_reconstruction(m, its_start, method)))
    return out


def run_map(args: argparse.Namespace) -> int:
    from lelsonar.cli.reconstruct import final_workers
    from lelsonar.errors import ConfigError, InvalidMessageError
    from lelsonar.keys import validate_identifier
    from lelsonar.map import floorplan
    from lelsonar.map.fusion import WallMapper
    from lelsonar.map.result import map_to_dict

    goal = _goal(args.goal)
    plan = floorplan.PlanConfig(robot_radius=args.robot_radius, resolution=args.resolution)
    config = _fusion_config(args)
    if args.scanner is not None:
        validate_identifier(args.scanner)
    _check_plan_outputs(args)
    views = getattr(args, "map_views", None)  # the viewer outputs (run_map_with_views), opened below
    found: list = []
    where: dict[int, Path] = {}
    others: set[str] = set()  # the scanners --scanner left out
    for path in args.source:
        for t, scanner, scan in scans_of(path, args.method, final_workers(args)):
            if args.scanner is not None and scanner != args.scanner:
                others.add(scanner)
                continue
            if scan.scan_id in where:
                raise InvalidMessageError(
                    f"scan {scan.scan_id} is in both {where[scan.scan_id]} and {path}: give each scan once"
                )
            where[scan.scan_id] = path
            found.append((t, scan.scan_id, scanner, scan))
    scanners = sorted({f[2] for f in found})
    if len(scanners) > 1:
        raise ConfigError(f"the recordings hold the scans of {', '.join(scanners)}: choose one robot with --scanner")
    # The robot's path is the order its scans started in, whatever the order of the files.
    scans = [f[3] for f in sorted(found, key=lambda f: (f[0], f[1]))]
    if not scans and others:
        raise ConfigError(
            f"the recordings hold no scan of scanner {args.scanner}: they hold {', '.join(sorted(others))}"
        )
    if not scans:
        print("lelsonar map: no final scan in the recordings", file=sys.stderr)
        return 1
    if views is not None:
        views.open()
    mapper = WallMapper(config)
    for scan in scans:
        mapper.add_scan(scan)
        if views is not None:
            views.add(mapper.snapshot(), scanners[0])
    fused = mapper.snapshot()
    out = map_to_dict(fused)
    if args.route:
        start = (fused.poses[0].x, fused.poses[0].y)
        path = floorplan.route(fused, start, goal, plan)
        out["route"] = None if path is None else [{"x": x, "y": y} for x, y in path]
        out["route_unseen_m"] = None if path is None else floorplan.unseen_length(fused, path, plan)
    if args.geojson:
        args.geojson.write_text(json.dumps(floorplan.to_geojson(fused, plan)))
    if args.grid:
        args.grid.write_text(json.dumps(floorplan.occupancy_grid(fused, plan).to_message()))
    if views is not None:
        views.finish(None if out.get("route") is None else [(p["x"], p["y"]) for p in out["route"]])
    if args.json:
        print(json.dumps(out, separators=(",", ":")))
    else:
        _print_table(out)
    return 0 if not args.route or out["route"] is not None else 1


def _check_plan_outputs(args: argparse.Namespace) -> None:
    """``--geojson`` and ``--grid`` checked before the replay: new files (unless ``--overwrite``), not the
    recordings.

    Raises
    ------
    ConfigError
        An output exists (without ``--overwrite``), is a directory, cannot be made, or is a recording read.
    """
    from lelsonar.cli.paths import output_file
    from lelsonar.errors import ConfigError

    sources = {Path(s).resolve() for s in args.source}
    for flag, path in (("--geojson", args.geojson), ("--grid", args.grid)):
        if path is not None:
            output_file(path, overwrite=args.overwrite, what=f"{flag} file")
            if Path(path).resolve() in sources:
                raise ConfigError("the recordings and the output files must differ")


def run_map_with_views(args: argparse.Namespace) -> int:
    """`lelsonar map` with its viewer outputs checked before the replay, opened once it gave scans to draw,
    and finished on any exit."""
    from lelsonar.cli.map_views import MapViews, wants_views
    from lelsonar.map.floorplan import PlanConfig

    if not wants_views(args):
        return run_map(args)
    args.map_views = MapViews(args, PlanConfig(robot_radius=args.robot_radius, resolution=args.resolution))
    try:
        return run_map(args)
    finally:
        args.map_views.close()


def _print_table(out: dict) -> None:
    from rich.table import Table

    from lelsonar.view import present

    console = present.console()
    t = Table(title=f"map: {len(out['walls'])} walls, {len(out['corners'])} corners, {len(out['poses'])} poses")
    for col in ("wall", "normal (x, y)", "offset m", "σ normal °", "σ offset mm", "quality", "scans", "reasons"):
        t.add_column(col)
    for w in out["walls"]:
        t.add_row(
            str(w["id"]),
            f"{w['normal']['x']:+.3f}, {w['normal']['y']:+.3f}",
            f"{w['offset']:.3f}",
            f"{math.degrees(w['normal_stderr']):.2f}",
            f"{1000 * w['offset_stderr']:.1f}",
            w["quality"],
            ",".join(map(str, w["scans"])),
            "; ".join(w["reasons"]),
        )
    console.print(t)
    for p in out["poses"]:
        console.print(
            f"scan {p['scan_id']}: x {p['x']:.3f} m, y {p['y']:.3f} m, heading {math.degrees(p['heading']):.1f}° "
            f"(odometry {p['odometry']['x']:.3f}, {p['odometry']['y']:.3f})",
            highlight=False,
        )
    for note in out["notes"]:
        console.print(f"note: {note}", highlight=False)
    if "route" in out:
        r = out["route"]
        console.print(
            "route: none" if r is None else "route: " + " → ".join(f"({p['x']:.2f}, {p['y']:.2f})" for p in r),
            highlight=False,
        )
        if r is not None and out["route_unseen_m"] > 0:
            console.print(
                f"route: {out['route_unseen_m']:.2f} m of it through space no scan saw free (a wall may stand there)",
                highlight=False,
            )


def run_mapper(args: argparse.Namespace) -> int:
    import signal
    import threading

    from google.protobuf.json_format import MessageToDict

    from lelsonar.cli.map_views import mapper_views
    from lelsonar.cli.paths import output_file
    from lelsonar.keys import ScannerKeys, validate_identifier
    from lelsonar.map.service import MapperService, ZenohMapper, map_key
    from lelsonar.net.transport import open_session, zenoh_settings_from_args

    scanner = validate_identifier(args.scanner)
    if args.record is not None:
        output_file(args.record, overwrite=args.overwrite, what="--record file")
    prefix = ScannerKeys(args.prefix or "lelsonar", scanner).prefix
    settings = zenoh_settings_from_args(args)
    if getattr(args, "secure", None) is not None:
        from lelsonar.net.secure import MAPPER, secure_settings

        settings = secure_settings(settings, args.secure, MAPPER, prefix)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    mapped = 0

    def on_map(msg) -> None:
        nonlocal mapped
        mapped += 1
        if args.json:
            print(json.dumps(MessageToDict(msg), separators=(",", ":")), flush=True)
        else:
            print(f"mapper: scan {mapped}: {len(msg.walls)} walls, {len(msg.corners)} corners", flush=True)
        if draw is not None:
            draw(msg, service.fused)
        if args.until_scans and mapped >= args.until_scans:
            stop.set()

    service = MapperService(scanner, args.method, config=_fusion_config(args))
    with (
        mapper_views(args) as draw,
        open_session(settings) as session,
        ZenohMapper(session, prefix, service, record=args.record, on_map=on_map),
    ):
        print(f"mapper: fusing {scanner}'s scans; the map on {map_key(prefix)}", file=sys.stderr, flush=True)
        while not stop.wait(0.2):
            pass
    return 0
