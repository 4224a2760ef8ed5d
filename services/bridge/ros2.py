"""ROS 2 view of a scan, and the rosbag2 export.  The only module that imports ``rosbags``.

:class:`Ros2View` is an observer of :class:`lelsonar.reconstruct.stream.service.ReconstructionService`:
it turns what the service sees into ROS 2 messages and hands each to a sink —
the rosbag2 writer here (:func:`export_rosbag2`), or the rmw_zenoh publisher
(:mod:`lelsonar.bridge.rmw_zenoh`).  Both carry the same topics:

==============================  ==================================  ======  ============================================
topic                           type                                QoS     what
==============================  ==================================  ======  ============================================
``/tf_static``                  ``tf2_msgs/msg/TFMessage``          TL, 1   per scan: base → axis, array → each capsule
``/tf``                         ``tf2_msgs/msg/TFMessage``          V, 100  per step: axis → array, γ_measured about x
``/lelsonar/range/capsule<i>``  ``sensor_msgs/msg/Range``           V, 10   per step, capsule; ``+inf`` without an echo
``/lelsonar/points/raw``        ``sensor_msgs/msg/PointCloud2``     V, 10   per step: eq. (9) points of the scan so far
``/lelsonar/points/corrected``  ``sensor_msgs/msg/PointCloud2``     V, 10   per estimate: §4 corrected points, a and b
``/lelsonar/planes``            ``visualization_msgs/MarkerArray``  TL, 1   per estimate: planes per method, truth, edge
``/lelsonar/estimate``          ``std_msgs/msg/String``             TL, 1   per estimate: the Reconstruction as JSON
``/map``                        ``nav_msgs/msg/OccupancyGrid``      TL, 1   per map update (:mod:`.ros2_map`)
``/lelsonar/map/walls``         ``visualization_msgs/MarkerArray``  TL, 1   per map update: walls, corners, path
==============================  ==================================  ======  ============================================

(TL = RELIABLE, TRANSIENT_LOCAL, KEEP_LAST depth; V = RELIABLE, VOLATILE, KEEP_LAST depth.)
Several scanners share these topics; their frame ids (and the estimate's
``scanner_id``) tell them apart.

Frames (``<s>`` is the scanner id; tf2 frame ids may hold ``.`` and ``-``):

* ``<s>/base`` — lelsonar's world frame: x is the rotation axis, at γ = 0 the
  beams point along +y.  Every point cloud and marker is in this frame.
  ``--parent-frame`` adds an identity ``<parent> → <s>/base`` to ``/tf_static``.
* ``<s>/axis`` — on the rotation axis, x along ``ScanStart.rotation_axis``.
* ``<s>/array`` — ``<s>/axis`` rotated by γ_measured about x (``/tf``).
* ``<s>/capsule<i>`` — at the capsule's position in the array frame, +x along
  its boresight, as REP 117 / ``sensor_msgs/Range`` expects.

Range fields: ``field_of_view`` is the full angle of the beam in which a wall
still returns a mirror echo, ``2 × FitOptions.beam_half_angle`` (70°) unless
given; ``min_range``/``max_range`` are the listening window,
``c·t0/2`` and ``c·(t0 + window_samples/sample_rate)/2``.

``/lelsonar/estimate`` carries exactly the line ``lelsonar reconstruct --json``
prints (``lelsonar.view.present.to_json``): the ``lelsonar.v1.Reconstruction``
fields with proto names, SI units, ``status`` as a lower-case name.
"""

from __future__ import annotations

import dataclasses
import math
import shutil
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.interfaces import Connection, Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from lelsonar import codec
from lelsonar.bridge.ros2_markers import estimate_markers
from lelsonar.bridge.ros2_shapes import (
    POINTFIELD_TYPES,
    RAW_POINT,
    corrected_rows,
    quat_from_x_to,
    quat_x,
    stack_rows,
)
from lelsonar.errors import ConfigError, RecordingError
from lelsonar.log.reader import check_recording_path
from lelsonar.reconstruct.estimate.pipeline import FitOptions
from lelsonar.reconstruct.estimate.results import ScanReconstruction
from lelsonar.reconstruct.stream.assembly import ScanAssembly, StepView
from lelsonar.reconstruct.stream.replay import replay_mcap
from lelsonar.reconstruct.stream.service import ReconstructionService
from lelsonar.view import present

