"""``lelsonar demo --world maze``: a rover tours a maze world, the map grows scan by scan, and the planner
gets the map and prints the route out.

On one host:

* the rover: it drives from waypoint to waypoint of the world (a world file, an example's name, or
  ``FAMILY:SEED``) and scans every ``--scan-every`` metres on the way (:mod:`lelsonar.cli.maze_tour`).  At
  each stop, the sweep the acquirer would make (the simulator, its odometry, the ``ScanStart`` it announces)
  and the sweep's final reconstruction of record with its surfaces, corners and edges
  (:func:`sweep_reconstruction`), both published on the scanner's keys;
* the mapper (:class:`lelsonar.map.service.ZenohMapper`, as ``lelsonar mapper`` runs it): one update a scan,
  each map published on ``<prefix>/map``;
* the planner: a ``get`` on ``<prefix>/map``, the map read back (:func:`lelsonar.map.wire.map_from_message`),
  and a route over the free space the scans saw that keeps the robot's radius from every wall piece
  whatever its verdict, and never crosses a gap of a wall that no scan saw through
  (:func:`lelsonar.map.floorplan.route`).

The three talk over Zenoh on a unix socket of their own.  Each sweep is simulated and reconstructed whole
in this process rather than streamed step by step through ``acquire`` and a live ``reconstruct`` (which
give the same final estimate, bit for bit): a demo of the map waits seconds, not a live sweep's minute
per stop.  The map growing, the truth under it and the route go to ``OUT/<world>.rrd`` (Rerun) and the
final map to ``OUT/<world>.png``; neither is replaced without ``--overwrite``.
"""

from __future__ import annotations

import argparse
import queue
import tempfile
import threading
import time
from contextlib import ExitStack
from pathlib import Path
from typing import TYPE_CHECKING

from lelsonar.cli.maze_tour import EXAMPLE_WORLDS, resolve_world

__all__ = ["EXAMPLE_WORLDS", "SCANNER", "PREFIX", "resolve_world", "run_maze_demo", "sweep_reconstruction"]

if TYPE_CHECKING:
    from lelsonar.v1 import map_pb2

#: The demo's scanner and key prefix.
SCANNER, PREFIX = "rover", "lelsonar"


def sweep_reconstruction(scan, scanner_id: str, scan_id: int, energy_model):
    """A world sweep's final ``Reconstruction`` of record: the L planes and every surface, corner and edge of
    the sweep (:func:`~lelsonar.reconstruct.estimate.record.reconstruct_scan` on its ranges, energies and echo
    amplitudes, as the reconstructor computes it)."""
    from lelsonar.reconstruct.estimate import wire
    from lelsonar.reconstruct.estimate.record import RecordOptions, reconstruct_scan
    from lelsonar.reconstruct.estimate.waveform_input import scan_input_of_waveforms

    given = scan_input_of_waveforms(scan, energy_model)
    msg = wire.estimate_message(reconstruct_scan(given, RecordOptions()), scanner_id, scan_id, status="final")
    msg.stamp_ns = time.time_ns()
    return msg


def _wait_matched(entity, timeout: float) -> bool:
    matched = threading.Event()

    def on_status(status) -> None:
        if status.matching:
            matched.set()

    entity.declare_matching_listener(on_status)
    return matched.wait(timeout)


def _outputs(args: argparse.Namespace, name: str) -> tuple[Path, Path]:
    """``OUT/<world>.rrd`` and ``OUT/<world>.png``, checked before the tour starts."""
    from lelsonar.cli.paths import output_dir, output_file
    from lelsonar.view.snapshot import check_image_path

    out = output_dir(args.out, what="--out")
    rrd, png = out / f"{name}.rrd", out / f"{name}.png"
    output_file(rrd, overwrite=args.overwrite, what="demo output")
    output_file(png, overwrite=args.overwrite, what="demo output")
    check_image_path(png)
    return rrd, png


