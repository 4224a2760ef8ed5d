"""The ROS 2 live bridge: rmw_zenoh key expressions, RIHS01 hashes, tokens, attachments and CDR bytes.

There is no ROS 2 install here.  Every expected value below is copied from a
published source (named next to it), or written out by hand from the XCDR1
rules, never computed by the code under test.
"""

from __future__ import annotations

import math
import struct
import threading

import numpy as np
import pytest
import zenoh
import zenoh.ext

from lelsonar import codec
from lelsonar.bridge import rmw_zenoh as rz
from lelsonar.bridge import ros2
from lelsonar.errors import ClosedError, ConfigError
from lelsonar.log.recording import McapRecorder
from lelsonar.net.transport import hermetic_settings, open_session

from .conftest import simulated_messages

# ros2/rmw_zenoh docs/design.md and shared/design.md §12 (std_msgs/String);
# `ros2 topic info -v /tf` on Jazzy (TFMessage); rcl test_type_hash.cpp, "copied directly from
# generated code", and `ros2 topic info -v` on Jazzy (PointCloud2); `ros2 topic info -v` of a
# Jazzy Range publisher (Range, with `variance`).
PUBLISHED_HASHES = {
    "std_msgs/msg/String": "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18",
    "tf2_msgs/msg/TFMessage": "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087",
    "sensor_msgs/msg/PointCloud2": "RIHS01_9198cabf7da3796ae6fe19c4cb3bdd3525492988c70522628af5daa124bae2b5",
    "sensor_msgs/msg/Range": "RIHS01_b42b62562e93cbfe9d42b82fe5994dfa3d63d7d5c90a317981703f7388adff3a",
    # a third-party Jazzy client's constant; no first-party listing found
    "visualization_msgs/msg/MarkerArray": "RIHS01_86cb8800b6fb05b5eff1abd7a56f62a5641d3ae9a1c29e78e67e704f1d067dcf",
}


@pytest.mark.parametrize("msgtype", sorted(PUBLISHED_HASHES))
def test_type_hashes_are_ros2s_published_values(msgtype):
    assert ros2.type_hash(msgtype, "jazzy") == PUBLISHED_HASHES[msgtype]


def test_key_and_tokens_match_rmw_zenohs_design_doc_examples():
    h = PUBLISHED_HASHES["std_msgs/msg/String"]
    assert rz.topic_key(0, "/chatter", "std_msgs/msg/String", h) == "0/chatter/std_msgs::msg::dds_::String_/" + h
    assert rz.topic_key(3, "/robot1/chatter", "std_msgs/msg/String", h).startswith("3/robot1/chatter/std_msgs::")
    # verbatim from docs/design.md
    assert (
        rz.node_token(0, "aac3178e146ba6f1fc6e6a4085e77f21", 0, "/", "listener")
        == "@ros2_lv/0/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
    )
    assert rz.publisher_token(
        0,
        "8b20917502ee955ac4476e0266340d5c",
        0,
        10,
        "/",
        "talker",
        "/chatter",
        "std_msgs/msg/String",
        h,
        ros2.TopicQos(7),
    ) == (
        "@ros2_lv/0/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/"
        "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18/::,7:,:,:,,"
    )
    # tf2's /tf (depth 100) as a public rmw_zenoh client writes it
    assert rz.qos_chunk(ros2.TopicQos(100)) == "::,100:,:,:,,"
    # robot_state_publisher's latched /robot_description token, as a public rmw_zenoh client's test
    # quotes it: TRANSIENT_LOCAL (enum value 1), depth 1
    assert rz.publisher_token(
        0,
        "2e44",
        0,
        13,
        "/",
        "robot_state_publisher",
        "/robot_description",
        "std_msgs/msg/String",
        "RIHS01_df668c",
        ros2.TopicQos(1, transient_local=True),
    ) == (
        "@ros2_lv/0/2e44/0/13/MP/%/%/robot_state_publisher/%robot_description/std_msgs::msg::dds_::String_/"
        "RIHS01_df668c/:1:,1:,:,:,,"
    )
    assert rz.qos_chunk(ros2.TopicQos(42)) == "::,:,:,:,,"
    assert rz.mangle("/robot1/ns") == "%robot1%ns" and rz.mangle("") == "%"


