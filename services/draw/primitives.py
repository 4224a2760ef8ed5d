"""The small pieces every Foxglove scene is built of: frames, colours, points, poses, entities.

Every builder sets every sub-message (an unset one breaks ``rerun mcap convert``).
"""

from __future__ import annotations

import math

import numpy as np
from foxglove_schemas_protobuf.Color_pb2 import Color
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.Point3_pb2 import Point3
from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
from google.protobuf import descriptor_pb2
from google.protobuf.message import Message

WORLD_FRAME = "world"
ARRAY_FRAME = "array"
MAP_FRAME = "map"
BASE_FRAME = "base_link"


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


def rgba(rgb: tuple[int, int, int], alpha: float = 1.0) -> Color:
    return Color(r=rgb[0] / 255.0, g=rgb[1] / 255.0, b=rgb[2] / 255.0, a=alpha)


def point3(p) -> Point3:
    return Point3(x=float(p[0]), y=float(p[1]), z=float(p[2]))


def set_position(pose, p) -> None:
    pose.position.x, pose.position.y, pose.position.z = float(p[0]), float(p[1]), float(p[2])


def quat_x_to(v: np.ndarray) -> tuple[float, float, float, float]:
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


def entity(frame_id: str, entity_id: str, t_ns: int) -> SceneEntity:
    """A ``SceneEntity`` stamped at ``t_ns`` that lives until replaced or deleted."""
    ent = SceneEntity(frame_id=frame_id, id=entity_id)
    ent.timestamp.FromNanoseconds(int(t_ns))
    ent.lifetime.SetInParent()
    return ent


def cube(ent: SceneEntity, center, size, yaw: float, rgb, alpha: float = 1.0) -> None:
    """Add a box to ``ent``: centred at ``center``, ``size`` (x along its length), turned by ``yaw`` about z."""
    c = ent.cubes.add()
    c.pose.position.x, c.pose.position.y, c.pose.position.z = (float(v) for v in center)
    c.pose.orientation.z, c.pose.orientation.w = math.sin(yaw / 2), math.cos(yaw / 2)
    c.size.x, c.size.y, c.size.z = (float(v) for v in size)
    c.color.CopyFrom(rgba(rgb, alpha))


def vec3(v) -> np.ndarray:
    """A contract ``Vector3`` as an array."""
    return np.array([v.x, v.y, v.z], dtype=float)
