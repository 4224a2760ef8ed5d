"""`reconstruct --source`, `review`, `info` and `recover` on damaged and wrong files: one line, never a traceback.

The damage is placed with the recorder's own promise: every write is flushed,
so the file size after writing step k is where step k's chunk ends.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap.writer import Writer as McapWriter

from lelsonar import codec
from lelsonar.cli.main import main as lelsonar_main
from lelsonar.draw import visual
from lelsonar.log import recording
from lelsonar.v1 import reconstruction_pb2

from .conftest import simulated_messages

STEPS = 184  # the paper-test1 schedule: enough for a corner and both planes
#: What the recorder writes for each step (the Sample's chunk, then its views'), and once per scan.
PER_STEP = (
    "/lelsonar/sample",
    "/tf",
    "/lelsonar/points",
    "/lelsonar/scan_points",
    "/lelsonar/step",
    "/lelsonar/energy",
)
PER_SCAN = ("/lelsonar/scan_start", "/tf_capsules", "/lelsonar/array", "/lelsonar/scan_end")


@pytest.fixture(scope="module")
def scan(tmp_path_factory) -> tuple[Path, list, list[tuple[int, int]]]:
    """A full recorded scan, its messages, and (start, end) of each Sample's chunk in the file."""
    path = tmp_path_factory.mktemp("cli") / "scan.mcap"
    msgs = simulated_messages()
    with recording.McapRecorder(path, metadata={"device": "sim"}) as rec:
        for msg in msgs:
            rec.write(msg)
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    (sample_channel,) = (cid for cid, ch in summary.channels.items() if ch.topic == "/lelsonar/sample")
    spans = sorted(
        (c.chunk_start_offset, c.chunk_start_offset + c.chunk_length)
        for c in summary.chunk_indexes
        if sample_channel in c.message_index_offsets
    )
    assert len(spans) == STEPS
    return path, msgs, spans


def run(capsys, *argv) -> tuple[int, str, str]:
    rc = lelsonar_main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


