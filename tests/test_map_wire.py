"""The ``Map`` a planner gets over Zenoh says what ``map --json`` says, per piece; its decode is bounded and typed."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from lelsonar.errors import (
    DecodeError,
    InvalidMessageError,
    NonFiniteValueError,
    PayloadTooLargeError,
    SchemaVersionError,
)
from lelsonar.map.fusion import WallMapper
from lelsonar.map.result import FusedFeature, map_to_dict
from lelsonar.map.synthetic import NoiseModel, maze, observe_world
from lelsonar.map.wire import MapLimits, decode_map, map_from_message, map_message
from lelsonar.v1 import map_pb2


def _feature(point, kind, source, walls=(), scans=()) -> FusedFeature:
    return FusedFeature(
        point=np.array(point, dtype=float),
        direction=np.array([0.0, 0.0, 1.0]) if kind != "horizontal" else np.array([1.0, 0.0, 0.0]),
        kind="concave" if kind == "horizontal" else kind,
        point_stderr=0.004,
        source=source,
        observations=len(scans) or 2,
        walls=walls,
        scans=scans,
    )


@pytest.fixture(scope="module")
def fused():
    """A maze fused from its scans (walls seen in pieces with gaps), with a corner, an edge and a horizontal
    corner of each source added: every key the JSON has."""
    world = maze(5, np.random.default_rng(0))
    scans, _, _ = observe_world(world, NoiseModel(), np.random.default_rng(0))
    mapper = WallMapper()
    for s in scans:
        mapper.add_scan(s)
    m = mapper.snapshot()
    assert any(len(w.pieces) > 1 for w in m.walls), "the maze should leave a wall seen in pieces"
    ids = tuple(w.id for w in m.walls[:2])
    return dataclasses.replace(
        m,
        features=(
            _feature([1.0, 2.0, 0.3], "concave", "walls", walls=ids),
            _feature([0.5, -1.0, 0.3], "edge", "observed", scans=(1, 2)),
        ),
        horizontal=(_feature([0.0, 1.0, 0.0], "horizontal", "observed", scans=(2, 3)),),
    )


def _same(a, b, where="map"):
    """JSON values equal: numbers to 1e-9 (the pieces' ends go through the wire as points), the rest exactly."""
    if isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for k in a:
            _same(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, list):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            _same(x, y, f"{where}[{i}]")
    elif isinstance(a, float) and not isinstance(b, str):
        assert b == pytest.approx(a, abs=1e-9), where
    else:
        assert a == b, where


def test_the_map_on_the_wire_says_what_the_json_says_per_piece(fused):
    json_map = map_to_dict(fused)
    payload = map_message(fused, "s1", stamp_ns=1).SerializeToString()
    received = map_to_dict(map_from_message(decode_map(payload)))
    _same(json_map, received)
    # Per piece, independently of the wall it belongs to: its own extent and scans.
    pieces = [w for w in json_map["walls"] if len(w["pieces"]) > 1]
    assert pieces and any(p["scans"] != p["wall_scans"] for p in pieces)
    assert [h["source"] for h in received["horizontal_corners"]] == ["observed"]
    assert {c["source"] for c in received["corners"] + received["edges"]} == {"walls", "observed"}


def test_a_map_from_an_older_writer_reads_with_the_wall_s_scans_for_each_piece(fused):
    msg = map_message(fused, "s1", stamp_ns=1)
    for w in msg.walls:
        w.ClearField("piece_scans")
    for f in (*msg.corners, *msg.edges):
        f.ClearField("source")
    msg.ClearField("horizontal_corners")
    back = map_to_dict(map_from_message(decode_map(msg.SerializeToString())))
    assert all(w["scans"] == w["wall_scans"] for w in back["walls"])
    assert {c["source"] for c in back["corners"] + back["edges"]} == {"map"}
    assert back["horizontal_corners"] == []
    assert len(back["walls"]) == len(map_to_dict(fused)["walls"])


def _message(fused) -> map_pb2.Map:
    return map_message(fused, "s1", stamp_ns=1)


def test_a_received_map_is_bounded_and_every_field_checked(fused):
    with pytest.raises(PayloadTooLargeError, match="MapLimits"):
        decode_map(_message(fused).SerializeToString(), MapLimits(max_payload_bytes=100))
    with pytest.raises(PayloadTooLargeError, match="map walls"):
        decode_map(_message(fused).SerializeToString(), MapLimits(max_walls=2))
    with pytest.raises(PayloadTooLargeError, match="pieces"):
        decode_map(_message(fused).SerializeToString(), MapLimits(max_pieces=1))
    with pytest.raises(InvalidMessageError, match="not a lelsonar.v1.Map"):
        decode_map(b"\xff\xff\xff")
    msg = _message(fused)
    msg.schema_version = 2
    with pytest.raises(SchemaVersionError, match="version 2"):
        decode_map(msg.SerializeToString())
    msg = _message(fused)
    msg.walls[0].pieces[0].x = math.nan
    with pytest.raises(NonFiniteValueError, match="pieces"):
        decode_map(msg.SerializeToString())
    msg = _message(fused)
    wall = next(w for w in msg.walls if len(w.piece_scans) > 1)
    del wall.piece_scans[0]
    with pytest.raises(InvalidMessageError, match="one per piece"):
        decode_map(msg.SerializeToString())
    msg = _message(fused)
    msg.horizontal_corners[0].direction.x = 2.0
    with pytest.raises(InvalidMessageError, match="horizontal_corners.*unit"):
        decode_map(msg.SerializeToString())
    msg = _message(fused)
    msg.views[0].polygon.add(x=math.inf)
    with pytest.raises(DecodeError, match="views"):
        decode_map(msg.SerializeToString())
