"""MCAP recordings: the lelsonar channels plus Foxglove channels that viewers draw.

A recording holds, in log-time order (log time = acquisition time):

==============================  ================================  ==========================
topic                           schema                            what
==============================  ================================  ==========================
``/lelsonar/scan_start``        ``lelsonar.v1.ScanStart``         one per scan
``/lelsonar/sample``            ``lelsonar.v1.Sample``            one per step
``/lelsonar/scan_end``          ``lelsonar.v1.ScanEnd``           one per scan
``/lelsonar/reconstruction``    ``lelsonar.v1.Reconstruction``    estimates, when recorded
``/tf``                         ``foxglove.FrameTransform``       world → array, per step
``/lelsonar/points``            ``foxglove.PointCloud``           raw points of the step (eq. 9)
``/log``                        ``foxglove.Log``                  events
``/tf_capsules``                ``foxglove.FrameTransforms``      array → capsule_X, per scan
``/lelsonar/array``             ``foxglove.SceneUpdate``          the capsules and their beams
``/lelsonar/scan_points``       ``foxglove.PointCloud``           every raw point of the scan so far
``/lelsonar/step``              JSON ``lelsonar.StepScalars``     γ, ranges, energies (plottable)
``/lelsonar/planes``            ``foxglove.SceneUpdate``          estimated planes, when recorded
==============================  ================================  ==========================

The viewer channels come from :mod:`lelsonar.visual`.  Each scan also adds a
``lelsonar.recording`` metadata record naming it (``name``, scanner, scan,
device, software).  ``rerun file.mcap`` shows ``/tf`` as a Transform3D and the
points as Points3D; Foxglove shows everything, and plots ``/lelsonar/step``.
A step's contract message and its viewer messages share one chunk.
"""

from __future__ import annotations

import bisect
import heapq
import json
import logging
import mmap
import os
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.Log_pb2 import Log
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from google.protobuf.message import Message
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from mcap_protobuf.schema import register_schema

from lelsonar import __version__, codec, visual
from lelsonar.errors import DecodeError, NoScansError, RecordingError
from lelsonar.recordings.reader import (
    MAGIC, ChannelInfo, DecompressAhead, RawMessage, Salvage, begin_salvage, chunk_schedule, end_salvage, open_bytes, salvage,
    walk_records)

_log = logging.getLogger(__name__)

TOPICS: dict[type[Message], str] = {
    codec.ScanStart: "/lelsonar/scan_start",
    codec.Sample: "/lelsonar/sample",
    codec.ScanEnd: "/lelsonar/scan_end",
    codec.Reconstruction: "/lelsonar/reconstruction",
}
TOPIC_TF = "/tf"
TOPIC_POINTS = visual.TOPIC_POINTS
TOPIC_LOG = "/log"
WORLD_FRAME = visual.WORLD_FRAME
ARRAY_FRAME = visual.ARRAY_FRAME

#: Metadata record naming each channel, ``lelsonar.channel.<id>`` → {"topic": ..., "schema": ...}.
CHANNEL_METADATA = "lelsonar.channel."
#: The protobuf types a lelsonar recording may hold, by full name (to rebuild a lost schema record).
RECORDED_TYPES: dict[str, type[Message]] = {
    **codec.MESSAGE_TYPES, **{cls.DESCRIPTOR.full_name: cls for cls in (FrameTransform, FrameTransforms, PointCloud, Log, SceneUpdate)}}

COMPRESSIONS = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}


