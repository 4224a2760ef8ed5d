"""A recording shows the scan by itself: accumulated points, capsule frames, plottable scalars, a name, planes.

Truth is computed here independently: points by rotating ``position + d·boresight``
about x, energies by ``lelsonar.signal.energy`` on the unpacked waveforms.
"""

from __future__ import annotations

import json
import math
import subprocess

import numpy as np
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from mcap.reader import make_reader
from rerun.chunk import RrdReader

from lelsonar import codec
from lelsonar.draw import palette, visual
from lelsonar.log import recording
from lelsonar.signal.energy import total_energy, waveform_energy
from lelsonar.v1 import reconstruction_pb2

from .conftest import make_sample, make_scan_start
from .test_contract_mcap import RERUN

STEPS = 6


def _rot_x(g: float) -> np.ndarray:
    c, s = math.cos(g), math.sin(g)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _truth_points(start, samples) -> np.ndarray:
    pts = []
    for smp in samples:
        for r in smp.sensors:
            cap = start.capsules[r.capsule_id]
            local = np.array([cap.position.x, cap.position.y, cap.position.z]) + r.distance * np.array(
                [cap.boresight.x, cap.boresight.y, cap.boresight.z]
            )
            pts.append(_rot_x(smp.gamma_measured) @ local)
    return np.array(pts)


