"""The per-sample fast path of ScanAssembly.add gives exactly (bit for bit) what the whole-scan
functions of lelsonar.signal.energy give on the same waveforms."""

from __future__ import annotations

import numpy as np

from lelsonar import codec
from lelsonar.reconstruct.stream.assembly import ScanAssembly
from lelsonar.signal.energy import (
    ECHO_PEAK_WINDOW,
    echo_amplitude,
    energy_ratio,
    total_energy,
    waveform_energy,
)

from .conftest import simulated_messages


def test_assembly_matches_the_whole_scan_functions_bit_for_bit():
    msgs = simulated_messages("paper-test1", seed=11)
    start, samples = msgs[0], msgs[1:-1]
    for m in samples[::7]:  # some capsules without an echo, and some steps without any
        m.sensors[1].echo_valid = False
    for m in samples[::22]:
        for s in m.sensors:
            s.echo_valid = False
    scan = ScanAssembly(start)
    for m in samples:
        assert scan.add(m)
    steps = np.flatnonzero(scan.received)
    assert len(steps) == len(samples)
    for m in samples:
        waves = np.stack([codec.unpack_waveform(s.waveform) for s in sorted(m.sensors, key=lambda s: s.capsule_id)])
        tof = np.array(
            [s.time_of_flight if s.echo_valid else np.nan for s in sorted(m.sensors, key=lambda s: s.capsule_id)]
        )
        w = m.sensors[0].waveform
        np.testing.assert_array_equal(scan.sensor_energy[m.step], waveform_energy(waves, w.sample_rate))
        # and eq. (10) by the rectangle rule, summed independently
        np.testing.assert_allclose(
            scan.sensor_energy[m.step], (waves.astype(np.float64) ** 2).sum(axis=1) / w.sample_rate, rtol=1e-12
        )
        np.testing.assert_array_equal(scan.echo_amplitude[m.step], _peak_by_definition(waves, w.sample_rate, w.t0, tof))
    # Some echoes have no range (NaN) and some do: both branches are covered.
    assert np.isnan(scan.distance[steps]).any() and np.isfinite(scan.distance[steps]).any()
    assert np.isnan(scan.distance[steps]).all(axis=1).any()
    np.testing.assert_array_equal(scan.step_energy[steps], total_energy(scan.sensor_energy[steps]))
    np.testing.assert_array_equal(
        scan.ratio[steps], energy_ratio(scan.step_energy[steps], scan.distance[steps], scan.energy_model)
    )


def _peak_by_definition(w: np.ndarray, rate: float, t0: float, tof: np.ndarray, window=ECHO_PEAK_WINDOW) -> np.ndarray:
    """echo_amplitude's definition written out the slow way, in float64: max |w| over the samples
    rint((tof + lo - t0)·rate) (clipped to [0, n]) and the next rint((hi - lo)·rate) - 1, clipped at the end;
    NaN without an echo or when the window starts at or after the end."""
    w = np.abs(np.asarray(w, dtype=np.float64))
    n = w.shape[-1]
    ok = np.isfinite(tof) & (tof > 0)
    start = np.clip(np.rint((np.where(ok, tof, 0.0) + window[0] - t0) * rate), 0, n).astype(np.intp)
    width = max(int(round((window[1] - window[0]) * rate)), 1)
    idx = np.minimum(start[..., None] + np.arange(width), n - 1)
    peak = np.take_along_axis(w, idx, axis=-1).max(axis=-1)
    return np.where(ok & (start < n), peak, np.nan)


def test_echo_peak_windows_at_the_waveform_edges():
    rng = np.random.default_rng(0)
    rate, t0 = 2.0**20, 2.0**-12  # powers of two: the edge times below are exact
    for n in (500, 501):
        # Before the window (clipped to 0), inside, running off the end, at the end, no echo, +inf, none; and a
        # start of exactly n - 0.5 samples (rint rounds half to even: inside for an odd n, outside for an even).
        tof = np.array([5e-5, 3e-4, t0 + (n - 20) / rate, t0 + n / rate, np.nan, np.inf, 0.0, t0 + (n - 0.5) / rate])
        assert (tof[-1] - t0) * rate == n - 0.5
        w32 = rng.standard_normal((len(tof), n)).astype(np.float32)
        got = echo_amplitude(w32, rate, t0, tof)
        np.testing.assert_array_equal(got, _peak_by_definition(w32, rate, t0, tof))
        # float32 in or float64 in, the same numbers (|w| and max are exact in either)
        np.testing.assert_array_equal(echo_amplitude(w32.astype(np.float64), rate, t0, tof), got)
        assert np.isfinite(got[:3]).all() and np.isnan(got[3:7]).all()
        assert np.isfinite(got[7]) == (n % 2 == 1)


def test_echo_amplitude_of_a_whole_scan_is_that_of_each_step():
    rng = np.random.default_rng(1)
    rate, t0 = 2e5, 0.0
    w = rng.standard_normal((30, 4, 700)).astype(np.float32)
    tof = rng.uniform(-1e-3, 4e-3, (30, 4))
    tof[rng.random((30, 4)) < 0.2] = np.nan
    whole = echo_amplitude(w, rate, t0, tof)
    np.testing.assert_array_equal(whole, _peak_by_definition(w, rate, t0, tof))
    for i in range(30):
        np.testing.assert_array_equal(echo_amplitude(w[i], rate, t0, tof[i]), whole[i])
        np.testing.assert_array_equal(waveform_energy(w[i], rate), waveform_energy(w, rate)[i])
