"""Framing codec of the sensor-board protocol (``schemas/SENSOR_BOARD.md``).

Pure functions and a streaming parser; no I/O.  All integers are little-endian::

    A5 5A | VER u8 | TYPE u8 | SEQ u16 | LEN u32 | HCRC u16 | PAYLOAD[LEN] | CRC32 u32

* HCRC is CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF; ``binascii.crc_hqx``)
  over VER..LEN (8 bytes).  It lets the parser trust LEN before waiting for the
  payload, and reject a false sync inside waveform data at once.
* CRC32 is the IEEE/zlib CRC-32 (``binascii.crc32``) over VER..PAYLOAD, HCRC
  included.

Payloads: FIRE (host → board), ACQ and ERR (board → host); see the dataclasses.
Waveform samples are unsigned ``bits``-wide ADC codes, offset binary (mid-scale
``2**(bits-1)`` is 0 V); :class:`WaveScale` turns them into volts.
"""

from __future__ import annotations

import binascii
import enum
import struct
from dataclasses import dataclass

import numpy as np

from lelsonar.errors import (
    DecodeError,
    InvalidMessageError,
    PayloadTooLargeError,
    SchemaVersionError,
    TruncatedDataError,
)

SYNC = b"\xa5\x5a"
VERSION = 1
N_CHANNELS = 4
#: TOF value meaning "no echo over the threshold".
NO_ECHO = 0xFFFFFFFF

_HEADER = struct.Struct("<2sBBHIH")  # sync, ver, type, seq, len, hcrc
HEADER_SIZE = _HEADER.size  # 12
TRAILER_SIZE = 4
_FIRE = struct.Struct("<HBBHI")  # step, mask, flags, n_samples, fs_hz
_ACQ = struct.Struct("<HBBIHHI4I")  # step, n_ch, bits, fs_hz, n_samples, status, t_fire_us, tof_ns[4]
_ERR = struct.Struct("<H")  # code, then UTF-8 text
ACQ_HEADER_SIZE = _ACQ.size  # 32
#: Longest ERR text, bytes.
ERR_TEXT_MAX = 240


class FrameType(enum.IntEnum):
    FIRE = 0x01
    ACQ = 0x81
    ERR = 0x82


class FireFlag(enum.IntFlag):
    """FIRE flags."""

    #: Send waveforms (otherwise ACQ carries TOFs only and n_samples = 0).
    WAVEFORMS = 1 << 0
    #: Resend the last acquisition of this step if the board still has it, instead of firing again.
    RESEND = 1 << 1


class AcqStatus(enum.IntFlag):
    """ACQ status bits."""

    #: At least one sample sits at an ADC rail.
    CLIPPED = 1 << 0
    #: The TOF timer overflowed on at least one channel.
    TOF_OVERFLOW = 1 << 1
    #: This is a resend of an earlier acquisition (FIRE with RESEND).
    RESENT = 1 << 2


class ErrCode(enum.IntEnum):
    """ERR codes."""

    #: The board received a FIRE whose CRC32 failed: send it again.
    BAD_CRC = 1
    #: A FIRE field is out of range (n_samples, fs_hz, mask).
    BAD_PARAM = 2
    #: Unknown frame TYPE.
    UNKNOWN_TYPE = 3
    #: Unsupported VER.
    BAD_VERSION = 4
    #: The board failed internally (e.g. its acquisition source raised).
    INTERNAL = 5


# --- errors ----------------------------------------------------------------------
class FrameTooLargeError(PayloadTooLargeError):
    """A header declares a payload longer than the configured maximum."""


class FrameCrcError(DecodeError):
    """A frame's payload CRC32 failed; the header (type, seq) was intact.

    Attributes
    ----------
    frame_type : int
    seq : int
    """

    def __init__(self, frame_type: int, seq: int, message: str) -> None:
        self.frame_type = frame_type
        self.seq = seq
        super().__init__(message)


class FrameVersionError(SchemaVersionError):
    """A header with a valid HCRC carries a protocol version this build does not speak."""


# --- payloads ----------------------------------------------------------------------
@dataclass(frozen=True)
class Frame:
    """One framed message as parsed: type, sequence number and raw payload."""

    type: int
    seq: int
    payload: bytes


