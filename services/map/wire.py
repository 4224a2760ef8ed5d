"""The map as the contract's ``Map`` message (published on ``<prefix>/map``, recorded to MCAP)."""

from __future__ import annotations

import math
import time

import numpy as np

from lelsonar import codec
from lelsonar.errors import InvalidMessageError
from lelsonar.map.lines import interval_on_line
from lelsonar.map.result import FusedFeature, FusedMap, FusedPose, FusedWall
from lelsonar.v1 import map_pb2

#: The contract version this module writes.
SCHEMA_VERSION = 1


def _set(vec, xyz) -> None:
    vec.x, vec.y, vec.z = (float(v) for v in xyz)


def _feature(out: map_pb2.MapFeature, f: FusedFeature) -> None:
    _set(out.point, f.point)
    _set(out.direction, f.direction)
    out.kind = f.kind
    out.point_stderr = f.point_stderr
    out.observations = f.observations
    out.wall_ids.extend(f.walls)


def map_message(m: FusedMap, scanner_id: str, stamp_ns: int | None = None) -> map_pb2.Map:
    """The ``Map`` message of a fused map (world frame, SI units)."""
    msg = map_pb2.Map(
        schema_version=SCHEMA_VERSION,
        scanner_id=scanner_id,
        stamp_ns=time.time_ns() if stamp_ns is None else stamp_ns,
        scans=len(m.poses),
    )
    for w in m.walls:
        out = msg.walls.add(
            id=w.id,
            offset=w.offset,
            normal_stderr=w.normal_stderr,
            offset_stderr=w.offset_stderr,
            quality=codec.QUALITY[w.quality],
            good_observations=w.good_observations,
            flagged_observations=w.flagged_observations,
        )
        _set(out.normal, w.normal)
        for p in w.extent():
            _set(out.extent.add(), p)
        out.covariance.extend(float(v) for v in w.covariance.ravel())
        out.quality_reasons.extend(w.reasons)
        out.scan_ids.extend(w.scans)
        for a, b in w.piece_segments:
            _set(out.pieces.add(), (a[0], a[1], w.z_range[0]))
            _set(out.pieces.add(), (b[0], b[1], w.z_range[0]))
    for f in m.corners:
        _feature(msg.corners.add(), f)
    for f in m.edges:
        _feature(msg.edges.add(), f)
    for p in m.poses:
        pose = msg.poses.add(scan_id=p.scan_id, heading=p.heading)
        _set(pose.position, (p.x, p.y, p.z))
        pose.covariance.extend(float(v) for v in p.covariance.ravel())
        _set(pose.odometry, p.odometry)
    msg.notes.extend(m.notes)
    scans = m.view_scans if len(m.view_scans) == len(m.views) else (0,) * len(m.views)
    for view, scan_id in zip(m.views, scans):
        out_view = msg.views.add(scan_id=scan_id)
        for p in view:
            _set(out_view.polygon.add(), (p[0], p[1], 0.0))
    return msg


def _xyz(v) -> np.ndarray:
    return np.array([v.x, v.y, v.z], dtype=float)


def _matrix(values, n: int, what: str) -> np.ndarray:
    m = np.array(values, dtype=float)
    if m.size != n * n or not np.all(np.isfinite(m)):
        raise InvalidMessageError(f"{what} covariance must be {n * n} finite numbers, got {m.size}")
    return m.reshape(n, n)


def _feature_from(f: map_pb2.MapFeature, source: str) -> FusedFeature:
    return FusedFeature(
        point=_xyz(f.point),
        direction=_xyz(f.direction),
        kind=f.kind,
        point_stderr=f.point_stderr,
        source=source,
        observations=f.observations,
        walls=tuple(f.wall_ids),
    )


def map_from_message(msg: map_pb2.Map) -> FusedMap:
    """A received ``Map`` as the library's :class:`~lelsonar.map.result.FusedMap` (what the floor plan and the
    route take); every field checked, a wrong one an :class:`~lelsonar.errors.InvalidMessageError` naming it."""
    walls = []
    for w in msg.walls:
        n = _xyz(w.normal)
        if abs(float(np.linalg.norm(n[:2])) - 1.0) > 1e-6 or not math.isfinite(w.offset):
            raise InvalidMessageError(f"map wall {w.id}: its normal must be a horizontal unit vector")
        line = np.array([math.atan2(n[1], n[0]), w.offset])
        if len(w.pieces) % 2 or not w.pieces:
            raise InvalidMessageError(f"map wall {w.id}: pieces must be end-point pairs, got {len(w.pieces)} points")
        ends = np.array([_xyz(p) for p in w.pieces])
        pieces = tuple(interval_on_line(line, ends[k : k + 2]) for k in range(0, len(ends), 2))
        zs = np.array([_xyz(p)[2] for p in w.extent]) if w.extent else ends[:, 2]
        walls.append(
            FusedWall(
                id=w.id,
                line=line,
                covariance=_matrix(w.covariance, 2, f"map wall {w.id}"),
                interval=(min(p[0] for p in pieces), max(p[1] for p in pieces)),
                pieces=pieces,
                z_range=(float(zs.min()), float(zs.max())),
                quality=codec.QUALITY_NAME.get(w.quality, "unreliable"),
                reasons=tuple(w.quality_reasons),
                scans=tuple(int(s) for s in w.scan_ids),
                good_observations=w.good_observations,
                flagged_observations=w.flagged_observations,
            )
        )
    poses = tuple(
        FusedPose(
            scan_id=int(p.scan_id),
            x=p.position.x,
            y=p.position.y,
            z=p.position.z,
            heading=p.heading,
            covariance=_matrix(p.covariance, 3, f"map pose {p.scan_id}"),
            odometry=(p.odometry.x, p.odometry.y, p.odometry.z),
        )
        for p in msg.poses
    )
    views = tuple(np.array([[q.x, q.y] for q in v.polygon]) for v in msg.views)
    return FusedMap(
        walls=tuple(walls),
        features=tuple(_feature_from(f, "map") for f in (*msg.corners, *msg.edges)),
        poses=poses,
        notes=tuple(msg.notes),
        views=views,
        view_scans=tuple(int(v.scan_id) for v in msg.views),
    )
