"""SerialSensorBoard (pyserial) against the sensor-board emulator on a pty."""

from __future__ import annotations

import binascii
import os
import time

import numpy as np
import pytest

from lelsonar.acquire.devices import sensor_frame as sf
from lelsonar.acquire.devices.link import Link
from lelsonar.acquire.devices.sensor_board import (
    SensorBoard,
    SensorBoardCommunicationError,
    SensorBoardConfig,
    SensorBoardDecodeError,
    SensorBoardReportedError,
    SensorBoardTimeoutError,
    SerialSensorBoard,
)
from lelsonar.acquire.emulate.pty_link import RawPty
from lelsonar.acquire.emulate.sensor_board_emulator import (
    SensorBoardEmulator,
    SensorBoardEmulatorConfig,
    echo_shot_source,
)
from lelsonar.errors import ConfigError, DecodeError, DeviceError, DeviceTimeoutError, InvalidMessageError

N, FS = 400, 200_000  # a 2 ms window keeps the tests quick


def board_config(emu: SensorBoardEmulator, **kw) -> SensorBoardConfig:
    # Short timeouts keep the retry tests quick; the line time of a 1 Mbaud UART (not USB's 12× less)
    # keeps them clear of a busy host's delays, as these tests were tuned.
    return SensorBoardConfig(
        port=emu.path,
        n_samples=kw.pop("n_samples", N),
        fs_hz=FS,
        timeout_margin_s=0.02,
        link=kw.pop("link", Link.uart(1_000_000)),
        **kw,
    )


def counting_source(step: int, gamma: float, n: int, fs: float) -> tuple[np.ndarray, np.ndarray]:
    """int16 codes: channel c, sample k = 100·c + step + k mod 50; TOF = step µs."""
    k = np.arange(n)
    waves = np.stack([(100 * c + step + k % 50).astype(np.int16) for c in range(4)])
    return np.full(4, step * 1000, dtype=np.uint32), waves


@pytest.fixture
def board():
    with SensorBoardEmulator(counting_source, lambda: 0.25, SensorBoardEmulatorConfig(seed=3)) as emu:
        with SerialSensorBoard(board_config(emu)) as drv:
            yield emu, drv


def expected_volts(step: int, n: int = N) -> np.ndarray:
    _, codes = counting_source(step, 0.0, n, FS)
    return codes.astype(np.float32) * np.float32(1.65 / 2048)


def test_fire_returns_volts_and_seconds(board) -> None:
    emu, drv = board
    assert isinstance(drv, SensorBoard)
    acq = drv.fire(7)
    assert (acq.step, acq.requests, acq.fs_hz) == (7, 1, FS)
    np.testing.assert_allclose(acq.tof_s, 7e-6)
    assert acq.waveforms.dtype == np.float32 and acq.waveforms.shape == (4, N)
    np.testing.assert_allclose(acq.waveforms, expected_volts(7), rtol=1e-6)
    assert list(emu.shots) == [(7, 0.25)]


def test_fire_waits_for_the_acoustic_window() -> None:
    with SensorBoardEmulator(echo_shot_source(1.0)) as emu:
        with SerialSensorBoard(SensorBoardConfig(port=emu.path, n_samples=3500, fs_hz=FS)) as drv:
            drv.fire(0)
            times = []
            for step in range(10):
                start = time.perf_counter()
                acq = drv.fire(step)
                times.append(time.perf_counter() - start)
    window = 3500 / FS
    # Never before the window ends (how soon after is `lelsonar bench acquire`'s to measure).
    assert min(times) >= window, times
    np.testing.assert_allclose(acq.tof_s, 2 / 343.2, rtol=1e-6)
    # The stand-in's burst starts at the TOF sample.
    first = int(np.argmax(np.abs(acq.waveforms[0]) > 0.05))
    assert abs(first / FS - 2 / 343.2) < 3 / FS


def test_corrupted_frames_are_re_requested_and_resent(board) -> None:
    emu, drv = board
    emu.inject_corruption(2)
    acq = drv.fire(11)
    assert acq.requests == 3 and drv.crc_retries == 2
    assert emu.resends == 2 and len(emu.shots) == 1  # the shot was fired once, sent three times
    assert acq.status & sf.AcqStatus.RESENT
    np.testing.assert_allclose(acq.waveforms, expected_volts(11), rtol=1e-6)


def test_header_corruption_is_recovered_after_a_timeout(board) -> None:
    emu, drv = board
    emu.inject_corruption(1, where="header")
    acq = drv.fire(12)
    assert acq.requests == 2 and drv.timeout_retries == 1
    np.testing.assert_allclose(acq.waveforms, expected_volts(12), rtol=1e-6)


def test_random_corruption_and_garbage_are_all_recovered() -> None:
    cfg = SensorBoardEmulatorConfig(corrupt_probability=0.2, garbage_probability=0.5, garbage_max_bytes=300, seed=11)
    with SensorBoardEmulator(counting_source, config=cfg) as emu:
        with SerialSensorBoard(board_config(emu, retries=6)) as drv:
            for step in range(40):
                acq = drv.fire(step)
                np.testing.assert_allclose(acq.waveforms, expected_volts(step), rtol=1e-6)
            assert emu.corrupted > 0 and drv.discarded_bytes > 0


