"""What viewers draw: Foxglove messages built from the contract messages.

The same builders feed the acquisition MCAP (:mod:`lelsonar.log.recording`),
``reconstruct --record`` and the live Foxglove WebSocket
(:mod:`lelsonar.bridge.foxglove`), so a recording opened alone shows what the
live view showed.  Every message is a ``foxglove_schemas_protobuf`` message
with every sub-message set (an unset one breaks ``rerun mcap convert``), or a
JSON object with a JSON schema (Foxglove plots its numeric fields).

Frames::

    world ── array          rotation γ about x, one transform per step
               ├─ capsule_A  translation = the capsule's position, x along its boresight
               ├─ capsule_B  (one transform per scan, at its start)
               └─ ...

Topics (the names are the same live and recorded):

==========================  =============================  =====================================
topic                       schema                         what
==========================  =============================  =====================================
``/tf``                     ``foxglove.FrameTransform``    world → array, per step (recording); map → odom →
                                                           base_link → world per scan, when the scan has a pose
``/tf_capsules``            ``foxglove.FrameTransforms``   array → capsule_X, per scan
``/lelsonar/array``         ``foxglove.SceneUpdate``       capsules and beams, in the array frame
``/lelsonar/points``        ``foxglove.PointCloud``        the raw points of the latest step
``/lelsonar/scan_points``   ``foxglove.PointCloud``        every raw point of the scan so far
``/lelsonar/step``          JSON ``lelsonar.StepScalars``  γ, ranges and energies of the step
``/lelsonar/energy``        JSON ``lelsonar.EnergyScalars`` E^γ, E0(d_m), R, critical step
``/lelsonar/planes``        ``foxglove.SceneUpdate``       planes, normals, labels, the edge
==========================  =============================  =====================================
"""

from __future__ import annotations

import functools
import json
import math

import numpy as np
from foxglove_schemas_protobuf.ArrowPrimitive_pb2 import ArrowPrimitive
from foxglove_schemas_protobuf.Color_pb2 import Color
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.KeyValuePair_pb2 import KeyValuePair
from foxglove_schemas_protobuf.LinePrimitive_pb2 import LinePrimitive
from foxglove_schemas_protobuf.Log_pb2 import Log
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.Point3_pb2 import Point3
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
from foxglove_schemas_protobuf.SceneEntityDeletion_pb2 import SceneEntityDeletion
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from foxglove_schemas_protobuf.SpherePrimitive_pb2 import SpherePrimitive
from foxglove_schemas_protobuf.TextPrimitive_pb2 import TextPrimitive
from foxglove_schemas_protobuf.TriangleListPrimitive_pb2 import TriangleListPrimitive
from google.protobuf import descriptor_pb2
from google.protobuf.message import Message

from lelsonar import codec
from lelsonar.draw.palette import QUALITY_NAME, method_color, quality_color
from lelsonar.energy_model import EnergyModel
from lelsonar.errors import ConfigError
from lelsonar.geometry import beam_heading, matrix_from_quaternion, quaternion_from_matrix, rotation_z
from lelsonar.v1 import reconstruction_pb2

WORLD_FRAME = "world"
ARRAY_FRAME = "array"

TOPIC_TF = "/tf"
TOPIC_CAPSULE_TF = "/tf_capsules"
TOPIC_ARRAY = "/lelsonar/array"
TOPIC_POINTS = "/lelsonar/points"
TOPIC_SCAN_POINTS = "/lelsonar/scan_points"
TOPIC_STEP = "/lelsonar/step"
TOPIC_ENERGY = "/lelsonar/energy"
TOPIC_PLANES = "/lelsonar/planes"
TOPIC_LOG = "/log"

_PATCH_ALPHA = 0.45
_NORMAL_LENGTH = 0.25  # m
_EDGE_RGB = (255, 255, 255)


def capsule_frame(capsule_id: int) -> str:
    """``capsule_A`` … (the paper names the capsules A, B, C, D)."""
    return f"capsule_{chr(ord('A') + capsule_id)}" if capsule_id < 26 else f"capsule_{capsule_id}"


def capsule_name(capsule_id: int) -> str:
    return capsule_frame(capsule_id).removeprefix("capsule_")


