"""The threaded reader of a replay (:class:`lelsonar.recording.PayloadStream`).

It must hand on exactly what the whole-file read gives (:func:`lelsonar.recordings.reader.salvage`, then
the log-time sort): the same payloads in the same order, the same damage account, for any writer and any
damage; its thread must never die silently, nor outlive a consumer that leaves early.  The truth for the
order is what each test wrote (its log times), not the reader.
"""

from __future__ import annotations

import threading
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.writer import Writer as McapWriter

from lelsonar import codec, recording, visual
from lelsonar.errors import NotMcapError, RecordingNotFoundError
from lelsonar.recordings import reader
from lelsonar.recordings.reader import salvage
from lelsonar.reconstruct.service import ReconstructionService
from lelsonar.reconstruct.sources import replay_mcap

from .conftest import simulated_messages

STEPS = 10


def _readers_alive() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == "recording-reader" and t.is_alive()]


def _mapped(path: Path) -> bool:
    """Whether this process still maps ``path`` (the reader maps the file it reads)."""
    return str(path.resolve()) in Path("/proc/self/maps").read_text()


def _streamed(path: Path, **kwargs) -> tuple[list[recording.RecordedPayload], recording.PayloadStream]:
    with recording.PayloadStream(path, **kwargs) as stream:
        return list(stream), stream


def _whole(path: Path) -> tuple[list[recording.RecordedPayload], str | None]:
    rec = recording.Recording(salvage(path))
    return rec.payloads(), rec.damage_warning()


@pytest.fixture(scope="module")
def scan_messages() -> list:
    return simulated_messages(steps=STEPS)


@pytest.fixture(scope="module", params=["zstd", "lz4", "none"])
def ours(tmp_path_factory, scan_messages, request) -> Path:
    """Our recorder's file: one chunk per step, the viewer channels beside the contract's."""
    path = tmp_path_factory.mktemp("stream") / f"ours-{request.param}.mcap"
    with recording.McapRecorder(path, compression=request.param) as rec:
        for msg in scan_messages:
            rec.write(msg)
    return path


def _plain(path: Path, msgs: list, log_times: list[int], chunk_size: int) -> None:
    """``msgs`` written with mcap's plain writer at ``log_times``, chunks of about ``chunk_size`` bytes."""
    with open(path, "wb") as f:
        w = McapWriter(f, chunk_size=chunk_size)
        w.start(profile="", library="another program")
        channels = {}
        for cls in (codec.ScanStart, codec.Sample, codec.ScanEnd):
            schema = w.register_schema(cls.DESCRIPTOR.full_name, "protobuf", visual.file_descriptor_set(cls))
            channels[cls] = w.register_channel(f"/other/{cls.__name__}", "protobuf", schema)
        for t, msg in zip(log_times, msgs):
            w.add_message(channels[type(msg)], log_time=t, publish_time=t, data=msg.SerializeToString())
        w.finish()


def _in_log_time_order(msgs: list, log_times: list[int]) -> list[tuple[int, bytes]]:
    """The truth: (log time, payload) sorted by log time, ties in the order written."""
    return sorted(((t, m.SerializeToString()) for t, m in zip(log_times, msgs)), key=lambda p: p[0])


def test_our_recorders_file_is_handed_on_as_written_while_it_is_read(ours, scan_messages):
    got, stream = _streamed(ours)
    assert stream.streams  # finished and indexed: handed on while read, not after
    assert [(p.log_time_ns, p.payload) for p in got] == [
        (recording._message_time(m), m.SerializeToString()) for m in scan_messages]
    assert stream.recording.damage_warning() is None and not _readers_alive() and not _mapped(ours)


@pytest.mark.parametrize("chunk_size", [1, 40_000, 1 << 20])
def test_another_writers_chunks_out_of_log_time_order_come_sorted(tmp_path, scan_messages, chunk_size):
    # Log times that go back and forth across chunks (and within them), with ties: the stable sort's order.
    n = len(scan_messages)
    log_times = [(7 * i) % 5 * 1000 + (i % 3) for i in range(n)]
    path = tmp_path / "other.mcap"
    _plain(path, scan_messages, log_times, chunk_size)
    got, stream = _streamed(path, batch=1, depth=1)
    assert stream.streams
    assert [(p.log_time_ns, p.payload) for p in got] == _in_log_time_order(scan_messages, log_times)
    assert got == _whole(path)[0]


