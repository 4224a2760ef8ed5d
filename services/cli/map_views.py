"""The viewer outputs of `lelsonar map`: the map growing scan by scan in Rerun (``--rrd``), Foxglove
(``--mcap``) and ROS 2 (``--ros2-bag``), and the final map as a picture (``--screenshot``).

Each output draws the ``Map`` message of each step (what the mapper publishes), with the free space the
fusion saw; nothing is overwritten without ``--overwrite``.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any


def add_view_arguments(p: argparse.ArgumentParser) -> None:
    from lelsonar.cli.paths import add_overwrite_argument

    g = p.add_argument_group("viewers", "the map growing scan by scan; each file is new unless --overwrite")
    g.add_argument("--rrd", type=Path, metavar="FILE.rrd", help="save the map as a Rerun recording")
    g.add_argument(
        "--mcap", type=Path, metavar="FILE.mcap", help="save the map as Foxglove scenes (and the Map messages)"
    )
    g.add_argument(
        "--ros2-bag",
        type=Path,
        metavar="DIR",
        help="write a rosbag2 directory: nav_msgs/OccupancyGrid on /map and the walls' MarkerArray",
    )
    g.add_argument(
        "--screenshot",
        type=Path,
        metavar="FILE.png",
        help="draw the final map (walls by verdict and σ, path, free space, route) into an image",
    )
    add_overwrite_argument(g)  # type: ignore[arg-type]  # an argument group takes arguments as its parser does


def wants_views(args: argparse.Namespace) -> bool:
    return any(getattr(args, k, None) is not None for k in ("rrd", "mcap", "ros2_bag", "screenshot"))


class MapViews:
    """The viewer outputs of one `map` run, checked when made: :meth:`open` them, :meth:`add` each step's map,
    :meth:`finish` with the last."""

    def __init__(self, args: argparse.Namespace, plan) -> None:
        from contextlib import ExitStack

        from lelsonar.cli.bridge import check_bag_dir
        from lelsonar.cli.paths import output_file
        from lelsonar.errors import ConfigError
        from lelsonar.log.recording import read_metadata, truth_world

        outs = [(f, p) for f, p in (("--rrd", args.rrd), ("--mcap", args.mcap), ("--screenshot", args.screenshot)) if p]
        for flag, path in outs:
            output_file(path, overwrite=args.overwrite, what=f"{flag} file")
        if args.screenshot is not None:
            from lelsonar.view.snapshot import check_image_path

            check_image_path(args.screenshot)
        if args.ros2_bag is not None:
            check_bag_dir(args.ros2_bag, args.overwrite, flag="--ros2-bag")
        sources = {Path(s).resolve() for s in args.source}
        if any(Path(p).resolve() in sources for _, p in outs):
            raise ConfigError("the recordings and the output files must differ")
        self.plan = plan
        self.world = None
        self.last: tuple | None = None
        for source in args.source:
            self.world = self.world or truth_world(read_metadata(source).get("lelsonar.config"))
        self._screenshot = args.screenshot
        self._stack = ExitStack()
        self._rec: Any = None  # rerun.RecordingStream
        self._mcap: Any = None  # (mcap Writer, MapScene)
        self._bag: Any = None  # (BagSink, Builder)
        self._t = 0
        self._paths = (args.rrd, args.mcap, args.ros2_bag)

    def open(self) -> None:
        """Create the files, once the recordings have given a map to draw: a run refused after the checks
        (several robots, no final scan) leaves no file behind to refuse the next run."""
        rrd, mcap, bag = self._paths
        try:
            if rrd is not None:
                self._open_rrd(rrd)
            if mcap is not None:
                self._open_mcap(mcap)
            if bag is not None:
                self._open_bag(bag)
        except BaseException:
            self._stack.close()
            raise

    def _open_rrd(self, path: Path) -> None:
        from lelsonar.view.rerun_layout import make_recording
        from lelsonar.view.rerun_map import map_blueprint
        from lelsonar.view.rerun_world import log_world_truth

        rec = make_recording(application_id="lelsonar-map")
        rec.save(path, default_blueprint=map_blueprint())
        self._stack.callback(rec.disconnect)
        self._stack.callback(rec.flush)
        if self.world is not None:
            log_world_truth(rec, self.world)
        self._rec = rec

    def _open_mcap(self, path: Path) -> None:
        from mcap_protobuf.writer import Writer

        from lelsonar.draw.map_scene import MapScene

        f = self._stack.enter_context(open(path, "wb"))
        writer = Writer(f)
        self._stack.callback(writer.finish)
        self._mcap = (writer, MapScene())
        if self.world is not None:
            from lelsonar.draw.world import TOPIC_WORLD, world_scene

            writer.write_message(TOPIC_WORLD, world_scene(self.world, 0), log_time=0, publish_time=0)

    def _open_bag(self, path: Path) -> None:
        from lelsonar.bridge.ros2 import BagSink, Builder, open_bag

        writer = self._stack.enter_context(open_bag(path))
        self._bag = (BagSink(writer, "jazzy"), Builder("jazzy"))

    def add(self, fused, scanner_id: str) -> None:
        """Draw one step's map (``fused``: the fusion's snapshot) at the next step of every output."""
        from lelsonar.map import floorplan
        from lelsonar.map.wire import map_message

        self._t += 1
        t = self._t * 1_000_000_000  # one second a scan: the outputs' common clock
        msg = map_message(fused, scanner_id, stamp_ns=t)
        space = floorplan.free_space(fused, self.plan)
        if self._rec is not None:
            from lelsonar.view.rerun_map import log_map

            log_map(self._rec, msg, free_space=space)
        if self._mcap is not None:
            from lelsonar.draw.map_scene import TOPIC_MAP_SCENE
            from lelsonar.map.service import MAP_TOPIC

            writer, scene = self._mcap
            writer.write_message(MAP_TOPIC, msg, log_time=t, publish_time=t)
            writer.write_message(TOPIC_MAP_SCENE, scene.update(msg, t, space), log_time=t, publish_time=t)
        if self._bag is not None:
            from lelsonar.bridge.ros2_map import map_ros_messages

            sink, b = self._bag
            for m in map_ros_messages(b, fused, t, self.plan):
                sink(m)
        self.last = (msg, space)

    def finish(self, route: list[tuple[float, float]] | None) -> None:
        """The last map again with its route (when one was planned), the picture, and every file closed."""
        try:
            if self.last is None:
                return
            msg, space = self.last
            if route is not None and self._rec is not None:
                from lelsonar.view.rerun_map import log_map

                log_map(self._rec, msg, free_space=space, route=route)
            if self._screenshot is not None:
                from lelsonar.view.map_picture import save_map_picture

                save_map_picture(self._screenshot, msg, free_space=space, route=route, world=self.world)
        finally:
            self._stack.close()

    def close(self) -> None:
        self._stack.close()


def add_mapper_view_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--foxglove",
        metavar="[HOST:]PORT",
        help="serve the map live on a Foxglove WebSocket (/lelsonar/map/scene), growing with every scan",
    )


@contextmanager
def mapper_views(args: argparse.Namespace) -> Iterator[Callable[[Any, Any], None] | None]:
    """``draw(map, fused)``: what `mapper` draws each map (and the fusion's free space) on (``--foxglove``),
    for the duration of the block; None without it."""
    if getattr(args, "foxglove", None) is None:
        yield None
        return
    import sys

    from lelsonar.bridge.foxglove import open_foxglove_map
    from lelsonar.map.floorplan import free_space

    with open_foxglove_map(args.foxglove) as view:
        print(f"mapper: Foxglove live on {view.server.url}", file=sys.stderr, flush=True)
        yield lambda msg, fused: view(msg, None if fused is None else free_space(fused))