# --- schemas for a live server -------------------------------------------------------------
def file_descriptor_set(message_type: type[Message]) -> bytes:
    """The serialized ``FileDescriptorSet`` of a protobuf type and its imports (a channel's schema)."""
    fds = descriptor_pb2.FileDescriptorSet()
    seen: set[str] = set()

    def add(fd) -> None:
        if fd.name in seen:
            return
        seen.add(fd.name)
        for dep in fd.dependencies:
            add(dep)
        proto = fds.file.add()
        fd.CopyToProto(proto)

    add(message_type.DESCRIPTOR.file)
    return fds.SerializeToString()


# --- frames --------------------------------------------------------------------------------
def _color(rgb: tuple[int, int, int], alpha: float = 1.0) -> Color:
    return Color(r=rgb[0] / 255.0, g=rgb[1] / 255.0, b=rgb[2] / 255.0, a=alpha)


def _point(p) -> Point3:
    return Point3(x=float(p[0]), y=float(p[1]), z=float(p[2]))


def _set_position(pose, p) -> None:
    pose.position.x, pose.position.y, pose.position.z = float(p[0]), float(p[1]), float(p[2])


def _quat_x_to(v: np.ndarray) -> tuple[float, float, float, float]:
    """(x, y, z, w) of the shortest rotation taking +x onto the unit vector ``v``."""
    v = np.asarray(v, dtype=float)
    v = v / np.linalg.norm(v)
    c = float(v[0])
    if c < -1.0 + 1e-12:
        return 0.0, 0.0, 1.0, 0.0  # half a turn about z
    axis = np.cross([1.0, 0.0, 0.0], v)
    w = math.sqrt(0.5 * (1.0 + c))
    axis = axis / (2.0 * w)
    return float(axis[0]), float(axis[1]), float(axis[2]), w


def frame_transform(
    parent: str, child: str, t_ns: int, translation=(0.0, 0.0, 0.0), rotation=(0.0, 0.0, 0.0, 1.0)
) -> FrameTransform:
    """A ``foxglove.FrameTransform``; ``rotation`` is (x, y, z, w), identity by default (w = 1)."""
    tf = FrameTransform(parent_frame_id=parent, child_frame_id=child)
    tf.timestamp.FromNanoseconds(int(t_ns))
    tf.translation.x, tf.translation.y, tf.translation.z = map(float, translation)
    tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w = map(float, rotation)
    return tf


def array_transform(gamma: float, t_ns: int) -> FrameTransform:
    """world → array: the array turned by γ about x."""
    half = 0.5 * gamma
    return frame_transform(WORLD_FRAME, ARRAY_FRAME, t_ns, rotation=(math.sin(half), 0.0, 0.0, math.cos(half)))


MAP_FRAME = "map"
BASE_FRAME = "base_link"


def pose_transforms(start: codec.ScanStart, t_ns: int) -> list[FrameTransform]:
    """map → odom → base_link → world of a scan that carries a pose; none for one that does not.

    ``odom`` is the pose's frame (map → odom is the identity: the odometry's own start).
    ``base_link`` is the floor point below the array, heading along its γ = 0 beam; ``world``
    (the array frame at γ = 0, the frame the scan is drawn in) sits on it by the mount.
    """
    if not start.HasField("pose"):
        return []
    pose = codec.scan_pose(start)
    out = []
    if pose.frame_id != MAP_FRAME:
        out.append(frame_transform(MAP_FRAME, pose.frame_id, t_ns))
    heading = beam_heading(pose.orientation)
    base_rot = rotation_z(heading)
    base_t = np.array([pose.position[0], pose.position[1], 0.0])
    out.append(
        frame_transform(
            pose.frame_id, BASE_FRAME, t_ns, base_t, (0.0, 0.0, math.sin(heading / 2), math.cos(heading / 2))
        )
    )
    mount = base_rot.T @ matrix_from_quaternion(pose.orientation)
    out.append(
        frame_transform(
            BASE_FRAME, WORLD_FRAME, t_ns, base_rot.T @ (pose.position - base_t), quaternion_from_matrix(mount)
        )
    )
    return out


def capsule_transforms(start: codec.ScanStart, t_ns: int | None = None) -> FrameTransforms:
    """array → capsule_X for every capsule of the scan: at its position, x along its boresight."""
    t = start.start_time_ns if t_ns is None else t_ns
    out = FrameTransforms()
    for c in start.capsules:
        b = np.array([c.boresight.x, c.boresight.y, c.boresight.z])
        rot = _quat_x_to(b) if np.linalg.norm(b) > 0 else (0.0, 0.0, 0.0, 1.0)
        out.transforms.append(
            frame_transform(
                ARRAY_FRAME, capsule_frame(c.capsule_id), t, (c.position.x, c.position.y, c.position.z), rot
            )
        )
    return out


