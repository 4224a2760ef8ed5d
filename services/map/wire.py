"""The map as the contract's ``Map`` message (published on ``<prefix>/map``, recorded to MCAP)."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
from google.protobuf.message import DecodeError as _ProtobufDecodeError

from lelsonar import codec
from lelsonar.checks import finite, finite_vector
from lelsonar.errors import ConfigError, InvalidMessageError, PayloadTooLargeError, SchemaVersionError
from lelsonar.map.lines import interval_on_line
from lelsonar.map.result import FusedFeature, FusedMap, FusedPose, FusedWall
from lelsonar.v1 import map_pb2

#: The contract version this module writes.
SCHEMA_VERSION = 1


@dataclass(frozen=True)
class MapLimits:
    """Bounds on everything in a received ``Map`` whose size comes from the wire.

    Parameters
    ----------
    max_payload_bytes : int
        Largest payload parsed at all.
    max_walls : int
        Most walls, and most poses.
    max_pieces : int
        Most observed pieces of one wall.
    max_scan_ids : int
        Most scan ids one wall, piece or feature lists.
    max_features : int
        Most corners, edges, and horizontal corners (each).
    max_views : int
        Most free-space views (one per wall observation).
    max_polygon : int
        Most corners of one view's polygon.
    max_reasons : int
        Most reasons per wall, and most notes.
    """

    max_payload_bytes: int = 32 * 1024 * 1024
    max_walls: int = 20_000
    max_pieces: int = 1_000
    max_scan_ids: int = 20_000
    max_features: int = 20_000
    max_views: int = 200_000
    max_polygon: int = 256
    max_reasons: int = 64

    def __post_init__(self) -> None:
        for name, value in vars(self).items():
            if value <= 0:
                raise ConfigError(f"MapLimits.{name} must be positive")


DEFAULT_MAP_LIMITS = MapLimits()


def _set(vec, xyz) -> None:
    vec.x, vec.y, vec.z = (float(v) for v in xyz)


def _feature(out: map_pb2.MapFeature, f: FusedFeature) -> None:
    _set(out.point, f.point)
    _set(out.direction, f.direction)
    out.kind = f.kind
    out.point_stderr = f.point_stderr
    out.observations = f.observations
    out.wall_ids.extend(f.walls)
    out.source = f.source
    out.scan_ids.extend(f.scans)


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
        if len(w.piece_scans) == len(w.pieces):
            for scans in w.piece_scans:
                out.piece_scans.add().scan_ids.extend(scans)
    for f in m.corners:
        _feature(msg.corners.add(), f)
    for f in m.edges:
        _feature(msg.edges.add(), f)
    for f in m.horizontal:
        _feature(msg.horizontal_corners.add(), f)
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


def decode_map(payload: bytes, limits: MapLimits = DEFAULT_MAP_LIMITS) -> map_pb2.Map:
    """A ``Map`` from its wire bytes: bounded before parsing, its contract version and every field checked
    (:func:`map_from_message`).

    Raises
    ------
    DecodeError
        A subclass naming what was wrong: too large, not a ``lelsonar.v1.Map``, another contract version, a
        field out of range or not finite.
    """
    if len(payload) > limits.max_payload_bytes:
        raise PayloadTooLargeError(
            f"a Map of {len(payload)} bytes exceeds the limit of {limits.max_payload_bytes} (MapLimits)"
        )
    msg = map_pb2.Map()
    try:
        msg.ParseFromString(bytes(payload))
    except _ProtobufDecodeError as exc:
        raise InvalidMessageError(f"not a lelsonar.v1.Map: {exc}") from None
    if msg.schema_version != SCHEMA_VERSION:
        raise SchemaVersionError(
            f"a Map of contract version {msg.schema_version}; this reader knows version {SCHEMA_VERSION} "
            "(upgrade the older side)"
        )
    map_from_message(msg, limits)
    return msg


def _bounded(what: str, n: int, limit: int) -> None:
    if n > limit:
        raise PayloadTooLargeError(f"{what}: {n} entries, more than the limit of {limit} (MapLimits)")


def _xyz(v, where: str) -> np.ndarray:
    finite_vector(where, v)
    return np.array([v.x, v.y, v.z], dtype=float)


def _matrix(values, n: int, what: str) -> np.ndarray:
    m = np.array(values, dtype=float)
    if m.size != n * n or not np.all(np.isfinite(m)):
        raise InvalidMessageError(f"{what} covariance must be {n * n} finite numbers, got {m.size}")
    return m.reshape(n, n)


def _feature_from(f: map_pb2.MapFeature, where: str, limits: MapLimits) -> FusedFeature:
    direction = _xyz(f.direction, f"{where}.direction")
    if abs(float(np.linalg.norm(direction)) - 1.0) > 1e-6:
        raise InvalidMessageError(f"{where}.direction is not a unit vector")
    finite(f"{where}.point_stderr", f.point_stderr)
    if len(f.kind) > 32 or len(f.source) > 32:
        raise InvalidMessageError(f"{where}: kind and source are names of at most 32 characters")
    _bounded(f"{where}.wall_ids", len(f.wall_ids), limits.max_walls)
    _bounded(f"{where}.scan_ids", len(f.scan_ids), limits.max_scan_ids)
    return FusedFeature(
        point=_xyz(f.point, f"{where}.point"),
        direction=direction,
        kind=f.kind,
        point_stderr=f.point_stderr,
        source=f.source or "map",
        observations=f.observations,
        walls=tuple(f.wall_ids),
        scans=tuple(int(s) for s in f.scan_ids),
    )


def _wall_from(w: map_pb2.MapWall, limits: MapLimits) -> FusedWall:
    where = f"map wall {w.id}"
    n = _xyz(w.normal, f"{where}.normal")
    if abs(float(np.linalg.norm(n[:2])) - 1.0) > 1e-6 or not math.isfinite(w.offset):
        raise InvalidMessageError(f"{where}: its normal must be a horizontal unit vector")
    finite(f"{where}.normal_stderr/offset_stderr", w.normal_stderr, w.offset_stderr)
    line = np.array([math.atan2(n[1], n[0]), w.offset])
    _bounded(f"{where}.pieces", len(w.pieces) // 2, limits.max_pieces)
    _bounded(f"{where}.extent", len(w.extent), 4)
    _bounded(f"{where}.scan_ids", len(w.scan_ids), limits.max_scan_ids)
    _bounded(f"{where}.quality_reasons", len(w.quality_reasons), limits.max_reasons)
    if len(w.pieces) % 2 or not w.pieces:
        raise InvalidMessageError(f"{where}: pieces must be end-point pairs, got {len(w.pieces)} points")
    if w.piece_scans and len(w.piece_scans) != len(w.pieces) // 2:
        raise InvalidMessageError(
            f"{where}: piece_scans lists {len(w.piece_scans)} pieces, pieces {len(w.pieces) // 2}; one per piece"
        )
    for k, scans in enumerate(w.piece_scans):
        _bounded(f"{where}.piece_scans[{k}]", len(scans.scan_ids), limits.max_scan_ids)
    ends = np.array([_xyz(p, f"{where}.pieces") for p in w.pieces])
    pieces = tuple(interval_on_line(line, ends[k : k + 2]) for k in range(0, len(ends), 2))
    zs = np.array([_xyz(p, f"{where}.extent")[2] for p in w.extent]) if w.extent else ends[:, 2]
    return FusedWall(
        id=w.id,
        line=line,
        covariance=_matrix(w.covariance, 2, where),
        interval=(min(p[0] for p in pieces), max(p[1] for p in pieces)),
        pieces=pieces,
        z_range=(float(zs.min()), float(zs.max())),
        quality=codec.QUALITY_NAME.get(w.quality, "unreliable"),
        reasons=tuple(w.quality_reasons),
        scans=tuple(int(s) for s in w.scan_ids),
        good_observations=w.good_observations,
        flagged_observations=w.flagged_observations,
        piece_scans=tuple(tuple(int(s) for s in p.scan_ids) for p in w.piece_scans),
    )


def map_from_message(msg: map_pb2.Map, limits: MapLimits = DEFAULT_MAP_LIMITS) -> FusedMap:
    """A received ``Map`` as the library's :class:`~lelsonar.map.result.FusedMap` (what the floor plan and the
    route take, and :func:`~lelsonar.map.result.map_to_dict` prints as ``map --json`` does); every table
    bounded by ``limits`` and every field checked, a wrong one a :class:`~lelsonar.errors.DecodeError`
    subclass naming it.  A map from an older writer (no piece scans, feature sources or horizontal corners)
    reads with those left empty."""
    _bounded("map walls", len(msg.walls), limits.max_walls)
    _bounded("map poses", len(msg.poses), limits.max_walls)
    for name, items in (("corners", msg.corners), ("edges", msg.edges), ("horizontal_corners", msg.horizontal_corners)):
        _bounded(f"map {name}", len(items), limits.max_features)
    _bounded("map views", len(msg.views), limits.max_views)
    _bounded("map notes", len(msg.notes), limits.max_reasons)
    walls = tuple(_wall_from(w, limits) for w in msg.walls)
    poses = []
    for p in msg.poses:
        where = f"map pose {p.scan_id}"
        finite(f"{where}.heading", p.heading)
        position = _xyz(p.position, f"{where}.position")
        odometry = _xyz(p.odometry, f"{where}.odometry")
        poses.append(
            FusedPose(
                scan_id=int(p.scan_id),
                x=float(position[0]),
                y=float(position[1]),
                z=float(position[2]),
                heading=p.heading,
                covariance=_matrix(p.covariance, 3, where),
                odometry=(float(odometry[0]), float(odometry[1]), float(odometry[2])),
            )
        )
    views = []
    for i, v in enumerate(msg.views):
        _bounded(f"map views[{i}].polygon", len(v.polygon), limits.max_polygon)
        views.append(np.array([_xyz(q, f"map views[{i}].polygon")[:2] for q in v.polygon]).reshape(-1, 2))
    features = tuple(
        _feature_from(f, f"map {name}[{i}]", limits)
        for name, items in (("corners", msg.corners), ("edges", msg.edges))
        for i, f in enumerate(items)
    )
    return FusedMap(
        walls=walls,
        features=features,
        poses=tuple(poses),
        notes=tuple(msg.notes),
        views=tuple(views),
        view_scans=tuple(int(v.scan_id) for v in msg.views),
        horizontal=tuple(
            _feature_from(f, f"map horizontal_corners[{i}]", limits) for i, f in enumerate(msg.horizontal_corners)
        ),
    )
