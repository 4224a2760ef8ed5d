"""The map in every viewer, against independent truth: the ROS 2 grid's cells are occupied where the true
walls run and its geometry is the floor plan's; the markers, the Foxglove scene and the Rerun recording hold
every wall with its σ and verdict, growing scan by scan; `map --rrd/--mcap/--ros2-bag/--screenshot` writes
them and refuses to overwrite."""

from __future__ import annotations

from collections import Counter, defaultdict
from pathlib import Path

import numpy as np
import pytest
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from google.protobuf.json_format import MessageToJson, Parse
from mcap.reader import make_reader
from rerun.chunk import RrdReader
from shapely.geometry import LineString

from lelsonar.bridge import ros2
from lelsonar.bridge.ros2_map import TOPIC_GRID, TOPIC_WALLS, map_ros_messages
from lelsonar.cli.main import main
from lelsonar.draw.estimates import SIGMA_BAND
from lelsonar.draw.map_scene import MapScene, wall_entity_id
from lelsonar.draw.palette import quality_color
from lelsonar.map import floorplan as fp
from lelsonar.map.fusion import WallMapper
from lelsonar.map.synthetic import NoiseModel, observe_world, room
from lelsonar.map.wire import map_from_message, map_message
from lelsonar.view.rerun_layout import make_recording
from lelsonar.view.rerun_map import log_map

PLAN = fp.PlanConfig(resolution=0.05)


@pytest.fixture(scope="module")
def room_maps():
    """A room (independent truth) fused scan by scan: each step's map and the world."""
    world = room()
    scans, _, _ = observe_world(world, NoiseModel(), np.random.default_rng(5))
    mapper = WallMapper()
    steps = []
    for s in scans:
        mapper.add_scan(s)
        steps.append(mapper.snapshot())
    return world, steps


def test_the_ros2_grid_is_the_floor_plan_s_and_occupied_where_the_true_walls_run(room_maps):
    world, steps = room_maps
    m = steps[-1]
    b = ros2.Builder("jazzy")
    out = {r.topic: r for r in map_ros_messages(b, m, 10, PLAN)}
    grid = ros2.deserialize(ros2.serialize(out[TOPIC_GRID].message, ros2.OCCUPANCY_GRID), ros2.OCCUPANCY_GRID)
    want = fp.occupancy_grid(m, PLAN)
    assert (grid.info.width, grid.info.height) == (want.width, want.height)
    assert grid.info.resolution == pytest.approx(PLAN.resolution)
    assert (grid.info.origin.position.x, grid.info.origin.position.y) == pytest.approx(want.origin)
    assert grid.header.frame_id == "map"
    data = np.asarray(grid.data, dtype=np.int8).reshape(grid.info.height, grid.info.width)
    assert np.array_equal(data, want.data)
    # Independent truth: every occupied cell lies on a true wall (within the fused walls' error and a cell),
    # and most cells along the true walls' observed stretches are occupied.
    x, y = want.centres()
    occupied = np.argwhere(data == fp.OCCUPIED)
    assert len(occupied) > 0
    truth = [LineString(seg) for seg in world.segments]
    tol = PLAN.resolution + 0.05
    from shapely.geometry import Point

    off = [min(t.distance(Point(x[r, c], y[r, c])) for t in truth) for r, c in occupied]
    assert max(off) < tol
    # And where a fused wall says a true wall runs, the grid holds it: the true wall's point nearest each
    # piece's middle is in an occupied cell or next to one.
    for w in m.walls:
        for seg in w.piece_segments:
            mid = Point(*(0.5 * (seg[0] + seg[1])))
            nearest = min(truth, key=lambda t: t.distance(mid))
            p = nearest.interpolate(nearest.project(mid))
            r, c = want.cell(p.x, p.y)
            assert (data[max(r - 1, 0) : r + 2, max(c - 1, 0) : c + 2] == fp.OCCUPIED).any()
    assert (data == fp.FREE).sum() > 0 and (data == fp.UNKNOWN).sum() > 0


def test_the_wall_markers_are_as_thick_as_each_wall_s_two_sigma_band_and_coloured_by_verdict(room_maps):
    _, steps = room_maps
    m = steps[-1]
    b = ros2.Builder("jazzy")
    out = {r.topic: r for r in map_ros_messages(b, m, 10, PLAN)}
    markers = ros2.deserialize(ros2.serialize(out[TOPIC_WALLS].message, ros2.MARKERS), ros2.MARKERS).markers
    assert markers[0].action == 3  # DELETEALL: a map update replaces the last
    walls = [mk for mk in markers if mk.ns == "walls"]
    pieces = [(w, seg) for w in m.walls for seg in w.piece_segments]
    assert len(walls) == len(pieces)
    for mk, (w, seg) in zip(walls, pieces):
        assert mk.scale.y == pytest.approx(max(0.01, 2 * SIGMA_BAND * w.offset_stderr))
        assert mk.scale.x == pytest.approx(max(0.01, float(np.hypot(*(seg[1] - seg[0])))))
        assert round(mk.color.r * 255) == pytest.approx(quality_color(w.quality)[0], abs=1)
    assert sum(mk.ns == "path" for mk in markers) == 1


