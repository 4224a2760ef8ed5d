"""`lelsonar map --source … --json` on recordings, and the adapter from the reconstruction's planes."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from lelsonar import codec
from lelsonar.cli.main import main
from lelsonar.log import recording
from lelsonar.map.from_reconstruction import observation_at, planar_pose, scan_from_reconstruction
from lelsonar.map.lines import line_in_world
from lelsonar.v1 import reconstruction_pb2 as pb
from tests.conftest import scene_truth, simulated_messages


def test_map_json_has_the_public_keys_and_the_wall_of_the_scene(two_scans, capsys, tmp_path):
    geo = tmp_path / "plan.geojson"
    assert main(["map", "--source", *map(str, two_scans), "--json", "--geojson", str(geo)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert {"walls", "corners", "edges", "poses"} <= set(out)
    assert [p["scan_id"] for p in out["poses"]] == [1, 2]
    for p in out["poses"]:
        assert {"scan_id", "x", "y", "z", "heading"} <= set(p)
    [wall] = out["walls"]  # plane b of the paper's L is the ceiling: not a wall of the floor plan
    assert {"normal", "offset", "extent", "quality", "normal_stderr", "offset_stderr"} <= set(wall)
    assert set(wall["normal"]) == {"x", "y", "z"} and all(set(p) == {"x", "y", "z"} for p in wall["extent"])
    assert wall["quality"] == "good" and wall["scans"] == [1, 2]
    normal, offset = scene_truth("paper-test1")["a"]
    n = np.array([wall["normal"][k] for k in "xyz"])
    # The recordings have no pose: the map's frame is the array frame (at the origin, unturned).
    assert math.acos(min(1.0, float(n @ normal))) < 4 * wall["normal_stderr"] + math.radians(0.5)
    assert abs(wall["offset"] - offset) < 4 * wall["offset_stderr"] + 0.005
    assert any("no pose" in note for note in out["notes"])
    # The L's edge is where the wall meets the ceiling: a line across the floor plan, not a corner of it.
    assert out["corners"] == []
    [corner] = out["horizontal_corners"]
    assert corner["kind"] == "concave" and abs(corner["direction"]["z"]) < 0.5 and corner["observations"] == 2
    assert json.loads(geo.read_text())["type"] == "FeatureCollection"


def test_map_refuses_a_scan_given_twice_and_a_missing_file_in_one_line(two_scans, capsys, tmp_path):
    assert main(["map", "--source", str(two_scans[0]), str(two_scans[0])]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "give each scan once" in err[0]
    assert main(["map", "--source", str(tmp_path / "none.mcap")]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1
    assert main(["map", "--source", str(two_scans[0]), "--goal", "x"]) == 2


def _plane(normal, offset, quality=pb.PLANE_QUALITY_GOOD, label="a") -> pb.PlaneEstimate:
    p = pb.PlaneEstimate(label=label, method="lel", offset=offset, normal_stderr=0.01, offset_stderr=0.002)
    p.normal.x, p.normal.y, p.normal.z = normal
    p.quality = quality
    n = np.asarray(normal, float)
    for q in (n * offset + [0.3, 0, 0.1], n * offset - [0.3, 0, 0.1]):
        p.patch.add(x=q[0], y=q[1], z=q[2])
    return p


def test_the_adapter_levels_planes_keeps_verdicts_and_leaves_out_floors():
    msg = codec.Reconstruction(scanner_id="s1", scan_id=4)
    msg.planes.extend(
        [
            _plane((0.0, 1.0, 0.0), 2.0),
            _plane((0.0, 0.0, 1.0), 1.1, label="b"),
            _plane((0.6, 0.8, 0.0), 1.5, pb.PLANE_QUALITY_UNRELIABLE, label="c"),
        ]
    )
    msg.planes[2].quality_reasons.append("residual too large")
    scan = scan_from_reconstruction(msg, None, "lel")
    # No ScanStart: the origin, the array frame unturned; the beams at γ = 0 look along +y (heading 90°).
    assert scan.pose.heading == pytest.approx(math.pi / 2)
    assert [w.label for w in scan.walls] == ["a", "c"]
    a, c = scan.walls
    np.testing.assert_allclose(a.line, [0.0, 2.0], atol=1e-12)  # straight ahead in the level frame
    assert c.quality == "unreliable" and c.reasons == ("residual too large",)
    assert any("horizontal" in n for n in scan.notes) and any("origin" in n for n in scan.notes)


def test_the_adapter_carries_the_parameter_covariance_to_theta_rho():
    """θ = n / d (the paper's parameters) with its covariance, to (azimuth, offset): against finite differences."""
    rng = np.random.default_rng(3)
    n = np.array([0.6, 0.8, 0.0])
    d = 1.7
    m = rng.normal(size=(3, 3))
    c_theta = 1e-6 * (m @ m.T + np.eye(3))
    msg = codec.Reconstruction(scanner_id="s1", scan_id=1)
    p = _plane(tuple(n), d)
    p.theta_covariance.extend(c_theta.ravel().tolist())
    msg.planes.append(p)
    [wall] = scan_from_reconstruction(msg, None, "lel").walls
    heading = math.pi / 2
    rot = np.array([[math.cos(heading), math.sin(heading), 0], [-math.sin(heading), math.cos(heading), 0], [0, 0, 1]])

    def f(theta):
        t = rot @ theta
        return np.array([math.atan2(t[1], t[0]), 1.0 / math.hypot(t[0], t[1])])

    theta0 = n / d
    eps = 1e-7
    jac = np.column_stack([(f(theta0 + e) - f(theta0 - e)) / (2 * eps) for e in np.eye(3) * eps])
    np.testing.assert_allclose(wall.covariance, jac @ c_theta @ jac.T, rtol=1e-5, atol=1e-9)


@pytest.mark.parametrize(
    "mount",
    [
        # base ← array at γ = 0: the columns are the array's axes in the robot's frame (x ahead, z up).
        np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]),  # fan: axis up, beams ahead then left
        np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),  # paper: axis to the right, beams ahead then up
    ],
    ids=["fan", "paper"],
)
def test_a_wall_seen_from_a_placed_array_lands_on_its_world_line(mount):
    heading, position = math.radians(30.0), np.array([2.0, 1.0, 0.3])
    c, s = math.cos(heading), math.sin(heading)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ mount
    phi, rho = math.radians(75.0), 4.0  # the true wall: cos φ x + sin φ y = ρ (world), facing away from the robot
    n_world = np.array([math.cos(phi), math.sin(phi), 0.0])
    n_array = rot.T @ n_world
    d_array = rho - float(n_world @ position)
    msg = codec.Reconstruction(scanner_id="s1", scan_id=9)
    msg.planes.append(_plane(tuple(n_array), d_array))
    cov6 = np.diag([1e-4, 2e-4, 1e-6, 1e-6, 1e-6, 3e-4])
    scan = observation_at(msg, rot, planar_pose(rot, position, cov6), "lel")
    assert scan.pose.heading == pytest.approx(heading)
    np.testing.assert_allclose(scan.pose.covariance, np.diag([1e-4, 2e-4, 3e-4]))
    [wall] = scan.walls
    world = line_in_world(scan.pose.vector, wall.line)
    assert world == pytest.approx([phi, rho], abs=1e-12)