def array_model(start: codec.ScanStart, t_ns: int | None = None) -> SceneUpdate:
    """The array in its own frame: a sphere per capsule, its beam direction and its name."""
    t = start.start_time_ns if t_ns is None else t_ns
    ent = SceneEntity(frame_id=ARRAY_FRAME, id=f"{start.scanner_id}/array", frame_locked=True)
    ent.timestamp.FromNanoseconds(int(t))
    ent.lifetime.SetInParent()
    for c in start.capsules:
        p = (c.position.x, c.position.y, c.position.z)
        b = np.array([c.boresight.x, c.boresight.y, c.boresight.z])
        s = SpherePrimitive(color=_color((230, 230, 230)))
        _set_position(s.pose, p)
        s.pose.orientation.w = 1.0
        s.size.x = s.size.y = s.size.z = 0.02
        ent.spheres.append(s)
        a = ArrowPrimitive(
            shaft_length=0.08, shaft_diameter=0.004, head_length=0.02, head_diameter=0.012, color=_color((90, 160, 255))
        )
        _set_position(a.pose, p)
        x, y, z, w = _quat_x_to(b) if np.linalg.norm(b) > 0 else (0.0, 0.0, 0.0, 1.0)
        a.pose.orientation.x, a.pose.orientation.y, a.pose.orientation.z, a.pose.orientation.w = x, y, z, w
        ent.arrows.append(a)
        label = TextPrimitive(
            billboard=True,
            font_size=14.0,
            scale_invariant=True,
            text=capsule_name(c.capsule_id),
            color=_color((255, 255, 255)),
        )
        _set_position(label.pose, (p[0], p[1], p[2] - 0.03))
        label.pose.orientation.w = 1.0
        ent.texts.append(label)
    return SceneUpdate(entities=[ent])


# --- points --------------------------------------------------------------------------------
#: Fields of the scan clouds: x, y, z (m), then the step and the capsule of each point.
CLOUD_FIELDS = ("x", "y", "z", "step", "capsule")


def point_cloud(
    points: np.ndarray,
    t_ns: int,
    frame_id: str = WORLD_FRAME,
    step: np.ndarray | None = None,
    capsule: np.ndarray | None = None,
) -> PointCloud:
    """A ``foxglove.PointCloud`` of float32 fields: x, y, z and, if given, step and capsule."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    cols = [pts[:, 0], pts[:, 1], pts[:, 2]]
    names = ["x", "y", "z"]
    if step is not None and capsule is not None:
        cols += [np.asarray(step, dtype=np.float64), np.asarray(capsule, dtype=np.float64)]
        names += ["step", "capsule"]
    data = np.ascontiguousarray(np.stack(cols, axis=1), dtype="<f4")
    msg = PointCloud(frame_id=frame_id, point_stride=4 * len(names), data=data.tobytes())
    msg.timestamp.FromNanoseconds(int(t_ns))
    msg.pose.position.SetInParent()
    msg.pose.orientation.w = 1.0
    for i, name in enumerate(names):
        msg.fields.append(PackedElementField(name=name, offset=4 * i, type=PackedElementField.FLOAT32))
    return msg


def sample_points(start: codec.ScanStart, sample: codec.Sample) -> tuple[np.ndarray, np.ndarray]:
    """The raw points of eq. (9) of one sample's valid echoes, and their capsule ids."""
    by_id = {c.capsule_id: c for c in start.capsules}
    rows = [(by_id[s.capsule_id], s.distance) for s in sample.sensors if s.echo_valid and s.capsule_id in by_id]
    if not rows:
        return np.empty((0, 3)), np.empty(0, dtype=int)
    local = np.array(
        [
            [c.position.x + d * c.boresight.x, c.position.y + d * c.boresight.y, c.position.z + d * c.boresight.z]
            for c, d in rows
        ]
    )
    # Eq. (9) as beam_points_from_capsules computes it, for one γ (its general form pays for many γ).
    cg, sg = math.cos(sample.gamma_measured), math.sin(sample.gamma_measured)
    rot = np.array([[1.0, 0.0, 0.0], [0.0, cg, -sg], [0.0, sg, cg]])
    return local @ rot.T, np.array([c.capsule_id for c, _ in rows])


