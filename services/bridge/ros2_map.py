"""The map for ROS 2: a ``nav_msgs/OccupancyGrid`` on ``/map`` and a ``visualization_msgs/MarkerArray`` of the
walls on ``/lelsonar/map/walls``, what RViz and Nav2 users expect.

The grid is :func:`lelsonar.map.floorplan.occupancy_grid`: occupied where a wall runs, free where the scans
saw free space, unknown elsewhere.  The markers are :func:`lelsonar.map.floorplan.wall_markers`: a box per
observed piece of each wall, as thick as its offset's ± 2σ, in its verdict's colour, plus a sphere of ± 2σ
at each corner and edge (the horizontal corners, where a wall meets the floor or the ceiling, apart) and the
corrected path against the odometry's.

From a ``Map`` message (a mapper's recording, the live bridge) the map is read back with
:func:`lelsonar.map.wire.map_from_message`, its free-space views included, so the grid is the one the
mapper's own fusion draws.
"""

from __future__ import annotations

import logging
import shutil
from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import zenoh

from lelsonar.bridge import ros2
from lelsonar.bridge.ros2_markers import CUBE, DELETEALL, LINE_STRIP, SPHERE, TEXT_VIEW_FACING, verdict_rgb
from lelsonar.draw.estimates import SIGMA_BAND
from lelsonar.draw.palette import CONCAVE_CORNER_COLOR, CONVEX_EDGE_COLOR, HORIZONTAL_CORNER_COLOR, unit_rgb
from lelsonar.errors import LelsonarError, RecordingError
from lelsonar.log.recording import open_recording
from lelsonar.map import floorplan
from lelsonar.map.result import FusedMap
from lelsonar.map.service import map_key
from lelsonar.map.wire import decode_map, map_from_message
from lelsonar.v1 import map_pb2

TOPIC_GRID = ros2.TOPIC_MAP_GRID
TOPIC_WALLS = ros2.TOPIC_MAP_WALLS
MAP_FRAME = "map"

_CORNER_RGB = unit_rgb(CONCAVE_CORNER_COLOR)
_EDGE_RGB = unit_rgb(CONVEX_EDGE_COLOR)
_PATH_RGB = (1.0, 0.78, 0.0)
_ODOMETRY_RGB = (0.6, 0.6, 0.6)
_HORIZONTAL_RGB = unit_rgb(HORIZONTAL_CORNER_COLOR)


MAP_SCHEMA = map_pb2.Map.DESCRIPTOR.full_name
_log = logging.getLogger("lelsonar.bridge.map")


def _is_map(channel, schema) -> bool:
    return schema is not None and channel.message_encoding == "protobuf" and schema.name == MAP_SCHEMA


def recorded_maps(path: Path | str) -> Iterator[tuple[int, map_pb2.Map]]:
    """``(log time ns, Map)`` of every map a recording holds (a mapper's ``--record``, ``map --mcap``)."""
    for m in open_recording(path).messages(_is_map):
        yield m.log_time, decode_map(m.data)


def export_map_rosbag2(
    source: Path | str, out_dir: Path | str, *, distro: str = "jazzy", plan: floorplan.PlanConfig | None = None
) -> dict[str, int]:
    """Write a rosbag2 directory of a map recording: the grid and the wall markers of every map in it.

    Returns
    -------
    dict
        Messages written per topic.

    Raises
    ------
    RecordingError
        ``out_dir`` exists, or the recording cannot be read; a partly written bag is removed.
    """
    out = Path(out_dir)
    if out.exists():
        raise RecordingError(f"{out} already exists; rosbag2 writes a new directory (remove it or pick another -o)")
    try:
        with ros2.open_bag(out, distro) as writer:
            sink = ros2.BagSink(writer, distro)
            view = MapRos2(sink, distro, plan)
            for t, msg in recorded_maps(source):
                view(msg, t)
    except BaseException:
        shutil.rmtree(out, ignore_errors=True)
        raise
    return dict(sink.counts)


def grid_message(b: ros2.Builder, grid: floorplan.Grid, t_ns: int, frame: str = MAP_FRAME) -> object:
    """A ``nav_msgs/OccupancyGrid`` of a floor-plan grid: row-major from its origin, x along rows."""
    return b(
        ros2.OCCUPANCY_GRID,
        header=b.header(t_ns, frame),
        info=b(
            "nav_msgs/msg/MapMetaData",
            map_load_time=b.time(t_ns),
            resolution=float(grid.resolution),
            width=int(grid.width),
            height=int(grid.height),
            origin=b(
                "geometry_msgs/msg/Pose",
                position=b.point((grid.origin[0], grid.origin[1], 0.0)),
                orientation=b.quaternion((0.0, 0.0, 0.0, 1.0)),
            ),
        ),
        data=np.ascontiguousarray(grid.data, dtype=np.int8).ravel(),
    )


