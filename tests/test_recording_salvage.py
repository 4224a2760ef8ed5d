"""The tolerant reader and `recover`: cut and bit-flipped recordings give back every intact message.

The truth is computed independently of lelsonar's reader: the intact file is
read with the ``mcap`` package (its summary's chunk indexes, each chunk parsed
by ``mcap``'s own StreamReader), so for any cut point or flipped bit we know
which messages lie wholly in undamaged chunks.
"""

from __future__ import annotations

import io
import shutil
import subprocess
import tempfile
from collections import Counter
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.exceptions import EndOfFile
from mcap.reader import make_reader
from mcap.records import Message
from mcap.stream_reader import StreamReader

from lelsonar import codec
from lelsonar.log import recording
from lelsonar.log.reader import salvage
from lelsonar.log.recover import recover

from .conftest import simulated_messages
from .test_contract_mcap import RERUN

STEPS = 12


class Original(tuple):
    """(file bytes, [(chunk start, chunk end, its messages)], every message); a short repr for hypothesis."""

    def __repr__(self) -> str:
        return f"<recording of {len(self[0])} bytes, {len(self[1])} chunks>"


@pytest.fixture(scope="module", params=["zstd", "none"])
def original(tmp_path_factory, request) -> Original:
    """A recorded scan (one chunk per step, as `acquire` writes it), and per chunk: (start, end, its messages).

    zstd is what `acquire` writes; uncompressed chunks have no decompression to fail, only the CRC.
    """
    path = tmp_path_factory.mktemp("salvage") / "scan.mcap"
    with recording.McapRecorder(path, metadata={"device": "sim"}, compression=request.param) as rec:
        for i, msg in enumerate(simulated_messages(steps=STEPS)):
            rec.write(msg)
            if i == 0:
                rec.log("INFO", "scan started", msg.start_time_ns)
    data = path.read_bytes()
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    topics = {cid: ch.topic for cid, ch in summary.channels.items()}
    chunks = []
    for ci in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
        start, end = ci.chunk_start_offset, ci.chunk_start_offset + ci.chunk_length
        msgs = Counter(
            (topics[r.channel_id], r.log_time, r.data) for r in chunk_records(data[start:end]) if isinstance(r, Message)
        )
        chunks.append((start, end, msgs))
    every = sum((c for *_, c in chunks), Counter())
    assert sum(every.values()) == summary.statistics.message_count  # the truth accounts for every message
    return Original((data, chunks, every))


def chunk_records(chunk: bytes) -> list:
    """The records of one chunk record, by ``mcap``'s StreamReader (which ends a magic-less stream with EndOfFile)."""
    out = []
    try:
        for r in StreamReader(io.BytesIO(chunk), skip_magic=True, validate_crcs=True).records:
            out.append(r)
    except EndOfFile:
        pass
    return out


def salvaged(data: bytes) -> tuple[Counter, object]:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "damaged.mcap"
        path.write_bytes(data)
        s = salvage(path)
        rec = recording.Recording(s)
        warning = rec.damage_warning()
    got = Counter((s.topic(m.channel_id), m.log_time, m.data) for m in s.messages)
    return got, (s, warning)


def test_intact_file_is_read_whole_and_reported_intact(original):
    data, chunks, every = original
    got, (s, warning) = salvaged(data)
    assert got == every and s.intact and s.finished and warning is None
    assert s.chunks_read == len(chunks) >= STEPS  # one chunk per step at least


def check_cut(original, cut: int) -> None:
    data, chunks, every = original
    got, (s, warning) = salvaged(data[:cut])
    expected = sum((msgs for _start, end, msgs in chunks if end <= cut), Counter())
    assert got == expected, f"cut at {cut} of {len(data)}"
    if cut < len(data):
        assert not s.finished and warning is not None and "samples salvaged" in warning


@pytest.mark.parametrize("where", ["every chunk boundary", "one byte either side"])
def test_every_chunk_boundary_cut_keeps_exactly_the_chunks_before_it(original, where):
    data, chunks, _ = original
    cuts = sorted({end for _s, end, _m in chunks} | {len(data) - 1, len(data) - 2000})
    if where != "every chunk boundary":
        cuts = sorted({c + d for c in cuts for d in (-1, 1)} - {len(data)})
    for cut in cuts:
        check_cut(original, cut)