class McapRecorder:
    """Write a lelsonar recording; always finishes the file, even on an exception.

    Durable before published: every :meth:`write` and :meth:`log` closes its own
    MCAP chunk (a Sample, its /tf and its points are one chunk: one step) and
    hands it to the operating system before returning, so a caller that
    publishes after ``write`` never publishes what the file lacks.  A process
    killed at any moment (``kill -9``) loses at most the message being written;
    :func:`lelsonar.recordings.recover.recover` turns the unfinished file into
    an indexed one.  ``fsync=True`` also forces each step to the disk (power
    loss), at the cost ``lelsonar bench recording`` measures.

    Use as a context manager::

        with McapRecorder(path, metadata={"scanner_id": "s1"}) as rec:
            rec.write(scan_start)
            rec.write(sample)      # also writes /tf and /lelsonar/points
            rec.log("INFO", "scan complete", t_ns)

    Parameters
    ----------
    path : Path
    compression : {"zstd", "lz4", "none"}
    metadata : mapping of str to str
        Stored as one ``lelsonar.config`` metadata record (e.g. the configuration).
    fsync : bool
        ``os.fsync`` after every step (default False: the OS page cache survives
        a killed process, not a power cut).
    durable : bool
        True (default): one chunk per step, flushed to the OS.  False: 1 MiB
        chunks written when full, the behaviour before durability; a killed
        writer then loses the whole chunk in progress.  Kept for the benchmark.
    """

    def __init__(self, path: Path | str, *, compression: str = "zstd",
                 metadata: Mapping[str, str] | None = None, fsync: bool = False, durable: bool = True) -> None:
        if compression not in COMPRESSIONS:
            raise RecordingError(f"compression must be one of {', '.join(COMPRESSIONS)}, got {compression!r}")
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, "wb")  # noqa: SIM115 - closed in finish()
        self._writer = McapWriter(self._file, compression=COMPRESSIONS[compression])
        self._writer.start(library=f"lelsonar {__version__}")
        self._channels: dict[str, int] = {}
        self._fsync = fsync
        self._durable = durable or fsync
        self._starts: dict[tuple[str, int], codec.ScanStart] = {}
        self._finished = False
        self.messages_written = 0
        if metadata:
            self._writer.add_metadata("lelsonar.config", {str(k): str(v) for k, v in metadata.items()})
        self._commit()
        if fsync:  # the new directory entry too, once
            dir_fd = os.open(self.path.parent, os.O_RDONLY)
            try:
                os.fsync(dir_fd)
            finally:
                os.close(dir_fd)

    def __enter__(self) -> McapRecorder:
        return self

    def __exit__(self, *exc_info) -> None:
        self.finish()

    def finish(self) -> None:
        """Write the summary and footer and close the file; safe to call twice."""
        if self._finished:
            return
        self._finished = True
        try:
            self._writer.finish()
            self._file.flush()
            if self._fsync:
                os.fsync(self._file.fileno())
        finally:
            self._file.close()

    def _commit(self) -> None:
        """Close the chunk in progress and hand it to the OS (and the disk, with fsync)."""
        if not self._durable:
            return
        self._writer.flush()  # finishes the chunk, writes its message index, flushes the stream
        if self._fsync:
            os.fsync(self._file.fileno())

    def _put(self, topic: str, message: Message, t: int) -> None:
        channel = self._channels.get(topic)
        if channel is None:
            schema = register_schema(self._writer, type(message))
            channel = self._channels[topic] = self._writer.register_channel(topic, "protobuf", schema)
            # The channel record rides in the chunk of its first message; this copy outside any chunk names
            # the channel's later messages if that one chunk is damaged (see open_recording).
            self._writer.add_metadata(f"{CHANNEL_METADATA}{channel}",
                                      {"topic": topic, "schema": type(message).DESCRIPTOR.full_name})
        self._writer.add_message(channel, log_time=t, data=message.SerializeToString(), publish_time=t)

    # --- writing ---------------------------------------------------------------------
    def write(self, message: Message, log_time_ns: int | None = None) -> None:
        """Record one contract message; a Sample also gets its /tf and /lelsonar/points."""
        if self._finished:
            raise RecordingError(f"{self.path} is already finished")
        topic = TOPICS.get(type(message))
        if topic is None:
            raise RecordingError(f"{type(message).__name__} is not a lelsonar contract message")
        t = log_time_ns if log_time_ns is not None else _message_time(message)
        self._put(topic, message, t)
        self.messages_written += 1
        if isinstance(message, codec.ScanStart):
            self._starts[(message.scanner_id, message.scan_id)] = message
        elif isinstance(message, codec.Sample):
            self._write_pose_and_points(message, t)
        self._write_views(message, t)
        self._commit()

    def log(self, level: str, text: str, log_time_ns: int | None = None, name: str = "lelsonar") -> None:
        """Record a ``foxglove.Log`` event (level: DEBUG, INFO, WARNING, ERROR, FATAL)."""
        t = log_time_ns if log_time_ns is not None else time.time_ns()
        self._put(TOPIC_LOG, visual.log_message(level, text, t, name), t)
        self._commit()

    # --- what viewers draw, beside the contract (lelsonar.visual) -------------------------
    @cached_property
    def _views(self) -> _ViewState:
        return _ViewState()

    def _write_views(self, message: Message, t: int) -> None:
        """The viewer channels of a contract message: a recording opened alone shows the scan."""
        views = self._views
        if isinstance(message, codec.ScanStart):
            views.cloud.scan_started(message)
            self._put(visual.TOPIC_CAPSULE_TF, visual.capsule_transforms(message, t), t)
            self._put(visual.TOPIC_ARRAY, visual.array_model(message, t), t)
            self._writer.add_metadata("lelsonar.recording", recording_name_metadata(message))
        elif isinstance(message, codec.Sample):
            cloud = views.cloud.add(message, t)
            if cloud is not None:
                self._put(visual.TOPIC_SCAN_POINTS, cloud, t)
            self.write_json(visual.TOPIC_STEP, visual.STEP_SCALARS_NAME, visual.STEP_SCALARS_SCHEMA,
                            visual.step_scalars(message), t)
        elif isinstance(message, codec.ScanEnd):
            views.cloud.scan_ended(message.scanner_id, message.scan_id)
        elif isinstance(message, codec.Reconstruction):
            self._put(visual.TOPIC_PLANES, views.planes.update(message, t), t)

    def write_json(self, topic: str, schema_name: str, schema: dict, payload: dict, log_time_ns: int) -> None:
        """Record a JSON message on a channel with a named JSON schema (Foxglove plots its numbers)."""
        if self._finished:
            raise RecordingError(f"{self.path} is already finished")
        channel = self._views.json_channels.get(topic)
        if channel is None:
            schema_id = self._writer.register_schema(schema_name, "jsonschema", visual.json_schema_bytes(schema))
            channel = self._views.json_channels[topic] = self._writer.register_channel(topic, "json", schema_id)
        self._writer.add_message(channel, log_time=log_time_ns, data=json.dumps(payload).encode(),
                                 publish_time=log_time_ns)

    def _write_pose_and_points(self, sample: codec.Sample, t: int) -> None:
        self._put(TOPIC_TF, visual.array_transform(sample.gamma_measured, t), t)
        start = self._starts.get((sample.scanner_id, sample.scan_id))
        if start is None:
            return
        pts, _capsules = visual.sample_points(start, sample)
        if len(pts):
            self._put(TOPIC_POINTS, visual.point_cloud(pts, t), t)


