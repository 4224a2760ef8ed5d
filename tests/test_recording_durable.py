"""Durable before published: the acquisition recording holds every step before Zenoh sees it.

The kill test runs a real `lelsonar acquire --device sim` and a Zenoh subscriber
in this process; the subscriber is the independent witness of what was
published before the SIGKILL.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from mcap.reader import make_reader

from lelsonar import codec
from lelsonar.acquire.scan_loop import ScanOutput
from lelsonar.cli.acquire import config_from_args
from lelsonar.cli.main import build_parser
from lelsonar.cli.main import main as lelsonar_main
from lelsonar.errors import RecordingError
from lelsonar.keys import ScannerKeys
from lelsonar.log import recording
from lelsonar.log.reader import salvage
from lelsonar.net.transport import hermetic_settings, open_session

from .conftest import simulated_messages
from .test_contract_mcap import RERUN


class FileWitness:
    """A publisher that, before each publish, reads the recording from disk through its own file descriptor."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.in_file: list[bool] = []

    def publish(self, message) -> None:
        try:
            stored = {m.data for m in salvage(self.path).messages}
        except RecordingError:  # nothing on disk yet, not even the magic
            stored = set()
        self.in_file.append(message.SerializeToString() in stored)


@pytest.mark.parametrize("durable", [True, False], ids=["chunk per step", "1 MiB chunks"])
def test_every_message_is_with_the_os_before_it_is_published(tmp_path, durable):
    path = tmp_path / "scan.mcap"
    witness = FileWitness(path)
    with recording.McapRecorder(path, durable=durable) as rec:
        output = ScanOutput(rec, witness)
        for msg in simulated_messages(steps=8):
            output.emit(msg)
    if durable:
        assert witness.in_file == [True] * 10
    else:  # the check can fail: with 1 MiB chunks nothing reaches the file before the end
        assert not any(witness.in_file)


def test_fsync_flag_syncs_every_step(tmp_path, monkeypatch):
    args = build_parser().parse_args(["acquire", "--device", "sim", "--fsync", "--out", str(tmp_path)])
    assert config_from_args(args).fsync
    (tmp_path / "rig.toml").write_text("[acquire]\nfsync = true\n")
    args = build_parser().parse_args(["acquire", "--config", str(tmp_path / "rig.toml")])
    assert config_from_args(args).fsync
    assert not config_from_args(build_parser().parse_args(["acquire"])).fsync
    calls = []
    real = os.fsync
    monkeypatch.setattr(os, "fsync", lambda fd: (calls.append(fd), real(fd)))
    with recording.McapRecorder(tmp_path / "scan.mcap", fsync=True) as rec:
        before = len(calls)
        for msg in simulated_messages(steps=5):
            rec.write(msg)
        assert len(calls) - before == 7  # ScanStart, 5 samples, ScanEnd
    assert len(calls) >= 8  # and once more at finish()


def test_kill_9_mid_scan_loses_nothing_that_was_published(tmp_path, zenoh_socket, capsys):
    keys = ScannerKeys("lelsonar", "k9")
    published: dict[int, bytes] = {}
    lock = threading.Lock()
    enough = threading.Event()

    def on_sample(sample) -> None:
        payload = sample.payload.to_bytes()
        with lock:
            published[codec.Sample.FromString(payload).step] = payload
            if len(published) >= 25:
                enough.set()

    cmd = [
        sys.executable,
        "-m",
        "lelsonar",
        "acquire",
        "--device",
        "sim",
        "--steps",
        "3000",
        "--scanner-id",
        "k9",
        "--out",
        str(tmp_path),
        "--mode",
        "client",
        "--connect",
        f"unixsock-stream/{zenoh_socket}",
    ]
    with open_session(hermetic_settings(zenoh_socket, listen=True)) as hub:
        sub = hub.declare_subscriber(keys.sample, on_sample)
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        try:
            arrived = enough.wait(60)
            proc.send_signal(signal.SIGKILL)  # mid-scan: 25 of 3000 steps are out
        finally:
            proc.kill()
            _, err = proc.communicate(timeout=30)
        assert arrived, f"acquire published too little: {err.decode()[-2000:]}"
        assert proc.returncode == -signal.SIGKILL
        sub.undeclare()
    with lock:
        witnessed = dict(published)

    src, out = tmp_path / "scan.mcap", tmp_path / "recovered.mcap"
    assert not salvage(src).finished  # really killed: no footer
    assert lelsonar_main(["recover", str(src), "-o", str(out)]) == 0
    assert capsys.readouterr().err.startswith("recovered ")
    with open(out, "rb") as f:
        reader = make_reader(f)
        recorded = {
            codec.Sample.FromString(m.data).step: m.data
            for _s, ch, m in reader.iter_messages(topics=["/lelsonar/sample"])
        }
        topics = {ch.topic for ch in reader.get_summary().channels.values()}
    assert set(witnessed) <= set(recorded), f"published but not recorded: {sorted(set(witnessed) - set(recorded))}"
    assert all(recorded[step] == payload for step, payload in witnessed.items())
    assert sorted(recorded) == list(range(len(recorded)))  # a prefix of the schedule, nothing skipped
    assert "/lelsonar/scan_start" in topics and "/lelsonar/scan_end" not in topics
    if Path(RERUN).exists():
        done = subprocess.run([RERUN, "mcap", "check", str(out)], capture_output=True, text=True, timeout=120)
        assert done.returncode == 0, done.stdout + done.stderr
