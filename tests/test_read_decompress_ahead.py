"""Chunks decompressed ahead on threads, and a replay that reads only the chunks it feeds the service.

A read with chunks decompressed ahead must yield, count and find damaged what a read decompressing each
chunk when it reaches it does; a replay must give the estimates the same service gives when fed the
file's payloads one by one.
"""

from __future__ import annotations

import threading

import pytest

from lelsonar import codec
from lelsonar.errors import RecordingNotFoundError
from lelsonar.log import recording
from lelsonar.reconstruct.stream import replay
from lelsonar.reconstruct.stream.config import ReconstructConfig
from lelsonar.reconstruct.stream.replay import REPLAYED, ReplayPlan, replay_mcap
from lelsonar.reconstruct.stream.service import ReconstructionService

from .conftest import simulated_messages


# --- the replay ---------------------------------------------------------------------------------------------
def _comparable(msg: codec.Reconstruction) -> bytes:
    m = codec.Reconstruction()
    m.CopyFrom(msg)
    m.ClearField("stamp_ns")
    m.ClearField("timings")
    return m.SerializeToString()


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """Two scans of one scanner, and an estimate recorded in the file as `reconstruct --record` does."""
    path = tmp_path_factory.mktemp("ahead") / "two.mcap"
    first = simulated_messages(scan_id=1)
    with recording.McapRecorder(path) as rec:
        for msg in first:
            rec.write(msg)
        service = ReconstructionService(ReconstructConfig(provisional=False))
        for msg in first:
            for est in service.handle(msg.DESCRIPTOR.full_name, msg.SerializeToString()):
                rec.write(est)
        assert service.stats.finals == 1
        for msg in simulated_messages(scan_id=2, seed=1):
            rec.write(msg)
    return path


@pytest.mark.parametrize(("workers", "threads"), [(0, 0), (0, 1), (0, 2), (1, 1)])
def test_a_replay_gives_the_estimates_of_the_payloads_fed_one_by_one(recorded, workers, threads):
    one_by_one = ReconstructionService(ReconstructConfig(provisional=False))
    fed = 0
    for rec in recording.iter_payloads(recorded):
        if rec.type_name != codec.Reconstruction.DESCRIPTOR.full_name:
            one_by_one.handle(rec.type_name, rec.payload)
            fed += 1
    one_by_one.finish()
    replayed = ReconstructionService(ReconstructConfig(provisional=False))
    # The plan given, whatever the host's load.
    assert replay_mcap(recorded, replayed, plan=ReplayPlan(workers, threads)) == fed
    assert len(replayed.finals) == 2
    assert [_comparable(m) for m in replayed.finals.values()] == [_comparable(m) for m in one_by_one.finals.values()]


def test_a_replays_plan_is_its_workers_and_decompressing_threads_for_the_load_now(recorded, monkeypatch):
    monkeypatch.setattr(replay, "decompress_threads", lambda: 1)
    monkeypatch.setattr(replay, "THREADED_CHUNK_BYTES", 0)  # whatever its chunks
    rec = recording.open_recording(recorded)
    assert replay.replay_plan(rec, 3) == ReplayPlan(workers=3, decompress_threads=1)  # workers as configured
    asked = []
    monkeypatch.setattr(
        replay, "replay_workers", lambda configured, scans, decompressing: asked.append(decompressing) or 7 * scans
    )
    assert replay.replay_plan(rec, None) == ReplayPlan(14, 1)  # the file's scans decide, as replay_workers says
    assert asked == [True]


def test_a_file_of_small_chunks_is_decompressed_by_the_reading_thread_alone(recorded, monkeypatch):
    monkeypatch.setattr(replay, "decompress_threads", lambda: 2)
    rec = recording.open_recording(recorded)
    # A chunk per contract message, as acquire writes: the Samples' chunks are tens of kB.
    size = replay.chunk_bytes(rec)
    assert size is not None and size < replay.THREADED_CHUNK_BYTES
    asked = []
    monkeypatch.setattr(replay, "replay_workers", lambda configured, scans, decompressing: asked.append(decompressing))
    assert replay.replay_plan(rec, None).decompress_threads == 0
    assert asked == [False]  # the workers are told no thread decompresses
    monkeypatch.setattr(replay, "THREADED_CHUNK_BYTES", size)
    assert replay.replay_plan(rec, None).decompress_threads == 2


