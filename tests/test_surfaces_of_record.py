"""Every surface of a sweep in the reconstruction of record: a final carries them, made from the very input
its L planes were fitted on; a provisional says nothing of them; the writer's findings judge them too."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import tomllib
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from lelsonar import codec
from lelsonar.log import recording
from lelsonar.reconstruct.estimate import wire
from lelsonar.reconstruct.estimate.quality import DEGRADED
from lelsonar.reconstruct.estimate.record import RecordOptions, ScanInput, reconstruct_scan, with_findings
from lelsonar.reconstruct.estimate.surfaces import extract_surfaces
from lelsonar.reconstruct.stream.config import ReconstructConfig
from lelsonar.reconstruct.stream.service import ReconstructionService
from lelsonar.signal.energy import echo_amplitude, waveform_energy
from lelsonar.sim import default_energy_model, preset, simulate_scan
from lelsonar.view import present

from .conftest import simulated_messages, type_name

ROOM = Path(__file__).resolve().parent.parent / "examples" / "worlds" / "room.toml"
#: A gate of three standard deviations: what a stated σ promises of nearly every estimate.
GATE = 3.0


@pytest.fixture(scope="module")
def given() -> ScanInput:
    scan = simulate_scan(preset("paper-test1"), seed=3)
    energy = waveform_energy(scan.waveforms, scan.sample_rate)
    amplitude = echo_amplitude(scan.waveforms, scan.sample_rate, scan.t0, scan.tof)
    return ScanInput.of_scan(
        scan.gamma_measured, scan.distance, energy, scan.geometry, default_energy_model(), echo_amplitude=amplitude
    )


def test_a_final_carries_the_surfaces_of_its_own_ranges_and_amplitudes(given):
    est = reconstruct_scan(given, RecordOptions())
    own = extract_surfaces(given.gamma, given.distance, given.geometry, amplitude=given.echo_amplitude)
    assert est.surfaces is not None and len(est.surfaces.surfaces) == len(own.surfaces) == 2
    for mine, theirs in zip(est.surfaces.surfaces, own.surfaces, strict=True):
        np.testing.assert_array_equal(mine.normal, theirs.normal)
        assert (mine.offset, mine.quality, mine.reasons) == (theirs.offset, theirs.quality, theirs.reasons)
    msg = wire.estimate_message(est, "s", 1, status="final")
    assert [s.label for s in msg.surfaces] == [s.label for s in own.surfaces]
    assert len(msg.corners) == len(own.corners) and msg.surface_echo_count == own.n_echoes


def test_the_writers_findings_lower_every_surface_as_every_plane(given):
    text = "the writer's ranges are one-way times"
    est = reconstruct_scan(replace(given, writer_problems=((DEGRADED, text),)), RecordOptions())
    assert est.surfaces is not None and est.surfaces.surfaces
    for s in est.surfaces.surfaces:
        assert s.quality != "good" and s.reasons[-1] == text
    # What the stream adds (a sweep stopped early, conflicting copies) goes the same way.
    clean = reconstruct_scan(given, RecordOptions())
    stopped = with_findings(clean, ((DEGRADED, "stopped early"),))
    assert stopped.surfaces is not None
    assert all(s.reasons[-1] == "stopped early" and s.quality != "good" for s in stopped.surfaces.surfaces)
    assert all(p.quality_reasons[-1] == "stopped early" for p in stopped.planes)


def test_a_surface_next_to_missing_steps_says_so(given):
    """An incomplete scan: the steps lost inside one wall's region of constant depth degrade that wall (its
    centre, hence its bearing, is no longer the region's), and only that one."""
    whole = reconstruct_scan(given, RecordOptions())
    assert whole.surfaces is not None
    first, second = whole.surfaces.surfaces[:2]
    lost = np.arange(int(first.steps.max()) - 3, int(first.steps.max()) + 2)  # the end of the first wall's region
    keep = np.setdiff1d(np.arange(len(given.steps)), lost)
    holed = replace(
        given,
        steps=given.steps[keep],
        gamma=given.gamma[keep],
        distance=given.distance[keep],
        sensor_energy=np.asarray(given.sensor_energy)[keep],
        echo_amplitude=np.asarray(given.echo_amplitude)[keep],
        n_schedule=len(given.steps),
    )
    est = reconstruct_scan(holed, RecordOptions())
    assert est.surfaces is not None
    near = [s for s in est.surfaces.surfaces if any("missing" in r for r in s.reasons)]
    assert len(near) == 1 and near[0].quality != "good"
    assert f"steps {lost[0]}-{lost[-1]} of the scan are missing" in near[0].reasons[-1]
    far = [s for s in est.surfaces.surfaces if s is not near[0]]
    assert far and all(not any("missing" in r for r in s.reasons) for s in far)


