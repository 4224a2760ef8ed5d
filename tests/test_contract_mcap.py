"""MCAP recordings: written, read back message for message, and accepted by the rerun CLI."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from rerun.chunk import RrdReader

from lelsonar import codec
from lelsonar.errors import RecordingError
from lelsonar.log import recording

from .conftest import make_sample, make_scan_start

RERUN = shutil.which("rerun") or str(Path(sys.executable).with_name("rerun"))


def write_scan(path: Path, steps: int = 6, **kwargs) -> list:
    sent = [make_scan_start(steps=steps)] + [make_sample(step=i) for i in range(steps)]
    sent.append(
        codec.ScanEnd(
            schema_version=1,
            scanner_id="s1",
            scan_id=7,
            status=1,
            steps_planned=steps,
            samples_sent=steps,
            end_time_ns=sent[-1].acquisition_time_ns + 1,
        )
    )
    with recording.McapRecorder(path, metadata={"scanner_id": "s1", "preset": "test"}, **kwargs) as rec:
        for msg in sent:
            rec.write(msg)
        rec.log("INFO", "scan complete", sent[-1].end_time_ns)
    return sent


@pytest.mark.parametrize("compression", ["zstd", "lz4"])
def test_recording_reads_back_message_for_message(tmp_path, compression):
    path = tmp_path / "scan.mcap"
    sent = write_scan(path, compression=compression)
    assert list(recording.read_messages(path)) == sent
    assert recording.read_metadata(path)["lelsonar.config"] == {"scanner_id": "s1", "preset": "test"}


def test_recorder_finishes_the_file_when_the_body_raises(tmp_path):
    path = tmp_path / "scan.mcap"
    with pytest.raises(RuntimeError):
        with recording.McapRecorder(path) as rec:
            rec.write(make_scan_start())
            rec.write(make_sample(step=0))
            raise RuntimeError("boom")
    assert [type(m) for m in recording.read_messages(path)] == [codec.ScanStart, codec.Sample]


def test_unfinished_or_foreign_file_is_a_recording_error(tmp_path):
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"not an mcap file at all")
    with pytest.raises(RecordingError, match="not a readable MCAP"):
        list(recording.iter_payloads(bad))
    with pytest.raises(RecordingError, match="no recording"):
        list(recording.iter_payloads(tmp_path / "missing.mcap"))


def test_rerun_cli_checks_converts_and_verifies(tmp_path):
    path, rrd = tmp_path / "scan.mcap", tmp_path / "scan.rrd"
    write_scan(path)
    for cmd in (
        [RERUN, "mcap", "check", str(path)],
        [RERUN, "mcap", "convert", str(path), "-o", str(rrd), "--application-id", "lelsonar"],
        [RERUN, "rrd", "verify", str(rrd)],
    ):
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
        assert done.returncode == 0, f"{cmd[1:3]} failed:\n{done.stdout}\n{done.stderr}"
    columns: dict[str, set[str]] = {}
    for chunk in RrdReader(rrd).store().stream().to_chunks():
        columns.setdefault(chunk.entity_path, set()).update(chunk.to_record_batch().schema.names)
    assert any(c.startswith("Transform3D:") for c in columns["/tf"])
    assert "Points3D:positions" in columns["/lelsonar/points"]
    assert any(c.startswith("TextLog:") for c in columns["/log"])
