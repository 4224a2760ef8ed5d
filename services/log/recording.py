"""MCAP recordings: the lelsonar channels plus Foxglove channels that viewers draw.

A recording holds, in log-time order (log time = acquisition time):

==============================  ================================  ==========================
topic                           schema                            what
==============================  ================================  ==========================
``/lelsonar/scan_start``        ``lelsonar.v1.ScanStart``         one per scan
``/lelsonar/sample``            ``lelsonar.v1.Sample``            one per step
``/lelsonar/scan_end``          ``lelsonar.v1.ScanEnd``           one per scan
``/lelsonar/reconstruction``    ``lelsonar.v1.Reconstruction``    estimates, when recorded
``/tf``                         ``foxglove.FrameTransform``       world → array, per step; map → odom →
                                                                  base_link → world per scan with a pose
``/lelsonar/points``            ``foxglove.PointCloud``           raw points of the step (eq. 9)
``/log``                        ``foxglove.Log``                  events
``/tf_capsules``                ``foxglove.FrameTransforms``      array → capsule_X, per scan
``/lelsonar/array``             ``foxglove.SceneUpdate``          the capsules and their beams
``/lelsonar/scan_points``       ``foxglove.PointCloud``           every raw point of the scan so far
``/lelsonar/step``              JSON ``lelsonar.StepScalars``     γ, ranges, energies (plottable)
``/lelsonar/energy``            JSON ``lelsonar.EnergyScalars``   E^γ, E0(d_m), R per step (plottable)
``/lelsonar/truth``             ``foxglove.SceneUpdate``          true planes, simulated scans only
``/lelsonar/planes``            ``foxglove.SceneUpdate``          estimated planes, when recorded
``/lelsonar/world``             ``foxglove.SceneUpdate``          the scan's pose; a simulated world as truth
==============================  ================================  ==========================

The viewer channels come from :mod:`lelsonar.draw.visual`.  Each scan also adds a
``lelsonar.log.recording`` metadata record naming it (``name``, scanner, scan,
device, software).  ``rerun file.mcap`` shows ``/tf`` as a Transform3D and the
points as Points3D; Foxglove shows everything, and plots ``/lelsonar/step``.
A step's contract message and its viewer messages share one chunk.
"""

from __future__ import annotations

import base64
import binascii
import errno
import json
import logging
import os
import shutil
import time
from collections.abc import Callable, Generator, Iterator, Mapping
from contextlib import contextmanager
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
from mcap_protobuf.schema import build_file_descriptor_set, register_schema

from lelsonar import __version__, codec
from lelsonar.draw import visual
from lelsonar.errors import DecodeError, NoScansError, RecordingError
from lelsonar.log.reader import ChannelInfo, McapSource, RawMessage, Salvage, SchemaInfo, open_mcap

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
#: Metadata record repeating each scan's ScanStart (outside the chunks), ``lelsonar.scan_start.<scanner>.<scan>``.
SCAN_START_METADATA = "lelsonar.scan_start."
#: The protobuf types a lelsonar recording may hold, by full name (to rebuild a lost schema record).
RECORDED_TYPES: dict[str, type[Message]] = {
    **codec.MESSAGE_TYPES,
    **{cls.DESCRIPTOR.full_name: cls for cls in (FrameTransform, FrameTransforms, PointCloud, Log, SceneUpdate)},
}

COMPRESSIONS = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}


