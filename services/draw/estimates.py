"""The Foxglove scene of an estimate (``/lelsonar/planes``): every method's planes and the L's edge, every
surface the sweep saw with its verdict and σ, its corners and edges, and what stayed unexplained.

Drawn from the ``Reconstruction`` message alone, so a recording shows what a remote reviewer receives.
"""

from __future__ import annotations

import math

import numpy as np
from foxglove_schemas_protobuf.ArrowPrimitive_pb2 import ArrowPrimitive
from foxglove_schemas_protobuf.KeyValuePair_pb2 import KeyValuePair
from foxglove_schemas_protobuf.LinePrimitive_pb2 import LinePrimitive
from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
from foxglove_schemas_protobuf.SceneEntityDeletion_pb2 import SceneEntityDeletion
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from foxglove_schemas_protobuf.SpherePrimitive_pb2 import SpherePrimitive
from foxglove_schemas_protobuf.TextPrimitive_pb2 import TextPrimitive
from foxglove_schemas_protobuf.TriangleListPrimitive_pb2 import TriangleListPrimitive

from lelsonar import codec
from lelsonar.draw.palette import CONCAVE_CORNER_COLOR, CONVEX_EDGE_COLOR, QUALITY_NAME, method_color, quality_color
from lelsonar.draw.primitives import WORLD_FRAME, entity, point3, quat_x_to, rgba, set_position, vec3
from lelsonar.v1 import reconstruction_pb2

TOPIC_PLANES = "/lelsonar/planes"
TOPIC_TRUTH = "/lelsonar/truth"

_PATCH_ALPHA = 0.45
_SURFACE_ALPHA = 0.3
_NORMAL_LENGTH = 0.25  # m
_EDGE_RGB = (255, 255, 255)
_FEATURE_HALF_LENGTH = 0.25  # m
_UNEXPLAINED_RGB = (200, 200, 200)
#: The σ band drawn around a surface: its patch shifted by ± this many σ of its offset along its normal.
SIGMA_BAND = 2.0


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


def plane_entity_id(scanner_id: str, scan_id: int, method: str, label: str) -> str:
    return f"{scanner_id}/{scan_id}/plane/{method}/{label}"


def edge_entity_id(scanner_id: str, scan_id: int) -> str:
    return f"{scanner_id}/{scan_id}/edge"


def _plane_entity(msg: codec.Reconstruction, p: reconstruction_pb2.PlaneEstimate, t_ns: int) -> SceneEntity | None:
    patch = np.array([vec3(v) for v in p.patch])
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
    tri = TriangleListPrimitive(color=rgba(rgb, _PATCH_ALPHA))
    tri.pose.position.SetInParent()
    tri.pose.orientation.w = 1.0
    for i in range(1, len(patch) - 1):
        for j in (0, i, i + 1):
            tri.points.append(point3(patch[j]))
    ent.triangles.append(tri)
    # Its outline in the colour of its quality verdict.
    outline = LinePrimitive(type=LinePrimitive.LINE_LOOP, thickness=0.012, scale_invariant=False, color=rgba(qrgb))
    outline.pose.position.SetInParent()
    outline.pose.orientation.w = 1.0
    outline.points.extend(point3(v) for v in patch)
    ent.lines.append(outline)
    centre = patch.mean(axis=0)
    n = vec3(p.normal)
    if np.linalg.norm(n) > 0:
        a = ArrowPrimitive(
            shaft_length=0.8 * _NORMAL_LENGTH,
            shaft_diameter=0.01,
            head_length=0.2 * _NORMAL_LENGTH,
            head_diameter=0.03,
            color=rgba(rgb),
        )
        set_position(a.pose, centre)
        x, y, z, w = quat_x_to(n)
        a.pose.orientation.x, a.pose.orientation.y, a.pose.orientation.z, a.pose.orientation.w = x, y, z, w
        ent.arrows.append(a)
    text = TextPrimitive(
        billboard=True,
        font_size=14.0,
        scale_invariant=True,
        color=rgba(qrgb),
        text=f"{p.method} {p.label}: h = {p.offset:.3f} m, σ = {p.sigma * 1e3:.1f} mm, {quality}",
    )
    set_position(text.pose, centre + (_NORMAL_LENGTH * n if np.linalg.norm(n) > 0 else 0.0))
    text.pose.orientation.w = 1.0
    ent.texts.append(text)
    return ent


def _edge_entity(msg: codec.Reconstruction, t_ns: int, half_length: float = 0.5) -> SceneEntity | None:
    if not msg.HasField("corner_edge"):
        return None
    point, direction = vec3(msg.corner_edge.point), vec3(msg.corner_edge.direction)
    if not (np.all(np.isfinite(point)) and np.linalg.norm(direction) > 0):
        return None
    ent = SceneEntity(frame_id=WORLD_FRAME, id=edge_entity_id(msg.scanner_id, msg.scan_id))
    ent.timestamp.FromNanoseconds(int(t_ns))
    ent.lifetime.SetInParent()
    line = LinePrimitive(type=LinePrimitive.LINE_STRIP, thickness=0.01, color=rgba(_EDGE_RGB))
    line.pose.position.SetInParent()
    line.pose.orientation.w = 1.0
    line.points.extend(point3(point + s * direction) for s in (-half_length, half_length))
    ent.lines.append(line)
    text = TextPrimitive(
        billboard=True, font_size=14.0, scale_invariant=True, color=rgba(_EDGE_RGB), text="corner edge"
    )
    set_position(text.pose, point + half_length * direction)
    text.pose.orientation.w = 1.0
    ent.texts.append(text)
    return ent