def test_a_map_message_rebuilds_the_walls_and_path_of_its_map_and_frees_only_the_way(room_maps):
    _, steps = room_maps
    m = steps[-1]
    back = map_from_message(map_message(m, "s", stamp_ns=1))
    assert [w.id for w in back.walls] == [w.id for w in m.walls]
    for a, w in zip(back.walls, m.walls):
        for sa, sw in zip(a.piece_segments, w.piece_segments):
            assert sa == pytest.approx(sw, abs=1e-9)
        assert a.quality == w.quality and a.offset_stderr == pytest.approx(w.offset_stderr)
    full, rebuilt = fp.occupancy_grid(m, PLAN), fp.occupancy_grid(back, PLAN)
    assert np.array_equal(full.data == fp.OCCUPIED, rebuilt.data == fp.OCCUPIED)
    # Without the views, nothing is free that the full map does not call free.
    assert not np.any((rebuilt.data == fp.FREE) & (full.data != fp.FREE))


def test_the_foxglove_map_scene_grows_and_drops_the_walls_that_are_gone(room_maps):
    _, steps = room_maps
    scene = MapScene()
    seen = []
    for i, m in enumerate(steps):
        msg = map_message(m, "s", stamp_ns=i + 1)
        update = scene.update(msg, free_space=fp.free_space(m, PLAN))
        back = SceneUpdate()
        back.ParseFromString(update.SerializeToString())
        assert Parse(MessageToJson(back), SceneUpdate()) == back
        ids = {e.id for e in back.entities}
        assert {wall_entity_id("s", w.id) for w in m.walls if w.pieces} <= ids
        assert "s/map/free_space" in ids and "s/map/path" in ids
        assert {d.id for d in back.deletions}.isdisjoint(ids)
        seen.append(len(m.walls))
        for w in msg.walls:
            ent = next(e for e in back.entities if e.id == wall_entity_id("s", w.id))
            assert ent.cubes[0].size.y == pytest.approx(max(0.01, 2 * SIGMA_BAND * w.offset_stderr))
    assert seen[-1] >= seen[0]


def test_the_rerun_map_holds_every_wall_at_each_scan(room_maps, tmp_path: Path):
    _, steps = room_maps
    path = tmp_path / "map.rrd"
    rec = make_recording(recording_id="map")
    rec.save(path)
    for m in steps:
        log_map(rec, map_message(m, "s", stamp_ns=1), free_space=fp.free_space(m, PLAN))
    rec.flush()
    rec.disconnect()
    rows: dict[str, list] = defaultdict(list)
    for chunk in RrdReader(path).store().stream().to_chunks():
        batch = chunk.to_record_batch()
        scans = batch.column("scans").to_pylist() if "scans" in batch.schema.names else [None] * batch.num_rows
        rows[str(chunk.entity_path)] += scans
    last = steps[-1]
    for w in last.walls:
        assert len(steps) in rows[f"/map/fused/walls/{w.id}"]
    assert set(range(1, len(steps) + 1)) <= set(rows["/map/fused/path/corrected"])
    assert "/map/fused/free_space" in rows and "/map/fused/free_space/outline" in rows


def test_map_writes_every_viewer_output_and_refuses_to_overwrite(two_scans, tmp_path, capsys):
    rrd, mcap, bag, png = tmp_path / "m.rrd", tmp_path / "m.mcap", tmp_path / "bag", tmp_path / "m.png"
    args = ["map", "--source", *map(str, two_scans), "--json"]
    views = ["--rrd", str(rrd), "--mcap", str(mcap), "--ros2-bag", str(bag), "--screenshot", str(png)]
    assert main([*args, *views]) == 0
    capsys.readouterr()
    assert png.stat().st_size > 0
    with open(mcap, "rb") as f:
        topics = Counter(ch.topic for _, ch, _ in make_reader(f).iter_messages())
    assert topics["/lelsonar/map"] == topics["/lelsonar/map/scene"] == 2  # one map a scan
    bag_topics = Counter(t for t, *_ in ros2.read_bag(bag))
    assert bag_topics == {"/map": 2, "/lelsonar/map/walls": 2}
    assert any("/map/fused/walls" in str(c.entity_path) for c in RrdReader(rrd).store().stream().to_chunks())
    # `export` of a map recording: the grid and the walls of each recorded map, the same as --ros2-bag's.
    exported = tmp_path / "exported"
    assert main(["export", str(mcap), "-o", str(exported)]) == 0
    capsys.readouterr()
    a, b = ros2.read_bag(exported), ros2.read_bag(bag)
    assert Counter(t for t, *_ in a) == bag_topics
    grids_a = [m for t, _, _, m in a if t == "/map"]
    grids_b = [m for t, _, _, m in b if t == "/map"]
    for ga, gb in zip(grids_a, grids_b):  # the Map carries no views: the walls match, cell for cell
        da, db = np.asarray(ga.data).reshape(ga.info.height, -1), np.asarray(gb.data).reshape(gb.info.height, -1)
        assert da.shape == db.shape and np.array_equal(da == fp.OCCUPIED, db == fp.OCCUPIED)
    for flag, path in (("--rrd", rrd), ("--ros2-bag", bag)):
        assert main([*args, flag, str(path)]) == 2
        err = capsys.readouterr().err
        assert "--overwrite" in err and err.count("\n") == 1
    assert main([*args, "--rrd", str(rrd), "--overwrite"]) == 0


