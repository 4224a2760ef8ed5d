"""A tolerant MCAP reader: every complete, intact message of a file, whatever happened to the rest.

The indexed reader of the ``mcap`` package needs the summary and the footer,
so a recording whose writer was killed, or that was cut or corrupted, reads as
nothing.  :func:`salvage` walks the file record by record from the start
instead:

* a chunk is kept only if it decompresses and its CRC (``uncompressed_crc``)
  matches, so a flipped bit never yields a wrong message — it costs the chunk
  it falls in, which is one step of a lelsonar recording (one chunk per step,
  see :class:`lelsonar.log.recording.McapRecorder`);
* after a damaged record it resynchronises on the next chunk whose CRC
  matches, so one bad chunk does not hide the rest of the file;
* what it skipped is reported as :class:`Damage` with the byte range and the
  number of messages lost: exact when the chunk's message index records or
  the file's statistics survived, an estimate (``≈``) otherwise.

Channels and schemas come from the data section and, when the footer is
intact, from the summary section too, so a damaged first chunk does not orphan
the messages of later ones.  Nothing here knows about lelsonar's topics.

Reading holds one chunk at a time, whatever the file's length: :func:`open_mcap`
walks the records' framing once (no decompression, except the first chunk of
each channel, to learn its definition) and :meth:`McapSource.read` then
decompresses and checks the chunks one by one, yielding their messages in log-time
order through a merge bounded by the chunks that overlap in time (as the indexed
reader does with its chunk index).  A chunk whose message index says it holds
none of the wanted channels is not decompressed at all.  :func:`salvage` is the
in-memory form: every message of the file in a list.
"""

from __future__ import annotations

import heapq
import mmap
import os
import struct
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from isal.isal_zlib import crc32

from lelsonar.errors import NotMcapError, RecordingError, RecordingNotFoundError

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

_U16, _U32, _U64 = struct.Struct("<H"), struct.Struct("<I"), struct.Struct("<Q")
_RECORD_HEAD = struct.Struct("<BQ")
_CHUNK_HEAD = struct.Struct("<QQQI")  # message_start_time, message_end_time, uncompressed_size, uncompressed_crc
_MESSAGE_HEAD = struct.Struct("<HIQQ")  # channel_id, sequence, log_time, publish_time
_INDEX_HEAD = struct.Struct("<HI")  # message index: channel_id, byte length of the entries


class _Bad(Exception):
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


@dataclass(frozen=True)
class RawMessage:
    """One intact message as stored; ``offset`` is where its record (or its chunk) starts in the file."""

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

    def _start_read(self) -> None:
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


# --- parsing helpers (all raise _Bad on malformed input) ----------------------------------------
class _Cursor:
    __slots__ = ("buf", "pos", "end")

    def __init__(self, buf, pos: int = 0, end: int | None = None) -> None:
        self.buf, self.pos, self.end = buf, pos, len(buf) if end is None else end

    def take(self, n: int):
        if n < 0 or self.pos + n > self.end:
            raise _Bad(f"field of {n} bytes runs past the record")
        out = self.buf[self.pos : self.pos + n]
        self.pos += n
        return out

    def u16(self) -> int:
        return _U16.unpack(self.take(2))[0]

    def u32(self) -> int:
        return _U32.unpack(self.take(4))[0]

    def u64(self) -> int:
        return _U64.unpack(self.take(8))[0]

    def string(self) -> str:
        try:
            return str(self.take(self.u32()), "utf-8")
        except UnicodeDecodeError as exc:
            raise _Bad(f"string is not UTF-8: {exc}") from None

    def bytes32(self) -> bytes:
        return bytes(self.take(self.u32()))

    def str_map(self) -> dict[str, str]:
        n = self.u32()
        inner = _Cursor(self.buf, self.pos, self.pos + n)
        if inner.end > self.end:
            raise _Bad("map runs past the record")
        out = {}
        while inner.pos < inner.end:
            k = inner.string()
            out[k] = inner.string()
        self.pos = inner.end
        return out


def _schema(c: _Cursor) -> SchemaInfo:
    return SchemaInfo(c.u16(), c.string(), c.string(), c.bytes32())


def _channel(c: _Cursor) -> ChannelInfo:
    return ChannelInfo(c.u16(), c.u16(), c.string(), c.string(), c.str_map())


_LOCAL = threading.local()  # one zstd decompressor per thread (they are not thread-safe, and costly to create)


