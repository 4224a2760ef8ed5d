"""A tolerant MCAP reader: every complete, intact message of a file, whatever happened to the rest.

The indexed reader of the ``mcap`` package needs the summary and the footer,
so a recording whose writer was killed, or that was cut or corrupted, reads as
nothing.  :func:`salvage` walks the file record by record from the start
instead:

* a chunk is kept only if it decompresses and its CRC (``uncompressed_crc``)
  matches, so a flipped bit never yields a wrong message — it costs the chunk
  it falls in, which is one step of a lelsonar recording (a chunk per contract
  message, then one for its views: see :class:`lelsonar.log.recording.McapRecorder`);
* after a damaged record it resynchronises on the next chunk whose CRC
  matches, so one bad chunk does not hide the rest of the file;
* what it skipped is reported as :class:`Damage` with the byte range and the
  number of messages lost: exact when the chunk's message index records or
  the file's statistics survived, an estimate (``≈``) otherwise.

Channels and schemas come from the data section and, when the footer is
intact, from the summary section too, so a damaged first chunk does not orphan
the messages of later ones.  Nothing here knows about lelsonar's topics.

Reading holds one chunk at a time, whatever the file's length: :func:`open_mcap`
walks the records' framing once (:mod:`lelsonar.log.walk`: no decompression,
except the first chunk of each channel, to learn its definition) and :meth:`McapSource.read` then
decompresses and checks the chunks one by one, yielding their messages in log-time
order through a merge bounded by the chunks that overlap in time (as the indexed
reader does with its chunk index).  A chunk whose message index says it holds
none of the wanted channels is not decompressed at all.  :func:`salvage` is the
in-memory form: every message of the file in a list.
"""

from __future__ import annotations

import heapq
import mmap
import struct
import threading
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from lelsonar.errors import NotMcapError
from lelsonar.log.records import (
    CHUNK_HEAD,
    MAGIC,
    MESSAGE_HEAD,
    OP_CHANNEL,
    OP_MESSAGE,
    OP_SCHEMA,
    RECORD_HEAD,
    BadRecord,
    ChannelInfo,
    Cursor,
    Damage,
    RawMessage,
    Salvage,
    SchemaInfo,
    Unit,
    chunk_raw,
    parse_channel,
    parse_schema,
    read_summary,
)
from lelsonar.log.walk import RELEASE_EVERY, check_recording_path, magic_ok, open_bytes, walk

