"""Reading a recording chunk by chunk: order, laziness, skipping, and the account it leaves.

Files are written here with ``mcap``'s own writer, so each chunk's content is known: the reader must
give what the indexed reader gives (log-time order, file order breaking ties), hold only what
overlaps in time, and decompress only what a caller wants.
"""

from __future__ import annotations

from pathlib import Path

from mcap.reader import make_reader
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter

from lelsonar import codec
from lelsonar.log import recording
from lelsonar.log.reader import open_mcap, salvage


def _write(path: Path, chunks: list[list[tuple[str, int]]]) -> None:
    """One chunk per inner list, of (topic, log time) messages; topics ``/a``, ``/b`` (raw) and ``/log``."""
    with open(path, "wb") as f:
        w = McapWriter(f, compression=CompressionType.ZSTD)
        w.start(profile="", library="test")
        schema = w.register_schema("raw", "", b"")
        ids = {t: w.register_channel(t, "raw", schema) for t in ("/a", "/b", "/log")}
        for chunk in chunks:
            for topic, t in chunk:
                w.add_message(ids[topic], log_time=t, data=f"{topic}@{t}".encode(), publish_time=t)
            w.flush()
        w.finish()


def test_overlapping_chunks_come_out_as_the_indexed_reader_orders_them(tmp_path):
    path = tmp_path / "overlap.mcap"
    # Two writers' chunks interleaved in the file with overlapping times, equal times across chunks too.
    _write(
        path,
        [[("/a", 0), ("/a", 10), ("/a", 20)], [("/b", 5), ("/b", 10), ("/b", 25)], [("/a", 30), ("/b", 30)]],
    )
    got = [m.data for m in open_mcap(path).read()]
    with open(path, "rb") as f:
        indexed = [m.data for _s, _c, m in make_reader(f).iter_messages(log_time_order=True)]
    assert got == indexed == sorted(got, key=lambda d: int(d.split(b"@")[1]))
    assert got.index(b"/a@10") < got.index(b"/b@10")  # a tie keeps file order


def test_a_read_decompresses_a_chunk_only_when_it_is_reached(tmp_path):
    path = tmp_path / "long.mcap"
    _write(path, [[("/a", 10 * k + i) for i in range(3)] for k in range(50)])
    source = open_mcap(path)
    messages = source.read()
    first = next(messages)
    assert first.data == b"/a@0" and source.account.chunks_read <= 2  # not the 50 chunks of the file
    rest = list(messages)
    assert len(rest) == 149 and source.account.chunks_read == 50 and source.account.read_done


def test_a_read_of_some_channels_skips_the_chunks_without_them_and_still_counts_them(tmp_path):
    path = tmp_path / "mixed.mcap"
    _write(path, [[("/a", 1), ("/b", 2)], [("/log", 3), ("/log", 4)], [("/a", 5)], [("/log", 6)]])
    source = open_mcap(path)
    got = [m.data for m in source.read(lambda ch, _schema: ch.topic == "/a", verify_all=False)]
    s = source.account
    assert got == [b"/a@1", b"/a@5"]
    assert s.chunks_read == 2  # the two /log chunks were not decompressed
    by_topic = {s.topic(cid): n for cid, n in s.counts.items()}
    assert by_topic == {"/a": 2, "/b": 1, "/log": 3}  # the skipped ones counted from their message index
    assert s.intact and s.messages_lost() == (0, True)


def test_a_damaged_chunk_is_found_by_the_read_and_accounted_exactly(tmp_path):
    path = tmp_path / "flip.mcap"
    _write(path, [[("/a", 1), ("/b", 2)], [("/a", 3), ("/b", 4)], [("/a", 5)]])
    data = bytearray(path.read_bytes())
    whole = salvage(path)
    second = sorted({m.offset for m in whole.messages})[1]  # the second chunk's record
    data[second + 9 + 60] ^= 0x10  # inside its compressed bytes
    path.write_bytes(bytes(data))
    source = open_mcap(path)
    assert not source.account.damage  # the framing is intact: only decompressing finds it
    got = [m.data for m in source.read()]
    s = source.account
    assert got == [b"/a@1", b"/b@2", b"/a@5"]
    (d,) = s.damage
    assert d.kind == "chunk" and d.offset == second and d.messages == 2
    assert s.messages_lost() == (2, True)
    assert salvage(path).damage == s.damage  # the in-memory reader agrees


def test_recording_payloads_stream_and_announce_their_count(tmp_path):
    from lelsonar.log.recording import McapRecorder

    path = tmp_path / "scan.mcap"
    start = codec.ScanStart(scanner_id="s1", scan_id=1, steps=3, start_time_ns=1)
    with McapRecorder(path) as rec:
        rec.write(start)
        rec.log("INFO", "started", 2)
        rec.write(codec.ScanEnd(scanner_id="s1", scan_id=1, end_time_ns=3, steps_planned=3))
    opened = recording.open_recording(path)
    assert opened.expected_payloads() == 2 and opened.has_scans
    names = [p.type_name for p in opened.payloads()]
    assert names == ["lelsonar.v1.ScanStart", "lelsonar.v1.ScanEnd"]
    assert opened.count(codec.ScanStart) == 1 and opened.damage_warning() is None
