"""Reading a lelsonar recording: the contract messages a file holds, what survived, and what did not.

:func:`open_recording` opens a file tolerantly (:mod:`lelsonar.log.reader`); :meth:`Recording.payloads`
and :func:`iter_payloads` yield its contract messages in log-time order, undecoded, chunk by chunk.
The names of the recorder's channels and metadata records live here, shared with the writer
(:mod:`lelsonar.log.recording`).
"""

from __future__ import annotations

import base64
import binascii
import logging
from collections.abc import Callable, Collection, Generator, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.Log_pb2 import Log
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from google.protobuf.message import Message
from mcap_protobuf.schema import build_file_descriptor_set

from lelsonar import codec
from lelsonar.errors import DecodeError, NoScansError
from lelsonar.log.reader import ChannelInfo, McapSource, RawMessage, Salvage, SchemaInfo, open_mcap

_log = logging.getLogger(__name__)

TOPICS: dict[type[Message], str] = {
    codec.ScanStart: "/lelsonar/scan_start",
    codec.Sample: "/lelsonar/sample",
    codec.ScanEnd: "/lelsonar/scan_end",
    codec.Reconstruction: "/lelsonar/reconstruction",
}

#: Metadata record naming each channel, ``lelsonar.channel.<id>`` → {"topic": ..., "schema": ...}.
CHANNEL_METADATA = "lelsonar.channel."
#: Metadata record repeating each scan's ScanStart (outside the chunks), ``lelsonar.scan_start.<scanner>.<scan>``.
SCAN_START_METADATA = "lelsonar.scan_start."
#: The protobuf types a lelsonar recording may hold, by full name (to rebuild a lost schema record).
RECORDED_TYPES: dict[str, type[Message]] = {
    **codec.MESSAGE_TYPES,
    **{cls.DESCRIPTOR.full_name: cls for cls in (FrameTransform, FrameTransforms, PointCloud, Log, SceneUpdate)},
}


class RecordedPayload(NamedTuple):
    """One contract message as stored: its type name and raw bytes, not yet decoded.

    Replay decodes these through :func:`lelsonar.codec.decode`, the same path as live data.  (A named tuple:
    one is made per message replayed, and a frozen dataclass costs several times as much to make.)
    """

    log_time_ns: int
    topic: str
    type_name: str
    payload: bytes