def _decompress(compression: str, data, size: int) -> bytes:
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
        raise _Bad(f"{compression} decompression failed: {type(exc).__name__}") from None
    raise _Bad(f"unknown compression {compression!r}")


def _chunk_frame(buf, start: int, length: int) -> tuple[str, int, int, int]:
    """Check one chunk record's layout without decompressing it.

    Returns (compression, uncompressed size, uncompressed CRC, offset of the compressed bytes).
    """
    end = start + length
    head = start + _CHUNK_HEAD.size
    if head + 4 > end:
        raise _Bad("chunk record too short for its header")
    _t0, _t1, size, crc = _CHUNK_HEAD.unpack_from(buf, start)
    cl = _U32.unpack_from(buf, head)[0]
    at = head + 4 + cl
    if at + 8 > end:
        raise _Bad(f"field of {cl} bytes runs past the record")
    try:
        compression = str(buf[head + 4 : at], "utf-8")
    except UnicodeDecodeError as exc:
        raise _Bad(f"string is not UTF-8: {exc}") from None
    if compression not in ("", "zstd", "lz4"):
        raise _Bad(f"unknown compression {compression!r}")
    if size > MAX_CHUNK_BYTES:
        raise _Bad(f"chunk claims {size} uncompressed bytes")
    n = _U64.unpack_from(buf, at)[0]
    if at + 8 + n > end:
        raise _Bad(f"field of {n} bytes runs past the record")
    if at + 8 + n != end:
        raise _Bad("chunk length does not match its content")
    return compression, size, crc, at + 8


def _chunk_raw(buf, start: int, length: int) -> bytes:
    """One chunk record's content decompressed and checked against its CRC: its inner records."""
    # The compressed bytes go to the decompressor as a view of the file, not a copy.
    compression, size, crc, at = _chunk_frame(buf, start, length)
    view = memoryview(buf)[at : start + length]
    try:
        raw = _decompress(compression, view, size)
    finally:
        view.release()  # the file's map must not be exported when it is closed
    if len(raw) != size:
        raise _Bad(f"chunk decompressed to {len(raw)} bytes, expected {size}")
    if crc and crc32(raw) != crc:
        raise _Bad("chunk CRC mismatch")
    return raw


def _chunk_records(buf, start: int, length: int) -> tuple[list[tuple[int, object]], int]:
    """Parse and verify one chunk record's content; return its inner records and its uncompressed size."""
    raw = _chunk_raw(buf, start, length)
    size = len(raw)
    records: list[tuple[int, object]] = []
    pos = 0
    unpack_head, unpack_message, message_head = _RECORD_HEAD.unpack_from, _MESSAGE_HEAD.unpack_from, _MESSAGE_HEAD.size
    while pos < size:
        if pos + 9 > size:
            raise _Bad("field of 9 bytes runs past the record")
        op, n = unpack_head(raw, pos)
        body, stop = pos + 9, pos + 9 + n
        if stop > size:
            raise _Bad("record inside the chunk runs past it")
        if op == OP_MESSAGE:
            if n < message_head:
                raise _Bad(f"field of {message_head} bytes runs past the record")
            records.append((op, (*unpack_message(raw, body), raw[body + message_head : stop])))
        elif op == OP_SCHEMA:
            records.append((op, _schema(_Cursor(raw, body, stop))))
        elif op == OP_CHANNEL:
            records.append((op, _channel(_Cursor(raw, body, stop))))
        pos = stop
    return records, size


def _message_index_count(buf, start: int, length: int) -> tuple[int, int]:
    if length < 6:
        raise _Bad("message index too short")
    channel_id, n = _INDEX_HEAD.unpack_from(buf, start)
    if n % 16 or 6 + n != length:
        raise _Bad("message index length is not a whole number of entries")
    return channel_id, n // 16


