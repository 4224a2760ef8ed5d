"""MCAP records, parsed strictly: the pieces the tolerant reader (:mod:`lelsonar.log.reader`) is built of.

Every parser here raises :class:`BadRecord` on malformed input; the reader turns
that into a :class:`Damage` of the file.  :class:`Salvage` is the account of one
file that the reader fills.
"""

from __future__ import annotations

import struct
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

from isal.isal_zlib import crc32

MAGIC = b"\x89MCAP0\r\n"

# Opcodes of the MCAP specification (https://mcap.dev/spec).
OP_HEADER, OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK, OP_MESSAGE_INDEX = (
    0x01,
    0x02,
    0x03,
    0x04,
    0x05,
    0x06,
    0x07,
)
OP_CHUNK_INDEX, OP_ATTACHMENT, OP_ATTACHMENT_INDEX, OP_STATISTICS, OP_METADATA = 0x08, 0x09, 0x0A, 0x0B, 0x0C
OP_METADATA_INDEX, OP_SUMMARY_OFFSET, OP_DATA_END = 0x0D, 0x0E, 0x0F

#: A chunk may not claim to decompress to more than this (a forged size must not allocate gigabytes).
MAX_CHUNK_BYTES = 256 * 1024 * 1024

U16, U32, U64 = struct.Struct("<H"), struct.Struct("<I"), struct.Struct("<Q")
RECORD_HEAD = struct.Struct("<BQ")
CHUNK_HEAD = struct.Struct("<QQQI")  # message_start_time, message_end_time, uncompressed_size, uncompressed_crc
MESSAGE_HEAD = struct.Struct("<HIQQ")  # channel_id, sequence, log_time, publish_time
INDEX_HEAD = struct.Struct("<HI")  # message index: channel_id, byte length of the entries


class BadRecord(Exception):
    """A record that does not parse; internal, becomes a :class:`Damage`."""


@dataclass(frozen=True)
class SchemaInfo:
    id: int
    name: str
    encoding: str
    data: bytes


@dataclass(frozen=True)
class ChannelInfo:
    id: int
    schema_id: int
    topic: str
    message_encoding: str
    metadata: dict[str, str]


class RawMessage(NamedTuple):
    """One intact message as stored; ``offset`` is where its record (or its chunk) starts in the file.

    (A named tuple: one is made per message read, and a frozen dataclass costs several times as much to make.)
    """

    channel_id: int
    sequence: int
    log_time: int
    publish_time: int
    data: bytes
    offset: int


@dataclass(frozen=True)
class Damage:
    """A part of the file that could not be read.

    Attributes
    ----------
    offset : int
        First byte of the damaged region.
    length : int
        Bytes skipped.
    kind : str
        ``"chunk"`` (a chunk that fails its CRC, decompression or parsing),
        ``"tail"`` (the file ends inside a record: cut, or killed while writing),
        ``"record"`` (a record outside chunks that does not parse), ``"header"``
        (the leading magic is damaged) or ``"summary"`` (the index at the end).
    reason : str
    messages : int or None
        Messages lost, when the chunk's message index says so; None if unknown.
    messages_estimate : int
        Messages lost, estimated from the bytes when ``messages`` is None.
    by_channel : dict of int to int
        Messages lost per channel id, when known.
    """

    offset: int
    length: int
    kind: str
    reason: str
    messages: int | None = None
    messages_estimate: int = 0
    by_channel: dict[int, int] = field(default_factory=dict)

    @property
    def messages_lost(self) -> int:
        return self.messages if self.messages is not None else self.messages_estimate