@settings(max_examples=80, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.data())
def test_a_cut_anywhere_salvages_every_complete_chunk(original, data):
    cut = data.draw(st.integers(0, len(original[0])), label="cut")
    if cut < 8:
        return  # not even the magic: covered by the file-error tests (NotMcapError)
    check_cut(original, cut)


@settings(
    max_examples=100, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(st.data())
def test_a_flipped_bit_costs_at_most_the_chunk_it_falls_in(original, data):
    raw, chunks, every = original
    pos = data.draw(st.integers(8, len(raw) - 1), label="byte")
    bit = data.draw(st.integers(0, 7), label="bit")
    damaged = bytearray(raw)
    damaged[pos] ^= 1 << bit
    got, (s, _warning) = salvaged(bytes(damaged))
    hit = [msgs for start, end, msgs in chunks if start <= pos < end]
    others = sum((msgs for start, end, msgs in chunks if not start <= pos < end), Counter())
    assert not got - every, "a salvaged message differs from every original one"
    assert not others - got, f"flip at byte {pos}: messages of undamaged chunks were lost"
    if hit and got != every:
        assert s.damage, "a chunk was lost without being reported"
        # All of the damaged chunk's messages, or none: the CRC guards the whole chunk.
        assert (got - others) in (Counter(), hit[0])


def _chunks_holding(chunks, topic: str) -> list:
    return [c for c in chunks if any(t == topic for t, _time, _data in c[2])]


def test_flipped_bit_in_a_sample_chunk_is_reported_with_its_exact_count(original):
    raw, chunks, every = original
    with_samples = _chunks_holding(chunks, recording.TOPICS[codec.Sample])
    start, end, msgs = with_samples[len(with_samples) // 2]
    assert sum(msgs.values()) == 1  # the Sample alone
    damaged = bytearray(raw)
    damaged[(start + end) // 2] ^= 0x10
    got, (s, warning) = salvaged(bytes(damaged))
    assert got == every - msgs
    assert warning == (
        f"warning: {s.path} is damaged: 1 chunk (1 message) unreadable after byte {start}; {STEPS - 1} samples salvaged"
    )


def test_each_contract_message_is_a_chunk_of_its_own_and_a_damaged_view_chunk_costs_no_step(original):
    raw, chunks, every = original
    contract = set(recording.TOPICS.values())
    mixed = [c for c in chunks if {t for t, *_ in c[2]} & contract and len(c[2]) > 1]
    assert not mixed, "a contract message shares its chunk"
    views = [c for c in chunks if not {t for t, *_ in c[2]} & contract]
    start, end, msgs = views[len(views) // 2]
    damaged = bytearray(raw)
    damaged[(start + end) // 2] ^= 0x10
    got, (s, _warning) = salvaged(bytes(damaged))
    assert got == every - msgs and len(s.damage) == 1
    assert sorted(m for m in got.elements() if m[0] in contract) == sorted(
        m for m in every.elements() if m[0] in contract
    )


def test_recover_writes_an_indexed_file_with_every_salvaged_message(original, tmp_path):
    raw, chunks, _ = original
    cut = chunks[-3][1] + 100  # mid-way into a later record: unfinished and cut
    src, dst = tmp_path / "cut.mcap", tmp_path / "recovered.mcap"
    src.write_bytes(raw[:cut])
    report = recover(src, dst)
    expected = sum((msgs for _s, end, msgs in chunks if end <= cut), Counter())
    with open(dst, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        got = Counter((ch.topic, m.log_time, m.data) for _sc, ch, m in reader.iter_messages())
    assert (
        summary is not None
        and summary.chunk_indexes
        and summary.statistics.message_count == len(list(expected.elements()))
    )
    assert got == expected and report.messages_written == sum(expected.values())
    assert recording.read_metadata(dst)["lelsonar.config"] == {"device": "sim"}
    assert salvage(dst).intact
    decoded = list(recording.read_messages(dst))
    assert isinstance(decoded[0], codec.ScanStart) and not isinstance(decoded[-1], codec.ScanEnd)


@pytest.mark.skipif(not Path(RERUN).exists() and shutil.which("rerun") is None, reason="rerun CLI not installed")
def test_rerun_accepts_the_recovered_file(original, tmp_path):
    raw, chunks, _ = original
    src, dst = tmp_path / "cut.mcap", tmp_path / "recovered.mcap"
    src.write_bytes(raw[: chunks[-2][1] + 10])
    recover(src, dst)
    done = subprocess.run([RERUN, "mcap", "check", str(dst)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