def surface_entity_id(scanner_id: str, scan_id: int, label: str) -> str:
    return f"{scanner_id}/{scan_id}/surface/{label}"


def feature_entity_id(scanner_id: str, scan_id: int, label: str) -> str:
    return f"{scanner_id}/{scan_id}/feature/{label}"


def unexplained_entity_id(scanner_id: str, scan_id: int) -> str:
    return f"{scanner_id}/{scan_id}/unexplained"


def _loop(points, rgb, alpha: float = 1.0, thickness: float = 0.008) -> LinePrimitive:
    line = LinePrimitive(
        type=LinePrimitive.LINE_LOOP, thickness=thickness, scale_invariant=False, color=rgba(rgb, alpha)
    )
    line.pose.position.SetInParent()
    line.pose.orientation.w = 1.0
    line.points.extend(point3(v) for v in points)
    return line


def _label(text: str, at, rgb) -> TextPrimitive:
    out = TextPrimitive(billboard=True, font_size=13.0, scale_invariant=True, color=rgba(rgb), text=text)
    set_position(out.pose, at)
    out.pose.orientation.w = 1.0
    return out


def surface_offset_sigma(s: reconstruction_pb2.SurfaceEstimate) -> float:
    """σ of a surface's offset, m: its covariance's (offset, offset) term, else the plane's standard error."""
    if len(s.covariance) == 9 and math.isfinite(s.covariance[8]) and s.covariance[8] >= 0:
        return math.sqrt(s.covariance[8])
    return float(s.plane.offset_stderr)


def surface_bearing_sigma(s: reconstruction_pb2.SurfaceEstimate) -> float:
    """σ of a surface's bearing in the fan, rad (NaN when it carries no covariance)."""
    if len(s.covariance) == 9 and math.isfinite(s.covariance[0]) and s.covariance[0] >= 0:
        return math.sqrt(s.covariance[0])
    return math.nan


def _surface_entity(msg: codec.Reconstruction, s: reconstruction_pb2.SurfaceEstimate, t_ns: int) -> SceneEntity | None:
    """A surface's observed patch filled in its verdict's colour, its σ band (the patch at ± SIGMA_BAND σ of
    its offset along its normal, as outlines), its normal and a label with its σ and verdict."""
    p = s.plane
    patch = np.array([vec3(v) for v in p.patch])
    n = vec3(p.normal)
    if len(patch) < 2 or not np.all(np.isfinite(patch)) or not np.isfinite(n).all() or np.linalg.norm(n) == 0:
        return None
    qrgb = quality_color(p.quality)
    quality = QUALITY_NAME.get(p.quality, "unknown")
    sigma = surface_offset_sigma(s)
    bearing_sigma = surface_bearing_sigma(s)
    ent = entity(WORLD_FRAME, surface_entity_id(msg.scanner_id, msg.scan_id, s.label), t_ns)
    for k, v in (
        ("kind", "surface"),
        ("label", s.label),
        ("quality", quality),
        ("quality_reasons", "; ".join(p.quality_reasons)),
        ("offset_m", f"{p.offset:.4f}"),
        ("offset_sigma_mm", f"{sigma * 1e3:.2f}"),
        ("bearing_deg", f"{math.degrees(s.bearing):.2f}"),
        ("bearing_sigma_deg", f"{math.degrees(bearing_sigma):.2f}"),
        ("bearing_source", s.bearing_source),
        ("echoes", str(s.echo_count)),
    ):
        ent.metadata.append(KeyValuePair(key=k, value=v))
    if len(patch) >= 3:
        tri = TriangleListPrimitive(color=rgba(qrgb, _SURFACE_ALPHA))
        tri.pose.position.SetInParent()
        tri.pose.orientation.w = 1.0
        for i in range(1, len(patch) - 1):
            tri.points.extend(point3(patch[j]) for j in (0, i, i + 1))
        ent.triangles.append(tri)
    ent.lines.append(_loop(patch, qrgb, thickness=0.01))
    if math.isfinite(sigma) and sigma > 0:
        for sign in (-1.0, 1.0):
            ent.lines.append(_loop(patch + sign * SIGMA_BAND * sigma * n, qrgb, alpha=0.6, thickness=0.004))
    centre = patch.mean(axis=0)
    a = ArrowPrimitive(
        shaft_length=0.8 * _NORMAL_LENGTH,
        shaft_diameter=0.008,
        head_length=0.2 * _NORMAL_LENGTH,
        head_diameter=0.025,
        color=rgba(qrgb),
    )
    set_position(a.pose, centre)
    a.pose.orientation.x, a.pose.orientation.y, a.pose.orientation.z, a.pose.orientation.w = quat_x_to(n)
    ent.arrows.append(a)
    bearing = "" if not math.isfinite(bearing_sigma) else f", bearing σ {math.degrees(bearing_sigma):.1f}°"
    ent.texts.append(
        _label(
            f"{s.label}: h = {p.offset:.3f} m ± {sigma * 1e3:.1f} mm{bearing}, {quality}",
            centre + 0.6 * _NORMAL_LENGTH * n,
            qrgb,
        )
    )
    return ent


