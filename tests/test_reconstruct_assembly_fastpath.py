"""The per-sample fast path of ScanAssembly.add gives exactly (bit for bit) what the whole-scan
functions of lelsonar.reconstruct.energy give on the same waveforms."""

from __future__ import annotations

import numpy as np

from lelsonar import codec
from lelsonar.reconstruct.assembly import ScanAssembly
from lelsonar.reconstruct.energy import echo_amplitude, energy_ratio, total_energy, waveform_energy

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
        tof = np.array([s.time_of_flight if s.echo_valid else np.nan
                        for s in sorted(m.sensors, key=lambda s: s.capsule_id)])
        w = m.sensors[0].waveform
        np.testing.assert_array_equal(scan.sensor_energy[m.step], waveform_energy(waves, w.sample_rate))
        np.testing.assert_array_equal(scan.echo_amplitude[m.step], echo_amplitude(waves, w.sample_rate, w.t0, tof))
    # Some echoes have no range (NaN) and some do: both branches are covered.
    assert np.isnan(scan.distance[steps]).any() and np.isfinite(scan.distance[steps]).any()
    assert np.isnan(scan.distance[steps]).all(axis=1).any()
    np.testing.assert_array_equal(scan.step_energy[steps], total_energy(scan.sensor_energy[steps]))
    np.testing.assert_array_equal(scan.ratio[steps],
                                  energy_ratio(scan.step_energy[steps], scan.distance[steps], scan.energy_model))


def test_echo_peak_windows_at_the_waveform_edges():
    from lelsonar.reconstruct.assembly import _echo_peaks

    rng = np.random.default_rng(0)
    w = rng.standard_normal((4, 500)).astype(np.float32).astype(np.float64)
    rate, t0 = 1e6, 1e-4
    # Before the window (clipped to 0), inside, running off the end, and at/after the end.
    tof = [5e-5, 3e-4, t0 + 480e-6, t0 + 500e-6]
    got = _echo_peaks(w, rate, t0, tof)
    want = echo_amplitude(w, rate, t0, np.array(tof))
    np.testing.assert_array_equal(got, want)
    assert np.isnan(got[3]) and np.isfinite(got[:3]).all()
