"""Honest σ (principle 1): a plane's reported standard errors cover its errors against the simulator's truth.

The amplitude peak that gives ``corner`` a wall's direction in the rotation plane
(:func:`lelsonar.reconstruct.estimate.corner.pitch.amplitude_pitch`) is a parabola's vertex; on a
window lopsided about the peak (the wall's normal near the end of the sweep, as
when the whole L is rolled) the beam pattern's departure from a parabola moves it
by several of the fit's own σ.  These tests hold the reported σ to the noise model:
for a calibrated σ, ``|error|/σ > 3`` has probability 0.27 % (a 1-D Gaussian) and
~1e-4 for the normal's RMS tilt (a Rayleigh with E[z²] = 1).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from lelsonar.reconstruct.estimate.corner.pitch import amplitude_pitch, window_bias_stderr
from lelsonar.signal.directivity import piston_directivity

#: The capsule's ka at 40 kHz (8 mm radius), as the simulator's receivers.
KA = 2 * math.pi * 40_000 / 343.2 * 0.008


def _beam_scan(phi: float, stop_deg: float, seed: int, noise: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """γ (4 capsules a step, 0.5° steps from −30° to ``stop_deg``); piston-beam amplitudes, log-normal ``noise``."""
    gamma = np.repeat(np.radians(np.arange(-30.0, stop_deg + 1e-9, 0.5)), 4)
    amp = piston_directivity(np.abs(gamma - phi), KA) ** 2 / (2 * 1.5)
    return gamma, amp * np.exp(np.random.default_rng(seed).normal(0, noise, amp.shape))


@pytest.mark.parametrize("margin_deg", [3.0, 5.0, 8.0])
def test_amplitude_pitch_sigma_covers_a_peak_near_the_end_of_the_sweep(margin_deg: float) -> None:
    # The wall's normal `margin_deg` inside the end of the sweep: the 10 dB window is ~20° on one side of the peak,
    # a few degrees on the other.  Over 40 draws of 1 % amplitude noise, a calibrated σ leaves |z| > 3 in 0.27 % of
    # them (≤ 2 of 40 is generous); the fit's own σ alone left 39, 29 and 6 of them beyond 3 (margins 3, 5, 8°).
    phi = math.radians(10.0)
    z = []
    for seed in range(40):
        gamma, amp = _beam_scan(phi, 10.0 + margin_deg, seed)
        res = amplitude_pitch(gamma, amp, np.full(gamma.shape, 1.5))
        if res is not None:  # no direction is an honest answer for a peak the sweep barely passes
            z.append(abs(res[0] - phi) / res[1])
    assert sum(v > 3 for v in z) <= 2, sorted(z)[-5:]


def test_amplitude_pitch_sigma_stays_tight_on_a_centred_peak() -> None:
    # Symmetric window: nothing to add; the σ stays the fit's (median |z| of a calibrated Gaussian ≈ 0.67).
    phi = math.radians(3.7)
    z, se = [], []
    for seed in range(40):
        gamma, amp = _beam_scan(phi, 37.4, seed)
        est, s = amplitude_pitch(gamma, amp, np.full(gamma.shape, 1.5))
        z.append(abs(est - phi) / s)
        se.append(s)
    assert 0.4 <= float(np.median(z)) <= 1.0 and max(z) <= 4.0
    assert float(np.median(se)) < math.radians(0.05)


def test_window_bias_stderr_counts_only_the_excess_over_noise() -> None:
    # Nested fits without bias: φ − φ_sym has variance σ_sym² − σ²; a shift within that adds nothing.
    assert window_bias_stderr(0.0, 1.0, 1.0, math.sqrt(2.0)) == pytest.approx(1.0)
    # A shift beyond it is bias: σ² + Δ² − (σ_sym² − σ²).
    assert window_bias_stderr(0.0, 1.0, 3.0, math.sqrt(2.0)) == pytest.approx(math.sqrt(1.0 + 9.0 - 1.0))


#: Stress draws of the rolled L (``lelsonar bench estimators --stress roll``) with a wall's normal within a few
#: degrees of the end of the sweep (8, 11, 14, 15, 17) or a later echo in the amplitude window (6), and
#: three without (0, 1, 3).
ROLL_SEEDS = (0, 1, 3, 6, 8, 11, 14, 15, 17)


@pytest.mark.slow
def test_rolled_corner_planes_that_claim_good_have_an_honest_normal_sigma() -> None:
    """Over the rolled scenes, |angle error| / normal_stderr > 3 on at most 1 of the planes claiming good.

    The truth is the scene's panels; the noise model allows ~1e-4 of them beyond 3 (one is generous).  The fit's
    own σ of the amplitude peak left 6 of the 16 good planes of these scenes beyond 3 (z 4.4–8.8).
    """
    from lelsonar.reconstruct.estimate.pipeline import reconstruct
    from lelsonar.reconstruct.estimate.results import PlaneFit
    from lelsonar.signal.energy import echo_amplitude, waveform_energy
    from lelsonar.tools.bench_stress import draw_case, energy_model, simulate

    z_good = []
    for seed in ROLL_SEEDS:
        scan = simulate(draw_case("roll", seed))
        assert not scan.case.reverse
        cfg = scan.config
        amp = echo_amplitude(scan.waveforms, cfg.sample_rate, scan.t0, scan.tof)
        res = reconstruct(
            scan.gamma_measured,
            cfg.sound_speed * scan.tof / 2,
            waveform_energy(scan.waveforms, cfg.sample_rate),
            cfg.geometry,
            energy_model(scan),
            echo_amplitude=amp,
        )
        for plane, panel in ((res.plane_a, cfg.scene.panels[0]), (res.plane_b, cfg.scene.panels[1])):
            if isinstance(plane, PlaneFit) and plane.quality == "good":
                angle = math.acos(min(1.0, float(plane.normal @ np.asarray(panel.normal))))
                z_good.append(angle / plane.normal_stderr)
    assert len(z_good) >= 10, "the scenes no longer give good planes: not what this test meant"
    assert sum(z > 3 for z in z_good) <= 1, sorted(z_good)[-6:]


def test_clipped_echoes_are_a_plateau_at_the_largest_amplitude() -> None:
    gamma, amp = _beam_scan(math.radians(10.0), 40.0, seed=0)
    from lelsonar.reconstruct.estimate.corner.pitch import clipped_echoes

    assert not clipped_echoes(amp).any()  # noisy, unclipped: one largest echo
    full_scale = float(np.quantile(amp, 0.9))
    clipped = np.minimum(amp, full_scale)
    assert np.array_equal(clipped_echoes(clipped), amp >= full_scale)
    assert not clipped_echoes(np.full(3, np.nan)).any()


@pytest.mark.parametrize("full_scale_db", [-1.0, -3.0, -6.0])
def test_amplitude_pitch_is_not_fooled_by_a_receiver_that_clips_at_the_start_of_the_sweep(full_scale_db: float) -> None:
    # The wall's normal 4° before the sweep starts, its strongest echoes clipped by the receiver's full scale: the
    # parabola through the plateau put its vertex inside the plateau, at the start of the sweep, with a σ of a
    # fraction of a degree (the stress sweep's `mixed` seed 505: 14° off, |z| 11, "good").  The peak was not
    # observed: either no direction, or one whose σ covers its error (|z| ≤ 3 for all but ~0.27 % of draws).
    phi = math.radians(-34.0)
    z = []
    for seed in range(20):
        gamma, amp = _beam_scan(phi, 20.0, seed)
        full_scale = float(amp.max()) * 10 ** (full_scale_db / 20)
        res = amplitude_pitch(gamma, np.minimum(amp, full_scale), np.full(gamma.shape, 1.5))
        if res is not None:
            z.append(abs(res[0] - phi) / res[1])
    assert sum(v > 3 for v in z) <= 1, sorted(z)[-5:]
