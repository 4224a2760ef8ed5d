"""The Foxglove scene of the map (``/lelsonar/map/scene``), drawn from the contract's ``Map`` message.

In the ``map`` frame:

* each wall, one entity: a box per observed piece, as thick as its offset's ± 2σ (at least 1 cm) and as
  tall as it was seen, in its verdict's colour, with a label naming it, its σ and its verdict;
* corners, edges and horizontal corners (where a wall meets the floor or the ceiling): a line along their
  direction and a sphere of ± 2σ at their point;
* the path: the corrected poses as a line with an arrow per pose and its ± 2σ ellipse, and the odometry's
  path before fusion as a grey line;
* the free space the caller gives (:func:`lelsonar.map.floorplan.free_space`): its outline, filled.

One :class:`MapScene` per output: each update replaces what the last one drew and deletes the walls that
are gone (merged or split), so the scene grows scan by scan as the map does.
"""

from __future__ import annotations

import math
from collections import OrderedDict

import numpy as np
import shapely
from foxglove_schemas_protobuf.KeyValuePair_pb2 import KeyValuePair
from foxglove_schemas_protobuf.LinePrimitive_pb2 import LinePrimitive
from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
from foxglove_schemas_protobuf.SceneEntityDeletion_pb2 import SceneEntityDeletion
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from foxglove_schemas_protobuf.TextPrimitive_pb2 import TextPrimitive
from foxglove_schemas_protobuf.TriangleListPrimitive_pb2 import TriangleListPrimitive

from lelsonar.draw.estimates import SIGMA_BAND
from lelsonar.draw.palette import (
    CONCAVE_CORNER_COLOR,
    CONVEX_EDGE_COLOR,
    HORIZONTAL_CORNER_COLOR,
    QUALITY_NAME,
    quality_color,
)
from lelsonar.draw.primitives import MAP_FRAME, cube, entity, point3, rgba, set_position, vec3
from lelsonar.v1 import map_pb2

TOPIC_MAP_SCENE = "/lelsonar/map/scene"

_PATH_RGB = (255, 200, 0)
_ODOMETRY_RGB = (150, 150, 150)
_FREE_RGB = (90, 170, 255)
_MIN_THICKNESS = 0.01  # m: a wall drawn thinner would vanish
_FLAT_HEIGHT = 0.05  # m: the height of a wall seen at one height only


def wall_entity_id(scanner_id: str, wall_id: int) -> str:
    return f"{scanner_id}/map/wall/{wall_id}"


def wall_pieces(w: map_pb2.MapWall) -> list[tuple[np.ndarray, np.ndarray]]:
    """The observed pieces of a wall as ``(a, b)`` floor points; its extent's two ends when it has none."""
    pts = [vec3(p) for p in w.pieces]
    if len(pts) >= 2:
        return [(pts[i], pts[i + 1]) for i in range(0, len(pts) - 1, 2)]
    ext = [vec3(p) for p in w.extent]
    return [(ext[0], ext[1])] if len(ext) >= 2 else []


def wall_heights(w: map_pb2.MapWall) -> tuple[float, float]:
    """The lowest and highest height the wall was seen at, m."""
    z = [p.z for p in w.extent] or [p.z for p in w.pieces] or [0.0]
    return float(min(z)), float(max(z))


def wall_thickness(w: map_pb2.MapWall) -> float:
    """The drawn thickness of a wall: its offset's ± SIGMA_BAND σ band, at least 1 cm, m."""
    s = w.offset_stderr if math.isfinite(w.offset_stderr) else 0.0
    return max(_MIN_THICKNESS, 2.0 * SIGMA_BAND * s)


