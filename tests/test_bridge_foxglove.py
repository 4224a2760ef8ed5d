"""`reconstruct --foxglove`: a real WebSocket client subscribes and decodes what the server sends.

The client offers both subprotocols (foxglove-sdk 0.30 speaks only ``foxglove.sdk.v1``),
subscribes to every advertised channel, and decodes the binary data frames
(``0x01 | u32 subscription id | u64 log time | payload``).  Values are checked
against the source recording: the points by rotating each capsule's beam, E^γ as
Σw²/f_s of the recorded waveforms, the planes against the estimate printed as JSON.
"""

from __future__ import annotations

import json
import math
import os
import signal
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.Log_pb2 import Log
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from websockets.sync.client import connect

from lelsonar import codec
from lelsonar.bridge.foxglove import SUBPROTOCOLS, parse_host_port
from lelsonar.errors import ConfigError
from lelsonar.log import recording

from .conftest import simulated_messages

LELSONAR = str(Path(sys.executable).with_name("lelsonar"))
DECODERS = {
    "foxglove.SceneUpdate": SceneUpdate.FromString,
    "foxglove.PointCloud": PointCloud.FromString,
    "foxglove.FrameTransforms": FrameTransforms.FromString,
    "foxglove.FrameTransform": FrameTransform.FromString,
    "foxglove.Log": Log.FromString,
}


def test_host_port_parsing():
    assert parse_host_port("8765") == ("127.0.0.1", 8765)
    assert parse_host_port("0.0.0.0:9000") == ("0.0.0.0", 9000)
    assert parse_host_port("[::1]:0") == ("::1", 0)
    for bad in ("x", "host:99999", "host:"):
        with pytest.raises(ConfigError):
            parse_host_port(bad)


@pytest.fixture(scope="module")
def source(tmp_path_factory):
    path = tmp_path_factory.mktemp("fox") / "scan.mcap"
    msgs = simulated_messages("paper-test1", seed=2, scanner_id="rig", scan_id=3)
    with recording.McapRecorder(path) as rec:
        for m in msgs:
            rec.write(m)
    return path, msgs


def _serve(source_path: Path) -> tuple[subprocess.Popen, str]:
    proc = subprocess.Popen(
        [
            LELSONAR,
            "reconstruct",
            "--source",
            str(source_path),
            "--foxglove",
            "127.0.0.1:0",
            "--foxglove-wait",
            "60",
            "--json",
            "--compare",
            "ls",
            "--truth-preset",
            "paper-test1",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "COLUMNS": "200"},
    )
    for line in proc.stderr:  # blocks until the server announces itself
        if "Foxglove live on" in line:
            return proc, line.split("Foxglove live on", 1)[1].strip()
    proc.kill()
    raise AssertionError(f"no server line; exit {proc.wait()}")


def _receive(url: str) -> tuple[dict, dict[str, list[tuple[int, object]]]]:
    """Subscribe to everything; collect decoded messages until the final-estimate log line."""
    got: dict[str, list[tuple[int, object]]] = {}
    with connect(url, subprotocols=list(SUBPROTOCOLS), open_timeout=30, max_size=None) as ws:
        assert ws.subprotocol == "foxglove.sdk.v1"
        channels: dict[int, dict] = {}
        while "/lelsonar/planes" not in {c["topic"] for c in channels.values()}:
            msg = json.loads(ws.recv(timeout=30))
            if msg["op"] == "advertise":
                channels.update({c["id"]: c for c in msg["channels"]})
        # Planes last: the server replays once it sees that subscription.
        order = sorted(channels.values(), key=lambda c: c["topic"] == "/lelsonar/planes")
        subs = {i + 1: c for i, c in enumerate(order)}
        ws.send(
            json.dumps(
                {"op": "subscribe", "subscriptions": [{"id": sid, "channelId": c["id"]} for sid, c in subs.items()]}
            )
        )
        while True:
            frame = ws.recv(timeout=60)
            if isinstance(frame, str):
                continue
            assert frame[0] == 0x01
            sid, log_time = struct.unpack_from("<IQ", frame, 1)
            ch = subs[sid]
            payload = frame[13:]
            decoded = json.loads(payload) if ch["encoding"] == "json" else DECODERS[ch["schemaName"]](payload)
            got.setdefault(ch["topic"], []).append((log_time, decoded))
            if ch["topic"] == "/log" and decoded.message.startswith("final estimate"):
                return {c["topic"]: c for c in channels.values()}, got


