"""``lelsonar demo --world maze``: a rover tours a maze world, the map grows scan by scan, and the planner
gets the map and prints the route out.

On one host:

* the rover: at each pose of the world, the sweep the acquirer would make (``acquire --device sim --world``'s
  own set-up, :func:`lelsonar.acquire.world_scans.prepare_world`: the simulator, its odometry, the
  ``ScanStart`` it announces) and the sweep's final reconstruction of record with its surfaces, corners and
  edges (:func:`sweep_reconstruction`), both published on the scanner's keys;
* the mapper (:class:`lelsonar.map.service.ZenohMapper`, as ``lelsonar mapper`` runs it): one update a scan,
  each map published on ``<prefix>/map``;
* the planner: a ``get`` on ``<prefix>/map``, the map read back (:func:`lelsonar.map.wire.map_from_message`),
  and a route over the free space the scans saw that keeps the robot's radius
  (:func:`lelsonar.map.floorplan.route`).

The three talk over Zenoh on a unix socket of their own.  Each sweep is simulated and reconstructed whole
in this process rather than streamed step by step through ``acquire`` and a live ``reconstruct`` (which
give the same final estimate, bit for bit): a demo of the map waits seconds, not a live sweep's minute
per pose.
"""

from __future__ import annotations

import argparse
import queue
import tempfile
import threading
import time
from pathlib import Path

#: Where the example worlds live (a name given to ``--world`` is looked up there).
EXAMPLE_WORLDS = Path(__file__).resolve().parents[2] / "examples" / "worlds"
#: The demo's scanner and key prefix.
SCANNER, PREFIX = "rover", "lelsonar"


def resolve_world(text: str) -> Path:
    """``--world``'s file: a path to a world file, or the name of an example world (``maze``)."""
    from lelsonar.errors import ConfigError

    path = Path(text)
    if path.is_file():
        return path
    named = EXAMPLE_WORLDS / f"{text}.toml"
    if named.is_file():
        return named
    known = ", ".join(sorted(p.stem for p in EXAMPLE_WORLDS.glob("*.toml"))) or "none found"
    raise ConfigError(f"--world {text!r} is neither a world file nor an example world ({known})")


def sweep_reconstruction(scan, scanner_id: str, scan_id: int, energy_model):
    """A world sweep's final ``Reconstruction`` of record: the L planes and every surface, corner and edge of
    the sweep (:func:`~lelsonar.reconstruct.estimate.record.reconstruct_scan` on its ranges, energies and echo
    amplitudes, as the reconstructor computes it)."""
    from lelsonar.reconstruct.estimate import wire
    from lelsonar.reconstruct.estimate.record import RecordOptions, ScanInput, reconstruct_scan
    from lelsonar.signal.energy import echo_amplitude, waveform_energy

    energy = waveform_energy(scan.waveforms, scan.sample_rate)
    amplitude = echo_amplitude(scan.waveforms, scan.sample_rate, scan.t0, scan.tof)
    given = ScanInput.of_scan(
        scan.gamma_measured, scan.distance, energy, scan.geometry, energy_model, echo_amplitude=amplitude
    )
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


def run_maze_demo(args: argparse.Namespace) -> int:
    import zenoh
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from lelsonar import codec
    from lelsonar.acquire import messages
    from lelsonar.acquire.world_scans import prepare_world
    from lelsonar.keys import ScannerKeys
    from lelsonar.map import floorplan
    from lelsonar.map.service import MapperService, ZenohMapper, map_key
    from lelsonar.map.wire import map_from_message
    from lelsonar.net.transport import hermetic_settings, open_session
    from lelsonar.reconstruct.estimate.pipeline import DEFAULT_METHOD
    from lelsonar.sim import default_energy_model
    from lelsonar.v1 import map_pb2
    from lelsonar.view import present

    console = present.console()
    path = resolve_world(args.world)
    run = prepare_world(path, seed=args.seed)
    poses = len(run.world.poses)
    energy_model = default_energy_model()
    if poses == 0:
        console.print(f"[red]the world {path} has no poses: nothing to tour")
        return 1
    console.rule(f"lelsonar demo — {run.world.name}: {poses} poses, mount {run.world.scanner.mount}, from {path}")
    keys = ScannerKeys(PREFIX, SCANNER)
    maps: queue.Queue = queue.Queue()
    t0 = time.monotonic()
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
                    console.print("[red]the mapper did not subscribe to the rover's keys")
                    return 1
                publishers[key] = pub
            querier = robot.declare_querier(map_key(PREFIX), timeout=10.0)
            if not _wait_matched(querier, 10):
                console.print("[red]the mapper's map is not reachable by a get")
                return 1
            with Progress(
                TextColumn("{task.description}"),
                BarColumn(),
                MofNCompleteColumn(),
                TimeElapsedColumn(),
                console=console,
                transient=False,
            ) as bar:
                task = bar.add_task("touring the maze", total=poses)
                for index in range(poses):
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
                        console.print(f"[red]the mapper published no map for scan {index + 1} ({dict(mapper.errors)})")
                        return 1
                    good = sum(1 for w in grown.walls if w.quality == 1)
                    bar.update(
                        task,
                        advance=1,
                        description=f"scan {index + 1}: {len(reconstruction.surfaces)} surfaces seen, "
                        f"map {len(grown.walls)} walls ({good} good)",
                    )
            replies = [r.ok for r in querier.get() if r.ok is not None]
            if not replies:
                console.print("[red]the planner's get on the map returned nothing")
                return 1
            latest = map_pb2.Map.FromString(replies[0].payload.to_bytes())
    fused = map_from_message(latest)
    plan = floorplan.PlanConfig(robot_radius=args.robot_radius)
    console.print(
        f"the planner got the map on {map_key(PREFIX)}: {len(fused.walls)} walls "
        f"({sum(w.quality == 'good' for w in fused.walls)} good), {len(fused.corners)} corners, "
        f"{len(fused.poses)} poses"
    )
    begin = (fused.poses[0].x, fused.poses[0].y)
    route = floorplan.route(fused, begin, None, plan)
    elapsed = time.monotonic() - t0
    if route is None:
        console.print(f"[red]no route out of the map from ({begin[0]:.2f}, {begin[1]:.2f}) in {elapsed:.1f} s")
        return 1
    length = sum(((b[0] - a[0]) ** 2 + (b[1] - a[1]) ** 2) ** 0.5 for a, b in zip(route, route[1:]))
    console.print(
        f"route out (robot radius {plan.robot_radius:g} m, {length:.2f} m): "
        + " → ".join(f"({x:.2f}, {y:.2f})" for x, y in route),
        highlight=False,
    )
    frontier = floorplan.frontier(fused, route, plan)
    if frontier is None:
        console.print("the exit is seen: the whole route runs through free space the scans saw", highlight=False)
    else:
        unseen = floorplan.unseen_length(fused, route, plan)
        console.print(
            f"the exit is not seen yet: {unseen:.2f} m of the route runs through space no scan saw free; "
            f"the rover would explore the frontier at ({frontier[0]:.2f}, {frontier[1]:.2f}) first",
            highlight=False,
        )
    console.print(f"done in {elapsed:.1f} s", highlight=False)
    return 0