class McapRecorder:
    """Write a lelsonar recording; always finishes the file, even on an exception.

    Durable before published: every :meth:`write` and :meth:`log` closes its own
    MCAP chunk (a Sample, its /tf and its points are one chunk: one step) and
    hands it to the operating system before returning, so a caller that
    publishes after ``write`` never publishes what the file lacks.  A process
    killed at any moment (``kill -9``) loses at most the message being written;
    :func:`lelsonar.log.recover.recover` turns the unfinished file into
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
        chunks written when full; a killed writer then loses the whole chunk in
        progress.  Kept as the benchmark's floor.
    truth : list of (label, normal, offset, corners), optional
        The true planes of a simulated scene, drawn on ``/lelsonar/truth`` at each ScanStart.
    """

    def __init__(
        self,
        path: Path | str,
        *,
        compression: str = "zstd",
        metadata: Mapping[str, str] | None = None,
        fsync: bool = False,
        durable: bool = True,
        truth=None,
    ) -> None:
        if compression not in COMPRESSIONS:
            raise RecordingError(f"compression must be one of {', '.join(COMPRESSIONS)}, got {compression!r}")
        self.path = Path(path)
        self._finished = False
        #: Why writing failed (a full or read-only disk), or None: once set, nothing more is written.
        self.failure: str | None = None
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file = open(self.path, "wb")  # noqa: SIM115 - closed in finish()
        except OSError as exc:
            raise RecordingError(write_failure(self.path, exc)) from None
        self._writer = McapWriter(self._file, compression=COMPRESSIONS[compression])
        self._channels: dict[str, int] = {}
        self._fsync = fsync
        self._durable = durable or fsync
        self._starts: dict[tuple[str, int], codec.ScanStart] = {}
        self._truth = truth
        self.messages_written = 0
        self._world = truth_world(metadata)
        with self._failing():
            self._writer.start(library=f"lelsonar {__version__}")
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
        """Write the summary and footer and close the file; safe to call twice.

        After a failed write the file is closed as it is: every step committed before the failure stays
        readable by the tolerant reader (:func:`open_recording`, ``lelsonar recover``).
        """
        if self._finished:
            return
        self._finished = True
        try:
            if self.failure is None:
                with self._failing():
                    self._writer.finish()
                    self._file.flush()
                    if self._fsync:
                        os.fsync(self._file.fileno())
        except RecordingError as exc:
            _log.error("%s", exc)
        finally:
            try:
                self._file.close()
            except OSError:
                pass  # the failure is recorded: a buffer that cannot be flushed is the failed write's

    @contextmanager
    def _failing(self) -> Iterator[None]:
        """Turn an OSError of the disk into one RecordingError naming the directory and its free space."""
        try:
            yield
        except OSError as exc:
            self.failure = write_failure(self.path, exc)
            raise RecordingError(self.failure) from None

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
            self._writer.add_metadata(
                f"{CHANNEL_METADATA}{channel}", {"topic": topic, "schema": type(message).DESCRIPTOR.full_name}
            )
        self._writer.add_message(channel, log_time=t, data=message.SerializeToString(), publish_time=t)

    # --- writing ---------------------------------------------------------------------
    def write(self, message: Message, log_time_ns: int | None = None) -> None:
        """Record one contract message; a Sample also gets its /tf and /lelsonar/points."""
        self._check_writable()
        topic = TOPICS.get(type(message))
        if topic is None:
            raise RecordingError(f"{type(message).__name__} is not a lelsonar contract message")
        t = log_time_ns if log_time_ns is not None else _message_time(message)
        with self._failing():
            self._put(topic, message, t)
            if isinstance(message, codec.ScanStart):
                self._starts[(message.scanner_id, message.scan_id)] = message
            elif isinstance(message, codec.Sample):
                self._write_pose_and_points(message, t)
            self._write_views(message, t)
            self._commit()
        self.messages_written += 1

    def _check_writable(self) -> None:
        if self.failure is not None:
            raise RecordingError(self.failure)
        if self._finished:
            raise RecordingError(f"{self.path} is already finished")

    def log(self, level: str, text: str, log_time_ns: int | None = None, name: str = "lelsonar") -> None:
        """Record a ``foxglove.Log`` event (level: DEBUG, INFO, WARNING, ERROR, FATAL)."""
        self._check_writable()
        t = log_time_ns if log_time_ns is not None else time.time_ns()
        with self._failing():
            self._put(TOPIC_LOG, visual.log_message(level, text, t, name), t)
            self._commit()

    # --- what viewers draw, beside the contract (lelsonar.draw.visual) -------------------------
    @cached_property
    def _views(self) -> _ViewState:
        return _ViewState()

    def _write_views(self, message: Message, t: int) -> None:
        """The viewer channels of a contract message: a recording opened alone shows the scan."""
        views = self._views
        if isinstance(message, codec.ScanStart):
            views.cloud.scan_started(message)
            self._put(visual.TOPIC_CAPSULE_TF, visual.capsule_transforms(message, t), t)
            for tf in visual.pose_transforms(message, t):  # where the robot was: map → odom → base_link → world
                self._put(TOPIC_TF, tf, t)
            pose = visual.pose_scene(message, t)
            if pose is not None:
                self._put(visual.TOPIC_WORLD, pose, t)
            if self._world is not None:  # a simulated world, drawn as truth
                self._put(visual.TOPIC_WORLD, visual.world_scene(self._world, t), t)
            self._put(visual.TOPIC_ARRAY, visual.array_model(message, t), t)
            self._writer.add_metadata("lelsonar.log.recording", recording_name_metadata(message))
            # The scan's header again, outside any chunk: a damaged first chunk does not take the scan with it.
            self._writer.add_metadata(*scan_start_metadata(message, t))
            if self._truth:
                self._put(visual.TOPIC_TRUTH, visual.truth_scene(self._truth, message.scanner_id, t), t)
        elif isinstance(message, codec.Sample):
            cloud = views.cloud.add(message, t)
            if cloud is not None:
                self._put(visual.TOPIC_SCAN_POINTS, cloud, t)
            step = visual.step_scalars(message)
            self.write_json(visual.TOPIC_STEP, visual.STEP_SCALARS_NAME, visual.STEP_SCALARS_SCHEMA, step, t)
            start = self._starts.get((message.scanner_id, message.scan_id))
            if start is not None:
                energy = visual.acquisition_energy_scalars(start, message, step)
                self.write_json(
                    visual.TOPIC_ENERGY, visual.ENERGY_SCALARS_NAME, visual.ENERGY_SCALARS_SCHEMA, energy, t
                )
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
        self._writer.add_message(
            channel, log_time=log_time_ns, data=json.dumps(payload).encode(), publish_time=log_time_ns
        )

    def _write_pose_and_points(self, sample: codec.Sample, t: int) -> None:
        self._put(TOPIC_TF, visual.array_transform(sample.gamma_measured, t), t)
        start = self._starts.get((sample.scanner_id, sample.scan_id))
        if start is None:
            return
        pts, _capsules = visual.sample_points(start, sample)
        if len(pts):
            self._put(TOPIC_POINTS, visual.point_cloud(pts, t), t)