@dataclass(frozen=True)
class FireRequest:
    """FIRE: fire the capsules in ``mask`` and record ``n_samples`` at ``fs_hz``."""

    step: int
    mask: int = 0x0F
    flags: int = FireFlag.WAVEFORMS
    n_samples: int = 0
    fs_hz: int = 0

    def __post_init__(self) -> None:
        if not (0 <= self.step <= 0xFFFF and 0 <= self.mask <= 0x0F and 0 <= self.flags <= 0xFF):
            raise InvalidMessageError(f"FIRE: step/mask/flags out of range: {self}")
        if not (0 <= self.n_samples <= 0xFFFF and 0 <= self.fs_hz <= 0xFFFFFFFF):
            raise InvalidMessageError(f"FIRE: n_samples/fs_hz out of range: {self}")


@dataclass(frozen=True, eq=False)
class AcqFrame:
    """ACQ: one shot of all channels.

    Attributes
    ----------
    step, n_ch, bits, fs_hz, n_samples, status, t_fire_us : int
    tof_ns : numpy.ndarray
        ``uint32 (4,)``; ``NO_ECHO`` (0xFFFFFFFF) for no echo.
    waves : numpy.ndarray
        ``uint16 (4, n_samples)`` ADC codes, offset binary.
    """

    step: int
    bits: int
    fs_hz: int
    status: int
    t_fire_us: int
    tof_ns: np.ndarray
    waves: np.ndarray

    @property
    def n_ch(self) -> int:
        return int(self.waves.shape[0])

    @property
    def n_samples(self) -> int:
        return int(self.waves.shape[1])


@dataclass(frozen=True)
class ErrReport:
    """ERR: the board refused or failed a request (``seq`` of the frame is the request's)."""

    code: int
    text: str = ""


@dataclass(frozen=True)
class WaveScale:
    """ADC code → volts: ``v = (code − 2**(bits−1)) · full_scale_v / 2**(bits−1)``.

    Parameters
    ----------
    full_scale_v : float
        Voltage at the positive rail relative to mid-scale (e.g. 1.65 V for a 3.3 V
        ADC biased at mid-rail).
    """

    full_scale_v: float = 1.65

    def __post_init__(self) -> None:
        if not (np.isfinite(self.full_scale_v) and self.full_scale_v > 0):
            raise InvalidMessageError(f"WaveScale: full_scale_v must be positive, not {self.full_scale_v}")

    def to_volts(self, codes: np.ndarray, bits: int) -> np.ndarray:
        """float32 volts of offset-binary codes."""
        half = float(1 << (bits - 1))
        return ((codes.astype(np.float32) - np.float32(half)) * np.float32(self.full_scale_v / half)).astype(
            np.float32, copy=False
        )

    def to_codes(self, volts: np.ndarray, bits: int) -> np.ndarray:
        """uint16 codes of volts, rounded and clipped to the rails."""
        half = float(1 << (bits - 1))
        codes = np.rint(np.asarray(volts, dtype=np.float64) * (half / self.full_scale_v) + half)
        return np.clip(codes, 0, (1 << bits) - 1).astype(np.uint16)


def acq_payload_size(n_samples: int, n_ch: int = N_CHANNELS) -> int:
    """Payload bytes of an ACQ with ``n_samples`` per channel."""
    return ACQ_HEADER_SIZE + 2 * n_ch * n_samples


#: Payload bytes of a FIRE.
FIRE_PAYLOAD_SIZE = _FIRE.size


def frame_size(payload_size: int) -> int:
    """Bytes on the wire of a frame with ``payload_size`` payload bytes: header + payload + CRC32."""
    return HEADER_SIZE + payload_size + TRAILER_SIZE


# --- encoding --------------------------------------------------------------------
def encode_frame(frame_type: int, seq: int, payload: bytes, version: int = VERSION) -> bytes:
    """Frame a payload: header with HCRC, payload, CRC32."""
    head = struct.pack("<BBHI", version, frame_type, seq & 0xFFFF, len(payload))
    hcrc = binascii.crc_hqx(head, 0xFFFF)
    body = head + struct.pack("<H", hcrc) + payload
    return SYNC + body + struct.pack("<I", binascii.crc32(body))