def test_a_replay_does_not_decompress_the_estimates_or_the_views(recorded):
    rec = recording.open_recording(recorded)
    got = list(rec.payloads(REPLAYED))
    assert {p.type_name for p in got} == {cls.DESCRIPTOR.full_name for cls in REPLAYED}
    s = rec.salvage
    # A chunk per contract message: only the replayed ones were decompressed.
    assert s.chunks_read == len(got)
    (estimates,) = (cid for cid, ch in s.channels.items() if ch.topic == recording.TOPICS[codec.Reconstruction])
    assert s.counts[estimates] == 1  # still counted, from the chunk's message index
    assert rec.damage_warning() is None


def test_a_replay_of_a_missing_file_raises_the_readers_error(tmp_path):
    with pytest.raises(RecordingNotFoundError, match="no recording at"):
        replay_mcap(tmp_path / "missing.mcap", ReconstructionService())


# --- chunks decompressed ahead -----------------------------------------------------------------------------
def _mcap(path, chunks: int, per_chunk: int = 3) -> None:
    """``chunks`` chunks of ``per_chunk`` messages of ~180 kB: decompressed ahead in jobs, past the bound on bytes."""
    from mcap.writer import CompressionType
    from mcap.writer import Writer as McapWriter

    with open(path, "wb") as f:
        w = McapWriter(f, compression=CompressionType.ZSTD)
        w.start(profile="", library="test")
        schema = w.register_schema("raw", "", b"")
        ids = {t: w.register_channel(t, "raw", schema) for t in ("/a", "/b")}
        for k in range(chunks):
            topic = "/a" if k % 3 else "/b"
            for i in range(per_chunk):
                t = 10 * k + i
                w.add_message(ids[topic], log_time=t, data=f"{topic}@{t}".encode() * 30_000, publish_time=t)
            w.flush()
        w.finish()


def _read(path, threads: int, want=None):
    from lelsonar.log.reader import open_mcap

    source = open_mcap(path)
    got = [(m.channel_id, m.log_time, m.data) for m in source.read(want, verify_all=False, decompress_threads=threads)]
    s = source.account
    return got, s.damage, s.counts, s.chunks_read


