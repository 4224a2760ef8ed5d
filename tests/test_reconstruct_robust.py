"""Scenes outside the bench families, judged against the simulator's ground truth (``lelsonar bench stress``).

A plane fails when its patch error is over 2 cm and over 3× the oracle's (LS
on the true mirror echoes); the rule is that a failing plane never claims
``good``.
"""

from __future__ import annotations

import dataclasses
import math

import pytest

from lelsonar.reconstruct.estimate.pipeline import reconstruct
from lelsonar.reconstruct.estimate.results import PlaneFit
from lelsonar.signal.energy import echo_amplitude, waveform_energy
from lelsonar.sim import simulate_scan
from lelsonar.sim.scenes import SceneParams, build_config, calibrated_energy_model
from lelsonar.tools.bench_families import is_failure, plane_errors, scene_truth

DEG = math.pi / 180.0


def _judge(params: SceneParams, seed: int) -> dict[str, tuple[float, float, str | None]]:
    """Label → (patch error cm, oracle patch error cm, quality) of the default method on a simulated scan."""
    cfg = build_config(params)
    scan = simulate_scan(cfg, seed=seed)
    amplitude = echo_amplitude(scan.waveforms, scan.sample_rate, scan.t0, scan.tof)
    energy = waveform_energy(scan.waveforms, scan.sample_rate)
    res = reconstruct(
        scan.gamma_measured,
        scan.distance,
        energy,
        scan.geometry,
        calibrated_energy_model(cfg),
        echo_amplitude=amplitude,
    )
    truth = scene_truth(scan)
    out = {}
    for label, plane in (("a", res.plane_a), ("b", res.plane_b)):
        tp = truth.planes[label]
        assert truth.oracle[label] is not None, f"plane {label} unobserved: the scene is not what the test meant"
        oracle = truth.oracle[label][2]
        if not isinstance(plane, PlaneFit):
            out[label] = (math.nan, oracle, None)
            continue
        out[label] = (
            plane_errors(plane.normal, plane.offset, tp.normal, tp.offset, truth.patch[label])[2],
            oracle,
            plane.quality,
        )
    return out


@pytest.mark.parametrize("roll_deg", [16.0, 20.0, -20.0])
def test_a_rolled_corner_is_found_where_it_is(roll_deg):
    """The whole L turned about the rotation axis (a robot not square to the corner): both walls are accurate.

    The joint model held each wall within 15° of the paper's axes, so beyond that roll it returned the axes
    themselves with the covariance of another fit, and the plane claimed good 7–11 cm off.
    """
    roll = roll_deg * DEG
    crit = math.atan2(1.06, 1.57) + roll
    params = SceneParams(
        tilt_a_x=roll,
        tilt_b_x=roll,
        gamma_start=min(-10 * DEG, crit - 60 * DEG),
        gamma_stop=max(110 * DEG, crit + 60 * DEG),
    )
    for label, (patch, oracle, quality) in _judge(params, seed=3).items():
        assert math.isfinite(patch), f"plane {label}: no plane"
        assert not is_failure(patch, oracle), f"plane {label}: patch {patch:.2f} cm, oracle {oracle:.2f} cm ({quality})"


def test_a_narrow_sweep_past_the_corner_does_not_take_the_corner_cluster_for_a_wall():
    """A sweep of 14–55° sees wall a off face-on, the corner cluster and barely wall b.

    The corner cluster looks like a wall facing the edge; the walls' fits pulled apart (one onto it) are not a
    turn of the whole L, so the model's axes must not follow them: no failing plane may claim good.
    """
    params = SceneParams(gamma_start=14.2 * DEG, gamma_stop=55.1 * DEG)
    cfg = build_config(SceneParams())  # panels of the full sweep (the narrow one's check wants the corner ±5°)
    scan = simulate_scan(dataclasses.replace(cfg, gamma_start=params.gamma_start, gamma_stop=params.gamma_stop), seed=4)
    amplitude = echo_amplitude(scan.waveforms, scan.sample_rate, scan.t0, scan.tof)
    energy = waveform_energy(scan.waveforms, scan.sample_rate)
    res = reconstruct(
        scan.gamma_measured,
        scan.distance,
        energy,
        scan.geometry,
        calibrated_energy_model(cfg),
        echo_amplitude=amplitude,
    )
    truth = scene_truth(scan)
    for label, plane in (("a", res.plane_a), ("b", res.plane_b)):
        if not isinstance(plane, PlaneFit) or plane.quality != "good":
            continue
        tp = truth.planes[label]
        assert truth.oracle[label] is not None, f"plane {label} claims good but the sweep never saw it"
        patch = plane_errors(plane.normal, plane.offset, tp.normal, tp.offset, truth.patch[label])[2]
        assert not is_failure(patch, truth.oracle[label][2]), f"plane {label} claims good {patch:.2f} cm off"