# --- the walk -------------------------------------------------------------------------------------
def open_bytes(path: Path | str):
    """Map a file for reading; typed errors for a missing path, a directory or an empty file.

    Returns
    -------
    (mmap.mmap or bytes, int)
        The contents and the size.

    Raises
    ------
    RecordingNotFoundError
        The path does not exist or is a directory.
    NotMcapError
        The file is empty.
    RecordingError
        The file cannot be opened (permissions).
    """
    path = Path(path)
    if path.is_dir():
        raise RecordingNotFoundError(f"{path} is a directory, not an MCAP recording; give the .mcap file inside it")
    try:
        with open(path, "rb") as f:
            size = os.fstat(f.fileno()).st_size
            if size == 0:
                raise NotMcapError(f"{path} is empty, not a readable MCAP file")
            return mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ), size
    except FileNotFoundError:
        raise RecordingNotFoundError(f"no recording at {path}; check the path") from None
    except PermissionError:
        raise RecordingError(f"cannot read {path}: permission denied") from None
    except OSError as exc:
        raise RecordingError(f"cannot read {path}: {exc.strerror or exc}") from None


def _magic_ok(head: bytes) -> bool:
    """The leading magic, allowing two flipped bits (a damaged header is damage, not a foreign file)."""
    if len(head) < len(MAGIC):
        return False
    return sum(bin(a ^ b).count("1") for a, b in zip(head, MAGIC, strict=False)) <= 2


def salvage(path: Path | str) -> Salvage:
    """Read every intact message of an MCAP file, finished or not, damaged or not, into memory.

    Holds the whole file's messages: for a file of any length, read it with :func:`open_mcap`
    and :meth:`McapSource.read` instead.

    Parameters
    ----------
    path : Path or str

    Returns
    -------
    Salvage
        Messages (in file order), channels, schemas, metadata and a list of the damaged parts.

    Raises
    ------
    RecordingNotFoundError
        Missing path or a directory.
    NotMcapError
        The file does not start with the MCAP magic (e.g. a text file).
    """
    source = open_mcap(path)
    source.account.messages = list(source.read(ordered=False))
    return source.account


#: A message whose record may land here: (log time, file order, message).
_Pending = tuple[int, int, RawMessage]


class Unit:
    """A chunk, or a message outside chunks, found by the opening walk: where, when, and what it holds.

    ``index`` is the chunk's message index, ((channel id, messages), …), or None without one.
    """

    __slots__ = ("offset", "length", "start", "end", "index", "stop", "chunk")

    def __init__(self, offset: int, length: int, start: int, end: int, chunk: bool) -> None:
        self.offset, self.length, self.start, self.end, self.chunk = offset, length, start, end, chunk
        self.index: tuple[tuple[int, int], ...] | None = None
        self.stop = offset + 9 + length  # past its message index records


class McapSource:
    """An MCAP file opened for reading in bounded memory; build with :func:`open_mcap`.

    ``account`` (a :class:`Salvage` without messages) holds what the opening walk found; each
    :meth:`read` completes it with what the chunks' contents hold.
    """

    def __init__(self, account: Salvage, units: list[Unit]) -> None:
        self.account = account
        self.units = units

    @property
    def path(self) -> Path:
        return self.account.path

    def read(
        self,
        want: Callable[[ChannelInfo, SchemaInfo | None], bool] | None = None,
        *,
        verify_all: bool = True,
        ordered: bool = True,
    ) -> Iterator[RawMessage]:
        """Yield the intact messages, chunk by chunk, in log-time order (file order breaks ties).

        Parameters
        ----------
        want : callable (channel, schema) -> bool, optional
            The channels to yield (all, and the messages of unknown channels too, if None).
        verify_all : bool
            True: decompress and check every chunk, so that the damage is complete.  False: a
            chunk whose message index shows none of the wanted channels is skipped, its messages
            counted from that index.
        ordered : bool
            False: file order, with no merge.

        Holds the chunks whose time ranges overlap the message being yielded, not the file:
        chunks are merged by the message start time their header records, as the indexed
        reader merges them.  The account is complete when the iterator is exhausted.
        """
        out = self.account
        out._start_read()
        buf, size = open_bytes(out.path)
        try:
            yield from _Read(self, buf, size, want, verify_all).messages(ordered)
        finally:
            if isinstance(buf, mmap.mmap):
                buf.close()


