"""The emulated rig: both real drivers against both emulators, linked by the servo angle; the CLI."""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import signal
import subprocess
import sys
import time
from types import SimpleNamespace

import numpy as np
import pytest

from lelsonar.acquire.devices import ax12
from lelsonar.acquire.devices import sensor_frame as sf
from lelsonar.acquire.devices.dynamixel import DynamixelMotor
from lelsonar.acquire.devices.motor import EMULATED_STALE_GUARD_S, MotorConfig
from lelsonar.acquire.devices.sensor_board import SensorBoardConfig, SerialSensorBoard
from lelsonar.acquire.emulate.ax12_emulator import AX12EmulatorConfig
from lelsonar.acquire.emulate.sensor_board_emulator import echo_shot_source, sim_shot_source
from lelsonar.cli import emulate as cli

FS = 200_000


def emulated_motor(path: str, **kw) -> MotorConfig:
    """As the emulated backend drives it: a 6 ms packet timeout, a long late-reply window."""
    return MotorConfig(port=path, latency_timer_ms=2.0, stale_guard_s=EMULATED_STALE_GUARD_S, **kw)


def _timed_scan(rig: cli.EmulatedRig, n: int) -> tuple[float, float]:
    """Run a 184-step scan through both real drivers; returns (wall time, physical bound)."""
    steps = [math.radians(-10.0 + 120.0 * i / 183) for i in range(184)]
    motor_cfg = emulated_motor(rig.motor.path, zero_raw=400)
    board_cfg = SensorBoardConfig(port=rig.board.path, n_samples=n, fs_hz=FS)
    with DynamixelMotor(motor_cfg) as motor, SerialSensorBoard(board_cfg) as board:
        previous = motor.move_to(steps[0]).raw
        bound = 0.0
        measured = []
        start = time.perf_counter()
        for step, gamma in enumerate(steps):
            goal = ax12.raw_from_gamma(gamma, 400)
            bound += ax12.travel_time_s(previous, goal, 0) + n / FS
            previous = goal
            position = motor.move_to(gamma)
            acq = board.fire(step)
            measured.append(position.gamma)
            # The board fired at the angle the servo reports.
            assert rig.board.shots[-1][1] == position.gamma
            assert acq.step == step and np.isfinite(acq.tof_s).all()
        elapsed = time.perf_counter() - start
    assert np.all(np.diff(measured) > 0)
    assert measured[-1] == pytest.approx(math.radians(110.0), abs=ax12.RAD_PER_UNIT)
    return elapsed, bound


@pytest.mark.slow
def test_scan_with_both_devices_fires_at_the_angle_the_servo_reports() -> None:
    """184 steps over 120° through both real drivers; the wall time against the physical
    bound is measured by `lelsonar bench acquire`, not asserted here."""
    source = echo_shot_source(0.5, noise_v=0.01, seed=1)  # a 2.9 ms echo inside the 5 ms window
    with cli.emulated_rig(source, AX12EmulatorConfig(return_delay=0), zero_raw=400) as rig:
        elapsed, bound = _timed_scan(rig, n=1000)
    assert elapsed >= bound * 0.95  # the emulated physics cannot be beaten


def test_sim_shot_source_adapts_the_simulator(monkeypatch) -> None:
    from lelsonar import sim

    calls = []

    def fake_simulate_step(cfg, gamma, rng):
        calls.append((cfg.window_samples, cfg.sample_rate, gamma))
        tof = np.array([0.005, np.nan, 0.0058, 0.006])
        waves = np.full((4, cfg.window_samples), 0.25, dtype=np.float32)
        return SimpleNamespace(tof=tof, distance=tof * 171.6, waveforms=waves, echo_source=None)

    from dataclasses import dataclass

    @dataclass(frozen=True)
    class FakeConfig:
        sample_rate: float = 200_000.0
        window_samples: int = 3500

    monkeypatch.setattr(sim, "simulate_step", fake_simulate_step, raising=False)
    source = sim_shot_source(FakeConfig(), np.random.default_rng(0))
    tof_ns, waves = source(3, 0.5, 64, 100_000.0)
    assert calls == [(64, 100_000.0, 0.5)]
    np.testing.assert_array_equal(tof_ns, [5_000_000, sf.NO_ECHO, 5_800_000, 6_000_000])
    assert waves.shape == (4, 64) and waves.dtype == np.float32


