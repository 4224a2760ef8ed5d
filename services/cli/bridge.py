"""`lelsonar export` (rosbag2) and `lelsonar ros2-bridge` (ROS 2 live over rmw_zenoh)."""

from __future__ import annotations

import argparse
import math
import signal
import threading
from contextlib import ExitStack
from pathlib import Path

from lelsonar.cli.values import count


def register(sub: argparse._SubParsersAction) -> None:
    from lelsonar.cli.paths import add_overwrite_argument
    from lelsonar.net.transport import add_zenoh_arguments

    p = sub.add_parser(
        "export",
        help="convert a recording for another ecosystem (rosbag2 for ROS 2)",
        description="Replay a recording through the reconstruction and write it as a rosbag2 directory "
        "(metadata.yaml + MCAP, CDR): /tf_static, /tf, a sensor_msgs/Range per capsule, raw and "
        "corrected PointCloud2, a MarkerArray of the planes, the edge and the truth, and the estimate "
        "as JSON on /lelsonar/estimate. No ROS install needed.",
    )
    p.add_argument("source", type=Path, metavar="IN.mcap", help="the recording to export")
    p.add_argument(
        "-o",
        "--output",
        type=Path,
        required=True,
        metavar="DIR",
        help="the bag directory to write (an existing one is refused; --overwrite replaces a rosbag2 directory)",
    )
    add_overwrite_argument(p)
    p.add_argument("--format", choices=("rosbag2",), default="rosbag2", help="output format (default: rosbag2)")
    p.add_argument(
        "--distro",
        choices=("jazzy", "humble"),
        default="jazzy",
        help="ROS 2 message definitions and bag version (jazzy: 9, humble: 8; default: jazzy)",
    )
    _add_ros_arguments(p)
    p.set_defaults(run=run_export)

    p = sub.add_parser(
        "ros2-bridge",
        help="publish scans and estimates as ROS 2 topics over rmw_zenoh",
        description="Reconstruct live (or replay --source) and publish the same topics as `export` on rmw_zenoh key "
        "expressions, with liveliness tokens, so `ros2 topic echo` on a robot running rmw_zenoh sees "
        "them. Connect it to the robot's rmw_zenohd router (default tcp/127.0.0.1:7447).",
    )
    p.add_argument("--source", type=Path, metavar="FILE.mcap", help="replay a recording instead of subscribing")
    p.add_argument(
        "--hold", action="store_true", help="with --source: keep the node (and the latched topics) up until Ctrl-C"
    )
    p.add_argument(
        "--until-scans",
        type=count,
        default=0,
        metavar="N",
        help="live: exit after N final estimates (default: run until Ctrl-C)",
    )
    p.add_argument("--scanner", default="*", help="only this scanner id (default: all)")
    p.add_argument("--domain-id", type=int, default=0, metavar="N", help="ROS_DOMAIN_ID (default: 0)")
    p.add_argument("--node-name", default="lelsonar_bridge", help="ROS 2 node name (default: lelsonar_bridge)")
    p.add_argument("--namespace", default="/", help="ROS 2 node namespace (default: /)")
    _add_ros_arguments(p)
    add_zenoh_arguments(p, default_mode="peer")
    p.set_defaults(run=run_bridge)


def _add_ros_arguments(p: argparse.ArgumentParser) -> None:
    from lelsonar.cli.reconstruct import add_jobs_argument, add_method_arguments, add_truth_preset_argument

    g = p.add_argument_group("estimation and drawing")
    add_method_arguments(g, "also draw these methods' planes (default: ls; '' for none)")
    add_jobs_argument(g)
    add_truth_preset_argument(
        g,
        "draw the true planes of this simulator preset (default: the recording's own preset when its device "
        "is sim or emulated)",
    )
    g.add_argument("--no-truth", action="store_true", help="never draw true planes")
    g.add_argument(
        "--parent-frame",
        metavar="FRAME",
        help="also publish an identity transform FRAME → <scanner>/base (e.g. base_link)",
    )
    g.add_argument(
        "--fov-deg",
        type=float,
        metavar="DEG",
        help="sensor_msgs/Range field_of_view, full angle (default: twice the estimator's beam half-angle, 70)",
    )


def _service_config(args: argparse.Namespace, *, provisional: bool):
    from lelsonar.cli.reconstruct import compared_methods, final_workers
    from lelsonar.reconstruct.stream.config import ReconstructConfig

    return ReconstructConfig(
        method=args.method,
        compare_methods=compared_methods(args),
        provisional=provisional,
        final_workers=final_workers(args),
    )


def _truth(args: argparse.Namespace, source: Path | None):
    """``truth(scan)`` for the view: the chosen preset's planes, or the recording's own when simulated."""
    from lelsonar.bridge.ros2 import TruePlane

    if args.no_truth:
        return None
    preset_name = args.truth_preset
    only_simulated = False
    if preset_name is None and source is not None:
        from lelsonar.log.recording import read_metadata

        try:
            preset_name = read_metadata(source).get("lelsonar.config", {}).get("preset")
        except Exception:  # noqa: BLE001 - an unreadable file fails properly in the replay
            preset_name = None
        only_simulated = True
    if not preset_name:
        return None
    from lelsonar.errors import ConfigError
    from lelsonar.sim import preset
    from lelsonar.sim.scan import true_planes

    try:
        planes = [TruePlane(p.label, p.normal, p.offset, p.corners) for p in true_planes(preset(preset_name))]
    except ConfigError:
        if only_simulated:
            return None
        raise
    return lambda scan: planes if (not only_simulated or scan.start.device in ("sim", "emulated")) else None


