"""Contract messages built from scanner measurements (no I/O)."""

from __future__ import annotations

import numpy as np

import lelsonar
from lelsonar import SCHEMA_VERSION, codec
from lelsonar.acquire.scanner import ScannerInfo, StepMeasurement
from lelsonar.energy_model import EnergyModel
from lelsonar.signal.energy import waveform_energy
from lelsonar.v1 import scan_pb2


def scan_start(
    scanner_id: str,
    scan_id: int,
    start_time_ns: int,
    info: ScannerInfo,
    gamma_schedule: np.ndarray,
    energy_model: EnergyModel,
) -> codec.ScanStart:
    msg = scan_pb2.ScanStart(
        schema_version=SCHEMA_VERSION,
        scanner_id=scanner_id,
        scan_id=scan_id,
        start_time_ns=start_time_ns,
        software_version=lelsonar.__version__,
        radial_offset=info.geometry.radial_offset,
        gamma_start=float(gamma_schedule[0]),
        gamma_stop=float(gamma_schedule[-1]),
        steps=len(gamma_schedule),
        direction=(
            scan_pb2.ROTATION_DIRECTION_INCREASING
            if gamma_schedule[-1] >= gamma_schedule[0]
            else scan_pb2.ROTATION_DIRECTION_DECREASING
        ),
        sound_speed=info.sound_speed,
        air_temperature=info.air_temperature,
        sample_rate=info.sample_rate,
        window_samples=info.window_samples,
        device=info.device,
    )
    msg.rotation_axis.x = 1.0
    for i, (x, y, z) in enumerate(info.geometry.capsules_in_array_frame()):
        c = msg.capsules.add(capsule_id=i)
        c.position.x, c.position.y, c.position.z = float(x), float(y), float(z)
        c.boresight.y = 1.0
    e = msg.energy_model
    e.phi0, e.phi1, e.phi2 = energy_model.phi0, energy_model.phi1, energy_model.phi2
    e.valid_min_range, e.valid_max_range = energy_model.d_min, energy_model.d_max
    e.distance_unit, e.energy_unit = "m", "V^2 s"
    if info.pose is not None:
        msg.pose.CopyFrom(info.pose)
    return msg


def sample(
    scanner_id: str,
    scan_id: int,
    step: int,
    gamma_commanded: float,
    shot: StepMeasurement,
    info: ScannerInfo,
    *,
    int16_scale: float | None = None,
) -> codec.Sample:
    """One ``Sample``; ranges are ``c · tof / 2`` with the configured speed of sound."""
    msg = scan_pb2.Sample(
        schema_version=SCHEMA_VERSION,
        scanner_id=scanner_id,
        scan_id=scan_id,
        step=step,
        acquisition_time_ns=shot.acquisition_time_ns,
        gamma_commanded=gamma_commanded,
        gamma_measured=shot.gamma_measured,
    )
    m = shot.motor
    msg.motor.present_position_raw = m.present_position_raw
    msg.motor.load, msg.motor.voltage, msg.motor.temperature, msg.motor.error_bits = (
        m.load,
        m.voltage,
        m.temperature,
        m.error_bits,
    )
    for i, (tof, wave) in enumerate(zip(shot.time_of_flight, shot.waveforms)):
        valid = bool(np.isfinite(tof) and tof > 0)
        r = msg.sensors.add(capsule_id=i, echo_valid=valid)
        if valid:
            r.time_of_flight = float(tof)
            r.distance = float(info.sound_speed * tof / 2.0)
        r.waveform.CopyFrom(codec.pack_waveform(wave, info.sample_rate, shot.t0, int16_scale=int16_scale))
    # Each waveform's energy (eq. 10) on the samples as packed, so that a reconstructor need not integrate
    # every waveform again (it checks these against the waveforms, in batches).
    msg.sensor_energy.extend(
        float(waveform_energy(codec.unpack_waveform(r.waveform, validated=True), info.sample_rate)) for r in msg.sensors
    )
    return msg


def scan_end(
    scanner_id: str,
    scan_id: int,
    end_time_ns: int,
    *,
    complete: bool,
    reason: str,
    steps_planned: int,
    samples_sent: int,
    echoes_missing: int,
) -> codec.ScanEnd:
    return scan_pb2.ScanEnd(
        schema_version=SCHEMA_VERSION,
        scanner_id=scanner_id,
        scan_id=scan_id,
        end_time_ns=end_time_ns,
        status=scan_pb2.SCAN_STATUS_COMPLETE if complete else scan_pb2.SCAN_STATUS_ABORTED,
        reason=reason,
        steps_planned=steps_planned,
        samples_sent=samples_sent,
        echoes_missing=echoes_missing,
    )