def truth_world(metadata: Mapping[str, str] | None) -> dict | None:
    """The simulated world of a recording's metadata (``truth_world``, JSON), or None."""
    text = (metadata or {}).get("truth_world")
    if not text:
        return None
    try:
        world = json.loads(text)
    except ValueError:
        _log.warning("the recording's truth_world metadata is not JSON; the world is not drawn")
        return None
    return world if isinstance(world, dict) and isinstance(world.get("walls"), list) else None


@dataclass
class _ViewState:
    cloud: visual.ScanCloud = field(default_factory=visual.ScanCloud)
    planes: visual.PlaneScene = field(default_factory=visual.PlaneScene)
    json_channels: dict[str, int] = field(default_factory=dict)


def scan_start_metadata(start: codec.ScanStart, log_time_ns: int) -> tuple[str, dict[str, str]]:
    """The metadata record that repeats a scan's ScanStart: ``lelsonar.scan_start.<scanner>.<scan_id>``."""
    return (
        f"{SCAN_START_METADATA}{start.scanner_id}.{start.scan_id}",
        {
            "scanner_id": start.scanner_id,
            "scan_id": str(start.scan_id),
            "log_time_ns": str(log_time_ns),
            "payload_base64": base64.b64encode(start.SerializeToString()).decode("ascii"),
        },
    )


def recording_name_metadata(start: codec.ScanStart) -> dict[str, str]:
    """The ``lelsonar.log.recording`` metadata record of a scan: a human name and what it was."""
    return {
        "name": f"lelsonar {start.scanner_id} scan {start.scan_id}",
        "scanner_id": start.scanner_id,
        "scan_id": str(start.scan_id),
        "device": start.device or "unknown",
        "software_version": start.software_version,
        "start_time_ns": str(start.start_time_ns),
        "steps": str(start.steps),
    }


def free_space(path: Path | str) -> int | None:
    """Bytes free for an unprivileged writer on the filesystem of ``path`` (or its nearest existing parent)."""
    p = Path(path).absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    try:
        return shutil.disk_usage(p).free
    except OSError:
        return None


def _mib(n: int | None) -> str:
    return "? MiB" if n is None else f"{n / 2**20:.1f} MiB"


def write_failure(path: Path, exc: OSError) -> str:
    """One line on a failed write: what, the directory, and its free space."""
    where = path.parent
    what = exc.strerror or str(exc)
    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        what = "no space left on the device"
    elif exc.errno in (errno.EROFS, errno.EACCES, errno.EPERM):
        what = "the directory is read-only or not writable" if exc.errno != errno.EROFS else "read-only filesystem"
    fix = (
        "free some space or give another --out directory"
        if exc.errno in (errno.ENOSPC, errno.EDQUOT)
        else "give a writable --out directory"
    )
    return f"cannot record to {where}: {what} ({_mib(free_space(where))} free); {fix}"


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

    def payloads(self) -> Iterator[RecordedPayload]:
        """The contract messages in log-time order, undecoded, read chunk by chunk.

        Only the chunks that hold contract messages are decompressed (by their message index);
        when the iterator is exhausted, ``salvage`` accounts for what was read.  A scan whose ScanStart
        was lost (a damaged chunk) gets it back from the recorder's ``lelsonar.scan_start.*`` metadata
        copy, in its place in log time (:attr:`restored` names those scans once read).
        """
        s = self.salvage
        start_name = codec.ScanStart.DESCRIPTOR.full_name
        copies = sorted(self.start_copies().items(), key=lambda kv: kv[1].log_time_ns)
        seen: set[tuple[str, int]] = set()
        names: dict[int, tuple[str, str]] = {}
        for m in self.messages(is_contract_channel):
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
        self, want: Callable[[ChannelInfo, SchemaInfo | None], bool] | None = None, *, verify_all: bool = False
    ) -> Iterator[RawMessage]:
        """The intact messages of the channels ``want`` accepts (all if None), in log-time order.

        ``verify_all`` decompresses and checks every chunk, wanted or not, so the damage is complete.
        """
        if self.source is not None:
            return self.source.read(want, verify_all=verify_all)
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


def iter_payloads(path: Path | str | Recording) -> Generator[RecordedPayload, None, None]:
    """Yield the contract messages of a recording in log-time order, undecoded.

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
    yield from rec.payloads()
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
