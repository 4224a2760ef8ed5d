"""Every surface, corner and edge of a sweep in Rerun, drawn from the ``Reconstruction`` message alone.

Under a scan's world path (``world/{scanner}/scans/{scan}``)::

    surfaces/{label}                  Mesh3D, the observed patch in its verdict's colour
    surfaces/{label}/outline          LineStrips3D, the patch's outline (verdict colour)
    surfaces/{label}/sigma_band       LineStrips3D, the patch at ± 2σ of its offset along its normal
    surfaces/{label}/normal           Arrows3D, labelled with the offset, its σ and the verdict
    corners/{label}, edges/{label}    Points3D at the point (radius 2σ), labelled
    corners/{label}/direction, …      Arrows3D along the line
    unexplained                       TextDocument: the echoes nothing explains, by cause

Logged at the recording's current time (the caller sets it, as the final estimate's).
"""

from __future__ import annotations

import math

import numpy as np
import rerun as rr

from lelsonar import codec
from lelsonar.draw.estimates import SIGMA_BAND, surface_bearing_sigma, surface_offset_sigma
from lelsonar.draw.palette import CONCAVE_CORNER_COLOR, CONVEX_EDGE_COLOR, QUALITY_NAME, quality_color

_NORMAL_LENGTH = 0.2  # m
_FEATURE_HALF_LENGTH = 0.25  # m
_SURFACE_ALPHA = 90  # 0–255: see-through, so the points behind show


def _vec(v) -> np.ndarray:
    return np.array([v.x, v.y, v.z], dtype=float)


def log_surfaces(rec: rr.RecordingStream, scan_path: str, msg: codec.Reconstruction) -> int:
    """Log every surface, corner, edge and the unexplained echoes of ``msg`` under ``scan_path``.

    Returns
    -------
    int
        How many surfaces, corners and edges were drawn (a malformed one is skipped, not drawn wrong).
    """
    drawn = 0
    rec.log(f"{scan_path}/surfaces", rr.Clear(recursive=True))
    rec.log(f"{scan_path}/corners", rr.Clear(recursive=True))
    rec.log(f"{scan_path}/edges", rr.Clear(recursive=True))
    for s in msg.surfaces:
        p = s.plane
        patch = np.array([_vec(v) for v in p.patch])
        n = _vec(p.normal)
        if len(patch) < 2 or not (np.isfinite(patch).all() and np.isfinite(n).all()):
            continue
        rgb = quality_color(p.quality)
        quality = QUALITY_NAME.get(p.quality, "unknown")
        path = f"{scan_path}/surfaces/{rr.escape_entity_path_part(s.label)}"
        if len(patch) >= 3:
            rec.log(
                path,
                rr.Mesh3D(
                    vertex_positions=patch,
                    triangle_indices=[[0, k, k + 1] for k in range(1, len(patch) - 1)],
                    vertex_normals=np.tile(n, (len(patch), 1)),
                    albedo_factor=(*rgb, _SURFACE_ALPHA),
                    face_rendering="DoubleSided",
                ),
            )
        outline = np.vstack([patch, patch[:1]])
        rec.log(f"{path}/outline", rr.LineStrips3D([outline], colors=rgb, radii=0.004))
        sigma = surface_offset_sigma(s)
        if math.isfinite(sigma):
            band = [outline + k * SIGMA_BAND * sigma * n for k in (-1.0, 1.0)]
            rec.log(f"{path}/sigma_band", rr.LineStrips3D(band, colors=rgb, radii=0.0015))
        bearing = surface_bearing_sigma(s)
        extra = f", bearing ± {math.degrees(bearing):.1f}°" if math.isfinite(bearing) else ""
        rec.log(
            f"{path}/normal",
            rr.Arrows3D(
                origins=[patch.mean(axis=0)],
                vectors=[n * _NORMAL_LENGTH],
                colors=rgb,
                radii=0.004,
                labels=f"{s.label}: h = {p.offset:.3f} m ± {sigma * 1e3:.1f} mm{extra}, {quality}",
                show_labels=True,
            ),
        )
        drawn += 1
    for group, rgb, items in (("corners", CONCAVE_CORNER_COLOR, msg.corners), ("edges", CONVEX_EDGE_COLOR, msg.edges)):
        for f in items:
            point, direction = _vec(f.line.point), _vec(f.line.direction)
            if not np.isfinite(point).all():
                continue
            path = f"{scan_path}/{group}/{rr.escape_entity_path_part(f.label)}"
            sigma = float(f.line.point_stderr) if math.isfinite(f.line.point_stderr) else 0.0
            rec.log(
                path,
                rr.Points3D(
                    [point],
                    colors=rgb,
                    radii=max(2.0 * sigma, 0.01),
                    labels=f"{group[:-1]} {f.label} ± {sigma * 1e3:.1f} mm",
                    show_labels=True,
                ),
            )
            if np.isfinite(direction).all() and np.linalg.norm(direction) > 0:
                d = _FEATURE_HALF_LENGTH * direction / np.linalg.norm(direction)
                rec.log(f"{path}/direction", rr.Arrows3D(origins=[point - d], vectors=[2 * d], colors=rgb, radii=0.004))
            drawn += 1
    total = sum(u.count for u in msg.unexplained)
    of = f" of {msg.surface_echo_count}" if msg.surface_echo_count else ""
    lines = [f"- {u.count} {u.cause}" for u in msg.unexplained]
    rec.log(
        f"{scan_path}/unexplained",
        rr.TextDocument("\n".join([f"**unexplained echoes: {total}{of}**", *lines]), media_type="text/markdown"),
    )
    return drawn