def test_the_scans_are_fused_in_the_order_they_started_and_one_robot_at_a_time(two_scans, capsys, tmp_path):
    assert main(["map", "--source", str(two_scans[1]), str(two_scans[0]), "--json"]) == 0
    reversed_files = json.loads(capsys.readouterr().out)
    assert main(["map", "--source", *map(str, two_scans), "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == reversed_files
    other = tmp_path / "other_robot.mcap"
    with recording.McapRecorder(other) as rec:
        for m in simulated_messages("paper-test1", seed=3, scanner_id="s2", scan_id=5):
            rec.write(m)
    assert main(["map", "--source", str(two_scans[0]), str(other)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--scanner" in err[0]
    assert main(["map", "--source", str(two_scans[0]), str(other), "--scanner", "s2", "--json"]) == 0
    assert [p["scan_id"] for p in json.loads(capsys.readouterr().out)["poses"]] == [5]


def test_a_refused_map_leaves_no_output_to_refuse_the_next_run(two_scans, capsys, tmp_path):
    other = tmp_path / "other_robot.mcap"
    with recording.McapRecorder(other) as rec:
        for m in simulated_messages("paper-test1", seed=3, scanner_id="s2", scan_id=5):
            rec.write(m)
    outputs = {"--rrd": tmp_path / "m.rrd", "--mcap": tmp_path / "m.mcap", "--ros2-bag": tmp_path / "bag"}
    outputs["--screenshot"] = tmp_path / "m.png"
    flags = [str(a) for item in outputs.items() for a in item]
    assert main(["map", "--source", str(two_scans[0]), str(other), *flags]) == 2  # two robots: one is needed
    assert "--scanner" in capsys.readouterr().err
    assert not any(p.exists() for p in outputs.values())
    assert main(["map", "--source", str(two_scans[0]), str(other), "--scanner", "s2", *flags]) == 0
    assert all(p.exists() for p in outputs.values())


def test_a_scan_start_s_pose_places_the_scan():
    from scipy.spatial.transform import Rotation

    from lelsonar.map.from_reconstruction import scan_pose
    from tests.conftest import make_scan_start

    heading = math.radians(-120.0)
    fan = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    rot = Rotation.from_euler("z", heading).as_matrix() @ fan
    start = make_scan_start()
    start.pose.frame_id = "odom"
    start.pose.position.x, start.pose.position.y, start.pose.position.z = 1.5, -2.0, 0.3
    qx, qy, qz, qw = Rotation.from_matrix(rot).as_quat()
    start.pose.orientation.x, start.pose.orientation.y, start.pose.orientation.z, start.pose.orientation.w = (
        qx,
        qy,
        qz,
        qw,
    )
    cov6 = np.diag([4e-4, 9e-4, 1e-6, 1e-6, 1e-6, 2.5e-3])
    start.pose.covariance.extend(cov6.ravel().tolist())
    got_rot, pose, note = scan_pose(start)
    assert note is None
    np.testing.assert_allclose(got_rot, rot, atol=1e-12)
    assert (pose.x, pose.y, pose.z) == pytest.approx((1.5, -2.0, 0.3))
    assert pose.heading == pytest.approx(heading)
    np.testing.assert_allclose(pose.covariance, np.diag([4e-4, 9e-4, 2.5e-3]))
    _, origin, note = scan_pose(make_scan_start())
    assert (origin.x, origin.y) == (0.0, 0.0) and "no pose" in note


WORLD = """
[world]
name = "two-pose room"
[room]
ceiling = 2.5
[[wall]]
from = [0.0, 0.0]
to = [3.0, 0.0]
[[wall]]
from = [3.0, 0.0]
to = [3.0, 2.5]
[[wall]]
from = [3.0, 2.5]
to = [0.0, 2.5]
[[wall]]
from = [0.0, 2.5]
to = [0.0, 0.0]
[scanner]
mount = "fan"
height = 0.3
[odometry]
seed = 3
[[pose]]
x = 1.0
y = 1.0
heading = 20.0
[[pose]]
x = 2.0
y = 1.4
heading = 110.0
"""


@pytest.mark.slow
def test_map_json_of_recordings_made_by_acquire_sim_world_puts_the_walls_on_the_true_ones(tmp_path, capsys):
    world = tmp_path / "room.toml"
    world.write_text(WORLD)
    out = tmp_path / "rec"
    assert main(["acquire", "--device", "sim", "--world", str(world), "--out", str(out), "--no-zenoh"]) == 0
    capsys.readouterr()
    assert main(["map", "--source", *sorted(str(p) for p in out.glob("*.mcap")), "--json"]) == 0
    m = json.loads(capsys.readouterr().out)
    assert {"walls", "corners", "edges", "poses"} <= set(m) and len(m["poses"]) == 2
    truths = [(1, 0.0), (0, 3.0), (1, 2.5), (0, 0.0)]  # the true walls: coordinate `axis` = c (y = 0, x = 3 …)
    good = [w for w in m["walls"] if w["quality"] == "good"]
    assert good
    for w in m["walls"]:
        assert {"normal", "offset", "extent", "quality", "normal_stderr", "offset_stderr"} <= set(w)
    for w in good:
        n = (w["normal"]["x"], w["normal"]["y"])
        for p in w["extent"]:
            # Each corner of a good wall's patch lies on a true wall, facing it, within 2 cm.
            xy = (p["x"], p["y"])
            d = min(abs(xy[axis] - c) for axis, c in truths if abs(n[axis]) > 0.99)
            assert d < 0.02, (w, p)
