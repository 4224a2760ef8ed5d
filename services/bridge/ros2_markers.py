"""ROS 2 markers (``visualization_msgs/Marker``) of an estimate: its planes, the L's edge, and every surface,
corner and edge the sweep saw with its verdict and σ.  Drawn from the ``Reconstruction`` message alone.

Namespaces of ``/lelsonar/planes``: ``plane/<method>``, ``normal/<method>``, ``label/<method>``, ``truth``,
``edge`` (the L's), ``surface`` (patch, verdict colour), ``surface/sigma`` (the patch at ± 2σ of its offset,
outlines), ``surface/label``, ``corner``, ``convex_edge`` (a line and a sphere of ± 2σ each),
``feature/label``, ``unexplained`` (a text with the counts by cause).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from lelsonar import codec
from lelsonar.codec import QUALITY_NAME
from lelsonar.draw.estimates import SIGMA_BAND, surface_bearing_sigma, surface_offset_sigma
from lelsonar.draw.palette import CONCAVE_CORNER_COLOR, CONVEX_EDGE_COLOR, method_color, quality_color, unit_rgb

# visualization_msgs/Marker types and actions
ARROW, CUBE, SPHERE, LINE_STRIP, LINE_LIST, TEXT_VIEW_FACING, TRIANGLE_LIST, DELETEALL = 0, 1, 2, 4, 5, 9, 11, 3

_TRUTH_RGB = (0.6, 0.6, 0.6)
_EDGE_RGB = (1.0, 0.1, 0.1)
_CORNER_RGB = unit_rgb(CONCAVE_CORNER_COLOR)
_CONVEX_RGB = unit_rgb(CONVEX_EDGE_COLOR)
_TEXT_RGB = (0.85, 0.85, 0.85)


def method_rgb(method: str) -> tuple[float, float, float]:
    r, g, b = method_color(method)
    return r / 255, g / 255, b / 255


def verdict_rgb(quality: str | int) -> tuple[float, float, float]:
    r, g, b = quality_color(quality)
    return r / 255, g / 255, b / 255


def _vec(v) -> np.ndarray:
    return np.array([v.x, v.y, v.z], dtype=float)


def estimate_markers(b, message: codec.Reconstruction, t: int, frame: str, truth: Sequence | None = None) -> list:
    """The MarkerArray of one estimate: a DELETEALL, then every method's planes (patch, normal, label), the
    true planes where known, the L's edge, and every surface, corner and edge of the sweep
    (:func:`surface_markers`).  ``b`` is the distro's :class:`~lelsonar.bridge.ros2.Builder`."""
    markers = [b.marker(t, frame, "", 0, 0, action=DELETEALL)]
    for i, plane in enumerate(message.planes):
        rgb = method_rgb(plane.method)
        corners = [(c.x, c.y, c.z) for c in plane.patch]
        if len(corners) >= 3:
            tri = [p for k in range(1, len(corners) - 1) for p in (corners[0], corners[k], corners[k + 1])]
            markers.append(
                b.marker(t, frame, f"plane/{plane.method}", i, TRIANGLE_LIST, points=tri, rgb=rgb, alpha=0.5)
            )
            centre = np.mean(np.asarray(corners), axis=0)
            n = np.array([plane.normal.x, plane.normal.y, plane.normal.z])
            markers.append(
                b.marker(
                    t,
                    frame,
                    f"normal/{plane.method}",
                    i,
                    ARROW,
                    points=[centre, centre + 0.2 * n],
                    rgb=rgb,
                    scale=(0.01, 0.02, 0.03),
                )
            )
            markers.append(
                b.marker(
                    t,
                    frame,
                    f"label/{plane.method}",
                    i,
                    TEXT_VIEW_FACING,
                    rgb=rgb,
                    scale=(0, 0, 0.05),
                    position=centre,
                    text=f"{plane.method} {plane.label}: h = {plane.offset:.3f} m, "
                    f"{QUALITY_NAME.get(plane.quality, 'unknown')}",
                )
            )
    for i, tp in enumerate(truth or ()):
        c = np.asarray(tp.corners, dtype=float)
        if len(c) >= 3:
            tri = [p for k in range(1, len(c) - 1) for p in (c[0], c[k], c[k + 1])]
            markers.append(b.marker(t, frame, "truth", i, TRIANGLE_LIST, points=tri, rgb=_TRUTH_RGB, alpha=0.3))
    if message.HasField("corner_edge"):
        e = message.corner_edge
        p = np.array([e.point.x, e.point.y, e.point.z])
        d = np.array([e.direction.x, e.direction.y, e.direction.z])
        markers.append(
            b.marker(
                t, frame, "edge", 0, LINE_LIST, points=[p - 0.5 * d, p + 0.5 * d], rgb=_EDGE_RGB, scale=(0.01, 0, 0)
            )
        )
    markers += surface_markers(b, message, t, frame)
    return markers