def encode_fire(seq: int, request: FireRequest) -> bytes:
    payload = _FIRE.pack(request.step, request.mask, request.flags, request.n_samples, request.fs_hz)
    return encode_frame(FrameType.FIRE, seq, payload)


def encode_acq(seq: int, acq: AcqFrame) -> bytes:
    waves = np.ascontiguousarray(acq.waves, dtype="<u2")
    tof = np.asarray(acq.tof_ns, dtype=np.uint32)
    if waves.ndim != 2 or waves.shape[0] != N_CHANNELS or tof.shape != (N_CHANNELS,):
        raise InvalidMessageError(f"ACQ: need waves (4, n) and tof (4,), got {waves.shape} and {tof.shape}")
    head = _ACQ.pack(
        acq.step,
        waves.shape[0],
        acq.bits,
        acq.fs_hz,
        waves.shape[1],
        acq.status,
        acq.t_fire_us & 0xFFFFFFFF,
        *tof.tolist(),
    )
    return encode_frame(FrameType.ACQ, seq, head + waves.tobytes())


def encode_err(seq: int, report: ErrReport) -> bytes:
    text = report.text.encode("utf-8")[:ERR_TEXT_MAX]
    return encode_frame(FrameType.ERR, seq, _ERR.pack(report.code) + text)


# --- decoding payloads ----------------------------------------------------------------
def decode_fire(payload: bytes) -> FireRequest:
    if len(payload) != _FIRE.size:
        raise TruncatedDataError(f"FIRE payload is {len(payload)} bytes, expected {_FIRE.size}")
    step, mask, flags, n_samples, fs_hz = _FIRE.unpack(payload)
    return FireRequest(step=step, mask=mask, flags=flags, n_samples=n_samples, fs_hz=fs_hz)


def decode_acq(payload: bytes, max_samples: int = 0xFFFF) -> AcqFrame:
    """Decode and validate an ACQ payload (lengths, channel count, bit depth, code range)."""
    if len(payload) < ACQ_HEADER_SIZE:
        raise TruncatedDataError(f"ACQ payload is {len(payload)} bytes, shorter than its {ACQ_HEADER_SIZE}-byte head")
    step, n_ch, bits, fs_hz, n_samples, status, t_fire_us, *tof = _ACQ.unpack_from(payload)
    if n_ch != N_CHANNELS:
        raise InvalidMessageError(f"ACQ: n_ch = {n_ch}, this protocol version has {N_CHANNELS} channels")
    if not 1 <= bits <= 16:
        raise InvalidMessageError(f"ACQ: bits = {bits}, must be 1..16")
    if n_samples > max_samples:
        raise PayloadTooLargeError(f"ACQ: {n_samples} samples per channel, over the maximum {max_samples}")
    if n_samples and fs_hz == 0:
        raise InvalidMessageError("ACQ: fs_hz = 0 with samples present")
    expected = acq_payload_size(n_samples, n_ch)
    if len(payload) != expected:
        raise TruncatedDataError(f"ACQ: payload is {len(payload)} bytes, {n_samples} samples need {expected}")
    waves = np.frombuffer(payload, dtype="<u2", offset=ACQ_HEADER_SIZE).reshape(n_ch, n_samples)
    if n_samples and bits < 16 and int(waves.max()) >= 1 << bits:
        raise InvalidMessageError(f"ACQ: a sample exceeds the {bits}-bit range")
    return AcqFrame(
        step=step,
        bits=bits,
        fs_hz=fs_hz,
        status=status,
        t_fire_us=t_fire_us,
        tof_ns=np.array(tof, dtype=np.uint32),
        waves=waves,
    )


def decode_err(payload: bytes) -> ErrReport:
    if len(payload) < _ERR.size:
        raise TruncatedDataError(f"ERR payload is {len(payload)} bytes, shorter than {_ERR.size}")
    (code,) = _ERR.unpack_from(payload)
    return ErrReport(code=code, text=payload[_ERR.size :].decode("utf-8", errors="replace"))


