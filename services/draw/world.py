"""A simulated world as truth, and where each scan was: Foxglove scenes in the ``map`` frame."""

from __future__ import annotations

import math

from foxglove_schemas_protobuf.KeyValuePair_pb2 import KeyValuePair
from foxglove_schemas_protobuf.LinePrimitive_pb2 import LinePrimitive
from foxglove_schemas_protobuf.Point3_pb2 import Point3
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

from lelsonar import codec, poses
from lelsonar.draw.primitives import MAP_FRAME, cube, entity, rgba
from lelsonar.geometry import beam_heading

TOPIC_WORLD = "/lelsonar/world"
_WALL_RGB = (150, 150, 150)
_BOX_RGB = (190, 160, 110)
_PATH_RGB = (120, 200, 255)
_POSE_RGB = (255, 200, 0)
_WALL_THICKNESS = 0.02  # m


def world_scene(world: dict, t_ns: int) -> SceneUpdate:
    """A simulated world (the recording's ``truth_world`` metadata) in the ``map`` frame: walls, boxes, the path.

    Walls are thin cubes, boxes cubes, the robot's true path a line through its poses with an arrow per pose.
    """
    out = SceneUpdate()
    floor = float(world.get("floor") or 0.0)
    ent = entity(MAP_FRAME, "world/truth", t_ns)
    for w in world.get("walls", []):
        (x0, y0), (x1, y1) = w["from"], w["to"]
        length = math.hypot(x1 - x0, y1 - y0)
        z = floor + float(w.get("bottom", 0.0)) + float(w["height"]) / 2
        cube(
            ent,
            ((x0 + x1) / 2, (y0 + y1) / 2, z),
            (length, _WALL_THICKNESS, w["height"]),
            math.atan2(y1 - y0, x1 - x0),
            _WALL_RGB,
            0.6,
        )
    for b in world.get("boxes", []):
        cube(ent, (b["center"][0], b["center"][1], floor + b["size"][2] / 2), b["size"], float(b["yaw"]), _BOX_RGB)
    poses = world.get("poses", [])
    if poses:
        line = ent.lines.add(type=LinePrimitive.LINE_STRIP, thickness=0.02, scale_invariant=False)
        line.pose.position.SetInParent()
        line.pose.orientation.w = 1.0
        line.color.CopyFrom(rgba(_PATH_RGB))
        for p in poses:
            line.points.append(Point3(x=float(p["x"]), y=float(p["y"]), z=floor + 0.01))
            arrow = ent.arrows.add(shaft_length=0.2, shaft_diameter=0.02, head_length=0.08, head_diameter=0.06)
            arrow.pose.position.x, arrow.pose.position.y, arrow.pose.position.z = (
                float(p["x"]),
                float(p["y"]),
                floor + 0.01,
            )
            arrow.pose.orientation.z, arrow.pose.orientation.w = math.sin(p["heading"] / 2), math.cos(p["heading"] / 2)
            arrow.color.CopyFrom(rgba(_PATH_RGB))
    out.entities.append(ent)
    return out


def pose_scene(start: codec.ScanStart, t_ns: int) -> SceneUpdate | None:
    """Where the scan was, as its pose says: an arrow along the γ = 0 beam in the pose's frame; None without one."""
    if not start.HasField("pose"):
        return None
    pose = poses.scan_pose(start)
    out = SceneUpdate()
    ent = entity(pose.frame_id, f"{start.scanner_id}/{start.scan_id}/pose", t_ns)
    heading = beam_heading(pose.orientation)
    arrow = ent.arrows.add(shaft_length=0.25, shaft_diameter=0.03, head_length=0.1, head_diameter=0.08)
    arrow.pose.position.x, arrow.pose.position.y, arrow.pose.position.z = (float(v) for v in pose.position)
    arrow.pose.orientation.z, arrow.pose.orientation.w = math.sin(heading / 2), math.cos(heading / 2)
    arrow.color.CopyFrom(rgba(_POSE_RGB))
    if pose.covariance is not None:
        sx, sy = (math.sqrt(max(pose.covariance[i, i], 0.0)) for i in (0, 1))
        sphere = ent.spheres.add()
        sphere.pose.position.x, sphere.pose.position.y, sphere.pose.position.z = (float(v) for v in pose.position)
        sphere.pose.orientation.w = 1.0
        sphere.size.x, sphere.size.y, sphere.size.z = max(4 * sx, 0.01), max(4 * sy, 0.01), 0.01  # ±2σ
        sphere.color.CopyFrom(rgba(_POSE_RGB, 0.3))
    ent.metadata.append(KeyValuePair(key="frame_id", value=pose.frame_id))
    out.entities.append(ent)
    return out
