"""The planes of an estimate in Rerun: each method's fitted patch with its verdict and uncertainty, the
L's edge, and the true planes of a simulated scene (:class:`lelsonar.view.rerun_log.ScanLogger` draws
through these)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import rerun as rr

from lelsonar.draw.palette import method_color, quality_color
from lelsonar.reconstruct.estimate.results import EdgeLine, PlaneFit
from lelsonar.view.rerun_shapes import cone

_PLANE_ALPHA = 110  # patches stay see-through so points behind them show
_TRUTH_RGBA = (160, 160, 160, 80)
_EDGE_RGB = (255, 255, 255)
_NORMAL_LENGTH = 0.25  # m


def log_plane_fit(rec: rr.RecordingStream, path: str, p: PlaneFit, main_method: str | None) -> None:
    """A fitted plane under ``path``: its patch in its method's colour, its normal (labelled when it is the
    method of record's, or every method's when ``main_method`` is None), its verdict as the outline, and its
    uncertainty: the offset band (the outline at ± 2σ_h) and the normal cone (half-angle 2σ_n)."""
    rgb = method_color(p.method)
    rec.log(
        path,
        rr.Mesh3D(
            vertex_positions=p.patch,
            triangle_indices=[[0, 1, 2], [0, 2, 3]],
            vertex_normals=np.tile(p.normal, (4, 1)),
            albedo_factor=(*rgb, _PLANE_ALPHA),
            face_rendering="DoubleSided",
        ),
    )
    centre = p.patch.mean(axis=0)
    # One label per plane, the method of record's, at the tip of its normal: compared methods'
    # planes share the centre, and their labels would cover each other.
    labelled = main_method is None or p.method == main_method
    rec.log(
        f"{path}/normal",
        rr.Arrows3D(
            origins=[centre],
            vectors=[p.normal * _NORMAL_LENGTH],
            colors=rgb,
            radii=0.005,
            labels=f"{p.label}: {p.method}, {p.quality or 'unassessed'}" if labelled else None,
            show_labels=labelled,
        ),
    )
    # The verdict as the patch's outline: green good, amber degraded, red unreliable.
    outline = np.vstack([p.patch, p.patch[:1]])
    rec.log(f"{path}/quality", rr.LineStrips3D([outline], colors=quality_color(p.quality), radii=0.004))
    # The uncertainty: the offset band (patch outline at ±2σ_h) and the normal cone (half-angle 2σ_n).
    band = [outline + k * 2.0 * p.offset_stderr * p.normal for k in (-1.0, 1.0)]
    rec.log(f"{path}/uncertainty/offset_band", rr.LineStrips3D(band, colors=rgb, radii=0.0015))
    rec.log(
        f"{path}/uncertainty/normal_cone",
        rr.Arrows3D(
            origins=np.tile(centre, (8, 1)),
            vectors=cone(p.normal, 2.0 * p.normal_stderr) * _NORMAL_LENGTH,
            colors=rgb,
            radii=0.0015,
        ),
    )


def log_edge(
    rec: rr.RecordingStream, path: str, edge: EdgeLine, fits: Sequence[PlaneFit], half_length: float = 0.5
) -> None:
    """The L's edge under ``path``, labelled with its angle and the σ of its point."""
    # Draw ±half_length around the point nearest the origin, but no further than the
    # observed patches reach along the edge (the edge beyond them is extrapolation).
    lo, hi = -half_length, half_length
    if fits:
        t = np.concatenate([(f.patch - edge.point) @ edge.direction for f in fits])
        lo_p, hi_p = max(lo, float(t.min())), min(hi, float(t.max()))
        if hi_p - lo_p > 1e-3:
            lo, hi = lo_p, hi_p
    seg = edge.point + np.outer([lo, hi], edge.direction)
    label = f"edge {math.degrees(edge.angle):.1f}°"
    if math.isfinite(edge.point_stderr):
        label += f" ± {edge.point_stderr * 1e3:.0f} mm"
    rec.log(path, rr.LineStrips3D([seg], colors=_EDGE_RGB, radii=0.004, labels=label))


def log_true_plane(rec: rr.RecordingStream, path: str, label: str, normal, offset: float, corners) -> None:
    """A true plane as a static grey patch under ``path``: ``normal`` (3,) unit, ``offset`` m, ``corners``
    (4, 3) in order around the patch, m."""
    corners = np.array(corners, dtype=np.float64).reshape(4, 3)  # a copy: the caller's array stays as it was
    n = np.asarray(normal, dtype=np.float64).reshape(3)
    rec.log(
        path,
        rr.Mesh3D(
            vertex_positions=corners,
            triangle_indices=[[0, 1, 2], [0, 2, 3]],
            vertex_normals=np.tile(n, (4, 1)),
            albedo_factor=_TRUTH_RGBA,
            face_rendering="DoubleSided",
        ),
        static=True,
    )
    rec.log(
        f"{path}/normal",
        rr.Arrows3D(
            origins=[corners.mean(axis=0)],
            vectors=[n * _NORMAL_LENGTH],
            colors=_TRUTH_RGBA[:3],
            radii=0.004,
        ),
        static=True,
    )
    # At the patch's first corner, away from the estimates' labels at the centre.
    rec.log(
        f"{path}/label",
        rr.Points3D(
            corners[:1], radii=0.001, colors=_TRUTH_RGBA[:3], labels=f"truth {label}: h = {float(offset):.3f} m"
        ),
        static=True,
    )