def test_attachment_is_zenohs_own_serialisation_of_seq_time_gid():
    gid = bytes(range(16))
    att = rz.attachment(1, 0x0102030405060708, gid)
    # by hand: i64 LE, i64 LE, LEB128(16) = 0x10, 16 bytes
    assert att.hex() == "0100000000000000" + "0807060504030201" + "10" + gid.hex()
    # and zenoh-ext's serializer (the one zenoh-cpp's serializer mirrors) agrees byte for byte
    ref = zenoh.ext.z_serialize(
        (zenoh.ext.Int64(1), zenoh.ext.Int64(0x0102030405060708), [zenoh.ext.UInt8(b) for b in gid])
    )
    assert att == ref.to_bytes()
    assert rz.parse_attachment(att) == (1, 0x0102030405060708, gid)


def test_gid_is_the_one_rmw_zenoh_derives():
    """A talker token hashed by rmw_zenoh_cpp's own simplified_xxhash3.cpp, as a public client's test quotes it."""
    token = (
        "@ros2_lv/0/abcdef0123456789abcdef0123456789/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/"
        "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18/::,7:,:,:,,"
    )
    assert rz.gid_of(token).hex() == "5d93eb0aa1fed6741fd0751922ffa030"


def test_cdr_bytes_match_hand_serialisation():
    b = ros2.Builder("jazzy")
    # std_msgs/String "hello": encapsulation CDR_LE, u32 length with the NUL, the bytes
    assert (
        ros2.serialize(b("std_msgs/msg/String", data="hello"), "std_msgs/msg/String").hex() == "00010000"
        "06000000"
        "68656c6c6f00"
    )
    # sensor_msgs/Range (Jazzy): Header{Time{i32 sec, u32 nanosec}, string frame_id}, u8 radiation_type,
    # then five float32 aligned to 4 (from the start of the payload, after the encapsulation)
    r = b(
        "sensor_msgs/msg/Range",
        header=b.header(1_000_000_002, "a"),
        radiation_type=0,
        field_of_view=0.5,
        min_range=0.1,
        max_range=2.0,
        range=1.5,
        variance=0.0,
    )
    expected = (
        bytes.fromhex("00010000")
        + struct.pack("<iI", 1, 2)
        + struct.pack("<I", 2)
        + b"a\0"
        + b"\0"
        + b"\0"
        + struct.pack("<5f", 0.5, 0.1, 2.0, 1.5, 0.0)
    )
    data = ros2.serialize(r, "sensor_msgs/msg/Range")
    assert data == expected
    back = ros2.deserialize(data, "sensor_msgs/msg/Range")
    assert (back.header.stamp.sec, back.header.stamp.nanosec, back.header.frame_id) == (1, 2, "a")
    assert back.range == np.float32(1.5)


def test_names_are_validated():
    with pytest.raises(ConfigError):
        rz.dds_type_name("String")
    with pytest.raises(ConfigError):
        rz.attachment(1, 1, b"short")


@pytest.fixture
def recording(tmp_path):
    path = tmp_path / "scan.mcap"
    messages = simulated_messages("paper-test1", seed=2, steps=60)
    with McapRecorder(path, metadata={"preset": "paper-test1", "device": "sim"}) as rec:
        for m in messages:
            rec.write(m)
    return path, messages