class _Read:
    """One pass over the units of a source: decompress, check, count, yield."""

    #: Drop the file pages behind the read from the process every this many bytes (they stay in the page
    #: cache): a mapped file's touched pages count in the resident set until unmapped.
    RELEASE_EVERY = 16 * 1024 * 1024

    def __init__(self, source: McapSource, buf, size: int, want, verify_all: bool) -> None:
        self.source, self.buf, self.size = source, buf, size
        self.out = source.account
        self.want = want
        self.verify_all = verify_all
        self.wanted: dict[int, bool] = {}
        self.released = 0
        self.good_bytes = self.good_messages = 0

    def is_wanted(self, cid: int) -> bool:
        hit = self.wanted.get(cid)
        if hit is None:
            ch = self.out.channels.get(cid)
            if ch is None:
                return self.want is None  # an orphan: only a read of everything keeps it
            hit = self.wanted[cid] = self.want is None or bool(self.want(ch, self.out.schemas.get(ch.schema_id)))
        return hit

    def skippable(self, unit: Unit) -> bool:
        if self.verify_all or unit.index is None or self.want is None:
            return False
        channels = self.out.channels
        return all(cid in channels and not self.is_wanted(cid) for cid, _n in unit.index)

    def release(self, upto: int) -> None:
        buf = self.buf
        if not isinstance(buf, mmap.mmap) or upto - self.released < self.RELEASE_EVERY:
            return
        end = upto - upto % mmap.PAGESIZE
        if end > self.released:
            buf.madvise(mmap.MADV_DONTNEED, self.released, end - self.released)
            self.released = end

    def messages(self, ordered: bool) -> Iterator[RawMessage]:
        units = self.source.units
        if not ordered:
            for unit in units:
                yield from self.unit_messages(unit)
                self.release(unit.offset)
            self.done()
            return
        # later[i]: the earliest message any unit from i on may hold; what is older can be yielded.
        later = [0] * (len(units) + 1)
        later[-1] = 1 << 64
        for i in range(len(units) - 1, -1, -1):
            later[i] = min(units[i].start, later[i + 1])
        heap: list[_Pending] = []
        seq = 0
        push, pop = heapq.heappush, heapq.heappop
        for i, unit in enumerate(units):
            for m in self.unit_messages(unit):
                push(heap, (m.log_time, seq, m))
                seq += 1
            bound = later[i + 1]
            while heap and heap[0][0] <= bound:
                yield pop(heap)[2]
            self.release(unit.offset)
        while heap:
            yield pop(heap)[2]
        self.done()

    def done(self) -> None:
        self.out.damage.sort(key=lambda d: d.offset)
        self.out.read_done = True

    def unit_messages(self, unit: Unit) -> list[RawMessage]:
        """The wanted messages of one unit, counted; [] and a Damage record if its content is damaged."""
        out, buf = self.out, self.buf
        if not unit.chunk:
            cid, seq, t_log, t_pub = _MESSAGE_HEAD.unpack_from(buf, unit.offset + 9)
            self.count(cid, 1, t_log, t_log)
            if cid not in out.channels:
                out.orphans += 1
            if not self.is_wanted(cid):
                return []
            body = unit.offset + 9 + _MESSAGE_HEAD.size
            return [RawMessage(cid, seq, t_log, t_pub, bytes(buf[body : unit.offset + 9 + unit.length]), unit.offset)]
        if self.skippable(unit):
            for cid, n in unit.index or ():
                self.count(cid, n, unit.start, unit.end)
            return []
        try:
            found, counts, t0, t1 = self.parse_chunk(unit)
        except (_Bad, struct.error) as exc:
            self.damaged(unit, str(exc))
            return []
        out.chunks_read += 1
        for cid, n in counts.items():
            self.count(cid, n, t0, t1)
            if cid not in out.channels:
                out.orphans += n
        self.good_bytes += 9 + unit.length
        self.good_messages += sum(counts.values())
        return found

    def parse_chunk(self, unit: Unit) -> tuple[list[RawMessage], dict[int, int], int, int]:
        """Decompress, check and walk one chunk; nothing is kept from a chunk that fails anywhere."""
        raw = _chunk_raw(self.buf, unit.offset + 9, unit.length)
        size = len(raw)
        out = self.out
        found: list[RawMessage] = []
        counts: dict[int, int] = {}
        schemas: list[SchemaInfo] = []
        channels: list[ChannelInfo] = []
        t0, t1 = 1 << 64, 0
        unpack_head, unpack_message, message_head = (
            _RECORD_HEAD.unpack_from,
            _MESSAGE_HEAD.unpack_from,
            _MESSAGE_HEAD.size,
        )
        known, wanted = out.channels, self.wanted
        pos = 0
        while pos < size:
            if pos + 9 > size:
                raise _Bad("field of 9 bytes runs past the record")
            op, n = unpack_head(raw, pos)
            body, stop = pos + 9, pos + 9 + n
            if stop > size:
                raise _Bad("record inside the chunk runs past it")
            if op == OP_MESSAGE:
                if n < message_head:
                    raise _Bad(f"field of {message_head} bytes runs past the record")
                cid, seq, t_log, t_pub = unpack_message(raw, body)
                counts[cid] = counts.get(cid, 0) + 1
                t0, t1 = min(t0, t_log), max(t1, t_log)
                hit = wanted.get(cid)
                if hit is None:
                    hit = self.is_wanted(cid) if cid in known or not channels else self.decide(cid, channels, schemas)
                if hit:
                    found.append(RawMessage(cid, seq, t_log, t_pub, raw[body + message_head : stop], unit.offset))
            elif op == OP_SCHEMA:
                schemas.append(_schema(_Cursor(raw, body, stop)))
            elif op == OP_CHANNEL:
                channels.append(_channel(_Cursor(raw, body, stop)))
            pos = stop
        for s in schemas:
            out.schemas.setdefault(s.id, s)
        for ch in channels:
            out.channels.setdefault(ch.id, ch)
        return found, counts, t0, t1

    def decide(self, cid: int, channels: list[ChannelInfo], schemas: list[SchemaInfo]) -> bool:
        """Whether a channel defined earlier in the chunk being parsed is wanted."""
        ch = next((c for c in reversed(channels) if c.id == cid), None)
        if ch is None:
            return self.want is None
        schema = self.out.schemas.get(ch.schema_id) or next((s for s in schemas if s.id == ch.schema_id), None)
        hit = self.wanted[cid] = self.want is None or bool(self.want(ch, schema))
        return hit

    def count(self, cid: int, n: int, t0: int, t1: int) -> None:
        out = self.out
        out.counts[cid] = out.counts.get(cid, 0) + n
        if n:
            out.first_time = t0 if out.first_time is None else min(out.first_time, t0)
            out.last_time = t1 if out.last_time is None else max(out.last_time, t1)

    def damaged(self, unit: Unit, reason: str) -> None:
        if unit.index is not None:
            n = sum(k for _cid, k in unit.index)
            by_channel: dict[int, int] = {}
            for cid, k in unit.index:
                by_channel[cid] = by_channel.get(cid, 0) + k
            self.out.damage.append(Damage(unit.offset, unit.stop - unit.offset, "chunk", reason, n, n, by_channel))
            return
        nbytes = unit.stop - unit.offset
        est = round(nbytes * self.good_messages / self.good_bytes) if self.good_bytes else 0
        self.out.damage.append(Damage(unit.offset, nbytes, "chunk", reason, None, est))