@dataclass
class _ViewState:
    cloud: visual.ScanCloud = field(default_factory=visual.ScanCloud)
    planes: visual.PlaneScene = field(default_factory=visual.PlaneScene)
    json_channels: dict[str, int] = field(default_factory=dict)


def recording_name_metadata(start: codec.ScanStart) -> dict[str, str]:
    """The ``lelsonar.recording`` metadata record of a scan: a human name and what it was."""
    return {"name": f"lelsonar {start.scanner_id} scan {start.scan_id}", "scanner_id": start.scanner_id,
            "scan_id": str(start.scan_id), "device": start.device or "unknown",
            "software_version": start.software_version, "start_time_ns": str(start.start_time_ns),
            "steps": str(start.steps)}


def _message_time(message: Message) -> int:
    for name in ("acquisition_time_ns", "start_time_ns", "end_time_ns", "stamp_ns"):
        if hasattr(message, name) and getattr(message, name):
            return int(getattr(message, name))
    return time.time_ns()


# --- reading -------------------------------------------------------------------------
@dataclass(frozen=True)
class RecordedPayload:
    """One contract message as stored: its type name and raw bytes, not yet decoded.

    Replay decodes these through :func:`lelsonar.codec.decode`, the same path as live data.
    """

    log_time_ns: int
    topic: str
    type_name: str
    payload: bytes