def test_bridge_publishes_rmw_zenoh_samples_and_tokens(tmp_path, recording):
    """A replay through the bridge, seen from a plain Zenoh peer as rmw_zenoh would see it."""
    from lelsonar.reconstruct.stream.config import ReconstructConfig
    from lelsonar.reconstruct.stream.replay import replay_mcap
    from lelsonar.reconstruct.stream.service import ReconstructionService

    path, source = recording
    samples = [m for m in source if isinstance(m, codec.Sample)]
    sock = tmp_path / "z.sock"
    got: list[tuple[str, bytes, bytes | None]] = []
    tokens: set[str] = set()
    lock = threading.Lock()
    estimate_seen = threading.Event()
    tokens_seen = threading.Event()

    def on_data(s: zenoh.Sample) -> None:
        key = str(s.key_expr)
        with lock:
            got.append((key, s.payload.to_bytes(), s.attachment.to_bytes() if s.attachment is not None else None))
        if key.startswith("0/lelsonar/estimate/"):
            estimate_seen.set()

    def on_token(s: zenoh.Sample) -> None:
        with lock:
            tokens.add(str(s.key_expr))
            if sum("/MP/" in k for k in tokens) >= 10:
                tokens_seen.set()

    with open_session(hermetic_settings(sock, listen=True)) as robot:
        robot.declare_subscriber("0/**", on_data)
        robot.liveliness().declare_subscriber("@ros2_lv/0/**", on_token, history=True)
        with (
            rz.open_ros_session(hermetic_settings(sock, listen=False)) as bridge_session,
            rz.RmwZenohNode(bridge_session, name="lelsonar_bridge") as node,
        ):
            view = ros2.Ros2View(node.publish, main_method="corner")
            service = ReconstructionService(
                ReconstructConfig(compare_methods=("ls",), provisional=False), observer=view
            )
            replay_mcap(path, service)
            assert estimate_seen.wait(30), "no estimate arrived"
            assert tokens_seen.wait(30), f"tokens: {tokens}"
            zid = node.zid
            pubs = node.publishers

            # a late joiner gets the latched /tf_static from the publisher's cache
            late: list[bytes] = []
            late_seen = threading.Event()

            def on_late(s: zenoh.Sample) -> None:
                late.append(s.payload.to_bytes())
                late_seen.set()

            late_sub = zenoh.ext.declare_advanced_subscriber(
                robot, pubs["/tf_static"].key, on_late, history=zenoh.ext.HistoryConfig(detect_late_publishers=True)
            )
            assert late_seen.wait(30), "the /tf_static cache did not answer a late subscriber"
            late_sub.undeclare()

    assert f"@ros2_lv/0/{zid}/0/0/NN/%/%/lelsonar_bridge" in tokens
    per_key: dict[str, list[tuple[bytes, bytes]]] = {}
    for key, payload, att in got:
        assert att is not None and len(att) == 33, key  # rmw_zenoh drops samples without one
        per_key.setdefault(key, []).append((payload, att))

    for topic, pub in pubs.items():
        msgtype = pub.msgtype
        h = PUBLISHED_HASHES.get(msgtype)
        if h is not None:
            assert pub.key.endswith("/" + h)
        assert pub.key == f"0/{topic[1:]}/{rz.dds_type_name(msgtype)}/{ros2.type_hash(msgtype)}"
        (token,) = [t for t in tokens if f"/MP/%/%/lelsonar_bridge/{rz.mangle(topic)}/" in t]
        chunks = token.split("/")
        assert chunks[:3] == ["@ros2_lv", "0", zid] and chunks[3] == "0" and chunks[5] == "MP"
        assert chunks[10:12] == [rz.dds_type_name(msgtype), ros2.type_hash(msgtype)]
        assert chunks[12] == rz.qos_chunk(ros2.topic_qos(topic))
        seqs = [rz.parse_attachment(a) for _, a in per_key[pub.key]]
        assert [s for s, _, _ in seqs] == list(range(1, len(seqs) + 1))  # per publisher, from 1
        assert {g for _, _, g in seqs} == {rz.gid_of(token)}

    tf = per_key[pubs["/tf"].key]
    assert len(tf) == len(samples)
    for (payload, _), sample in zip(tf, samples):
        assert payload[:4] == bytes.fromhex("00010000")
        (t,) = ros2.deserialize(payload, "tf2_msgs/msg/TFMessage").transforms
        q = t.transform.rotation
        assert (q.x, q.w) == pytest.approx((math.sin(sample.gamma_measured / 2), math.cos(sample.gamma_measured / 2)))
        assert t.header.stamp.sec * 10**9 + t.header.stamp.nanosec == sample.acquisition_time_ns
    ranges = per_key[pubs["/lelsonar/range/capsule1"].key]
    assert [ros2.deserialize(p, "sensor_msgs/msg/Range").range for p, _ in ranges] == [
        np.float32(next(s.distance for s in smp.sensors if s.capsule_id == 1)) for smp in samples
    ]
    assert ros2.deserialize(late[0], "tf2_msgs/msg/TFMessage").transforms[0].child_frame_id == "s1/axis"