__all__ = [
    "ChannelInfo",
    "check_recording_path",
    "Damage",
    "McapSource",
    "RawMessage",
    "Salvage",
    "SchemaInfo",
    "open_bytes",
    "open_mcap",
    "salvage",
]


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
        decompress_threads: int = 0,
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
        decompress_threads : int
            Threads that decompress and check the next chunks while this one is walked (zstd releases
            the GIL); 0: each chunk is decompressed when it is reached.  A read that reaches a chunk
            still being decompressed decompresses a later one itself meanwhile.  What is yielded is the
            same.

        Holds the chunks whose time ranges overlap the message being yielded, not the file:
        chunks are merged by the message start time their header records, as the indexed
        reader merges them.  The account is complete when the iterator is exhausted.
        """
        out = self.account
        out.start_read()
        buf, size = open_bytes(out.path)
        try:
            yield from _Read(self, buf, size, want, verify_all, decompress_threads).messages(ordered)
        finally:
            if isinstance(buf, mmap.mmap):
                buf.close()


class _Read:
    """One pass over the units of a source: decompress, check, count, yield."""

    #: Uncompressed bytes of the chunks decompressed ahead of the one being walked, at most (a bound
    #: on memory whatever the file's length, and room enough for a scan's final estimate to overlap).
    AHEAD_BYTES = 16 * 1024 * 1024
    #: About this many uncompressed bytes per job: a thread hand-over per small chunk would cost a good
    #: part of what decompressing it does.
    JOB_BYTES = 1024 * 1024

    def __init__(self, source: McapSource, buf, size: int, want, verify_all: bool, threads: int = 0) -> None:
        self.source, self.buf, self.size = source, buf, size
        self.threads = threads
        self.pool: ThreadPoolExecutor | None = None
        #: Chunks being decompressed ahead, by offset: (job, place in the job, uncompressed bytes).
        self.inflight: dict[int, tuple[_Job, int, int]] = {}
        self.jobs: deque[_Job] = deque()  # the jobs ahead, in the file's order (the done ones dropped lazily)
        self.inflight_bytes = 0
        self.next_ahead = 0  # the first unit not yet considered for decompressing ahead
        self.out = source.account
        self.want = want
        self.verify_all = verify_all
        self.wanted: dict[int, bool] = {}
        self.unknown = True  # some channel named by a message index may be undefined so far
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
        """A chunk holding none of the wanted channels, while every channel of the file is known.

        A chunk may define a channel whose messages are in later chunks: until all are known, none is skipped.
        """
        if self.verify_all or unit.index is None or self.want is None:
            return False
        channels = self.out.channels
        if self.unknown and any(cid not in channels for cid in self.out.indexed_counts):
            return False
        self.unknown = False
        return all(not self.is_wanted(cid) for cid, _n in unit.index)

    def release(self, upto: int) -> None:
        buf = self.buf
        if not isinstance(buf, mmap.mmap) or upto - self.released < RELEASE_EVERY:
            return
        end = upto - upto % mmap.PAGESIZE
        if end > self.released:
            buf.madvise(mmap.MADV_DONTNEED, self.released, end - self.released)
            self.released = end

    def ahead(self, i: int) -> None:
        """Keep the chunks of the units after ``i`` being decompressed, up to AHEAD_BYTES of them.

        A chunk the read turns out to skip (its channels learnt meanwhile) costs its decompression only.
        """
        if self.pool is None:
            return
        units, buf, jobs = self.source.units, self.buf, self.jobs
        while jobs and jobs[0].finished.is_set():
            jobs.popleft()
        j = max(self.next_ahead, i + 1)
        while j < len(units) and self.inflight_bytes < self.AHEAD_BYTES:
            job: list[tuple[Unit, int]] = []
            nbytes = 0
            while j < len(units) and nbytes < self.JOB_BYTES:
                u = units[j]
                j += 1
                if u.chunk and not self.skippable(u):
                    usize = CHUNK_HEAD.unpack_from(buf, u.offset + 9)[2]  # checked by the walk
                    job.append((u, usize))
                    nbytes += usize
            if job:
                work = _Job(buf, [(u.offset + 9, u.length) for u, _ in job])
                self.pool.submit(work.run)
                self.jobs.append(work)
                for k, (u, usize) in enumerate(job):
                    self.inflight[u.offset] = (work, k, usize)
                self.inflight_bytes += nbytes
        self.next_ahead = j

    def take_raw(self, unit: Unit) -> bytes:
        """One chunk's content decompressed and checked: decompressed ahead, or now.

        While its job is still being decompressed by a thread, this thread decompresses the next job no
        thread has started (the two then share the cores instead of one waiting for the other).
        """
        pending = self.inflight.pop(unit.offset, None)
        if pending is None:
            return chunk_raw(self.buf, unit.offset + 9, unit.length)
        work, k, usize = pending
        self.inflight_bytes -= usize
        if not work.run():
            jobs = self.jobs
            while not work.finished.is_set():
                while jobs and jobs[0].claimed.locked() and jobs[0] is not work:
                    jobs.popleft()  # started by now: taken by a thread, or done
                later = next((j for j in jobs if not j.claimed.locked()), None)
                if later is None or not later.run():
                    work.finished.wait()
        raw = work.results[k]
        if isinstance(raw, Exception):
            raise raw
        return raw

    def messages(self, ordered: bool) -> Iterator[RawMessage]:
        if self.threads > 0:
            self.pool = ThreadPoolExecutor(self.threads, thread_name_prefix="mcap-decompress")
        try:
            yield from self.in_order() if ordered else self.in_file_order()
        finally:
            if self.pool is not None:
                self.pool.shutdown(wait=True, cancel_futures=True)  # before the file's map is closed
                self.inflight.clear()
                self.jobs.clear()

    def in_file_order(self) -> Iterator[RawMessage]:
        for i, unit in enumerate(self.source.units):
            self.ahead(i)
            yield from self.unit_messages(unit)
            self.release(unit.offset)
        self.done()

    def in_order(self) -> Iterator[RawMessage]:
        units = self.source.units
        # later[i]: the earliest message any unit from i on may hold; what is older can be yielded.
        later = [0] * (len(units) + 1)
        later[-1] = 1 << 64
        for i in range(len(units) - 1, -1, -1):
            later[i] = min(units[i].start, later[i + 1])
        heap: list[_Pending] = []
        seq = 0
        push, pop = heapq.heappush, heapq.heappop
        for i, unit in enumerate(units):
            self.ahead(i)
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
            cid, seq, t_log, t_pub = MESSAGE_HEAD.unpack_from(buf, unit.offset + 9)
            self.count(cid, 1, t_log, t_log)
            if cid not in out.channels:
                out.orphans += 1
            if not self.is_wanted(cid):
                return []
            body = unit.offset + 9 + MESSAGE_HEAD.size
            return [RawMessage(cid, seq, t_log, t_pub, bytes(buf[body : unit.offset + 9 + unit.length]), unit.offset)]
        if self.skippable(unit):
            pending = self.inflight.pop(unit.offset, None)
            if pending is not None:  # decompressed ahead before its channels were known: not needed
                self.inflight_bytes -= pending[2]
            for cid, n in unit.index or ():
                self.count(cid, n, unit.start, unit.end)
            return []
        try:
            found, counts, t0, t1 = self.parse_chunk(unit)
        except (BadRecord, struct.error) as exc:
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
        """Decompress, check and walk one chunk; nothing is kept from a chunk that fails anywhere.

        The records are walked as :func:`~lelsonar.log.records.inner_records` walks them (the same checks,
        the same errors), inline: a chunk holds a few records per step, and the walk is per record.
        """
        raw = self.take_raw(unit)
        out = self.out
        found: list[RawMessage] = []
        counts: dict[int, int] = {}
        schemas: list[SchemaInfo] = []
        channels: list[ChannelInfo] = []
        t0, t1 = 1 << 64, 0
        unpack_head, unpack_message, message_head = RECORD_HEAD.unpack_from, MESSAGE_HEAD.unpack_from, MESSAGE_HEAD.size
        known, wanted = out.channels, self.wanted
        offset = unit.offset
        size = len(raw)
        pos = 0
        while pos < size:
            if pos + 9 > size:
                raise BadRecord("field of 9 bytes runs past the record")
            op, n = unpack_head(raw, pos)
            body = pos + 9
            pos = body + n
            if pos > size:
                raise BadRecord("record inside the chunk runs past it")
            if op == OP_MESSAGE:
                if n < message_head:
                    raise BadRecord(f"field of {message_head} bytes runs past the record")
                cid, seq, t_log, t_pub = unpack_message(raw, body)
                counts[cid] = counts.get(cid, 0) + 1
                if t_log < t0:
                    t0 = t_log
                if t_log > t1:
                    t1 = t_log
                hit = wanted.get(cid)
                if hit is None:
                    hit = self.is_wanted(cid) if cid in known or not channels else self.decide(cid, channels, schemas)
                if hit:
                    found.append(RawMessage(cid, seq, t_log, t_pub, raw[body + message_head : pos], offset))
            elif op == OP_SCHEMA:
                schemas.append(parse_schema(Cursor(raw, body, pos)))
            elif op == OP_CHANNEL:
                channels.append(parse_channel(Cursor(raw, body, pos)))
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


class _Job:
    """Chunks decompressed together, by whichever thread claims the job first: a decompressing thread, or
    the reading thread when it gets there first."""

    __slots__ = ("buf", "places", "claimed", "finished", "results")

    def __init__(self, buf, places: list[tuple[int, int]]) -> None:
        self.buf, self.places = buf, places
        self.claimed = threading.Lock()  # taken once, never released: the claim
        self.finished = threading.Event()
        self.results: list[bytes | Exception] = []

    def run(self) -> bool:
        """Decompress the chunks here, unless another thread has claimed them; whether this one did."""
        if not self.claimed.acquire(blocking=False):
            return False
        try:
            self.results = decompress_chunks(self.buf, self.places)
        except Exception as exc:  # noqa: BLE001 - not damage (decompress_chunks returns that): the reader raises it
            self.results = [exc] * len(self.places)
        finally:
            self.finished.set()
        return True


def decompress_chunks(buf, places: list[tuple[int, int]]) -> list[bytes | Exception]:
    """Each chunk record's content at (start, length) of ``buf``, decompressed and checked, or why not."""
    out: list[bytes | Exception] = []
    for start, length in places:
        try:
            out.append(chunk_raw(buf, start, length))
        except (BadRecord, struct.error) as exc:
            out.append(exc)
    return out


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
        if not magic_ok(bytes(buf[:8])):
            head = bytes(buf[:16])
            raise NotMcapError(f"{path} is not a readable MCAP file (it starts with {head!r}, not the MCAP magic)")
        out = Salvage(path, size)
        if bytes(buf[:8]) != MAGIC:
            out.damage.append(Damage(0, 8, "header", "the leading magic has flipped bits", 0))
        read_summary(buf, size, out)
        units = walk(buf, size, out)
        out.framing_damage = list(out.damage)
        return McapSource(out, units)
    finally:
        if isinstance(buf, mmap.mmap):
            buf.close()