def test_the_live_foxglove_map_view_serves_each_map_as_a_scene(room_maps):
    import json
    import struct

    from websockets.sync.client import connect

    from lelsonar.bridge.foxglove import SUBPROTOCOLS, open_foxglove_map
    from lelsonar.draw.map_scene import TOPIC_MAP_SCENE

    _, steps = room_maps
    msg = map_message(steps[-1], "s", stamp_ns=5)
    with open_foxglove_map("127.0.0.1:0") as view:
        with connect(view.server.url, subprotocols=list(SUBPROTOCOLS), open_timeout=30, max_size=None) as ws:
            channels: dict[int, dict] = {}
            while TOPIC_MAP_SCENE not in {c["topic"] for c in channels.values()}:
                op = json.loads(ws.recv(timeout=30))
                if op["op"] == "advertise":
                    channels.update({c["id"]: c for c in op["channels"]})
            cid = next(i for i, c in channels.items() if c["topic"] == TOPIC_MAP_SCENE)
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 1, "channelId": cid}]}))
            assert view.server.wait_for_subscribers([TOPIC_MAP_SCENE], timeout=30)
            view(msg, fp.free_space(steps[-1], PLAN))
            frame = ws.recv(timeout=30)
            while isinstance(frame, str):
                frame = ws.recv(timeout=30)
    sid, log_time = struct.unpack_from("<IQ", frame, 1)
    assert (sid, log_time) == (1, 5)
    scene = SceneUpdate.FromString(frame[13:])
    assert {wall_entity_id("s", w.id) for w in msg.walls if w.pieces} | {"s/map/free_space"} <= {
        e.id for e in scene.entities
    }


def test_the_live_ros2_bridge_republishes_each_map_as_rmw_zenoh_grid_and_markers(room_maps, tmp_path):
    import threading

    import zenoh

    from lelsonar.bridge import rmw_zenoh as rz
    from lelsonar.bridge.ros2_map import MapRos2, MapSubscription
    from lelsonar.net.transport import hermetic_settings, open_session

    _, steps = room_maps
    m = steps[-1]
    msg = map_message(m, "s", stamp_ns=7)
    key = f"0/map/{rz.dds_type_name(ros2.OCCUPANCY_GRID)}/{ros2.type_hash(ros2.OCCUPANCY_GRID)}"
    got: list[tuple[bytes, bytes | None]] = []
    seen = threading.Event()

    def on_grid(s: zenoh.Sample) -> None:
        got.append((s.payload.to_bytes(), s.attachment.to_bytes() if s.attachment is not None else None))
        seen.set()

    walls_key = f"0/lelsonar/map/walls/{rz.dds_type_name(ros2.MARKERS)}/{ros2.type_hash(ros2.MARKERS)}"
    walls_seen = threading.Event()

    sock = tmp_path / "z.sock"
    with open_session(hermetic_settings(sock, listen=True)) as robot:
        robot.declare_subscriber(key, on_grid)
        robot.declare_subscriber(walls_key, lambda _s: walls_seen.set())
        with (
            rz.open_ros_session(hermetic_settings(sock, listen=False)) as bridge_session,
            rz.RmwZenohNode(bridge_session, name="lelsonar_bridge") as node,
            MapSubscription(bridge_session, "lelsonar", MapRos2(node.publish)) as sub,
        ):
            mapper = robot.declare_publisher("lelsonar/map")
            matched = threading.Event()
            listener = mapper.declare_matching_listener(lambda status: status.matching and matched.set())
            assert matched.wait(30) or mapper.matching_status.matching, "the bridge never subscribed"
            listener.undeclare()
            mapper.put(b"not a map")  # counted and logged, and the subscription goes on
            mapper.put(msg.SerializeToString())
            assert seen.wait(30), "no OccupancyGrid arrived"
            assert walls_seen.wait(30), "no MarkerArray arrived"  # published after the grid
            assert set(node.publishers) == {"/map", "/lelsonar/map/walls"}
            assert node.publishers["/map"].key == key
            assert sub.errors == {"InvalidMessageError": 1} and sub.received == 1
    payload, att = got[0]
    assert att is not None and len(att) == 33
    grid = ros2.deserialize(payload, ros2.OCCUPANCY_GRID)
    # The grid drawn from the Map is the fused map's, cell for cell.
    want = fp.occupancy_grid(map_from_message(msg))
    assert (grid.info.width, grid.info.height) == (want.width, want.height)
    data = np.asarray(grid.data, dtype=np.int8).reshape(want.height, want.width)
    assert np.array_equal(data, want.data)
    assert np.array_equal(data == fp.OCCUPIED, fp.occupancy_grid(m).data == fp.OCCUPIED)