@dataclass
class Salvage:
    """The account of one file: what :func:`open_mcap` and :meth:`McapSource.read` found.

    Schemas, channels, metadata, attachments and the damage to the records' framing are known
    once the file is opened; the messages counted, and a chunk whose content fails its check,
    once it has been read (``read_done``).  ``messages`` is filled by :func:`salvage` only (in
    file order; :meth:`in_log_time_order` sorts them the way the indexed reader does).
    ``finished`` is True when the file ends with an intact footer and magic (the writer called
    ``finish()``).
    """

    path: Path
    size: int
    schemas: dict[int, SchemaInfo] = field(default_factory=dict)
    channels: dict[int, ChannelInfo] = field(default_factory=dict)
    messages: list[RawMessage] = field(default_factory=list)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    attachments: list[tuple[int, int, str, str, bytes]] = field(default_factory=list)
    damage: list[Damage] = field(default_factory=list)
    chunks_read: int = 0
    finished: bool = False
    data_end_seen: bool = False
    statistics_counts: dict[int, int] | None = None  # channel id → messages, from an intact Statistics record
    orphans: int = 0  # intact messages whose channel definition was lost
    summary_start: int | None = None  # from an intact footer
    #: Messages per channel that the chunks' message indexes announce (framing only, before any read).
    indexed_counts: dict[int, int] = field(default_factory=dict)
    #: Messages per channel read intact (or, for a chunk a read skipped, as its message index says).
    counts: dict[int, int] = field(default_factory=dict)
    first_time: int | None = None  # smallest log time read
    last_time: int | None = None
    read_done: bool = False  # a read has been to the end of the file
    framing_damage: list[Damage] = field(default_factory=list)  # what the opening walk found

    @property
    def intact(self) -> bool:
        """Finished and nothing lost."""
        return self.finished and not self.damage and not self.orphans

    def in_log_time_order(self) -> list[RawMessage]:
        """The intact messages with a known channel, by log time (stable: file order breaks ties)."""
        return sorted((m for m in self.messages if m.channel_id in self.channels), key=lambda m: m.log_time)

    def count_by_channel(self) -> dict[int, int]:
        return dict(self.counts)

    def lost_by_channel(self) -> dict[int, int]:
        """Messages lost per channel: from the file's statistics when they survived, else from the damage records."""
        if self.statistics_counts is not None:
            have = self.counts
            return {cid: n - have.get(cid, 0) for cid, n in self.statistics_counts.items() if n > have.get(cid, 0)}
        lost: dict[int, int] = {}
        for d in self.damage:
            for cid, n in d.by_channel.items():
                lost[cid] = lost.get(cid, 0) + n
        return lost

    def messages_lost(self) -> tuple[int, bool]:
        """(messages lost, exact?) over the whole file."""
        if self.statistics_counts is not None:
            return sum(self.lost_by_channel().values()), True
        exact = all(d.messages is not None for d in self.damage)
        return sum(d.messages_lost for d in self.damage), exact

    def start_read(self) -> None:
        """Forget what an earlier read found: a read recounts everything past the framing."""
        self.damage = list(self.framing_damage)
        self.counts, self.orphans, self.chunks_read = {}, 0, 0
        self.first_time = self.last_time = None
        self.read_done = False

    def topic(self, channel_id: int) -> str:
        ch = self.channels.get(channel_id)
        return ch.topic if ch else f"<channel {channel_id}>"

    def schema_name(self, channel_id: int) -> str:
        ch = self.channels.get(channel_id)
        schema = self.schemas.get(ch.schema_id) if ch else None
        return schema.name if schema else ""


# --- parsing helpers (all raise BadRecord on malformed input) ----------------------------------------
class Cursor:
    __slots__ = ("buf", "pos", "end")

    def __init__(self, buf, pos: int = 0, end: int | None = None) -> None:
        self.buf, self.pos, self.end = buf, pos, len(buf) if end is None else end

    def take(self, n: int):
        if n < 0 or self.pos + n > self.end:
            raise BadRecord(f"field of {n} bytes runs past the record")
        out = self.buf[self.pos : self.pos + n]
        self.pos += n
        return out

    def u16(self) -> int:
        return U16.unpack(self.take(2))[0]

    def u32(self) -> int:
        return U32.unpack(self.take(4))[0]

    def u64(self) -> int:
        return U64.unpack(self.take(8))[0]

    def string(self) -> str:
        try:
            return str(self.take(self.u32()), "utf-8")
        except UnicodeDecodeError as exc:
            raise BadRecord(f"string is not UTF-8: {exc}") from None

    def bytes32(self) -> bytes:
        return bytes(self.take(self.u32()))

    def str_map(self) -> dict[str, str]:
        n = self.u32()
        inner = Cursor(self.buf, self.pos, self.pos + n)
        if inner.end > self.end:
            raise BadRecord("map runs past the record")
        out = {}
        while inner.pos < inner.end:
            k = inner.string()
            out[k] = inner.string()
        self.pos = inner.end
        return out


def parse_schema(c: Cursor) -> SchemaInfo:
    return SchemaInfo(c.u16(), c.string(), c.string(), c.bytes32())


def parse_channel(c: Cursor) -> ChannelInfo:
    return ChannelInfo(c.u16(), c.u16(), c.string(), c.string(), c.str_map())


_LOCAL = threading.local()  # one zstd decompressor per thread (they are not thread-safe, and costly to create)