def _cloud(msg: PointCloud) -> np.ndarray:
    names = [f.name for f in msg.fields]
    return np.frombuffer(msg.data, dtype="<f4").reshape(-1, msg.point_stride // 4)[:, [names.index(a) for a in "xyz"]]


def _record(path, extra=()):
    start = make_scan_start(steps=STEPS)
    samples = [make_sample(step=i) for i in range(STEPS)]
    # One capsule without an echo: its point must be absent, its range null.
    samples[2].sensors[1].echo_valid = False
    samples[2].sensors[1].distance = 0.0
    end = codec.ScanEnd(
        schema_version=1,
        scanner_id="s1",
        scan_id=7,
        status=1,
        steps_planned=STEPS,
        samples_sent=STEPS,
        end_time_ns=samples[-1].acquisition_time_ns + 1,
    )
    with recording.McapRecorder(path) as rec:
        for m in (start, *samples, end, *extra):
            rec.write(m)
    return start, samples


def _messages(path, topic):
    with open(path, "rb") as f:
        return [(s, c, m) for s, c, m in make_reader(f).iter_messages(topics=[topic], log_time_order=True)]


def test_scan_points_accumulate_and_match_the_geometry(tmp_path):
    path = tmp_path / "scan.mcap"
    start, samples = _record(path)
    clouds = _messages(path, visual.TOPIC_SCAN_POINTS)
    assert [s.name for s, _, _ in clouds] == ["foxglove.PointCloud"] * STEPS
    for k, (_, _, m) in enumerate(clouds):
        msg = PointCloud.FromString(m.data)
        assert m.log_time == samples[k].acquisition_time_ns
        truth = _truth_points(start, [_valid_only(s) for s in samples[: k + 1]])
        np.testing.assert_allclose(_cloud(msg), truth, atol=1e-6)  # float32
    last = PointCloud.FromString(clouds[-1][2].data)
    assert len(last.data) // last.point_stride == 4 * STEPS - 1  # not the ≤ 4 points of one step


def _valid_only(sample):
    out = codec.Sample()
    out.CopyFrom(sample)
    del out.sensors[:]
    out.sensors.extend(r for r in sample.sensors if r.echo_valid)
    return out


def test_capsule_frames_put_x_along_each_boresight(tmp_path):
    path = tmp_path / "scan.mcap"
    start, _ = _record(path)
    ((schema, _, m),) = _messages(path, visual.TOPIC_CAPSULE_TF)
    assert schema.name == "foxglove.FrameTransforms"
    tfs = FrameTransforms.FromString(m.data).transforms
    assert [t.child_frame_id for t in tfs] == ["capsule_A", "capsule_B", "capsule_C", "capsule_D"]
    for t, cap in zip(tfs, start.capsules):
        assert t.parent_frame_id == "array"
        assert (t.translation.x, t.translation.y, t.translation.z) == (cap.position.x, cap.position.y, cap.position.z)
        q = np.array([t.rotation.x, t.rotation.y, t.rotation.z])
        w = t.rotation.w
        x_axis = np.array([1.0, 0, 0])
        rotated = x_axis + 2 * w * np.cross(q, x_axis) + 2 * np.cross(q, np.cross(q, x_axis))
        np.testing.assert_allclose(rotated, [cap.boresight.x, cap.boresight.y, cap.boresight.z], atol=1e-12)


def test_step_scalars_are_plottable_json_with_the_true_energies_and_ranges(tmp_path):
    path = tmp_path / "scan.mcap"
    _, samples = _record(path)
    rows = _messages(path, visual.TOPIC_STEP)
    assert len(rows) == STEPS
    schema, channel, _ = rows[0]
    assert (schema.name, schema.encoding, channel.message_encoding) == ("lelsonar.StepScalars", "jsonschema", "json")
    assert json.loads(schema.data)["properties"]["energy"]["type"] == "number"
    for (_, _, m), smp in zip(rows, samples):
        row = json.loads(m.data)
        w = np.stack([codec.unpack_waveform(r.waveform) for r in smp.sensors])
        per = waveform_energy(w, smp.sensors[0].waveform.sample_rate)
        assert row["step"] == smp.step and math.isclose(row["gamma_deg"], math.degrees(smp.gamma_measured))
        assert math.isclose(row["energy"], float(total_energy(per)), rel_tol=1e-9)
        np.testing.assert_allclose([row["energy_by_capsule"][c] for c in "ABCD"], per, rtol=1e-9)
        assert [row["range"][c] for c in "ABCD"] == [r.distance if r.echo_valid else None for r in smp.sensors]
    assert json.loads(rows[2][2].data)["range"]["B"] is None


def test_recording_is_named_and_rerun_converts_the_views(tmp_path):
    path, rrd = tmp_path / "scan.mcap", tmp_path / "scan.rrd"
    _record(path)
    meta = recording.read_metadata(path)["lelsonar.log.recording"]
    assert meta["name"] == "lelsonar s1 scan 7" and meta["scanner_id"] == "s1" and meta["scan_id"] == "7"
    for cmd in (
        [RERUN, "mcap", "convert", str(path), "-o", str(rrd), "--application-id", "lelsonar"],
        [RERUN, "rrd", "verify", str(rrd)],
    ):
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
        assert done.returncode == 0, done.stderr
    positions: list[int] = []
    frames: set[str] = set()
    names: list = []
    for chunk in RrdReader(rrd).store().stream().to_chunks():
        rb = chunk.to_record_batch()
        batch = {
            n: rb.column(n).to_pylist()
            for n in rb.schema.names
            if n in ("Points3D:positions", "Transform3D:child_frame", "lelsonar.log.recording")
        }
        if chunk.entity_path == "/lelsonar/scan_points" and "Points3D:positions" in batch:
            positions += [len(p) for p in batch["Points3D:positions"]]
        if chunk.entity_path == "/tf_capsules" and "Transform3D:child_frame" in batch:
            frames |= {f for row in batch["Transform3D:child_frame"] for f in row}
        if chunk.entity_path == "/__mcap_metadata" and "lelsonar.log.recording" in batch:
            names += batch["lelsonar.log.recording"]
    assert max(positions) == 4 * STEPS - 1
    assert frames == {"capsule_A", "capsule_B", "capsule_C", "capsule_D"}
    assert {"first": "name", "second": "lelsonar s1 scan 7"} in names[0][0]


def _estimate(planes, edge=True) -> codec.Reconstruction:
    msg = codec.Reconstruction(
        schema_version=1,
        scanner_id="s1",
        scan_id=7,
        last_step=STEPS - 1,
        status=reconstruction_pb2.ESTIMATE_STATUS_FINAL,
        stamp_ns=1_700_000_001_000_000_000,
    )
    for label, method, quality, normal, h in planes:
        p = msg.planes.add(label=label, method=method, offset=h, sigma=0.002, quality=quality)
        p.normal.x, p.normal.y, p.normal.z = normal
        normal = np.asarray(normal, dtype=float)
        u = np.cross(normal, [1.0, 0, 0] if abs(normal[0]) < 0.9 else [0, 1.0, 0])
        u /= np.linalg.norm(u)
        v = np.cross(normal, u)
        for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
            c = h * np.asarray(normal) + 0.3 * (a * u + b * v)
            q = p.patch.add()
            q.x, q.y, q.z = c
    if edge:
        msg.corner_edge.point.y, msg.corner_edge.point.z = 1.57, 1.06
        msg.corner_edge.direction.x = 1.0
    return msg


def _rgb(color) -> tuple[int, int, int]:
    return tuple(round(255 * x) for x in (color.r, color.g, color.b))


def test_record_adds_planes_coloured_by_method_and_quality_and_deletes_stale_ones(tmp_path):
    path = tmp_path / "scan.mcap"
    first = _estimate(
        [
            ("a", "ls", reconstruction_pb2.PLANE_QUALITY_GOOD, (0, 1, 0), 1.57),
            ("b", "ls", reconstruction_pb2.PLANE_QUALITY_UNRELIABLE, (0, 0, 1), 1.06),
            ("a", "lel", reconstruction_pb2.PLANE_QUALITY_UNSPECIFIED, (0, 1, 0), 1.57),
        ]
    )
    second = _estimate([("a", "ls", reconstruction_pb2.PLANE_QUALITY_DEGRADED, (0, 1, 0), 1.50)], edge=False)
    second.stamp_ns += 1
    _record(path, extra=(first, second))
    (s1, _, m1), (_, _, m2) = _messages(path, visual.TOPIC_PLANES)
    assert s1.name == "foxglove.SceneUpdate"
    u1, u2 = SceneUpdate.FromString(m1.data), SceneUpdate.FromString(m2.data)
    by_id = {e.id: e for e in u1.entities}
    assert set(by_id) == {"s1/7/plane/ls/a", "s1/7/plane/ls/b", "s1/7/plane/lel/a", "s1/7/edge"}
    # One palette for every viewer: Foxglove draws what Rerun and the ROS 2 markers draw.
    ls, lel = palette.METHOD_COLORS["ls"], palette.METHOD_COLORS["lel"]
    q = palette.QUALITY_COLORS
    expect = {
        "s1/7/plane/ls/a": (ls, q["good"], "good"),
        "s1/7/plane/ls/b": (ls, q["unreliable"], "unreliable"),
        "s1/7/plane/lel/a": (lel, palette.UNASSESSED_COLOR, "unassessed"),
    }
    assert len({ls, lel, *q.values(), palette.UNASSESSED_COLOR}) == 6  # distinguishable
    for eid, (fill, outline, quality) in expect.items():
        e = by_id[eid]
        assert _rgb(e.triangles[0].color) == fill and _rgb(e.lines[0].color) == outline
        assert {kv.key: kv.value for kv in e.metadata}["quality"] == quality
        assert quality in e.texts[0].text
        assert len(e.triangles[0].points) == 6 and len(e.lines[0].points) == 4 and len(e.arrows) == 1
    # The patch drawn is the patch estimated.
    src = first.planes[1]
    drawn = {(p.x, p.y, p.z) for p in by_id["s1/7/plane/ls/b"].lines[0].points}
    assert drawn == {(q.x, q.y, q.z) for q in src.patch}
    edge = by_id["s1/7/edge"].lines[0].points
    assert (edge[0].y, edge[0].z) == (1.57, 1.06) and edge[1].x - edge[0].x == 1.0
    # The second estimate redraws ls/a in amber and deletes what it no longer has.
    assert [e.id for e in u2.entities] == ["s1/7/plane/ls/a"]
    assert _rgb(u2.entities[0].lines[0].color) == q["degraded"]
    assert sorted(d.id for d in u2.deletions) == ["s1/7/edge", "s1/7/plane/lel/a", "s1/7/plane/ls/b"]


def test_a_new_scan_replaces_the_planes_of_the_last_one():
    scene = visual.PlaneScene()
    first = _estimate([("a", "ls", reconstruction_pb2.PLANE_QUALITY_GOOD, (0, 1, 0), 1.57)])
    scene.update(first)
    second = _estimate([("b", "lel", reconstruction_pb2.PLANE_QUALITY_GOOD, (0, 0, 1), 1.06)], edge=False)
    second.scan_id = 8
    other = _estimate([("a", "ls", reconstruction_pb2.PLANE_QUALITY_GOOD, (0, 1, 0), 1.57)], edge=False)
    other.scanner_id = "s2"
    assert not scene.update(other).deletions
    update = scene.update(second)
    assert [e.id for e in update.entities] == ["s1/8/plane/lel/b"]
    assert sorted(d.id for d in update.deletions) == ["s1/7/edge", "s1/7/plane/ls/a"]


def test_a_simulated_recording_carries_energy_ratio_and_truth(tmp_path):
    """/lelsonar/energy on the acquisition recording gives the R the reconstruction computes (independently:
    the service's own per-step ratio), so the layout's ratio panel is filled on a recording; a simulated
    scan also carries its true planes."""
    from lelsonar.acquire.simulated import record_scan
    from lelsonar.reconstruct.stream.config import ReconstructConfig
    from lelsonar.reconstruct.stream.replay import replay_mcap
    from lelsonar.reconstruct.stream.service import ReconstructionService
    from lelsonar.sim import default_energy_model, preset, simulate_scan

    path = tmp_path / "sim.mcap"
    scan = simulate_scan(preset("paper-test1"), seed=2)
    record_scan(scan, path, default_energy_model())
    rows = [json.loads(m.data) for _, _, m in _messages(path, visual.TOPIC_ENERGY)]
    assert [r["step"] for r in rows] == list(range(scan.n_steps))
    assert all(r["critical_step"] is None for r in rows)  # the reconstruction's to find

    ratios = {}

    class Ratios:  # the service's observer: what the reconstruction computes per step
        def scan_started(self, s): ...
        def estimate(self, *a): ...
        def event(self, *a, **k): ...
        def step(self, s, view, energy, expected, ratio):
            ratios[view.step] = (energy, expected, ratio)

    replay_mcap(path, ReconstructionService(ReconstructConfig(provisional=False), observer=Ratios()))
    for r in rows:
        energy, expected, ratio = ratios[r["step"]]
        assert math.isclose(r["energy"], energy, rel_tol=1e-6)
        if ratio > 0:
            assert math.isclose(r["ratio"], ratio, rel_tol=1e-6) and math.isclose(r["expected_energy"], expected)
    ((_, _, m),) = _messages(path, visual.TOPIC_TRUTH)
    drawn = {e.id: e for e in SceneUpdate.FromString(m.data).entities}
    for plane in scan.truth.planes:
        assert f"sim/truth/{plane.label}" in drawn


def test_a_recording_without_truth_has_no_truth_channel(tmp_path):
    path = tmp_path / "scan.mcap"
    _record(path)
    assert _messages(path, visual.TOPIC_TRUTH) == []
    assert len(_messages(path, visual.TOPIC_ENERGY)) == STEPS