def _view(args: argparse.Namespace, emit, source: Path | None, distro: str = "jazzy"):
    from lelsonar.bridge.ros2 import Ros2View

    return Ros2View(
        emit,
        main_method=args.method,
        distro=distro,
        truth=_truth(args, source),
        field_of_view=math.radians(args.fov_deg) if args.fov_deg is not None else None,
        parent_frame=args.parent_frame,
    )


def check_bag_dir(out: Path, overwrite: bool, flag: str = "-o") -> None:
    """A new bag directory, or (with ``overwrite``) an old rosbag2 directory, removed; anything else refused."""
    import shutil

    from lelsonar.cli.paths import output_dir
    from lelsonar.errors import ConfigError

    if out.exists() or out.is_symlink():
        if not overwrite:
            raise ConfigError(f"{out} already exists; pass --overwrite to replace the bag, or give another {flag}")
        if not (out.is_dir() and not out.is_symlink() and (out / "metadata.yaml").is_file()):
            raise ConfigError(f"{out} exists and is not a rosbag2 directory (no metadata.yaml); give another {flag}")
        shutil.rmtree(out)
    output_dir(out.parent, what=f"the folder of {out}")


def run_export(args: argparse.Namespace) -> int:
    from lelsonar.bridge.ros2 import export_rosbag2
    from lelsonar.cli.paths import input_file
    from lelsonar.reconstruct.stream.service import ReconstructionService

    input_file(args.source)
    check_bag_dir(args.output, args.overwrite)
    if is_map_recording(args.source):
        return export_maps(args)
    from lelsonar.cli.warm_up import ensure_compiled

    ensure_compiled()
    config = _service_config(args, provisional=False)  # a batch export needs only the finals
    counts = export_rosbag2(
        args.source,
        args.output,
        distro=args.distro,
        view_factory=lambda sink: _view(args, sink, args.source, args.distro),
        service_factory=lambda view: ReconstructionService(config, observer=view),
    )
    for topic, n in sorted(counts.items()):
        print(f"{n:8d}  {topic}")
    print(f"wrote {args.output} — inspect it with: ros2 bag info {args.output}")
    return 0 if counts.get("/lelsonar/estimate") else 1


def map_to_ros2(session, prefix: str, publish):
    """The mapper's maps (``<prefix>/map``) as /map (OccupancyGrid) and /lelsonar/map/walls on the node."""
    from lelsonar.bridge.ros2_map import MapRos2, MapSubscription

    return MapSubscription(session, prefix, MapRos2(publish))


def is_map_recording(path: Path) -> bool:
    """A recording of maps (a mapper's ``--record``, ``map --mcap``) rather than of scans."""
    from lelsonar.bridge.ros2_map import recorded_maps
    from lelsonar.log.recording import open_recording

    if open_recording(path).has_scans:
        return False
    return next(recorded_maps(path), None) is not None


def export_maps(args: argparse.Namespace) -> int:
    """`export` of a map recording: the floor plan's OccupancyGrid on /map and the walls' MarkerArray, per map."""
    from lelsonar.bridge.ros2_map import export_map_rosbag2

    counts = export_map_rosbag2(args.source, args.output, distro=args.distro)
    for topic, n in sorted(counts.items()):
        print(f"{n:8d}  {topic}")
    print(f"wrote {args.output} — inspect it with: ros2 bag info {args.output}")
    return 0 if counts else 1


def run_bridge(args: argparse.Namespace) -> int:
    from lelsonar.bridge.rmw_zenoh import RmwZenohNode, open_ros_session
    from lelsonar.keys import ScannerKeys
    from lelsonar.net.transport import zenoh_settings_from_args
    from lelsonar.reconstruct.stream.replay import replay_mcap
    from lelsonar.reconstruct.stream.service import ReconstructionService
    from lelsonar.reconstruct.stream.sources import LiveSource

    if args.source is not None:
        from lelsonar.cli.paths import input_file

        input_file(args.source)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    n_final = 0
    from lelsonar.cli.warm_up import ensure_compiled

    ensure_compiled()
    with ExitStack() as stack:
        session = stack.enter_context(open_ros_session(zenoh_settings_from_args(args)))
        node = stack.enter_context(
            RmwZenohNode(session, name=args.node_name, namespace=args.namespace, domain_id=args.domain_id)
        )

        def emit(message) -> None:
            nonlocal n_final
            node.publish(message)
            if message.topic == "/lelsonar/estimate" and '"status":"final' in message.message.data:
                n_final += 1
                if args.until_scans and n_final >= args.until_scans:
                    stop.set()

        service = ReconstructionService(
            _service_config(args, provisional=args.source is None), observer=_view(args, emit, args.source)
        )
        print(
            f"ros2-bridge: node {args.namespace.rstrip('/')}/{args.node_name} on domain {args.domain_id} "
            f"(zenoh id {node.zid})",
            flush=True,
        )
        if args.source is not None:
            n = replay_mcap(args.source, service)
            print(f"ros2-bridge: replayed {n} payloads, {n_final} final estimates", flush=True)
            if args.hold:
                stop.wait()
            return 0 if n_final else 1
        keys = ScannerKeys(args.prefix or "lelsonar", args.scanner)
        print(f"ros2-bridge: listening on {keys.sample} and {keys.scan}", flush=True)
        stack.enter_context(map_to_ros2(session, keys.prefix, node.publish))
        with LiveSource(session, keys, service, stop):
            # declared once subscribed, like every lelsonar service: `<prefix>/<scanner>/alive/ros2-bridge`
            stack.callback(session.liveliness().declare_token(keys.alive("ros2-bridge")).undeclare)
            stop.wait()  # Ctrl-C, SIGTERM or --until-scans
    return 0