def test_a_corrupt_chunk_mid_file_costs_its_messages_and_nothing_else(ours, scan_messages, tmp_path):
    spans = [(o, o + 9 + int.from_bytes(ours.read_bytes()[o + 1:o + 9], "little"))
             for o, _t in reader.chunk_schedule(ours.read_bytes(), ours.stat().st_size)]
    start, end = spans[len(spans) // 2]
    data = bytearray(ours.read_bytes())
    data[end - 20] ^= 0x04  # inside the compressed (or stored) records: the CRC or the codec fails
    path = tmp_path / "corrupt.mcap"
    path.write_bytes(bytes(data))
    got, stream = _streamed(path, batch=1, depth=1)
    assert stream.streams  # the footer and the index are intact: still handed on while read
    lost = {p.payload for p in got} ^ {m.SerializeToString() for m in scan_messages}
    assert len(lost) == 1  # one step's chunk: its Sample, and only it
    assert [p.payload for p in got] == [m.SerializeToString() for m in scan_messages
                                        if m.SerializeToString() not in lost]
    whole, warning = _whole(path)
    assert got == whole and stream.recording.damage_warning() == warning
    assert warning is not None and f"unreadable after byte {start}" in warning


def test_a_cut_file_is_read_whole_before_it_is_handed_on(ours, tmp_path):
    data = ours.read_bytes()
    path = tmp_path / "cut.mcap"
    path.write_bytes(data[:len(data) * 2 // 3])
    got, stream = _streamed(path)
    assert not stream.streams
    whole, warning = _whole(path)
    assert got == whole and stream.recording.damage_warning() == warning and "cut at byte" in warning


@settings(max_examples=60, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.data())
def test_a_flipped_bit_anywhere_gives_what_the_whole_file_read_gives(ours, tmp_path, data):
    raw = ours.read_bytes()
    pos = data.draw(st.integers(8, len(raw) - 1), label="byte")
    damaged = bytearray(raw)
    damaged[pos] ^= 1 << data.draw(st.integers(0, 7), label="bit")
    path = tmp_path / "flipped.mcap"
    path.write_bytes(bytes(damaged))
    got, stream = _streamed(path, batch=1)
    whole, warning = _whole(path)
    assert got == whole and stream.recording.damage_warning() == warning


def test_an_error_in_the_reader_is_raised_in_the_consumer(ours, monkeypatch):
    real, calls = reader._chunk_records, []

    def failing(*args):
        calls.append(1)
        if len(calls) == 5:
            raise RuntimeError("the reader broke")
        return real(*args)

    monkeypatch.setattr(reader, "_chunk_records", failing)
    got = []
    with pytest.raises(RuntimeError, match="the reader broke"), recording.PayloadStream(ours, batch=1) as stream:
        got.extend(stream)
    assert len(got) < STEPS  # not a silently shortened replay
    assert not _readers_alive() and not _mapped(ours)


def test_an_error_in_the_decompressing_thread_is_raised_in_the_consumer(ours, monkeypatch):
    import zstandard

    class Broken:
        def __init__(self, *args, **kwargs):
            raise RuntimeError("no decompressor")

    if "zstd" not in ours.name:
        pytest.skip("only zstd chunks are decompressed ahead")
    monkeypatch.setattr(zstandard, "ZstdDecompressor", Broken)
    with pytest.raises(RuntimeError, match="no decompressor"), recording.PayloadStream(ours, batch=1) as stream:
        list(stream)
    assert not _readers_alive() and not _mapped(ours)


def test_an_error_in_the_consumer_stops_the_reader_and_closes_the_file(ours):
    class Failing(ReconstructionService):
        def handle(self, type_name, payload, **kwargs):
            if type_name == codec.Sample.DESCRIPTOR.full_name:
                raise KeyboardInterrupt  # what Ctrl-C raises in the main thread
            return super().handle(type_name, payload, **kwargs)

    # One-chunk batches, one waiting: the decompressing thread is blocked on its full queue when the consumer
    # leaves.
    with pytest.raises(KeyboardInterrupt):
        replay_mcap(recording.PayloadStream(ours, batch=1, depth=1), Failing())
    assert not _readers_alive() and not _mapped(ours)
    with pytest.raises(KeyboardInterrupt):
        replay_mcap(ours, Failing())  # a path: iter_payloads' stream, closed as well
    assert not _readers_alive() and not _mapped(ours)


def test_a_stream_not_read_closes_its_file_and_bad_paths_are_typed(ours, tmp_path):
    stream = recording.PayloadStream(ours)
    assert _mapped(ours)
    stream.close()
    assert not _mapped(ours)
    with pytest.raises(RecordingNotFoundError):
        recording.PayloadStream(tmp_path / "missing.mcap")
    (tmp_path / "text.mcap").write_text("not a recording\n")
    with pytest.raises(NotMcapError):
        recording.PayloadStream(tmp_path / "text.mcap")


def test_a_chunk_holding_messages_before_its_stated_start_is_warned_about(tmp_path, scan_messages, caplog):
    # Against the MCAP specification: the last chunk's header and its chunk index agree on a start later
    # than its message (the ScanEnd, logged before every sample).  The samples are handed on before it is
    # read; the end check finds the order broken and says so; every payload still comes, once.
    n = len(scan_messages)
    log_times = [*range(100, 100 + n - 1), 50]
    path = tmp_path / "lying.mcap"
    _plain(path, scan_messages, log_times, chunk_size=1)
    data = bytearray(path.read_bytes())
    offset, start = reader.chunk_schedule(bytes(data), len(data))[-1]
    assert start == 50
    index_at = bytes(data).rindex(offset.to_bytes(8, "little"))  # chunk_start_offset in the chunk's index
    assert index_at > offset
    for at in (offset + 9, index_at - 16):  # message_start_time, message_end_time: header, then index
        data[at:at + 16] = (10_000).to_bytes(8, "little") * 2
    path.write_bytes(bytes(data))
    with caplog.at_level("WARNING", logger="lelsonar.recording"):
        got, stream = _streamed(path, batch=1)
    assert stream.streams
    assert [p.payload for p in got] == [m.SerializeToString() for m in scan_messages]  # the order as handed on
    assert "earlier than its stated start time" in caplog.text
    assert sorted(p.payload for p in got) == sorted(p.payload for p in _whole(path)[0])
