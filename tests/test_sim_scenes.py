"""Scene families: every draw valid, as specified, deterministic per seed."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from lelsonar.errors import ConfigError
from lelsonar.sim import EchoSource, Receiver, SimConfig, SimulatedWallShots, simulate_scan
from lelsonar.sim.scenes import (
    FAMILIES,
    SceneParams,
    build_config,
    calibrated_energy_model,
    check_config,
    draw_scene,
    parse_families,
    required_window_samples,
    sample_scene,
)

SEEDS = range(6)
DEG = math.pi / 180


def _angle(a, b) -> float:
    return math.degrees(math.acos(float(np.clip(np.dot(a, b), -1, 1))))


@pytest.mark.parametrize("family", FAMILIES)
def test_every_draw_is_valid_and_deterministic(family):
    for seed in SEEDS:
        draw = draw_scene(family, seed)
        assert check_config(draw.config) == []
        again = draw_scene(family, seed)
        assert again.params == draw.params and again.config == draw.config
        assert draw.description.startswith(f"{family} #{seed}: ")
        cfg = draw.config
        crit = cfg.scene.critical_angle()
        assert cfg.gamma_start + 5 * DEG <= crit <= cfg.gamma_stop - 5 * DEG
        assert cfg.window_samples >= max(3500, required_window_samples(cfg))
    assert len({draw_scene(family, s).params for s in SEEDS}) == len(SEEDS)


def test_families_are_independent_streams_and_sample_scene_uses_the_generator():
    a = sample_scene("mixed", np.random.default_rng(5))
    b = sample_scene("mixed", np.random.default_rng(5))
    assert a == b
    assert draw_scene("distance", 0).params.distance_a != draw_scene("mixed", 0).params.distance_a


def _params(family):
    return [draw_scene(family, s).params for s in SEEDS]


def test_paper_family_keeps_the_papers_geometry_and_varies_noise():
    for draw in (draw_scene("paper", s) for s in SEEDS):
        a, b = draw.config.scene.panels
        assert a.offset == pytest.approx(1.57) and b.offset == pytest.approx(1.06)
        assert _angle(a.normal, (0, 1, 0)) < 1e-9 and _angle(b.normal, (0, 0, 1)) < 1e-9
        assert draw.config.steps in (184, 220)
        assert math.degrees(draw.config.gamma_start) == pytest.approx(-10)
        assert 0.001 <= draw.config.receiver.tof_jitter <= 0.003
    assert len({p.tof_jitter for p in _params("paper")}) == len(SEEDS)


def test_distance_family_draws_each_wall_in_range():
    ds = []
    for draw in (draw_scene("distance", s) for s in range(20)):
        a, b = draw.config.scene.panels
        assert 0.6 <= a.offset <= 2.6 and 0.6 <= b.offset <= 2.6
        ds.append((a.offset, b.offset))
    ds = np.array(ds)
    assert ds.min() < 1.0 and ds.max() > 2.2  # broad, not clustered near the paper's L
    assert abs(np.corrcoef(ds[:, 0], ds[:, 1])[0, 1]) < 0.7  # drawn independently


def test_far_walls_get_a_window_that_holds_the_corner_echo():
    cfg = build_config(SceneParams(distance_a=2.6, distance_b=2.6))
    assert check_config(cfg) == []
    assert cfg.window_samples > 3500
    scan = simulate_scan(cfg, seed=0, with_waveforms=False)
    corner = scan.truth.echo_source == EchoSource.CORNER
    assert corner.sum() > 0
    assert np.nanmax(scan.truth.echo_range) == pytest.approx(2.6 * math.sqrt(2) - 0.03, abs=0.02)


def test_tilted_family_tilts_each_plane_about_two_axes_up_to_6_degrees():
    axes = {"a": (0, 1, 0), "b": (0, 0, 1)}
    seen = []
    for draw in (draw_scene("tilted", s) for s in SEEDS):
        p = draw.params
        tilts = np.array([p.tilt_a_x, p.tilt_a_z, p.tilt_b_x, p.tilt_b_y])
        assert np.all(np.abs(tilts) <= 6 * DEG) and np.all(tilts != 0)
        seen.append(tilts)
        a, b = draw.config.scene.panels
        # Plane a's normal is ŷ turned about x then z; b's is ẑ turned about x then y.
        na = np.array(a.normal)
        assert math.degrees(math.asin(na[2])) == pytest.approx(math.degrees(p.tilt_a_x), abs=1e-6)
        assert _angle(na, axes["a"]) <= math.hypot(6, 6) + 1e-9
        assert _angle(np.array(b.normal), axes["b"]) <= math.hypot(6, 6) + 1e-9
        assert a.offset == pytest.approx(np.dot(a.normal, (0, 1.57, 1.06)))  # turned about the edge point
    assert np.ptp(np.array(seen), axis=0).min() > 3 * DEG  # every axis varies


def test_partial_family_sweeps_start_late_or_stop_early_and_contain_the_corner():
    starts, stops = [], []
    for draw in (draw_scene("partial", s) for s in range(20)):
        cfg = draw.config
        assert -10 <= math.degrees(cfg.gamma_start) <= 15 and 70 <= math.degrees(cfg.gamma_stop) <= 110
        starts.append(math.degrees(cfg.gamma_start))
        stops.append(math.degrees(cfg.gamma_stop))
        g = cfg.gamma_commanded()
        assert g.min() < cfg.scene.critical_angle() < g.max()
    assert min(starts) < 0 < max(starts) and min(stops) < 90 < max(stops)


@pytest.mark.parametrize(
    ("family", "field", "lo", "hi"),
    [
        ("steps", "steps", 90, 400),
        ("beam", "capsule_radius", 0.006, 0.012),
        ("corner", "corner_gain", 1.0, 2.5),
        ("noise", "tof_jitter", 0.001, 0.006),
        ("noise", "amplitude_noise", 0.01, 0.05),
    ],
)
def test_one_parameter_families_draw_in_range(family, field, lo, hi):
    values = [getattr(p, field) for p in _params(family)]
    assert all(lo <= v <= hi for v in values) and len(set(values)) > 1
    cfgs = [draw_scene(family, s).config for s in SEEDS]
    where = {
        "steps": lambda c: c.steps,
        "capsule_radius": lambda c: c.acoustics.capsule_radius,
        "corner_gain": lambda c: c.acoustics.corner_gain,
        "tof_jitter": lambda c: c.receiver.tof_jitter,
        "amplitude_noise": lambda c: c.receiver.amplitude_noise,
    }[field]
    assert [where(c) for c in cfgs] == values


def test_mixed_family_varies_everything_at_once():
    ps = _params("mixed")
    for p in ps:
        assert 0.6 <= p.distance_a <= 2.6 and 0.6 <= p.distance_b <= 2.6
        assert 90 <= p.steps <= 400 and 0.006 <= p.capsule_radius <= 0.012 and 1 <= p.corner_gain <= 2.5
        assert max(abs(p.tilt_a_x), abs(p.tilt_b_y)) <= 6 * DEG
    for f in dataclasses.fields(SceneParams):
        assert len({getattr(p, f.name) for p in ps}) > 1, f.name


def test_unknown_family_and_parse():
    with pytest.raises(ConfigError):
        draw_scene("cave", 0)
    with pytest.raises(ConfigError):
        parse_families(["paper", "cave"])
    assert parse_families(["all"]) == FAMILIES
    assert parse_families(["noise", "paper", "noise"]) == ("noise", "paper")
    with pytest.raises(ConfigError):
        SceneParams(gamma_start=1.0, gamma_stop=0.5)


def test_amplitude_noise_scales_echo_energy_and_defaults_to_off():
    assert Receiver().amplitude_noise == 0.0
    with pytest.raises(ConfigError):
        Receiver(amplitude_noise=-0.1)

    def energies(sigma):
        cfg = SimConfig(receiver=dataclasses.replace(Receiver(), amplitude_noise=sigma, noise_std=0.0))
        shots = SimulatedWallShots(cfg, np.random.default_rng(1))
        return np.array([shots.total_energy(1.2) for _ in range(40)])

    quiet, noisy = energies(0.0), energies(0.05)
    # Without it only the diffuse echo's random phase moves the energy (< 1 %).
    assert np.std(quiet) / np.mean(quiet) < 0.01
    # Four capsules share no factor: the total's spread is ≈ 2σ/√4 = 5 %.
    assert 0.03 < np.std(noisy) / np.mean(noisy) < 0.08


def test_calibrated_energy_model_is_cached_per_rig():
    a, b = draw_scene("noise", 0).config, draw_scene("noise", 1).config
    assert calibrated_energy_model(a) is calibrated_energy_model(dataclasses.replace(a, steps=99))
    assert calibrated_energy_model(a) != calibrated_energy_model(b)  # another amplitude noise, other shots
    # Face-on shots see the on-axis gain D(0) = 1 whatever the capsule radius: the beam family's rigs
    # calibrate to the default simulator's E0(d).
    beam = draw_scene("beam", 0).config
    assert calibrated_energy_model(beam) == calibrated_energy_model(SimConfig())