def test_the_board_fires_the_real_simulator_at_the_servo_angle() -> None:
    """The simulator's shot reaches the driver intact, and it is the scene's echo.

    Independent truth: (1) the simulator itself, called with the same seed at the angle the servo
    reports: the TOF to the ns the frame carries, the waveforms to the ADC's step; (2) the scene:
    at γ = 0 every beam meets wall a (y = 1.57 m) from capsules at y = 0.03 m, 1.54 m away.
    """
    from lelsonar import sim  # a broken simulator import must fail here, not skip

    cfg = sim.preset("paper-test1")
    source = sim_shot_source(cfg, np.random.default_rng(0))
    with cli.emulated_rig(source, AX12EmulatorConfig(return_delay=0)) as rig:
        board_cfg = SensorBoardConfig(
            port=rig.board.path,
            n_samples=int(cfg.window_samples),
            fs_hz=int(cfg.sample_rate),
            max_payload_bytes=max(256 * 1024, sf.acq_payload_size(int(cfg.window_samples))),
        )
        with DynamixelMotor(emulated_motor(rig.motor.path)) as motor:
            with SerialSensorBoard(board_cfg) as board:
                gamma = motor.move_to(0.0).gamma
                acq = board.fire(0)
        assert list(rig.board.shots) == [(0, gamma)] and gamma == 0.0
    expected = sim.simulate_step(cfg, gamma, np.random.default_rng(0))
    np.testing.assert_array_equal(acq.tof_s, np.round(expected.tof * 1e9) * 1e-9)
    lsb = board_cfg.full_scale_v / 2 ** (12 - 1)  # the emulated board's 12-bit ADC
    clipped = np.clip(expected.waveforms, -board_cfg.full_scale_v, board_cfg.full_scale_v - lsb)
    np.testing.assert_allclose(acq.waveforms, clipped, rtol=0, atol=lsb / 2 + 1e-6)
    assert np.ptp(acq.waveforms) > 100 * lsb  # an echo, not silence
    # Range from the TOF: the noise model allows 4σ of comparator jitter (σ = tof_jitter, 2 mm)
    # plus one cycle slip (λ/2 = c / 2f, 4.3 mm).
    c = cfg.sound_speed
    tolerance = 4 * cfg.receiver.tof_jitter + c / (2 * cfg.acoustics.frequency)
    np.testing.assert_allclose(c * acq.tof_s / 2, 1.57 - 0.03, rtol=0, atol=tolerance)


def test_cli_registers_and_runs_until_signalled(capsys, monkeypatch) -> None:
    parser = argparse.ArgumentParser()
    cli.register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["emulate", "--source", "echo", "--json", "--seed", "3"])
    # Signal handlers can only be installed from the main thread: run the CLI there, and send
    # SIGTERM once its rig is up (its handlers are installed before), not after a guessed delay.
    real_rig = cli.emulated_rig
    served = []

    @contextlib.contextmanager
    def rig_then_terminate(*a, **kw):
        with real_rig(*a, **kw) as rig:
            served.append(rig.motor.running and rig.board.running)
            os.kill(os.getpid(), signal.SIGTERM)
            yield rig

    monkeypatch.setattr(cli, "emulated_rig", rig_then_terminate)
    rc = args.run(args)
    assert rc == 0 and served == [True]
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1  # --json: only the JSON line on stdout
    paths = json.loads(out[-1])
    assert paths["source"] == "echo:1.0m" and paths["motor"].startswith("/dev/pts/")
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL  # handlers restored


@pytest.mark.slow
def test_cli_in_a_subprocess_serves_the_real_drivers() -> None:
    code = (
        "import argparse, sys\n"
        "from lelsonar.cli import emulate as cli\n"
        "p = argparse.ArgumentParser(); cli.register(p.add_subparsers(dest='command'))\n"
        "a = p.parse_args(sys.argv[1:]); sys.exit(a.run(a))\n"
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", code, "emulate", "--source", "echo", "--json"],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    try:
        line = ""
        while not line.startswith("{"):
            line = proc.stdout.readline()
            assert line, "emulate exited before printing its paths"
        paths = json.loads(line)
        with DynamixelMotor(emulated_motor(paths["motor"])) as motor:
            assert motor.ping() == 12
            gamma = motor.move_to(math.radians(20.0)).gamma
        with SerialSensorBoard(SensorBoardConfig(port=paths["sensor_board"], n_samples=1500, fs_hz=FS)) as board:
            acq = board.fire(0)
        assert gamma == pytest.approx(math.radians(20.0), abs=ax12.RAD_PER_UNIT)
        assert acq.tof_s == pytest.approx(np.full(4, 2 / 343.2))
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=5) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stdout.close()