def test_ros2_bridge_command_bridges_a_live_scan(tmp_path):
    """`lelsonar ros2-bridge` as a process: lelsonar samples in, ROS 2 topics out, on one Zenoh network."""
    import os
    import subprocess
    import sys

    from lelsonar.keys import ScannerKeys

    source = simulated_messages("paper-test1", seed=4, steps=50)
    endpoint = f"unixsock-stream/{tmp_path}/z.sock"
    keys = ScannerKeys("lelsonar", "s1")
    up, estimate = threading.Event(), threading.Event()
    tokens: list[str] = []
    estimates: list[bytes] = []

    def on_token(s: zenoh.Sample) -> None:
        tokens.append(str(s.key_expr))
        if str(s.key_expr).endswith("/alive/ros2-bridge"):
            up.set()

    def on_estimate(s: zenoh.Sample) -> None:
        estimates.append(s.payload.to_bytes())
        estimate.set()

    with open_session(hermetic_settings(tmp_path / "z.sock", listen=True)) as robot:
        robot.liveliness().declare_subscriber("lelsonar/**", on_token, history=True)
        robot.liveliness().declare_subscriber("@ros2_lv/**", on_token, history=True)  # `**` skips `@` chunks
        robot.declare_subscriber("0/lelsonar/estimate/**", on_estimate)
        proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "lelsonar",
                "ros2-bridge",
                "--until-scans",
                "1",
                "--node-name",
                "sonar",
                "--namespace",
                "/robot7",
                "--mode",
                "client",
                "--connect",
                endpoint,
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env={**os.environ, "COLUMNS": "120"},
        )
        try:
            assert up.wait(60), f"the bridge did not come up: {tokens}"
            sample_pub = robot.declare_publisher(keys.sample, congestion_control=zenoh.CongestionControl.BLOCK)
            for m in source:
                payload = m.SerializeToString()
                enc = zenoh.Encoding(codec.encoding_name(m))
                if isinstance(m, codec.Sample):
                    sample_pub.put(payload, encoding=enc)
                else:
                    robot.put(keys.scan, payload, encoding=enc)
            assert estimate.wait(60), "no estimate on the ROS 2 key"
            out, err = proc.communicate(timeout=60)
        finally:
            proc.kill()
    assert proc.returncode == 0, err
    assert any(t.startswith("@ros2_lv/0/") and t.endswith("/NN/%/%robot7/sonar") for t in tokens), tokens
    assert any("/MP/%/%robot7/sonar/%lelsonar%estimate/std_msgs::msg::dds_::String_/" in t for t in tokens)
    final = [e for e in estimates if b'"status":"final"' in e]
    assert len(final) == 1
    text = ros2.deserialize(final[0], "std_msgs/msg/String").data
    assert '"samples_used":50' in text and '"scanner_id":"s1"' in text


def test_publishers_are_declared_as_rmw_zenoh_declares_its_own():
    """rmw_zenoh (rmw_publisher_data.cpp): every publisher advanced; DROP for KEEP_LAST, so a slow ROS
    subscriber never stalls the bridge; TRANSIENT_LOCAL adds a cache of depth samples, publisher detection
    and sample-miss detection by sporadic heartbeat (0.5 s)."""
    import zenoh.ext

    from lelsonar.bridge import ros2
    from lelsonar.bridge.rmw_zenoh import SAMPLE_MISS_HEARTBEAT_PERIOD, publisher_options

    assert SAMPLE_MISS_HEARTBEAT_PERIOD == 0.5
    for topic in (*ros2.TOPIC_QOS, "/lelsonar/points"):
        qos = ros2.topic_qos(topic)
        options = publisher_options(qos)
        assert options["congestion_control"] == zenoh.CongestionControl.DROP
        assert options["reliability"] == zenoh.Reliability.RELIABLE
        if qos.transient_local:
            assert options["publisher_detection"] is True
            assert isinstance(options["cache"], zenoh.ext.CacheConfig)
            assert isinstance(options["sample_miss_detection"], zenoh.ext.MissDetectionConfig)
        else:
            assert not {"cache", "publisher_detection", "sample_miss_detection"} & set(options)


def test_a_node_closed_while_a_thread_publishes_refuses_further_messages_with_one_typed_error(tmp_path):
    """A subscription's callback may still be publishing as the bridge shuts down: the close waits for the put
    in flight, and every later publish is a ClosedError, never Zenoh's "Already borrowed" or a re-declaration."""
    b = ros2.Builder("jazzy")
    message = ros2.RosMessage("/chatter", "std_msgs/msg/String", 0, b("std_msgs/msg/String", data="hello"))
    sock = tmp_path / "z.sock"
    published = threading.Event()
    outcome: list[BaseException | None] = []

    def publish_until_refused(node: rz.RmwZenohNode) -> None:
        try:
            while True:
                node.publish(message)
                published.set()
        except BaseException as exc:  # noqa: BLE001 (what ended the loop is the test's subject)
            outcome.append(exc)

    with (
        open_session(hermetic_settings(sock, listen=True)),
        rz.open_ros_session(hermetic_settings(sock, listen=False)) as session,
    ):
        node = rz.RmwZenohNode(session, name="racer")
        publisher = threading.Thread(target=publish_until_refused, args=(node,))
        publisher.start()
        assert published.wait(30), "the thread published nothing"
        node.close()
        publisher.join(30)
        assert not publisher.is_alive()
        assert len(outcome) == 1 and isinstance(outcome[0], ClosedError), repr(outcome)
        assert node.publishers == {}
        node.close()  # (a second close is a no-op)