# --- streaming parser --------------------------------------------------------------------
class FrameParser:
    """Turns a byte stream into frames, resynchronising on garbage.

    Feed bytes with :meth:`feed`; call :meth:`next_frame` until it returns None.
    A sync pattern whose HCRC fails is garbage: one byte is dropped and the search
    goes on.  The parser's state is consistent after every raise, so the caller
    can keep calling :meth:`next_frame`.

    Parameters
    ----------
    max_payload : int
        Largest LEN accepted; checked before waiting for the payload.

    Attributes
    ----------
    discarded : int
        Bytes dropped while searching for a frame (garbage, broken headers, rejected frames).
    """

    def __init__(self, max_payload: int) -> None:
        if max_payload <= 0:
            raise ValueError("max_payload must be positive")
        self.max_payload = max_payload
        self._buf = bytearray()
        self.discarded = 0

    def feed(self, data: bytes) -> None:
        self._buf += data

    def reset(self) -> None:
        """Forget buffered bytes (e.g. after the port was flushed)."""
        self.discarded += len(self._buf)
        self._buf.clear()

    @property
    def buffered(self) -> int:
        return len(self._buf)

    def pending_header(self) -> tuple[int, int] | None:
        """``(type, seq)`` of the frame whose header has arrived, and checked out, but not all of its payload.

        Valid after :meth:`next_frame` returned None (it leaves the buffer at such a header, or
        short of one); None if no sound header is waiting.  A receiver learns from it that the
        sender has begun a frame: for an ACQ, that the acoustic window it carries is over.
        """
        buf = self._buf
        if len(buf) < HEADER_SIZE or buf[:2] != SYNC:
            return None
        _, _, frame_type, seq, _, hcrc = _HEADER.unpack_from(buf)
        if binascii.crc_hqx(bytes(buf[2:10]), 0xFFFF) != hcrc:
            return None
        return frame_type, seq

    def _drop(self, n: int) -> None:
        del self._buf[:n]
        self.discarded += n

    def next_frame(self) -> Frame | None:
        """The next complete, CRC-checked frame, or None if more bytes are needed.

        Raises
        ------
        FrameCrcError
            A frame arrived whole but its CRC32 failed (the frame is dropped).
        FrameTooLargeError
            A valid header declares LEN over ``max_payload`` (the header is dropped).
        FrameVersionError
            A valid header carries another VER (the header is dropped).
        """
        buf = self._buf
        while True:
            start = buf.find(SYNC)
            if start < 0:
                # Keep a trailing A5: it may be the first half of the next sync.
                self._drop(len(buf) - 1 if buf.endswith(SYNC[:1]) else len(buf))
                return None
            if start:
                self._drop(start)
            if len(buf) < HEADER_SIZE:
                return None
            _, version, frame_type, seq, length, hcrc = _HEADER.unpack_from(buf)
            if binascii.crc_hqx(bytes(buf[2:10]), 0xFFFF) != hcrc:
                self._drop(1)  # a false sync (garbage or a broken header): look further
                continue
            if version != VERSION:
                self._drop(HEADER_SIZE)
                raise FrameVersionError(f"frame version {version}, this build speaks {VERSION}")
            if length > self.max_payload:
                self._drop(HEADER_SIZE)
                raise FrameTooLargeError(
                    f"frame type 0x{frame_type:02X} seq {seq} declares {length} payload bytes, "
                    f"over the configured maximum {self.max_payload}"
                )
            total = HEADER_SIZE + length + TRAILER_SIZE
            if len(buf) < total:
                return None
            body = bytes(buf[2 : HEADER_SIZE + length])
            (crc,) = struct.unpack_from("<I", buf, HEADER_SIZE + length)
            if binascii.crc32(body) != crc:
                # The header was sound, so the whole frame is known to be bad: drop it all.
                self._drop(total)
                raise FrameCrcError(frame_type, seq, f"CRC32 mismatch in frame type 0x{frame_type:02X} seq {seq}")
            del buf[:total]
            return Frame(type=frame_type, seq=seq, payload=body[HEADER_SIZE - 2 :])