def open_mcap(path: Path | str) -> McapSource:
    """Open an MCAP file, finished or not, damaged or not: its framing walked, nothing decompressed yet.

    Only the first chunk of each channel whose definition is not outside the chunks (in the
    summary) is decompressed, to learn the channel.

    Raises
    ------
    RecordingNotFoundError
        Missing path or a directory.
    NotMcapError
        The file does not start with the MCAP magic (e.g. a text file).
    """
    path = Path(path)
    buf, size = open_bytes(path)
    try:
        if not _magic_ok(bytes(buf[:8])):
            head = bytes(buf[:16])
            raise NotMcapError(f"{path} is not a readable MCAP file (it starts with {head!r}, not the MCAP magic)")
        out = Salvage(path, size)
        if bytes(buf[:8]) != MAGIC:
            out.damage.append(Damage(0, 8, "header", "the leading magic has flipped bits", 0))
        _read_summary(buf, size, out)
        units = _Walk(buf, size, out).run()
        out.framing_damage = list(out.damage)
        return McapSource(out, units)
    finally:
        if isinstance(buf, mmap.mmap):
            buf.close()


class _Walk:
    """The opening walk over the records' framing: units to read, top-level records, damage to the framing."""

    def __init__(self, buf, size: int, out: Salvage) -> None:
        self.buf, self.size, self.out = buf, size, out
        self.good_bytes = self.good_messages = self.good_raw = 0
        self.summary_start = out.summary_start = _summary_start(buf, size)
        self.units: list[Unit] = []
        self.indexes: dict[tuple[tuple[int, int], ...], tuple[tuple[int, int], ...]] = {}  # shared, not repeated
        self.learnt: set[int] = set()  # channels whose first chunk was tried
        self.released = 0

    def estimate(self, nbytes: int) -> int:
        return round(nbytes * self.good_messages / self.good_bytes) if self.good_bytes else 0

    def take_chunk(self, pos: int, length: int) -> Unit:
        t0, t1, usize, _crc = _CHUNK_HEAD.unpack_from(self.buf, pos + 9)
        unit = Unit(pos, length, t0, t1, True)
        self.units.append(unit)
        self.good_bytes += 9 + length
        self.good_raw += usize
        return unit

    def take_index(self, unit: Unit, entries: dict[int, int], stop: int) -> None:
        """The message index after a chunk: what the chunk holds, per channel."""
        unit.stop = stop
        if not entries:
            return
        key = tuple(sorted(entries.items()))
        unit.index = self.indexes.setdefault(key, key)
        n = sum(entries.values())
        self.good_messages += n
        counts = self.out.indexed_counts
        for cid, k in key:
            counts[cid] = counts.get(cid, 0) + k
        if n == 0 and unit.start == unit.end == 0:
            unit.start = 1 << 64  # no message: it holds nothing back
        unknown = [cid for cid, _k in key if cid not in self.out.channels and cid not in self.learnt]
        if unknown:
            # The first chunk of a channel holds its definition: read it now, so a read can choose channels.
            self.learnt.update(unknown)
            try:
                records, _usize = _chunk_records(self.buf, unit.offset + 9, unit.length)
            except (_Bad, struct.error):
                return  # damaged: the read says so
            for rop, rec in records:
                if rop == OP_SCHEMA:
                    self.out.schemas.setdefault(rec.id, rec)  # type: ignore[attr-defined]
                elif rop == OP_CHANNEL:
                    self.out.channels.setdefault(rec.id, rec)  # type: ignore[attr-defined]

    def damaged(self, pos: int, reason: str) -> int | None:
        """Record damage starting at ``pos``; return where reading resumes (the next intact chunk), or None."""
        buf, size, out = self.buf, self.size, self.out
        if self.summary_start is not None and pos >= self.summary_start:
            # In the summary section: no message can be lost here, and _read_summary reads it via the footer.
            out.damage.append(Damage(pos, size - pos, "summary", f"summary section unreadable at byte {pos}", 0))
            return None
        nxt = _resync(buf, size, pos + 1)
        if nxt is not None:
            out.damage.append(_lost(buf, pos, nxt, reason, self.estimate(nxt - pos)))
            return nxt
        if out.data_end_seen:
            out.damage.append(Damage(pos, size - pos, "summary", f"summary section unreadable at byte {pos}", 0))
            return None
        op = _RECORD_HEAD.unpack_from(buf, pos)[0] if pos + 9 <= size else 0
        est = max(1, self.estimate(size - pos)) if self.good_bytes else 0
        if op == OP_CHUNK and pos + 9 + _CHUNK_HEAD.size <= size and self.good_raw:
            usize = _CHUNK_HEAD.unpack_from(buf, pos + 9)[2]
            if usize <= MAX_CHUNK_BYTES:
                est = max(1, round(usize * self.good_messages / self.good_raw))
        out.damage.append(Damage(pos, size - pos, "tail", reason, None, est))
        return None

    def run(self) -> list[Unit]:
        buf, size, out = self.buf, self.size, self.out
        pos = len(MAGIC)
        chunk: Unit | None = None  # the chunk whose message index records may follow
        entries: dict[int, int] = {}
        while pos < size:
            if pos + 9 > size:
                self.damaged(pos, "the file ends inside a record header")
                break
            op, length = _RECORD_HEAD.unpack_from(buf, pos)
            body = pos + 9
            if chunk is not None and (op != OP_MESSAGE_INDEX or body + length > size):
                self.take_index(chunk, entries, pos)
                chunk, entries = None, {}
            if body + length > size:
                nxt = self.damaged(
                    pos,
                    "the file ends inside a record (cut, or the writer was killed)"
                    if op == OP_CHUNK
                    else f"record runs past the end of the file (opcode {op:#04x}, length {length})",
                )
            elif op == OP_CHUNK:
                try:
                    _chunk_frame(buf, body, length)
                except (_Bad, struct.error) as exc:
                    nxt = self.damaged(pos, str(exc))
                else:
                    chunk = self.take_chunk(pos, length)
                    nxt = body + length
            elif op == OP_MESSAGE_INDEX and chunk is not None:
                try:
                    cid, n = _message_index_count(buf, body, length)
                except (_Bad, struct.error) as exc:
                    self.take_index(chunk, {}, pos)
                    chunk, entries = None, {}
                    nxt = self.damaged(pos, f"record with opcode {op:#04x}: {exc}")
                else:
                    entries[cid] = entries.get(cid, 0) + n
                    nxt = body + length
            elif _looks_like_chunk(buf, body, length):
                try:
                    _chunk_records(buf, body, length)  # rare: worth proving before calling it intact
                except (_Bad, struct.error) as exc:
                    nxt = self.damaged(pos, str(exc))
                else:
                    out.damage.append(
                        Damage(
                            pos,
                            1,
                            "record",
                            f"opcode at byte {pos} damaged ({op:#04x}); the chunk behind it is intact",
                            0,
                        )
                    )
                    chunk = self.take_chunk(pos, length)
                    nxt = body + length
            else:
                try:
                    _top_level(buf, op, pos, body, length, out, self.units)
                except (_Bad, struct.error) as exc:
                    nxt = self.damaged(pos, f"record with opcode {op:#04x}: {exc}")
                else:
                    if op == OP_FOOTER:
                        break
                    nxt = body + length
            if nxt is None:
                break
            pos = nxt
            if isinstance(buf, mmap.mmap) and pos - self.released >= _Read.RELEASE_EVERY:
                end = pos - pos % mmap.PAGESIZE
                buf.madvise(mmap.MADV_DONTNEED, self.released, end - self.released)
                self.released = end
        if chunk is not None:
            self.take_index(chunk, entries, min(pos, size))
        return self.units


