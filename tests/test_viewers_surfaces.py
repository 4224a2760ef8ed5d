"""Every surface, corner, edge and the unexplained echoes of a sweep, in Foxglove, ROS 2 and Rerun, drawn
from the Reconstruction message alone."""

from __future__ import annotations

import math
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from google.protobuf.json_format import MessageToJson, Parse
from rerun.chunk import RrdReader

from lelsonar import codec
from lelsonar.bridge import ros2
from lelsonar.bridge.ros2_markers import estimate_markers
from lelsonar.draw.estimates import SIGMA_BAND, PlaneScene
from lelsonar.draw.palette import quality_color
from lelsonar.view.rerun_layout import make_recording
from lelsonar.view.rerun_surfaces import log_surfaces

SIGMA_WALL = 0.004  # m, the offset σ of wall s1
SIGMA_BOX = 0.02  # m, the offset σ of the box face s2


def _patch(normal, offset: float, along, half: float = 0.3, height: float = 0.1) -> list:
    n, t = np.asarray(normal, float), np.asarray(along, float)
    up = np.cross(n, t)
    c = offset * n
    return [c + a * half * t + b * height * up for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))]


def _message() -> codec.Reconstruction:
    """A sweep that saw a wall (good), a box face (degraded), their corner and a free edge."""
    msg = codec.Reconstruction(scanner_id="s", scan_id=7, status=2, schema_version=1)
    for label, normal, offset, sigma, quality in (
        ("s1", (0.0, 1.0, 0.0), 1.0, SIGMA_WALL, "good"),
        ("s2", (0.0, 0.0, 1.0), 0.6, SIGMA_BOX, "degraded"),
    ):
        s = msg.surfaces.add(label=label, bearing=math.atan2(normal[2], normal[1]), echo_count=40)
        s.bearing_source = "amplitude peak"
        s.covariance.extend([math.radians(2.0) ** 2, 0, 0, 0, math.radians(1.0) ** 2, 0, 0, 0, sigma**2])
        p = s.plane
        p.label, p.method, p.offset = label, "surfaces", offset
        p.normal.x, p.normal.y, p.normal.z = normal
        p.quality = codec.QUALITY[quality]
        if quality != "good":
            p.quality_reasons.append("seen by 12 echoes only")
        for v in _patch(normal, offset, (1.0, 0.0, 0.0)):
            q = p.patch.add()
            q.x, q.y, q.z = v
    for group, label, point in ((msg.corners, "c1", (0.0, 1.0, 0.6)), (msg.edges, "e1", (0.0, -0.4, 0.6))):
        f = group.add(label=label, echo_count=5)
        f.line.point.x, f.line.point.y, f.line.point.z = point
        f.line.direction.x = 1.0
        f.line.point_stderr = 0.01
        f.covariance.extend([1e-4, 0, 0, 0, 1e-4, 0, 0, 0, 1e-4])
        f.surfaces.append("s1")
    msg.unexplained.add(cause="multipath", count=9)
    msg.surface_echo_count = 200
    codec.validate(msg)
    return msg


def _rgba(color) -> tuple:
    return tuple(round(v * 255) for v in (color.r, color.g, color.b))


def test_foxglove_scene_draws_each_surface_in_its_verdict_colour_with_its_sigma_band():
    msg = _message()
    update = PlaneScene().update(msg, t_ns=123)
    back = SceneUpdate()
    back.ParseFromString(update.SerializeToString())
    assert Parse(MessageToJson(back), SceneUpdate()) == back  # its JSON form is valid too
    by_id = {e.id: e for e in back.entities}
    assert {"s/7/surface/s1", "s/7/surface/s2", "s/7/feature/c1", "s/7/feature/e1", "s/7/unexplained"} <= set(by_id)
    for label, sigma, quality in (("s1", SIGMA_WALL, "good"), ("s2", SIGMA_BOX, "degraded")):
        e = by_id[f"s/7/surface/{label}"]
        surface = next(s for s in msg.surfaces if s.label == label)
        n = np.array([surface.plane.normal.x, surface.plane.normal.y, surface.plane.normal.z])
        assert _rgba(e.triangles[0].color) == quality_color(quality)
        # The outline sits on the plane; the two band outlines at ± 2σ of the offset along the normal.
        heights = sorted(
            {round(float(np.dot(n, [p.x, p.y, p.z])) - surface.plane.offset, 9) for ln in e.lines for p in ln.points}
        )
        assert heights == pytest.approx([-SIGMA_BAND * sigma, 0.0, SIGMA_BAND * sigma], abs=1e-9)
        meta = {kv.key: kv.value for kv in e.metadata}
        assert meta["quality"] == quality and float(meta["offset_sigma_mm"]) == pytest.approx(sigma * 1e3, abs=0.01)
    corner = by_id["s/7/feature/c1"]
    assert corner.spheres[0].size.x == pytest.approx(4 * 0.01)  # ± 2σ of the point
    assert "9 multipath" in by_id["s/7/unexplained"].texts[0].text
    assert "of 200 echoes" in by_id["s/7/unexplained"].texts[0].text


def test_foxglove_scene_deletes_the_surfaces_a_later_estimate_no_longer_has():
    scene = PlaneScene()
    scene.update(_message(), t_ns=1)
    later = _message()
    del later.surfaces[1]
    update = scene.update(later, t_ns=2)
    assert [d.id for d in update.deletions] == ["s/7/surface/s2"]