class ScanCloud:
    """The raw points of each scan so far: :meth:`add` returns the cloud of the whole scan up to a sample.

    Each scan's points live in one float32 buffer (x, y, z, step, capsule) that grows by
    doubling, so adding a step costs the same at step 1 and step 1000.
    """

    def __init__(self) -> None:
        self._starts: dict[tuple[str, int], codec.ScanStart] = {}
        self._buffers: dict[tuple[str, int], np.ndarray] = {}
        self._counts: dict[tuple[str, int], int] = {}

    def scan_started(self, start: codec.ScanStart) -> None:
        key = (start.scanner_id, start.scan_id)
        self._starts[key] = start
        self._buffers[key] = np.empty((max(4, 4 * int(start.steps or 1)), len(CLOUD_FIELDS)), dtype="<f4")
        self._counts[key] = 0

    def add(self, sample: codec.Sample, t_ns: int | None = None) -> PointCloud | None:
        """The cloud of the scan with this sample's points added; None before its ScanStart."""
        key = (sample.scanner_id, sample.scan_id)
        start = self._starts.get(key)
        if start is None:
            return None
        pts, caps = sample_points(start, sample)
        buf, n = self._buffers[key], self._counts[key]
        if n + len(pts) > len(buf):
            buf = self._buffers[key] = np.concatenate([buf, np.empty_like(buf)])
        rows = buf[n : n + len(pts)]
        rows[:, :3] = pts
        rows[:, 3] = sample.step
        rows[:, 4] = caps
        n = self._counts[key] = n + len(pts)
        msg = PointCloud(frame_id=WORLD_FRAME, point_stride=4 * len(CLOUD_FIELDS), data=buf[:n].tobytes())
        msg.timestamp.FromNanoseconds(int(sample.acquisition_time_ns if t_ns is None else t_ns))
        msg.pose.position.SetInParent()
        msg.pose.orientation.w = 1.0
        for i, name in enumerate(CLOUD_FIELDS):
            msg.fields.append(PackedElementField(name=name, offset=4 * i, type=PackedElementField.FLOAT32))
        return msg

    def scan_ended(self, scanner_id: str, scan_id: int) -> None:
        for table in (self._starts, self._buffers, self._counts):
            table.pop((scanner_id, scan_id), None)


# --- plottable scalars ---------------------------------------------------------------------
def _nullable_numbers(description: str) -> dict:
    return {"type": "object", "description": description, "additionalProperties": {"type": ["number", "null"]}}


STEP_SCALARS_NAME = "lelsonar.StepScalars"
#: JSON schema of ``/lelsonar/step``; plot e.g. ``/lelsonar/step.energy`` or ``/lelsonar/step.range.A``.
STEP_SCALARS_SCHEMA: dict = {
    "title": STEP_SCALARS_NAME,
    "description": "One step of a scan as plottable numbers (SI units; angles also in degrees).",
    "type": "object",
    "properties": {
        "scanner_id": {"type": "string"},
        "scan_id": {"type": "integer"},
        "step": {"type": "integer"},
        "gamma": {"type": "number", "description": "measured rotation, rad"},
        "gamma_deg": {"type": "number", "description": "measured rotation, degrees"},
        "energy": {"type": "number", "description": "E^γ, the summed waveform energy of the step, V²·s (eq. 11)"},
        "energy_by_capsule": _nullable_numbers("E_i^γ per capsule, V²·s (eq. 10)"),
        "range": _nullable_numbers("range per capsule, m; null without an echo"),
        "valid_echoes": {"type": "integer"},
    },
}

ENERGY_SCALARS_NAME = "lelsonar.EnergyScalars"
#: JSON schema of ``/lelsonar/energy`` (the reconstruction's view of each step).
ENERGY_SCALARS_SCHEMA: dict = {
    "title": ENERGY_SCALARS_NAME,
    "description": "The corner detector's numbers at each step (the paper's Figs. 4–6).",
    "type": "object",
    "properties": {
        "scanner_id": {"type": "string"},
        "scan_id": {"type": "integer"},
        "step": {"type": "integer"},
        "gamma_deg": {"type": "number"},
        "energy": {"type": ["number", "null"], "description": "E^γ, V²·s"},
        "expected_energy": {"type": ["number", "null"], "description": "E0(d_m), V²·s (eq. 12)"},
        "ratio": {"type": ["number", "null"], "description": "R = E^γ / E0(d_m)"},
        "critical_step": {"type": ["integer", "null"], "description": "the confirmed critical step, if any"},
    },
}


