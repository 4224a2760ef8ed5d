"""Shared fixtures: contract messages built the way the services build them, hermetic Zenoh."""

from __future__ import annotations

import numpy as np
import pytest

from lelsonar import SCHEMA_VERSION, codec
from lelsonar.v1 import scan_pb2


def make_scan_start(scanner_id: str = "s1", scan_id: int = 7, steps: int = 5) -> codec.ScanStart:
    start = scan_pb2.ScanStart(
        schema_version=SCHEMA_VERSION, scanner_id=scanner_id, scan_id=scan_id, start_time_ns=1_700_000_000_000_000_000,
        software_version="test", radial_offset=0.03, gamma_start=np.deg2rad(-10), gamma_stop=np.deg2rad(110),
        steps=steps, direction=scan_pb2.ROTATION_DIRECTION_INCREASING, sound_speed=343.2, air_temperature=293.15,
        sample_rate=200_000.0, window_samples=64,
    )
    start.rotation_axis.x = 1.0
    for i, x in enumerate((-0.12, -0.04, 0.04, 0.12)):
        c = start.capsules.add(capsule_id=i)
        c.position.x, c.position.y = x, 0.03
        c.boresight.y = 1.0
    e = start.energy_model
    e.phi0, e.phi1, e.phi2, e.valid_min_range, e.valid_max_range = 0.1, 0.2, 0.05, 0.9, 1.8
    e.distance_unit, e.energy_unit = "m", "V^2 s"
    return start


def make_sample(step: int = 0, scanner_id: str = "s1", scan_id: int = 7, n_samples: int = 64,
                seed: int = 0) -> codec.Sample:
    rng = np.random.default_rng(seed + step)
    gamma = np.deg2rad(-10 + 2 * step)
    s = scan_pb2.Sample(schema_version=SCHEMA_VERSION, scanner_id=scanner_id, scan_id=scan_id, step=step,
                        acquisition_time_ns=1_700_000_000_000_000_000 + step * 10_000_000,
                        gamma_commanded=gamma, gamma_measured=gamma + 1e-3)
    s.motor.present_position_raw, s.motor.voltage, s.motor.temperature = 512, 12.0, 310.0
    for i in range(4):
        d = 1.5 + 0.01 * i
        r = s.sensors.add(capsule_id=i, echo_valid=True, time_of_flight=2 * d / 343.2, distance=d)
        r.waveform.CopyFrom(codec.pack_waveform(rng.normal(0, 0.1, n_samples).astype(np.float32), 200_000.0))
    return s


@pytest.fixture
def zenoh_socket(tmp_path):
    """A unix-socket path private to this test (no TCP port, no multicast)."""
    return tmp_path / "z.sock"
