"""Reconstruction results as ``lelsonar.v1.Reconstruction`` messages (no I/O)."""

from __future__ import annotations

import time
from collections.abc import Iterable
from typing import TYPE_CHECKING

import numpy as np

from lelsonar import SCHEMA_VERSION, codec
from lelsonar.codec import QUALITY
from lelsonar.errors import ConfigError, ScannerMismatchError
from lelsonar.keys import ScannerKeys
from lelsonar.reconstruct.estimate.results import EdgeLine, FitFailure, PlaneFit, PlaneResult
from lelsonar.reconstruct.estimate.surfaces import Feature, SurfaceSet
from lelsonar.v1 import reconstruction_pb2 as pb

if TYPE_CHECKING:  # (the estimate's type only: decoding an estimate needs no estimator)
    from lelsonar.reconstruct.estimate.record import ScanEstimate

STATUS = {
    "provisional": pb.ESTIMATE_STATUS_PROVISIONAL,
    "final": pb.ESTIMATE_STATUS_FINAL,
    "final_timeout": pb.ESTIMATE_STATUS_FINAL_TIMEOUT,
    "incomplete": pb.ESTIMATE_STATUS_INCOMPLETE,
    "aborted": pb.ESTIMATE_STATUS_ABORTED,
}
#: Statuses after which no other estimate of the scan comes (but a re-finalised one, of a higher revision).
TERMINAL = frozenset({"final", "final_timeout", "incomplete", "aborted"})
_STATUS_NAME = {v: k for k, v in STATUS.items()}


def status_name(msg: codec.Reconstruction) -> str:
    return _STATUS_NAME.get(msg.status, "unknown")


def is_terminal(msg: codec.Reconstruction) -> bool:
    """No other estimate of this scan will come (final, final_timeout, incomplete or aborted)."""
    return status_name(msg) in TERMINAL


def _set(vec, xyz) -> None:
    vec.x, vec.y, vec.z = (float(v) for v in xyz)


def plane_message(plane: PlaneFit) -> pb.PlaneEstimate:
    msg = pb.PlaneEstimate(
        label=plane.label,
        method=plane.method,
        offset=plane.offset,
        sigma_relative=plane.sigma_relative,
        sigma=plane.sigma,
        inlier_count=plane.n_inliers,
        point_count=plane.n_points,
        lel_cost=plane.entropy,
        normal_stderr=plane.normal_stderr,
        offset_stderr=plane.offset_stderr,
        quality=QUALITY[plane.quality],
        quality_reasons=list(plane.quality_reasons),
    )
    _set(msg.normal, plane.normal)
    _set(msg.theta, plane.theta)
    msg.theta_covariance.extend(float(v) for v in np.asarray(plane.theta_covariance).ravel())
    for corner in plane.patch:
        _set(msg.patch.add(), corner)
    return msg


class PlaneMessages:
    """The message of each label's last plane, reused while the plane is the same object.

    A scan's provisional estimates carry plane a unchanged from the corner on, and plane b unchanged while its
    estimate is kept: a :class:`PlaneFit` is immutable, so its message is made once (it holds the plane, whose
    identity cannot be reused meanwhile).
    """

    def __init__(self) -> None:
        self._last: dict[str, tuple[PlaneFit, pb.PlaneEstimate]] = {}

    def message(self, plane: PlaneFit) -> pb.PlaneEstimate:
        """``plane_message(plane)``, made once per plane object."""
        last = self._last.get(plane.label)
        if last is not None and last[0] is plane:
            return last[1]
        msg = plane_message(plane)
        self._last[plane.label] = (plane, msg)
        return msg


def feature_message(feature: Feature) -> pb.FeatureEstimate:
    msg = pb.FeatureEstimate(
        label=feature.label,
        surfaces=list(feature.surfaces),
        reasons=list(feature.reasons),
        echo_count=feature.n_echoes,
    )
    _set(msg.line.point, feature.point)
    _set(msg.line.direction, feature.direction)
    # Across the line: the larger spread of the point's covariance (the bearing's, at the feature's depth).
    msg.line.point_stderr = float(np.sqrt(max(np.linalg.eigvalsh(feature.covariance).max(), 0.0)))
    msg.covariance.extend(float(v) for v in np.asarray(feature.covariance).ravel())
    return msg


def add_surfaces(msg: codec.Reconstruction, result: SurfaceSet) -> codec.Reconstruction:
    """Fill a ``Reconstruction``'s surfaces, corners, edges and unexplained echoes from one sweep's extraction."""
    for surface in result.surfaces:
        plane = plane_message(surface.plane)
        plane.label = surface.label
        item = msg.surfaces.add(
            label=surface.label,
            bearing=float(surface.bearing),
            tilt=float(surface.tilt),
            bearing_source=surface.bearing_source,
            echo_count=surface.n_echoes,
        )
        item.plane.CopyFrom(plane)
        item.covariance.extend(float(v) for v in np.asarray(surface.covariance).ravel())
    msg.corners.extend(feature_message(f) for f in result.corners)
    msg.edges.extend(feature_message(f) for f in result.edges)
    for cause, count in result.unexplained.items():
        if count:
            msg.unexplained.add(cause=cause, count=int(count))
    msg.surface_echo_count = int(result.n_echoes)
    return msg