def test_ros2_markers_carry_the_surfaces_corners_and_edges_and_deserialise():
    b = ros2.Builder("jazzy")
    msg = _message()
    markers = estimate_markers(b, msg, 5, "s/base")
    data = ros2.serialize(b(ros2.MARKERS, markers=markers), ros2.MARKERS)
    back = ros2.deserialize(data, ros2.MARKERS).markers
    by_ns = defaultdict(list)
    for m in back:
        by_ns[m.ns].append(m)
    assert len(by_ns["surface"]) == 2 and len(by_ns["surface/sigma"]) == 2
    colors = {round(m.color.r * 255): m for m in by_ns["surface"]}
    assert set(colors) == {quality_color("good")[0], quality_color("degraded")[0]}
    band = by_ns["surface/sigma"][1]  # s2, the box face: normal +z at 0.6 m
    zs = sorted({round(p.z, 9) for p in band.points})
    assert zs == pytest.approx([0.6 - SIGMA_BAND * SIGMA_BOX, 0.6 + SIGMA_BAND * SIGMA_BOX], abs=1e-9)
    assert len(by_ns["corner"]) == 1 and len(by_ns["convex_edge"]) == 1
    assert by_ns["corner/sigma"][0].scale.x == pytest.approx(0.04)
    assert "9 multipath" in by_ns["unexplained"][0].text


def test_rerun_holds_every_surface_corner_edge_and_the_unexplained_count(tmp_path: Path):
    rec = make_recording(recording_id="surfaces")
    path = tmp_path / "surfaces.rrd"
    rec.save(path)
    rec.set_time("step", sequence=299)
    assert log_surfaces(rec, "/world/s/scans/scan_7", _message()) == 4
    rec.flush()
    rec.disconnect()
    ents: dict[str, list] = defaultdict(list)
    for chunk in RrdReader(path).store().stream().to_chunks():
        ents[str(chunk.entity_path)].append(chunk.to_record_batch())
    root = "/world/s/scans/scan_7"
    for p in ("surfaces/s1", "surfaces/s1/sigma_band", "surfaces/s2/normal", "corners/c1", "edges/e1/direction"):
        assert f"{root}/{p}" in ents, p
    band = ents[f"{root}/surfaces/s2/sigma_band"][0].column("LineStrips3D:strips").to_pylist()[0]
    assert sorted({round(pt[2], 6) for strip in band for pt in strip}) == pytest.approx(
        [0.6 - SIGMA_BAND * SIGMA_BOX, 0.6 + SIGMA_BAND * SIGMA_BOX], abs=1e-6
    )
    text = ents[f"{root}/unexplained"][0].column("TextDocument:text").to_pylist()[0]
    assert "9 of 200" in text[0] and "multipath" in text[0]


def test_an_extracted_sweep_is_drawn_whole_in_every_viewer(tmp_path: Path):
    from lelsonar.reconstruct.estimate import wire
    from lelsonar.reconstruct.estimate.surfaces import extract_surfaces
    from tests.test_surfaces import GAMMA, GEOMETRY, Echoes

    e = Echoes(seed=3)
    e.plane(0.0, 1.0)
    e.plane(math.pi / 2, 1.5)
    e.vertical_line(1.0, 1.5, gain=1.5)
    result = extract_surfaces(GAMMA, e.ranges(), GEOMETRY, amplitude=e.amp)
    msg = wire.reconstruction_message(
        "s",
        1,
        status="final",
        last_step=299,
        samples_used=300,
        critical_step=None,
        critical_angle=0.0,
        planes=(),
        edge=None,
        timings=(0.0, 0.0, 0.0),
        surfaces=result,
    )
    want = {s.label for s in result.surfaces}
    scene = PlaneScene().update(msg, t_ns=1)
    assert {e.id.rsplit("/", 1)[1] for e in scene.entities if "/surface/" in e.id} == want
    assert sum("/feature/" in e.id for e in scene.entities) == len(result.corners) + len(result.edges)
    markers = estimate_markers(ros2.Builder("jazzy"), msg, 1, "s/base")
    assert sum(m.ns == "surface" for m in markers) == len(want)
    rec = make_recording(recording_id="extracted")
    rec.save(tmp_path / "x.rrd")
    assert log_surfaces(rec, "/world/s/scans/scan_1", msg) == len(want) + len(result.corners) + len(result.edges)


def test_review_draws_the_surfaces_of_the_final_estimate_of_record(tmp_path: Path, capsys):
    import json

    from lelsonar.cli.main import main
    from lelsonar.log import recording
    from tests.conftest import simulated_messages

    src, rrd = tmp_path / "scan.mcap", tmp_path / "scan.rrd"
    with recording.McapRecorder(src) as rec:
        for m in simulated_messages("paper-test1", seed=4, scanner_id="s", scan_id=9):
            rec.write(m)
    assert main(["reconstruct", "--source", str(src), "--json"]) == 0
    final = json.loads(capsys.readouterr().out.splitlines()[-1])
    assert main(["review", str(src), "-o", str(rrd)]) == 0
    paths = {str(c.entity_path) for c in RrdReader(rrd).store().stream().to_chunks()}
    root = "/world/s/scans/scan_9"
    want = {f"{root}/surfaces/{s['label']}/outline" for s in final.get("surfaces", [])}
    want |= {f"{root}/corners/{f['label']}" for f in final.get("corners", [])}
    want |= {f"{root}/edges/{f['label']}" for f in final.get("edges", [])}
    assert want and want <= paths
