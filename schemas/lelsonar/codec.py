"""Bytes ⇄ validated messages, and numpy arrays ⇄ packed waveforms.

Every payload that enters lelsonar, from Zenoh or from a file, goes through
:func:`decode`.  It bounds the size before parsing, parses, then validates the
schema version, the identifiers, the lengths and the finiteness of numbers, and
raises a :class:`~lelsonar.errors.DecodeError` subclass that says what was wrong.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np
from google.protobuf.message import DecodeError as _ProtobufDecodeError
from google.protobuf.message import Message

from lelsonar import SCHEMA_VERSION
from lelsonar.checks import finite, finite_vector
from lelsonar.errors import (
    ConfigError,
    DecodeError,
    InvalidIdentifierError,
    InvalidMessageError,
    NonFiniteValueError,
    PayloadTooLargeError,
    SchemaVersionError,
    TruncatedDataError,
)
from lelsonar.keys import validate_identifier
from lelsonar.poses import validate_pose
from lelsonar.v1 import reconstruction_pb2, scan_pb2

ScanStart = scan_pb2.ScanStart
Sample = scan_pb2.Sample
ScanEnd = scan_pb2.ScanEnd
Reconstruction = reconstruction_pb2.Reconstruction
Waveform = scan_pb2.Waveform

#: A top-level message of the contract: each carries ``schema_version`` and ``scanner_id``.
WireMessage = ScanStart | Sample | ScanEnd | Reconstruction
#: A message of a scan, as ``acquire`` sends and records it: each carries ``scan_id`` too.
ScanMessage = ScanStart | Sample | ScanEnd
_TOP_LEVEL = (ScanStart, Sample, ScanEnd, Reconstruction)

#: The top-level messages of the contract, by their full protobuf name.
MESSAGE_TYPES: dict[str, type[WireMessage]] = {cls.DESCRIPTOR.full_name: cls for cls in _TOP_LEVEL}

M = TypeVar("M", bound=Message)

#: The verdict's short names (``--json``, the planner, labels) and their wire values.
QUALITY = {
    "": reconstruction_pb2.PLANE_QUALITY_UNSPECIFIED,
    "good": reconstruction_pb2.PLANE_QUALITY_GOOD,
    "degraded": reconstruction_pb2.PLANE_QUALITY_DEGRADED,
    "unreliable": reconstruction_pb2.PLANE_QUALITY_UNRELIABLE,
}
QUALITY_NAME: dict[int, str] = {v: (k or "unassessed") for k, v in QUALITY.items()}

_ITEM_SIZE = {
    scan_pb2.WAVEFORM_ENCODING_FLOAT32_LE: 4,
    scan_pb2.WAVEFORM_ENCODING_INT16_LE: 2,
}
#: A valid echo's distance is below this, m: far beyond any 40 kHz echo; larger is a corrupt value.
MAX_RANGE_M = 100.0
_FLOAT32 = scan_pb2.WAVEFORM_ENCODING_FLOAT32_LE


@dataclass(frozen=True)
class DecodeLimits:
    """Bounds on everything whose size comes from the wire.

    Parameters
    ----------
    max_payload_bytes : int
        Largest payload parsed at all.
    max_waveform_samples : int
        Largest waveform accepted, per capsule.
    max_sensors : int
        Most sensor readings in one sample.
    max_steps : int
        Most steps in one scan (``ScanStart.steps``, ``Sample.step``,
        ``ScanEnd.samples_sent``).  The AX-12 resolves 1024 positions over
        300°, so a scan has at most 1024 distinct angles; 4096 leaves room for
        repeated angles and keeps what one forged ScanStart can make a
        reconstructor hold bounded (the assembly also grows with the steps that
        actually arrive, never with the step count a ScanStart claims).
    max_planes : int
        Most plane estimates in one ``Reconstruction``: two planes for each of
        the method of record and every compared method (11 registered today),
        with room to grow.
    max_reasons : int
        Most quality reasons per plane, and most failures per reconstruction.
    """

    max_payload_bytes: int = 4 * 1024 * 1024
    max_waveform_samples: int = 65_536
    max_sensors: int = 16
    max_steps: int = 4096
    max_planes: int = 64
    max_reasons: int = 64

    def __post_init__(self) -> None:
        for name in (
            "max_payload_bytes",
            "max_waveform_samples",
            "max_sensors",
            "max_steps",
            "max_planes",
            "max_reasons",
        ):
            if getattr(self, name) <= 0:
                raise ConfigError(f"DecodeLimits.{name} must be positive")


DEFAULT_LIMITS = DecodeLimits()


# --- waveforms -----------------------------------------------------------------------
def pack_waveform(
    volts: np.ndarray,
    sample_rate: float,
    t0: float = 0.0,
    *,
    int16_scale: float | None = None,
) -> Waveform:
    """Pack one waveform as little-endian bytes, without per-sample Python work.

    Parameters
    ----------
    volts : (n,) array
        Samples, V.
    sample_rate : float
        Hz.
    t0 : float
        Time of the first sample after firing, s.
    int16_scale : float, optional
        V per count.  When given, samples are stored as int16 (half the bytes);
        otherwise as float32.
    """
    v = np.asarray(volts)
    if v.ndim != 1:
        raise ConfigError(f"a waveform must be one-dimensional, got shape {v.shape}")
    if int16_scale is None:
        data = v.astype("<f4", copy=False).tobytes()
        return Waveform(
            encoding=scan_pb2.WAVEFORM_ENCODING_FLOAT32_LE,
            data=data,
            sample_rate=sample_rate,
            t0=t0,
            sample_count=v.size,
        )
    counts = np.clip(np.rint(v / int16_scale), -32768, 32767).astype("<i2")
    return Waveform(
        encoding=scan_pb2.WAVEFORM_ENCODING_INT16_LE,
        data=counts.tobytes(),
        scale=int16_scale,
        sample_rate=sample_rate,
        t0=t0,
        sample_count=v.size,
    )


def unpack_waveform(
    waveform: Waveform, limits: DecodeLimits = DEFAULT_LIMITS, *, validated: bool = False
) -> np.ndarray:
    """Validated samples of a packed waveform as float32 volts, shape ``(sample_count,)``.

    ``validated=True`` skips the checks for a waveform of a message that :func:`decode` returned.
    """
    if not validated:
        _check_waveform(waveform, limits, where="waveform")
    if waveform.encoding == scan_pb2.WAVEFORM_ENCODING_FLOAT32_LE:
        return np.frombuffer(waveform.data, dtype="<f4").astype(np.float32, copy=False)
    # Scale in float64, round once to float32: at most half a count plus half a float32 ulp off.  A scale left
    # unset (0) gives counts: everything reconstruction reads of a waveform is relative (the energy ratio's
    # peak, the amplitudes' directions), so a writer that never states its volts per count loses nothing.
    return (np.frombuffer(waveform.data, dtype="<i2") * (waveform.scale or 1.0)).astype(np.float32)


def _check_waveform(w: Waveform, limits: DecodeLimits, where: str, *, samples: bool = True) -> None:
    """Check one waveform; ``samples=False`` leaves the finiteness of float32 samples to the caller
    (:func:`_validate_sample` checks a sample's waveforms in one pass)."""
    if w.sample_count > limits.max_waveform_samples:
        raise PayloadTooLargeError(
            f"{where} declares {w.sample_count} samples; the limit is {limits.max_waveform_samples}"
        )
    size = _ITEM_SIZE.get(w.encoding)
    if size is None:
        raise InvalidMessageError(f"{where} has unknown encoding {w.encoding}")
    if len(w.data) != w.sample_count * size:
        raise TruncatedDataError(
            f"{where} declares {w.sample_count} samples ({w.sample_count * size} bytes) but carries {len(w.data)} bytes"
        )
    finite(where + ".sample_rate", w.sample_rate)
    finite(where + ".t0", w.t0)
    if w.sample_rate <= 0:
        raise InvalidMessageError(f"{where}.sample_rate must be positive, got {w.sample_rate}")
    if w.encoding == scan_pb2.WAVEFORM_ENCODING_INT16_LE:
        finite(where + ".scale", w.scale)
        if w.scale < 0:
            raise InvalidMessageError(
                f"{where}.scale must be positive for int16 data (or 0: unset, counts), got {w.scale}"
            )
    elif samples and not np.isfinite(np.frombuffer(w.data, dtype="<f4")).all():
        raise NonFiniteValueError(f"{where} holds NaN or infinite samples")


# --- messages ------------------------------------------------------------------------
def encoding_name(message: Message) -> str:
    """The Zenoh encoding string that names this message's type."""
    return f"application/protobuf;{message.DESCRIPTOR.full_name}"


def type_from_encoding(encoding: str) -> type[Message]:
    """The message class named by a Zenoh encoding string, or a DecodeError."""
    media, _, schema = str(encoding).partition(";")
    if media != "application/protobuf" or schema not in MESSAGE_TYPES:
        raise InvalidMessageError(
            f"unexpected encoding {str(encoding)[:80]!r}; expected one of "
            + ", ".join(f"application/protobuf;{n}" for n in MESSAGE_TYPES)
        )
    return MESSAGE_TYPES[schema]


def decode(payload: bytes, message_type: type[M], limits: DecodeLimits = DEFAULT_LIMITS) -> M:
    """Parse and validate one top-level message.

    Raises
    ------
    DecodeError
        A subclass that says what was wrong: too large, unparseable, wrong
        schema version, bad identifier, truncated or non-finite data.
    """
    message = _parse(payload, message_type, limits)
    validate(message, limits)
    return message


def parse(payload: bytes, message_type: type[M], limits: DecodeLimits = DEFAULT_LIMITS) -> M:
    """The first half of :func:`decode`: parse one top-level message and check its header (schema version,
    scanner id), what routing it needs.  Its body is unchecked: :func:`validate_body` (or the same checks,
    naming the culprit by it when they fail) must pass it before it is used or refused for another reason.

    Raises
    ------
    DecodeError
        A subclass: too large, unparseable, wrong schema version, bad identifier.
    """
    message = _parse(payload, message_type, limits)
    _validate_header(message)
    return message


def validate_body(message: Message, limits: DecodeLimits = DEFAULT_LIMITS) -> None:
    """The second half of :func:`decode`: every check of a parsed message but its header's."""
    _VALIDATORS[type(_top_level(message))](message, limits)


def check_samplesfinite(m: Sample) -> None:
    """The check of every float32 sample of a ``Sample`` for NaN and infinity (part of :func:`validate`).

    Raises
    ------
    NonFiniteValueError
        Naming the first waveform that holds one.
    """
    for i, s in enumerate(m.sensors):
        if s.waveform.encoding == _FLOAT32 and not np.isfinite(np.frombuffer(s.waveform.data, dtype="<f4")).all():
            raise NonFiniteValueError(f"Sample.sensors[{i}].waveform holds NaN or infinite samples")


def sample_readings(sensors) -> tuple[list, list, list]:
    """What a ``Sample``'s ``sensors`` (in the order given) hold, read out of the message once, as three flat
    lists in the order of the sensors: the ranges, 3 numbers a sensor (``echo_valid, distance,
    time_of_flight``); the layout, 6 a sensor (``capsule_id``, and its waveform's ``sample_count,
    sample_rate, t0, encoding`` and the length of its ``data``); and each waveform's ``data``."""
    ranges: list = []
    layout: list = []
    data: list = []
    for s in sensors:
        w = s.waveform
        samples = w.data
        data.append(samples)
        ranges += (s.echo_valid, s.distance, s.time_of_flight)
        layout += (s.capsule_id, w.sample_count, w.sample_rate, w.t0, w.encoding, len(samples))
    return ranges, layout, data


def _parse(payload: bytes, message_type: type[M], limits: DecodeLimits) -> M:
    if len(payload) > limits.max_payload_bytes:
        raise PayloadTooLargeError(f"payload of {len(payload)} bytes exceeds the limit of {limits.max_payload_bytes}")
    message = message_type()
    try:
        message.ParseFromString(bytes(payload))
    except _ProtobufDecodeError as exc:
        raise DecodeError(f"not a valid {message_type.DESCRIPTOR.full_name}: {exc}") from None
    return message


def validate(message: Message, limits: DecodeLimits = DEFAULT_LIMITS) -> None:
    """Check a message of the contract; raise a DecodeError subclass if it is invalid."""
    _validate_header(message)
    _VALIDATORS[type(message)](message, limits)


def _top_level(message: Message) -> WireMessage | scan_pb2.Odometry:
    """``message`` if it carries the contract's header (``schema_version``, ``scanner_id``)."""
    if not isinstance(message, (*_TOP_LEVEL, scan_pb2.Odometry)):
        raise InvalidMessageError(
            f"{message.DESCRIPTOR.full_name} is not a top-level message of the contract; "
            f"pass one of {', '.join(MESSAGE_TYPES)}"
        )
    return message


def _validate_header(any_message: Message) -> None:
    message = _top_level(any_message)
    name = message.DESCRIPTOR.full_name
    if message.schema_version != SCHEMA_VERSION:
        fix = (
            f"the writer left it unset: set schema_version = {SCHEMA_VERSION}"
            if message.schema_version == 0
            else "upgrade the older side"
        )
        raise SchemaVersionError(
            f"{name} has schema version {message.schema_version}; this build speaks {SCHEMA_VERSION} ({fix})"
        )
    try:
        validate_identifier(message.scanner_id)
    except InvalidIdentifierError as exc:
        raise InvalidMessageError(f"{name}: {exc}") from None


def _validate_scan_start(m: ScanStart, limits: DecodeLimits) -> None:
    if not 1 <= len(m.capsules) <= limits.max_sensors:
        raise InvalidMessageError(f"ScanStart lists {len(m.capsules)} capsules; expected 1 to {limits.max_sensors}")
    for i, c in enumerate(m.capsules):
        finite_vector(f"ScanStart.capsules[{i}].position", c.position)
        finite_vector(f"ScanStart.capsules[{i}].boresight", c.boresight)
    finite_vector("ScanStart.rotation_axis", m.rotation_axis)
    finite(
        "ScanStart schedule and acoustics",
        m.radial_offset,
        m.gamma_start,
        m.gamma_stop,
        m.sound_speed,
        m.air_temperature,
        m.sample_rate,
    )
    if not 1 <= m.steps <= limits.max_steps:
        raise InvalidMessageError(f"ScanStart.steps is {m.steps}; expected 1 to {limits.max_steps}")
    if m.window_samples > limits.max_waveform_samples:
        raise PayloadTooLargeError(
            f"ScanStart.window_samples is {m.window_samples}; the limit is {limits.max_waveform_samples}"
        )
    # 0 is proto3's "unset": the reconstruction then takes c from air_temperature, or needs no conversion
    # (every echo carries its distance); the waveforms carry their own sample rate.
    if m.sound_speed != 0.0 and not 200.0 < m.sound_speed < 500.0:
        raise InvalidMessageError(f"ScanStart.sound_speed {m.sound_speed} m/s is not a speed of sound in air")
    if m.sample_rate < 0:
        raise InvalidMessageError("ScanStart.sample_rate must be positive (or 0: unset)")
    ids = [c.capsule_id for c in m.capsules]
    if len(set(ids)) != len(ids):
        raise InvalidMessageError(f"ScanStart lists capsule ids {ids}; each capsule needs its own id")
    e = m.energy_model
    finite("ScanStart.energy_model", e.phi0, e.phi1, e.phi2, e.valid_min_range, e.valid_max_range)
    if m.HasField("pose"):
        validate_pose("ScanStart.pose", m.pose)


Odometry = scan_pb2.Odometry


def _validate_odometry(m: Odometry, limits: DecodeLimits) -> None:
    if not m.HasField("pose"):
        raise InvalidMessageError("Odometry carries no pose; set pose (frame_id, position, orientation)")
    validate_pose("Odometry.pose", m.pose)


def _validate_sample(m: Sample, limits: DecodeLimits) -> None:
    # Every check of the contract, in two tiers: a screen of a few comparisons per sensor that a valid float32
    # sample passes (one sum is finite only if each term is; each comparison is one of the exact checks), and,
    # for anything the screen does not pass (int16 data, a malformed field, an overflowing sum), the exact
    # checks field by field, which name the culprit.  The screen never accepts what the exact checks refuse.
    sensors = m.sensors
    if not 1 <= len(sensors) <= limits.max_sensors:
        raise InvalidMessageError(f"Sample carries {len(sensors)} sensor readings; expected 1 to {limits.max_sensors}")
    if m.step >= limits.max_steps:
        raise InvalidMessageError(f"Sample.step {m.step} exceeds the limit of {limits.max_steps}")
    motor = m.motor
    if not math.isfinite(m.gamma_commanded + m.gamma_measured + motor.load + motor.voltage + motor.temperature):
        finite("Sample.gamma_commanded/gamma_measured", m.gamma_commanded, m.gamma_measured)
        finite("Sample.motor", motor.load, motor.voltage, motor.temperature)
    float32 = []
    max_samples = limits.max_waveform_samples
    for i, s in enumerate(sensors):
        w = s.waveform
        data, count, rate, t0, tof, distance, valid = (
            w.data,
            w.sample_count,
            w.sample_rate,
            w.t0,
            s.time_of_flight,
            s.distance,
            s.echo_valid,
        )
        if not (
            w.encoding == _FLOAT32
            and count <= max_samples
            and len(data) == 4 * count
            and rate > 0.0
            and math.isfinite(rate + t0)
            and (math.isfinite(tof + distance) and 0.0 < distance < MAX_RANGE_M and tof > 0.0 if valid else True)
        ):
            _check_sensor(i, s, limits)  # raises, or the sensor is valid (e.g. int16 data)
        if w.encoding == _FLOAT32:
            float32.append(data)
    # Every float32 sample of the message in one pass; the culprit is looked for only on failure.
    if float32:
        check_joinedfinite(m, b"".join(float32))


def check_joinedfinite(m: Sample, joined: bytes) -> None:
    """:func:`check_samples_finite` of a ``Sample`` whose float32 samples are ``joined``: in one pass, the
    culprit looked for only on failure."""
    if not np.isfinite(np.frombuffer(joined, dtype="<f4")).all():
        check_samplesfinite(m)


def _check_sensor(i: int, s, limits: DecodeLimits) -> None:
    """The exact checks of one sensor reading (all but the finiteness of float32 samples).

    A reading without an echo (``echo_valid`` false) carries no range: whatever its time of flight and
    distance hold (0 as the contract says, NaN or −1 as other writers mark "no echo") is never read, so it is
    not checked.  A valid echo needs its range: the distance, or the time of flight (the reconstruction
    converts one into the other with the scan's speed of sound); an unset field (0) is the other's to fill.
    """
    if s.echo_valid:
        finite(f"Sample.sensors[{i}].time_of_flight/distance", s.time_of_flight, s.distance)
        d, t = s.distance, s.time_of_flight
        if not (0.0 <= d < MAX_RANGE_M and t >= 0.0 and (d > 0.0 or t > 0.0)):
            raise InvalidMessageError(
                f"Sample.sensors[{i}] is marked valid but has distance {d} m and time of flight {t} s "
                "(a valid echo needs a positive distance or time of flight; mark a reading without an echo "
                "echo_valid = false)"
            )
    _check_waveform(s.waveform, limits, where=f"Sample.sensors[{i}].waveform", samples=False)


def _validate_scan_end(m: ScanEnd, limits: DecodeLimits) -> None:
    if m.status not in (scan_pb2.SCAN_STATUS_COMPLETE, scan_pb2.SCAN_STATUS_ABORTED):
        raise InvalidMessageError(f"ScanEnd.status {m.status} is neither COMPLETE nor ABORTED")
    if m.samples_sent > limits.max_steps or m.steps_planned > limits.max_steps:
        raise InvalidMessageError(
            f"ScanEnd counts {m.samples_sent} samples sent of {m.steps_planned} planned; "
            f"the limit is {limits.max_steps} steps"
        )


def _validate_reconstruction(m: Reconstruction, limits: DecodeLimits) -> None:
    finite("Reconstruction.critical_angle", m.critical_angle)
    if len(m.planes) > limits.max_planes:
        raise InvalidMessageError(f"Reconstruction carries {len(m.planes)} planes; at most {limits.max_planes}")
    if len(m.failures) > limits.max_reasons:
        raise InvalidMessageError(f"Reconstruction carries {len(m.failures)} failures; at most {limits.max_reasons}")
    for i, p in enumerate(m.planes):
        where = f"Reconstruction.planes[{i}]"
        finite_vector(f"{where}.normal", p.normal)
        finite(f"{where}.offset/sigma/lel_cost", p.offset, p.sigma, p.sigma_relative, p.lel_cost)
        if abs(math.hypot(p.normal.x, p.normal.y, p.normal.z) - 1.0) > 1e-6:
            raise InvalidMessageError(f"{where}.normal is not a unit vector")
        if len(p.theta_covariance) not in (0, 9):
            raise InvalidMessageError(f"{where}.theta_covariance must hold 0 or 9 numbers")
        if len(p.quality_reasons) > limits.max_reasons:
            raise InvalidMessageError(
                f"{where} carries {len(p.quality_reasons)} quality reasons; at most {limits.max_reasons}"
            )
    _validate_surfaces(m, limits)


def _validate_surfaces(m: Reconstruction, limits: DecodeLimits) -> None:
    """The sweep's surfaces, corners and edges: bounded, finite, unit normals and directions, 3×3 covariances."""
    for name, items in (("surfaces", m.surfaces), ("corners", m.corners), ("edges", m.edges)):
        if len(items) > limits.max_planes:
            raise InvalidMessageError(f"Reconstruction carries {len(items)} {name}; at most {limits.max_planes}")
    if len(m.unexplained) > limits.max_reasons:
        raise InvalidMessageError(
            f"Reconstruction carries {len(m.unexplained)} unexplained causes; at most {limits.max_reasons}"
        )
    for i, s in enumerate(m.surfaces):
        where = f"Reconstruction.surfaces[{i}]"
        p = s.plane
        finite_vector(f"{where}.plane.normal", p.normal)
        finite(f"{where}.plane.offset/sigma", p.offset, p.sigma, p.offset_stderr, p.normal_stderr)
        if abs(math.hypot(p.normal.x, p.normal.y, p.normal.z) - 1.0) > 1e-6:
            raise InvalidMessageError(f"{where}.plane.normal is not a unit vector")
        finite(f"{where}.bearing/tilt", s.bearing, s.tilt)
        if len(s.covariance) != 9 or not all(math.isfinite(v) for v in s.covariance):
            raise InvalidMessageError(f"{where}.covariance must hold 9 finite numbers (bearing, tilt, offset)")
        if len(p.quality_reasons) > limits.max_reasons:
            raise InvalidMessageError(f"{where} carries {len(p.quality_reasons)} reasons; at most {limits.max_reasons}")
    for name, items in (("corners", m.corners), ("edges", m.edges)):
        for i, f in enumerate(items):
            where = f"Reconstruction.{name}[{i}]"
            finite_vector(f"{where}.line.point", f.line.point)
            finite_vector(f"{where}.line.direction", f.line.direction)
            d = f.line.direction
            if abs(math.hypot(d.x, d.y, d.z) - 1.0) > 1e-6:
                raise InvalidMessageError(f"{where}.line.direction is not a unit vector")
            if len(f.covariance) != 9 or not all(math.isfinite(v) for v in f.covariance):
                raise InvalidMessageError(f"{where}.covariance must hold 9 finite numbers (m²)")
            if len(f.reasons) > limits.max_reasons or len(f.surfaces) > limits.max_planes:
                raise InvalidMessageError(f"{where} carries too many reasons or surfaces")


#: Each validator takes the message type it is keyed by.
_VALIDATORS: dict[type[Message], Callable[[Any, DecodeLimits], None]] = {
    ScanStart: _validate_scan_start,
    Sample: _validate_sample,
    ScanEnd: _validate_scan_end,
    Reconstruction: _validate_reconstruction,
    Odometry: _validate_odometry,
}