def _tour(run, console, on_map) -> map_pb2.Map | str:
    """Tour every stop of ``run`` with the rover, the mapper and the planner on Zenoh; ``on_map`` is called with
    each map the mapper publishes.  Returns the map the planner's ``get`` returns at the end, or a one-line
    reason (str) why there is none."""
    import zenoh
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from lelsonar import codec
    from lelsonar.acquire import messages
    from lelsonar.keys import ScannerKeys
    from lelsonar.map.service import MapperService, ZenohMapper, map_key
    from lelsonar.map.wire import decode_map
    from lelsonar.net.transport import hermetic_settings, open_session
    from lelsonar.reconstruct.estimate.pipeline import DEFAULT_METHOD
    from lelsonar.sim import default_energy_model
    from lelsonar.v1 import reconstruction_pb2

    stops = len(run.world.poses)
    energy_model = default_energy_model()
    keys = ScannerKeys(PREFIX, SCANNER)
    maps: queue.Queue = queue.Queue()
    with tempfile.TemporaryDirectory(prefix="lelsonar-demo-") as tmp:
        sock = Path(tmp) / "zenoh.sock"
        with (
            open_session(hermetic_settings(sock, listen=True)) as mapper_session,
            open_session(hermetic_settings(sock, listen=False)) as robot,
            ZenohMapper(mapper_session, PREFIX, MapperService(SCANNER, DEFAULT_METHOD), on_map=maps.put) as mapper,
        ):
            publishers = {}
            for key, example in ((keys.scan, codec.ScanStart()), (keys.planes, codec.Reconstruction())):
                pub = robot.declare_publisher(key, encoding=zenoh.Encoding(codec.encoding_name(example)))
                if not _wait_matched(pub, 10):
                    return "the mapper did not subscribe to the rover's keys"
                publishers[key] = pub
            querier = robot.declare_querier(map_key(PREFIX), timeout=10.0)
            if not _wait_matched(querier, 10):
                return "the mapper's map is not reachable by a get"
            with Progress(
                TextColumn("{task.description}"),
                BarColumn(),
                MofNCompleteColumn(),
                TimeElapsedColumn(),
                console=console,
                transient=False,
            ) as bar:
                task = bar.add_task("touring", total=stops)
                for index in range(stops):
                    replay = run.scanner(index)
                    start = messages.scan_start(
                        SCANNER, index + 1, time.time_ns(), replay.info, run.schedule, energy_model
                    )
                    reconstruction = sweep_reconstruction(replay.scan, SCANNER, index + 1, energy_model)
                    publishers[keys.scan].put(start.SerializeToString())
                    publishers[keys.planes].put(reconstruction.SerializeToString())
                    try:
                        grown = maps.get(timeout=120)
                    except queue.Empty:
                        return f"the mapper published no map for scan {index + 1} ({dict(mapper.errors)})"
                    on_map(grown)
                    good = sum(1 for w in grown.walls if w.quality == reconstruction_pb2.PLANE_QUALITY_GOOD)
                    bar.update(
                        task,
                        advance=1,
                        description=f"scan {index + 1}: {len(reconstruction.surfaces)} surfaces, "
                        f"map {len(grown.walls)} walls ({good} good)",
                    )
            replies = [r.ok for r in querier.get() if r.ok is not None]
            if not replies:
                return "the planner's get on the map returned nothing"
            return decode_map(replies[0].payload.to_bytes())


def run_maze_demo(args: argparse.Namespace) -> int:
    from lelsonar.acquire.world_scans import world_json
    from lelsonar.cli.maze_tour import load_tour_world, tour_run
    from lelsonar.cli.route_report import print_map, print_route
    from lelsonar.map import floorplan
    from lelsonar.map.service import map_key
    from lelsonar.map.wire import map_from_message
    from lelsonar.view import present
    from lelsonar.view.map_picture import save_map_picture
    from lelsonar.view.rerun_layout import make_recording
    from lelsonar.view.rerun_map import log_map, map_blueprint
    from lelsonar.view.rerun_world import log_world_truth

    console = present.console()
    world, source = load_tour_world(args.world)
    if not world.poses:
        console.print(f"[red]the world {source} has no poses: nothing to tour")
        return 1
    run = tour_run(world, source, seed=args.seed, spacing=args.scan_every)
    rrd, png = _outputs(args, world.name)
    truth = world_json(run.world)
    plan = floorplan.PlanConfig(robot_radius=args.robot_radius)
    console.rule(
        f"lelsonar demo — {world.name} from {source}: {len(world.poses)} waypoints, a scan every "
        f"{args.scan_every:g} m: {len(run.world.poses)} stops, mount {world.scanner.mount}"
    )
    t0 = time.monotonic()
    with ExitStack() as files:
        rec = make_recording(application_id="lelsonar-map")
        rec.save(rrd, default_blueprint=map_blueprint())
        files.callback(rec.disconnect)
        files.callback(rec.flush)
        log_world_truth(rec, truth)

        def draw(msg) -> None:
            log_map(rec, msg, free_space=floorplan.free_space(map_from_message(msg), plan))

        latest = _tour(run, console, draw)
        if isinstance(latest, str):
            console.print(f"[red]{latest}")
            return 1
        fused = map_from_message(latest)
        space = floorplan.free_space(fused, plan)
        print_map(console, fused, map_key(PREFIX))
        begin = (fused.poses[0].x, fused.poses[0].y)
        path = floorplan.route(fused, begin, None, plan)
        log_map(rec, latest, free_space=space, route=path)
        evidence = sum(1 for w in fused.walls if w.good_observations > 0)
        title = f"{world.name}: {evidence} walls of good evidence, {len(fused.poses)} scans"
        closed = floorplan.closed_gaps(fused, plan)
        save_map_picture(png, latest, free_space=space, route=path, world=truth, title=title, closed=closed)
        elapsed = time.monotonic() - t0
        print_route(console, fused, begin, path, plan)
    console.print(f"the map growing, the truth and the route: rerun {rrd}; the final map: {png}", highlight=False)
    console.print(f"done in {elapsed:.1f} s", highlight=False)
    return 0 if path is not None else 1