def _wall_entity(msg: map_pb2.Map, w: map_pb2.MapWall, t_ns: int) -> SceneEntity | None:
    pieces = wall_pieces(w)
    if not pieces:
        return None
    rgb = quality_color(w.quality)
    quality = QUALITY_NAME.get(w.quality, "unknown")
    lo, hi = wall_heights(w)
    height = hi - lo if hi - lo > 1e-6 else _FLAT_HEIGHT
    ent = entity(MAP_FRAME, wall_entity_id(msg.scanner_id, w.id), t_ns)
    for k, v in (
        ("kind", "wall"),
        ("id", str(w.id)),
        ("quality", quality),
        ("quality_reasons", "; ".join(w.quality_reasons)),
        ("offset_m", f"{w.offset:.4f}"),
        ("offset_sigma_mm", f"{w.offset_stderr * 1e3:.2f}"),
        ("normal_sigma_deg", f"{math.degrees(w.normal_stderr):.2f}"),
        ("scans", ",".join(map(str, w.scan_ids))),
    ):
        ent.metadata.append(KeyValuePair(key=k, value=v))
    for a, b in pieces:
        length = float(np.hypot(*(b - a)[:2]))
        yaw = math.atan2(b[1] - a[1], b[0] - a[0])
        mid = 0.5 * (a + b)
        cube(
            ent,
            (mid[0], mid[1], lo + 0.5 * height),
            (max(length, _MIN_THICKNESS), wall_thickness(w), height),
            yaw,
            rgb,
            0.8,
        )
    a, b = max(pieces, key=lambda ab: float(np.hypot(*(ab[1] - ab[0])[:2])))
    text = TextPrimitive(
        billboard=True,
        font_size=13.0,
        scale_invariant=True,
        color=rgba(rgb),
        text=f"wall {w.id}: ± {w.offset_stderr * 1e3:.1f} mm, ± {math.degrees(w.normal_stderr):.2f}°, {quality}",
    )
    mid = 0.5 * (a + b)
    set_position(text.pose, (mid[0], mid[1], hi + 0.05))
    text.pose.orientation.w = 1.0
    ent.texts.append(text)
    return ent


def _features_entity(msg: map_pb2.Map, t_ns: int) -> SceneEntity:
    ent = entity(MAP_FRAME, f"{msg.scanner_id}/map/features", t_ns)
    for kind, rgb, items in (
        ("corner", CONCAVE_CORNER_COLOR, msg.corners),
        ("edge", CONVEX_EDGE_COLOR, msg.edges),
        ("horizontal corner", HORIZONTAL_CORNER_COLOR, msg.horizontal_corners),
    ):
        for f in items:
            p, d = vec3(f.point), vec3(f.direction)
            if not np.isfinite(p).all():
                continue
            if np.isfinite(d).all() and np.linalg.norm(d) > 0:
                d = 0.25 * d / np.linalg.norm(d)
                line = ent.lines.add(type=LinePrimitive.LINE_STRIP, thickness=0.015, scale_invariant=False)
                line.pose.position.SetInParent()
                line.pose.orientation.w = 1.0
                line.color.CopyFrom(rgba(rgb))
                line.points.extend([point3(p - d), point3(p + d)])
            s = ent.spheres.add()
            set_position(s.pose, p)
            s.pose.orientation.w = 1.0
            size = max(4.0 * f.point_stderr, 0.03)  # ± 2σ
            s.size.x = s.size.y = s.size.z = size
            s.color.CopyFrom(rgba(rgb, 0.6))
            ent.metadata.append(
                KeyValuePair(key=f"{kind} {f.kind}", value=f"{p[0]:.3f}, {p[1]:.3f} ± {f.point_stderr * 1e3:.1f} mm")
            )
    return ent