def decompress(compression: str, data, size: int) -> bytes:
    if compression == "":
        return bytes(data)
    try:
        if compression == "zstd":
            zstd = getattr(_LOCAL, "zstd", None)
            if zstd is None:
                import zstandard

                zstd = _LOCAL.zstd = zstandard.ZstdDecompressor()
            return zstd.decompress(data, max_output_size=size)
        if compression == "lz4":
            import lz4.frame

            return lz4.frame.decompress(data)
    except Exception as exc:  # noqa: BLE001 - every codec failure is damage, whatever the library raises
        raise BadRecord(f"{compression} decompression failed: {type(exc).__name__}") from None
    raise BadRecord(f"unknown compression {compression!r}")


def chunk_frame(buf, start: int, length: int) -> tuple[str, int, int, int]:
    """Check one chunk record's layout without decompressing it.

    Returns (compression, uncompressed size, uncompressed CRC, offset of the compressed bytes).
    """
    end = start + length
    head = start + CHUNK_HEAD.size
    if head + 4 > end:
        raise BadRecord("chunk record too short for its header")
    _t0, _t1, size, crc = CHUNK_HEAD.unpack_from(buf, start)
    cl = U32.unpack_from(buf, head)[0]
    at = head + 4 + cl
    if at + 8 > end:
        raise BadRecord(f"field of {cl} bytes runs past the record")
    try:
        compression = str(buf[head + 4 : at], "utf-8")
    except UnicodeDecodeError as exc:
        raise BadRecord(f"string is not UTF-8: {exc}") from None
    if compression not in ("", "zstd", "lz4"):
        raise BadRecord(f"unknown compression {compression!r}")
    if size > MAX_CHUNK_BYTES:
        raise BadRecord(f"chunk claims {size} uncompressed bytes")
    n = U64.unpack_from(buf, at)[0]
    if at + 8 + n > end:
        raise BadRecord(f"field of {n} bytes runs past the record")
    if at + 8 + n != end:
        raise BadRecord("chunk length does not match its content")
    return compression, size, crc, at + 8


def chunk_raw(buf, start: int, length: int) -> bytes:
    """One chunk record's content decompressed and checked against its CRC: its inner records."""
    # The compressed bytes go to the decompressor as a view of the file, not a copy.
    compression, size, crc, at = chunk_frame(buf, start, length)
    view = memoryview(buf)[at : start + length]
    try:
        raw = decompress(compression, view, size)
    finally:
        view.release()  # the file's map must not be exported when it is closed
    if len(raw) != size:
        raise BadRecord(f"chunk decompressed to {len(raw)} bytes, expected {size}")
    if crc and crc32(raw) != crc:
        raise BadRecord("chunk CRC mismatch")
    return raw


def inner_records(raw) -> Iterator[tuple[int, int, int]]:
    """(opcode, start, stop of its content) of each record inside a decompressed chunk, in order.

    Raises BadRecord where a record runs past the chunk, or a message record is shorter than its header.
    """
    size = len(raw)
    unpack_head, message_head = RECORD_HEAD.unpack_from, MESSAGE_HEAD.size
    pos = 0
    while pos < size:
        if pos + 9 > size:
            raise BadRecord("field of 9 bytes runs past the record")
        op, n = unpack_head(raw, pos)
        body, stop = pos + 9, pos + 9 + n
        if stop > size:
            raise BadRecord("record inside the chunk runs past it")
        if op == OP_MESSAGE and n < message_head:
            raise BadRecord(f"field of {message_head} bytes runs past the record")
        yield op, body, stop
        pos = stop


def chunk_records(buf, start: int, length: int) -> tuple[list[tuple[int, object]], int]:
    """Parse and verify one chunk record's content; return its inner records and its uncompressed size."""
    raw = chunk_raw(buf, start, length)
    records: list[tuple[int, object]] = []
    unpack_message, message_head = MESSAGE_HEAD.unpack_from, MESSAGE_HEAD.size
    for op, body, stop in inner_records(raw):
        if op == OP_MESSAGE:
            records.append((op, (*unpack_message(raw, body), raw[body + message_head : stop])))
        elif op == OP_SCHEMA:
            records.append((op, parse_schema(Cursor(raw, body, stop))))
        elif op == OP_CHANNEL:
            records.append((op, parse_channel(Cursor(raw, body, stop))))
    return records, len(raw)


def message_index_count(buf, start: int, length: int) -> tuple[int, int]:
    if length < 6:
        raise BadRecord("message index too short")
    channel_id, n = INDEX_HEAD.unpack_from(buf, start)
    if n % 16 or 6 + n != length:
        raise BadRecord("message index length is not a whole number of entries")
    return channel_id, n // 16


