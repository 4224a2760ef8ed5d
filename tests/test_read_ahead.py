"""Reading ahead on a thread, and a replay that reads only the chunks it feeds the service.

The replay's answers with and without reading ahead are compared on the same file: a replay must give
the estimates the same service gives when fed the file's payloads one by one on one thread.
"""

from __future__ import annotations

import contextlib
import threading

import pytest

from lelsonar import codec
from lelsonar.errors import RecordingNotFoundError
from lelsonar.log import recording
from lelsonar.log.ahead import ReadAhead
from lelsonar.reconstruct.stream.config import ReconstructConfig
from lelsonar.reconstruct.stream.service import ReconstructionService
from lelsonar.reconstruct.stream.sources import REPLAYED, replay_mcap

from .conftest import simulated_messages


class Source:
    """Yields 0 … n-1 (raising ``fail`` after ``fail_after`` items), counting what it produced and whether it
    was closed, and on which thread."""

    def __init__(self, n: int, fail_after: int | None = None, fail: BaseException | None = None) -> None:
        self.n, self.fail_after, self.fail = n, fail_after, fail
        self.produced = 0
        self.closed_on: str | None = None

    def __iter__(self):
        try:
            for i in range(self.n):
                if i == self.fail_after:
                    raise self.fail  # type: ignore[misc]
                self.produced += 1
                yield i
        finally:
            self.closed_on = threading.current_thread().name


@pytest.mark.parametrize(("n", "depth", "batch"), [(0, 1, 1), (1, 1, 1), (100, 2, 7), (1000, 4, 16)])
def test_every_item_comes_once_in_order(n, depth, batch):
    src = Source(n)
    with ReadAhead(src, depth=depth, batch=batch) as items:
        got = list(items)
    assert got == list(range(n)) and src.closed_on == "read-ahead"


def test_an_exception_of_the_source_comes_after_the_items_before_it():
    src = Source(100, fail_after=37, fail=RecordingNotFoundError("no recording at x.mcap; check the path"))
    got = []
    with pytest.raises(RecordingNotFoundError, match="no recording at x.mcap"):
        with ReadAhead(src, depth=2, batch=5) as items:
            for i in items:
                got.append(i)
    assert got == list(range(37))


@pytest.mark.parametrize("how", ["break", "raise"])
def test_a_consumer_that_stops_stops_the_thread_which_closes_the_source_and_read_a_bounded_way_ahead(how):
    depth, batch, taken = 2, 4, 3
    src = Source(10_000)
    with pytest.raises(KeyError) if how == "raise" else contextlib.nullcontext():
        with ReadAhead(src, depth=depth, batch=batch) as items:
            for i in items:
                if i == taken - 1:
                    if how == "raise":
                        raise KeyError("the consumer failed")
                    break
    assert src.closed_on == "read-ahead" and not any(th.name == "read-ahead" for th in threading.enumerate())
    # What waits in the queue, one batch being handed over and one being filled, at most.
    assert src.produced <= taken + (depth + 2) * batch


def test_bad_sizes_are_refused():
    with pytest.raises(ValueError, match="depth and batch must be >= 1"):
        ReadAhead([], depth=0)


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


def test_a_replay_gives_the_estimates_of_the_payloads_fed_one_by_one(recorded):
    one_by_one = ReconstructionService(ReconstructConfig(provisional=False))
    fed = 0
    for rec in recording.iter_payloads(recorded):
        if rec.type_name != codec.Reconstruction.DESCRIPTOR.full_name:
            one_by_one.handle(rec.type_name, rec.payload)
            fed += 1
    one_by_one.finish()
    replayed = ReconstructionService(ReconstructConfig(provisional=False))
    assert replay_mcap(recorded, replayed) == fed
    assert len(replayed.finals) == 2
    assert [_comparable(m) for m in replayed.finals.values()] == [_comparable(m) for m in one_by_one.finals.values()]


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
                w.add_message(ids[topic], log_time=t, data=f"{topic}@{t}".encode() * 50, publish_time=t)
            w.flush()
        w.finish()


def _read(path, threads: int, want=None):
    from lelsonar.log.reader import open_mcap

    source = open_mcap(path)
    got = [(m.channel_id, m.log_time, m.data) for m in source.read(want, verify_all=False, decompress_threads=threads)]
    s = source.account
    return got, s.damage, s.counts, s.chunks_read


@pytest.mark.parametrize("flip", [None, 9, 21])  # chunks of /b (every third)
@pytest.mark.parametrize("only_b", [False, True])
def test_chunks_decompressed_ahead_read_as_chunks_decompressed_in_turn(tmp_path, flip, only_b):
    path = tmp_path / "many.mcap"
    _mcap(path, 40)
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
    _mcap(path, 40)
    messages = open_mcap(path).read(decompress_threads=2)
    assert next(messages).log_time == 0
    messages.close()
    assert not any(th.name.startswith("mcap-decompress") for th in threading.enumerate())
