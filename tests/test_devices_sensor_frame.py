"""The sensor-board framing codec and its streaming parser (pure, no I/O)."""

from __future__ import annotations

import binascii
import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lelsonar.acquire.devices import sensor_frame as sf
from lelsonar.errors import DecodeError, InvalidMessageError, PayloadTooLargeError, TruncatedDataError


def make_acq(n: int = 64, seed: int = 0, step: int = 3) -> sf.AcqFrame:
    rng = np.random.default_rng(seed)
    return sf.AcqFrame(
        step=step,
        bits=12,
        fs_hz=200_000,
        status=0,
        t_fire_us=123456,
        tof_ns=np.array([5_800_000, sf.NO_ECHO, 1, 2], dtype=np.uint32),
        waves=rng.integers(0, 4096, size=(4, n), dtype=np.uint16),
    )


def test_frame_layout_is_the_documented_one() -> None:
    frame = sf.encode_fire(0x1234, sf.FireRequest(step=7, mask=0x0F, flags=1, n_samples=3500, fs_hz=200_000))
    assert frame[:2] == b"\xa5\x5a"
    ver, typ, seq, length, hcrc = struct.unpack_from("<BBHIH", frame, 2)
    assert (ver, typ, seq, length) == (1, 0x01, 0x1234, 10)
    assert hcrc == binascii.crc_hqx(frame[2:10], 0xFFFF)
    assert len(frame) == 12 + 10 + 4
    assert struct.unpack_from("<I", frame, 22)[0] == binascii.crc32(frame[2:22])
    assert frame[12:22] == struct.pack("<HBBHI", 7, 0x0F, 1, 3500, 200_000)
    assert sf.acq_payload_size(3500) == 32 + 28_000


def test_acq_round_trip() -> None:
    acq = make_acq()
    parser = sf.FrameParser(max_payload=1 << 20)
    parser.feed(sf.encode_acq(9, acq))
    frame = parser.next_frame()
    assert frame is not None and (frame.type, frame.seq) == (sf.FrameType.ACQ, 9)
    back = sf.decode_acq(frame.payload)
    assert (back.step, back.bits, back.fs_hz, back.t_fire_us, back.n_ch, back.n_samples) == (
        3,
        12,
        200_000,
        123456,
        4,
        64,
    )
    np.testing.assert_array_equal(back.tof_ns, acq.tof_ns)
    np.testing.assert_array_equal(back.waves, acq.waves)
    assert parser.next_frame() is None and parser.discarded == 0


def test_err_and_fire_round_trip() -> None:
    parser = sf.FrameParser(max_payload=1024)
    parser.feed(sf.encode_err(5, sf.ErrReport(code=sf.ErrCode.BAD_PARAM, text="n_samples 0")))
    parser.feed(sf.encode_fire(6, sf.FireRequest(step=1, n_samples=10, fs_hz=1000)))
    err = parser.next_frame()
    assert sf.decode_err(err.payload) == sf.ErrReport(code=2, text="n_samples 0")
    fire = parser.next_frame()
    assert sf.decode_fire(fire.payload) == sf.FireRequest(step=1, n_samples=10, fs_hz=1000)


def test_wave_scale_maps_mid_scale_to_zero_volts() -> None:
    scale = sf.WaveScale(1.65)
    volts = scale.to_volts(np.array([0, 2048, 4095], dtype=np.uint16), 12)
    assert volts.dtype == np.float32
    np.testing.assert_allclose(volts, [-1.65, 0.0, 1.65 * 2047 / 2048], rtol=1e-6)
    np.testing.assert_array_equal(scale.to_codes(np.array([-5.0, 0.0, 5.0]), 12), [0, 2048, 4095])


@settings(max_examples=60, deadline=None)
@given(
    garbage=st.lists(st.binary(max_size=80), min_size=3, max_size=3),
    chunk=st.integers(1, 97),
    seed=st.integers(0, 2**16),
)
def test_parser_resyncs_on_garbage_in_any_chunking(garbage: list[bytes], chunk: int, seed: int) -> None:
    frames = [make_acq(n=8 + i, seed=seed + i, step=i) for i in range(2)]
    stream = garbage[0] + sf.encode_acq(1, frames[0]) + garbage[1] + sf.encode_acq(2, frames[1]) + garbage[2]
    parser = sf.FrameParser(max_payload=4096)
    got = []
    for i in range(0, len(stream), chunk):
        parser.feed(stream[i : i + chunk])
        while (frame := parser.next_frame()) is not None:
            got.append(frame)
    # Garbage can (rarely) fake a sync with a valid HCRC; the real frames must still all come through.
    acqs = [(f.seq, sf.decode_acq(f.payload)) for f in got if f.type == sf.FrameType.ACQ and f.seq in (1, 2)]
    assert [seq for seq, _ in acqs] == [1, 2]
    for (_, back), original in zip(acqs, frames):
        np.testing.assert_array_equal(back.waves, original.waves)


def test_bit_flips_are_detected_and_the_next_frame_survives() -> None:
    rng = np.random.default_rng(1)
    clean = sf.encode_acq(1, make_acq(n=32))
    detected = 0
    for _ in range(200):
        bad = bytearray(clean)
        bit = int(rng.integers(16, len(bad) * 8))  # anywhere after the sync
        bad[bit // 8] ^= 1 << (bit % 8)
        parser = sf.FrameParser(max_payload=4096)
        parser.feed(bytes(bad) + sf.encode_acq(2, make_acq(n=32)))
        seqs = []
        while True:
            try:
                frame = parser.next_frame()
            except sf.FrameCrcError as exc:
                assert exc.seq == 1
                detected += 1
                continue
            if frame is None:
                break
            seqs.append(frame.seq)
        assert seqs == [2]  # the damaged frame never passes, the next always does
    assert detected > 150  # payload flips are reported; header flips are resynced past


def test_oversize_len_is_rejected_before_the_payload() -> None:
    parser = sf.FrameParser(max_payload=100)
    frame = sf.encode_acq(4, make_acq(n=64))
    parser.feed(frame[:12])  # only the header: the parser must not wait for 544 bytes
    with pytest.raises(sf.FrameTooLargeError, match="over the configured maximum 100") as info:
        parser.next_frame()
    assert isinstance(info.value, PayloadTooLargeError)
    assert parser.buffered == 0


def test_unknown_version_is_a_typed_error() -> None:
    parser = sf.FrameParser(max_payload=100)
    parser.feed(sf.encode_frame(sf.FrameType.ERR, 1, b"\x00\x00", version=2))
    with pytest.raises(sf.FrameVersionError):
        parser.next_frame()


@pytest.mark.parametrize(
    ("mutate", "error"),
    [
        (lambda p: p[:-2], TruncatedDataError),
        (lambda p: p[:2] + b"\x03" + p[3:], InvalidMessageError),  # n_ch = 3
        (lambda p: p[:3] + b"\x11" + p[4:], InvalidMessageError),  # 17 bits
        (lambda p: p[:32] + b"\xff\xff" + p[34:], InvalidMessageError),  # code over 12 bits
        (lambda p: p[:10], TruncatedDataError),
    ],
)
def test_acq_payload_is_validated(mutate, error) -> None:
    payload = sf.encode_acq(1, make_acq(n=4))[12:-4]
    sf.decode_acq(payload)
    with pytest.raises(error):
        sf.decode_acq(mutate(payload))
    with pytest.raises(DecodeError):
        sf.decode_acq(payload, max_samples=3)