@pytest.mark.parametrize("flip", [None, 9, 51])  # chunks of /b (every third)
@pytest.mark.parametrize("only_b", [False, True])
def test_chunks_decompressed_ahead_read_as_chunks_decompressed_in_turn(tmp_path, flip, only_b):
    path = tmp_path / "many.mcap"
    _mcap(path, 60)
    if flip is not None:
        from mcap.reader import make_reader

        with open(path, "rb") as f:
            chunks = sorted(make_reader(f).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)
        hit = chunks[flip]
        data = bytearray(path.read_bytes())
        data[hit.chunk_start_offset + hit.chunk_length // 2] ^= 0x20
        path.write_bytes(bytes(data))
    want = (lambda ch, _schema: ch.topic == "/b") if only_b else None
    in_turn = _read(path, 0, want)
    assert in_turn[0], "nothing read"
    assert (flip is None) == (not in_turn[1])
    assert _read(path, 1, want) == _read(path, 2, want) == in_turn


def test_a_read_left_early_stops_its_decompressing_threads(tmp_path):
    from lelsonar.log.reader import open_mcap

    path = tmp_path / "many.mcap"
    _mcap(path, 60)
    messages = open_mcap(path).read(decompress_threads=2)
    assert next(messages).log_time == 0
    messages.close()
    assert not any(th.name.startswith("mcap-decompress") for th in threading.enumerate())


def test_a_read_waiting_for_a_stalled_thread_decompresses_later_chunks_itself(tmp_path, monkeypatch):
    """A thread that finds no core (here: held until the reader has done three jobs) does not stall the read."""
    from lelsonar.log import reader

    path = tmp_path / "many.mcap"
    _mcap(path, 60, per_chunk=6)  # chunks of ~1 MB: a job each
    reading = threading.get_ident()
    by_reader: list[int] = []
    stalled = threading.Event()
    real = reader.decompress_chunks

    def decompress(buf, places):
        if threading.get_ident() == reading:
            by_reader.append(len(places))
            if len(by_reader) == 3:
                stalled.set()
        else:
            assert stalled.wait(60), "the reader waited for the stalled thread instead of decompressing"
        return real(buf, places)

    in_turn = _read(path, 0)
    monkeypatch.setattr(reader, "decompress_chunks", decompress)
    assert _read(path, 1) == in_turn
    assert len(by_reader) >= 3


@pytest.mark.parametrize(
    ("cpus", "runnable", "threads"),
    [(2, 1, 1), (2, 2, 0), (2, 15, 0), (4, 1, 2), (4, 3, 1), (1, 1, 0)],
)
def test_a_replay_decompresses_ahead_on_the_cores_no_task_runs_on(cpus, runnable, threads):
    assert replay.decompress_threads(cpus, runnable) == threads


def test_the_tasks_running_now_count_the_caller():
    assert replay.runnable_tasks() >= 1


@pytest.mark.parametrize(
    ("cpus", "runnable", "workers"),
    [(2, 1, 0), (2, 2, 0), (2, 15, 0), (3, 1, 1), (4, 1, 2), (4, 3, 0), (8, 1, 2), (1, 1, 0)],
)
def test_a_replays_final_workers_leave_the_decompression_its_core(monkeypatch, cpus, runnable, workers):
    monkeypatch.setattr(replay, "workers_warm", lambda: True)  # workers ready at once: the core is still shared
    for scans in (2, replay.COLD_START_SCANS, replay.COLD_START_SHARED_SCANS - 1, None):
        assert replay.replay_workers(None, scans, cpus=cpus, runnable=runnable) == workers


@pytest.mark.parametrize(("cpus", "runnable", "workers"), [(2, 1, 1), (2, 2, 0), (4, 1, 2), (4, 3, 1), (1, 1, 0)])
@pytest.mark.parametrize("warm", [True, False])
def test_without_threads_decompressing_a_long_replays_workers_take_every_idle_core(
    monkeypatch, warm, cpus, runnable, workers
):
    monkeypatch.setattr(replay, "workers_warm", lambda: warm)
    for scans in (replay.COLD_START_SCANS, replay.COLD_START_SHARED_SCANS - 1):
        assert replay.replay_workers(None, scans, cpus=cpus, runnable=runnable, decompressing=False) == workers
    # A short one: its finals stay in the caller, whose pool is ready or not.
    assert (
        replay.replay_workers(None, replay.COLD_START_SCANS - 1, cpus=cpus, runnable=runnable, decompressing=False) == 0
    )


@pytest.mark.parametrize(("cpus", "runnable", "workers"), [(2, 1, 1), (2, 2, 0), (4, 1, 2), (4, 3, 1), (1, 1, 0)])
def test_a_very_long_replays_final_workers_take_every_idle_core(monkeypatch, cpus, runnable, workers):
    monkeypatch.setattr(replay, "workers_warm", lambda: True)
    assert replay.replay_workers(None, replay.COLD_START_SHARED_SCANS, cpus=cpus, runnable=runnable) == workers


@pytest.mark.parametrize(
    ("cpus", "runnable", "workers"),
    [(2, 1, 0), (2, 2, 0), (3, 1, 1), (4, 1, 2), (4, 2, 1), (4, 3, 0), (8, 1, 2), (1, 1, 0)],
)
def test_a_cold_start_leaves_the_decompression_its_core(monkeypatch, cpus, runnable, workers):
    monkeypatch.setattr(replay, "workers_warm", lambda: False)
    assert replay.replay_workers(None, replay.COLD_START_SCANS, cpus=cpus, runnable=runnable) == workers
    assert replay.replay_workers(None, replay.COLD_START_SCANS - 1, cpus=cpus, runnable=runnable) == 0


@pytest.mark.parametrize(("cpus", "runnable", "workers"), [(2, 1, 1), (2, 2, 0), (4, 1, 2), (4, 3, 1), (1, 1, 0)])
def test_a_long_file_starts_workers_cold_on_every_idle_core(monkeypatch, cpus, runnable, workers):
    monkeypatch.setattr(replay, "workers_warm", lambda: False)
    assert replay.replay_workers(None, replay.COLD_START_SHARED_SCANS, cpus=cpus, runnable=runnable) == workers


def test_a_replay_of_one_scan_or_with_workers_set_asks_no_load():
    assert replay.replay_workers(None, 1, cpus=8, runnable=1) == 0
    assert replay.replay_workers(3, 100, cpus=2, runnable=40) == 3


def test_a_replay_decompressing_ahead_restores_the_interpreters_switch_interval(recorded):
    import sys

    before = sys.getswitchinterval()
    seen = []
    service = ReconstructionService(ReconstructConfig(provisional=False))
    replay_mcap(recorded, service, lambda _t: seen.append(sys.getswitchinterval()), plan=ReplayPlan(0, 1))
    assert seen and max(seen) <= replay.DECOMPRESSING_SWITCH_S  # the threads get the GIL back promptly ...
    assert sys.getswitchinterval() == before  # ... for the replay only
    replay_mcap(recorded, ReconstructionService(ReconstructConfig(provisional=False)), plan=ReplayPlan(0, 0))
    assert sys.getswitchinterval() == before  # (no thread: not changed)
