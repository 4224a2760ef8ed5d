"""Ranges that do not walk with the echo's amplitude (design notes §8).

A comparator that times an echo's threshold crossing fires later on weaker echoes.  The simulator models
such a board (``Receiver.timing = "crossing"``); reconstruction re-times each echo from its waveform by
constant fraction (:mod:`lelsonar.signal.echo_timing`) where the writer's ranges walk.  Everything is
judged against the truth of the scene or of the synthetic burst, never against the code's own output.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from lelsonar.signal.echo_timing import MIN_WALK, TIMING_WINDOW, echo_onsets, range_walk, walk_free_ranges
from lelsonar.signal.energy import echo_amplitude
from lelsonar.sim import SimConfig, simulate_scan
from lelsonar.sim.acoustics import comparator_delay, echo_envelope
from lelsonar.sim.presets import preset as preset_config
from lelsonar.sim.presets import preset_names
from lelsonar.tools import bench_stress as stress

C = 343.2


# ----------------------------------------------------------------------------- the board
def test_the_crossing_delay_is_where_the_envelope_reaches_the_threshold():
    rise, threshold = 0.15e-3, 0.05
    peak = np.array([0.05, 0.06, 0.1, 0.5, 2.0])
    delay = comparator_delay(peak, threshold, rise)
    # The envelope scaled to its peak is at the threshold there, on its rising half (before the peak at τ).
    assert np.allclose(peak * echo_envelope(delay, rise), threshold, rtol=1e-9)
    assert np.all(delay <= rise) and np.all(np.diff(delay) < 0)  # weaker echoes cross later


def test_a_crossing_board_reads_weaker_echoes_farther_by_its_delay_and_an_onset_board_does_not():
    cfg = SimConfig()
    onset = simulate_scan(cfg, 5)
    crossing = simulate_scan(dataclasses.replace(cfg, receiver=dataclasses.replace(cfg.receiver, timing="crossing")), 5)
    # The same seed draws the same jitter and slips: the boards differ by the crossing delay alone.
    assert np.array_equal(np.isnan(onset.distance), np.isnan(crossing.distance))
    ok = np.isfinite(onset.distance)
    extra = (crossing.distance - onset.distance)[ok]
    # Each echo's peak at the receiver, from the waveforms (the truth the board saw).
    peak = echo_amplitude(onset.waveforms, onset.sample_rate, onset.t0, onset.truth.echo_range * 2 / onset.sound_speed)[
        ok
    ]
    want = onset.sound_speed / 2 * comparator_delay(peak, cfg.receiver.threshold, cfg.receiver.envelope_time)
    # The waveform's peak is the echo's to the noise (2 mV) and the sampling of the carrier (cos 36° at worst).
    assert np.all(extra > 0) and np.all(extra <= onset.sound_speed / 2 * cfg.receiver.envelope_time + 1e-12)
    assert np.corrcoef(np.log(peak), extra)[0, 1] < -0.8
    assert np.median(np.abs(extra - want)) < 1e-3


# ----------------------------------------------------------------------------- constant-fraction timing
def _bursts(
    shape: str,
    peaks: np.ndarray,
    rng: np.random.Generator,
    rate: float = 200_000.0,
    threshold: float = 0.05,
    noise: float = 0.002,
):
    """Windows holding one 40 kHz burst each at a known arrival, cut around the time a threshold-crossing board
    would report: (windows, that time and the arrival after each window's first sample)."""
    width = int(round((TIMING_WINDOW[1] - TIMING_WINDOW[0]) * rate))
    arrival = 5e-3 + rng.uniform(0, 1 / rate, peaks.size)  # s after firing
    if shape == "rise":  # the simulator's envelope, τ = 0.15 ms
        cross = arrival + comparator_delay(peaks, threshold, 0.15e-3)
    else:  # a 0.3 ms Hann burst (tests/foreign_scenes.py)
        length = 0.3e-3
        cross = arrival + length / np.pi * np.arcsin(np.sqrt(threshold / peaks))
    first = np.round((cross + TIMING_WINDOW[0]) * rate) / rate  # the window's first sample, on the clock
    u = first[:, None] + np.arange(width) / rate - arrival[:, None]
    if shape == "rise":
        env = echo_envelope(u, 0.15e-3)
    else:
        env = np.where((u >= 0) & (u <= length), np.sin(np.pi * np.clip(u, 0, length) / length) ** 2, 0.0)
    w = peaks[:, None] * env * np.sin(2 * np.pi * 40_000.0 * np.maximum(u, 0)) + rng.normal(0, noise, env.shape)
    return w, cross - first, arrival - first


@pytest.mark.parametrize("shape", ["rise", "hann"])
def test_constant_fraction_times_a_burst_whatever_its_strength(shape):
    rng = np.random.default_rng(11)
    peaks = np.exp(rng.uniform(math.log(0.06), math.log(1.5), 300))
    windows, tof_at, arrival_at = _bursts(shape, peaks, rng)
    onset, peak, edge = echo_onsets(windows, 200_000.0, tof_at)
    assert np.isfinite(onset).all()
    lag = tof_at + onset - arrival_at  # constant-fraction time after the true arrival
    walk = tof_at - arrival_at  # the board's
    # Noise model: 2 mV on an edge rising ~1.6·A per rise time gives a timing σ of 2 mV·τ/(1.6·A).
    sigma = 0.002 * 0.15e-3 / (1.6 * peaks)
    assert np.all(np.abs(lag - np.median(lag)) < 5 * sigma + 1e-6)
    assert np.ptp(walk) > 40e-6  # while the board's crossing walked by over 7 mm of range
    assert np.allclose(peak, peaks, rtol=0.1)


# ----------------------------------------------------------------------------- the test and the correction
def test_a_walk_is_detected_and_removed_and_flat_ranges_never_are():
    rng = np.random.default_rng(2)
    true = rng.uniform(1.0, 2.0, 400)
    peak = np.exp(rng.uniform(math.log(0.06), math.log(0.8), 400))
    walk = C / 2 * comparator_delay(peak, 0.05, 0.15e-3)
    retimed_noise = rng.normal(0, 2e-4, 400)
    writer = true + walk + rng.normal(0, 0.002, 400)
    offset = writer - (true + retimed_noise + 0.004)  # re-timed at a constant 4 mm after the onset
    w = range_walk(offset, peak)
    assert w.detected and w.walk > MIN_WALK
    fixed = walk_free_ranges(writer, offset, peak, w)
    # The walk is gone: what is left against the truth does not follow the amplitude, and sits at the
    # strongest echoes' own delay (the writer's zero) to the re-timing's noise (0.2 mm; 5σ), but for the
    # few echoes whose offset strays over 3σ from the walk's curve (moved by the curve, so they keep the
    # writer's 2 mm noise).
    left = fixed - true
    assert abs(np.polyfit(np.log(peak), left, 1)[0]) < 3e-4
    zero = np.median(walk[peak >= np.percentile(peak, 75)])
    assert np.mean(np.abs(left - zero) < 1e-3) > 0.97
    assert np.all(np.abs(left - zero) < 5 * 0.002)
    # A board timing the onset: never detected (4σ one-sided), over many seeded scans.
    alarms = sum(
        range_walk(rng.normal(0, 0.002, 200) + rng.normal(0, 2e-4, 200), np.exp(rng.uniform(-3, 0, 200))).detected
        for _ in range(300)
    )
    assert alarms == 0


# ----------------------------------------------------------------------------- through the CLI, against the scene
def _cli(tmp_path, case):
    scan = stress.simulate(case)
    path = tmp_path / f"{case.family}-{case.seed}.mcap"
    stress.record(scan, path)
    code, lines, err = stress.run_cli(path)
    return code, stress.judge(scan, code, lines, err)


@pytest.mark.slow
@pytest.mark.parametrize(
    "kw",
    [
        dict(distance_a=1.57, distance_b=1.06, threshold=0.05),  # the paper's corner
        dict(distance_a=2.2, distance_b=0.8, roll=math.radians(8), threshold=0.03, envelope_time=0.3e-3),
        dict(distance_a=0.9, distance_b=1.8, roll=math.radians(-12), threshold=0.12, echo_gain=4.0),
    ],
)
def test_a_board_timing_threshold_crossings_gives_accurate_planes(tmp_path, kw):
    case = stress.StressCase("comparator", 0, timing="crossing", **kw)
    code, rows = _cli(tmp_path, case)
    assert code == 0
    for row in rows:
        assert row["verdict"] == "accurate", row
        assert any("re-timed" in r for r in row["reasons"]), row["reasons"]
        # Range noise 2 mm over a lever arm of decimetres: the normal within a degree; the offset within the
        # writer's zero (the strongest echoes' own crossing delay, ≤ 0.2 τ of range) and 1 cm.
        assert row["angle_deg"] < 1.0, row
        assert abs(row["offset_cm"]) < 100 * (C / 2 * 0.2 * case.envelope_time) + 1.0, row


@pytest.mark.slow
@pytest.mark.parametrize("family,seed", [("distance", 0), ("tilt", 3), ("noise", 1), ("rate", 2), ("mixed", 4)])
def test_an_onset_board_is_never_re_timed(tmp_path, family, seed):
    code, rows = _cli(tmp_path, stress.draw_case(family, seed))
    for row in rows:
        assert not any("re-timed" in r for r in row.get("reasons") or []), row


def _timing_windows(scan):
    """Each reading's waveform over :data:`TIMING_WINDOW` around its time of flight, as the assembly keeps it:
    (windows, sample rate, the time of flight after each window's first sample)."""
    rate = scan.sample_rate
    width = int(round((TIMING_WINDOW[1] - TIMING_WINDOW[0]) * rate))
    rows, at = [], []
    for (i, j), t in np.ndenumerate(scan.tof):
        a = int(round((t + TIMING_WINDOW[0] - scan.t0) * rate)) if np.isfinite(t) else -1
        if 0 <= a and a + width <= scan.waveforms.shape[-1]:
            rows.append(scan.waveforms[i, j, a : a + width])
            at.append(t - (scan.t0 + a / rate))
    return np.array(rows), rate, np.array(at)


@pytest.mark.parametrize("preset", preset_names())
def test_our_default_board_shows_no_walk(preset):
    """The test itself on every preset scene of the default simulator (onset timing), over several seeds."""
    for seed in range(4):
        scan = simulate_scan(preset_config(preset), seed)
        onset, peak, edge = echo_onsets(*_timing_windows(scan))
        assert np.isfinite(onset).mean() > 0.9
        walk = range_walk(-scan.sound_speed / 2 * onset, peak)
        assert not walk.detected, (preset, seed, walk)


# ----------------------------------------------------------------------------- the kernels against array code
def _onsets_by_arrays(windows, rate, tof_at, fraction=0.5):
    """echo_onsets written as whole-array NumPy/SciPy (the form the kernel replaced), for the comparison."""
    from scipy import fft as sfft
    from scipy.ndimage import maximum_filter1d, uniform_filter1d

    w = np.asarray(windows, dtype=np.float64)
    n, width = w.shape
    head, half, period = max(round(1e-4 * rate), 4), max(round(5e-5 * rate), 1), max(round(rate / 40_000.0), 1)
    hi, lo = w.max(axis=-1, keepdims=True), w.min(axis=-1, keepdims=True)
    clipped = (((w[:, 1:] == hi) & (w[:, :-1] == hi)) | ((w[:, 1:] == lo) & (w[:, :-1] == lo))).any(axis=-1)
    clipped |= ((w == w.max()).sum(axis=-1) >= 3) | ((w == w.min()).sum(axis=-1) >= 3)
    x = (w - w[:, :head].mean(axis=-1, keepdims=True)).astype(np.float32)
    size = sfft.next_fast_len(2 * width, real=True)
    spectrum = sfft.rfft(x, size, axis=-1)
    spectrum[:, 0] = spectrum[:, -1] = 0.0
    env = np.hypot(x, sfft.irfft(spectrum * np.complex64(-1j), size, axis=-1)[:, :width]).astype(np.float64)
    env = uniform_filter1d(env, period, axis=-1, mode="nearest")
    floor = np.median(env[:, :head], axis=-1)
    sigma = 1.4826 * np.median(np.abs(env[:, :head] - floor[:, None]), axis=-1)
    idx, rows = np.arange(width), np.arange(n)
    start = np.round(tof_at * rate).astype(np.int64) - half
    risen = (env > (floor + 8.0 * sigma)[:, None]) & (idx >= start[:, None])
    is_peak = (env >= maximum_filter1d(env, 2 * half + 1, axis=-1, mode="nearest")) & risen
    found, k_peak, j = is_peak.any(axis=-1), np.argmax(is_peak, axis=-1), np.argmax(risen, axis=-1)
    rise = np.zeros_like(env)
    rise[:, period:] = env[:, period:] - env[:, :-period]
    steepest = np.argmax(np.where((idx >= j[:, None]) & (idx <= k_peak[:, None]), rise, -np.inf), axis=-1)
    knee = np.argmin(np.where((idx >= steepest[:, None]) & (idx <= k_peak[:, None]), rise, np.inf), axis=-1)
    merged = (
        (knee < k_peak - period)
        & (rise[rows, knee] < 0.3 * rise[rows, steepest])
        & (env[rows, k_peak] - env[rows, knee] > np.maximum(0.2 * (env[rows, knee] - floor), 8.0 * sigma))
    )
    k_peak = np.where(merged, knee, k_peak)

    def crossing(f):
        level = floor + f * (env[rows, k_peak] - floor)
        last = np.where((env < level[:, None]) & (idx < k_peak[:, None]), idx, -1).max(axis=-1)
        jj = np.maximum(last, 0)
        e0, e1 = env[rows, jj], env[rows, np.minimum(jj + 1, width - 1)]
        with np.errstate(divide="ignore", invalid="ignore"):
            return last, jj + (level - e0) / (e1 - e0)

    last, t = crossing(fraction)
    found &= floor <= np.median(floor) + 8.0 * np.median(sigma)
    peak = np.where(found, env[rows, k_peak] - floor, np.nan)
    found &= (last >= head // 2) & ~clipped
    onset = np.where(found, t / rate - tof_at, np.nan)
    return onset, peak, np.where(found, (crossing(0.8)[1] - crossing(0.2)[1]) / rate, np.nan)


@pytest.mark.parametrize("threshold,envelope_time", [(0.05, 0.15e-3), (0.12, 0.3e-3)])
def test_the_timing_kernels_agree_with_array_code_on_a_crossing_board(threshold, envelope_time):
    """On a threshold-crossing board's own windows (the simulator's, two seeds), the compiled re-timing and
    walk statistics give what whole-array NumPy gives, to rounding."""
    from scipy.ndimage import uniform_filter1d

    from lelsonar.signal import echo_timing as et

    cfg = SimConfig()
    cfg = dataclasses.replace(
        cfg,
        receiver=dataclasses.replace(cfg.receiver, timing="crossing", threshold=threshold, envelope_time=envelope_time),
    )
    for seed in range(2):
        scan = simulate_scan(cfg, seed)
        windows, rate, at = _timing_windows(scan)
        got, want = echo_onsets(windows, rate, at), _onsets_by_arrays(windows, rate, at)
        assert np.isfinite(got[0]).mean() > 0.8
        for g, w in zip(got, want):
            np.testing.assert_allclose(g, w, rtol=1e-12, atol=0)  # NaN where NaN
        # The smoothing sums as SciPy's does: the same to the bit (on float64 values; the envelope's are float32's).
        env = np.random.default_rng(seed).normal(size=(8, windows.shape[1]))
        smooth = np.empty_like(env)
        for row, out in zip(env, smooth):
            et._moving_mean(row, 5, out)
        assert np.array_equal(smooth, uniform_filter1d(env, 5, axis=-1, mode="nearest"))
        # The floor's medians are NumPy's, to the bit, whatever the count's parity (NaN in, NaN out).
        ordered = np.empty(env.shape[1])
        for m in (4, 7, 20, 21):
            for row in env:
                assert et._head_median(row, m, ordered) == np.median(row[:m])
        assert np.isnan(et._head_median(np.array([1.0, np.nan, 2.0, 3.0]), 4, ordered))
        # The walk's statistics: order statistics exactly, the least-squares lines to rounding.
        onset, peak, _ = got
        offset = -C / 2 * onset
        ok = np.isfinite(offset) & np.isfinite(peak)
        o, a = offset[ok], np.log(peak[ok])
        n, line, curve = et._walk_line(o, a)
        med = np.median(o)
        keep = np.abs(o - med) <= 5.0 * max(1.4826 * np.median(np.abs(o - med)), 1e-4)
        o, a = o[keep], a[keep]
        assert n == o.size and n >= 100
        slope = np.polyfit(a, o, 1)[0]
        lo, hi, strong = np.percentile(a, [10.0, 90.0, 75.0])
        np.testing.assert_allclose(line[[0, 2]], [slope, -slope * (hi - lo)], rtol=1e-9)
        assert line[3] == np.median(o[a >= strong])
        for bin_, row in zip(np.array_split(np.argsort(a), len(curve)), curve):
            assert row[0] == np.median(a[bin_]) and row[1] == np.median(o[bin_])
        for q in (0.0, 10.0, 37.5, 75.0, 90.0, 100.0):
            assert et._percentile(np.sort(a), q) == np.percentile(a, q)