def _path_entity(msg: map_pb2.Map, t_ns: int) -> SceneEntity:
    ent = entity(MAP_FRAME, f"{msg.scanner_id}/map/path", t_ns)
    corrected = ent.lines.add(type=LinePrimitive.LINE_STRIP, thickness=0.02, scale_invariant=False)
    odometry = ent.lines.add(type=LinePrimitive.LINE_STRIP, thickness=0.01, scale_invariant=False)
    for line, rgb in ((corrected, _PATH_RGB), (odometry, _ODOMETRY_RGB)):
        line.pose.position.SetInParent()
        line.pose.orientation.w = 1.0
        line.color.CopyFrom(rgba(rgb))
    for p in msg.poses:
        x, y = p.position.x, p.position.y
        corrected.points.append(point3((x, y, 0.01)))
        odometry.points.append(point3((p.odometry.x, p.odometry.y, 0.005)))
        arrow = ent.arrows.add(shaft_length=0.15, shaft_diameter=0.02, head_length=0.06, head_diameter=0.05)
        set_position(arrow.pose, (x, y, 0.01))
        arrow.pose.orientation.z, arrow.pose.orientation.w = math.sin(p.heading / 2), math.cos(p.heading / 2)
        arrow.color.CopyFrom(rgba(_PATH_RGB))
        if len(p.covariance) == 9:
            sx, sy = (math.sqrt(max(p.covariance[i], 0.0)) for i in (0, 4))
            s = ent.spheres.add()
            set_position(s.pose, (x, y, 0.01))
            s.pose.orientation.w = 1.0
            s.size.x, s.size.y, s.size.z = max(4 * sx, 0.01), max(4 * sy, 0.01), 0.005  # ± 2σ
            s.color.CopyFrom(rgba(_PATH_RGB, 0.3))
    return ent


def _free_space_entity(scanner_id: str, free_space, t_ns: int) -> SceneEntity | None:
    """The free space's outlines and its fill (a constrained Delaunay triangulation of the polygon)."""
    if free_space is None or free_space.is_empty:
        return None
    ent = entity(MAP_FRAME, f"{scanner_id}/map/free_space", t_ns)
    tri = TriangleListPrimitive(color=rgba(_FREE_RGB, 0.2))
    tri.pose.position.SetInParent()
    tri.pose.orientation.w = 1.0
    for t in shapely.get_parts(shapely.constrained_delaunay_triangles(free_space)):
        tri.points.extend(point3((x, y, 0.0)) for x, y in list(t.exterior.coords)[:3])
    ent.triangles.append(tri)
    for polygon in shapely.get_parts(free_space):
        for ring in (polygon.exterior, *polygon.interiors):
            line = ent.lines.add(type=LinePrimitive.LINE_LOOP, thickness=0.008, scale_invariant=False)
            line.pose.position.SetInParent()
            line.pose.orientation.w = 1.0
            line.color.CopyFrom(rgba(_FREE_RGB, 0.8))
            line.points.extend(point3((x, y, 0.0)) for x, y in list(ring.coords)[:-1])
    return ent


class MapScene:
    """Turns each ``Map`` into a ``SceneUpdate`` (see the module docstring); one instance per output."""

    #: Scanners whose drawn walls are remembered (the oldest forgotten first): the ids come off the wire.
    MAX_SCANNERS = 64

    def __init__(self) -> None:
        self._walls: OrderedDict[str, set[str]] = OrderedDict()

    def update(self, msg: map_pb2.Map, t_ns: int | None = None, free_space=None) -> SceneUpdate:
        """The scene of ``msg``; ``free_space`` a shapely (multi)polygon in the map frame, or None."""
        t = int(msg.stamp_ns if t_ns is None else t_ns)
        walls = [e for e in (_wall_entity(msg, w, t) for w in msg.walls) if e is not None]
        entities = [*walls, _features_entity(msg, t), _path_entity(msg, t)]
        space = _free_space_entity(msg.scanner_id, free_space, t)
        if space is not None:
            entities.append(space)
        ids = {e.id for e in walls}
        gone = self._walls.get(msg.scanner_id, set()) - ids
        self._walls[msg.scanner_id] = ids
        self._walls.move_to_end(msg.scanner_id)
        while len(self._walls) > self.MAX_SCANNERS:
            self._walls.popitem(last=False)
        out = SceneUpdate(entities=entities)
        for entity_id in sorted(gone):
            d = SceneEntityDeletion(type=SceneEntityDeletion.MATCHING_ID, id=entity_id)
            d.timestamp.FromNanoseconds(t)
            out.deletions.append(d)
        return out
