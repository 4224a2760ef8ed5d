"""What a lelsonar recording holds (``lelsonar info``): scans, steps, channels, damage, estimates.

Works on finished, unfinished and damaged files alike: it summarises what the
tolerant reader (:mod:`lelsonar.log.reader`) salvaged and says what was
lost.  Everything is plain data (:meth:`FileSummary.as_dict` is the ``--json``
form); the text tables live in :mod:`lelsonar.cli.recordings`.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path

from google.protobuf.descriptor import EnumDescriptor
from google.protobuf.message import DecodeError as ProtobufDecodeError

from lelsonar import codec, poses
from lelsonar.errors import DecodeError
from lelsonar.geometry import beam_heading
from lelsonar.log.reader import Damage
from lelsonar.log.recording import (
    CHANNEL_METADATA,
    Recording,
    describe_damage,
    is_contract_channel,
    open_recording,
)
from lelsonar.v1 import reconstruction_pb2, scan_pb2

_SCAN_STATUS = scan_pb2.DESCRIPTOR.enum_types_by_name["ScanStatus"]
_EST_STATUS = reconstruction_pb2.DESCRIPTOR.enum_types_by_name["EstimateStatus"]
_QUALITY = reconstruction_pb2.DESCRIPTOR.enum_types_by_name["PlaneQuality"]


def _enum_name(enum: EnumDescriptor, value: int, prefix: str) -> str:
    v = enum.values_by_number.get(value)
    return v.name.removeprefix(prefix).lower() if v else str(value)


def step_ranges(steps: list[int]) -> str:
    """Sorted step numbers as compact ranges, e.g. ``[3, 4, 5, 9]`` → ``"3-5, 9"``.

    Parameters
    ----------
    steps : list of int
        Sorted, distinct.

    Returns
    -------
    str
        Empty for no steps.
    """
    out: list[str] = []
    i = 0
    while i < len(steps):
        j = i
        while j + 1 < len(steps) and steps[j + 1] == steps[j] + 1:
            j += 1
        out.append(str(steps[i]) if i == j else f"{steps[i]}-{steps[j]}")
        i = j + 1
    return ", ".join(out)


@dataclass
class ScanSummary:
    """One scan of one scanner as recorded."""

    scanner_id: str
    scan_id: int
    device: str = ""
    steps_planned: int | None = None  # from ScanStart (or ScanEnd when the start was lost)
    steps_received: int = 0  # distinct steps with a Sample in the file
    missing_steps: list[int] = field(default_factory=list)
    duplicates: int = 0
    status: str = "no ScanEnd"  # complete, aborted, or "no ScanEnd" (unfinished or lost)
    reason: str = ""
    samples_sent: int | None = None  # ScanEnd.samples_sent: what the acquirer says it published
    start_ns: int | None = None
    end_ns: int | None = None
    has_start: bool = False
    # Where the array frame was (ScanStart.pose): frame_id, x, y, z (m), heading (rad, of the γ = 0 beam),
    # orientation (x, y, z, w), covariance (36, row-major, or None), known, note.
    pose: dict | None = None
    #: What of the scan could not be read, e.g. its ScanStart in a damaged chunk (empty: nothing).
    unreadable: list[str] = field(default_factory=list)

    @property
    def duration_s(self) -> float | None:
        if self.start_ns is None or self.end_ns is None:
            return None
        return (self.end_ns - self.start_ns) / 1e9


@dataclass
class EstimateSummary:
    """The last recorded estimate of a scan (final ones win over provisional)."""

    scanner_id: str
    scan_id: int
    status: str
    samples_used: int
    critical_step: int | None
    planes: list[dict]
    missing_steps: list[int]


@dataclass
class ChannelSummary:
    topic: str
    schema: str
    encoding: str
    messages: int
    lost: int | None  # known when the statistics or a message index survived


@dataclass
class FileSummary:
    """Everything ``lelsonar info`` prints about one file."""

    path: str
    size: int
    finished: bool
    intact: bool
    damage_text: str | None
    damage: list[dict]
    messages: int
    messages_lost: int
    messages_lost_exact: bool
    start_ns: int | None
    end_ns: int | None
    device: str
    scanners: list[str]
    channels: list[ChannelSummary]
    scans: list[ScanSummary]
    estimates: list[EstimateSummary]
    undecodable: int
    metadata: dict[str, dict[str, str]]

    @property
    def duration_s(self) -> float | None:
        if self.start_ns is None or self.end_ns is None:
            return None
        return (self.end_ns - self.start_ns) / 1e9

    def as_dict(self) -> dict:
        """JSON-ready: SI units, times in Unix ns, durations in s."""
        d = asdict(self)
        d["duration_s"] = self.duration_s
        for scan, obj in zip(d["scans"], self.scans, strict=True):
            scan["duration_s"] = obj.duration_s
        return d


def summarize(path: Path | str | Recording) -> FileSummary:
    """Summarise one recording, damaged or not.

    Parameters
    ----------
    path : Path, str or Recording

    Returns
    -------
    FileSummary

    Raises
    ------
    RecordingError
        Missing path, a directory or not an MCAP file (typed subclasses).
    """
    rec = open_recording(path)
    s = rec.salvage
    scans: dict[tuple[str, int], ScanSummary] = {}
    steps: dict[tuple[str, int], list[int]] = {}
    estimates: dict[tuple[str, int], codec.Reconstruction] = {}
    undecodable = 0

    def scan(scanner_id: str, scan_id: int) -> ScanSummary:
        return scans.setdefault((scanner_id, scan_id), ScanSummary(scanner_id, scan_id))

    # Every chunk is read and checked (the damage is complete); only the contract's messages are kept, one chunk
    # at a time.
    for m in rec.messages(is_contract_channel, verify_all=True):
        cls = codec.MESSAGE_TYPES[s.schema_name(m.channel_id)]
        try:
            msg = cls.FromString(m.data)
        except ProtobufDecodeError:
            undecodable += 1
            continue
        if isinstance(msg, codec.ScanStart):
            sc = scan(msg.scanner_id, msg.scan_id)
            sc.has_start, sc.device, sc.steps_planned = True, msg.device, msg.steps
            sc.start_ns = msg.start_time_ns
            sc.pose = _pose_dict(msg)
        elif isinstance(msg, codec.Sample):
            sc = scan(msg.scanner_id, msg.scan_id)
            steps.setdefault((msg.scanner_id, msg.scan_id), []).append(msg.step)
            sc.start_ns = min(sc.start_ns, msg.acquisition_time_ns) if sc.start_ns else msg.acquisition_time_ns
            sc.end_ns = max(sc.end_ns or 0, msg.acquisition_time_ns)
        elif isinstance(msg, codec.ScanEnd):
            sc = scan(msg.scanner_id, msg.scan_id)
            sc.status = _enum_name(_SCAN_STATUS, msg.status, "SCAN_STATUS_")
            sc.reason, sc.samples_sent, sc.end_ns = msg.reason, msg.samples_sent, msg.end_time_ns
            if sc.steps_planned is None:
                sc.steps_planned = msg.steps_planned
        elif isinstance(msg, codec.Reconstruction):
            key = (msg.scanner_id, msg.scan_id)
            old = estimates.get(key)
            final = msg.status != _EST_STATUS.values_by_name["ESTIMATE_STATUS_PROVISIONAL"].number
            if old is None or final or old.status == _EST_STATUS.values_by_name["ESTIMATE_STATUS_PROVISIONAL"].number:
                estimates[key] = msg
    for key, got in steps.items():
        sc = scans[key]
        distinct = sorted(set(got))
        sc.steps_received, sc.duplicates = len(distinct), len(got) - len(distinct)
        planned = sc.steps_planned if sc.steps_planned is not None else (max(distinct) + 1 if distinct else 0)
        have = set(distinct)
        sc.missing_steps = [i for i in range(planned) if i not in have]
    for key, sc in scans.items():
        if key not in steps and sc.steps_planned:
            sc.missing_steps = list(range(sc.steps_planned))
    restored = rec.start_copies()
    for key, sc in scans.items():
        if sc.has_start:
            continue
        copy = restored.get(key)
        if copy is None:
            sc.unreadable.append(
                "ScanStart unreadable and no copy of it: the scan cannot be reconstructed (no geometry, no schedule)"
            )
            continue
        sc.unreadable.append("ScanStart unreadable; restored from the recording's metadata copy")
        try:
            start = codec.ScanStart.FromString(copy.payload)
        except ProtobufDecodeError:
            continue
        sc.device, sc.steps_planned = start.device, start.steps
        sc.start_ns = start.start_time_ns

    lost_by = s.lost_by_channel()
    exact_channels = s.statistics_counts is not None or all(d.messages is not None for d in s.damage)
    counts = s.count_by_channel()
    channels = []
    for cid, ch in sorted(s.channels.items()):
        schema = s.schemas.get(ch.schema_id)
        channels.append(
            ChannelSummary(
                ch.topic,
                schema.name if schema else "",
                ch.message_encoding,
                counts.get(cid, 0),
                lost_by.get(cid, 0) if exact_channels else None,
            )
        )
    lost, exact = s.messages_lost()
    devices = sorted({sc.device for sc in scans.values() if sc.device})
    device = ", ".join(devices) or s.metadata.get("lelsonar.config", {}).get("device", "")
    return FileSummary(
        path=str(s.path),
        size=s.size,
        finished=s.finished,
        intact=s.intact,
        damage_text=None if s.intact else describe_damage(s),
        damage=[_damage_dict(d, s) for d in s.damage],
        messages=sum(s.counts.values()),
        messages_lost=lost,
        messages_lost_exact=exact,
        start_ns=s.first_time,
        end_ns=s.last_time,
        device=device,
        scanners=sorted({k[0] for k in scans} | {k[0] for k in estimates}),
        channels=channels,
        scans=[scans[k] for k in sorted(scans)],
        estimates=[_estimate(estimates[k]) for k in sorted(estimates)],
        undecodable=undecodable,
        metadata={k: v for k, v in s.metadata.items() if not k.startswith(CHANNEL_METADATA)},
    )


def _damage_dict(d: Damage, s) -> dict:
    return {
        "offset": d.offset,
        "length": d.length,
        "kind": d.kind,
        "reason": d.reason,
        "messages_lost": d.messages_lost,
        "exact": d.messages is not None,
        "by_topic": {s.topic(cid): n for cid, n in d.by_channel.items()},
    }


def _estimate(msg: codec.Reconstruction) -> EstimateSummary:
    planes = [
        {
            "label": p.label,
            "method": p.method,
            "normal": [p.normal.x, p.normal.y, p.normal.z],
            "offset": p.offset,
            "sigma": p.sigma,
            "inliers": p.inlier_count,
            "points": p.point_count,
            "quality": _enum_name(_QUALITY, p.quality, "PLANE_QUALITY_"),
        }
        for p in sorted(msg.planes, key=lambda p: (p.label, p.method))
    ]
    return EstimateSummary(
        msg.scanner_id,
        msg.scan_id,
        _enum_name(_EST_STATUS, msg.status, "ESTIMATE_STATUS_"),
        msg.samples_used,
        msg.critical_step if msg.HasField("critical_step") else None,
        planes,
        list(msg.missing_steps),
    )


def _pose_dict(start: codec.ScanStart) -> dict:
    """The scan's pose for ``info`` (the origin, with a note, for a scan without one; a note for an invalid one)."""
    note = ""
    if start.HasField("pose"):
        try:
            poses.validate_pose("ScanStart.pose", start.pose)
        except DecodeError as exc:
            note = f"invalid pose, taken as the origin: {exc}"
            start = codec.ScanStart()
    pose = poses.scan_pose(start)
    return {
        "frame_id": pose.frame_id,
        "x": float(pose.position[0]),
        "y": float(pose.position[1]),
        "z": float(pose.position[2]),
        "heading": beam_heading(pose.orientation),
        "orientation": list(pose.orientation),
        "covariance": None if pose.covariance is None else [float(v) for v in pose.covariance.reshape(-1)],
        "known": pose.known and not note,
        "note": note or pose.note,
    }