@pytest.mark.slow
@pytest.mark.parametrize(
    "family,seed", [("tilt", 9), ("tilt", 14), ("sweep", 4), ("nocorner", 0), ("roll", 0), ("extreme", 6)]
)
def test_stress_cases_through_the_cli_never_claim_good_when_wrong(family, seed, tmp_path):
    """Recorded by the scan loop, replayed by ``reconstruct --source --json``: no crash, no wrong plane
    claiming good."""
    from lelsonar.tools.bench_stress import stress_scan

    rows = stress_scan(family, seed)
    assert rows and all(r["verdict"] in ("accurate", "flagged") for r in rows), rows


#: Scans of the stress sweep whose planes claimed good while failing, each for a different reason (the draws
#: of ``lelsonar bench estimators --stress``, spelled out so the tests do not move when the sweep's draws do).
_FAR_WALL_BESIDE_NEAR = dict(
    distance_a=2.03783111576983,
    distance_b=0.5212544260357854,
    opening=1.7685358865626426,
    roll=0.18113367955055737,
    skew_a=0.15908759639382272,
    skew_b=0.20498145379801908,
    steps=320,
    capsules=5,
    pitch=0.1318814262548935,
    tof_jitter=0.005415442181261191,
    amplitude_noise=0.08984824778432403,
    cycle_slip_probability=0.03175780270371016,
    missing=0.0516463086517168,
    missing_runs=True,
)
CLAIMED_GOOD = {
    # A far wall beside a near one (2.04 m, 0.52 m, opening 101°): its mirror echoes and the corner's double
    # bounces lie within the assignment tolerance of each other; fitted mostly to corner echoes, 2.8 cm off.
    "wall-echoes-are-the-edge's": (
        "mixed",
        16,
        dict(
            _FAR_WALL_BESIDE_NEAR,
            gamma_start=-0.7967780470744431,
            gamma_stop=1.9198621771937625,
            radial_offset=0.03242359693372813,
            sample_rate=100000.0,
            noise_std=0.010066747934311634,
            corner_gain=0.637819632080508,
            e0_scale=0.5088808238579527,
        ),
    ),
    # No double bounce above the threshold (corner gain 0.12, opening 72°), yet the model's "edge" explained
    # 284 of wall b's echoes and tied wall a's direction to them: 17° off, wall a's face-on outside the sweep.
    "edge-echoes-are-a-wall's": (
        "extreme",
        6,
        dict(
            distance_a=1.463760450740369,
            distance_b=2.5751788631678587,
            opening=1.2527732976255288,
            roll=-0.22580451180749467,
            skew_a=-0.1043958429914224,
            skew_b=-0.05892509986042223,
            gamma_start=-0.17453292519943295,
            gamma_stop=2.1011253708037976,
            steps=325,
            spacing="jitter",
            capsules=7,
            pitch=0.1119064662535685,
            uneven=0.3095341710315847,
            radial_offset=0.08850718956862212,
            sample_rate=250000.0,
            window_start=0.001,
            tof_jitter=0.006196423293829198,
            cycle_slip_probability=0.07316242357206562,
            amplitude_noise=0.06402125579061417,
            noise_std=0.005585882500798769,
            corner_gain=0.12319158598582403,
            corner_max_error=0.767944870877505,
            missing=0.07018575634714999,
            missing_runs=True,
            e0_scale=0.2537417261309924,
        ),
    ),
    # A far wall beside a near one (2.87 m, 0.91 m, opening 100°, L rolled −11°): the edge lies 5° from the far
    # wall's normal, so its 438 double bounces passed for wall b (5 mirror echoes of it), 3.5 cm off, and the
    # model's own edge, beside the cluster, explained none of them.
    "corner-cluster-is-the-wall": (
        "extreme",
        500,
        dict(
            distance_a=0.9056439240034528,
            distance_b=2.874792960229462,
            opening=1.747279908568496,
            roll=-0.19589416822379369,
            skew_a=0.13846967316071493,
            skew_b=0.1134423631324446,
            gamma_stop=2.3128064269053503,
            reverse=True,
            steps=251,
            spacing="dense",
            pitch=0.04877806113823298,
            uneven=0.017947211508245076,
            radial_offset=0.04017700957700983,
            sample_rate=100000.0,
            int16=True,
            tof_jitter=0.002091861148933949,
            cycle_slip_probability=0.0683575218274668,
            amplitude_noise=0.08018474390861637,
            noise_std=0.00937059005964818,
            corner_gain=1.2151696298441106,
            corner_max_error=0.767944870877505,
            missing=0.03149148992260311,
            missing_runs=True,
            e0_scale=2.203668332273951,
        ),
    ),
    # A far wall (2.19 m) beside a near one (0.42 m): where the boresight faces the edge (γ ≈ 79°), the corner's
    # double bounce (gain 2.1) returns 4 cm behind wall b's echo, inside the window whose peak is the echo's
    # amplitude, so wall b's amplitudes peaked at the edge's direction: 10° off, σ 0.6°, "good".
    "double-bounce-in-the-amplitude-window": (
        "mixed",
        1136,
        dict(
            distance_a=0.41708206847883056,
            distance_b=2.1885053293516927,
            opening=1.6213545461782521,
            roll=0.014492681095263362,
            skew_a=-0.06582384028657728,
            skew_b=-0.014604590800815347,
            gamma_stop=2.429673644517023,
            reverse=True,
            steps=78,
            capsules=6,
            pitch=0.1372249134418498,
            uneven=0.08958397172837791,
            radial_offset=0.014352863738394762,
            sample_rate=125000.0,
            int16=True,
            window_start=0.001,
            tof_jitter=0.00796458340737418,
            cycle_slip_probability=0.04055979099393087,
            amplitude_noise=0.04761447656621262,
            noise_std=0.007911067021093465,
            corner_gain=2.1324527262068638,
            missing=0.18054830437618288,
            e0_scale=1.7375837639320273,
        ),
    ),
    # A sweep of −40…24° sees wall a only: no pair of bands, the energy-split fallback fitted wall a 2.5 cm off.
    "one-wall-fallback": (
        "mixed",
        16,
        dict(
            _FAR_WALL_BESIDE_NEAR,
            gamma_start=-0.6981317007977318,
            gamma_stop=0.4227985756505899,
            uneven=0.12969438773491251,
            radial_offset=0.08796540685386804,
            sample_rate=100000.0,
            int16=True,
            window_start=0.001,
            tof_jitter=0.003778807736574639,
            cycle_slip_probability=0.07187859822745922,
            amplitude_noise=0.08066747934311634,
            noise_std=0.00412606544026836,
            corner_gain=0.774694629775752,
            missing=0.09493178281263742,
            e0_scale=1.427031183336294,
        ),
    ),
}


