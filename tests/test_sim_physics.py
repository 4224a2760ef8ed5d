"""Simulator building blocks: configuration, scene geometry, acoustics, echoes, servo, waveforms."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from lelsonar.errors import ConfigError
from lelsonar.sim import (
    Acoustics,
    EchoSource,
    Panel,
    Receiver,
    Scene,
    Servo,
    SimConfig,
    echo_table,
    piston_directivity,
    preset,
    simulate_scan,
    simulate_step,
    sound_speed,
)
from lelsonar.sim.config import AX12_DEG_PER_UNIT


def quiet(cfg: SimConfig, **receiver) -> SimConfig:
    """The same config with the given receiver fields replaced."""
    return dataclasses.replace(cfg, receiver=dataclasses.replace(cfg.receiver, **receiver))


# ---------------------------------------------------------------------------- acoustics
def test_sound_speed_matches_design_notes():
    assert sound_speed(293.15) == pytest.approx(343.2, abs=0.05)
    # +0.17 % per kelvin near room temperature
    assert sound_speed(294.15) / sound_speed(293.15) - 1 == pytest.approx(0.0017, abs=0.0002)


def test_piston_two_way_half_power_angle_for_5mm_is_26_degrees():
    ka = Acoustics().wavenumber(sound_speed(293.15)) * 0.005
    theta = np.radians(np.linspace(0, 60, 60001))
    two_way = piston_directivity(theta, ka) ** 2
    half_angle = np.degrees(theta[np.argmax(two_way < 0.5)])
    assert half_angle == pytest.approx(26.0, abs=1.0)
    assert piston_directivity(np.array([0.0]), ka)[0] == pytest.approx(1.0)


def test_default_beam_keeps_plane_a_to_30_degrees_and_has_a_first_null():
    cfg = preset("paper-test1")
    lobe = cfg.acoustics.main_lobe(cfg.sound_speed)
    assert math.radians(40) < lobe < math.radians(55)
    ka = cfg.acoustics.wavenumber(cfg.sound_speed) * cfg.acoustics.capsule_radius
    assert piston_directivity(np.radians(30.0), ka) ** 2 > 0.1  # −10 dB: still usable for the arc


# ---------------------------------------------------------------------------- scene
def test_default_l_corner_geometry():
    scene = Scene.l_corner()
    a, b = scene.panels
    assert np.allclose(a.normal, [0, 1, 0]) and a.offset == pytest.approx(1.57)
    assert np.allclose(b.normal, [0, 0, 1]) and b.offset == pytest.approx(1.06)
    edge = scene.edges[0]
    assert np.allclose(edge.direction, [1, 0, 0])
    assert np.allclose(edge.point, [0, 1.57, 1.06])
    assert edge.opening == pytest.approx(math.pi / 2)
    assert math.degrees(scene.critical_angle()) == pytest.approx(math.degrees(math.atan2(1.06, 1.57)))
    # both panels end on the edge
    assert np.isclose(a.corners()[:, 2].max(), 1.06) and np.isclose(b.corners()[:, 1].max(), 1.57)


def test_tilted_l_corner_normals_follow_the_tilts():
    t = math.radians(4.0)
    yawed = Scene.l_corner(tilt_a_z=t)
    assert np.allclose(yawed.panels[0].normal, [-math.sin(t), math.cos(t), 0])
    assert yawed.edges[0].opening == pytest.approx(math.pi / 2)  # still a right corner
    assert abs(yawed.edges[0].direction[1]) == pytest.approx(math.sin(t), abs=1e-9)  # the edge leaves x
    opened = Scene.l_corner(tilt_a_x=t)
    assert opened.edges[0].opening == pytest.approx(math.pi / 2 + t)
    rolled = Scene.l_corner(tilt_a_x=t, tilt_b_x=t)
    assert rolled.edges[0].opening == pytest.approx(math.pi / 2)
    for scene in (yawed, opened, rolled):  # the panels still share the edge point
        assert np.allclose(scene.edges[0].point @ np.array(scene.panels[0].normal), scene.panels[0].offset)
        assert np.allclose(scene.edges[0].point @ np.array(scene.panels[1].normal), scene.panels[1].offset)


@pytest.mark.parametrize(
    "make",
    [
        lambda: Panel(center=(0, 1, 0), normal=(0, 2, 0), u_axis=(1, 0, 0), width=1, height=1),
        lambda: Panel(center=(0, 1, 0), normal=(0, 1, 0), u_axis=(0, 1, 0), width=1, height=1),
        lambda: Panel(center=(0, -1, 0), normal=(0, 1, 0), u_axis=(1, 0, 0), width=1, height=1),
        lambda: Panel(center=(0, 1, 0), normal=(0, 1, 0), u_axis=(1, 0, 0), width=0, height=1),
        lambda: Panel(center=(0, 1, 0), normal=(0, 1, 0), u_axis=(1, 0, 0), width=1, height=1, reflectivity=1.5),
        lambda: Scene(panels=(Scene.wall(1.0).panels[0], Scene.wall(2.0).panels[0]), corners=((0, 1),)),
        lambda: Scene(panels=Scene.wall(1.0).panels, corners=((0, 1),)),
        lambda: Scene.l_corner(distance_a=-1.0),
        lambda: SimConfig(steps=0),
        lambda: SimConfig(temperature=20.0),  # Celsius by mistake: the field is kelvin
        lambda: SimConfig(gamma_start=1.0, gamma_stop=0.5),
        lambda: SimConfig(gamma_start=math.radians(-170)),  # beyond the AX-12's 300°
        lambda: SimConfig(sample_rate=50_000.0),
        lambda: Acoustics(capsule_radius=0.0),
        lambda: Receiver(adc_bits=40),
        lambda: Servo(position_error=-1.0),
        lambda: preset("no-such-preset"),
    ],
)
def test_invalid_configuration_raises_config_error(make):
    with pytest.raises(ConfigError):
        make()


def test_config_is_frozen():
    cfg = preset("paper-test1")
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.steps = 3  # type: ignore[misc]


# ---------------------------------------------------------------------------- echoes and TOF
def test_face_on_range_is_the_perpendicular_distance():
    cfg = quiet(preset("paper-test1"), tof_jitter=0.0, cycle_slip_probability=0.0)
    step = simulate_step(cfg, 0.0, np.random.default_rng(0))
    assert np.all(step.echo_source == EchoSource.PLANE_A)
    assert np.allclose(step.distance, 1.57 - cfg.geometry.radial_offset, atol=1e-9)
    # at 20° the range of plane a's mirror echo is still perpendicular, not along the beam
    g = math.radians(20.0)
    step = simulate_step(cfg, g, np.random.default_rng(0))
    assert np.all(step.echo_source == EchoSource.PLANE_A)
    assert np.allclose(step.distance, 1.57 - cfg.geometry.radial_offset * math.cos(g), atol=1e-9)


def test_corner_range_is_the_distance_to_the_edge():
    cfg = quiet(preset("paper-test1"), tof_jitter=0.0, cycle_slip_probability=0.0)
    g = cfg.scene.critical_angle()
    step = simulate_step(cfg, g, np.random.default_rng(0))
    assert np.all(step.echo_source == EchoSource.CORNER)
    edge_range = math.hypot(1.57, 1.06) - cfg.geometry.radial_offset
    assert np.allclose(step.distance, edge_range, atol=1e-9)
    assert math.hypot(1.57, 1.06) == pytest.approx(1.894, abs=1e-3)


def test_no_echo_gives_nan_and_none():
    cfg = dataclasses.replace(preset("paper-test1"), scene=Scene.wall(1.2))
    step = simulate_step(cfg, math.radians(80.0), np.random.default_rng(0))  # wall normal far outside the beam
    assert np.all(np.isnan(step.tof)) and np.all(np.isnan(step.distance))
    assert np.all(step.echo_source == EchoSource.NONE)


def test_mirror_echo_needs_its_foot_on_the_panel():
    small = Panel(center=(0.0, 1.2, 0.6), normal=(0.0, 1.0, 0.0), u_axis=(1.0, 0.0, 0.0), width=1.0, height=0.4)
    cfg = dataclasses.replace(preset("paper-test1"), scene=Scene(panels=(small,)))
    table = echo_table(cfg, np.array([0.0, math.radians(30.0)]))
    # the perpendicular from the capsules (z ≈ 0…0.015 m) misses a panel spanning z 0.4…0.8 m
    assert np.all(table.amplitude[:, :, 0] == 0) and np.all(np.isnan(table.range[:, :, 0]))
    # but at 30° the boresight does hit it: a weak diffuse echo along the beam
    assert np.all(table.amplitude[1, :, -1] > 0)
    assert np.allclose(
        table.range[1, :, -1],
        (1.2 - cfg.geometry.radial_offset * math.cos(math.radians(30))) / math.cos(math.radians(30)),
    )


def test_tof_noise_is_jitter_plus_half_wavelength_slips():
    cfg = quiet(preset("paper-test2"), tof_jitter=0.002, cycle_slip_probability=0.0)
    scan = simulate_scan(cfg, seed=1, with_waveforms=False)
    err = scan.distance - scan.truth.echo_range
    assert np.nanstd(err) == pytest.approx(0.002, rel=0.15)
    cfg = quiet(cfg, tof_jitter=0.0, cycle_slip_probability=0.5)
    scan = simulate_scan(cfg, seed=1, with_waveforms=False)
    err = (scan.distance - scan.truth.echo_range)[np.isfinite(scan.distance)]
    half_wave = cfg.sound_speed / cfg.acoustics.frequency / 2
    assert half_wave == pytest.approx(0.00429, abs=1e-5)
    levels = np.round(err / half_wave)
    assert np.allclose(err, levels * half_wave, atol=1e-9)
    assert set(np.unique(levels)) == {-1.0, 0.0, 1.0}
    assert 0.35 < np.mean(levels != 0) < 0.65


def test_temperature_changes_the_time_of_flight_not_the_range():
    base = quiet(preset("paper-test1"), tof_jitter=0.0, cycle_slip_probability=0.0)
    cold = simulate_step(dataclasses.replace(base, temperature=273.15), 0.0, np.random.default_rng(0))
    warm = simulate_step(dataclasses.replace(base, temperature=303.15), 0.0, np.random.default_rng(0))
    assert np.allclose(cold.distance, warm.distance)
    assert np.allclose(cold.tof / warm.tof, sound_speed(303.15) / sound_speed(273.15))


# ---------------------------------------------------------------------------- servo
def test_measured_gamma_is_quantised_like_the_ax12():
    cfg = preset("paper-test1")
    scan = simulate_scan(cfg, seed=0, with_waveforms=False)
    unit = math.radians(AX12_DEG_PER_UNIT)
    units = (scan.gamma_measured - cfg.servo.mount_offset) / unit
    assert np.allclose(units, np.round(units), atol=1e-9)
    assert np.all(np.abs(scan.gamma_measured - scan.gamma_commanded) <= unit / 2 + 1e-12)
    assert np.array_equal(cfg.servo.to_raw(scan.gamma_measured), scan.gamma_raw)
    assert scan.gamma_raw.min() >= 0 and scan.gamma_raw.max() <= 1023
    assert cfg.servo.to_raw(0.0) == 512
    noisy = dataclasses.replace(cfg, servo=Servo(position_error=math.radians(0.3)))
    scan = simulate_scan(noisy, seed=0, with_waveforms=False)
    assert np.any(np.abs(scan.gamma_measured - scan.gamma_commanded) > unit)
    units = scan.gamma_measured / unit
    assert np.allclose(units, np.round(units), atol=1e-9)


# ---------------------------------------------------------------------------- waveforms
def test_waveforms_are_adc_codes_in_volts_with_the_echo_at_its_arrival():
    cfg = preset("paper-test1")
    scan = simulate_scan(cfg, seed=0)
    assert scan.waveforms.dtype == np.float32
    assert scan.waveforms.shape == (184, 4, cfg.window_samples)
    lsb = cfg.receiver.adc_lsb
    codes = scan.waveforms.astype(np.float64) / lsb
    assert np.allclose(codes, np.round(codes), atol=1e-3)
    assert np.abs(scan.waveforms).max() <= cfg.receiver.adc_range
    # step nearest γ = 0: the envelope peaks one rise time after the plane-a arrival
    k = int(np.argmin(np.abs(scan.gamma_measured)))
    fs = cfg.sample_rate
    blank = int(cfg.receiver.blanking_time * fs)
    peak = blank + np.argmax(np.abs(scan.waveforms[k, :, blank:]), axis=-1)
    expected = (2 * scan.truth.echo_range[k] / cfg.sound_speed + cfg.receiver.envelope_time) * fs
    assert np.all(np.abs(peak - expected) < 10)  # within a quarter of the envelope width
    # the ring-down is at t = 0
    assert np.abs(scan.waveforms[k, :, :40]).max() > 10 * np.abs(scan.waveforms[k, :, 2500:]).max()


def test_same_seed_same_bytes_other_seed_other_bytes():
    cfg = preset("tilted")
    a, b, c = simulate_scan(cfg, seed=7), simulate_scan(cfg, seed=7), simulate_scan(cfg, seed=8)
    for field in ("tof", "distance", "waveforms", "gamma_measured"):
        assert getattr(a, field).tobytes() == getattr(b, field).tobytes()
    assert a.waveforms.tobytes() != c.waveforms.tobytes()
    assert a.tof.tobytes() != c.tof.tobytes()
    s1 = simulate_step(cfg, 0.3, np.random.default_rng(5))
    s2 = simulate_step(cfg, 0.3, np.random.default_rng(5))
    assert s1.waveforms.tobytes() == s2.waveforms.tobytes() and s1.waveforms.shape == (4, cfg.window_samples)


def test_step_and_scan_share_the_physics():
    cfg = quiet(preset("paper-test1"), tof_jitter=0.0, cycle_slip_probability=0.0)
    scan = simulate_scan(cfg, seed=0, with_waveforms=False)
    for k in (0, 40, scan.truth.critical_step, 150):
        step = simulate_step(cfg, float(scan.truth.gamma_true[k]), np.random.default_rng(0))
        assert np.array_equal(step.echo_source, scan.truth.echo_source[k])
        assert np.allclose(step.distance, scan.distance[k], equal_nan=True)
