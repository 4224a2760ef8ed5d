"""`lelsonar export --format rosbag2`: the bag read back with rosbags' AnyReader, checked against the source Samples.

The truth is the recording itself (the Samples' γ, ranges and times, the
ScanStart's capsules) and the paper's formulas written out here, not the code
under test.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.interfaces import QosDurability

from lelsonar import codec
from lelsonar.bridge.ros2 import read_bag, typestore
from lelsonar.cli.main import main
from lelsonar.log.recording import McapRecorder

from .conftest import simulated_messages

CAPSULES = 4


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> tuple[Path, list]:
    path = tmp_path_factory.mktemp("src") / "scan.mcap"
    messages = simulated_messages("paper-test1", seed=3)
    for step in (10, 11, 120):  # a few missed echoes, as a real rig has: Range says +inf, no point
        miss = messages[1 + step].sensors[2]
        miss.echo_valid, miss.distance, miss.time_of_flight = False, 0.0, 0.0
    with McapRecorder(path, metadata={"preset": "paper-test1", "device": "sim"}) as rec:
        for m in messages:
            rec.write(m)
    return path, messages


@pytest.fixture(scope="module")
def bag(recording, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("out") / "bag"
    assert main(["export", str(recording[0]), "-o", str(out), "--format", "rosbag2"]) == 0
    return out


@pytest.fixture(scope="module")
def messages(bag) -> list:
    return read_bag(bag)


def by_topic(messages, topic):
    return [(t, m) for top, _, t, m in messages if top == topic]


def stamp_ns(header) -> int:
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


def samples_of(source):
    return [m for m in source if isinstance(m, codec.Sample)]


def rotate(q, v):
    """Rotate v by the unit quaternion q = (x, y, z, w): v + 2w(u×v) + 2u×(u×v)."""
    u, w = np.array(q[:3]), q[3]
    v = np.asarray(v, dtype=float)
    return v + 2 * w * np.cross(u, v) + 2 * np.cross(u, np.cross(u, v))


def test_topics_types_counts_and_qos(bag, recording):
    samples = samples_of(recording[1])
    expected = {
        "/tf_static": ("tf2_msgs/msg/TFMessage", 1),
        "/tf": ("tf2_msgs/msg/TFMessage", len(samples)),
        "/lelsonar/points/raw": ("sensor_msgs/msg/PointCloud2", len(samples)),
        "/lelsonar/points/corrected": ("sensor_msgs/msg/PointCloud2", 1),
        "/lelsonar/planes": ("visualization_msgs/msg/MarkerArray", 1),
        "/lelsonar/estimate": ("std_msgs/msg/String", 1),
        **{f"/lelsonar/range/capsule{i}": ("sensor_msgs/msg/Range", len(samples)) for i in range(CAPSULES)},
    }
    with AnyReader([bag], default_typestore=typestore("jazzy")) as reader:
        got = {c.topic: (c.msgtype, c.msgcount) for c in reader.connections}
        qos = {c.topic: c.ext.offered_qos_profiles[0] for c in reader.connections}
        digests = {c.topic: c.digest for c in reader.connections}
        assert reader.message_count == sum(n for _, n in expected.values())
    assert got == expected
    assert qos["/tf_static"].durability == QosDurability.TRANSIENT_LOCAL and qos["/tf_static"].depth == 1
    assert qos["/tf"].durability == QosDurability.VOLATILE
    # metadata.yaml's type_description_hash, as Jazzy's `ros2 topic info -v /tf` prints it
    assert digests["/tf"] == "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"
    assert "version: 9" in (bag / "metadata.yaml").read_text()
    assert (bag / "bag.mcap").is_file()


def test_tf_is_the_measured_rotation_of_every_step(messages, recording):
    samples = samples_of(recording[1])
    tfs = by_topic(messages, "/tf")
    assert len(tfs) == len(samples)
    for (t, msg), sample in zip(tfs, samples):
        (tf,) = msg.transforms
        assert t == sample.acquisition_time_ns == stamp_ns(tf.header)
        assert (tf.header.frame_id, tf.child_frame_id) == ("s1/axis", "s1/array")
        q = tf.transform.rotation
        g = sample.gamma_measured
        # about +x by γ: the array's +y (the beams at γ = 0) goes to (0, cos γ, sin γ)
        assert np.allclose(rotate((q.x, q.y, q.z, q.w), (0, 1, 0)), (0, math.cos(g), math.sin(g)), atol=1e-12)


def test_tf_static_places_each_capsule_facing_its_boresight(messages, recording):
    start = recording[1][0]
    ((t, msg),) = by_topic(messages, "/tf_static")
    assert t == start.start_time_ns
    frames = {tf.child_frame_id: tf for tf in msg.transforms}
    assert frames["s1/axis"].header.frame_id == "s1/base"
    for c in start.capsules:
        tf = frames[f"s1/capsule{c.capsule_id}"]
        assert tf.header.frame_id == "s1/array"
        tr, q = tf.transform.translation, tf.transform.rotation
        assert (tr.x, tr.y, tr.z) == pytest.approx((c.position.x, c.position.y, c.position.z))
        # REP 117: a Range measures along the sensor frame's +x
        assert np.allclose(rotate((q.x, q.y, q.z, q.w), (1, 0, 0)), (c.boresight.x, c.boresight.y, c.boresight.z))


def test_ranges_are_the_sample_distances(messages, recording):
    start = recording[1][0]
    samples = samples_of(recording[1])
    for i in range(CAPSULES):
        ranges = by_topic(messages, f"/lelsonar/range/capsule{i}")
        for (t, r), sample in zip(ranges, samples, strict=True):
            reading = next(s for s in sample.sensors if s.capsule_id == i)
            assert stamp_ns(r.header) == t == sample.acquisition_time_ns
            assert r.header.frame_id == f"s1/capsule{i}" and r.radiation_type == 0  # ULTRASOUND
            if reading.echo_valid:
                assert r.range == np.float32(reading.distance)
            else:
                assert r.range == math.inf
            assert r.field_of_view == np.float32(math.radians(70))
            t0 = reading.waveform.t0
            assert r.min_range == pytest.approx(start.sound_speed * t0 / 2, rel=1e-6)
            assert r.max_range == pytest.approx(
                start.sound_speed * (t0 + start.window_samples / start.sample_rate) / 2, rel=1e-6
            )
    assert sum(not s.echo_valid for sample in samples for s in sample.sensors) == 3


def cloud_rows(msg) -> dict[str, np.ndarray]:
    kinds = {7: "<f4", 6: "<u4", 2: "u1"}
    raw = np.asarray(msg.data, dtype=np.uint8).tobytes()
    assert len(raw) == msg.point_step * msg.width == msg.row_step
    dt = np.dtype(
        {
            "names": [f.name for f in msg.fields],
            "formats": [kinds[f.datatype] for f in msg.fields],
            "offsets": [f.offset for f in msg.fields],
            "itemsize": msg.point_step,
        }
    )
    arr = np.frombuffer(raw, dtype=dt)
    return {n: arr[n] for n in dt.names}


def test_raw_cloud_accumulates_the_eq9_points_of_the_scan(messages, recording):
    start = recording[1][0]
    samples = samples_of(recording[1])
    xs = {c.capsule_id: c.position.x for c in start.capsules}
    r = start.radial_offset
    expected = []
    for sample in samples:
        g = sample.gamma_measured
        for s in sample.sensors:
            if s.echo_valid:  # eq. (9): the capsule rotated about x, plus d along the boresight
                expected.append(
                    (
                        xs[s.capsule_id],
                        r * math.cos(g) + s.distance * math.cos(g),
                        r * math.sin(g) + s.distance * math.sin(g),
                        sample.step,
                        s.capsule_id,
                    )
                )
    clouds = by_topic(messages, "/lelsonar/points/raw")
    assert [m.width for _, m in clouds] == list(
        np.cumsum([sum(s.echo_valid for s in sample.sensors) for sample in samples])
    )
    t, last = clouds[-1]
    assert last.header.frame_id == "s1/base" and last.height == 1 and not last.is_bigendian
    rows = cloud_rows(last)
    got = np.column_stack([rows["x"], rows["y"], rows["z"]])
    exp = np.array(expected)
    assert np.array_equal(rows["step"], exp[:, 3]) and np.array_equal(rows["capsule"], exp[:, 4])
    assert np.allclose(got, exp[:, :3], atol=2e-6)


def test_corrected_points_follow_the_paper_correction(messages, recording):
    """§4: a point of subset a sits at y = r cos γ + d, of subset b at z = r sin γ + d."""
    start = recording[1][0]
    samples = {s.step: s for s in samples_of(recording[1])}
    by_x = {round(c.position.x, 6): c.capsule_id for c in start.capsules}
    ((_, msg),) = by_topic(messages, "/lelsonar/points/corrected")
    rows = cloud_rows(msg)
    estimate = json.loads(by_topic(messages, "/lelsonar/estimate")[0][1].data)
    crit = estimate["critical_step"]
    assert msg.width > 100 and set(np.unique(rows["subset"])) == {0, 1}
    r = start.radial_offset
    for x, y, z, step, subset in zip(rows["x"], rows["y"], rows["z"], rows["step"], rows["subset"]):
        sample = samples[int(step)]
        g = sample.gamma_measured
        d = next(s.distance for s in sample.sensors if s.capsule_id == by_x[round(float(x), 6)])
        if subset == 0:
            assert step < crit and y == pytest.approx(r * math.cos(g) + d, abs=2e-6)
        else:
            assert step > crit and z == pytest.approx(r * math.sin(g) + d, abs=2e-6)
    assert 0.5 < rows["inlier"].mean() <= 1.0


def test_estimate_and_markers(messages, recording):
    from lelsonar.sim import preset
    from lelsonar.sim.scan import true_planes

    samples = samples_of(recording[1])
    ((t, msg),) = by_topic(messages, "/lelsonar/estimate")
    est = json.loads(msg.data)
    assert t == recording[1][-1].end_time_ns
    assert (est["scanner_id"], int(est["scan_id"]), est["status"]) == ("s1", 1, "final")
    assert est["samples_used"] == len(samples)
    assert {(p["method"], p["label"]) for p in est["planes"]} == {(m, lab) for m in ("corner", "ls") for lab in "ab"}

    ((_, arr),) = by_topic(messages, "/lelsonar/planes")
    markers = arr.markers
    assert markers[0].action == 3  # DELETEALL first: a new scan replaces the last one
    planes = {p["method"] + p["label"]: p for p in est["planes"]}
    patches = [m for m in markers if m.ns.startswith("plane/")]
    assert len(patches) == 4
    for m in patches:
        p = est["planes"][m.id]
        assert m.ns == f"plane/{p['method']}" and m.type == 11 and len(m.points) % 3 == 0
        n = np.array([p["normal"][k] for k in "xyz"])
        for v in m.points:  # every vertex is on the estimated plane n·v = h
            assert np.dot(n, (v.x, v.y, v.z)) == pytest.approx(p["offset"], abs=1e-9)
    truth = {tp.label: tp for tp in true_planes(preset("paper-test1"))}
    drawn = [m for m in markers if m.ns == "truth"]
    assert len(drawn) == len(truth)
    for m, tp in zip(drawn, truth.values()):
        assert {(round(v.x, 9), round(v.y, 9), round(v.z, 9)) for v in m.points} == {
            tuple(np.round(c, 9)) for c in tp.corners
        }
    for label in "ab":  # and the estimate is close to the truth the sim drew
        n = np.array([planes["corner" + label]["normal"][k] for k in "xyz"])
        assert math.degrees(math.acos(min(1.0, abs(n @ truth[label].normal)))) < 2.0
    (edge,) = [m for m in markers if m.ns == "edge"]
    e = est["corner_edge"]
    mid = np.mean([(v.x, v.y, v.z) for v in edge.points], axis=0)
    assert np.allclose(mid, [e["point"][k] for k in "xyz"])


def test_existing_output_and_bad_input_fail_cleanly(tmp_path, recording, capsys):
    out = tmp_path / "bag"
    out.mkdir()
    assert main(["export", str(recording[0]), "-o", str(out)]) == 2
    assert "already exists" in capsys.readouterr().err
    text = tmp_path / "notes.mcap"
    text.write_text("not an mcap\n" * 10)
    assert main(["export", str(text), "-o", str(tmp_path / "bag2")]) == 2
    assert "lelsonar export: error:" in capsys.readouterr().err
    assert not (tmp_path / "bag2").exists()


def test_humble_bag_is_version_8_without_range_variance(tmp_path):
    path = tmp_path / "short.mcap"
    with McapRecorder(path) as rec:
        for m in simulated_messages("paper-test1", seed=1, steps=40):
            rec.write(m)
    out = tmp_path / "humble"
    assert main(["export", str(path), "-o", str(out), "--distro", "humble", "--no-truth"]) in (0, 1)
    assert "version: 8" in (out / "metadata.yaml").read_text()
    rng = [m for top, _, _, m in read_bag(out, "humble") if top == "/lelsonar/range/capsule0"]
    assert len(rng) == 40 and not hasattr(rng[0], "variance")


def test_bag_mcap_is_what_rosbag2s_mcap_plugin_reads(bag):
    """Read with the plain `mcap` reader: ros2msg schemas, cdr channels, offered QoS in channel metadata."""
    from mcap.reader import make_reader

    with open(bag / "bag.mcap", "rb") as f:
        summary = make_reader(f).get_summary()
    assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
    assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}
    names = {s.name for s in summary.schemas.values()}
    assert {"tf2_msgs/msg/TFMessage", "sensor_msgs/msg/Range", "visualization_msgs/msg/MarkerArray"} <= names
    (static,) = [c for c in summary.channels.values() if c.topic == "/tf_static"]
    assert "durability: transient_local" in static.metadata["offered_qos_profiles"]
