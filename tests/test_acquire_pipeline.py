"""The emulated links run at their rates, and the pipelined loop moves the servo under the
frame's transfer, never during an acoustic window, and measures what the sequential loop measures.

Timing is checked as ratios and orders of events on the devices' own timelines, never against a
wall-clock threshold: a loaded host can only make the emulators later, and a paced link is never early.
"""

from __future__ import annotations

import os
import select
import threading
import time

import numpy as np
import pytest

from lelsonar.acquire.backends import open_scanner
from lelsonar.acquire.config import AcquireConfig
from lelsonar.acquire.devices import ax12
from lelsonar.acquire.devices import sensor_frame as sf
from lelsonar.acquire.devices.dynamixel import DynamixelMotor
from lelsonar.acquire.devices.link import AX12_BUS, SENSOR_BOARD_USB, Link
from lelsonar.acquire.devices.motor import EMULATED_STALE_GUARD_S, MotorConfig
from lelsonar.acquire.devices.sensor_board import SensorBoardConfig, SensorBoardProtocolError, SerialSensorBoard
from lelsonar.acquire.emulate.ax12_emulator import AX12Emulator, AX12EmulatorConfig
from lelsonar.acquire.emulate.pty_link import PtyDevice
from lelsonar.acquire.emulate.sensor_board_emulator import SensorBoardEmulator, SensorBoardEmulatorConfig
from lelsonar.acquire.scan_loop import ScanIdentity, gamma_schedule, run_scan
from lelsonar.acquire.service import energy_model, sim_config
from lelsonar.v1 import scan_pb2

from .conftest import Collect


class Blob(PtyDevice):
    """Answers any input with ``n`` bytes, due at once: the link alone sets their pace."""

    def __init__(self, link: Link, n: int) -> None:
        super().__init__("blob", link)
        self.n = n

    def _on_input(self, data: bytes, now: float) -> None:
        self._schedule(bytes(i & 0xFF for i in range(self.n)), now)


def test_a_paced_link_is_never_early_and_keeps_its_rate_under_load(cpu_hog):
    """50,000 bytes over a 1 Mbaud UART (100 kB/s, 0.5 s), every core busy with another process.

    Never early: by any instant t after the request was written, at most rate · (t − t0) bytes have
    arrived (the emulator releases a chunk when its last byte would have crossed the line).  Keeps up:
    a late thread writes every chunk that is due, so the whole transfer takes its line time plus the
    last wake-up's delay (a 1.5 × bound leaves a 250 ms lateness to a starved host)."""
    link, n = Link.uart(1_000_000), 50_000
    arrivals: list[tuple[float, int]] = []
    with Blob(link, n) as dev:
        fd = os.open(dev.path, os.O_RDWR | os.O_NOCTTY)
        try:
            t0 = time.monotonic()
            os.write(fd, b"go")
            got = 0
            while got < n:
                readable, _, _ = select.select([fd], [], [], 5.0)
                assert readable, "the emulated link stalled"
                got += len(os.read(fd, 65536))
                arrivals.append((time.monotonic(), got))
        finally:
            os.close(fd)
    assert got == n
    line_s = link.seconds(n)
    for t, received in arrivals:
        assert received <= link.bytes_per_s * (t - t0) + 1e-6, "bytes arrived faster than the link carries them"
    ratio = (arrivals[-1][0] - t0) / line_s
    assert 1.0 <= ratio <= 1.5, f"transfer took {ratio:.3f} × its line time"


def test_every_servo_transaction_pays_its_bytes_on_the_bus(cpu_hog):
    """60 reads of Present Position .. Moving through the real driver: each READ is 8 bytes out and 17 back
    at 10 µs a byte on the 1 Mbps bus, so 60 cannot take less than 60 × 250 µs (load only adds)."""
    with (
        AX12Emulator(AX12EmulatorConfig(return_delay=0, link=AX12_BUS)) as servo,
        DynamixelMotor(
            MotorConfig(port=servo.path, latency_timer_ms=2.0, stale_guard_s=EMULATED_STALE_GUARD_S)
        ) as motor,
    ):
        start = time.perf_counter()
        for _ in range(60):
            motor.position()
        elapsed = time.perf_counter() - start
    assert elapsed / (60 * AX12_BUS.seconds(8 + 17)) >= 1.0


def _scan(pipeline: bool):
    cfg = AcquireConfig(device="emulated", steps=24, pipeline=pipeline, record=False, seed=3)
    sim = sim_config(cfg)
    schedule = gamma_schedule(sim.gamma_start, sim.gamma_stop, sim.steps)
    out = Collect()
    with open_scanner(cfg, sim) as scanner:
        end = run_scan(scanner, schedule, ScanIdentity("rig1", 1), energy_model(cfg), out, threading.Event())
        rig = scanner.rig
        shots, windows, moves = list(rig.board.shots), list(rig.board.windows), list(rig.motor.moves)
    assert end.status == scan_pb2.SCAN_STATUS_COMPLETE, end.reason
    samples = out.messages[1:-1]
    assert [s.step for s in samples] == list(range(24))
    return sim, schedule, samples, shots, windows, moves


