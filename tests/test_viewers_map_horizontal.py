"""The map's horizontal corners (where a wall meets the floor) in every viewer: a room whose scans see one
wall's foot on the floor, fused; the Rerun recording, the Foxglove scene in an MCAP, the ROS 2 markers in a
bag each hold every horizontal corner at its point with its ± 2σ, apart from the corners."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from mcap.reader import make_reader
from mcap_protobuf.writer import Writer
from rerun.chunk import RrdReader

from lelsonar.bridge import ros2
from lelsonar.bridge.ros2_map import TOPIC_WALLS, map_ros_messages
from lelsonar.draw.map_scene import TOPIC_MAP_SCENE, MapScene
from lelsonar.draw.palette import HORIZONTAL_CORNER_COLOR
from lelsonar.map.fusion import WallMapper
from lelsonar.map.observation import FeatureObservation
from lelsonar.map.synthetic import NoiseModel, observe_world, room
from lelsonar.map.wire import map_message
from lelsonar.view.rerun_layout import make_recording
from lelsonar.view.rerun_map import log_map

#: m: the floor, below the scanner.
FLOOR = -0.3
#: m: a scan's own σ of the foot's point across its line.
FOOT_SIGMA = 0.01


@pytest.fixture(scope="module")
def foot_map():
    """A room fused from its scans, three of which (facing the wall y = 0) also see that wall meet the floor:
    a line along x at z = FLOOR, reported in each scan's sensor frame from its true pose."""
    world = room()
    scans, _, _ = observe_world(world, NoiseModel(), np.random.default_rng(3))
    for k, pose in enumerate(world.poses):
        if abs(pose[2]) > 1e-9:
            continue
        # Sensor frame from the true pose (heading 0): the wall's foot nearest the scanner, along x.
        foot = FeatureObservation(
            point=[0.0, -pose[1], FLOOR - scans[k].pose.z], direction=[1.0, 0.0, 0.0], point_stderr=FOOT_SIGMA
        )
        scans[k] = replace(scans[k], features=(foot,))
    mapper = WallMapper()
    for s in scans:
        mapper.add_scan(s)
    m = mapper.snapshot()
    assert m.horizontal, "the wall's foot is a horizontal corner"
    assert all(abs(c.direction[2]) > 0.9 for c in m.corners), "the plan's corners stand upright"
    assert all(len(f.scans) >= 2 for f in m.horizontal)
    # Independent truth: the foot lies on y = 0, z = FLOOR, within its σ (the scans' own and the poses').
    for f in m.horizontal:
        assert abs(f.point[1]) <= 3 * f.point_stderr and f.point[2] == pytest.approx(FLOOR, abs=1e-9)
    return m, map_message(m, "s", stamp_ns=1)


def test_the_rerun_map_holds_each_horizontal_corner_at_its_point(foot_map, tmp_path: Path):
    _, msg = foot_map
    path = tmp_path / "map.rrd"
    rec = make_recording(recording_id="map")
    rec.save(path)
    log_map(rec, msg)
    rec.flush()
    rec.disconnect()
    positions, radii = [], []
    for chunk in RrdReader(path).store().stream().to_chunks():
        if str(chunk.entity_path) != "/map/fused/horizontal_corners":
            continue
        batch = chunk.to_record_batch()
        for name in batch.schema.names:
            if name.endswith(":positions"):
                positions += [p for row in batch.column(name).to_pylist() for p in row]
            elif name.endswith(":radii"):
                radii += [r for row in batch.column(name).to_pylist() for r in row]
    want = msg.horizontal_corners
    assert len(positions) == len(want) >= 1
    for p, r, f in zip(positions, radii, want):
        assert p == pytest.approx([f.point.x, f.point.y, 0.0], abs=1e-6)  # on the plan, as the corners
        assert r == pytest.approx(max(2.0 * f.point_stderr, 0.03), rel=1e-6)


def test_the_foxglove_map_scene_in_an_mcap_draws_each_horizontal_corner(foot_map, tmp_path: Path):
    _, msg = foot_map
    path = tmp_path / "map.mcap"
    with open(path, "wb") as out:
        writer = Writer(out)
        writer.write_message(TOPIC_MAP_SCENE, MapScene().update(msg, 1), log_time=1, publish_time=1)
        writer.finish()
    with open(path, "rb") as f:
        [(_, _, message)] = list(make_reader(f).iter_messages(topics=[TOPIC_MAP_SCENE]))
    scene = SceneUpdate.FromString(message.data)
    [features] = [e for e in scene.entities if e.id == "s/map/features"]
    rgb = tuple(c / 255 for c in HORIZONTAL_CORNER_COLOR)
    spheres = [s for s in features.spheres if (s.color.r, s.color.g, s.color.b) == pytest.approx(rgb)]
    lines = [ln for ln in features.lines if (ln.color.r, ln.color.g, ln.color.b) == pytest.approx(rgb)]
    want = msg.horizontal_corners
    assert len(spheres) == len(lines) == len(want) >= 1
    for s, line, f in zip(spheres, lines, want):
        p = np.array([f.point.x, f.point.y, f.point.z])
        assert [s.pose.position.x, s.pose.position.y, s.pose.position.z] == pytest.approx(p, abs=1e-9)
        assert s.size.x == pytest.approx(max(4.0 * f.point_stderr, 0.03))  # ± 2σ
        a, b = (np.array([q.x, q.y, q.z]) for q in line.points)
        along = (b - a) / np.linalg.norm(b - a)
        assert abs(float(along @ [f.direction.x, f.direction.y, f.direction.z])) == pytest.approx(1.0)
        assert 0.5 * (a + b) == pytest.approx(p, abs=1e-9)
    keys = [kv.key for kv in features.metadata]
    assert keys.count("horizontal corner concave") == len(want)


def test_the_ros2_markers_in_a_bag_hold_each_horizontal_corner_apart(foot_map, tmp_path: Path):
    m, _ = foot_map
    bag = tmp_path / "bag"
    with ros2.open_bag(bag) as w:
        sink, b = ros2.BagSink(w, "jazzy"), ros2.Builder("jazzy")
        for out in map_ros_messages(b, m, 10):
            sink(out)
    [markers] = [msg for topic, _, _, msg in ros2.read_bag(bag) if topic == TOPIC_WALLS]
    drawn = [mk for mk in markers.markers if mk.ns == "horizontal_corners"]
    assert len(drawn) == len(m.horizontal) >= 1
    for mk, f in zip(drawn, m.horizontal):
        assert [mk.pose.position.x, mk.pose.position.y, mk.pose.position.z] == pytest.approx(f.point, abs=1e-9)
        assert mk.scale.x == pytest.approx(max(4.0 * f.point_stderr, 0.03))
        assert round(mk.color.b * 255) == HORIZONTAL_CORNER_COLOR[2]
    assert sum(mk.ns == "corners" for mk in markers.markers) == len(m.corners)