class Unit:
    """A chunk, or a message outside chunks, found by the opening walk: where, when, and what it holds.

    ``index`` is the chunk's message index, ((channel id, messages), …), or None without one.
    """

    __slots__ = ("offset", "length", "start", "end", "index", "stop", "chunk")

    def __init__(self, offset: int, length: int, start: int, end: int, chunk: bool) -> None:
        self.offset, self.length, self.start, self.end, self.chunk = offset, length, start, end, chunk
        self.index: tuple[tuple[int, int], ...] | None = None
        self.stop = offset + 9 + length  # past its message index records


def looks_like_chunk(buf, body: int, length: int) -> bool:
    """Cheap test: does this record's content have a chunk's layout (known compression, lengths that add up)?"""
    head = CHUNK_HEAD.size
    if length < head + 4 + 8:
        return False
    cl = U32.unpack_from(buf, body + head)[0]
    if cl not in (0, 3, 4) or bytes(buf[body + head + 4 : body + head + 4 + cl]) not in (b"", b"lz4", b"zstd"):
        return False
    at = body + head + 4 + cl
    return at + 8 <= body + length and at + 8 + U64.unpack_from(buf, at)[0] == body + length


def summary_start(buf, size: int) -> int | None:
    """Where the summary section starts, from an intact footer; None if there is none."""
    foot = size - len(MAGIC) - 9 - 20
    if foot < len(MAGIC) or bytes(buf[size - len(MAGIC) :]) != MAGIC:
        return None
    op, length = RECORD_HEAD.unpack_from(buf, foot)
    if op != OP_FOOTER or length != 20:
        return None
    start = U64.unpack_from(buf, foot + 9)[0]
    return start if len(MAGIC) <= start <= foot else None


def top_level_record(buf, op: int, pos: int, body: int, length: int, out: Salvage, units: list[Unit]) -> None:
    """Parse one record outside chunks strictly (its content must fill its length exactly)."""
    c = Cursor(buf, body, body + length)
    if op == OP_HEADER:
        c.string(), c.string()
    elif op == OP_FOOTER:
        c.take(20)
        out.finished = body + length + len(MAGIC) == len(buf) and bytes(buf[body + length :]) == MAGIC
    elif op == OP_SCHEMA:
        s = parse_schema(c)
        out.schemas.setdefault(s.id, s)
    elif op == OP_CHANNEL:
        ch = parse_channel(c)
        out.channels.setdefault(ch.id, ch)
    elif op == OP_MESSAGE:
        cid, seq, t_log, t_pub = MESSAGE_HEAD.unpack(c.take(MESSAGE_HEAD.size))
        if cid not in out.channels:  # the spec puts a channel before its messages: this is not a message
            raise BadRecord(f"message on channel {cid}, which is not defined before it")
        if out.data_end_seen or (out.summary_start is not None and pos >= out.summary_start):
            raise BadRecord("a message record in the summary section")
        units.append(Unit(pos, length, t_log, t_log, False))
        c.pos = c.end
    elif op == OP_MESSAGE_INDEX:
        message_index_count(buf, body, length)
        c.pos = c.end
    elif op == OP_CHUNK_INDEX:
        check_chunk_index(buf, body, length)  # one per chunk in the summary: checked without a Cursor
        c.pos = c.end
    elif op == OP_ATTACHMENT:
        t_log, t_create = c.u64(), c.u64()
        name, media = c.string(), c.string()
        data = bytes(c.take(c.u64()))
        crc = c.u32()
        if crc and crc32(buf[body : c.pos - 4]) != crc:
            raise BadRecord("attachment CRC mismatch")
        out.attachments.append((t_log, t_create, name, media, data))
    elif op == OP_ATTACHMENT_INDEX:
        c.take(40)
        c.string(), c.string()
    elif op == OP_STATISTICS:
        c.take(8 + 2 + 4 * 4 + 16)
        n = c.u32()
        inner = Cursor(buf, c.pos, c.pos + n)
        if n % 10 or inner.end > c.end:
            raise BadRecord("statistics counts are not whole entries")
        counts = {}
        while inner.pos < inner.end:
            cid = inner.u16()
            counts[cid] = inner.u64()
        c.pos = inner.end
        out.statistics_counts = counts
    elif op == OP_METADATA:
        name = c.string()
        out.metadata[name] = c.str_map()
    elif op == OP_METADATA_INDEX:
        c.take(16)
        c.string()
    elif op == OP_SUMMARY_OFFSET:
        c.take(17)
    elif op == OP_DATA_END:
        c.take(4)
        out.data_end_seen = True
    else:
        raise BadRecord(f"unknown opcode {op:#04x}")
    if c.pos != c.end:
        raise BadRecord(f"{length - (c.pos - body)} bytes left over in the record")


