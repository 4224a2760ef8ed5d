"""What viewers draw: Foxglove messages built from the contract messages.

This module draws a scan (frames, points, scalars, log); :mod:`lelsonar.draw.estimates` the estimates,
:mod:`lelsonar.draw.world` a simulated world and the scan poses, :mod:`lelsonar.draw.map_scene` the map,
from the pieces of :mod:`lelsonar.draw.primitives`.  The names used across the house are importable here.

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
``/lelsonar/planes``        ``foxglove.SceneUpdate``       planes, normals, labels, the edge; every surface,
                                                           corner and edge of the sweep (:mod:`.estimates`)
``/lelsonar/truth``         ``foxglove.SceneUpdate``       the true planes of a simulated scene
``/lelsonar/world``         ``foxglove.SceneUpdate``       a simulated world, the robot's true path (:mod:`.world`)
``/lelsonar/map/scene``     ``foxglove.SceneUpdate``       the map: walls, corners, path (:mod:`.map_scene`)
==========================  =============================  =====================================
"""

from __future__ import annotations

import functools
import json
import math

import numpy as np
from foxglove_schemas_protobuf.ArrowPrimitive_pb2 import ArrowPrimitive
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.Log_pb2 import Log
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from foxglove_schemas_protobuf.SpherePrimitive_pb2 import SpherePrimitive
from foxglove_schemas_protobuf.TextPrimitive_pb2 import TextPrimitive

from lelsonar import codec, poses
from lelsonar.draw.estimates import (
    TOPIC_PLANES,
    TOPIC_TRUTH,
    PlaneScene,
    edge_entity_id,
    plane_entity_id,
    truth_scene,
)
from lelsonar.draw.primitives import (
    ARRAY_FRAME,
    BASE_FRAME,
    MAP_FRAME,
    WORLD_FRAME,
    file_descriptor_set,
    frame_transform,
    quat_x_to,
    rgba,
    set_position,
)
from lelsonar.draw.world import TOPIC_WORLD, pose_scene, world_scene
from lelsonar.energy_model import EnergyModel
from lelsonar.errors import ConfigError
from lelsonar.geometry import beam_heading, matrix_from_quaternion, quaternion_from_matrix, rotation_z

__all__ = [
    "ARRAY_FRAME",
    "BASE_FRAME",
    "MAP_FRAME",
    "TOPIC_PLANES",
    "TOPIC_TRUTH",
    "TOPIC_WORLD",
    "WORLD_FRAME",
    "FrameTransform",
    "FrameTransforms",
    "Log",
    "PlaneScene",
    "PointCloud",
    "SceneUpdate",
    "edge_entity_id",
    "file_descriptor_set",
    "frame_transform",
    "plane_entity_id",
    "pose_scene",
    "truth_scene",
    "world_scene",
]

TOPIC_TF = "/tf"
TOPIC_CAPSULE_TF = "/tf_capsules"
TOPIC_ARRAY = "/lelsonar/array"
TOPIC_POINTS = "/lelsonar/points"
TOPIC_SCAN_POINTS = "/lelsonar/scan_points"
TOPIC_STEP = "/lelsonar/step"
TOPIC_ENERGY = "/lelsonar/energy"
TOPIC_LOG = "/log"


def capsule_frame(capsule_id: int) -> str:
    """``capsule_A`` … (the paper names the capsules A, B, C, D)."""
    return f"capsule_{chr(ord('A') + capsule_id)}" if capsule_id < 26 else f"capsule_{capsule_id}"


def capsule_name(capsule_id: int) -> str:
    return capsule_frame(capsule_id).removeprefix("capsule_")


def array_transform(gamma: float, t_ns: int) -> FrameTransform:
    """world → array: the array turned by γ about x."""
    half = 0.5 * gamma
    return frame_transform(WORLD_FRAME, ARRAY_FRAME, t_ns, rotation=(math.sin(half), 0.0, 0.0, math.cos(half)))


def pose_transforms(start: codec.ScanStart, t_ns: int) -> list[FrameTransform]:
    """map → odom → base_link → world of a scan that carries a pose; none for one that does not.

    ``odom`` is the pose's frame (map → odom is the identity: the odometry's own start).
    ``base_link`` is the floor point below the array, heading along its γ = 0 beam; ``world``
    (the array frame at γ = 0, the frame the scan is drawn in) sits on it by the mount.
    """
    if not start.HasField("pose"):
        return []
    pose = poses.scan_pose(start)
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
        rot = quat_x_to(b) if np.linalg.norm(b) > 0 else (0.0, 0.0, 0.0, 1.0)
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
        s = SpherePrimitive(color=rgba((230, 230, 230)))
        set_position(s.pose, p)
        s.pose.orientation.w = 1.0
        s.size.x = s.size.y = s.size.z = 0.02
        ent.spheres.append(s)
        a = ArrowPrimitive(
            shaft_length=0.08, shaft_diameter=0.004, head_length=0.02, head_diameter=0.012, color=rgba((90, 160, 255))
        )
        set_position(a.pose, p)
        x, y, z, w = quat_x_to(b) if np.linalg.norm(b) > 0 else (0.0, 0.0, 0.0, 1.0)
        a.pose.orientation.x, a.pose.orientation.y, a.pose.orientation.z, a.pose.orientation.w = x, y, z, w
        ent.arrows.append(a)
        label = TextPrimitive(
            billboard=True,
            font_size=14.0,
            scale_invariant=True,
            text=capsule_name(c.capsule_id),
            color=rgba((255, 255, 255)),
        )
        set_position(label.pose, (p[0], p[1], p[2] - 0.03))
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