def test_a_provisional_estimate_says_nothing_of_surfaces():
    messages = simulated_messages("paper-test1", seed=4)
    service = ReconstructionService(ReconstructConfig(provisional=True, provisional_period=0.0))
    out = []
    for m in messages:
        out += service.handle(type_name(m), m.SerializeToString())
    provisional = [m for m in out if wire.status_name(m) == "provisional"]
    (final,) = [m for m in out if wire.is_terminal(m)]
    assert provisional and not any(m.surfaces or m.corners or m.edges or m.surface_echo_count for m in provisional)
    assert final.surfaces and final.surface_echo_count
    # The console's table of them: one row per surface, corner and edge; none for a provisional.
    assert all(present.surfaces_table(m) is None for m in provisional)
    table = present.surfaces_table(final)
    assert table is not None and table.row_count == len(final.surfaces) + len(final.corners) + len(final.edges)


def test_reading_a_json_estimate_back_leaves_the_callers_dict_as_it_was(given):
    """A live estimate compared with its replay after being read back must still be the one printed."""
    msg = wire.estimate_message(reconstruct_scan(given, RecordOptions()), "s", 1, status="final")
    line = present.to_json(msg)
    d = json.loads(line)
    assert present.from_json(d) == present.from_json(line)
    assert d == json.loads(line)


def _rotation(q) -> np.ndarray:
    """world ← array, from the pose's unit quaternion (x, y, z, w)."""
    x, y, z, w = q.x, q.y, q.z, q.w
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _walls_seen(start: codec.ScanStart, walls: list[dict]) -> list[tuple[str, np.ndarray, float, float, float]]:
    """The world file's walls in the scan's array frame, those whose perpendicular's foot the sweep crossed
    (on the wall, at a γ of the schedule): (name, normal towards the wall, offset m, σ of the bearing from
    the pose rad, σ of the offset from the pose m)."""
    pose = start.pose
    rot = _rotation(pose.orientation)
    origin = np.array([pose.position.x, pose.position.y, pose.position.z])
    cov = np.array(pose.covariance).reshape(6, 6) if len(pose.covariance) else np.zeros((6, 6))
    out = []
    for w in walls:
        a, b = np.array([*w["from"], 0.0]), np.array([*w["to"], 0.0])
        along = (b - a) / np.linalg.norm(b - a)
        n = np.array([-along[1], along[0], 0.0])
        h = float(n @ (a - origin))
        if h < 0:
            n, h = -n, -h
        on_wall = 0.0 <= float(along @ (origin + h * n - a)) <= float(np.linalg.norm(b - a))
        na = rot.T @ n
        bearing = math.atan2(na[2], na[1])
        lo, hi = sorted((start.gamma_start, start.gamma_stop))
        if on_wall and lo <= bearing <= hi:
            # The fan turns about the vertical: the pose's heading error is a bearing error; its position
            # error along the wall's normal an offset error.
            out.append((f"{w['from']}→{w['to']}", na, h, math.sqrt(cov[5, 5]), math.sqrt(float(n @ cov[:3, :3] @ n))))
    return out


