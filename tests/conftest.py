"""Shared fixtures: contract messages built the way the services build them, hermetic Zenoh."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

from lelsonar import SCHEMA_VERSION, codec
from lelsonar.v1 import scan_pb2


def make_scan_start(scanner_id: str = "s1", scan_id: int = 7, steps: int = 5) -> codec.ScanStart:
    start = scan_pb2.ScanStart(
        schema_version=SCHEMA_VERSION,
        scanner_id=scanner_id,
        scan_id=scan_id,
        start_time_ns=1_700_000_000_000_000_000,
        software_version="test",
        radial_offset=0.03,
        gamma_start=np.deg2rad(-10),
        gamma_stop=np.deg2rad(110),
        steps=steps,
        direction=scan_pb2.ROTATION_DIRECTION_INCREASING,
        sound_speed=343.2,
        air_temperature=293.15,
        sample_rate=200_000.0,
        window_samples=64,
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


def make_sample(
    step: int = 0, scanner_id: str = "s1", scan_id: int = 7, n_samples: int = 64, seed: int = 0
) -> codec.Sample:
    rng = np.random.default_rng(seed + step)
    gamma = np.deg2rad(-10 + 2 * step)
    s = scan_pb2.Sample(
        schema_version=SCHEMA_VERSION,
        scanner_id=scanner_id,
        scan_id=scan_id,
        step=step,
        acquisition_time_ns=1_700_000_000_000_000_000 + step * 10_000_000,
        gamma_commanded=gamma,
        gamma_measured=gamma + 1e-3,
    )
    s.motor.present_position_raw, s.motor.voltage, s.motor.temperature = 512, 12.0, 310.0
    for i in range(4):
        d = 1.5 + 0.01 * i
        r = s.sensors.add(capsule_id=i, echo_valid=True, time_of_flight=2 * d / 343.2, distance=d)
        r.waveform.CopyFrom(codec.pack_waveform(rng.normal(0, 0.1, n_samples).astype(np.float32), 200_000.0))
    return s


class QuietObserver:
    """A reconstruction service observer that ignores everything: a test's observer overrides what it watches."""

    def scan_started(self, scan) -> None:
        pass

    def step(self, *args) -> None:
        pass

    def estimate(self, scan, message, results, partial) -> None:
        pass

    def event(self, level: str, text: str, time_ns: int | None = None) -> None:
        pass


@pytest.fixture
def zenoh_socket(tmp_path):
    """A unix-socket path private to this test (no TCP port, no multicast)."""
    return tmp_path / "z.sock"


def simulated_messages(
    preset_name: str = "paper-test1",
    seed: int = 0,
    *,
    scanner_id: str = "s1",
    scan_id: int = 1,
    steps: int | None = None,
) -> list:
    """ScanStart, Samples and ScanEnd of one simulated scan, built as the acquisition service builds them."""
    import dataclasses

    from lelsonar.acquire import messages
    from lelsonar.acquire.backends import SimScanner
    from lelsonar.acquire.scan_loop import gamma_schedule
    from lelsonar.sim import preset
    from lelsonar.sim.calibrate import default_energy_model

    sim = preset(preset_name)
    if steps is not None:
        sim = dataclasses.replace(sim, steps=steps)
    scanner = SimScanner(sim, seed)
    schedule = gamma_schedule(sim.gamma_start, sim.gamma_stop, sim.steps)
    out = [
        messages.scan_start(
            scanner_id, scan_id, 1_700_000_000_000_000_000, scanner.info, schedule, default_energy_model()
        )
    ]
    for step, gamma in enumerate(schedule):
        out.append(
            messages.sample(scanner_id, scan_id, step, float(gamma), scanner.measure(step, float(gamma)), scanner.info)
        )
    out.append(
        messages.scan_end(
            scanner_id,
            scan_id,
            out[-1].acquisition_time_ns + 1,
            complete=True,
            reason="",
            steps_planned=len(schedule),
            samples_sent=len(schedule),
            echoes_missing=0,
        )
    )
    return out


def estimate_only(msg: codec.Reconstruction) -> bytes:
    """An estimate's bytes without what the clock stamps on it (its time, its timings): what must match bit for bit."""
    m = codec.Reconstruction()
    m.CopyFrom(msg)
    for f in ("stamp_ns", "timings"):
        m.ClearField(f)
    return m.SerializeToString()


def type_name(message) -> str:
    return message.DESCRIPTOR.full_name


#: A busy loop that bounds itself (so a crashed test run cannot leave it behind) and says when it spins.
_HOG = (
    "import sys, time\nend = time.monotonic() + {limit}\nprint('spinning', flush=True)\n"
    "while time.monotonic() < end: pass\n"
)


@pytest.fixture
def cpu_hog():
    """Every core this process may use saturated by another process, for this test only.

    One busy-looping Python process per core (bounded to 120 s on its own), started before the
    test body and killed when it ends.  Device timing must hold on a loaded host.
    """
    procs = [
        subprocess.Popen([sys.executable, "-c", _HOG.format(limit=120)], stdout=subprocess.PIPE, text=True)
        for _ in range(len(os.sched_getaffinity(0)))
    ]
    try:
        for proc in procs:
            assert proc.stdout.readline().strip() == "spinning"  # it is on a core now
        yield len(procs)
    finally:
        for proc in procs:
            proc.kill()
            proc.wait()
            proc.stdout.close()