def _looks_like_chunk(buf, body: int, length: int) -> bool:
    """Cheap test: does this record's content have a chunk's layout (known compression, lengths that add up)?"""
    head = _CHUNK_HEAD.size
    if length < head + 4 + 8:
        return False
    cl = _U32.unpack_from(buf, body + head)[0]
    if cl not in (0, 3, 4) or bytes(buf[body + head + 4 : body + head + 4 + cl]) not in (b"", b"lz4", b"zstd"):
        return False
    at = body + head + 4 + cl
    return at + 8 <= body + length and at + 8 + _U64.unpack_from(buf, at)[0] == body + length


def _summary_start(buf, size: int) -> int | None:
    """Where the summary section starts, from an intact footer; None if there is none."""
    foot = size - len(MAGIC) - 9 - 20
    if foot < len(MAGIC) or bytes(buf[size - len(MAGIC) :]) != MAGIC:
        return None
    op, length = _RECORD_HEAD.unpack_from(buf, foot)
    if op != OP_FOOTER or length != 20:
        return None
    start = _U64.unpack_from(buf, foot + 9)[0]
    return start if len(MAGIC) <= start <= foot else None


def _top_level(buf, op: int, pos: int, body: int, length: int, out: Salvage, units: list[Unit]) -> None:
    """Parse one record outside chunks strictly (its content must fill its length exactly)."""
    c = _Cursor(buf, body, body + length)
    if op == OP_HEADER:
        c.string(), c.string()
    elif op == OP_FOOTER:
        c.take(20)
        out.finished = body + length + len(MAGIC) == len(buf) and bytes(buf[body + length :]) == MAGIC
    elif op == OP_SCHEMA:
        s = _schema(c)
        out.schemas.setdefault(s.id, s)
    elif op == OP_CHANNEL:
        ch = _channel(c)
        out.channels.setdefault(ch.id, ch)
    elif op == OP_MESSAGE:
        cid, seq, t_log, t_pub = _MESSAGE_HEAD.unpack(c.take(_MESSAGE_HEAD.size))
        if cid not in out.channels:  # the spec puts a channel before its messages: this is not a message
            raise _Bad(f"message on channel {cid}, which is not defined before it")
        if out.data_end_seen or (out.summary_start is not None and pos >= out.summary_start):
            raise _Bad("a message record in the summary section")
        units.append(Unit(pos, length, t_log, t_log, False))
        c.pos = c.end
    elif op == OP_MESSAGE_INDEX:
        _message_index_count(buf, body, length)
        c.pos = c.end
    elif op == OP_CHUNK_INDEX:
        c.take(32)
        n = c.u32()
        if n % 10:
            raise _Bad("chunk index offsets are not whole entries")
        c.take(n + 8)
        c.string()
        c.take(16)
    elif op == OP_ATTACHMENT:
        t_log, t_create = c.u64(), c.u64()
        name, media = c.string(), c.string()
        data = bytes(c.take(c.u64()))
        crc = c.u32()
        if crc and crc32(buf[body : c.pos - 4]) != crc:
            raise _Bad("attachment CRC mismatch")
        out.attachments.append((t_log, t_create, name, media, data))
    elif op == OP_ATTACHMENT_INDEX:
        c.take(40)
        c.string(), c.string()
    elif op == OP_STATISTICS:
        c.take(8 + 2 + 4 * 4 + 16)
        n = c.u32()
        inner = _Cursor(buf, c.pos, c.pos + n)
        if n % 10 or inner.end > c.end:
            raise _Bad("statistics counts are not whole entries")
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
        raise _Bad(f"unknown opcode {op:#04x}")
    if c.pos != c.end:
        raise _Bad(f"{length - (c.pos - body)} bytes left over in the record")