@pytest.mark.slow
def test_reconstruct_json_lists_every_wall_a_room_sweep_saw(tmp_path):
    """``acquire --device sim --world room.toml`` then ``reconstruct --source --json``: each wall the sweep
    crossed is a surface, within its stated σ (and the pose's) of the world file's wall seen from the
    pose in ScanStart; a surface that claims good is one of those walls."""
    run = [sys.executable, "-m", "lelsonar"]
    acq = subprocess.run(
        [*run, "acquire", "--device", "sim", "--world", str(ROOM), "--no-zenoh", "--out", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert acq.returncode == 0, acq.stderr
    walls = tomllib.loads(ROOM.read_text())["wall"]
    paths = sorted(tmp_path.glob("scan-*.mcap"))
    assert len(paths) == len(tomllib.loads(ROOM.read_text())["pose"])
    for path in paths:
        start = next(m for m in recording.read_messages(path) if isinstance(m, codec.ScanStart))
        seen = _walls_seen(start, walls)
        assert len(seen) >= 3, f"{path.name}: the sweep should cross most of the room's walls"
        out = subprocess.run(
            [*run, "reconstruct", "--source", str(path), "--json"], capture_output=True, text=True, timeout=300
        )
        assert out.returncode == 0, out.stderr
        (estimate,) = [json.loads(line) for line in out.stdout.splitlines() if line.startswith("{")]
        surfaces = estimate["surfaces"]
        for s in surfaces:
            assert s["kind"] == "plane" and s["quality"] == s["plane"]["quality"]
            assert s["reasons"] == s["plane"]["quality_reasons"] and s["echo_count"] > 0
        for kind in ("corners", "edges"):
            assert all(f["kind"] == kind[:-1] for f in estimate[kind])
        counted = sum(u["count"] for u in estimate["unexplained"])
        assert estimate["unexplained_share"] == pytest.approx(counted / estimate["surface_echo_count"])

        def within(s: dict, wall) -> bool:
            _, na, h, sb_pose, sh_pose = wall
            normal = np.array([s["plane"]["normal"][k] for k in "xyz"])
            cov = np.array(s["covariance"]).reshape(3, 3)
            bearing = math.atan2(na[2], na[1])
            db = (s["bearing"] - bearing + math.pi) % (2 * math.pi) - math.pi
            return (
                float(normal @ na) > 0
                and abs(db) <= GATE * math.hypot(math.sqrt(cov[0, 0]), sb_pose)
                and abs(s["tilt"]) <= GATE * math.sqrt(cov[1, 1])
                and abs(s["plane"]["offset"] - h) <= GATE * math.hypot(math.sqrt(cov[2, 2]), sh_pose)
            )

        for wall in seen:
            assert any(within(s, wall) for s in surfaces), f"{path.name}: wall {wall[0]} not among the surfaces"
        for s in surfaces:
            if s["quality"] == "good":
                assert any(within(s, wall) for wall in seen), f"{path.name}: {s['label']} claims good, matches no wall"


PAPER_ROOM = Path(__file__).resolve().parent / "data" / "paper_mount_room.toml"


def _planes_ahead(start: codec.ScanStart, world: dict) -> list[tuple[str, np.ndarray, float, float, float]]:
    """The paper-mount world's floor, ceiling and the walls the vertical fan faces, in the scan's array
    frame, those whose perpendicular's foot lies in the sweep and (for a wall) on the wall: (name, normal
    towards the plane, offset m, σ of its direction from the pose rad, σ of the offset from the pose m)."""
    pose = start.pose
    rot = _rotation(pose.orientation)
    origin = np.array([pose.position.x, pose.position.y, pose.position.z])
    cov = np.array(pose.covariance).reshape(6, 6) if len(pose.covariance) else np.zeros((6, 6))
    sd_turn = math.sqrt(float(np.max(np.diag(cov)[3:])))
    lo, hi = sorted((start.gamma_start, start.gamma_stop))
    out = []
    room = world["room"]
    planes: list[tuple[str, np.ndarray, np.ndarray, object]] = [
        ("floor", np.array([0.0, 0.0, -1.0]), np.array([0.0, 0.0, room["floor"]]), None)
    ]
    if "ceiling" in room:
        planes.append(("ceiling", np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, room["ceiling"]]), None))
    for w in world["wall"]:
        a, b = np.array([*w["from"], 0.0]), np.array([*w["to"], 0.0])
        along = (b - a) / np.linalg.norm(b - a)
        planes.append((f"{w['from']}→{w['to']}", np.array([-along[1], along[0], 0.0]), a, (a, b, along)))
    for name, n, p, seg in planes:
        h = float(n @ (p - origin))
        if h < 0:
            n, h = -n, -h
        if seg is not None:
            a, b, along = seg
            if not 0.0 <= float(along @ (origin + h * n - a)) <= float(np.linalg.norm(b - a)):
                continue
        na = rot.T @ n
        bearing = math.atan2(na[2], na[1])
        # The fan crosses the plane's foot only if its normal leaves the fan by less than the beam's reach.
        if lo <= bearing <= hi and abs(na[0]) < math.sin(math.radians(20.0)):
            out.append((name, na, h, sd_turn, math.sqrt(float(n @ cov[:3, :3] @ n))))
    return out