@dataclass(frozen=True)
class Recording:
    """A recording as read by the tolerant reader: what survived, and what did not.

    Build with :func:`open_recording`; iterate the contract payloads with
    :meth:`payloads` or :func:`iter_payloads` (which takes a Recording or a path), in
    memory bounded by a chunk, whatever the file's length.  What the reads found (counts,
    damage) accumulates in ``salvage``.
    """

    salvage: Salvage
    source: McapSource | None = None
    #: Scans whose ScanStart :meth:`payloads` restored from its metadata copy (the one in the chunks was lost).
    restored: set[tuple[str, int]] = field(default_factory=set)

    @property
    def path(self) -> Path:
        return self.salvage.path

    def contract_channels(self) -> dict[int, type[codec.WireMessage]]:
        """The channels that hold contract messages, and the message type of each.

        A channel is the contract's by its protobuf schema name (``lelsonar.v1.Sample`` …), whatever
        its topic: another writer of the schema (a simulator, a bridge) may name its topics otherwise.
        Every payload is still decoded and validated by the consumer.
        """
        s = self.salvage
        out: dict[int, type[codec.WireMessage]] = {}
        for cid, ch in s.channels.items():
            cls = codec.MESSAGE_TYPES.get(s.schema_name(cid))
            if cls is not None and ch.message_encoding == "protobuf":
                out[cid] = cls
        return out

    def payloads(
        self, types: Collection[type[Message]] | None = None, *, decompress_threads: int = 0
    ) -> Iterator[RecordedPayload]:
        """The contract messages in log-time order, undecoded, read chunk by chunk.

        ``types``: the contract messages wanted (all if None); a chunk holding none of them is not
        decompressed (by its message index), as the chunks of the viewer channels are not;
        ``decompress_threads``: see :meth:`~lelsonar.log.reader.McapSource.read`;
        when the iterator is exhausted, ``salvage`` accounts for what was read.  A scan whose ScanStart
        was lost (a damaged chunk) gets it back from the recorder's ``lelsonar.scan_start.*`` metadata
        copy, in its place in log time (:attr:`restored` names those scans once read).
        """
        s = self.salvage
        start_name = codec.ScanStart.DESCRIPTOR.full_name
        wanted = None if types is None else frozenset(cls.DESCRIPTOR.full_name for cls in types)

        def want(channel: ChannelInfo, schema: SchemaInfo | None) -> bool:
            if not is_contract_channel(channel, schema):
                return False
            return wanted is None or (schema is not None and schema.name in wanted)

        copies = sorted(self.start_copies().items(), key=lambda kv: kv[1].log_time_ns)
        if wanted is not None and start_name not in wanted:
            copies = []
        seen: set[tuple[str, int]] = set()
        names: dict[int, tuple[str, str]] = {}
        for m in self.messages(want, decompress_threads=decompress_threads):
            # Messages come in log-time order: a copy older than this message whose ScanStart has not
            # come is one whose ScanStart was lost.
            while copies and copies[0][1].log_time_ns < m.log_time:
                key, copy = copies.pop(0)
                if key not in seen:
                    seen.add(key)
                    self.restored.add(key)
                    yield copy
            name = names.get(m.channel_id)
            if name is None:
                name = names[m.channel_id] = (s.topic(m.channel_id), s.schema_name(m.channel_id))
            if name[1] == start_name:
                try:
                    start = codec.ScanStart.FromString(m.data)
                    seen.add((start.scanner_id, start.scan_id))
                except Exception:  # noqa: BLE001 - an unreadable ScanStart is refused by the decoding, later
                    pass
            yield RecordedPayload(m.log_time, name[0], name[1], m.data)
        for key, copy in copies:
            if key not in seen:
                self.restored.add(key)
                yield copy

    def start_copies(self) -> dict[tuple[str, int], RecordedPayload]:
        """Every scan's ScanStart as its metadata copy holds it (outside the chunks), by (scanner, scan)."""
        out = {}
        for name, md in self.salvage.metadata.items():
            if not name.startswith(SCAN_START_METADATA):
                continue
            try:
                key = (md["scanner_id"], int(md["scan_id"]))
                payload = base64.b64decode(md["payload_base64"], validate=True)
                t = int(md["log_time_ns"])
            except (KeyError, ValueError, binascii.Error):
                continue  # a damaged copy: the scan stays without its start, as it would without a copy
            out[key] = RecordedPayload(t, TOPICS[codec.ScanStart], codec.ScanStart.DESCRIPTOR.full_name, payload)
        return out

    def messages(
        self,
        want: Callable[[ChannelInfo, SchemaInfo | None], bool] | None = None,
        *,
        verify_all: bool = False,
        decompress_threads: int = 0,
    ) -> Iterator[RawMessage]:
        """The intact messages of the channels ``want`` accepts (all if None), in log-time order.

        ``verify_all`` decompresses and checks every chunk, wanted or not, so the damage is complete.
        """
        if self.source is not None:
            return self.source.read(want, verify_all=verify_all, decompress_threads=decompress_threads)
        s = self.salvage  # read already, into memory (lelsonar.log.reader.salvage)
        return (
            m
            for m in s.in_log_time_order()
            if want is None or want(s.channels[m.channel_id], s.schemas.get(s.channels[m.channel_id].schema_id))
        )

    def read_all(self) -> Recording:
        """Read (and check) every chunk once, keeping nothing, so that the counts and the damage are complete."""
        if not self.salvage.read_done:
            for _ in self.messages(_nothing, verify_all=True):
                pass
        return self

    def expected_payloads(self) -> int | None:
        """Contract messages the file's indexes announce (its statistics, or the chunks' message indexes)."""
        s = self.salvage
        counts = s.statistics_counts if s.statistics_counts is not None else s.indexed_counts
        if not counts:
            return None
        return sum(counts.get(cid, 0) for cid in self.contract_channels())

    def count(self, kind: str | type[Message]) -> int:
        """Messages read on a topic, or of a contract message type (on whichever topics); reads the file if needed."""
        if isinstance(kind, str):
            ids = {cid for cid, ch in self.salvage.channels.items() if ch.topic == kind}
        else:
            ids = {cid for cid, cls in self.contract_channels().items() if cls is kind}
        counts = self.read_all().salvage.counts
        return sum(counts.get(cid, 0) for cid in ids)

    @property
    def has_scans(self) -> bool:
        """Whether the file holds a scan message: as read, or before any read, as its indexes announce."""
        s = self.salvage
        ids = [
            cid
            for cid, cls in self.contract_channels().items()
            if cls in (codec.ScanStart, codec.Sample, codec.ScanEnd)
        ]
        if s.read_done:
            return any(s.counts.get(cid) for cid in ids)
        announced = s.statistics_counts if s.statistics_counts is not None else s.indexed_counts
        if announced:
            return any(announced.get(cid) for cid in ids)
        return bool(ids)  # no index: the read decides (require_scans again after it)

    def damage_warning(self) -> str | None:
        """One line saying what was lost, or None for an intact, finished file; reads the file if no read has.

        e.g. ``warning: scan.mcap is damaged: 1 chunk (≈10 messages) unreadable after byte 81234; 118 samples
        salvaged``.  After :meth:`payloads`, it tells what that read found (in the chunks it read).
        """
        s = self.read_all().salvage
        if s.intact:
            return None
        return f"warning: {s.path} {describe_damage(s)}; {self.count(codec.Sample)} samples salvaged"

    def require_scans(self) -> Recording:
        """Self, or :class:`NoScansError` when no scan message survived (foreign channels, or all lost).

        Before a read, it goes by what the indexes announce; after one, by what was read.
        """
        if self.has_scans:
            return self
        s = self.salvage
        held = sorted({ch.topic for ch in s.channels.values()})
        what = f"its channels are {', '.join(held)}" if held else "it has no readable channels"
        lost = f"; {describe_damage(s)}" if not s.intact else ""
        raise NoScansError(f"no lelsonar scans in {s.path}: {what}{lost}")


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
        what = "message" if n == 1 and not approx else "messages"
        parts.append(f"{len(chunks)} {label} ({approx}{n} {what}) unreadable after byte {chunks[0].offset}")
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
        return (
            "is unfinished (no footer: the writer was stopped or killed), nothing lost"
            if not s.finished
            else "is intact"
        )
    lossless = not (lost or s.orphans or tail)
    return (
        f"is damaged: {', '.join(parts)}"
        + ("" if s.finished else ", unfinished")
        + (", no message lost" if lossless else "")
    )


