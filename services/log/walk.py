"""The opening walk over an MCAP file's records: where its chunks are, what they hold, what is damaged.

:func:`walk` goes over the framing of every record once, from the start (no decompression, except
the first chunk of each channel not defined outside the chunks, to learn it): the chunks and messages
to read (:class:`~lelsonar.log.records.Unit`), the records outside chunks, and the damage to the
framing, resynchronising on the next intact chunk after a damaged record.  :mod:`lelsonar.log.reader`
reads the units it finds.
"""

from __future__ import annotations

import mmap
import os
import stat
import struct
from pathlib import Path

from lelsonar.errors import NotMcapError, RecordingError, RecordingNotFoundError
from lelsonar.log.records import (
    CHUNK_HEAD,
    INDEX_HEAD,
    MAGIC,
    MAX_CHUNK_BYTES,
    OP_CHUNK,
    OP_CHUNK_INDEX,
    OP_FOOTER,
    OP_MESSAGE_INDEX,
    RECORD_HEAD,
    BadRecord,
    ChannelInfo,
    Damage,
    Salvage,
    SchemaInfo,
    Unit,
    check_chunk_index,
    chunk_frame,
    chunk_records,
    looks_like_chunk,
    lost_region,
    message_index_count,
    resync,
    summary_start,
    top_level_record,
)

#: Drop the file pages behind a walk or a read from the process every this many bytes (they stay in the
#: page cache): a mapped file's touched pages count in the resident set until unmapped.
RELEASE_EVERY = 16 * 1024 * 1024


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
    check_recording_path(path)
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


def check_recording_path(path: Path | str) -> None:
    """Refuse, before opening it, a path that cannot be a recording.

    Raises
    ------
    RecordingNotFoundError
        A directory.
    RecordingError
        A named pipe, a device or a socket (opening a pipe waits for a writer; a device never ends).
    """
    path = Path(path)
    if path.is_dir():
        raise RecordingNotFoundError(f"{path} is a directory, not an MCAP recording; give the .mcap file inside it")
    kind = _not_regular(path)
    if kind:
        raise RecordingError(f"{path} is {kind}, not a regular file; give a recorded .mcap file")


