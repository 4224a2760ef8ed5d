"""Reconstruction results as ``lelsonar.v1.Reconstruction`` messages (no I/O)."""

from __future__ import annotations

import time
from collections.abc import Iterable

import numpy as np

from lelsonar import SCHEMA_VERSION, codec
from lelsonar.reconstruct.results import EdgeLine, FitFailure, PlaneFit, PlaneResult
from lelsonar.v1 import reconstruction_pb2 as pb

QUALITY = {
    "": pb.PLANE_QUALITY_UNSPECIFIED,
    "good": pb.PLANE_QUALITY_GOOD,
    "degraded": pb.PLANE_QUALITY_DEGRADED,
    "unreliable": pb.PLANE_QUALITY_UNRELIABLE,
}
#: Short names of the quality enum, as ``--json`` and the planner print them.
QUALITY_NAME = {v: (k or "unassessed") for k, v in QUALITY.items()}

STATUS = {
    "provisional": pb.ESTIMATE_STATUS_PROVISIONAL,
    "final": pb.ESTIMATE_STATUS_FINAL,
    "final_timeout": pb.ESTIMATE_STATUS_FINAL_TIMEOUT,
}


def _set(vec, xyz) -> None:
    vec.x, vec.y, vec.z = (float(v) for v in xyz)


def plane_message(plane: PlaneFit) -> pb.PlaneEstimate:
    msg = pb.PlaneEstimate(
        label=plane.label, method=plane.method, offset=plane.offset, sigma_relative=plane.sigma_relative,
        sigma=plane.sigma, inlier_count=plane.n_inliers, point_count=plane.n_points, lel_cost=plane.entropy,
        normal_stderr=plane.normal_stderr, offset_stderr=plane.offset_stderr,
        quality=QUALITY[plane.quality], quality_reasons=list(plane.quality_reasons),
    )
    _set(msg.normal, plane.normal)
    _set(msg.theta, plane.theta)
    msg.theta_covariance.extend(float(v) for v in np.asarray(plane.theta_covariance).ravel())
    for corner in plane.patch:
        _set(msg.patch.add(), corner)
    return msg


def reconstruction_message(scanner_id: str, scan_id: int, *, status: str, last_step: int, samples_used: int,
                           critical_step: int | None, critical_angle: float, planes: Iterable[PlaneResult],
                           edge: EdgeLine | FitFailure | None, timings: tuple[float, float, float],
                           stamp_ns: int | None = None) -> codec.Reconstruction:
    """Build a validated-to-be ``Reconstruction``.

    ``critical_step`` is a step index of the scan's schedule (not of the
    received subset); ``timings`` is (segmentation, fit, total) in s.
    """
    msg = pb.Reconstruction(
        schema_version=SCHEMA_VERSION, scanner_id=scanner_id, scan_id=scan_id, last_step=last_step,
        status=STATUS[status], stamp_ns=stamp_ns if stamp_ns is not None else time.time_ns(),
        samples_used=samples_used,
    )
    if critical_step is not None:
        msg.critical_step = critical_step
        msg.critical_angle = float(critical_angle)
    for plane in planes:
        if isinstance(plane, PlaneFit):
            msg.planes.append(plane_message(plane))
        else:
            msg.failures.append(str(plane))
    if isinstance(edge, EdgeLine):
        _set(msg.corner_edge.point, edge.point)
        _set(msg.corner_edge.direction, edge.direction)
        msg.corner_edge.point_stderr = float(edge.point_stderr)
        msg.corner_edge.direction_stderr = float(edge.direction_stderr)
    elif isinstance(edge, FitFailure):
        msg.failures.append(str(edge))
    msg.timings.segmentation, msg.timings.fit, msg.timings.total = (float(t) for t in timings)
    return msg
