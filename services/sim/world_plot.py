"""A plan view of a world: walls, boxes, the robot's poses and path, and where each sweep's echoes came from.

Uses matplotlib's object API with the Agg canvas (no global backend, no window).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from lelsonar.errors import ConfigError
from lelsonar.geometry import boresight
from lelsonar.sim.scan import EchoSource
from lelsonar.sim.world_geometry import WorldModel
from lelsonar.sim.world_render import WorldScan, pose_frame

_SOURCE_STYLE = {
    EchoSource.PLANE_OTHER: ("tab:blue", "mirror"),
    EchoSource.CORNER: ("tab:red", "dihedral corner"),
    EchoSource.TRIHEDRAL: ("tab:orange", "trihedral corner"),
    EchoSource.EDGE: ("tab:green", "edge diffraction"),
    EchoSource.DIFFUSE: ("tab:purple", "diffuse"),
}


def world_points(scan: WorldScan) -> np.ndarray:
    """Each reading's point along its beam (eq. 9) in the world frame, (n, m, 3); NaN without an echo."""
    rot, trans = pose_frame(scan.rig, scan.pose)
    pos = scan.geometry.capsule_positions(scan.gamma_measured)
    pts = pos + scan.distance[..., None] * boresight(scan.gamma_measured)[:, None, :]
    return pts @ rot.T + trans


def world_figure(model: WorldModel, scans: list[WorldScan], odometry=None):
    """The world from above with every pose's sweep.

    Parameters
    ----------
    model : WorldModel
    scans : list of WorldScan
        One per pose drawn: its echo points coloured by the echo that set them, and its sweep's edges.
    odometry : list of OdometryPose, optional
        Drawn as the path the robot believes it took.

    Returns
    -------
    matplotlib.figure.Figure
    """
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
        from matplotlib.patches import Polygon
    except ModuleNotFoundError:
        raise ConfigError("figures need matplotlib, an optional extra: pip install 'lelsonar[plot]'") from None
    world = model.world
    x0, y0, x1, y1 = world.bounds()
    span = max(x1 - x0, y1 - y0, 1.0)
    fig = Figure(figsize=(8, 8 * min(max((y1 - y0) / max(x1 - x0, 1e-3), 0.5), 1.6)), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    for w in world.walls:
        ax.plot([w.start[0], w.end[0]], [w.start[1], w.end[1]], "k-", lw=3, solid_capstyle="butt")
    for b in world.boxes:
        ax.add_patch(Polygon(np.array(b.footprint()), closed=True, fc="0.75", ec="k", lw=1.5))
        ax.annotate(b.name, b.center, ha="center", va="center", fontsize=7)
    drawn: set[int] = set()
    for scan in scans:
        pts = world_points(scan)
        for code, (colour, label) in _SOURCE_STYLE.items():
            sel = (scan.echo_source == code) & np.isfinite(pts[..., 0])
            if sel.any():
                ax.scatter(
                    pts[sel][:, 0], pts[sel][:, 1], s=3, c=colour, label=None if code in drawn else label, zorder=3
                )
                drawn.add(int(code))
        # The sweep's two edges and its middle, as far as the window reaches.
        rot, trans = pose_frame(scan.rig, scan.pose)
        reach = 0.12 * span
        for g, style in ((scan.rig.gamma_start, ":"), (scan.rig.gamma_stop, ":"), (0.0, "-")):
            d = rot @ boresight(g)
            ax.plot([trans[0], trans[0] + reach * d[0]], [trans[1], trans[1] + reach * d[1]], "c" + style, lw=1)
    poses = world.poses
    ax.plot([p.x for p in poses], [p.y for p in poses], "-", c="tab:gray", lw=1, label="path (truth)")
    for i, p in enumerate(poses):
        ax.annotate(
            "",
            xy=(p.x + 0.06 * span * math.cos(p.heading), p.y + 0.06 * span * math.sin(p.heading)),
            xytext=(p.x, p.y),
            arrowprops={"arrowstyle": "->", "color": "k", "lw": 1.5},
        )
        ax.annotate(str(i + 1), (p.x, p.y), xytext=(-10, -10), textcoords="offset points", fontsize=8)
    if odometry:
        ax.plot([o.x for o in odometry], [o.y for o in odometry], "--", c="tab:brown", lw=1, label="path (odometry)")
    ax.set(
        xlabel="x (m)",
        ylabel="y (m)",
        aspect="equal",
        xlim=(x0 - 0.1 * span, x1 + 0.1 * span),
        ylim=(y0 - 0.1 * span, y1 + 0.1 * span),
        title=f"world {world.name}: {len(world.walls)} walls, {len(world.boxes)} boxes, {len(poses)} poses "
        f"({world.scanner.mount} mount)",
    )
    ax.legend(fontsize=7, loc="upper right", markerscale=3)
    return fig


def save_world_figure(model: WorldModel, scans: list[WorldScan], path: str | Path, odometry=None) -> Path:
    """Render :func:`world_figure` to ``path`` (PNG, PDF, SVG by suffix); creates the folder."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    world_figure(model, scans, odometry).savefig(path, dpi=110)
    return path