__all__ = [
    "DISTROS",
    "TOPIC_TF",
    "TOPIC_TF_STATIC",
    "TOPIC_POINTS_RAW",
    "TOPIC_POINTS_CORRECTED",
    "TOPIC_PLANES",
    "TOPIC_ESTIMATE",
    "TOPIC_MAP_GRID",
    "TOPIC_MAP_WALLS",
    "TopicQos",
    "TOPIC_QOS",
    "RosMessage",
    "Ros2View",
    "TruePlane",
    "typestore",
    "range_topic",
    "type_hash",
    "serialize",
    "deserialize",
    "export_rosbag2",
    "open_bag",
    "read_bag",
]

#: distro → (rosbags typestore, rosbag2 metadata version).  Humble's ``ros2 bag`` reads version 8.
#: The rosbag2 type store and bag version of each distro.
DISTROS: dict[str, tuple[Stores, Literal[8, 9]]] = {"jazzy": (Stores.ROS2_JAZZY, 9), "humble": (Stores.ROS2_HUMBLE, 8)}

TOPIC_TF = "/tf"
TOPIC_TF_STATIC = "/tf_static"
TOPIC_POINTS_RAW = "/lelsonar/points/raw"
TOPIC_POINTS_CORRECTED = "/lelsonar/points/corrected"
TOPIC_PLANES = "/lelsonar/planes"
TOPIC_ESTIMATE = "/lelsonar/estimate"
TOPIC_MAP_GRID = "/map"
TOPIC_MAP_WALLS = "/lelsonar/map/walls"

TF = "tf2_msgs/msg/TFMessage"
RANGE = "sensor_msgs/msg/Range"
CLOUD = "sensor_msgs/msg/PointCloud2"
MARKERS = "visualization_msgs/msg/MarkerArray"
STRING = "std_msgs/msg/String"
OCCUPANCY_GRID = "nav_msgs/msg/OccupancyGrid"


def range_topic(capsule_id: int) -> str:
    return f"/lelsonar/range/capsule{capsule_id}"


@dataclass(frozen=True)
class TopicQos:
    """The QoS a topic is offered with (always RELIABLE, KEEP_LAST)."""

    depth: int
    transient_local: bool = False


TOPIC_QOS: dict[str, TopicQos] = {
    TOPIC_TF_STATIC: TopicQos(1, True),
    TOPIC_TF: TopicQos(100),
    TOPIC_PLANES: TopicQos(1, True),
    TOPIC_ESTIMATE: TopicQos(1, True),
    TOPIC_MAP_GRID: TopicQos(1, True),
    TOPIC_MAP_WALLS: TopicQos(1, True),
}
DEFAULT_QOS = TopicQos(10)


def topic_qos(topic: str) -> TopicQos:
    return TOPIC_QOS.get(topic, DEFAULT_QOS)


@dataclass(frozen=True)
class RosMessage:
    """One ROS 2 message ready for a sink."""

    topic: str
    msgtype: str
    time_ns: int
    message: object


@dataclass(frozen=True)
class TruePlane:
    """A true plane of a simulated scene, drawn grey: normal (unit), offset (m), corners (k, 3)."""

    label: str
    normal: np.ndarray
    offset: float
    corners: np.ndarray


# --- typestore, hashes, CDR ---------------------------------------------------------------
_STORES: dict[str, object] = {}


def typestore(distro: str = "jazzy"):
    """The rosbags typestore of a ROS 2 distro (cached)."""
    if distro not in DISTROS:
        raise ConfigError(f"ROS 2 distro must be one of {', '.join(DISTROS)}, got {distro!r}")
    if distro not in _STORES:
        _STORES[distro] = get_typestore(DISTROS[distro][0])
    return _STORES[distro]


