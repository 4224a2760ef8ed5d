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
Each contract message is a chunk of its own, handed to the OS before ``write`` returns; its
viewer messages follow in the next chunk, so a reader of the contract (a replay) skips them
through the chunks' message indexes without decompressing them.
"""

from __future__ import annotations

import base64
import errno
import json
import logging
import os
import shutil
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

from google.protobuf.message import Message
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from mcap_protobuf.schema import register_schema

from lelsonar import __version__, codec
from lelsonar.draw import visual
from lelsonar.errors import RecordingError
from lelsonar.log.recorded import (
    CHANNEL_METADATA,
    RECORDED_TYPES,
    SCAN_START_METADATA,
    TOPICS,
    RecordedPayload,
    Recording,
    describe_damage,
    is_contract_channel,
    iter_payloads,
    open_recording,
    read_messages,
    read_metadata,
)

# The reading side is lelsonar.log.recorded; its names are importable from here too.
__all__ = [
    "ARRAY_FRAME",
    "CHANNEL_METADATA",
    "COMPRESSIONS",
    "RECORDED_TYPES",
    "SCAN_START_METADATA",
    "TOPICS",
    "TOPIC_LOG",
    "TOPIC_POINTS",
    "TOPIC_TF",
    "WORLD_FRAME",
    "McapRecorder",
    "RecordedPayload",
    "Recording",
    "describe_damage",
    "free_space",
    "is_contract_channel",
    "iter_payloads",
    "open_recording",
    "read_messages",
    "read_metadata",
    "recording_name_metadata",
    "scan_start_metadata",
    "truth_world",
    "write_failure",
]

_log = logging.getLogger(__name__)

TOPIC_TF = "/tf"
TOPIC_POINTS = visual.TOPIC_POINTS
TOPIC_LOG = "/log"
WORLD_FRAME = visual.WORLD_FRAME
ARRAY_FRAME = visual.ARRAY_FRAME

COMPRESSIONS = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}


class McapRecorder:
    """Write a lelsonar recording; always finishes the file, even on an exception.

    Durable before published: every :meth:`write` and :meth:`log` closes its own
    MCAP chunk (a Sample alone: one step) and hands it to the operating system
    before returning, so a caller that publishes after ``write`` never publishes
    what the file lacks; the step's viewer messages (its /tf, its points …) are
    the next chunk, handed over before ``write`` returns too.  A process
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
        True (default): a chunk per contract message (and one for its views), flushed to the OS.  False: 1 MiB
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

    def _commit(self, *, views: bool = False) -> None:
        """Close the chunk in progress and hand it to the OS (and the disk, with fsync).

        A chunk of ``views`` is not forced to the disk: what viewers draw is derived from the contract
        messages, and the next step's fsync takes it along (it precedes that step in the file).
        """
        if not self._durable:
            return
        self._writer.flush()  # finishes the chunk, writes its message index, flushes the stream
        if self._fsync and not views:
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
            self._commit()  # the contract message alone in its chunk: a replay decompresses nothing else
            self.messages_written += 1
            if isinstance(message, codec.ScanStart):
                self._starts[(message.scanner_id, message.scan_id)] = message
            elif isinstance(message, codec.Sample):
                self._write_pose_and_points(message, t)
            self._write_views(message, t)
            self._commit(views=True)

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