def test_a_websocket_client_receives_live_planes_points_frames_and_series(source):
    path, msgs = source
    proc, url = _serve(path)
    try:
        channels, got = _receive(url)
    finally:
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    final = json.loads(out.splitlines()[-1])

    assert channels["/lelsonar/energy"]["schemaName"] == "lelsonar.EnergyScalars"
    assert channels["/lelsonar/planes"]["schemaName"] == "foxglove.SceneUpdate"
    assert channels["/lelsonar/planes"]["encoding"] == "protobuf"

    start, samples = msgs[0], [m for m in msgs if isinstance(m, codec.Sample)]

    # Capsule frames and the array pose.
    assert len(got["/tf_capsules"]) == 1 + len(samples)  # again at every step, for late viewers
    _, tfs = got["/tf_capsules"][-1]
    assert [t.child_frame_id for t in tfs.transforms] == [f"capsule_{c}" for c in "ABCD"]
    assert [(t.translation.x, t.translation.y) for t in tfs.transforms] == [
        (c.position.x, c.position.y) for c in start.capsules
    ]

    # Points as they arrive: one cloud per step, growing, the last one every valid echo of the scan.
    clouds = got["/lelsonar/scan_points"]
    assert len(clouds) == len(samples)
    sizes = [len(c.data) // c.point_stride for _, c in clouds]
    assert sizes == sorted(sizes) and sizes[0] <= 4
    truth = []
    for smp in samples:
        c, s = math.cos(smp.gamma_measured), math.sin(smp.gamma_measured)
        rot = np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
        for r in smp.sensors:
            if r.echo_valid:
                cap = start.capsules[r.capsule_id]
                truth.append(
                    rot
                    @ (
                        np.array([cap.position.x, cap.position.y, cap.position.z])
                        + r.distance * np.array([cap.boresight.x, cap.boresight.y, cap.boresight.z])
                    )
                )
    latest = got["/lelsonar/points"][-1][1]
    np.testing.assert_allclose(
        np.frombuffer(latest.data, "<f4").reshape(-1, 3),
        np.array(truth[-sum(r.echo_valid for r in samples[-1].sensors) :]),
        atol=2e-6,
    )
    last = clouds[-1][1]
    xyz = np.frombuffer(last.data, "<f4").reshape(-1, last.point_stride // 4)[:, :3]
    np.testing.assert_allclose(xyz, np.array(truth), atol=2e-6)

    # E^γ as a plottable series, equal to Σ w²/f_s of the recorded waveforms; R = E/E0.
    series = {row["step"]: row for _, row in got["/lelsonar/energy"]}
    assert len(series) == len(samples)
    for smp in samples[::37]:
        e = sum(
            float(np.sum(codec.unpack_waveform(r.waveform).astype(np.float64) ** 2)) / r.waveform.sample_rate
            for r in smp.sensors
        )
        row = series[smp.step]
        assert math.isclose(row["energy"], e, rel_tol=1e-6)
        if row["expected_energy"]:
            assert math.isclose(row["ratio"], row["energy"] / row["expected_energy"], rel_tol=1e-9)
    assert series[samples[-1].step]["critical_step"] == final["critical_step"]

    # The last SceneUpdate holds the final planes of both methods, drawn where the estimate says.
    _, scene = got["/lelsonar/planes"][-1]
    by_id = {e.id: e for e in scene.entities}
    planes = {f"rig/3/plane/{p['method']}/{p['label']}" for p in final["planes"]} | {"rig/3/edge"}
    # Beside them, every surface, corner and edge of the sweep, and its unexplained echoes, as the estimate has them.
    surfaces = {f"rig/3/surface/{s['label']}" for s in final.get("surfaces", [])}
    features = {f"rig/3/feature/{f['label']}" for f in final.get("corners", []) + final.get("edges", [])}
    unexplained = {"rig/3/unexplained"} if any(u.get("count") for u in final.get("unexplained", [])) else set()
    assert planes | surfaces | features | unexplained == set(by_id)
    for p in final["planes"]:
        e = by_id[f"rig/3/plane/{p['method']}/{p['label']}"]
        drawn = [(q.x, q.y, q.z) for q in e.lines[0].points]
        assert drawn == [(q["x"], q["y"], q["z"]) for q in p["patch"]]
        assert f"h = {p['offset']:.3f} m" in e.texts[0].text
        n = np.array([p["normal"][a] for a in "xyz"])
        o = e.arrows[0].pose.orientation
        q = np.array([o.x, o.y, o.z])
        arrow = np.array([1.0, 0, 0]) + 2 * o.w * np.cross(q, [1.0, 0, 0]) + 2 * np.cross(q, np.cross(q, [1.0, 0, 0]))
        np.testing.assert_allclose(arrow, n, atol=1e-9)
    # The true planes of the preset, grey, where the simulator put them.
    from lelsonar.sim import preset
    from lelsonar.sim.scan import true_planes

    _, truth_scene = got["/lelsonar/truth"][-1]
    drawn = {e.id: e for e in truth_scene.entities}
    for plane in true_planes(preset("paper-test1")):
        e = drawn[f"rig/truth/{plane.label}"]
        np.testing.assert_allclose([(q.x, q.y, q.z) for q in e.lines[0].points], plane.corners)
        assert e.texts[0].text == f"truth {plane.label}: h = {plane.offset:.3f} m"
    logs = [m.message for _, m in got["/log"]]
    assert any(text.startswith("scan 3 of rig") for text in logs)
    assert any(text.startswith("critical step") for text in logs)


def test_shipped_layout_is_current_and_names_served_topics():
    from lelsonar.bridge.foxglove import _PROTO_TOPICS, layout_json
    from lelsonar.draw.visual import TOPIC_ENERGY, TOPIC_STEP

    shipped = Path(__file__).parents[1] / "examples" / "foxglove-layout.json"
    assert shipped.read_text() == layout_json(), "regenerate: python -m lelsonar.bridge.foxglove > " + str(shipped)
    layout = json.loads(shipped.read_text())
    config = layout["configById"]
    ids = []

    def walk(node):
        if isinstance(node, str):
            ids.append(node)
        else:
            walk(node["first"])
            walk(node["second"])

    walk(layout["layout"])
    assert sorted(ids) == sorted(config)
    assert {i.split("!")[0] for i in ids} == {"3D", "Plot", "RosOut"}
    panels = [{"config": config[i]} for i in ids]
    topics = set(_PROTO_TOPICS) | {TOPIC_ENERGY, TOPIC_STEP}
    for p in panels:
        for t in p["config"].get("topics", {}):
            assert t in topics
        for s in p["config"].get("paths", []):
            assert s["value"].split(".", 1)[0] in topics
    # One quantity (one unit) per axis: R (about 0.2-1.5) and the critical step (tens) never share one.
    plotted = {i: {s["value"] for s in config[i]["paths"]} for i in ids if i.startswith("Plot")}
    ratio = next(i for i, v in plotted.items() if f"{TOPIC_ENERGY}.ratio" in v)
    assert plotted[ratio] == {f"{TOPIC_ENERGY}.ratio"}
    assert any(v == {f"{TOPIC_ENERGY}.critical_step"} for v in plotted.values())
    ranges = next(v for v in plotted.values() if any(".range." in x for x in v))  # as the README says
    assert ranges == {f"{TOPIC_STEP}.range.{c}" for c in "ABCD"}


def test_a_busy_port_is_one_clear_error():
    from lelsonar.bridge.foxglove import FoxgloveServer

    first = FoxgloveServer("127.0.0.1", 0)
    try:
        with pytest.raises(ConfigError, match="cannot serve Foxglove on 127.0.0.1"):
            FoxgloveServer("127.0.0.1", first.port)
    finally:
        first.close()