def wall_marker_array(b: ros2.Builder, m: FusedMap, t_ns: int, frame: str = MAP_FRAME) -> object:
    """A DELETEALL, then each wall piece (``walls``: a box, ± 2σ thick, verdict colour) and its label
    (``walls/label``), each corner and edge (``corners``, ``edges``: a sphere of ± 2σ), the corrected path
    (``path``) and the odometry's (``odometry``)."""
    markers = [b.marker(t_ns, frame, "", 0, 0, action=DELETEALL)]
    # floorplan.wall_markers gives each wall's pieces in order; the colours are the viewers' palette.
    owners = [w for w in m.walls for _ in w.piece_segments]
    for i, (d, w) in enumerate(zip(floorplan.wall_markers(m, frame, thickness_sigmas=2 * SIGMA_BAND), owners)):
        p, q, s, c = d["pose"]["position"], d["pose"]["orientation"], d["scale"], d["color"]
        position = (p["x"], p["y"], p["z"])
        rgb = verdict_rgb(w.quality)
        markers.append(
            b.marker(
                t_ns,
                frame,
                "walls",
                i,
                CUBE,
                rgb=rgb,
                alpha=c["a"],
                scale=(s["x"], s["y"], s["z"]),
                position=position,
                orientation=(q["x"], q["y"], q["z"], q["w"]),
            )
        )
        markers.append(
            b.marker(
                t_ns,
                frame,
                "walls/label",
                i,
                TEXT_VIEW_FACING,
                rgb=rgb,
                scale=(0, 0, 0.1),
                position=(p["x"], p["y"], p["z"] + 0.5 * s["z"] + 0.05),
                text=d["text"],
            )
        )
    features = [
        ("edges", _EDGE_RGB, k, f) if f.kind == "edge" else ("corners", _CORNER_RGB, k, f)
        for k, f in enumerate(m.features)
    ]
    features += [("horizontal_corners", _HORIZONTAL_RGB, k, f) for k, f in enumerate(m.horizontal)]
    for ns, rgb, i, f in features:
        size = max(4.0 * f.point_stderr, 0.03)  # ± 2σ
        markers.append(
            b.marker(t_ns, frame, ns, i, SPHERE, rgb=rgb, alpha=0.7, scale=(size, size, size), position=f.point)
        )
    if m.poses:
        path = [(p.x, p.y, 0.01) for p in m.poses]
        odometry = [(p.odometry[0], p.odometry[1], 0.005) for p in m.poses]
        markers.append(b.marker(t_ns, frame, "path", 0, LINE_STRIP, points=path, rgb=_PATH_RGB, scale=(0.02, 0, 0)))
        markers.append(
            b.marker(t_ns, frame, "odometry", 0, LINE_STRIP, points=odometry, rgb=_ODOMETRY_RGB, scale=(0.01, 0, 0))
        )
    return b(ros2.MARKERS, markers=markers)


def map_ros_messages(
    b: ros2.Builder, m: FusedMap, t_ns: int, plan: floorplan.PlanConfig | None = None, frame: str = MAP_FRAME
) -> list[ros2.RosMessage]:
    """The grid and the wall markers of one map, ready for a sink (a bag or the rmw_zenoh node)."""
    grid = floorplan.occupancy_grid(m, plan)
    return [
        ros2.RosMessage(TOPIC_GRID, ros2.OCCUPANCY_GRID, int(t_ns), grid_message(b, grid, t_ns, frame)),
        ros2.RosMessage(TOPIC_WALLS, ros2.MARKERS, int(t_ns), wall_marker_array(b, m, t_ns, frame)),
    ]


class MapRos2:
    """Turns each ``Map`` message into the grid and the wall markers and hands them to ``emit``."""

    def __init__(
        self,
        emit: Callable[[ros2.RosMessage], None],
        distro: str = "jazzy",
        plan: floorplan.PlanConfig | None = None,
    ) -> None:
        self._emit = emit
        self._b = ros2.Builder(distro)
        self._plan = plan

    def __call__(self, msg: map_pb2.Map, t_ns: int | None = None) -> None:
        t = int(msg.stamp_ns if t_ns is None else t_ns)
        for out in map_ros_messages(self._b, map_from_message(msg), t, self._plan):
            self._emit(out)


class MapSubscription:
    """Each ``Map`` published on ``<prefix>/map`` (by ``lelsonar mapper``), decoded and handed to ``on_map``.

    A map that cannot be decoded or drawn is counted in :attr:`errors` and logged; the subscription goes on.
    A context manager: the subscriber is undeclared on exit.
    """

    def __init__(self, session: zenoh.Session, prefix: str, on_map: Callable[[map_pb2.Map], None]) -> None:
        self._on_map = on_map
        self.key = map_key(prefix)
        self.errors: Counter[str] = Counter()
        self.received = 0
        self._subscriber = session.declare_subscriber(self.key, self._handle)

    def _handle(self, sample: zenoh.Sample) -> None:
        try:
            msg = decode_map(sample.payload.to_bytes())
            self.received += 1
            self._on_map(msg)
        except LelsonarError as exc:
            self.errors[type(exc).__name__] += 1
            _log.warning("map on %s: %s: %s", self.key, type(exc).__name__, exc)
        except Exception:  # a Zenoh callback must not die silently: count it, log it with its traceback
            self.errors["unexpected"] += 1
            _log.exception("map on %s: unexpected error", self.key)

    def __enter__(self) -> MapSubscription:
        return self

    def __exit__(self, *exc_info) -> None:
        self._subscriber.undeclare()
