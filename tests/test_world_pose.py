"""Where each scan was: the pose in ScanStart, its validation, /tf, `acquire --world` and `info`."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from mcap.reader import make_reader

from lelsonar import codec, poses
from lelsonar.cli.main import main as lelsonar_main
from lelsonar.errors import DecodeError, InvalidMessageError, NonFiniteValueError
from lelsonar.geometry import matrix_from_quaternion
from lelsonar.log import recording
from lelsonar.sim.odometry import simulate_odometry
from lelsonar.sim.world import Odometry, Pose2

from .conftest import simulated_messages

WORLD = """
[room]
ceiling = 2.5

[[wall]]
from = [0.0, 0.0]
to = [3.0, 0.0]
[[wall]]
from = [3.0, 0.0]
to = [3.0, 2.0]
[[wall]]
from = [3.0, 2.0]
to = [0.0, 2.0]
[[wall]]
from = [0.0, 2.0]
to = [0.0, 0.0]

[scanner]
mount = "fan"
height = 0.3
steps = 24

[odometry]
heading_drift = 2.0
seed = 3

[[pose]]
x = 1.0
y = 1.0
heading = 30.0

[[pose]]
x = 2.0
y = 1.2
heading = 0.0
"""


def _pose(**kw) -> poses.PoseWithCovariance:
    args = {"frame_id": "odom", "position": (1.0, 2.0, 0.3), "orientation": (0.0, 0.0, 0.0, 1.0)}
    args.update(kw)
    return poses.pose_message(args["frame_id"], args["position"], args["orientation"], args.get("covariance"))


def test_a_pose_is_validated_when_decoded():
    cov = np.diag([0.01, 0.01, 0.0, 0.0, 0.0, 0.004])
    start = simulated_messages(steps=4)[0]
    start.pose.CopyFrom(_pose(covariance=cov))
    back = codec.decode(start.SerializeToString(), codec.ScanStart)
    got = poses.scan_pose(back)
    assert got.known and got.frame_id == "odom"
    np.testing.assert_array_equal(got.position, [1.0, 2.0, 0.3])
    np.testing.assert_array_equal(got.covariance, cov)
    bad = {
        "frame_id": ("no spaces", InvalidMessageError),
        "orientation": ((0.0, 0.0, 0.1, 1.0), InvalidMessageError),  # norm 1.005
        "position": ((math.nan, 0.0, 0.0), NonFiniteValueError),
    }
    for field_name, (value, error) in bad.items():
        msg = codec.ScanStart()
        msg.CopyFrom(start)
        p = msg.pose
        if field_name == "frame_id":
            p.frame_id = value
        elif field_name == "orientation":
            p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w = value
        else:
            p.position.x, p.position.y, p.position.z = value
        with pytest.raises(error):
            codec.decode(msg.SerializeToString(), codec.ScanStart)
    asym = cov.copy()
    asym[0, 1] = 0.005
    negative = np.diag([0.01, -0.01, 0, 0, 0, 0])
    for c, words in ((asym, "not symmetric"), (negative, "positive semi-definite")):
        msg = codec.ScanStart()
        msg.CopyFrom(start)
        del msg.pose.covariance[:]
        msg.pose.covariance.extend(c.reshape(-1).tolist())
        with pytest.raises(InvalidMessageError, match=words):
            codec.decode(msg.SerializeToString(), codec.ScanStart)
    msg.pose.covariance.append(0.0)
    with pytest.raises(InvalidMessageError, match="holds 37 numbers"):
        codec.decode(msg.SerializeToString(), codec.ScanStart)


def test_a_scan_without_a_pose_reads_as_the_origin_and_says_so():
    start = simulated_messages(steps=4)[0]
    assert not start.HasField("pose")
    got = poses.scan_pose(start)
    assert not got.known and got.covariance is None
    np.testing.assert_array_equal(got.position, [0.0, 0.0, 0.0])
    assert "no pose" in got.note


def test_odometry_messages_round_trip_and_need_a_pose():
    msg = codec.Odometry(schema_version=1, scanner_id="s1", time_ns=5)
    with pytest.raises(DecodeError, match="carries no pose"):
        codec.decode(msg.SerializeToString(), codec.Odometry)
    msg.pose.CopyFrom(_pose())
    assert codec.decode(msg.SerializeToString(), codec.Odometry) == msg


def test_odometry_is_exact_at_the_start_and_its_covariance_grows_with_the_path():
    poses = tuple(Pose2(x=float(i), y=0.0, heading=0.0) for i in range(6))
    model = Odometry(translation_noise=0.05, rotation_noise=0.02, heading_drift=0.01, heading_noise=0.02, seed=1)
    odo = simulate_odometry(poses, model)
    assert (odo[0].x, odo[0].y, odo[0].heading) == (0.0, 0.0, 0.0)
    assert not odo[0].covariance.any()
    variances = [np.trace(o.covariance) for o in odo]
    assert all(b > a for a, b in zip(variances, variances[1:]))
    # Straight ahead along x: the distance's variance is (σ_t·d)² summed, d = 1 m per leg (the heading's
    # variance adds to x only through the sine of the few milliradians the odometry's heading is off).
    assert odo[5].covariance[0, 0] == pytest.approx(5 * 0.05**2, rel=1e-3)
    for o in odo:
        assert np.min(np.linalg.eigvalsh(o.covariance)) >= -1e-15
    # Seeded: the same seed gives the same path.
    again = simulate_odometry(poses, model)
    assert [(o.x, o.y, o.heading) for o in again] == [(o.x, o.y, o.heading) for o in odo]


def _compose(transforms, parent: str, child: str):
    """Chain /tf from ``parent`` to ``child``: rotation and translation of child in parent."""
    by_child = {t.child_frame_id: t for t in transforms}
    chain = []
    frame = child
    while frame != parent:
        t = by_child[frame]
        chain.append(t)
        frame = t.parent_frame_id
    rot, trans = np.eye(3), np.zeros(3)
    for t in reversed(chain):
        r = matrix_from_quaternion((t.rotation.x, t.rotation.y, t.rotation.z, t.rotation.w))
        trans = trans + rot @ np.array([t.translation.x, t.translation.y, t.translation.z])
        rot = rot @ r
    return rot, trans


def test_acquire_world_records_one_scan_per_pose_with_its_pose_on_scan_start_and_tf(tmp_path, capsys):
    world = tmp_path / "w.toml"
    world.write_text(WORLD)
    out = tmp_path / "out"
    rc = lelsonar_main(["acquire", "--device", "sim", "--world", str(world), "--out", str(out), "--no-zenoh"])
    assert rc == 0
    paths = sorted(out.glob("*.mcap"))
    assert [p.name for p in paths] == ["scan-1.mcap", "scan-2.mcap"]
    capsys.readouterr()
    assert lelsonar_main(["info", *map(str, paths), "--json"]) == 0
    infos = [json.loads(line) for line in capsys.readouterr().out.splitlines() if line.strip()]
    truth = [(1.0, 1.0, math.radians(30.0)), (2.0, 1.2, 0.0)]
    for path, info, (x, y, heading) in zip(paths, infos, truth):
        (scan,) = info["scans"]
        pose = scan["pose"]
        assert pose["known"] and pose["frame_id"] == "odom" and scan["status"] == "complete"
        meta = info["metadata"]["lelsonar.config"]
        assert json.loads(meta["truth_pose"]) == pytest.approx({"x": x, "y": y, "heading": heading, "frame_id": "map"})
        # Which element set each reading: one per step and capsule, an index into the element list.
        elements = json.loads(meta["truth_elements"])
        which = np.array(json.loads(meta["truth_echo_element"]))
        assert which.shape == (24, 4) and which.max() < len(elements) and (which >= 0).mean() > 0.5
        starts = [m for m in recording.read_messages(path) if isinstance(m, codec.ScanStart)]
        tfs = []
        with open(path, "rb") as f:
            for _schema, _channel, message in make_reader(f).iter_messages(topics=["/tf"]):
                tfs.append(FrameTransform.FromString(message.data))
        frames = {(t.parent_frame_id, t.child_frame_id) for t in tfs}
        assert {("map", "odom"), ("odom", "base_link"), ("base_link", "world"), ("world", "array")} <= frames
        # The chain map → odom → base_link → world is the ScanStart's pose.
        rot, trans = _compose([t for t in tfs if t.child_frame_id != "array"], "map", "world")
        p = poses.scan_pose(starts[0])
        np.testing.assert_allclose(trans, p.position, atol=1e-9)
        np.testing.assert_allclose(rot, matrix_from_quaternion(p.orientation), atol=1e-9)
        # The fan mount: the array's x (the rotation axis) is vertical and its γ = 0 beam along the heading.
        np.testing.assert_allclose(rot[:, 0], [0, 0, 1], atol=1e-9)
        assert pose["z"] == pytest.approx(0.3)
        assert pose["heading"] == pytest.approx(math.atan2(rot[1, 1], rot[0, 1]))
    # Foxglove draws the world as truth and the scan's pose.
    with open(paths[0], "rb") as f:
        scenes = [
            SceneUpdate.FromString(m.data) for _s, _c, m in make_reader(f).iter_messages(topics=["/lelsonar/world"])
        ]
    ids = {(e.frame_id, e.id.split("/")[-1]) for u in scenes for e in u.entities}
    assert ("map", "truth") in ids and ("odom", "pose") in ids
    drawn = next(e for u in scenes for e in u.entities if e.id == "world/truth")
    assert len(drawn.cubes) == 4 and len(drawn.arrows) == 2
    # The first pose is where the odometry starts: exact, no covariance.
    first = infos[0]["scans"][0]["pose"]
    assert (first["x"], first["y"], first["heading"]) == pytest.approx(truth[0])
    assert not any(first["covariance"])
    # The second is the odometry's, off by its drift, with a covariance that says by how much.
    second = infos[1]["scans"][0]["pose"]
    cov = np.array(second["covariance"]).reshape(6, 6)
    assert cov[0, 0] > 0 and cov[5, 5] > 0
    assert abs(second["heading"] - truth[1][2]) < 4 * math.sqrt(cov[5, 5])


def test_an_old_recording_without_a_pose_lists_the_origin_with_a_note(tmp_path, capsys):
    path = tmp_path / "old.mcap"
    with recording.McapRecorder(path) as rec:
        for msg in simulated_messages(steps=4):
            rec.write(msg)
    assert lelsonar_main(["info", str(path), "--json"]) == 0
    (scan,) = json.loads(capsys.readouterr().out)["scans"]
    assert scan["pose"]["known"] is False and "no pose" in scan["pose"]["note"]
    assert (scan["pose"]["x"], scan["pose"]["y"], scan["pose"]["z"]) == (0.0, 0.0, 0.0)


def test_acquire_world_errors_are_one_line(tmp_path, capsys):
    world = tmp_path / "w.toml"
    world.write_text(WORLD)
    assert lelsonar_main(["acquire", "--device", "emulated", "--world", str(world), "--no-zenoh"]) != 0
    err = capsys.readouterr().err.strip()
    assert "--world needs --device sim" in err and "Traceback" not in err
    assert lelsonar_main(["acquire", "--device", "sim", "--world", str(tmp_path / "nope.toml"), "--no-zenoh"]) != 0
    err = capsys.readouterr().err.strip()
    assert "does not exist" in err and "Traceback" not in err


def _odometry(scanner_id="scanner1", yaw=math.pi / 2, cov=None) -> bytes:
    msg = codec.Odometry(schema_version=1, scanner_id=scanner_id, time_ns=1)
    msg.pose.CopyFrom(
        poses.pose_message("odom", (1.0, 2.0, 0.0), (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)), cov)
    )
    return msg.SerializeToString()


def test_a_robot_s_odometry_becomes_the_array_s_pose_through_the_mount():
    from lelsonar.acquire.odometry import OdometryFollower
    from lelsonar.keys import ScannerKeys

    follower = OdometryFollower(None, ScannerKeys("lelsonar", "scanner1"), max_age=1.0)
    pose, why = follower.pose_for_scan("fan", 0.3, now_ns=10)
    assert pose is None and "no odometry received on lelsonar/scanner1/odom" in why
    assert not follower.offer(b"\x00garbage", 5) and follower.rejected == 1
    assert not follower.offer(_odometry("other"), 5) and follower.rejected == 2
    # Base at (1, 2) facing +y; roll variance s² about x, yaw variance t².
    s2, t2 = 0.01**2, 0.02**2
    cov = np.diag([0.04, 0.09, 0.0, s2, 0.0, t2])
    assert follower.offer(_odometry(cov=cov), 1_000_000_000)
    pose, why = follower.pose_for_scan("fan", 0.3, now_ns=1_500_000_000)
    assert why == ""
    got = poses.scan_pose(codec.ScanStart(pose=pose))
    np.testing.assert_allclose(got.position, [1.0, 2.0, 0.3], atol=1e-12)
    rot = matrix_from_quaternion(got.orientation)
    # Fan: the rotation axis up, the γ = 0 beam along the base's heading (+y), γ = 90° to its left (−x).
    np.testing.assert_allclose(rot, [[0, 0, -1], [0, 1, 0], [1, 0, 0]], atol=1e-12)
    # A roll δθ about x moves the array, 0.3 m up, by δθ × (0, 0, 0.3) = (0, −0.3 δθ, 0): y gains 0.09·s².
    expected = cov.copy()
    expected[1, 1] += 0.3**2 * s2
    expected[1, 3] = expected[3, 1] = -0.3 * s2
    np.testing.assert_allclose(got.covariance, expected, atol=1e-15)
    stale, why = follower.pose_for_scan("fan", 0.3, now_ns=3_000_000_000)
    assert stale is None and "2.0 s old" in why