def _read_summary(buf, size: int, out: Salvage) -> None:
    """Channels and schemas from the summary section, through the footer, if both are intact."""
    summary_start = _summary_start(buf, size)
    if not summary_start:
        return
    foot = size - len(MAGIC) - 9 - 20
    pos = summary_start
    try:
        while pos < foot:
            op, length = _RECORD_HEAD.unpack_from(buf, pos)
            if pos + 9 + length > foot:
                raise _Bad("summary record runs past the footer")
            c = _Cursor(buf, pos + 9, pos + 9 + length)
            if op == OP_SCHEMA:
                s = _schema(c)
                out.schemas.setdefault(s.id, s)
            elif op == OP_CHANNEL:
                ch = _channel(c)
                out.channels.setdefault(ch.id, ch)
            elif op == OP_STATISTICS and out.statistics_counts is None:
                _top_level(buf, op, pos, pos + 9, length, out, [])
            pos += 9 + length
    except (_Bad, struct.error):
        pass  # the walk has already reported it


def _resync(buf, size: int, start: int) -> int | None:
    """Offset of the next chunk at or after ``start`` that decompresses and passes its CRC, or None."""
    pos = start
    while True:
        pos = buf.find(b"\x06", pos, size)
        if pos < 0 or pos + 9 + _CHUNK_HEAD.size > size:
            return None
        length = _U64.unpack_from(buf, pos + 1)[0]
        if pos + 9 + length <= size and length >= _CHUNK_HEAD.size + 12:
            # Cheap checks first: the compression string must be one we know.
            cl_at = pos + 9 + _CHUNK_HEAD.size
            cl = _U32.unpack_from(buf, cl_at)[0]
            if cl in (0, 3, 4) and bytes(buf[cl_at + 4 : cl_at + 4 + cl]) in (b"", b"lz4", b"zstd"):
                try:
                    _chunk_records(buf, pos + 9, length)
                    return pos
                except (_Bad, struct.error):
                    pass
        pos += 1