@pytest.mark.slow
def test_reconstruct_json_lists_the_wall_and_the_floor_a_vertical_fan_saw(tmp_path):
    """``acquire --device sim --world`` a paper-mount room, then ``reconstruct --source --json``: the wall
    the robot faces (6° off square: a tilt along the capsule stack), the floor and the ceiling are surfaces
    within 3σ of the world file's, and a surface that claims good is one of them."""
    run = [sys.executable, "-m", "lelsonar"]
    acq = subprocess.run(
        [*run, "acquire", "--device", "sim", "--world", str(PAPER_ROOM), "--no-zenoh", "--out", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert acq.returncode == 0, acq.stderr
    world = tomllib.loads(PAPER_ROOM.read_text())
    (path,) = sorted(tmp_path.glob("scan*.mcap"))
    start = next(m for m in recording.read_messages(path) if isinstance(m, codec.ScanStart))
    seen = _planes_ahead(start, world)
    assert {name for name, *_ in seen} >= {"floor", "ceiling"} and len(seen) == 3, [s[0] for s in seen]
    out = subprocess.run(
        [*run, "reconstruct", "--source", str(path), "--json"], capture_output=True, text=True, timeout=300
    )
    assert out.returncode == 0, out.stderr
    (estimate,) = [json.loads(line) for line in out.stdout.splitlines() if line.startswith("{")]
    surfaces = estimate["surfaces"]

    def within(s: dict, plane) -> bool:
        _, na, h, sd_pose, sh_pose = plane
        normal = np.array([s["plane"]["normal"][k] for k in "xyz"])
        cov = np.array(s["covariance"]).reshape(3, 3)
        db = (s["bearing"] - math.atan2(na[2], na[1]) + math.pi) % (2 * math.pi) - math.pi
        return (
            float(normal @ na) > 0
            and abs(db) <= GATE * math.hypot(math.sqrt(cov[0, 0]), sd_pose)
            and abs(s["tilt"] - math.asin(na[0])) <= GATE * math.hypot(math.sqrt(cov[1, 1]), sd_pose)
            and abs(s["plane"]["offset"] - h) <= GATE * math.hypot(math.sqrt(cov[2, 2]), sh_pose)
        )

    for plane in seen:
        assert any(within(s, plane) for s in surfaces), f"{plane[0]} not among the surfaces: {surfaces}"
    for s in surfaces:
        if s["quality"] == "good":
            assert any(within(s, plane) for plane in seen), f"{s['label']} claims good, matches no plane"