def test_garbage_between_frames_is_skipped(board) -> None:
    emu, drv = board
    emu.inject_garbage(1000, n=3)
    for step in (1, 2, 3):
        acq = drv.fire(step)
        assert acq.requests == 1
        np.testing.assert_allclose(acq.waveforms, expected_volts(step), rtol=1e-6)
    assert drv.discarded_bytes >= 3000


def test_oversize_len_is_rejected_with_a_typed_error() -> None:
    """A board declaring 10 MB is refused from the header alone, without waiting for the payload."""
    with RawPty() as fake_board:
        with SerialSensorBoard(SensorBoardConfig(port=fake_board.path, n_samples=N, fs_hz=FS)) as drv:
            header = sf.encode_frame(sf.FrameType.ACQ, 1, b"")[:12]  # the first FIRE has SEQ 1
            ver_to_len = header[2:6] + (10_000_000).to_bytes(4, "little")
            os.write(
                fake_board.master_fd,
                b"\xa5\x5a" + ver_to_len + binascii.crc_hqx(ver_to_len, 0xFFFF).to_bytes(2, "little"),
            )
            with pytest.raises(SensorBoardDecodeError, match="10000000") as info:
                drv.fire(1)
            # Refused at the header: had it waited for the payload, it would have timed out and asked again.
            assert (drv.timeout_retries, drv.crc_retries) == (0, 0)
            assert isinstance(info.value.__cause__, sf.FrameTooLargeError)
            assert isinstance(info.value, DecodeError) and isinstance(info.value, DeviceError)
    with pytest.raises(ConfigError, match="max_payload_bytes"):
        SensorBoardConfig(port="x", n_samples=3500, max_payload_bytes=1000)


def test_no_answer_is_a_timeout_after_the_retries(board) -> None:
    emu, drv = board
    emu.drop_next(2)
    assert drv.fire(4).requests == 3
    emu.drop_next(10)
    with pytest.raises(SensorBoardTimeoutError) as info:
        drv.fire(5)
    assert isinstance(info.value, DeviceTimeoutError)


def test_board_errors_are_typed() -> None:
    with SensorBoardEmulator(counting_source, config=SensorBoardEmulatorConfig(max_samples=100)) as emu:
        with SerialSensorBoard(board_config(emu)) as drv:
            with pytest.raises(SensorBoardReportedError, match="BAD_PARAM") as info:
                drv.fire(1)
            assert info.value.code == sf.ErrCode.BAD_PARAM


def test_a_corrupt_fire_is_answered_bad_crc() -> None:
    with SensorBoardEmulator(counting_source) as emu:
        fd = os.open(emu.path, os.O_RDWR | os.O_NOCTTY)
        try:
            bad = bytearray(sf.encode_fire(77, sf.FireRequest(step=1, n_samples=10, fs_hz=FS)))
            bad[14] ^= 0x01
            os.write(fd, bytes(bad))
            parser = sf.FrameParser(1024)
            frame = None
            deadline = time.monotonic() + 2.0
            while frame is None and time.monotonic() < deadline:
                parser.feed(os.read(fd, 1024))
                frame = parser.next_frame()
        finally:
            os.close(fd)
    assert frame is not None and (frame.type, frame.seq) == (sf.FrameType.ERR, 77)
    assert sf.decode_err(frame.payload).code == sf.ErrCode.BAD_CRC


def _with_bits(frame: bytes, bits: int) -> bytes:
    """The same ACQ frame, re-framed (CRCs sound) with another bit depth in its payload."""
    if frame[3] != sf.FrameType.ACQ:
        return frame
    seq = int.from_bytes(frame[4:6], "little")
    payload = bytearray(frame[sf.HEADER_SIZE : -sf.TRAILER_SIZE])
    payload[3] = bits  # step u16, n_ch u8, bits u8, ...
    return sf.encode_frame(sf.FrameType.ACQ, seq, bytes(payload))


def test_an_undecodable_answer_is_a_device_error_and_the_next_shot_works(board, monkeypatch) -> None:
    emu, drv = board
    send = emu._send
    monkeypatch.setattr(emu, "_send", lambda frame, due: send(_with_bits(frame, 17), due))
    with pytest.raises(SensorBoardDecodeError, match="bits = 17") as info:
        drv.fire(3)
    assert isinstance(info.value, DeviceError) and isinstance(info.value, DecodeError)
    assert isinstance(info.value.__cause__, InvalidMessageError)
    monkeypatch.setattr(emu, "_send", send)
    np.testing.assert_allclose(drv.fire(4).waveforms, expected_volts(4), rtol=1e-6)


def test_a_failed_port_is_a_device_error(board) -> None:
    emu, drv = board
    emu.stop()  # the board is unplugged: its end of the line is gone
    with pytest.raises(SensorBoardCommunicationError, match="serial I/O") as info:
        drv.fire(5)
    assert isinstance(info.value, DeviceError) and isinstance(info.value.__cause__, OSError)