@dataclass(frozen=True)
class Recording:
    """A recording as read by the tolerant reader: what survived, and what did not.

    Build with :func:`open_recording`; iterate the contract payloads with
    :func:`iter_payloads` (which takes a Recording or a path).
    """

    salvage: Salvage

    @property
    def path(self) -> Path:
        return self.salvage.path

    def contract_channels(self) -> dict[int, type[Message]]:
        """The channels that hold contract messages, and the message type of each.

        A channel is the contract's by its protobuf schema name (``lelsonar.v1.Sample`` …), whatever
        its topic: another writer of the schema (a simulator, a bridge) may name its topics otherwise.
        Every payload is still decoded and validated by the consumer.
        """
        s = self.salvage
        out = {}
        for cid, ch in s.channels.items():
            cls = _contract_type(ch, s.schema_name(cid))
            if cls is not None:
                out[cid] = cls
        return out

    def payloads(self) -> list[RecordedPayload]:
        """The contract messages in log-time order, undecoded."""
        return self._payloads_of(self.salvage.in_log_time_order())

    def _payloads_of(self, messages: list[RawMessage]) -> list[RecordedPayload]:
        s = self.salvage
        wanted = self.contract_channels()
        return [RecordedPayload(m.log_time, s.topic(m.channel_id), s.schema_name(m.channel_id), m.data)
                for m in messages if m.channel_id in wanted]

    def count(self, kind: str | type[Message]) -> int:
        """Messages on a topic, or of a contract message type (on whichever topics)."""
        if isinstance(kind, str):
            ids = {cid for cid, ch in self.salvage.channels.items() if ch.topic == kind}
        else:
            ids = {cid for cid, cls in self.contract_channels().items() if cls is kind}
        return sum(1 for m in self.salvage.messages if m.channel_id in ids)

    @property
    def has_scans(self) -> bool:
        return any(self.count(cls) for cls in (codec.ScanStart, codec.Sample, codec.ScanEnd))

    def damage_warning(self) -> str | None:
        """One line saying what was lost, or None for an intact, finished file.

        e.g. ``warning: scan.mcap is damaged: 1 chunk (≈10 messages) unreadable after byte 81234; 118 samples
        salvaged``.
        """
        s = self.salvage
        if s.intact:
            return None
        return f"warning: {s.path} {describe_damage(s)}; {self.count(codec.Sample)} samples salvaged"

    def require_scans(self) -> Recording:
        """Self, or :class:`NoScansError` when no scan message survived (foreign channels, or all lost)."""
        if self.has_scans:
            return self
        s = self.salvage
        held = sorted({ch.topic for ch in s.channels.values()})
        what = f"its channels are {', '.join(held)}" if held else "it has no readable channels"
        lost = f"; {describe_damage(s)}" if not s.intact else ""
        raise NoScansError(f"no lelsonar scans in {s.path}: {what}{lost}")


def _contract_type(channel: ChannelInfo, schema_name: str) -> type[Message] | None:
    """The contract message type a channel holds, by its protobuf schema name; None for any other channel."""
    cls = codec.MESSAGE_TYPES.get(schema_name)
    return cls if cls is not None and channel.message_encoding == "protobuf" else None