def json_schema_bytes(schema: dict) -> bytes:
    return json.dumps(schema, separators=(",", ":")).encode()


def _finite_or_none(x: float) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None


def step_scalars(sample: codec.Sample) -> dict:
    """γ, the range and the waveform energy of each capsule and their sum, for one sample.

    ``E_i = Σ w² / f_s`` (eq. 10, the rectangle rule, as the reconstruction computes it).
    """
    energies: dict[str, float | None] = {}
    ranges: dict[str, float | None] = {}
    valid = 0
    for s in sample.sensors:
        name = capsule_name(s.capsule_id)
        ranges[name] = float(s.distance) if s.echo_valid else None
        valid += bool(s.echo_valid)
        w = s.waveform
        if w.data and w.sample_rate > 0:
            samples = codec.unpack_waveform(w).astype(np.float64)
            energies[name] = _finite_or_none(np.dot(samples, samples) / w.sample_rate)
        else:
            energies[name] = None
    total = sum(e for e in energies.values() if e is not None)
    return {
        "scanner_id": sample.scanner_id,
        "scan_id": int(sample.scan_id),
        "step": int(sample.step),
        "gamma": float(sample.gamma_measured),
        "gamma_deg": math.degrees(sample.gamma_measured),
        "energy": float(total),
        "energy_by_capsule": energies,
        "range": ranges,
        "valid_echoes": valid,
    }


def energy_scalars(
    scanner_id: str,
    scan_id: int,
    step: int,
    gamma: float,
    energy: float,
    expected: float,
    ratio: float,
    critical_step: int | None,
) -> dict:
    return {
        "scanner_id": scanner_id,
        "scan_id": int(scan_id),
        "step": int(step),
        "gamma_deg": math.degrees(gamma),
        "energy": _finite_or_none(energy),
        "expected_energy": _finite_or_none(expected),
        "ratio": _finite_or_none(ratio),
        "critical_step": None if critical_step is None else int(critical_step),
    }