def open_recording(path: Path | str | Recording) -> Recording:
    """Open a recording tolerantly: its channels and framing now, its messages as they are read.

    Raises
    ------
    RecordingNotFoundError
        Missing path or a directory.
    NotMcapError
        The file is not an MCAP file.
    """
    if isinstance(path, Recording):
        return path
    source = open_mcap(path)
    _adopt_orphans(source.account)
    return Recording(source.account, source)


def is_contract_channel(channel: ChannelInfo, schema: SchemaInfo | None) -> bool:
    """A channel of contract messages: by its protobuf schema's name, whatever its topic."""
    return schema is not None and channel.message_encoding == "protobuf" and schema.name in codec.MESSAGE_TYPES


def _nothing(channel: ChannelInfo, schema: SchemaInfo | None) -> bool:
    return False


def _adopt_orphans(s: Salvage) -> None:
    """Name the channels whose definition was in a damaged chunk, from the recorder's channel metadata.

    The schema is rebuilt from this build's protobuf descriptors, so ``recover`` can write the messages again.
    """
    referenced = set(s.indexed_counts) | set(s.statistics_counts or ()) | {m.channel_id for m in s.messages}
    missing = referenced - set(s.channels)
    if not missing:
        return
    by_name = {schema.name: sid for sid, schema in s.schemas.items()}
    for cid in sorted(missing):
        md = s.metadata.get(f"{CHANNEL_METADATA}{cid}", {})
        cls = RECORDED_TYPES.get(md.get("schema", ""))
        if cls is None or not md.get("topic"):
            continue
        name = cls.DESCRIPTOR.full_name
        if name not in by_name:
            sid = by_name[name] = max(s.schemas, default=0) + 1
            s.schemas[sid] = SchemaInfo(sid, name, "protobuf", build_file_descriptor_set(cls).SerializeToString())
        s.channels[cid] = ChannelInfo(cid, by_name[name], md["topic"], "protobuf", {})
    if s.messages:
        s.orphans = sum(1 for m in s.messages if m.channel_id not in s.channels)


def iter_payloads(
    path: Path | str | Recording, types: Collection[type[Message]] | None = None, *, decompress_threads: int = 0
) -> Generator[RecordedPayload, None, None]:
    """Yield the contract messages of a recording (of ``types``, all if None) in log-time order, undecoded.

    A damaged or unfinished file yields every intact message and, at the end,
    logs one warning (pass an opened :class:`Recording` to report the damage
    yourself: then nothing is logged).

    Raises
    ------
    RecordingError
        If the file is missing, a directory or not an MCAP file
        (:class:`~lelsonar.errors.RecordingNotFoundError`,
        :class:`~lelsonar.errors.NotMcapError`).
    """
    rec = open_recording(path)
    yield from rec.payloads(types, decompress_threads=decompress_threads)
    if not isinstance(path, Recording) and (line := rec.damage_warning()):
        _log.warning("%s", line.removeprefix("warning: "))


def read_messages(path: Path | str | Recording, limits: codec.DecodeLimits = codec.DEFAULT_LIMITS) -> Iterator[Message]:
    """Decoded, validated contract messages in log-time order; a bad record raises DecodeError."""
    for rec in iter_payloads(path):
        cls = codec.MESSAGE_TYPES.get(rec.type_name)
        if cls is None:
            raise DecodeError(f"{rec.topic} holds {rec.type_name!r}, not a lelsonar.v1 message")
        yield codec.decode(rec.payload, cls, limits)


def read_metadata(path: Path | str | Recording) -> dict[str, dict[str, str]]:
    """All metadata records of a recording, by name."""
    return dict(open_recording(path).salvage.metadata)
