"""The acquisition service end to end: emulated devices through the real drivers, MCAP and Zenoh."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading

import pytest
import zenoh

from lelsonar import codec
from lelsonar.acquire.backends import open_scanner
from lelsonar.acquire.config import AcquireConfig
from lelsonar.acquire.scan_loop import ScanIdentity, ScanOutput, gamma_schedule, run_scan
from lelsonar.acquire.service import energy_model, run_acquisition, sim_config
from lelsonar.keys import ScannerKeys
from lelsonar.log import recording
from lelsonar.net.transport import hermetic_settings, open_session
from lelsonar.v1 import scan_pb2

from .test_contract_mcap import RERUN


def collect(sub, stop_after: int, got: list, done: threading.Event) -> None:
    for s in sub:
        cls = codec.type_from_encoding(str(s.encoding))
        got.append(codec.decode(s.payload.to_bytes(), cls))
        if len(got) >= stop_after:
            done.set()
            return


@pytest.mark.slow
def test_emulated_scan_is_recorded_and_published_in_order(tmp_path, zenoh_socket):
    cfg = AcquireConfig(scanner_id="rig1", device="emulated", out_dir=tmp_path, serve_log_for=0)
    steps = sim_config(cfg).steps
    keys = ScannerKeys("lelsonar", "rig1")
    got: list = []
    done = threading.Event()
    with open_session(hermetic_settings(zenoh_socket, listen=True)) as hub:
        sub_samples = hub.declare_subscriber(keys.sample, zenoh.handlers.FifoChannel(1024))
        sub_scan = hub.declare_subscriber(keys.scan, zenoh.handlers.FifoChannel(16))
        scan_events: list = []
        scan_done = threading.Event()
        threads = [
            threading.Thread(target=collect, args=(sub_samples, steps, got, done), daemon=True),
            threading.Thread(target=collect, args=(sub_scan, 2, scan_events, scan_done), daemon=True),
        ]
        for t in threads:
            t.start()
        report = run_acquisition(cfg, hermetic_settings(zenoh_socket, listen=False), threading.Event())
        assert done.wait(30) and scan_done.wait(30)
    assert report.ok and report.publish_failures == 0
    recorded = list(recording.read_messages(report.paths[0]))
    assert isinstance(recorded[0], codec.ScanStart) and isinstance(recorded[-1], codec.ScanEnd)
    samples = recorded[1:-1]
    assert [s.step for s in samples] == list(range(steps))
    assert [s.step for s in got] == list(range(steps))
    assert got == samples
    assert [type(m) for m in scan_events] == [codec.ScanStart, codec.ScanEnd]
    assert (
        recorded[-1].status
        == codec.ScanEnd.DESCRIPTOR.fields_by_name["status"].enum_type.values_by_name["SCAN_STATUS_COMPLETE"].number
    )
    # The measured angle is the servo's read-back, on the AX-12's 0.29° grid, near the commanded one.
    for s in samples:
        assert abs(s.gamma_measured - s.gamma_commanded) < 0.006
    for cmd in (
        [RERUN, "mcap", "check", str(report.paths[0])],
        [RERUN, "mcap", "convert", str(report.paths[0]), "-o", str(tmp_path / "x.rrd")],
        [RERUN, "rrd", "verify", str(tmp_path / "x.rrd")],
    ):
        done_cmd = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
        assert done_cmd.returncode == 0, done_cmd.stderr


@pytest.mark.parametrize(("pipeline", "failing_step"), [(False, 13), (True, 14)], ids=["sequential", "pipelined"])
def test_motor_fault_mid_scan_aborts_cleanly_and_keeps_what_was_recorded(tmp_path, pipeline, failing_step):
    """The servo overloads once sample 12 is out; the first move commanded after that fails, and every
    sample before it is recorded.  Sequential: that is the move to step 13.  Pipelined: the move to
    step 13 was made while step 12's frame crossed the link, and sample 12 goes out during step 13's
    window, so the move that meets the overload is step 14's (made during step 13's transfer)."""
    cfg = AcquireConfig(device="emulated", out_dir=tmp_path, steps=40, pipeline=pipeline)
    sim = sim_config(cfg)
    schedule = gamma_schedule(sim.gamma_start, sim.gamma_stop, sim.steps)
    path = tmp_path / "fault.mcap"
    with open_scanner(cfg, sim) as scanner, recording.McapRecorder(path) as rec:

        def overload_at_step_12(step: int, _gamma: float) -> None:
            if step == 12:
                scanner.rig.motor.inject_overload()

        end = run_scan(
            scanner,
            schedule,
            ScanIdentity("s1", 5),
            energy_model(cfg),
            ScanOutput(rec, None),
            threading.Event(),
            on_step=overload_at_step_12,
        )
    assert end.status == 2 and "overload" in end.reason.lower() and f"step {failing_step}:" in end.reason
    recorded = list(recording.read_messages(path))
    assert [s.step for s in recorded if isinstance(s, codec.Sample)] == list(range(failing_step))
    assert recorded[-1] == end and end.samples_sent == failing_step


@pytest.mark.parametrize("pipeline", [False, True], ids=["sequential", "pipelined"])
def test_the_servo_status_byte_reaches_every_sample(tmp_path, pipeline):
    """The AX-12's ERR byte of each step's read-back is carried in Sample.motor.error_bits: here a
    supply that sags below the Min Voltage Limit while samples 5-8 go out (tolerated, so the scan goes
    on).  The read-backs that see it are those of the moves made then: steps 6-9 one after the other;
    pipelined, steps 7-10 (the move to step 6 was made during step 5's transfer, before sample 5 went out)."""
    import numpy as np

    from lelsonar.acquire.backends import DeviceScanner, sim_info
    from lelsonar.acquire.devices.ax12 import ErrorBit
    from lelsonar.acquire.devices.dynamixel import DynamixelMotor
    from lelsonar.acquire.devices.motor import EMULATED_STALE_GUARD_S, MotorConfig
    from lelsonar.acquire.devices.sensor_board import SensorBoardConfig, SerialSensorBoard
    from lelsonar.acquire.emulate.ax12_emulator import AX12EmulatorConfig
    from lelsonar.acquire.emulate.rig import emulated_rig
    from lelsonar.acquire.emulate.sensor_board_emulator import sim_shot_source

    cfg = AcquireConfig(device="emulated", out_dir=tmp_path, steps=16)
    sim = sim_config(cfg)
    schedule = gamma_schedule(sim.gamma_start, sim.gamma_stop, sim.steps)
    zero_raw = int(sim.servo.to_raw(0.0))
    lo, hi = sorted((sim.gamma_start, sim.gamma_stop))
    with (
        emulated_rig(
            sim_shot_source(sim, np.random.default_rng(0)),
            AX12EmulatorConfig(return_delay=0, initial_position=int(sim.servo.to_raw(sim.gamma_start))),
            zero_raw=zero_raw,
        ) as rig,
        DynamixelMotor(
            MotorConfig(
                port=rig.motor.path,
                gamma_min=lo,
                gamma_max=hi,
                latency_timer_ms=2.0,
                stale_guard_s=EMULATED_STALE_GUARD_S,
                zero_raw=zero_raw,
                tolerated_error_bits=int(ErrorBit.INPUT_VOLTAGE),
            )
        ) as motor,
        SerialSensorBoard(
            SensorBoardConfig(port=rig.board.path, n_samples=sim.window_samples, fs_hz=int(sim.sample_rate))
        ) as board,
    ):
        scanner = DeviceScanner(motor, board, sim_info(sim, "emulated"), rig, pipeline=pipeline)

        def supply(step: int, _gamma: float) -> None:
            if step == 5:
                rig.motor.set_register("present_voltage", 55)  # 5.5 V < the 6.0 V limit
            elif step == 9:
                rig.motor.set_register("present_voltage", 120)

        collected: list = []
        output = ScanOutput()
        output.emit = collected.append
        end = run_scan(
            scanner, schedule, ScanIdentity("s1", 8), energy_model(cfg), output, threading.Event(), on_step=supply
        )
    assert end.status == scan_pb2.SCAN_STATUS_COMPLETE, end.reason
    samples = [m for m in collected if isinstance(m, codec.Sample)]
    first = 7 if pipeline else 6
    assert [s.motor.error_bits for s in samples] == [0] * first + [int(ErrorBit.INPUT_VOLTAGE)] * 4 + [0] * (12 - first)
    assert [s.motor.voltage for s in samples][first - 1 : first + 5] == pytest.approx([12.0, 5.5, 5.5, 5.5, 5.5, 12.0])


def _undecodable_from_step_12(scanner) -> None:
    """The board frames the ACQ of step 12 on with a bit depth of 17: well framed, undecodable."""
    from .test_devices_sensor_board import _with_bits

    board = scanner.rig.board
    send = board._send

    def send_from_step_12(frame: bytes, due: float) -> None:
        is_acq = frame[3] == 0x81
        send(_with_bits(frame, 17) if is_acq and int.from_bytes(frame[12:14], "little") >= 12 else frame, due)

    board._send = send_from_step_12


def _unplugged_after_step_11(scanner) -> None:
    """The board is unplugged once sample 11 is out, i.e. while step 12's shot is in flight at the latest."""
    return lambda step, _gamma: scanner.rig.board.stop() if step == 11 else None


@pytest.mark.parametrize("pipeline", [False, True], ids=["sequential", "pipelined"])
@pytest.mark.parametrize(
    ("fault", "reason"),
    [
        (_undecodable_from_step_12, "cannot be decoded"),
        (_unplugged_after_step_11, "serial I/O"),
    ],
    ids=["decode-error", "serial-error"],
)
def test_a_sensor_board_fault_mid_scan_aborts_cleanly(tmp_path, fault, reason, pipeline):
    cfg = AcquireConfig(device="emulated", out_dir=tmp_path, steps=20, pipeline=pipeline)
    sim = sim_config(cfg)
    schedule = gamma_schedule(sim.gamma_start, sim.gamma_stop, sim.steps)
    path = tmp_path / "fault.mcap"
    with open_scanner(cfg, sim) as scanner, recording.McapRecorder(path) as rec:
        on_step = fault(scanner)  # installed now, or a hook that strikes after sample 11
        end = run_scan(
            scanner,
            schedule,
            ScanIdentity("s1", 6),
            energy_model(cfg),
            ScanOutput(rec, None),
            threading.Event(),
            on_step=on_step,
        )
    assert end.status == scan_pb2.SCAN_STATUS_ABORTED
    assert "device failure at step 12" in end.reason and reason in end.reason
    recorded = list(recording.read_messages(path))
    assert [s.step for s in recorded if isinstance(s, codec.Sample)] == list(range(12))
    assert recorded[-1] == end and end.samples_sent == 12


@pytest.mark.slow
def test_sigint_mid_scan_leaves_a_finished_recording_that_ends_in_an_aborted_scan_end(tmp_path, zenoh_socket):
    keys = ScannerKeys("lelsonar", "scanner1")
    got: list = []
    twenty = threading.Event()
    with open_session(hermetic_settings(zenoh_socket, listen=True)) as hub:
        sub = hub.declare_subscriber(keys.sample, zenoh.handlers.FifoChannel(1024))
        threading.Thread(target=collect, args=(sub, 20, got, twenty), daemon=True).start()
        proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "lelsonar",
                "acquire",
                "--device",
                "emulated",
                "--out",
                str(tmp_path),
                "--mode",
                "client",
                "--connect",
                f"unixsock-stream/{zenoh_socket}",
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env={**os.environ, "COLUMNS": "120"},
        )
        try:
            assert twenty.wait(60), "the scan did not start"
            proc.send_signal(signal.SIGINT)
            out, err = proc.communicate(timeout=60)
        finally:
            proc.kill()
    assert proc.returncode == 130, err  # interrupted by Ctrl-C, as documented
    recorded = list(recording.read_messages(tmp_path / "scan.mcap"))
    end = recorded[-1]
    assert isinstance(end, codec.ScanEnd) and end.status == 2 and "stopped by request" in end.reason
    samples = [m for m in recorded if isinstance(m, codec.Sample)]
    assert 20 <= len(samples) == end.samples_sent < 184
    assert [s.step for s in samples] == list(range(len(samples)))