def _feature_entity(
    msg: codec.Reconstruction, f: reconstruction_pb2.FeatureEstimate, kind: str, t_ns: int
) -> SceneEntity | None:
    """A corner or an edge: its line, a sphere at its point sized ± 2σ along each axis, and its label."""
    point, direction = vec3(f.line.point), vec3(f.line.direction)
    if not np.all(np.isfinite(point)):
        return None
    rgb = CONCAVE_CORNER_COLOR if kind == "corner" else CONVEX_EDGE_COLOR
    ent = entity(WORLD_FRAME, feature_entity_id(msg.scanner_id, msg.scan_id, f.label), t_ns)
    for k, v in (
        ("kind", kind),
        ("label", f.label),
        ("surfaces", ",".join(f.surfaces)),
        ("reasons", "; ".join(f.reasons)),
        ("point_stderr_mm", f"{f.line.point_stderr * 1e3:.2f}"),
        ("echoes", str(f.echo_count)),
    ):
        ent.metadata.append(KeyValuePair(key=k, value=v))
    if np.all(np.isfinite(direction)) and np.linalg.norm(direction) > 0:
        d = direction / np.linalg.norm(direction)
        line = LinePrimitive(type=LinePrimitive.LINE_STRIP, thickness=0.01, color=rgba(rgb))
        line.pose.position.SetInParent()
        line.pose.orientation.w = 1.0
        line.points.extend(point3(point + t * d) for t in (-_FEATURE_HALF_LENGTH, _FEATURE_HALF_LENGTH))
        ent.lines.append(line)
    if len(f.covariance) == 9:
        sd = np.sqrt(np.clip(np.diag(np.asarray(f.covariance, dtype=float).reshape(3, 3)), 0.0, None))
    else:
        sd = np.full(3, max(float(f.line.point_stderr), 0.0))
    sphere = SpherePrimitive(color=rgba(rgb, 0.5))
    set_position(sphere.pose, point)
    sphere.pose.orientation.w = 1.0
    sphere.size.x, sphere.size.y, sphere.size.z = (max(4.0 * float(v), 0.01) for v in sd)  # ± 2σ
    ent.spheres.append(sphere)
    ent.texts.append(_label(f"{kind} {f.label} ± {f.line.point_stderr * 1e3:.1f} mm", point, rgb))
    return ent


def _unexplained_entity(msg: codec.Reconstruction, t_ns: int) -> SceneEntity | None:
    """What no surface, corner or edge explains: a text at the array, with the share of the sweep's echoes."""
    total = sum(u.count for u in msg.unexplained)
    if total == 0:
        return None
    ent = entity(WORLD_FRAME, unexplained_entity_id(msg.scanner_id, msg.scan_id), t_ns)
    share = f" of {msg.surface_echo_count} echoes" if msg.surface_echo_count else ""
    causes = ", ".join(f"{u.count} {u.cause}" for u in msg.unexplained)
    for u in msg.unexplained:
        ent.metadata.append(KeyValuePair(key=u.cause, value=str(u.count)))
    ent.texts.append(_label(f"unexplained: {total}{share} ({causes})", (0.0, 0.0, -0.1), _UNEXPLAINED_RGB))
    return ent


def estimate_entities(msg: codec.Reconstruction, t_ns: int) -> list[SceneEntity]:
    """Every entity of one estimate: planes, the L's edge, surfaces, corners, edges, unexplained echoes."""
    drawn = (
        *(_plane_entity(msg, p, t_ns) for p in msg.planes),
        _edge_entity(msg, t_ns),
        *(_surface_entity(msg, s, t_ns) for s in msg.surfaces),
        *(_feature_entity(msg, f, "corner", t_ns) for f in msg.corners),
        *(_feature_entity(msg, f, "edge", t_ns) for f in msg.edges),
        _unexplained_entity(msg, t_ns),
    )
    return [e for e in drawn if e is not None]


class PlaneScene:
    """Turns each estimate into a ``SceneUpdate`` (:func:`estimate_entities`), and deletions of what it no
    longer has (and of what the scanner's previous scan drew).

    One instance per output (live server or file): it remembers which entities it drew.
    """

    def __init__(self) -> None:
        self._drawn: dict[tuple[str, int], set[str]] = {}

    def update(self, msg: codec.Reconstruction, t_ns: int | None = None) -> SceneUpdate:
        t = int(msg.stamp_ns if t_ns is None else t_ns)
        entities = estimate_entities(msg, t)
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
