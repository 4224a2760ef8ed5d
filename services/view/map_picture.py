"""``lelsonar map --source … --screenshot OUT.png``: the final map as a still image (matplotlib), from above.

Drawn from the ``Map`` message, as the other viewers draw it: the free space the scans saw (light blue),
each wall as a band as wide as its offset's ± 2σ (at least a hairline) in its verdict's colour, corners,
edges and horizontal corners (where a wall meets the floor or the ceiling), the corrected path against the
odometry's, the planner's route, and the simulated world's true walls (grey, thin) where the recording
carries them.  ``docs/map.png`` is made with it.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import shapely

from lelsonar.draw.estimates import SIGMA_BAND
from lelsonar.draw.map_scene import wall_pieces
from lelsonar.draw.palette import (
    CONCAVE_CORNER_COLOR,
    CONVEX_EDGE_COLOR,
    HORIZONTAL_CORNER_COLOR,
    QUALITY_COLORS,
    quality_color,
    unit_rgb,
)
from lelsonar.v1 import map_pb2, reconstruction_pb2

#: Opacity and drawing order of a wall by verdict (wire value): good, degraded, unreliable.
_WALL_ALPHA: dict[int, tuple[float, float]] = {
    reconstruction_pb2.PLANE_QUALITY_GOOD: (0.95, 3.2),
    reconstruction_pb2.PLANE_QUALITY_DEGRADED: (0.6, 3.1),
}


def save_map_picture(
    path: Path | str,
    msg: map_pb2.Map,
    *,
    free_space=None,
    route: list[tuple[float, float]] | None = None,
    world: dict | None = None,
    title: str = "",
    closed: np.ndarray | None = None,
) -> Path:
    """Draw the map and write it to ``path`` (png, pdf or svg); returns the path.

    ``closed``: stretches (n, 2, 2) of walls' lines that no scan saw but a route never crosses (the floor
    plan's ``closed_gaps``), drawn as thin dotted lines.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D
    from matplotlib.patches import Polygon as Patch

    fig, ax = plt.subplots(figsize=(8, 7), dpi=110)
    if free_space is not None and not free_space.is_empty:
        for poly in shapely.get_parts(free_space):
            ax.add_patch(
                Patch(np.asarray(poly.exterior.coords), closed=True, fc=(0.75, 0.87, 1.0), ec="none", zorder=0)
            )
            for hole in poly.interiors:
                ax.add_patch(Patch(np.asarray(hole.coords), closed=True, fc="white", ec="none", zorder=0))
    for w in (world or {}).get("walls", []):
        (x0, y0), (x1, y1) = w["from"], w["to"]
        ax.plot([x0, x1], [y0, y1], color=(0.45, 0.45, 0.45), lw=0.8, ls="--", zorder=1)
    # The walls a planner may trust stand out; flagged ones (lone echoes, often a corner's or a wall end's) are
    # drawn fainter beneath them, at their full σ.
    for w in sorted(msg.walls, key=lambda w: -int(w.quality)):
        sigma = w.offset_stderr if math.isfinite(w.offset_stderr) else 0.0
        n = np.array([w.normal.x, w.normal.y])
        alpha, z = _WALL_ALPHA.get(int(w.quality), (0.35, 2.0))
        for a, b in wall_pieces(w):
            band = SIGMA_BAND * sigma * n
            corners = np.array([a[:2] - band, b[:2] - band, b[:2] + band, a[:2] + band])
            color = unit_rgb(quality_color(w.quality))
            ax.add_patch(Patch(corners, closed=True, fc=color, ec=color, lw=1.2, alpha=alpha, zorder=z))
    for a, b in closed if closed is not None else ():
        ax.plot([a[0], b[0]], [a[1], b[1]], color=(0.15, 0.15, 0.15), lw=0.9, ls=":", zorder=2.5)
    for items, color, marker in (
        (msg.corners, unit_rgb(CONCAVE_CORNER_COLOR), "o"),
        (msg.edges, unit_rgb(CONVEX_EDGE_COLOR), "s"),
        (msg.horizontal_corners, unit_rgb(HORIZONTAL_CORNER_COLOR), "^"),
    ):
        if len(items):
            ax.scatter(
                [f.point.x for f in items], [f.point.y for f in items], s=18, color=color, marker=marker, zorder=4
            )
    if msg.poses:
        odo = np.array([[p.odometry.x, p.odometry.y] for p in msg.poses])
        fused = np.array([[p.position.x, p.position.y] for p in msg.poses])
        ax.plot(odo[:, 0], odo[:, 1], color=(0.55, 0.55, 0.55), lw=1, marker=".", zorder=5)
        ax.plot(fused[:, 0], fused[:, 1], color=(0.9, 0.65, 0.0), lw=1.6, marker="o", ms=3, zorder=6)
    if route:
        r = np.asarray(route)
        ax.plot(r[:, 0], r[:, 1], color=(0.1, 0.1, 0.1), lw=2, zorder=7)
        ax.plot(*r[-1], marker="*", color=(0.1, 0.1, 0.1), ms=12, zorder=7)
    legend = [
        Line2D([], [], color=unit_rgb(QUALITY_COLORS[q]), lw=4, label=f"wall {q} (± 2σ)")
        for q in ("good", "degraded", "unreliable")
    ]
    legend += [
        Line2D([], [], color=(0.9, 0.65, 0.0), lw=1.6, marker="o", ms=3, label="path after fusion"),
        Line2D([], [], color=(0.55, 0.55, 0.55), lw=1, marker=".", label="odometry"),
        Line2D([], [], color=unit_rgb(CONCAVE_CORNER_COLOR), marker="o", ls="none", label="corner"),
    ]
    if len(msg.edges):
        legend.append(Line2D([], [], color=unit_rgb(CONVEX_EDGE_COLOR), marker="s", ls="none", label="convex edge"))
    if len(msg.horizontal_corners):
        legend.append(
            Line2D(
                [], [], color=unit_rgb(HORIZONTAL_CORNER_COLOR), marker="^", ls="none", label="wall on floor/ceiling"
            )
        )
    if closed is not None and len(closed):
        legend.append(Line2D([], [], color=(0.15, 0.15, 0.15), lw=0.9, ls=":", label="unseen, closed"))
    if free_space is not None:
        legend.append(Line2D([], [], color=(0.75, 0.87, 1.0), lw=6, label="seen free"))
    if route:
        legend.append(Line2D([], [], color=(0.1, 0.1, 0.1), lw=2, label="route out"))
    if world:
        legend.append(Line2D([], [], color=(0.45, 0.45, 0.45), lw=0.8, ls="--", label="true walls"))
    ax.legend(handles=legend, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
    ax.set_aspect("equal")
    ax.autoscale_view()
    ax.set_xlabel("x, m")
    ax.set_ylabel("y, m")
    ax.set_title(title or f"map of {msg.scanner_id}: {len(msg.walls)} walls, {msg.scans} scans", fontsize=10)
    ax.grid(True, lw=0.3, alpha=0.5)
    fig.tight_layout()
    out = Path(path)
    fig.savefig(out, bbox_inches="tight")  # the legend stands outside the axes
    plt.close(fig)
    return out
