"""The map as the contract's ``Map`` message (published on ``<prefix>/map``, recorded to MCAP)."""

from __future__ import annotations

import time

from lelsonar import codec
from lelsonar.map.result import FusedFeature, FusedMap
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
    return msg
