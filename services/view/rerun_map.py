"""The map in Rerun, growing scan by scan: drawn from each ``Map`` message on the ``scans`` timeline.

Under ``<root>/map/fused`` (the world's truth, where known, is under ``<root>/map/truth``)::

    walls/{id}         LineStrips3D on the floor, one strip per observed piece, as wide as the offset's ± 2σ,
                       in the verdict's colour, labelled with σ and verdict
    corners, edges     Points3D, radius 2σ of the point
    horizontal_corners Points3D, radius 2σ of the point: where a wall meets the floor or the ceiling
    path/corrected     LineStrips3D through the corrected poses, and path/poses (Arrows3D, the headings)
    path/odometry      LineStrips3D through the odometry's poses, before fusion
    free_space         Mesh3D (filled) and free_space/outline (LineStrips3D), where the caller knows it
    route              LineStrips3D, the planner's route, where one was asked for

Every update clears ``walls`` first: walls merge and split as scans come, and a wall gone from the map
must leave the picture.
"""

from __future__ import annotations

import math

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
import shapely

from lelsonar.draw.estimates import SIGMA_BAND
from lelsonar.draw.map_scene import wall_pieces
from lelsonar.draw.palette import (
    CONCAVE_CORNER_COLOR,
    CONVEX_EDGE_COLOR,
    HORIZONTAL_CORNER_COLOR,
    QUALITY_NAME,
    quality_color,
)
from lelsonar.v1 import map_pb2
from lelsonar.view.rerun_layout import join_path

#: The sequence timeline of the map: how many scans it holds.
SCANS_TIMELINE = "scans"

_PATH_RGB = (255, 200, 0)
_ODOMETRY_RGB = (150, 150, 150)
_FREE_RGB = (90, 170, 255)
_ROUTE_RGB = (255, 255, 255)
_MIN_RADIUS = 0.005  # m: a thinner strip would vanish


def map_blueprint(root: str = "/") -> rrb.Blueprint:
    """One 3D view of the map (and the truth under it), from above."""
    return rrb.Blueprint(
        rrb.Spatial3DView(origin=join_path(root, "map"), name="map"),
        rrb.TimePanel(timeline=SCANS_TIMELINE),
        collapse_panels=True,
    )


def log_map(
    rec: rr.RecordingStream,
    msg: map_pb2.Map,
    *,
    free_space=None,
    route: list[tuple[float, float]] | None = None,
    root: str = "/",
) -> None:
    """Log one map at ``scans = msg.scans`` (see the module docstring); ``free_space`` a shapely geometry."""
    base = join_path(root, "map", "fused")
    rec.log(join_path(root, "map"), rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    rec.set_time(SCANS_TIMELINE, sequence=int(msg.scans))
    rec.log(f"{base}/walls", rr.Clear(recursive=True))
    for w in msg.walls:
        pieces = wall_pieces(w)
        if not pieces:
            continue
        sigma = w.offset_stderr if math.isfinite(w.offset_stderr) else 0.0
        label = f"wall {w.id}: ± {sigma * 1e3:.1f} mm, {QUALITY_NAME.get(w.quality, 'unknown')}"
        rec.log(
            f"{base}/walls/{w.id}",
            rr.LineStrips3D(
                [np.array([[a[0], a[1], 0.0], [b[0], b[1], 0.0]]) for a, b in pieces],
                colors=quality_color(w.quality),
                radii=max(SIGMA_BAND * sigma, _MIN_RADIUS),
                labels=[label] + [""] * (len(pieces) - 1),
                show_labels=True,
            ),
        )
    for name, rgb, items in (
        ("corners", CONCAVE_CORNER_COLOR, msg.corners),
        ("edges", CONVEX_EDGE_COLOR, msg.edges),
        ("horizontal_corners", HORIZONTAL_CORNER_COLOR, msg.horizontal_corners),
    ):
        pts = [(f.point.x, f.point.y, 0.0) for f in items]
        if pts:
            rec.log(
                f"{base}/{name}",
                rr.Points3D(pts, colors=rgb, radii=[max(2.0 * f.point_stderr, 0.03) for f in items]),
            )
        else:
            rec.log(f"{base}/{name}", rr.Clear(recursive=False))
    if msg.poses:
        path = np.array([[p.position.x, p.position.y, 0.01] for p in msg.poses])
        heads = np.array([[0.2 * math.cos(p.heading), 0.2 * math.sin(p.heading), 0.0] for p in msg.poses])
        rec.log(f"{base}/path/corrected", rr.LineStrips3D([path], colors=_PATH_RGB, radii=0.01))
        rec.log(
            f"{base}/path/poses",
            rr.Arrows3D(origins=path, vectors=heads, colors=_PATH_RGB, labels=[str(p.scan_id) for p in msg.poses]),
        )
        odometry = np.array([[p.odometry.x, p.odometry.y, 0.005] for p in msg.poses])
        rec.log(f"{base}/path/odometry", rr.LineStrips3D([odometry], colors=_ODOMETRY_RGB, radii=0.005))
    if free_space is not None and not free_space.is_empty:
        _log_free_space(rec, f"{base}/free_space", free_space)
    if route:
        rec.log(
            f"{base}/route",
            rr.LineStrips3D([np.array([[x, y, 0.02] for x, y in route])], colors=_ROUTE_RGB, radii=0.015),
        )


def _log_free_space(rec: rr.RecordingStream, path: str, space) -> None:
    """The free space filled (a constrained Delaunay triangulation) with its outlines."""
    triangles = [
        np.asarray(t.exterior.coords)[:3] for t in shapely.get_parts(shapely.constrained_delaunay_triangles(space))
    ]
    if triangles:
        vertices = np.concatenate(triangles)
        vertices = np.column_stack([vertices, np.zeros(len(vertices))])
        rec.log(
            path,
            rr.Mesh3D(
                vertex_positions=vertices,
                triangle_indices=np.arange(len(vertices)).reshape(-1, 3),
                albedo_factor=(*_FREE_RGB, 64),
            ),
        )
    rings = [
        np.column_stack([np.asarray(r.coords), np.zeros(len(r.coords))])
        for poly in shapely.get_parts(space)
        for r in (poly.exterior, *poly.interiors)
    ]
    rec.log(f"{path}/outline", rr.LineStrips3D(rings, colors=_FREE_RGB, radii=0.004))
