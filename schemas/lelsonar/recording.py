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
"""

from __future__ import annotations

import json
import struct
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

from google.protobuf.message import Message
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.writer import CompressionType
from mcap_protobuf.writer import Writer

from lelsonar import codec, visual
from lelsonar.errors import DecodeError, RecordingError

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

COMPRESSIONS = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}


class McapRecorder:
    """Write a lelsonar recording; always finishes the file, even on an exception.

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
    """

    def __init__(self, path: Path | str, *, compression: str = "zstd",
                 metadata: Mapping[str, str] | None = None) -> None:
        if compression not in COMPRESSIONS:
            raise RecordingError(f"compression must be one of {', '.join(COMPRESSIONS)}, got {compression!r}")
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, "wb")  # noqa: SIM115 - closed in finish()
        self._writer = Writer(self._file, compression=COMPRESSIONS[compression])
        self._starts: dict[tuple[str, int], codec.ScanStart] = {}
        self._finished = False
        self.messages_written = 0
        if metadata:
            self._writer.add_metadata("lelsonar.config", {str(k): str(v) for k, v in metadata.items()})

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
        finally:
            self._file.close()

    # --- writing ---------------------------------------------------------------------
    def write(self, message: Message, log_time_ns: int | None = None) -> None:
        """Record one contract message; a Sample also gets its /tf and /lelsonar/points."""
        if self._finished:
            raise RecordingError(f"{self.path} is already finished")
        topic = TOPICS.get(type(message))
        if topic is None:
            raise RecordingError(f"{type(message).__name__} is not a lelsonar contract message")
        t = log_time_ns if log_time_ns is not None else _message_time(message)
        self._writer.write_message(topic, message, log_time=t, publish_time=t)
        self.messages_written += 1
        if isinstance(message, codec.ScanStart):
            self._starts[(message.scanner_id, message.scan_id)] = message
        elif isinstance(message, codec.Sample):
            self._write_pose_and_points(message, t)
        self._write_views(message, t)

    def log(self, level: str, text: str, log_time_ns: int | None = None, name: str = "lelsonar") -> None:
        """Record a ``foxglove.Log`` event (level: DEBUG, INFO, WARNING, ERROR, FATAL)."""
        t = log_time_ns if log_time_ns is not None else time.time_ns()
        self._writer.write_message(TOPIC_LOG, visual.log_message(level, text, t, name), log_time=t, publish_time=t)

    # --- what viewers draw, beside the contract (lelsonar.visual) -------------------------
    @cached_property
    def _views(self) -> _ViewState:
        return _ViewState()

    def _write_views(self, message: Message, t: int) -> None:
        """The viewer channels of a contract message: a recording opened alone shows the scan."""
        w, views = self._writer, self._views
        if isinstance(message, codec.ScanStart):
            views.cloud.scan_started(message)
            w.write_message(visual.TOPIC_CAPSULE_TF, visual.capsule_transforms(message, t), log_time=t, publish_time=t)
            w.write_message(visual.TOPIC_ARRAY, visual.array_model(message, t), log_time=t, publish_time=t)
            w.add_metadata("lelsonar.recording", recording_name_metadata(message))
        elif isinstance(message, codec.Sample):
            cloud = views.cloud.add(message, t)
            if cloud is not None:
                w.write_message(visual.TOPIC_SCAN_POINTS, cloud, log_time=t, publish_time=t)
            self.write_json(visual.TOPIC_STEP, visual.STEP_SCALARS_NAME, visual.STEP_SCALARS_SCHEMA,
                            visual.step_scalars(message), t)
        elif isinstance(message, codec.ScanEnd):
            views.cloud.scan_ended(message.scanner_id, message.scan_id)
        elif isinstance(message, codec.Reconstruction):
            w.write_message(visual.TOPIC_PLANES, views.planes.update(message, t), log_time=t, publish_time=t)

    def write_json(self, topic: str, schema_name: str, schema: dict, payload: dict, log_time_ns: int) -> None:
        """Record a JSON message on a channel with a named JSON schema (Foxglove plots its numbers)."""
        if self._finished:
            raise RecordingError(f"{self.path} is already finished")
        # The mcap.writer.Writer under mcap-protobuf-support's Writer (or the writer itself, if it is one).
        raw = getattr(self._writer, "_writer", self._writer)
        channel = self._views.json_channels.get(topic)
        if channel is None:
            schema_id = raw.register_schema(schema_name, "jsonschema", visual.json_schema_bytes(schema))
            channel = self._views.json_channels[topic] = raw.register_channel(topic, "json", schema_id)
        raw.add_message(channel, log_time=log_time_ns, data=json.dumps(payload).encode(),
                        publish_time=log_time_ns)

    def _write_pose_and_points(self, sample: codec.Sample, t: int) -> None:
        self._writer.write_message(TOPIC_TF, visual.array_transform(sample.gamma_measured, t), log_time=t,
                                   publish_time=t)
        start = self._starts.get((sample.scanner_id, sample.scan_id))
        if start is None:
            return
        pts, _capsules = visual.sample_points(start, sample)
        if len(pts):
            self._writer.write_message(TOPIC_POINTS, visual.point_cloud(pts, t), log_time=t, publish_time=t)


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
    for field in ("acquisition_time_ns", "start_time_ns", "end_time_ns", "stamp_ns"):
        if hasattr(message, field) and getattr(message, field):
            return int(getattr(message, field))
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


def iter_payloads(path: Path | str) -> Iterator[RecordedPayload]:
    """Yield the contract messages of a recording in log-time order, undecoded.

    Raises
    ------
    RecordingError
        If the file is missing or is not an MCAP file.
    """
    topics = list(TOPICS.values())
    try:
        with open(path, "rb") as f:
            reader = make_reader(f)
            for schema, channel, message in reader.iter_messages(topics=topics, log_time_order=True):
                yield RecordedPayload(message.log_time, channel.topic, schema.name if schema else "", message.data)
    except FileNotFoundError:
        raise RecordingError(f"no recording at {path}") from None
    except (McapError, ValueError, EOFError, struct.error, OSError) as exc:  # short or truncated files too
        raise RecordingError(f"{path} is not a readable MCAP file ({exc}); was it finished?") from None


def read_messages(path: Path | str, limits: codec.DecodeLimits = codec.DEFAULT_LIMITS) -> Iterator[Message]:
    """Decoded, validated contract messages in log-time order; a bad record raises DecodeError."""
    for rec in iter_payloads(path):
        cls = codec.MESSAGE_TYPES.get(rec.type_name)
        if cls is None:
            raise DecodeError(f"{rec.topic} holds {rec.type_name!r}, not a lelsonar.v1 message")
        yield codec.decode(rec.payload, cls, limits)


def read_metadata(path: Path | str) -> dict[str, dict[str, str]]:
    """All metadata records of a recording, by name."""
    with open(path, "rb") as f:
        return {m.name: dict(m.metadata) for m in make_reader(f).iter_metadata()}