def surface_markers(b, message: codec.Reconstruction, t: int, frame: str) -> list:
    """Every surface (patch in its verdict's colour, its ± 2σ band as outlines, a label with σ and verdict),
    corner and edge (a line, a sphere of ± 2σ at its point, a label) and the unexplained echoes (a text)."""
    out: list = []
    for i, s in enumerate(message.surfaces):
        p = s.plane
        patch = np.array([_vec(v) for v in p.patch])
        n = _vec(p.normal)
        if len(patch) < 2 or not (np.isfinite(patch).all() and np.isfinite(n).all()):
            continue
        rgb = verdict_rgb(p.quality)
        quality = QUALITY_NAME.get(p.quality, "unknown")
        if len(patch) >= 3:
            tri = [q for k in range(1, len(patch) - 1) for q in (patch[0], patch[k], patch[k + 1])]
            out.append(b.marker(t, frame, "surface", i, TRIANGLE_LIST, points=tri, rgb=rgb, alpha=0.35))
        sigma = surface_offset_sigma(s)
        if math.isfinite(sigma) and sigma > 0:
            band = []
            for sign in (-1.0, 1.0):
                ring = patch + sign * SIGMA_BAND * sigma * n
                band += [q for k in range(len(ring)) for q in (ring[k], ring[(k + 1) % len(ring)])]
            out.append(b.marker(t, frame, "surface/sigma", i, LINE_LIST, points=band, rgb=rgb, scale=(0.004, 0, 0)))
        bearing = surface_bearing_sigma(s)
        extra = f", bearing σ {math.degrees(bearing):.1f}°" if math.isfinite(bearing) else ""
        out.append(
            b.marker(
                t,
                frame,
                "surface/label",
                i,
                TEXT_VIEW_FACING,
                rgb=rgb,
                scale=(0, 0, 0.04),
                position=patch.mean(axis=0),
                text=f"{s.label}: h = {p.offset:.3f} m ± {sigma * 1e3:.1f} mm{extra}, {quality}",
            )
        )
    features = [("corner", f, _CORNER_RGB) for f in message.corners] + [
        ("convex_edge", f, _CONVEX_RGB) for f in message.edges
    ]
    for i, (ns, f, rgb) in enumerate(features):
        point, direction = _vec(f.line.point), _vec(f.line.direction)
        if not np.isfinite(point).all():
            continue
        if np.isfinite(direction).all() and np.linalg.norm(direction) > 0:
            d = 0.25 * direction / np.linalg.norm(direction)
            out.append(b.marker(t, frame, ns, i, LINE_LIST, points=[point - d, point + d], rgb=rgb, scale=(0.01, 0, 0)))
        if len(f.covariance) == 9:
            sd = np.sqrt(np.clip(np.diag(np.asarray(f.covariance, dtype=float).reshape(3, 3)), 0.0, None))
        else:
            sd = np.full(3, max(float(f.line.point_stderr), 0.0))
        size = tuple(max(4.0 * float(v), 0.01) for v in sd)  # ± 2σ
        out.append(b.marker(t, frame, f"{ns}/sigma", i, SPHERE, rgb=rgb, alpha=0.5, scale=size, position=point))
        out.append(
            b.marker(
                t,
                frame,
                "feature/label",
                i,
                TEXT_VIEW_FACING,
                rgb=rgb,
                scale=(0, 0, 0.04),
                position=point,
                text=f"{ns.replace('_', ' ')} {f.label} ± {f.line.point_stderr * 1e3:.1f} mm",
            )
        )
    total = sum(u.count for u in message.unexplained)
    if total:
        causes = ", ".join(f"{u.count} {u.cause}" for u in message.unexplained)
        of = f" of {message.surface_echo_count} echoes" if message.surface_echo_count else ""
        out.append(
            b.marker(
                t,
                frame,
                "unexplained",
                0,
                TEXT_VIEW_FACING,
                rgb=_TEXT_RGB,
                scale=(0, 0, 0.04),
                position=(0.0, 0.0, -0.1),
                text=f"unexplained: {total}{of} ({causes})",
            )
        )
    return out