def check_chunk_index(buf, body: int, length: int) -> None:
    """A chunk index record's layout: times and place (32 bytes), offsets, index length, compression, sizes."""
    end = body + length
    if body + 36 > end:
        raise BadRecord(f"field of 36 bytes runs past the record of {length}")
    n = U32.unpack_from(buf, body + 32)[0]
    if n % 10:
        raise BadRecord("chunk index offsets are not whole entries")
    at = body + 36 + n + 8
    if at + 4 > end:
        raise BadRecord(f"field of {n + 12} bytes runs past the record")
    cl = U32.unpack_from(buf, at)[0]
    stop = at + 4 + cl + 16
    if stop > end:
        raise BadRecord(f"field of {cl + 16} bytes runs past the record")
    if stop != end:
        raise BadRecord(f"{end - stop} bytes left over in the record")
    try:
        str(buf[at + 4 : at + 4 + cl], "utf-8")
    except UnicodeDecodeError as exc:
        raise BadRecord(f"string is not UTF-8: {exc}") from None


def read_summary(buf, size: int, out: Salvage) -> None:
    """Channels and schemas from the summary section, through the footer, if both are intact."""
    start = summary_start(buf, size)
    if not start:
        return
    foot = size - len(MAGIC) - 9 - 20
    pos = start
    try:
        while pos < foot:
            op, length = RECORD_HEAD.unpack_from(buf, pos)
            if pos + 9 + length > foot:
                raise BadRecord("summary record runs past the footer")
            c = Cursor(buf, pos + 9, pos + 9 + length)
            if op == OP_SCHEMA:
                s = parse_schema(c)
                out.schemas.setdefault(s.id, s)
            elif op == OP_CHANNEL:
                ch = parse_channel(c)
                out.channels.setdefault(ch.id, ch)
            elif op == OP_STATISTICS and out.statistics_counts is None:
                top_level_record(buf, op, pos, pos + 9, length, out, [])
            pos += 9 + length
    except (BadRecord, struct.error):
        pass  # the walk has already reported it


def resync(buf, size: int, start: int) -> int | None:
    """Offset of the next chunk at or after ``start`` that decompresses and passes its CRC, or None."""
    pos = start
    while True:
        pos = buf.find(b"\x06", pos, size)
        if pos < 0 or pos + 9 + CHUNK_HEAD.size > size:
            return None
        length = U64.unpack_from(buf, pos + 1)[0]
        if pos + 9 + length <= size and length >= CHUNK_HEAD.size + 12:
            # Cheap checks first: the compression string must be one we know.
            cl_at = pos + 9 + CHUNK_HEAD.size
            cl = U32.unpack_from(buf, cl_at)[0]
            if cl in (0, 3, 4) and bytes(buf[cl_at + 4 : cl_at + 4 + cl]) in (b"", b"lz4", b"zstd"):
                try:
                    chunk_records(buf, pos + 9, length)
                    return pos
                except (BadRecord, struct.error):
                    pass
        pos += 1


def index_after(buf, size: int, pos: int) -> tuple[int | None, dict[int, int]]:
    """Message counts from the MessageIndex records that follow a chunk ending at ``pos``."""
    counts: dict[int, int] = {}
    while pos + 9 <= size:
        op, length = RECORD_HEAD.unpack_from(buf, pos)
        if op != OP_MESSAGE_INDEX or pos + 9 + length > size:
            break
        try:
            cid, n = message_index_count(buf, pos + 9, length)
        except (BadRecord, struct.error):
            return None, {}
        counts[cid] = counts.get(cid, 0) + n
        pos += 9 + length
    return (sum(counts.values()) if counts else None), counts


def lost_region(buf, start: int, end: int, reason: str, estimate: int) -> Damage:
    """Damage over [start, end): exact counts from the message index after the chunk when it is intact."""
    size = len(buf)
    kind = "record"
    if start + 9 <= size:
        op, length = RECORD_HEAD.unpack_from(buf, start)
        after = start + 9 + length
        if op == OP_CHUNK or (after <= size and looks_like_chunk(buf, start + 9, length)):
            kind = "chunk"
            if after <= end:
                n, by_channel = index_after(buf, size, after)
                if n is not None:
                    return Damage(start, end - start, kind, reason, n, n, by_channel)
    return Damage(start, end - start, kind, reason, None, estimate)