def scene_truth(preset_name: str = "paper-test1") -> dict[str, tuple[np.ndarray, float]]:
    """Label → (unit normal, offset h) of each wall of the preset's scene: ``n · x = h``."""
    from lelsonar.sim import preset

    return {
        p.label: (np.asarray(p.normal, dtype=float), float(np.dot(p.center, p.normal)))
        for p in preset(preset_name).scene.panels
    }


def assert_matches_the_scene(estimate: codec.Reconstruction, method: str, preset_name: str = "paper-test1") -> None:
    """The estimate of ``method`` against the scene's truth, within bounds derived from the simulator's
    noise model (5σ of the estimator's error if it averages the inliers' noise):

    * a point's error across the wall, σ_p: the comparator's range jitter (``receiver.tof_jitter``),
      and the servo's angle error (``servo.position_error``) times the longest range (the far corner);
      cycle slips and corner echoes are outliers, which the method must reject (it reports inliers);
    * offset h: σ_p / √n_inliers (the mean of n independent errors);
    * normal, per in-plane axis: σ_p / (√n_inliers · s), s the points' spread along that axis: along
      the rotation axis x only the four capsules spread them (RMS of their x); across it, the beams'
      hits of the wall as γ sweeps (z = h_a tan γ before the corner, y = h_b / tan γ after);
    * the critical angle: the corner is at γ = atan(h_b / h_a); a step is within one step spacing.
    """
    from lelsonar.sim import preset

    cfg = preset(preset_name)
    truth = scene_truth(preset_name)
    far = float(np.hypot(truth["a"][1], truth["b"][1]))
    sigma_p = float(np.hypot(cfg.receiver.tof_jitter, far * cfg.servo.position_error))
    spread_x = float(np.sqrt(np.mean(np.square(cfg.geometry.capsule_x))))
    corner = np.arctan2(truth["b"][1], truth["a"][1])
    gamma = np.linspace(cfg.gamma_start, cfg.gamma_stop, cfg.steps)
    across = {
        "a": (2, np.std(truth["a"][1] * np.tan(gamma[gamma < corner]))),  # z on wall a
        "b": (1, np.std(truth["b"][1] / np.tan(gamma[gamma > corner]))),
    }  # y on wall b
    planes = {p.label: p for p in estimate.planes if p.method == method}
    assert set(planes) == set(truth), f"{method} estimated {sorted(planes)}; failures: {list(estimate.failures)}"
    for label, (normal, h) in truth.items():
        p = planes[label]
        n = np.array([p.normal.x, p.normal.y, p.normal.z])
        root_n = np.sqrt(p.inlier_count)
        axis, spread = across[label]
        for k, s in ((0, spread_x), (axis, spread)):
            assert abs(n[k] - normal[k]) <= 5 * sigma_p / (root_n * s), f"plane {label}: normal {n} (axis {k})"
        assert abs(p.offset - h) <= 5 * sigma_p / root_n, f"plane {label}: h off by {(p.offset - h) * 1e3:.2f} mm"
    spacing = abs(cfg.gamma_stop - cfg.gamma_start) / (cfg.steps - 1)
    assert estimate.HasField("critical_step") and abs(estimate.critical_angle - corner) <= spacing
    # The corner edge is where the true walls meet: along x (n_a × n_b), through (y, z) = (h_a, h_b) for
    # the paper's right-angled corner.  Both planes' bounds add: their tilts (with the far corner as
    # lever) and offsets.
    n_min = min(planes[label].inlier_count for label in truth)
    tilt_bound = 5 * sigma_p / (np.sqrt(n_min) * spread_x)
    edge = estimate.corner_edge
    direction = np.array([edge.direction.x, edge.direction.y, edge.direction.z])
    along = np.cross(truth["a"][0], truth["b"][0])
    assert np.arccos(min(1.0, abs(float(direction @ along)))) <= 2 * tilt_bound
    point = np.array([edge.point.x, edge.point.y, edge.point.z])
    for normal, h in truth.values():
        assert abs(float(point @ normal) - h) <= 2 * (5 * sigma_p / np.sqrt(n_min) + far * tilt_bound)


class Collect:
    """A ScanOutput stand-in that keeps the messages."""

    def __init__(self) -> None:
        self.messages: list = []

    def emit(self, message) -> None:
        self.messages.append(message)

    def log(self, level: str, text: str) -> None:
        pass


@pytest.fixture(scope="session")
def two_scans(tmp_path_factory):
    """Two simulated paper scans (scan ids 1 and 2), each recorded to its own MCAP file: read them, never write."""
    from lelsonar.log import recording

    d = tmp_path_factory.mktemp("two_scans")
    paths = []
    for i in (1, 2):
        path = d / f"scan{i}.mcap"
        with recording.McapRecorder(path) as rec:
            for m in simulated_messages("paper-test1", seed=i, scan_id=i):
                rec.write(m)
        paths.append(path)
    return paths