def _not_regular(path: Path) -> str | None:
    """What ``path`` is when it is not a regular file (``"a named pipe"`` …); None for a regular file or none."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return None  # missing or unreadable: open() says which
    if stat.S_ISREG(mode):
        return None
    for test, kind in (
        (stat.S_ISFIFO, "a named pipe"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISSOCK, "a socket"),
    ):
        if test(mode):
            return kind
    return "a special file"


def magic_ok(head: bytes) -> bool:
    """The leading magic, allowing two flipped bits (a damaged header is damage, not a foreign file)."""
    if len(head) < len(MAGIC):
        return False
    return sum(bin(a ^ b).count("1") for a, b in zip(head, MAGIC, strict=False)) <= 2


class _Walk:
    """The opening walk over the records' framing: units to read, top-level records, damage to the framing."""

    def __init__(self, buf, size: int, out: Salvage) -> None:
        self.buf, self.size, self.out = buf, size, out
        self.good_bytes = self.good_messages = self.good_raw = 0
        self.summary_start = out.summary_start = summary_start(buf, size)
        self.units: list[Unit] = []
        self.indexes: dict[tuple[tuple[int, int], ...], tuple[tuple[int, int], ...]] = {}  # shared, not repeated
        self.learnt: set[int] = set()  # channels whose first chunk was tried
        #: Each distinct index by its entries in file order: a chunk per step repeats a few, each sorted and its
        #: channels checked once.
        self.keys: dict[tuple[tuple[int, int], ...], tuple[tuple[int, int], ...]] = {}
        self.released = 0

    def estimate(self, nbytes: int) -> int:
        return round(nbytes * self.good_messages / self.good_bytes) if self.good_bytes else 0

    def take_chunk(self, pos: int, length: int) -> Unit:
        t0, t1, usize, _crc = CHUNK_HEAD.unpack_from(self.buf, pos + 9)
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
        in_order = tuple(entries.items())
        key = self.keys.get(in_order)
        seen = key is not None
        if key is None:
            ordered = tuple(sorted(in_order))
            key = self.keys[in_order] = self.indexes.setdefault(ordered, ordered)
        unit.index = key
        n = sum(entries.values())
        self.good_messages += n
        counts = self.out.indexed_counts
        for cid, k in key:
            counts[cid] = counts.get(cid, 0) + k
        if n == 0 and unit.start == unit.end == 0:
            unit.start = 1 << 64  # no message: it holds nothing back
        if seen:
            return  # each of its channels is defined, or its first chunk was tried, already
        unknown = [cid for cid, _k in key if cid not in self.out.channels and cid not in self.learnt]
        if unknown:
            # The first chunk of a channel holds its definition: read it now, so a read can choose channels.
            self.learnt.update(unknown)
            try:
                records, _usize = chunk_records(self.buf, unit.offset + 9, unit.length)
            except (BadRecord, struct.error):
                return  # damaged: the read says so
            for _op, rec in records:
                if isinstance(rec, SchemaInfo):
                    self.out.schemas.setdefault(rec.id, rec)
                elif isinstance(rec, ChannelInfo):
                    self.out.channels.setdefault(rec.id, rec)

    def damaged(self, pos: int, reason: str) -> int | None:
        """Record damage starting at ``pos``; return where reading resumes (the next intact chunk), or None."""
        buf, size, out = self.buf, self.size, self.out
        if self.summary_start is not None and pos >= self.summary_start:
            # In the summary section: no message can be lost here, and read_summary reads it via the footer.
            out.damage.append(Damage(pos, size - pos, "summary", f"summary section unreadable at byte {pos}", 0))
            return None
        nxt = resync(buf, size, pos + 1)
        if nxt is not None:
            out.damage.append(lost_region(buf, pos, nxt, reason, self.estimate(nxt - pos)))
            return nxt
        if out.data_end_seen:
            out.damage.append(Damage(pos, size - pos, "summary", f"summary section unreadable at byte {pos}", 0))
            return None
        op = RECORD_HEAD.unpack_from(buf, pos)[0] if pos + 9 <= size else 0
        est = max(1, self.estimate(size - pos)) if self.good_bytes else 0
        if op == OP_CHUNK and pos + 9 + CHUNK_HEAD.size <= size and self.good_raw:
            usize = CHUNK_HEAD.unpack_from(buf, pos + 9)[2]
            if usize <= MAX_CHUNK_BYTES:
                est = max(1, round(usize * self.good_messages / self.good_raw))
        out.damage.append(Damage(pos, size - pos, "tail", reason, None, est))
        return None

    def run(self) -> list[Unit]:
        buf, size, out = self.buf, self.size, self.out
        pos = len(MAGIC)
        chunk: Unit | None = None  # the chunk whose message index records may follow
        entries: dict[int, int] = {}
        head, index_head = RECORD_HEAD.unpack_from, INDEX_HEAD.unpack_from
        mapped = isinstance(buf, mmap.mmap)
        summary = self.summary_start
        while pos < size:
            if pos + 9 > size:
                self.damaged(pos, "the file ends inside a record header")
                break
            op, length = head(buf, pos)
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
                    chunk_frame(buf, body, length)
                except (BadRecord, struct.error) as exc:
                    nxt = self.damaged(pos, str(exc))
                else:
                    chunk = self.take_chunk(pos, length)
                    nxt = body + length
            elif op == OP_MESSAGE_INDEX and chunk is not None:
                if length >= 6 and (found := index_head(buf, body))[1] % 16 == 0 and 6 + found[1] == length:
                    # (message_index_count's checks, inline: a few index records follow every chunk)
                    cid = found[0]
                    entries[cid] = entries.get(cid, 0) + found[1] // 16
                    pos = body + length
                    continue
                try:
                    cid, n = message_index_count(buf, body, length)
                except (BadRecord, struct.error) as exc:
                    self.take_index(chunk, {}, pos)
                    chunk, entries = None, {}
                    nxt = self.damaged(pos, f"record with opcode {op:#04x}: {exc}")
                else:
                    entries[cid] = entries.get(cid, 0) + n
                    nxt = body + length
            elif op == OP_CHUNK_INDEX and summary is not None and pos >= summary:
                # top_level_record's check of a chunk index, without its cursor: one such record per chunk.
                try:
                    check_chunk_index(buf, body, length)
                except (BadRecord, struct.error) as exc:
                    nxt = self.damaged(pos, f"record with opcode {op:#04x}: {exc}")
                else:
                    nxt = body + length
            elif (summary is None or pos < summary) and looks_like_chunk(buf, body, length):
                try:
                    chunk_records(buf, body, length)  # rare: worth proving before calling it intact
                except (BadRecord, struct.error) as exc:
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
                    top_level_record(buf, op, pos, body, length, out, self.units)
                except (BadRecord, struct.error) as exc:
                    nxt = self.damaged(pos, f"record with opcode {op:#04x}: {exc}")
                else:
                    if op == OP_FOOTER:
                        break
                    nxt = body + length
            if nxt is None:
                break
            pos = nxt
            if mapped and pos - self.released >= RELEASE_EVERY:
                end = pos - pos % mmap.PAGESIZE
                buf.madvise(mmap.MADV_DONTNEED, self.released, end - self.released)
                self.released = end
        if chunk is not None:
            self.take_index(chunk, entries, min(pos, size))
        return self.units


def walk(buf, size: int, out: Salvage) -> list[Unit]:
    """Walk the framing of ``buf`` (``size`` bytes) into ``out``; return the units a read goes over, in file order."""
    return _Walk(buf, size, out).run()