def _index_after(buf, size: int, pos: int) -> tuple[int | None, dict[int, int]]:
    """Message counts from the MessageIndex records that follow a chunk ending at ``pos``."""
    counts: dict[int, int] = {}
    while pos + 9 <= size:
        op, length = _RECORD_HEAD.unpack_from(buf, pos)
        if op != OP_MESSAGE_INDEX or pos + 9 + length > size:
            break
        try:
            cid, n = _message_index_count(buf, pos + 9, length)
        except (_Bad, struct.error):
            return None, {}
        counts[cid] = counts.get(cid, 0) + n
        pos += 9 + length
    return (sum(counts.values()) if counts else None), counts


def _lost(buf, start: int, end: int, reason: str, estimate: int) -> Damage:
    """Damage over [start, end): exact counts from the message index after the chunk when it is intact."""
    size = len(buf)
    kind = "record"
    if start + 9 <= size:
        op, length = _RECORD_HEAD.unpack_from(buf, start)
        after = start + 9 + length
        if op == OP_CHUNK or (after <= size and _looks_like_chunk(buf, start + 9, length)):
            kind = "chunk"
            if after <= end:
                n, by_channel = _index_after(buf, size, after)
                if n is not None:
                    return Damage(start, end - start, kind, reason, n, n, by_channel)
    return Damage(start, end - start, kind, reason, None, estimate)