def describe_damage(s: Salvage) -> str:
    """What happened to a file, as a clause for a one-line warning.

    e.g. ``is damaged: 1 chunk (3 messages) unreadable after byte 688187`` or
    ``is damaged: cut at byte 1498671 mid-record (≈3 messages), unfinished`` or
    ``is unfinished (no footer: the writer was stopped or killed), nothing lost``.
    """
    parts = []
    chunks = [d for d in s.damage if d.kind == "chunk"]
    records = [d for d in s.damage if d.kind == "record"]
    tail = [d for d in s.damage if d.kind == "tail"]
    lost, exact = s.messages_lost()
    if chunks:
        n = lost if s.statistics_counts is not None else sum(d.messages_lost for d in chunks)
        approx = "" if exact or all(d.messages is not None for d in chunks) else "≈"
        label = "chunk" if len(chunks) == 1 else "chunks"
        parts.append(f"{len(chunks)} {label} ({approx}{n} messages) unreadable after byte {chunks[0].offset}")
    if records:
        label = "other record" if len(records) == 1 else "other records"
        parts.append(f"{len(records)} {label} unreadable after byte {records[0].offset}")
    if tail:
        parts.append(f"cut at byte {tail[0].offset} mid-record (≈{tail[0].messages_lost} messages)")
    if any(d.kind == "header" for d in s.damage):
        parts.append("the leading magic has flipped bits")
    if any(d.kind == "summary" for d in s.damage):
        parts.append("its index is unreadable")
    if s.orphans:
        parts.append(f"{s.orphans} messages on channels whose definition was lost")
    if lost and not chunks and not tail:
        parts.append(f"{'' if exact else '≈'}{lost} messages lost")
    if not parts:
        return ("is unfinished (no footer: the writer was stopped or killed), nothing lost" if not s.finished
                else "is intact")
    lossless = not (lost or s.orphans or tail)
    return (f"is damaged: {', '.join(parts)}" + ("" if s.finished else ", unfinished")
            + (", no message lost" if lossless else ""))


def open_recording(path: Path | str | Recording) -> Recording:
    """Read a recording tolerantly: every intact message, and an account of the damage.

    Raises
    ------
    RecordingNotFoundError
        Missing path or a directory.
    NotMcapError
        The file is not an MCAP file.
    """
    if isinstance(path, Recording):
        return path
    s = salvage(path)
    if s.orphans:
        _adopt_orphans(s)
    return Recording(s)


def _adopt_orphans(s: Salvage) -> None:
    """Name the channels whose definition was in a damaged chunk, from the recorder's channel metadata.

    The schema is rebuilt from this build's protobuf descriptors, so ``recover`` can write the messages again.
    """
    from mcap_protobuf.schema import build_file_descriptor_set

    from lelsonar.recordings.reader import SchemaInfo

    by_name = {schema.name: sid for sid, schema in s.schemas.items()}
    for cid in sorted({m.channel_id for m in s.messages} - set(s.channels)):
        md = s.metadata.get(f"{CHANNEL_METADATA}{cid}", {})
        cls = RECORDED_TYPES.get(md.get("schema", ""))
        if cls is None or not md.get("topic"):
            continue
        name = cls.DESCRIPTOR.full_name
        if name not in by_name:
            sid = by_name[name] = max(s.schemas, default=0) + 1
            s.schemas[sid] = SchemaInfo(sid, name, "protobuf", build_file_descriptor_set(cls).SerializeToString())
        s.channels[cid] = ChannelInfo(cid, by_name[name], md["topic"], "protobuf", {})
    s.orphans = sum(1 for m in s.messages if m.channel_id not in s.channels)