def acquisition_energy_scalars(start: codec.ScanStart, sample: codec.Sample, step: dict | None = None) -> dict:
    """``/lelsonar/energy`` of one recorded step, from what the scan announced: E^γ of the waveforms
    (eq. 10–11), E0(d_m) of the ScanStart's energy model (eq. 12) at d_m, the median of the step's valid
    ranges (§4), and R = E^γ / E0(d_m) (0 without a range, as the reconstruction has it).  The critical
    step is the reconstruction's: null here.  ``step``: the sample's :func:`step_scalars`, if already made.
    """
    step = step_scalars(sample) if step is None else step
    ranges = sorted(r for r in step["range"].values() if r is not None and math.isfinite(r))
    e = step["energy"]
    em = start.energy_model
    expected = ratio = None
    if not ranges:
        ratio = 0.0
    else:
        model = _energy_model(em.phi0, em.phi1, em.phi2, em.valid_min_range, em.valid_max_range)
        if model is not None:
            n = len(ranges)
            d_m = 0.5 * (ranges[(n - 1) // 2] + ranges[n // 2])  # the median
            expected = float(model.expected_energy(float(d_m)))
            ratio = e / expected if expected > 0 else None
    return energy_scalars(
        sample.scanner_id,
        sample.scan_id,
        sample.step,
        sample.gamma_measured,
        e,
        math.nan if expected is None else expected,
        math.nan if ratio is None else ratio,
        None,
    )


@functools.lru_cache(maxsize=16)
def _energy_model(phi0: float, phi1: float, phi2: float, d_min: float, d_max: float) -> EnergyModel | None:
    """The announced model, checked once per scan (None: unusable, nothing to divide by)."""
    try:
        return EnergyModel(phi0, phi1, phi2, d_min, d_max)
    except ConfigError:
        return None


TOPIC_TRUTH = "/lelsonar/truth"


def truth_scene(planes, scanner_id: str, t_ns: int) -> SceneUpdate:
    """The true planes of a simulated scene, ``(label, normal, offset, corners)`` each, as grey patches."""
    entities: list[SceneEntity] = []
    for label, normal, offset, corners in planes:
        msg = codec.Reconstruction(scanner_id=scanner_id, scan_id=0)
        p = msg.planes.add(label=str(label), method="truth", offset=float(offset))
        p.normal.x, p.normal.y, p.normal.z = map(float, normal)
        for c in np.asarray(corners, dtype=float).reshape(-1, 3):
            q = p.patch.add()
            q.x, q.y, q.z = c
        entities.extend(PlaneScene().update(msg, t_ns).entities)
    for e, (label, _normal, offset, _corners) in zip(entities, planes):
        e.id = f"{scanner_id}/truth/{label}"
        del e.metadata[:]
        for prim in (*e.triangles, *e.lines, *e.arrows, *e.texts):
            # Every primitive message has a color; the tuple's element type is only Message.
            prim.color.r = prim.color.g = prim.color.b = 0.63  # type: ignore[attr-defined]
        e.triangles[0].color.a = 0.3
        e.texts[0].text = f"truth {label}: h = {float(offset):.3f} m"
    return SceneUpdate(entities=entities)


# --- planes --------------------------------------------------------------------------------
def _vec(v) -> np.ndarray:
    return np.array([v.x, v.y, v.z], dtype=float)


def plane_entity_id(scanner_id: str, scan_id: int, method: str, label: str) -> str:
    return f"{scanner_id}/{scan_id}/plane/{method}/{label}"


def edge_entity_id(scanner_id: str, scan_id: int) -> str:
    return f"{scanner_id}/{scan_id}/edge"


def _plane_entity(msg: codec.Reconstruction, p: reconstruction_pb2.PlaneEstimate, t_ns: int) -> SceneEntity | None:
    patch = np.array([_vec(v) for v in p.patch])
    if len(patch) < 3 or not np.all(np.isfinite(patch)):
        return None
    rgb, qrgb = method_color(p.method), quality_color(p.quality)
    quality = QUALITY_NAME.get(p.quality, "unknown")
    ent = SceneEntity(frame_id=WORLD_FRAME, id=plane_entity_id(msg.scanner_id, msg.scan_id, p.method, p.label))
    ent.timestamp.FromNanoseconds(int(t_ns))
    ent.lifetime.SetInParent()
    for k, v in (
        ("method", p.method),
        ("label", p.label),
        ("quality", quality),
        ("quality_reasons", "; ".join(p.quality_reasons)),
        ("offset_m", f"{p.offset:.4f}"),
        ("sigma_mm", f"{p.sigma * 1e3:.2f}"),
        ("inliers", f"{p.inlier_count}/{p.point_count}"),
    ):
        ent.metadata.append(KeyValuePair(key=k, value=v))
    # The patch as a fan of triangles, in the method's colour.
    tri = TriangleListPrimitive(color=_color(rgb, _PATCH_ALPHA))
    tri.pose.position.SetInParent()
    tri.pose.orientation.w = 1.0
    for i in range(1, len(patch) - 1):
        for j in (0, i, i + 1):
            tri.points.append(_point(patch[j]))
    ent.triangles.append(tri)
    # Its outline in the colour of its quality verdict.
    outline = LinePrimitive(type=LinePrimitive.LINE_LOOP, thickness=0.012, scale_invariant=False, color=_color(qrgb))
    outline.pose.position.SetInParent()
    outline.pose.orientation.w = 1.0
    outline.points.extend(_point(v) for v in patch)
    ent.lines.append(outline)
    centre = patch.mean(axis=0)
    n = _vec(p.normal)
    if np.linalg.norm(n) > 0:
        a = ArrowPrimitive(
            shaft_length=0.8 * _NORMAL_LENGTH,
            shaft_diameter=0.01,
            head_length=0.2 * _NORMAL_LENGTH,
            head_diameter=0.03,
            color=_color(rgb),
        )
        _set_position(a.pose, centre)
        x, y, z, w = _quat_x_to(n)
        a.pose.orientation.x, a.pose.orientation.y, a.pose.orientation.z, a.pose.orientation.w = x, y, z, w
        ent.arrows.append(a)
    text = TextPrimitive(
        billboard=True,
        font_size=14.0,
        scale_invariant=True,
        color=_color(qrgb),
        text=f"{p.method} {p.label}: h = {p.offset:.3f} m, σ = {p.sigma * 1e3:.1f} mm, {quality}",
    )
    _set_position(text.pose, centre + (_NORMAL_LENGTH * n if np.linalg.norm(n) > 0 else 0.0))
    text.pose.orientation.w = 1.0
    ent.texts.append(text)
    return ent


def _edge_entity(msg: codec.Reconstruction, t_ns: int, half_length: float = 0.5) -> SceneEntity | None:
    if not msg.HasField("corner_edge"):
        return None
    point, direction = _vec(msg.corner_edge.point), _vec(msg.corner_edge.direction)
    if not (np.all(np.isfinite(point)) and np.linalg.norm(direction) > 0):
        return None
    ent = SceneEntity(frame_id=WORLD_FRAME, id=edge_entity_id(msg.scanner_id, msg.scan_id))
    ent.timestamp.FromNanoseconds(int(t_ns))
    ent.lifetime.SetInParent()
    line = LinePrimitive(type=LinePrimitive.LINE_STRIP, thickness=0.01, color=_color(_EDGE_RGB))
    line.pose.position.SetInParent()
    line.pose.orientation.w = 1.0
    line.points.extend(_point(point + s * direction) for s in (-half_length, half_length))
    ent.lines.append(line)
    text = TextPrimitive(
        billboard=True, font_size=14.0, scale_invariant=True, color=_color(_EDGE_RGB), text="corner edge"
    )
    _set_position(text.pose, point + half_length * direction)
    text.pose.orientation.w = 1.0
    ent.texts.append(text)
    return ent


class PlaneScene:
    """Turns each estimate into a ``SceneUpdate``: its planes and edge, and deletions of what it no longer has
    (and of the planes of the scanner's previous scan).

    One instance per output (live server or file): it remembers which entities it drew.
    """

    def __init__(self) -> None:
        self._drawn: dict[tuple[str, int], set[str]] = {}

    def update(self, msg: codec.Reconstruction, t_ns: int | None = None) -> SceneUpdate:
        t = int(msg.stamp_ns if t_ns is None else t_ns)
        entities = [e for e in (*(_plane_entity(msg, p, t) for p in msg.planes), _edge_entity(msg, t)) if e is not None]
        key = (msg.scanner_id, msg.scan_id)
        ids = {e.id for e in entities}
        gone = set(self._drawn.get(key, set()) - ids)
        for other in [k for k in self._drawn if k[0] == msg.scanner_id and k != key]:
            gone |= self._drawn.pop(other)  # a new scan of this scanner replaces the last one's planes
        self._drawn[key] = ids
        out = SceneUpdate(entities=entities)
        for entity_id in sorted(gone):
            d = SceneEntityDeletion(type=SceneEntityDeletion.MATCHING_ID, id=entity_id)
            d.timestamp.FromNanoseconds(t)
            out.deletions.append(d)
        return out


# --- log -----------------------------------------------------------------------------------
_LOG_LEVELS = {
    "trace": "DEBUG",
    "debug": "DEBUG",
    "info": "INFO",
    "warn": "WARNING",
    "warning": "WARNING",
    "error": "ERROR",
    "critical": "FATAL",
    "fatal": "FATAL",
}


def log_message(level: str, text: str, t_ns: int, name: str = "lelsonar") -> Log:
    """A ``foxglove.Log``; levels as the services name them (info, warn, error, ...)."""
    msg = Log(level=Log.Level.Value(_LOG_LEVELS.get(level.lower(), "INFO")), message=text, name=name, file="")
    msg.timestamp.FromNanoseconds(int(t_ns))
    return msg


# --- a simulated world as truth, and where each scan was ------------------------------------
TOPIC_WORLD = "/lelsonar/world"
_WALL_RGB = (150, 150, 150)
_BOX_RGB = (190, 160, 110)
_PATH_RGB = (120, 200, 255)
_POSE_RGB = (255, 200, 0)
_WALL_THICKNESS = 0.02  # m


def _entity(frame_id: str, entity_id: str, t_ns: int) -> SceneEntity:
    ent = SceneEntity(frame_id=frame_id, id=entity_id)
    ent.timestamp.FromNanoseconds(int(t_ns))
    ent.lifetime.SetInParent()
    return ent


def _cube(ent: SceneEntity, center, size, yaw: float, rgb, alpha: float = 1.0) -> None:
    cube = ent.cubes.add()
    cube.pose.position.x, cube.pose.position.y, cube.pose.position.z = (float(v) for v in center)
    cube.pose.orientation.z, cube.pose.orientation.w = math.sin(yaw / 2), math.cos(yaw / 2)
    cube.size.x, cube.size.y, cube.size.z = (float(v) for v in size)
    cube.color.CopyFrom(_color(rgb, alpha))


def world_scene(world: dict, t_ns: int) -> SceneUpdate:
    """A simulated world (the recording's ``truth_world`` metadata) in the ``map`` frame: walls, boxes, the path.

    Walls are thin cubes, boxes cubes, the robot's true path a line through its poses with an arrow per pose.
    """
    out = SceneUpdate()
    floor = float(world.get("floor") or 0.0)
    ent = _entity(MAP_FRAME, "world/truth", t_ns)
    for w in world.get("walls", []):
        (x0, y0), (x1, y1) = w["from"], w["to"]
        length = math.hypot(x1 - x0, y1 - y0)
        z = floor + float(w.get("bottom", 0.0)) + float(w["height"]) / 2
        _cube(
            ent,
            ((x0 + x1) / 2, (y0 + y1) / 2, z),
            (length, _WALL_THICKNESS, w["height"]),
            math.atan2(y1 - y0, x1 - x0),
            _WALL_RGB,
            0.6,
        )
    for b in world.get("boxes", []):
        _cube(ent, (b["center"][0], b["center"][1], floor + b["size"][2] / 2), b["size"], float(b["yaw"]), _BOX_RGB)
    poses = world.get("poses", [])
    if poses:
        line = ent.lines.add(type=LinePrimitive.LINE_STRIP, thickness=0.02, scale_invariant=False)
        line.pose.position.SetInParent()
        line.pose.orientation.w = 1.0
        line.color.CopyFrom(_color(_PATH_RGB))
        for p in poses:
            line.points.append(Point3(x=float(p["x"]), y=float(p["y"]), z=floor + 0.01))
            arrow = ent.arrows.add(shaft_length=0.2, shaft_diameter=0.02, head_length=0.08, head_diameter=0.06)
            arrow.pose.position.x, arrow.pose.position.y, arrow.pose.position.z = (
                float(p["x"]),
                float(p["y"]),
                floor + 0.01,
            )
            arrow.pose.orientation.z, arrow.pose.orientation.w = math.sin(p["heading"] / 2), math.cos(p["heading"] / 2)
            arrow.color.CopyFrom(_color(_PATH_RGB))
    out.entities.append(ent)
    return out


def pose_scene(start: codec.ScanStart, t_ns: int) -> SceneUpdate | None:
    """Where the scan was, as its pose says: an arrow along the γ = 0 beam in the pose's frame; None without one."""
    if not start.HasField("pose"):
        return None
    pose = codec.scan_pose(start)
    out = SceneUpdate()
    ent = _entity(pose.frame_id, f"{start.scanner_id}/{start.scan_id}/pose", t_ns)
    heading = beam_heading(pose.orientation)
    arrow = ent.arrows.add(shaft_length=0.25, shaft_diameter=0.03, head_length=0.1, head_diameter=0.08)
    arrow.pose.position.x, arrow.pose.position.y, arrow.pose.position.z = (float(v) for v in pose.position)
    arrow.pose.orientation.z, arrow.pose.orientation.w = math.sin(heading / 2), math.cos(heading / 2)
    arrow.color.CopyFrom(_color(_POSE_RGB))
    if pose.covariance is not None:
        sx, sy = (math.sqrt(max(pose.covariance[i, i], 0.0)) for i in (0, 1))
        sphere = ent.spheres.add()
        sphere.pose.position.x, sphere.pose.position.y, sphere.pose.position.z = (float(v) for v in pose.position)
        sphere.pose.orientation.w = 1.0
        sphere.size.x, sphere.size.y, sphere.size.z = max(4 * sx, 0.01), max(4 * sy, 0.01), 0.01  # ±2σ
        sphere.color.CopyFrom(_color(_POSE_RGB, 0.3))
    ent.metadata.append(KeyValuePair(key="frame_id", value=pose.frame_id))
    out.entities.append(ent)
    return out
