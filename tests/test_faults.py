"""A bad day on the disk and on the wire: each fault is reproduced, and what survives is checked against the truth.

The truth is the intact data: the replay of an undamaged recording, or the scan as the simulator made it.
The network faults (a partition, a restarting router) are in :mod:`tests.test_partition`; a full disk
needs root to mount a tmpfs (skipped with the reason otherwise).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
from pathlib import Path

import pytest
import zenoh
from mcap.reader import make_reader

from lelsonar import codec
from lelsonar.cli.main import main as lelsonar_main
from lelsonar.errors import RecordingError
from lelsonar.keys import ScannerKeys
from lelsonar.log import recording
from lelsonar.log.recover import recover
from lelsonar.log.summary import summarize
from lelsonar.net.transport import MAX_MESSAGE_BYTES, ZenohSettings, open_session
from lelsonar.reconstruct.estimate import wire
from lelsonar.reconstruct.stream.config import ReconstructConfig
from lelsonar.reconstruct.stream.recovery import LogPresence, RecoveryPolicy, RecoveryRequest
from lelsonar.reconstruct.stream.replay import replay_mcap
from lelsonar.reconstruct.stream.service import ReconstructionService
from lelsonar.reconstruct.stream.sources import PayloadFifo
from lelsonar.v1 import scan_pb2

from .conftest import simulated_messages
from .test_reconstruct_gaps import Clock, feed, terminal

STEPS = 120
ENV = {**os.environ, "COLUMNS": "120", "PYTHONUNBUFFERED": "1"}


@pytest.fixture(scope="module")
def scan():
    return simulated_messages("paper-test1", seed=3, steps=STEPS)


def _record(path: Path, messages) -> Path:
    with recording.McapRecorder(path, metadata={"device": "sim"}) as rec:
        for m in messages:
            rec.write(m)
    return path


def _replay(path: Path) -> list[codec.Reconstruction]:
    service = ReconstructionService(ReconstructConfig(provisional=False))
    replay_mcap(path, service)
    return list(service.finals.values())


def _same_estimate(a: codec.Reconstruction, b: codec.Reconstruction) -> None:
    a, b = (
        codec.Reconstruction.FromString(a.SerializeToString()),
        codec.Reconstruction.FromString(b.SerializeToString()),
    )
    a.stamp_ns = b.stamp_ns = 0
    a.ClearField("timings")
    b.ClearField("timings")
    assert a == b


# --- a flipped bit in the first chunk ------------------------------------------------------------------
def test_a_flipped_bit_in_the_first_chunk_still_reconstructs_the_scan_and_info_says_what_was_lost(tmp_path, scan):
    intact = _record(tmp_path / "intact.mcap", scan)
    data = bytearray(intact.read_bytes())
    with open(intact, "rb") as f:
        first = min(make_reader(f).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)
    data[first.chunk_start_offset + first.chunk_length // 2] ^= 0x10  # inside the chunk holding the ScanStart
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(bytes(data))

    rec = recording.open_recording(damaged)
    assert rec.count(codec.ScanStart) == 0  # the only message copy of the ScanStart is lost ...
    (truth,) = _replay(intact)
    (got,) = _replay(damaged)  # ... and the scan is reconstructed all the same
    assert wire.status_name(got) == "final" and got.samples_used == STEPS
    _same_estimate(got, truth)
    (sc,) = summarize(damaged).scans
    assert sc.steps_planned == STEPS and any("ScanStart unreadable" in u for u in sc.unreadable)
    assert summarize(intact).scans[0].unreadable == []
    fixed = tmp_path / "fixed.mcap"
    recover(damaged, fixed)  # the copy survives `recover` too
    (again,) = _replay(fixed)
    _same_estimate(again, truth)


# --- conflicting duplicates ----------------------------------------------------------------------------
def _forged(sample: codec.Sample) -> codec.Sample:
    forged = codec.Sample.FromString(sample.SerializeToString())
    forged.sensors[0].distance += 0.25  # a plausible reading, 25 cm off
    forged.sensors[0].time_of_flight = 2 * forged.sensors[0].distance / 343.2
    return forged


def test_a_conflicting_duplicate_is_counted_flagged_and_settled_by_the_acquirers_log(scan):
    clock = Clock()
    asked: list[RecoveryRequest] = []
    truth = ReconstructionService(ReconstructConfig(provisional=False))
    (want,) = terminal(feed(truth, scan))
    service = ReconstructionService(
        ReconstructConfig(provisional=False), clock=clock, recover=lambda r: asked.append(r) or True
    )
    step = 40
    real = scan[1 + step]
    # The forged copy arrives first, then the acquirer's own: a conflict, not an identical resend.
    assert terminal(feed(service, [scan[0], _forged(real), *scan[1:]])) == []  # the final waits for the log
    assert RecoveryRequest("s1", 1, steps=(step,)) in asked
    clock.t = 0.5
    (got,) = terminal(feed(service, [real], origin="recovered") + service.tick())
    a = got.accounting
    assert (a.duplicates, a.conflicts) == (2, 1)  # the acquirer's live copy, then the log's
    assert wire.status_name(got) == "final"
    # The log's copy replaced the forged one: the planes are the truth's, flagged.
    for mine, theirs in zip(got.planes, want.planes, strict=True):
        assert (mine.normal.x, mine.normal.y, mine.normal.z, mine.offset) == pytest.approx(
            (theirs.normal.x, theirs.normal.y, theirs.normal.z, theirs.offset), abs=1e-9
        )
        assert mine.quality != codec.QUALITY["good"]
        assert any("differed" in r and "settled" in r for r in mine.quality_reasons)


def test_an_identical_resend_is_a_duplicate_not_a_conflict(scan):
    service = ReconstructionService(ReconstructConfig(provisional=False))
    (got,) = terminal(feed(service, [*scan[:50], scan[10], scan[20], *scan[50:]]))
    assert (got.accounting.duplicates, got.accounting.conflicts) == (2, 0)
    assert all(not any("differed" in r for r in p.quality_reasons) for p in got.planes)


def test_a_replay_with_a_conflicting_duplicate_says_it_cannot_tell(scan):
    service = ReconstructionService(ReconstructConfig(provisional=False))
    (got,) = terminal(feed(service, [scan[0], _forged(scan[41]), *scan[1:]]))
    assert got.accounting.conflicts == 1 and wire.status_name(got) == "final"
    assert all(p.quality != codec.QUALITY["good"] for p in got.planes)
    assert all(any("nothing can tell which is right" in r for r in p.quality_reasons) for p in got.planes)


def test_steps_after_a_final_timeout_re_finalise_the_scan_with_a_higher_revision(scan):
    clock = Clock()
    asked: list[RecoveryRequest] = []
    config = ReconstructConfig(provisional=False, scan_timeout=5.0, recovery_attempts=1)
    service = ReconstructionService(config, clock=clock, recover=lambda r: asked.append(r) or True)
    feed(service, scan[: 1 + 80])  # the link drops after step 79, and the log does not answer in time
    out: list = []
    for t in (1.0, 2.0, 3.0, 5.0):
        clock.t = t
        out += service.tick()
    (timed_out,) = terminal(out)
    assert wire.status_name(timed_out) == "final_timeout" and timed_out.revision == 0
    asked.clear()
    # A step after the verdict: the scan is re-opened and asked of the log whole ...
    assert feed(service, [scan[1 + 81]]) == []
    (ask,) = asked
    assert ask.want_start and ask.want_end and ask.steps == tuple(range(STEPS))
    # ... whose replies give the complete scan again, published with a higher revision.
    (again,) = terminal(feed(service, scan, origin="recovered"))
    want = terminal(feed(ReconstructionService(ReconstructConfig(provisional=False)), scan))[0]
    assert wire.status_name(again) == "final" and again.revision == 1 and list(again.missing_steps) == []
    assert again.accounting.recovered == STEPS
    for mine, theirs in zip(again.planes, want.planes, strict=True):
        assert (mine.normal.x, mine.normal.y, mine.normal.z, mine.offset) == pytest.approx(
            (theirs.normal.x, theirs.normal.y, theirs.normal.z, theirs.offset), abs=1e-9
        )


# --- an aborted scan -----------------------------------------------------------------------------------
def test_an_aborted_scan_is_estimated_aborted_over_the_steps_it_covers(scan):
    sent = 91
    end = codec.ScanEnd.FromString(scan[-1].SerializeToString())
    end.status, end.reason, end.samples_sent = scan_pb2.SCAN_STATUS_ABORTED, "stopped by request before step 91", sent
    service = ReconstructionService(ReconstructConfig(provisional=False))
    (got,) = terminal(feed(service, [*scan[: 1 + sent], end]))
    assert wire.status_name(got) == "aborted" and wire.is_terminal(got)
    assert got.samples_used == sent and got.last_step == sent - 1 and list(got.missing_steps) == []
    assert got.aborted_reason == "stopped by request before step 91"
    assert got.planes and all(any("partial sweep" in r and "91 of" in r for r in p.quality_reasons) for p in got.planes)
    assert all(p.quality != codec.QUALITY["good"] for p in got.planes)


# --- recovery that outlives an outage ------------------------------------------------------------------
def test_recovery_asks_on_while_the_acquirers_log_may_answer_and_stops_once_it_is_gone():
    clock = Clock()
    presence = LogPresence(None, ScannerKeys(), gone_after=30.0, clock=clock)
    policy = RecoveryPolicy(
        attempts=5, interval=1.0, max_interval=4.0, log_may_answer=lambda s, _: presence.may_answer(s)
    )
    key = ("s1", 1)
    assert [policy.wait_after(n) for n in range(1, 7)] == [1, 2, 4, 4, 4, 4]
    # Unknown acquirer (never seen alive): the fixed budget.
    assert policy.can_ask(4, 0.0, 100.0, key) and not policy.can_ask(5, 0.0, 100.0, key)
    assert policy.exhausted(5, 0.0, 4.0, key) and not policy.exhausted(5, 0.0, 3.9, key)
    presence.note("s1", True)  # its token is seen: its log may answer
    assert policy.can_ask(12, 0.0, 4.0, key) and not policy.exhausted(12, 0.0, 100.0, key)
    clock.t = 50.0
    presence.note("s1", False)  # the token goes (a partition, a restarting router, or the end)
    clock.t = 79.9
    assert policy.can_ask(12, 70.0, 79.9, key)  # absent less than gone_after: not gone yet
    clock.t = 80.0
    assert not policy.can_ask(12, 70.0, 80.0, key) and policy.exhausted(12, 70.0, 80.0, key)
    presence.note("s1", True)  # back (the partition healed): ask on
    assert policy.can_ask(12, 70.0, 80.0, key)
    # Patience: even a present log is given up on after `patience` s of asking without progress.
    assert not RecoveryPolicy(5, 1.0, 4.0, patience=20.0, log_may_answer=lambda *_: True).can_ask(12, 0.0, 99.0, key)


# --- a named pipe, and memory per payload --------------------------------------------------------------
@pytest.mark.parametrize(
    "argv",
    [
        ["info", "{p}"],
        ["reconstruct", "--source", "{p}"],
        ["review", "{p}", "-o", "{d}/out.rrd"],
        ["recover", "{p}", "-o", "{d}/out.mcap"],
        ["export", "{p}", "-o", "{d}/bag"],
    ],
    ids=lambda a: a[0],
)
def test_a_named_pipe_as_a_recording_is_refused_in_one_line(tmp_path, capsys, argv):
    fifo = tmp_path / "scan.mcap"
    os.mkfifo(fifo)
    cmd = [a.format(p=fifo, d=tmp_path) for a in argv]
    done: dict = {}
    worker = threading.Thread(target=lambda: done.update(rc=lelsonar_main(cmd)), daemon=True)
    worker.start()
    worker.join(60)
    if worker.is_alive():  # it opened the pipe and waits for a writer: release it, and fail
        os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
        worker.join(10)
        pytest.fail(f"`lelsonar {argv[0]}` opened the named pipe and waited for a writer")
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert done["rc"] == 2 and "Traceback" not in err, err
    assert len(lines) == 1 and lines[0].startswith(f"lelsonar {argv[0]}: error: "), err
    assert "pipe" in lines[0] and "regular file" in lines[0], err


def test_the_reader_itself_refuses_a_named_pipe_before_opening_it(tmp_path):
    fifo = tmp_path / "scan.mcap"
    os.mkfifo(fifo)  # (opening it would wait for a writer: the test would hang, not fail, without the check)
    for read in (recording.open_recording, lambda p: list(recording.read_messages(p))):
        with pytest.raises(RecordingError, match="named pipe, not a regular file"):
            read(fifo)


def test_the_payload_fifo_is_bounded_in_bytes_and_sessions_refuse_huge_messages():
    fifo = PayloadFifo(capacity=100, batch=10, max_bytes=1000)
    assert fifo.put(("t", b"x" * 600, "recovered", None), timeout=0)
    assert not fifo.put(("t", b"x" * 600, "recovered", None), timeout=0)  # over the bytes, under the count
    assert fifo.put(("t", b"x" * 400, "recovered", None), timeout=0)
    taken = fifo.take(0)
    assert len(taken) == 2 and fifo.put(("t", b"x" * 5000, "recovered", None), timeout=0)  # one larger item, alone
    cfg = ZenohSettings().to_config()
    assert json.loads(cfg.get_json("transport/link/rx/max_message_size")) == MAX_MESSAGE_BYTES
    assert MAX_MESSAGE_BYTES < 64 * 2**20  # Zenoh's own default is 1 GiB


# --- a full disk ---------------------------------------------------------------------------------------
def _why_no_tmpfs() -> str | None:
    if sys.platform != "linux" or os.geteuid() != 0:
        return "mounting a tmpfs needs root on Linux"
    return None


@pytest.mark.slow
def test_a_disk_that_fills_mid_scan_gives_one_line_and_a_published_aborted_scan_end(tmp_path):
    reason = _why_no_tmpfs()
    if reason:
        pytest.skip(reason)
    out = tmp_path / "disk"
    out.mkdir()
    # Room for the check before the scan (its upper estimate), not for what another writer takes mid-scan.
    assert subprocess.run(["mount", "-t", "tmpfs", "-o", "size=16m", "tmpfs", str(out)], timeout=20).returncode == 0
    endpoint = f"unixsock-stream/{tmp_path}/z.sock"
    link = ["--mode", "client", "--connect", endpoint]
    procs: list[subprocess.Popen] = []

    def start(*argv: str) -> subprocess.Popen:
        p = subprocess.Popen(
            [sys.executable, "-m", "lelsonar", *argv],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=ENV,
        )
        procs.append(p)
        return p

    try:
        router = start("router", "--listen", endpoint)
        assert "listening" in router.stdout.readline()
        with open_session(ZenohSettings(mode="client", connect=(endpoint,))) as watcher:
            up, mid_scan, samples = threading.Event(), threading.Event(), [0]

            def on_sample(_s: zenoh.Sample) -> None:
                samples[0] += 1
                if samples[0] == 40:
                    mid_scan.set()

            watcher.liveliness().declare_subscriber("lelsonar/*/alive/reconstruct", lambda _s: up.set(), history=True)
            watcher.declare_subscriber("lelsonar/*/sample", on_sample)
            recon = start("reconstruct", "--json", "--until-scans", "1", *link)
            assert up.wait(120), "reconstruct did not come up"
            acquire = start("acquire", "--device", "emulated", "--out", str(out), *link)
            assert mid_scan.wait(120), "the scan never got under way"
            with open(out / "another-writer", "wb") as hog:  # the disk fills under the scan
                try:
                    while True:
                        hog.write(b"\0" * 2**20)
                        hog.flush()
                except OSError:
                    pass
            acq_out, acq_err = acquire.communicate(timeout=120)
            recon_out, recon_err = recon.communicate(timeout=120)
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait(timeout=10)
        subprocess.run(["umount", "-l", str(out)], timeout=20)
    assert acquire.returncode == 1 and "Traceback" not in acq_err, acq_err[-3000:]
    failures = [line for line in acq_err.splitlines() if "cannot record to" in line]
    assert len(failures) == 1 and str(out) in failures[0] and "MiB free" in failures[0], acq_err[-3000:]
    assert "ABORTED" in failures[0] and "no space left" in failures[0]
    # The ScanEnd(ABORTED) was published with its reason: the reconstructor did not wait for its timeout.
    (live,) = [json.loads(line) for line in recon_out.splitlines() if line.startswith("{")]
    assert live["status"] == "aborted" and "no space left" in live["aborted_reason"], recon_err[-3000:]
    assert live["accounting"]["published"] == live["samples_used"] >= 40


# --- nobody listening, and how long the log is served ---------------------------------------------------
def test_acquire_counts_the_samples_nobody_subscribed_to(zenoh_socket):
    from lelsonar.acquire.scan_loop import ScanPublisher

    sample = simulated_messages(steps=2)[1]
    keys = ScannerKeys("lelsonar", "s1")
    with open_session(ZenohSettings(mode="peer", connect=(), listen=(f"unixsock-stream/{zenoh_socket}",))) as s:
        alone = ScanPublisher(s, keys)
        for _ in range(3):
            alone.publish(sample)
        assert alone.take_unmatched() == 3 and alone.unmatched == 0
        alone.close()
        got = threading.Event()
        sub = s.declare_subscriber(keys.sample, lambda _s: got.set())
        heard = ScanPublisher(s, keys)  # a subscriber matches from the start
        heard.publish(sample)
        assert got.wait(10) and heard.take_unmatched() == 0
        heard.close()
        sub.undeclare()


class _Receipts:
    def __init__(self, wanted_until: float, clock: Clock) -> None:
        self.until, self.clock = wanted_until, clock

    def wanted(self, _scan_id: int) -> bool:
        return self.clock.t < self.until


class _Stop:
    """A stop event whose wait advances the fake clock instead of sleeping."""

    def __init__(self, clock: Clock) -> None:
        self.clock = clock

    def wait(self, s: float) -> bool:
        self.clock.t += s
        return False


@pytest.mark.parametrize(("wanted_until", "served"), [(0.0, 10.0), (25.0, 25.0), (1e9, 120.0)])
def test_the_log_is_served_while_a_reconstructor_still_lacks_the_final(wanted_until, served):
    from lelsonar.acquire.service import serve_log

    clock = Clock()
    serve_log(_Receipts(wanted_until, clock), [1], 10.0, _Stop(clock), longest=120.0, clock=clock)
    assert clock.t == pytest.approx(served, abs=0.25)