class PayloadStream:
    """The contract payloads of a recording in log-time order, handed on while the file is still being read.

    The same payloads, in the same order, as :meth:`Recording.payloads` of :func:`open_recording` (the
    same walk, :func:`~lelsonar.recordings.reader.walk_records`: every chunk's CRC checked, damage
    accounted for the same way), but the consumer does not wait for the whole file: the walk runs in the
    consumer's thread, a chunk at a time, and hands on every message no later chunk can precede, while a
    thread decompresses the zstd chunks ahead of it (:class:`~lelsonar.recordings.reader.DecompressAhead`,
    the GIL released a batch of chunks at a time).  Which messages no later chunk can precede, it knows
    from the chunk schedule of a finished, indexed file (:func:`~lelsonar.recordings.reader.chunk_schedule`:
    each chunk's earliest log time, stated twice, in its header and in the summary): a message is handed on
    once its log time is at most the earliest start of the chunks still unread (ties go in file order, as
    the stable sort does).  A file without a schedule (unfinished, cut, damaged record chain), and a message
    whose channel or schema is not yet known from the data section, stop the hand-on until the whole file
    is read; the rest then follows in the sorted order.  At the end the handed-on messages are checked
    against the sorted order of the whole salvage; a writer whose chunks hold messages earlier than their
    stated start (against the MCAP specification) is warned about (the handed-on ones stay as they were)
    and the rest follows sorted.

    Use as a context manager, iterate once; then :attr:`recording` is the :class:`Recording` the walk
    built, with its damage.  The constructor opens the file and raises the typed errors
    (:class:`~lelsonar.errors.RecordingNotFoundError`, :class:`~lelsonar.errors.NotMcapError`); an
    exception of the decompressing thread is raised in the consumer, as it is; leaving the ``with`` early
    (an exception in the consumer, Ctrl-C) stops the thread and closes the file.

    Parameters
    ----------
    path : Path or str
    batch : int
        zstd chunks decompressed per call, ahead of the walk.
    depth : int
        Batches decompressed ahead at most.
    """

    def __init__(self, path: Path | str, *, batch: int = 16, depth: int = 4) -> None:
        self.path = Path(path)
        self._batch, self._depth = batch, depth
        self._ahead: DecompressAhead | None = None
        self._started = False
        #: The recording as read, once the iteration has ended.
        self.recording: Recording | None = None
        self._buf, self._size = open_bytes(self.path)
        try:
            if bytes(self._buf[:8]) != MAGIC:
                begin_salvage(self.path, self._buf, self._size)  # NotMcapError for a foreign file
                self._schedule = None  # flipped bits in the magic: read the way salvage() does, whole
            else:
                self._schedule = chunk_schedule(self._buf, self._size)
        except BaseException:
            self.close()
            raise

    @property
    def streams(self) -> bool:
        """True if payloads can be handed on before the whole file is read (a finished, indexed file)."""
        return self._schedule is not None

    def claimed_scan_messages(self) -> int | None:
        """Scan messages (ScanStart, Sample, ScanEnd) the summary's statistics count; None without them."""
        if self._buf is None or self._schedule is None:
            return None
        summary = Salvage(self.path, self._size)
        end_salvage(self._buf, self._size, summary)
        if summary.statistics_counts is None:
            return None
        scan_types = (codec.ScanStart, codec.Sample, codec.ScanEnd)
        return sum(summary.statistics_counts.get(cid, 0) for cid, cls in Recording(summary).contract_channels().items()
                   if cls in scan_types)

    def __enter__(self) -> PayloadStream:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def close(self) -> None:
        """Stop the decompressing thread (if running) and close the file; safe to call twice."""
        if self._ahead is not None:
            self._ahead.close()
            self._ahead = None
        if self._buf is not None:
            _close(self._buf)
            self._buf = None

    def __iter__(self) -> Iterator[RecordedPayload]:
        if self._started or self._buf is None:
            raise RecordingError(f"a PayloadStream of {self.path} is read once")
        self._started = True
        try:
            yield from self._walk()
        finally:
            self.close()

    def _walk(self) -> Iterator[RecordedPayload]:
        buf, size = self._buf, self._size
        out = begin_salvage(self.path, buf, size)
        schedule = self._schedule or []
        offsets = [offset for offset, _ in schedule]
        if offsets:
            self._ahead = DecompressAhead(buf, offsets, batch=self._batch, depth=self._depth)
        # earliest[k]: the earliest log time chunks k, k+1, ... of the schedule may hold.
        earliest = [0] * (len(schedule) + 1)
        earliest[-1] = 2 ** 64
        for k in range(len(schedule) - 1, -1, -1):
            earliest[k] = min(schedule[k][1], earliest[k + 1])
        held: list[tuple[int, int, RawMessage]] = []  # (log time, file order, message): a heap
        handed: list[RawMessage] = []
        seen = 0
        blocked = self._schedule is None
        for pos in walk_records(buf, size, out, self._ahead):
            messages = out.messages
            if len(messages) == seen:
                continue  # a record without messages (an index, metadata, a damaged chunk)
            if blocked:
                seen = len(messages)
                continue  # the rest comes sorted once the whole file is read
            while seen < len(messages):
                m = messages[seen]
                heapq.heappush(held, (m.log_time, seen, m))
                seen += 1
            until = earliest[bisect.bisect_left(offsets, pos)]
            while held and held[0][0] <= until:
                m = held[0][2]
                channel = out.channels.get(m.channel_id)
                schema = out.schemas.get(channel.schema_id) if channel is not None else None
                if schema is None:  # the summary or a later record may still name it: wait for the end
                    blocked = True
                    break
                heapq.heappop(held)
                handed.append(m)
                if _contract_type(channel, schema.name) is not None:
                    yield RecordedPayload(m.log_time, channel.topic, schema.name, m.data)
        end_salvage(buf, size, out)
        if out.orphans:
            _adopt_orphans(out)
        recording = Recording(out)
        ordered = out.in_log_time_order()
        n = len(handed)
        if len(ordered) >= n and all(a is b for a, b in zip(ordered, handed)):
            rest = ordered[n:]
        else:
            _log.warning("%s: a chunk holds messages earlier than its stated start time (the MCAP "
                         "specification forbids it); %d messages were replayed before they should have been "
                         "in log-time order", self.path, n)
            done = {id(m) for m in handed}
            rest = [m for m in ordered if id(m) not in done]
        self.recording = recording
        yield from recording._payloads_of(rest)