def type_hash(msgtype: str, distro: str = "jazzy") -> str:
    """The RIHS01 type hash ROS 2 (Iron and later) computes for ``msgtype``."""
    return typestore(distro).hash_rihs01(msgtype)


def serialize(message: object, msgtype: str, distro: str = "jazzy") -> bytes:
    """CDR bytes with the 4-byte encapsulation header, as rmw and rosbag2 carry them."""
    return bytes(typestore(distro).serialize_cdr(message, msgtype))


def deserialize(data: bytes, msgtype: str, distro: str = "jazzy") -> object:
    return typestore(distro).deserialize_cdr(data, msgtype)


class Builder:
    """Message constructors for one typestore; fields a distro lacks (e.g. Humble's Range.variance) are dropped."""

    def __init__(self, distro: str) -> None:
        self.distro = distro
        self._ts = typestore(distro)
        self._fields: dict[str, set[str]] = {}

    def __call__(self, msgtype: str, **fields):
        cls = self._ts.types[msgtype]
        names = self._fields.get(msgtype)
        if names is None:
            names = self._fields[msgtype] = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in fields.items() if k in names})

    def time(self, t_ns: int):
        return self("builtin_interfaces/msg/Time", sec=int(t_ns // 1_000_000_000), nanosec=int(t_ns % 1_000_000_000))

    def header(self, t_ns: int, frame: str):
        return self("std_msgs/msg/Header", stamp=self.time(t_ns), frame_id=frame)

    def vector3(self, v) -> object:
        return self("geometry_msgs/msg/Vector3", x=float(v[0]), y=float(v[1]), z=float(v[2]))

    def point(self, v) -> object:
        return self("geometry_msgs/msg/Point", x=float(v[0]), y=float(v[1]), z=float(v[2]))

    def quaternion(self, q) -> object:
        return self("geometry_msgs/msg/Quaternion", x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))

    def transform(self, t_ns: int, parent: str, child: str, translation, rotation) -> object:
        return self(
            "geometry_msgs/msg/TransformStamped",
            header=self.header(t_ns, parent),
            child_frame_id=child,
            transform=self(
                "geometry_msgs/msg/Transform", translation=self.vector3(translation), rotation=self.quaternion(rotation)
            ),
        )

    def color(self, rgb: Sequence[float], alpha: float) -> object:
        return self("std_msgs/msg/ColorRGBA", r=float(rgb[0]), g=float(rgb[1]), b=float(rgb[2]), a=float(alpha))

    def cloud(self, t_ns: int, frame: str, points: np.ndarray) -> object:
        """A PointCloud2 of a structured array (its named fields become the PointFields)."""
        dt = points.dtype
        if dt.fields is None or dt.names is None:
            raise ConfigError(f"a point cloud needs a structured array, got dtype {dt}")
        fields = [
            self(
                "sensor_msgs/msg/PointField",
                name=name,
                offset=int(dt.fields[name][1]),
                datatype=POINTFIELD_TYPES[dt.fields[name][0].str.lstrip("<|")],
                count=1,
            )
            for name in dt.names
        ]
        data = np.frombuffer(np.ascontiguousarray(points).tobytes(), dtype=np.uint8)
        return self(
            CLOUD,
            header=self.header(t_ns, frame),
            height=1,
            width=int(points.shape[0]),
            fields=fields,
            is_bigendian=False,
            point_step=int(dt.itemsize),
            row_step=int(dt.itemsize * points.shape[0]),
            data=data,
            is_dense=True,
        )

    def marker(
        self,
        t_ns: int,
        frame: str,
        ns: str,
        id_: int,
        kind: int,
        *,
        points=(),
        rgb=(0.5, 0.5, 0.5),
        alpha: float = 1.0,
        scale=(1.0, 1.0, 1.0),
        text: str = "",
        position=(0.0, 0.0, 0.0),
        action: int = 0,
        orientation=(0.0, 0.0, 0.0, 1.0),
    ) -> object:
        b = self
        return b(
            "visualization_msgs/msg/Marker",
            header=b.header(t_ns, frame),
            ns=ns,
            id=int(id_),
            type=int(kind),
            action=int(action),
            pose=b("geometry_msgs/msg/Pose", position=b.point(position), orientation=b.quaternion(orientation)),
            scale=b.vector3(scale),
            color=b.color(rgb, alpha),
            lifetime=b("builtin_interfaces/msg/Duration", sec=0, nanosec=0),
            frame_locked=False,
            points=[b.point(p) for p in points],
            colors=[],
            texture_resource="",
            texture=b(
                "sensor_msgs/msg/CompressedImage", header=b.header(0, ""), format="", data=np.zeros(0, dtype=np.uint8)
            ),
            uv_coordinates=[],
            text=text,
            mesh_resource="",
            mesh_file=b("visualization_msgs/msg/MeshFile", filename="", data=np.zeros(0, dtype=np.uint8)),
            mesh_use_embedded_materials=False,
        )


# --- the observer -------------------------------------------------------------------------
class Ros2View:
    """Implements :class:`lelsonar.reconstruct.stream.service.Observer`: every event becomes ROS 2 messages.

    Parameters
    ----------
    emit : callable
        Receives each :class:`RosMessage`, in the order the service saw things.
    main_method : str
        The estimator of record: its subsets are the corrected points.
    distro : {"jazzy", "humble"}
    truth : callable, optional
        ``truth(scan) -> list[TruePlane] | None``: the true planes, drawn when known.
    field_of_view : float, optional
        Full beam angle written into each ``Range``, rad (default ``2 × FitOptions.beam_half_angle``).
    parent_frame : str, optional
        Also publish an identity ``parent_frame → <s>/base``.
    """

    def __init__(
        self,
        emit: Callable[[RosMessage], None],
        *,
        main_method: str,
        distro: str = "jazzy",
        truth: Callable[[ScanAssembly], Sequence[TruePlane] | None] | None = None,
        field_of_view: float | None = None,
        parent_frame: str | None = None,
    ) -> None:
        self._emit = emit
        self._b = Builder(distro)
        self.main_method = main_method
        self._truth = truth
        self.field_of_view = float(field_of_view if field_of_view is not None else 2.0 * FitOptions().beam_half_angle)
        if not 0 < self.field_of_view < math.pi:
            raise ConfigError(f"the field of view must be in (0, 180°), got {math.degrees(self.field_of_view):.1f}°")
        self.parent_frame = parent_frame
        self._raw: dict[tuple[str, int], list[np.ndarray]] = {}

    @staticmethod
    def frame(scanner: str, name: str) -> str:
        return f"{scanner}/{name}"

    def _send(self, topic: str, msgtype: str, t_ns: int, message: object) -> None:
        self._emit(RosMessage(topic, msgtype, int(t_ns), message))

    # Observer protocol -------------------------------------------------------------------
    def scan_started(self, scan: ScanAssembly) -> None:
        s, b = scan.start, self._b
        t = s.start_time_ns
        base, axis, array = (self.frame(s.scanner_id, n) for n in ("base", "axis", "array"))
        tfs = []
        if self.parent_frame:
            tfs.append(b.transform(t, self.parent_frame, base, (0, 0, 0), (0, 0, 0, 1)))
        ax = (s.rotation_axis.x, s.rotation_axis.y, s.rotation_axis.z)
        tfs.append(b.transform(t, base, axis, (0, 0, 0), quat_from_x_to(ax) if any(ax) else (0, 0, 0, 1)))
        for c in sorted(s.capsules, key=lambda c: c.capsule_id):
            tfs.append(
                b.transform(
                    t,
                    array,
                    self.frame(s.scanner_id, f"capsule{c.capsule_id}"),
                    (c.position.x, c.position.y, c.position.z),
                    quat_from_x_to((c.boresight.x, c.boresight.y, c.boresight.z)),
                )
            )
        self._send(TOPIC_TF_STATIC, TF, t, b(TF, transforms=tfs))
        self._raw[scan.key] = []

    def step(self, scan: ScanAssembly, view: StepView, energy: float, expected: float, ratio: float) -> None:
        s, b = scan.start, self._b
        t = view.time_ns
        self._send(
            TOPIC_TF,
            TF,
            t,
            b(
                TF,
                transforms=[
                    b.transform(
                        t,
                        self.frame(s.scanner_id, "axis"),
                        self.frame(s.scanner_id, "array"),
                        (0, 0, 0),
                        quat_x(view.gamma),
                    )
                ],
            ),
        )
        lo = s.sound_speed * view.t0 / 2.0
        hi = s.sound_speed * (view.t0 + s.window_samples / s.sample_rate) / 2.0 if s.sample_rate > 0 else math.inf
        ids = sorted(c.capsule_id for c in s.capsules)
        for k, cid in enumerate(ids):
            d = float(view.distance[k])
            self._send(
                range_topic(cid),
                RANGE,
                t,
                b(
                    RANGE,
                    header=b.header(t, self.frame(s.scanner_id, f"capsule{cid}")),
                    radiation_type=0,
                    field_of_view=self.field_of_view,
                    min_range=lo,
                    max_range=hi,
                    range=d if math.isfinite(d) else math.inf,
                    variance=0.0,
                ),
            )
        pts = scan.raw_points(view.step)
        ok = np.all(np.isfinite(pts), axis=-1)
        rows = np.zeros(int(ok.sum()), dtype=RAW_POINT)
        rows["x"], rows["y"], rows["z"] = pts[ok].T
        rows["step"], rows["capsule"] = view.step, np.asarray(ids)[ok]
        acc = self._raw.setdefault(scan.key, [])
        acc.append(rows)
        self._send(TOPIC_POINTS_RAW, CLOUD, t, b.cloud(t, self.frame(s.scanner_id, "base"), stack_rows(acc, RAW_POINT)))

    def estimate(
        self, scan: ScanAssembly, message: codec.Reconstruction, results: dict[str, ScanReconstruction] | None, partial
    ) -> None:
        s, b = scan.start, self._b
        final = results is not None
        if final and scan.end is not None:
            t = scan.end.end_time_ns
        else:
            t = int(scan.time_ns[message.last_step])
        base = self.frame(s.scanner_id, "base")
        if results is not None:
            subsets = self._final_subsets(scan, results[self.main_method])
            self._raw.pop(scan.key, None)
        else:
            subsets = [(partial.data_a, partial.plane_a), (partial.data_b, partial.plane_b)]
        self._send(TOPIC_POINTS_CORRECTED, CLOUD, t, b.cloud(t, base, corrected_rows(subsets)))
        self._send(
            TOPIC_PLANES,
            MARKERS,
            t,
            b(MARKERS, markers=estimate_markers(b, message, t, base, self._truth(scan) if self._truth else None)),
        )
        self._send(TOPIC_ESTIMATE, STRING, t, b(STRING, data=present.to_json(message)))

    def event(self, level: str, text: str, time_ns: int | None = None) -> None:
        pass  # the service logs it; a /rosout bridge is future work

    # helpers -----------------------------------------------------------------------------
    @staticmethod
    def _final_subsets(scan: ScanAssembly, main: ScanReconstruction) -> list:
        # The points each plane was fitted on, as reconstruct() chose them; plane_data numbers
        # steps within the received ones, so report schedule steps.
        steps = np.flatnonzero(scan.received)
        return [
            (dataclasses.replace(data, step=steps[data.step]) if data.n else data, plane)
            for data, plane in ((main.data_a, main.plane_a), (main.data_b, main.plane_b))
            if data is not None
        ]


# --- rosbag2 ------------------------------------------------------------------------------
def rosbags_qos(qos: TopicQos) -> Qos:
    never = QosTime(sec=0, nsec=0)  # 0 s = the rmw default: no deadline, lifespan or lease
    return Qos(
        history=QosHistory.KEEP_LAST,
        depth=qos.depth,
        reliability=QosReliability.RELIABLE,
        durability=QosDurability.TRANSIENT_LOCAL if qos.transient_local else QosDurability.VOLATILE,
        deadline=never,
        lifespan=never,
        liveliness=QosLiveliness.AUTOMATIC,
        liveliness_lease_duration=never,
        avoid_ros_namespace_conventions=False,
    )


class BagSink:
    """Writes RosMessages to an open rosbags ``Writer``, adding each topic's connection on first use."""

    def __init__(self, writer: Writer, distro: str) -> None:
        self._writer = writer
        self._distro = distro
        self._ts = typestore(distro)
        self._connections: dict[str, Connection] = {}
        self.counts: dict[str, int] = {}

    def __call__(self, m: RosMessage) -> None:
        conn = self._connections.get(m.topic)
        if conn is None:
            conn = self._connections[m.topic] = self._writer.add_connection(
                m.topic, m.msgtype, typestore=self._ts, offered_qos_profiles=[rosbags_qos(topic_qos(m.topic))]
            )
        self._writer.write(conn, m.time_ns, serialize(m.message, m.msgtype, self._distro))
        self.counts[m.topic] = self.counts.get(m.topic, 0) + 1


@contextmanager
def open_bag(out_dir: Path | str, distro: str = "jazzy") -> Iterator[Writer]:
    """An open rosbag2 writer (MCAP storage) of a new directory; finished on any exit."""
    typestore(distro)  # an unknown distro is refused before the directory is made
    with Writer(Path(out_dir), version=DISTROS[distro][1], storage_plugin=StoragePlugin.MCAP) as w:
        yield w


def export_rosbag2(
    source: Path | str,
    out_dir: Path | str,
    *,
    view_factory: Callable[[Callable], Ros2View],
    service_factory: Callable[[Ros2View], ReconstructionService],
    distro: str = "jazzy",
) -> dict[str, int]:
    """Write a rosbag2 directory (``metadata.yaml`` + MCAP, ``cdr``) from a lelsonar recording.

    The recording is replayed through a reconstruction service (``service_factory(view)``)
    whose observer is the :class:`Ros2View` built by ``view_factory(sink)``.

    Returns
    -------
    dict
        Messages written per topic.

    Raises
    ------
    RecordingError
        ``out_dir`` exists (rosbag2 never overwrites), or the recording cannot be read; a
        partly written bag is removed.
    """
    out = Path(out_dir)
    if out.exists():
        raise RecordingError(f"{out} already exists; rosbag2 writes a new directory (remove it or pick another -o)")
    check_recording_path(source)  # a named pipe or a device is refused before it is opened
    if not Path(source).is_file():
        raise RecordingError(f"no recording at {source}")
    out.parent.mkdir(parents=True, exist_ok=True)
    try:
        with Writer(out, version=DISTROS[distro][1], storage_plugin=StoragePlugin.MCAP) as writer:
            sink = BagSink(writer, distro)
            service = service_factory(view_factory(sink))
            replay_mcap(source, service)
    except BaseException:
        shutil.rmtree(out, ignore_errors=True)
        raise
    return dict(sink.counts)


def read_bag(path: Path | str, distro: str = "jazzy") -> list[tuple[str, str, int, object]]:
    """Every message of a rosbag2 directory as ``(topic, msgtype, log time ns, message)``, in time order."""
    out = []
    with AnyReader([Path(path)], default_typestore=typestore(distro)) as reader:
        for conn, t, raw in reader.messages():
            out.append((conn.topic, conn.msgtype, t, reader.deserialize(raw, conn.msgtype)))
    return out