@pytest.mark.parametrize("name", sorted(CLAIMED_GOOD))
def test_stress_scans_that_claimed_good_while_wrong_are_accurate_or_flagged(name, tmp_path):
    """Recorded by the scan loop and replayed through ``reconstruct --source --json``, judged on the scene's truth."""
    from lelsonar.tools.bench_stress import StressCase, judge, record, run_cli, simulate

    family, seed, fields = CLAIMED_GOOD[name]
    scan = simulate(StressCase(family, seed, **fields))
    path = tmp_path / "scan.mcap"
    record(scan, path)
    rows = judge(scan, *run_cli(path))
    assert [r for r in rows if r["verdict"] not in ("accurate", "flagged")] == []


def test_a_sweep_that_never_sees_the_corner_still_places_the_wall_it_sees(tmp_path):
    """A reversed sweep of 116…53° sees wall b only (the corner is at 34°): wall b is accurate on its own.

    The joint model needs a band of echoes on both walls; without one the energy-split fallback fitted wall b
    9.4 cm off (oracle 0.05 cm).  Through the CLI: wall a gets no good plane.
    """
    from lelsonar.tools.bench_stress import StressCase, judge, record, run_cli, simulate

    scan = simulate(
        StressCase("nocorner", 6, gamma_start=0.9245008798800993, gamma_stop=2.030476872555467, reverse=True)
    )
    path = tmp_path / "scan.mcap"
    record(scan, path)
    rows = {r["label"]: r for r in judge(scan, *run_cli(path))}
    assert rows["a"]["n_mirror"] == 0 and rows["a"]["verdict"] == "flagged", rows["a"]
    assert rows["b"]["verdict"] == "accurate", rows["b"]