def _close(buf) -> None:
    if isinstance(buf, mmap.mmap):
        buf.close()


def iter_payloads(path: Path | str | Recording) -> Iterator[RecordedPayload]:
    """Yield the contract messages of a recording in log-time order, undecoded.

    A path is read by a :class:`PayloadStream` (handed on as it is read).  A damaged or
    unfinished file yields every intact message and logs one warning once it has been read (pass an
    opened :class:`Recording` to report the damage yourself: then nothing is logged).

    Raises
    ------
    RecordingError
        If the file is missing, a directory or not an MCAP file
        (:class:`~lelsonar.errors.RecordingNotFoundError`,
        :class:`~lelsonar.errors.NotMcapError`).
    """
    if isinstance(path, Recording):
        yield from path.payloads()
        return
    with PayloadStream(path) as stream:
        yield from stream
        if line := stream.recording.damage_warning():
            _log.warning("%s", line.removeprefix("warning: "))


def read_messages(path: Path | str | Recording,
                  limits: codec.DecodeLimits = codec.DEFAULT_LIMITS) -> Iterator[Message]:
    """Decoded, validated contract messages in log-time order; a bad record raises DecodeError."""
    for rec in iter_payloads(path):
        cls = codec.MESSAGE_TYPES.get(rec.type_name)
        if cls is None:
            raise DecodeError(f"{rec.topic} holds {rec.type_name!r}, not a lelsonar.v1 message")
        yield codec.decode(rec.payload, cls, limits)


def read_metadata(path: Path | str | Recording) -> dict[str, dict[str, str]]:
    """All metadata records of a recording, by name."""
    return dict(open_recording(path).salvage.metadata)


