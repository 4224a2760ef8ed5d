"""Device timing on a loaded host: the emulated rig and the real drivers with every core saturated
by other processes.  The emulators are threads of this process, so a busy host starves
them: their replies come late, and the drivers must wait them out rather than give up or take a late
reply for the next one."""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest

from lelsonar.acquire.backends import open_scanner
from lelsonar.acquire.config import AcquireConfig
from lelsonar.acquire.devices import ax12
from lelsonar.acquire.scan_loop import ScanIdentity, gamma_schedule, run_scan
from lelsonar.acquire.service import energy_model, sim_config
from lelsonar.v1 import scan_pb2

from .conftest import Collect

pytestmark = pytest.mark.slow


def test_a_full_emulated_scan_completes_with_every_core_saturated(cpu_hog) -> None:
    """184 steps through both real drivers and both emulators, as `acquire --device emulated` runs
    them, while one busy process per core competes for the CPU."""
    cfg = AcquireConfig(scanner_id="rig1", device="emulated", record=False)
    sim = sim_config(cfg)
    schedule = gamma_schedule(sim.gamma_start, sim.gamma_stop, sim.steps)
    out = Collect()
    with open_scanner(cfg, sim) as scanner:
        end = run_scan(scanner, schedule, ScanIdentity("rig1", 1), energy_model(cfg), out, threading.Event())
        motor = scanner.motor
    assert end.status == scan_pb2.SCAN_STATUS_COMPLETE, end.reason
    assert end.samples_sent == len(schedule) == 184
    samples = out.messages[1:-1]
    assert [s.step for s in samples] == list(range(184))
    # Every sample is the servo's own read-back of its own step: on the 0.29° grid, at the goal
    # (a reply taken for the wrong request would put a step at its neighbour's angle).
    zero_raw = int(sim.servo.to_raw(0.0))
    for s, gamma in zip(samples, schedule):
        goal = ax12.raw_from_gamma(float(gamma), zero_raw)
        assert s.motor.present_position_raw == goal
        assert s.gamma_measured == pytest.approx(ax12.gamma_from_raw(goal, zero_raw), abs=1e-12)
        assert s.motor.error_bits == 0
    assert np.all(np.diff([s.gamma_measured for s in samples]) > 0)
    assert math.isclose(samples[-1].gamma_measured, sim.gamma_stop, abs_tol=ax12.RAD_PER_UNIT)
    # Diagnostics of what the load did (reported by `pytest -rA -s`).
    print(
        f"\nunder load: {motor.late_replies} late replies waited out, {motor.retries_used} resends, "
        f"{motor.stale_replies_binned} stale replies binned"
    )