def test_the_pipelined_scan_measures_what_the_sequential_one_does_and_moves_only_between_windows():
    """Same seed, same schedule, both loops, the emulated rig paced at its links.

    Truth from the devices: the board's record of where the servo was when it fired each shot, its
    acoustic windows, and the servo's record of when it travelled."""
    results = {p: _scan(p) for p in (False, True)}
    sim, schedule = results[True][0], results[True][1]
    zero_raw = int(sim.servo.to_raw(0.0))
    acq_s = SENSOR_BOARD_USB.seconds(sf.frame_size(sf.acq_payload_size(sim.window_samples)))
    for pipeline, (_, _, samples, shots, windows, moves) in results.items():
        # Each sample is the servo's read-back at its own goal, and the board fired there.
        for s, gamma in zip(samples, schedule):
            assert s.motor.present_position_raw == ax12.raw_from_gamma(float(gamma), zero_raw)
        assert shots == [(s.step, s.gamma_measured) for s in samples]
        # One move per step after the first (the servo starts at the first goal); none while the capsules listen.
        assert len(moves) == 23 and len(windows) == 24
        for start, end in moves:
            for _, w_start, w_end in windows:
                assert end <= w_start or start >= w_end, f"the servo travelled during a window (pipeline={pipeline})"
        # The move to step k+1 starts after shot k's window; pipelined, while its frame is still on the link.
        under_frame = sum(start < windows[k][2] + acq_s for k, (start, _) in enumerate(moves))
        assert all(start >= windows[k][2] for k, (start, _) in enumerate(moves))
        if pipeline:
            assert under_frame >= len(moves) // 2, f"only {under_frame} of {len(moves)} moves were under a frame"
        else:
            assert under_frame == 0
    # The same shots: same angles, same echoes, same waveforms.
    sequential, pipelined = results[False][2], results[True][2]
    for a, b in zip(sequential, pipelined):
        assert (a.gamma_measured, a.motor.present_position_raw) == (b.gamma_measured, b.motor.present_position_raw)
        assert [(r.echo_valid, r.time_of_flight) for r in a.sensors] == [
            (r.echo_valid, r.time_of_flight) for r in b.sensors
        ]
        assert [r.waveform.data for r in a.sensors] == [r.waveform.data for r in b.sensors]


def _counting_source(step: int, gamma: float, n: int, fs: float):
    return np.full(4, 1000 * (step + 1), dtype=np.uint32), np.zeros((4, n), dtype=np.int16)


@pytest.mark.parametrize("board_kept_the_shot", [True, False], ids=["resent", "fired-anew"])
def test_after_the_window_a_re_requested_shot_must_be_the_same_shot(board_kept_the_shot):
    """The servo moves once the answer's header is in; if the frame then fails its CRC, the driver asks
    again, and only a resend of that shot (status RESENT) will do: a board that fired anew fired at the
    angle the servo has moved to."""
    with (
        SensorBoardEmulator(_counting_source, config=SensorBoardEmulatorConfig(link=SENSOR_BOARD_USB)) as emu,
        SerialSensorBoard(SensorBoardConfig(port=emu.path, n_samples=400, fs_hz=200_000)) as board,
    ):
        emu.inject_corruption(1, "payload")
        moved: list[int] = []

        def servo_moves() -> None:
            moved.append(emu.fires)
            if not board_kept_the_shot:
                emu._last = None  # the board lost the shot it was sending (e.g. it reset)

        shot = board.send_fire(5)
        if board_kept_the_shot:
            acq = board.receive(shot, after_window=servo_moves)
            assert acq.status & sf.AcqStatus.RESENT and acq.requests == 2 and acq.step == 5
        else:
            with pytest.raises(SensorBoardProtocolError, match="RESENT"):
                board.receive(shot, after_window=servo_moves)
    assert moved == [1]  # once, after the first FIRE's window


def test_a_sample_measured_before_an_unexpected_error_is_still_recorded():
    """The pipelined loop holds each sample until the next shot listens; if something other than a device
    fault ends the loop before that (a bug, an interrupt), the held sample still goes out first."""
    from lelsonar.acquire.backends import SimScanner

    cfg = AcquireConfig(device="sim", steps=10)
    sim = sim_config(cfg)
    inner = SimScanner(sim, seed=1)

    class Breaks:
        info = inner.info

        def measure(self, step, gamma, *, next_gamma=None, while_listening=None):
            if step == 5:
                raise RuntimeError("a bug in the scanner")
            if while_listening is not None:
                while_listening()  # works while listening, like the pipelined device scanner
            return inner.measure(step, gamma)

    out = Collect()
    schedule = gamma_schedule(sim.gamma_start, sim.gamma_stop, sim.steps)
    with pytest.raises(RuntimeError, match="a bug"):
        run_scan(Breaks(), schedule, ScanIdentity("s", 1), energy_model(cfg), out, threading.Event())
    assert [m.step for m in out.messages[1:]] == [0, 1, 2, 3, 4]