def reconstruction_message(
    scanner_id: str,
    scan_id: int,
    *,
    status: str,
    last_step: int,
    samples_used: int,
    critical_step: int | None,
    critical_angle: float,
    planes: Iterable[PlaneResult],
    edge: EdgeLine | FitFailure | None,
    timings: tuple[float, float, float],
    stamp_ns: int | None = None,
    missing_steps: Iterable[int] = (),
    accounting: pb.ScanAccounting | None = None,
    surfaces: SurfaceSet | None = None,
    plane_messages: PlaneMessages | None = None,
) -> codec.Reconstruction:
    """Build a validated-to-be ``Reconstruction``.

    ``critical_step`` is a step index of the scan's schedule (not of the
    received subset); ``timings`` is (segmentation, fit, total) in s; ``plane_messages`` reuses the
    messages of planes encoded before (the same scan's earlier estimates).
    """
    msg = pb.Reconstruction(
        schema_version=SCHEMA_VERSION,
        scanner_id=scanner_id,
        scan_id=scan_id,
        last_step=last_step,
        status=STATUS[status],
        stamp_ns=stamp_ns if stamp_ns is not None else time.time_ns(),
        samples_used=samples_used,
    )
    if critical_step is not None:
        msg.critical_step = critical_step
        msg.critical_angle = float(critical_angle)
    for plane in planes:
        if isinstance(plane, PlaneFit):
            msg.planes.append(plane_message(plane) if plane_messages is None else plane_messages.message(plane))
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
    msg.missing_steps.extend(int(s) for s in missing_steps)
    if accounting is not None:
        msg.accounting.CopyFrom(accounting)
    if surfaces is not None:
        add_surfaces(msg, surfaces)
    return msg


def estimate_message(
    estimate: ScanEstimate,
    scanner_id: str,
    scan_id: int,
    *,
    status: str = "provisional",
    missing_steps: Iterable[int] = (),
    accounting: pb.ScanAccounting | None = None,
    surfaces: SurfaceSet | None = None,
    plane_messages: PlaneMessages | None = None,
) -> codec.Reconstruction:
    """The ``Reconstruction`` message of an estimate of record
    (:func:`lelsonar.reconstruct.estimate.record.reconstruct_scan`): its planes, edge and failures,
    then the failures beyond them (``estimate.failures``), and the sweep's surfaces (``surfaces``, by
    default the estimate's own: a final's; a provisional estimate has none); ``plane_messages`` reuses the
    messages of planes its scan's earlier estimates carried.

    ``status`` is a terminal status for a final estimate (the stream decides which: final, incomplete,
    final_timeout), "provisional" for a provisional one.
    """
    if estimate.provisional != (status == "provisional"):
        raise ConfigError(f"a {'provisional' if estimate.provisional else 'final'} estimate cannot be {status}")
    msg = reconstruction_message(
        scanner_id,
        scan_id,
        status=status,
        last_step=estimate.last_step,
        samples_used=estimate.samples_used,
        critical_step=estimate.critical_step,
        critical_angle=estimate.critical_angle,
        planes=estimate.planes,
        edge=estimate.edge,
        timings=estimate.timings,
        missing_steps=missing_steps,
        accounting=accounting,
        surfaces=surfaces if surfaces is not None else estimate.surfaces,
        plane_messages=plane_messages,
    )
    msg.failures.extend(estimate.failures)
    return msg


def accounting_message(
    *,
    published: int,
    received_live: int,
    recovered: int,
    duplicates: int,
    rejected: dict[str, int],
    missing: int,
    conflicts: int = 0,
) -> pb.ScanAccounting:
    """Where every sample of one scan went (see ``ScanAccounting`` in reconstruction.proto)."""
    acc = pb.ScanAccounting(
        published=published,
        received_live=received_live,
        recovered=recovered,
        duplicates=duplicates,
        missing=missing,
        conflicts=conflicts,
    )
    for reason, n in sorted(rejected.items()):
        if n:
            acc.rejected[reason] = int(n)
    return acc


def accounting_text(acc: pb.ScanAccounting) -> str:
    """One line, e.g. ``published 184, live 180, recovered 4, duplicates 0, rejected 0, missing 0``."""
    rejected = sum(acc.rejected.values())
    detail = f" ({', '.join(f'{k} {v}' for k, v in sorted(acc.rejected.items()))})" if rejected else ""
    return (
        f"published {acc.published}, live {acc.received_live}, recovered {acc.recovered}, "
        f"duplicates {acc.duplicates}"
        + (f" (conflicting {acc.conflicts})" if acc.conflicts else "")
        + f", rejected {rejected}{detail}, missing {acc.missing}"
    )


def decode_estimate(key: str, payload: bytes, prefix: str) -> codec.Reconstruction:
    """A Reconstruction received on ``key``, validated, whose scanner id must be the key's.

    Raises
    ------
    DecodeError
        The payload is not a valid Reconstruction.
    ScannerMismatchError
        It claims another scanner than the planes key it came on (a forgery or a misconfiguration).
    """
    message = codec.decode(payload, codec.Reconstruction)
    on_key = ScannerKeys(prefix).scanner_chunk(key)
    if message.scanner_id != on_key:
        raise ScannerMismatchError(
            f"an estimate for scanner {message.scanner_id!r} came on the planes key of "
            f"scanner {on_key[:80]!r}; ignored (a forgery, or a misconfigured publisher)"
        )
    return message