def flipped(scan, tmp_path: Path, step: int) -> Path:
    path, _msgs, spans = scan
    start, end = spans[step]
    data = bytearray(path.read_bytes())
    data[(start + end) // 2] ^= 0x04
    out = tmp_path / "flipped.mcap"
    out.write_bytes(bytes(data))
    return out


def cut(scan, tmp_path: Path, after_step: int, extra: int = 50) -> Path:
    path, _msgs, spans = scan
    out = tmp_path / "cut.mcap"
    out.write_bytes(path.read_bytes()[: spans[after_step][1] + extra])
    return out


def warnings(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.startswith("warning:")]


# --- file errors ----------------------------------------------------------------------------------
def foreign_mcap(path: Path) -> Path:
    with open(path, "wb") as f:
        w = McapWriter(f)
        w.start()
        ch = w.register_channel("/camera/info", "json", 0)
        w.add_message(ch, log_time=1, data=b"{}", publish_time=1)
        w.finish()
    return path


BAD_FILES = {
    "missing": (lambda d: d / "missing.mcap", "no recording at"),
    "directory": (lambda d: d, "is a directory"),
    "text file": (lambda d: (d / "notes.mcap").write_text("hello\n") and d / "notes.mcap", "not a readable MCAP"),
    "empty file": (lambda d: (d / "empty.mcap").write_bytes(b"") or d / "empty.mcap", "is empty"),
}
COMMANDS = {
    "reconstruct": lambda f, d: ["reconstruct", "--source", f, "--json"],
    "review": lambda f, d: ["review", f, "-o", d / "out.rrd"],
    "info": lambda f, d: ["info", f],
    "recover": lambda f, d: ["recover", f, "-o", d / "out.mcap"],
}


def assert_one_error_line(rc: int, err: str, command: str, phrase: str) -> None:
    lines = [line for line in err.splitlines() if line.strip()]
    assert rc == 2 and "Traceback" not in err, err
    assert len(lines) == 1 and lines[0].startswith(f"lelsonar {command}: error: ") and phrase in lines[0], err


@pytest.mark.parametrize("command", COMMANDS)
@pytest.mark.parametrize("case", BAD_FILES)
def test_a_bad_path_is_one_error_line_and_exit_2(tmp_path, capsys, command, case):
    make, phrase = BAD_FILES[case]
    target = make(tmp_path)
    rc, _out, err = run(capsys, *COMMANDS[command](target, tmp_path))
    assert_one_error_line(rc, err, command, phrase)


@pytest.mark.parametrize("command", ["reconstruct", "review"])
def test_foreign_channels_only_is_no_lelsonar_scans(tmp_path, capsys, command):
    target = foreign_mcap(tmp_path / "camera.mcap")
    rc, _out, err = run(capsys, *COMMANDS[command](target, tmp_path))
    assert_one_error_line(rc, err, command, f"no lelsonar scans in {target}: its channels are /camera/info")
    rc, out, _err = run(capsys, "info", target)  # info describes it, it is not an error
    assert rc == 0 and "no lelsonar scans" in out


def _write_as_another_program(path: Path, msgs: list, topics: dict, log_times: list[int]) -> None:
    """``msgs`` written with mcap's plain writer, as another program would: a channel per message class on
    ``topics[cls]``, each message at its ``log_times`` entry, no viewer channels."""
    with open(path, "wb") as f:
        w = McapWriter(f)
        w.start(profile="", library="another simulator")
        channels = {}
        for cls, topic in topics.items():
            schema = w.register_schema(cls.DESCRIPTOR.full_name, "protobuf", visual.file_descriptor_set(cls))
            channels[cls] = w.register_channel(topic, "protobuf", schema)
        for t, msg in zip(log_times, msgs):
            w.add_message(channels[type(msg)], log_time=t, publish_time=t, data=msg.SerializeToString())
        w.finish()


def test_another_writer_of_the_schema_on_its_own_topics_gives_the_same_estimate(scan, tmp_path, capsys):
    # A simulator or bridge that writes lelsonar.v1 messages with mcap's plain writer, on topics of its
    # own and with no viewer channels, is read by the schema names of its channels.
    path, msgs, _spans = scan
    other = tmp_path / "other.mcap"
    topics = {codec.ScanStart: "/rig7/start", codec.Sample: "/rig7/ultrasound", codec.ScanEnd: "/rig7/end"}
    _write_as_another_program(other, msgs, topics, list(range(len(msgs))))
    rc, theirs, _ = run(capsys, "reconstruct", "--source", other, "--json")
    assert rc == 0
    rc, ours, _ = run(capsys, "reconstruct", "--source", path, "--json")
    assert rc == 0

    def estimate(out: str) -> dict:
        (line,) = [x for x in out.splitlines() if x.startswith("{")]
        return {k: v for k, v in json.loads(line).items() if k not in ("stamp_ns", "timings")}

    got = estimate(theirs)
    assert got["status"] == "final" and got["accounting"]["missing"] == 0
    assert got == estimate(ours)
    rc, described, _ = run(capsys, "info", other)
    assert rc == 0 and "no lelsonar scans" not in described and str(STEPS) in described


def test_a_scan_end_logged_before_its_samples_still_gives_one_complete_final(scan, tmp_path):
    # Another writer's log times (e.g. the samples' acquisition times on another clock) can sort a
    # ScanEnd before samples that follow it in the file: no false alarm, one complete final.
    _path, msgs, _spans = scan
    other = tmp_path / "late_samples.mcap"
    order = {codec.ScanStart: 0, codec.ScanEnd: 1}
    topics = {cls: recording.TOPICS[cls] for cls in (codec.ScanStart, codec.Sample, codec.ScanEnd)}
    _write_as_another_program(other, msgs, topics, [order.get(type(msg), 10 + i) for i, msg in enumerate(msgs)])
    done = subprocess.run(
        [sys.executable, "-m", "lelsonar", "reconstruct", "--source", str(other), "--json"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    (line,) = [x for x in done.stdout.splitlines() if x.startswith("{")]
    got = json.loads(line)
    assert got["status"] == "final" and got["accounting"]["missing"] == 0 and not got.get("missing_steps")
    assert "WARNING" not in done.stderr and "steps missing" not in done.stderr, done.stderr


@pytest.mark.parametrize("energy_model", [None, dict(phi0=-1.0, phi1=0.0, phi2=0.0)], ids=["absent", "negative"])
def test_a_scan_whose_energy_model_is_unusable_is_still_reconstructed_and_says_so(scan, tmp_path, energy_model):
    # The planes of the default method do not depend on E0; another writer's scan must not be lost for it.
    path, msgs, _spans = scan
    start = codec.ScanStart()
    start.CopyFrom(msgs[0])
    start.ClearField("energy_model")
    if energy_model:
        for k, v in energy_model.items():
            setattr(start.energy_model, k, v)
        start.energy_model.valid_min_range, start.energy_model.valid_max_range = 0.9, 1.8
    target = tmp_path / "uncalibrated.mcap"
    with recording.McapRecorder(target) as rec:
        for msg in [start, *msgs[1:]]:
            rec.write(msg)

    def final(p: Path) -> tuple[dict, str]:
        done = subprocess.run(
            [sys.executable, "-m", "lelsonar", "reconstruct", "--source", str(p), "--json", "--compare", ""],
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert done.returncode == 0, done.stderr
        (line,) = [x for x in done.stdout.splitlines() if x.startswith("{")]
        return json.loads(line), done.stderr

    got, err = final(target)
    assert "its energy model is unusable" in err and "uncalibrated" in err
    reference, _ = final(path)
    assert got["status"] == "final"
    for ours, theirs in zip(got["planes"], reference["planes"], strict=True):
        assert (ours["label"], ours["quality"]) == (theirs["label"], theirs["quality"])
        assert ours["offset"] == pytest.approx(theirs["offset"], abs=1e-9)


def test_a_scan_without_its_scan_start_is_reported_not_silently_skipped(scan, tmp_path):
    _path, msgs, _spans = scan
    target = tmp_path / "headless.mcap"
    with recording.McapRecorder(target) as rec:
        for msg in msgs:
            if not isinstance(msg, codec.ScanStart):
                rec.write(msg)
    done = subprocess.run(
        [sys.executable, "-m", "lelsonar", "reconstruct", "--source", str(target), "--json"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 1 and "Traceback" not in done.stderr
    assert f"scan ('s1', 1): {STEPS + 1} messages but never its ScanStart" in done.stderr
    assert done.stdout == ""  # stdout carries estimates only
    stats = json.loads(done.stderr.splitlines()[-1])["stats"]
    assert stats["scans_without_start"] == 1 and stats["finals"] == 0


@pytest.mark.parametrize("command", ["reconstruct", "review", "recover"])
def test_a_file_with_nothing_left_is_one_error_line(scan, tmp_path, capsys, command):
    target = tmp_path / "stub.mcap"
    target.write_bytes(scan[0].read_bytes()[:30])  # the magic and half a header
    rc, _out, err = run(capsys, *COMMANDS[command](target, tmp_path))
    phrase = "nothing to recover" if command == "recover" else "no lelsonar scans in"
    assert_one_error_line(rc, err, command, phrase)


# --- damaged files still give estimates, with one warning line ------------------------------------
def test_reconstruct_source_on_a_bit_flip_warns_once_and_estimates(scan, tmp_path, capsys):
    target = flipped(scan, tmp_path, step=120)
    rc, out, err = run(capsys, "reconstruct", "--source", target, "--json")
    assert rc == 0 and "Traceback" not in err
    assert len(warnings(err)) == 1
    assert re.fullmatch(
        rf"warning: {re.escape(str(target))} is damaged: 1 chunk \(1 message\) "
        rf"unreadable after "
        rf"byte {scan[2][120][0]}; {STEPS - 1} samples salvaged",
        warnings(err)[0],
    )
    finals = [json.loads(line) for line in out.splitlines()]
    assert len(finals) == 1 and finals[0]["samples_used"] == STEPS - 1 and len(finals[0]["planes"]) >= 2


def test_review_of_a_cut_file_warns_once_and_writes_the_rrd(scan, tmp_path, capsys):
    target = cut(scan, tmp_path, after_step=150)
    rc, _out, err = run(capsys, "review", target, "-o", tmp_path / "cut.rrd")
    assert rc == 0 and "Traceback" not in err and (tmp_path / "cut.rrd").stat().st_size > 0
    (line,) = warnings(err)
    assert "cut at byte" in line and line.endswith(f"; {151} samples salvaged")


def test_recover_cli_writes_what_survived_of_a_bit_flip(scan, tmp_path, capsys):
    target = flipped(scan, tmp_path, step=7)
    rc, _out, err = run(capsys, "recover", target, "-o", tmp_path / "fixed.mcap")
    # Every step's messages but step 7's Sample (its views are a chunk of their own), plus ScanStart with its
    # two viewer channels and ScanEnd.
    total = len(PER_STEP) * STEPS - 1 + len(PER_SCAN)
    assert rc == 0 and err.startswith(f"recovered {total} messages ({STEPS - 1} samples)")
    with open(tmp_path / "fixed.mcap", "rb") as f:
        steps = sorted(
            codec.Sample.FromString(m.data).step
            for _s, _c, m in make_reader(f).iter_messages(topics=["/lelsonar/sample"])
        )
    assert steps == [s for s in range(STEPS) if s != 7]


# --- lelsonar info ---------------------------------------------------------------------------------
def info_json(capsys, path: Path) -> dict:
    rc, out, err = run(capsys, "info", path, "--json")
    assert rc == 0, err
    return json.loads(out)


def test_info_of_an_intact_scan(scan, capsys):
    path, msgs, _ = scan
    info = info_json(capsys, path)
    assert info["intact"] and info["finished"] and info["messages_lost"] == 0 and info["damage"] == []
    (s,) = info["scans"]
    assert (s["scanner_id"], s["scan_id"], s["status"], s["device"]) == ("s1", 1, "complete", "sim")
    assert (s["steps_received"], s["steps_planned"], s["missing_steps"]) == (STEPS, STEPS, [])
    counts = {c["topic"]: c["messages"] for c in info["channels"]}
    assert counts == {**{t: STEPS for t in PER_STEP}, **{t: 1 for t in PER_SCAN}}
    assert info["duration_s"] == pytest.approx((msgs[-1].end_time_ns - msgs[0].start_time_ns) / 1e9)
    rc, out, _ = run(capsys, "info", path)
    assert rc == 0 and f"{STEPS}/{STEPS}" in out and "finished, intact" in out


def test_info_names_the_missing_step_and_the_damage(scan, tmp_path, capsys):
    info = info_json(capsys, flipped(scan, tmp_path, step=42))
    (s,) = info["scans"]
    assert s["missing_steps"] == [42] and s["steps_received"] == STEPS - 1 and s["status"] == "complete"
    (d,) = info["damage"]
    assert d["kind"] == "chunk" and d["offset"] == scan[2][42][0] and d["exact"]
    assert d["by_topic"] == {"/lelsonar/sample": 1}
    lost = {c["topic"]: c["lost"] for c in info["channels"]}
    assert lost["/lelsonar/sample"] == 1 and lost["/lelsonar/scan_end"] == 0


def test_a_killed_file_whose_first_sample_chunk_is_damaged_keeps_the_later_samples(scan, tmp_path, capsys):
    # The Sample channel is defined in step 0's chunk only; the file has no summary to repeat it.
    path, _msgs, spans = scan
    data = bytearray(path.read_bytes()[: spans[20][1]])
    data[(spans[0][0] + spans[0][1]) // 2] ^= 0x01
    target = tmp_path / "killed.mcap"
    target.write_bytes(bytes(data))
    (s,) = info_json(capsys, target)["scans"]
    assert s["missing_steps"] == [0, *range(21, STEPS)] and s["steps_received"] == 20
    rc, _out, err = run(capsys, "recover", target, "-o", tmp_path / "fixed.mcap")
    assert rc == 0, err
    with open(tmp_path / "fixed.mcap", "rb") as f:
        steps = sorted(
            codec.Sample.FromString(m.data).step
            for _s, _c, m in make_reader(f).iter_messages(topics=["/lelsonar/sample"])
        )
    assert steps == list(range(1, 21))
    assert [type(m) for m in recording.read_messages(tmp_path / "fixed.mcap")][:2] == [codec.ScanStart, codec.Sample]


def test_info_of_a_cut_file_and_of_skipped_steps(scan, tmp_path, capsys):
    info = info_json(capsys, cut(scan, tmp_path, after_step=99))
    (s,) = info["scans"]
    assert not info["finished"] and s["status"] == "no ScanEnd"
    assert s["missing_steps"] == list(range(100, STEPS)) and s["steps_planned"] == STEPS
    path = tmp_path / "skipped.mcap"
    with recording.McapRecorder(path) as rec:
        for msg in scan[1]:
            if not (isinstance(msg, codec.Sample) and msg.step in (3, 4)):
                rec.write(msg)
    (s,) = info_json(capsys, path)["scans"]
    assert s["missing_steps"] == [3, 4] and s["steps_received"] == STEPS - 2


def test_info_shows_recorded_estimates(tmp_path, capsys):
    est = reconstruction_pb2.Reconstruction(
        schema_version=1,
        scanner_id="s1",
        scan_id=1,
        stamp_ns=5,
        status=reconstruction_pb2.ESTIMATE_STATUS_FINAL,
        samples_used=180,
        critical_step=68,
    )
    p = est.planes.add(label="b", method="adaptive", offset=1.06, sigma=0.002, inlier_count=300, point_count=320)
    p.normal.z = 1.0
    path = tmp_path / "estimates.mcap"
    with recording.McapRecorder(path) as rec:
        rec.write(est)
    (e,) = info_json(capsys, path)["estimates"]
    assert (e["status"], e["samples_used"], e["critical_step"]) == ("final", 180, 68)
    assert e["planes"][0]["normal"] == [0.0, 0.0, 1.0] and e["planes"][0]["offset"] == 1.06
    rc, out, _ = run(capsys, "info", path)
    assert rc == 0 and "adaptive" in out and "106.00" in out


def test_info_reports_every_file_and_fails_only_for_the_bad_one(scan, tmp_path, capsys):
    rc, out, err = run(capsys, "info", tmp_path / "missing.mcap", scan[0], "--json")
    assert rc == 2 and len(err.strip().splitlines()) == 1 and "no recording at" in err
    assert json.loads(out)["scans"][0]["steps_received"] == STEPS
