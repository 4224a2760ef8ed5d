"""``Sample.sensor_energy``: each waveform's energy (eq. 10) as its writer computed it.

Present and right, the reconstructor uses it (it does not integrate the waveforms again); present and
wrong (tampered in a recording) or not plausible, it finds out against the waveforms, counts, warns and
recomputes, and the final is the one the true energies give; absent (another writer), it computes it.
The truth each time is eq. (10) worked out here from the waveforms, independently of the code under test.
"""

from __future__ import annotations

import json
import logging
import subprocess
import sys

import numpy as np
import pytest

from lelsonar import codec
from lelsonar.log.recording import McapRecorder
from lelsonar.reconstruct.stream import assembly
from lelsonar.reconstruct.stream.assembly import ScanAssembly
from lelsonar.reconstruct.stream.config import ReconstructConfig
from lelsonar.reconstruct.stream.fastwire import UNREAD
from lelsonar.reconstruct.stream.replay import replay_mcap
from lelsonar.reconstruct.stream.service import ReconstructionService
from lelsonar.reconstruct.stream.step_features import RISE_STRIDE
from lelsonar.signal.energy import waveform_energy_agrees

from .conftest import simulated_messages
from .test_reconstruct_service import comparable


def _waves(sample: codec.Sample) -> np.ndarray:
    return np.stack([codec.unpack_waveform(s.waveform) for s in sample.sensors])


def _true_energy(sample: codec.Sample) -> np.ndarray:
    """Eq. (10) by the rectangle rule, summed here in float64 (the definition, not the code under test)."""
    w = _waves(sample).astype(np.float64)
    return (w * w).sum(axis=1) / sample.sensors[0].waveform.sample_rate


@pytest.fixture(scope="module")
def scan():
    return simulated_messages("paper-test1", seed=5)


def _copy(messages):
    out = []
    for m in messages:
        c = type(m)()
        c.CopyFrom(m)
        out.append(c)
    return out


def _assemble(messages) -> ScanAssembly:
    scan = ScanAssembly(messages[0])
    for m in messages[1:-1]:
        assert scan.add(m)
    scan.end = messages[-1]
    return scan


def test_the_acquisition_service_carries_each_waveforms_energy(scan):
    for m in scan[1:-1]:
        assert len(m.sensor_energy) == len(m.sensors)
        np.testing.assert_allclose(m.sensor_energy, _true_energy(m), rtol=1e-12)


def test_present_and_right_it_is_used_not_recomputed(scan, monkeypatch):
    recomputed = []
    real = assembly.waveform_energy
    monkeypatch.setattr(assembly, "waveform_energy", lambda *a: recomputed.append(a) or real(*a))
    got = _assemble(scan)
    steps = np.flatnonzero(got.received)
    assert len(steps) == len(scan) - 2
    assert recomputed == [] and got.energy_mismatches == 0
    np.testing.assert_array_equal(got.sensor_energy[steps], [list(m.sensor_energy) for m in scan[1:-1]])


@pytest.mark.parametrize("tamper", ["scaled", "slightly", "negative", "nan", "short", "swapped"])
def test_present_and_wrong_it_is_found_counted_warned_and_recomputed(scan, tamper, caplog):
    messages = _copy(scan)
    bad = [5, 40, 41, 120]
    for m in (messages[1 + s] for s in bad):
        e = list(m.sensor_energy)
        if tamper == "scaled":
            e[2] *= 1.5
        elif tamper == "slightly":  # 0.1 %: well outside float32 rounding over 3500 samples (≤ 0.042 %)
            e[0] *= 1.001
        elif tamper == "negative":
            e[1] = -e[1]
        elif tamper == "nan":
            e[3] = float("nan")
        elif tamper == "short":
            e = e[:-1]
        else:  # two capsules' energies exchanged: each value plausible, the pairing wrong
            e[0], e[3] = e[3], e[0] * (1.01 if e[0] == e[3] else 1.0)
        del m.sensor_energy[:]
        m.sensor_energy.extend(e)
    with caplog.at_level(logging.WARNING, logger="lelsonar.reconstruct.stream.assembly"):
        got = _assemble(messages)
    assert got.energy_mismatches == len(bad)
    assert sum("disagrees with its waveforms" in r.getMessage() for r in caplog.records) == 1  # once a scan
    truth = np.array([_true_energy(m) for m in scan[1:-1]])
    np.testing.assert_allclose(got.sensor_energy[: len(truth)], truth, rtol=1e-12)
    # and exactly what the untampered samples give
    clean = _assemble(_copy(scan))
    for name in ("sensor_energy", "echo_amplitude", "step_energy", "expected_energy", "ratio"):
        np.testing.assert_array_equal(getattr(got, name), getattr(clean, name), err_msg=name)


def test_absent_it_is_computed(scan):
    messages = _copy(scan)
    for m in messages[1:-1]:
        m.ClearField("sensor_energy")
    got = _assemble(messages)
    clean = _assemble(_copy(scan))
    assert got.energy_mismatches == 0
    truth = np.array([_true_energy(m) for m in scan[1:-1]])
    np.testing.assert_allclose(got.sensor_energy[: len(truth)], truth, rtol=1e-12)
    for name in ("sensor_energy", "echo_amplitude", "step_energy", "expected_energy", "ratio"):
        np.testing.assert_array_equal(getattr(got, name), getattr(clean, name), err_msg=name)


def test_a_mix_of_writers_and_encodings_in_one_scan(scan):
    """Samples with and without energies, int16 waveforms, and a batch cut by the ScanEnd and by a change of
    waveform length: every step gets eq. (10) of its own waveforms."""
    messages = _copy(scan)
    for m in messages[1:-1:3]:
        m.ClearField("sensor_energy")
    for m in messages[2:-1:5]:  # int16 data, energies of the int16 samples as the writer packed them
        for s in m.sensors:
            w = s.waveform
            v = codec.unpack_waveform(w)
            s.waveform.CopyFrom(codec.pack_waveform(v, w.sample_rate, w.t0, int16_scale=1e-4))
        del m.sensor_energy[:]
        m.sensor_energy.extend(_true_energy(m).tolist())
    for m in messages[60:63]:  # shorter waveforms for a few steps, with the energies of those
        for s in m.sensors:
            w = s.waveform
            s.waveform.CopyFrom(codec.pack_waveform(codec.unpack_waveform(w)[:2000], w.sample_rate, w.t0))
        if len(m.sensor_energy):
            del m.sensor_energy[:]
            m.sensor_energy.extend(_true_energy(m).tolist())
    got = _assemble(messages)
    assert got.energy_mismatches == 0
    truth = np.array([_true_energy(m) for m in messages[1:-1]])
    np.testing.assert_allclose(got.sensor_energy[: len(truth)], truth, rtol=1e-12)
    view = got.latest
    np.testing.assert_array_equal(view.waveforms, _waves(messages[-2]))


def test_the_check_refuses_what_is_off_by_more_than_float32_rounding():
    rng = np.random.default_rng(3)
    rate = 2e5
    for _ in range(50):
        w = (rng.standard_normal((4, 3500)) * rng.uniform(1e-3, 10.0)).astype(np.float32)
        exact = (w.astype(np.float64) ** 2).sum(axis=-1) / rate  # eq. (10), in float64 here
        assert waveform_energy_agrees(w, rate, exact.tolist())
        # float32 sums of 3500 terms are within 3501·2⁻²⁴ ≈ 2.1e-4 of the exact sum; 1e-3 off is another value
        for factor in (1 + 1e-3, 1 - 1e-3, 2.0, 0.0):
            for i in range(4):
                wrong = exact.copy()
                wrong[i] *= factor
                assert not waveform_energy_agrees(w, rate, wrong.tolist())
        for bad in (np.nan, np.inf, -exact[0]):
            assert not waveform_energy_agrees(w, rate, [bad, *exact[1:]])
        assert not waveform_energy_agrees(w, rate, exact[:3].tolist())  # not one a waveform
    assert waveform_energy_agrees(np.zeros((2, 10), np.float32), 1e3, [0.0, 0.0])


def test_a_tampered_recording_replays_to_the_final_of_the_true_one(scan, tmp_path, caplog):
    """In an MCAP: the final of a recording whose energies were tampered with is the final of the
    untouched recording, the tampering counted and warned about."""
    tampered = _copy(scan)
    for m in tampered[1:-1:10]:
        e = list(m.sensor_energy)
        e[1] *= 3.0
        del m.sensor_energy[:]
        m.sensor_energy.extend(e)
    paths = {}
    for name, messages in (("true", scan), ("tampered", tampered)):
        paths[name] = tmp_path / f"{name}.mcap"
        with McapRecorder(paths[name]) as rec:
            for i, m in enumerate(messages):
                rec.write(m, log_time_ns=1_700_000_000_000_000_000 + i * 20_000_000)
    finals, services = {}, {}
    with caplog.at_level(logging.WARNING, logger="lelsonar.reconstruct.stream.assembly"):
        for name, path in paths.items():
            services[name] = service = ReconstructionService(ReconstructConfig())
            replay_mcap(path, service)
            (finals[name],) = service.finals.values()
    assert comparable(finals["tampered"]) == comparable(finals["true"])
    assert services["tampered"].ingest.energy_mismatches == len(tampered[1:-1:10])
    assert services["true"].ingest.energy_mismatches == 0
    assert sum("disagrees with its waveforms" in r.getMessage() for r in caplog.records) == 1
    # and in the accounting `reconstruct --source --json` prints on exit
    for name, want in (("tampered", len(tampered[1:-1:10])), ("true", 0)):
        assert services[name].stats_dict()["samples"]["energy_mismatches"] == want
        done = subprocess.run(
            [sys.executable, "-m", "lelsonar", "reconstruct", "--source", str(paths[name]), "--json"],
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert done.returncode == 0, done.stderr
        (line,) = [x for x in done.stderr.splitlines() if x.startswith('{"stats"')]
        assert json.loads(line)["stats"]["samples"]["energy_mismatches"] == want
        assert (f"energy mismatches {want}" in done.stderr) == bool(want)


def test_the_ingest_stage_reads_samples_from_their_payloads_to_the_values_of_the_messages(scan, monkeypatch):
    """Through the ingest stage, every sample after the first is read from its payload (fastwire.place_wire), to the
    arrays of a scan assembled from the parsed messages alone, bit for bit, and the latest step's waveforms;
    a payload encoded otherwise (a field sent twice: the parser keeps the last) is read from the message."""
    from lelsonar.reconstruct.stream.ingest import Ingest

    read = []
    place_wire = assembly.place_wire
    monkeypatch.setattr(assembly, "place_wire", lambda *a: read.append(place_wire(*a)) or read[-1])
    ingest = Ingest()
    for m in scan:
        ingest.accept(m.DESCRIPTOR.full_name, m.SerializeToString())
    (routed,) = ingest.scans.values()
    assert len(read) == len(scan) - 3 and UNREAD not in [status for status, _, _ in read]  # all but the first
    alone = _assemble(_copy(scan))
    for name in (
        "distance",
        "sensor_energy",
        "echo_amplitude",
        "pre_echo_peak",
        "dc_level",
        "range_tof_ratio",
        "gamma",
        "gamma_commanded",
        "step_energy",
        "expected_energy",
        "ratio",
        "time_ns",
        "received",
    ):
        assert getattr(routed, name).tobytes() == getattr(alone, name).tobytes(), name
    np.testing.assert_array_equal(routed.latest.waveforms, _waves(scan[-2]))
    # γ sent again at the end of the payload: protobuf's merge keeps the last value, and so does the scan
    extra = codec.Sample(gamma_measured=0.123).SerializeToString()
    ingest = Ingest()
    for m in scan[:3]:
        ingest.accept(m.DESCRIPTOR.full_name, m.SerializeToString())
    sample = scan[3]
    (ev,) = ingest.accept(sample.DESCRIPTOR.full_name, sample.SerializeToString() + extra)
    assert ev.kind == "sample" and read[-1][0] == UNREAD
    assert ev.scan.gamma[sample.step] == codec.Sample.FromString(sample.SerializeToString() + extra).gamma_measured


# ----------------------------------------------------------------------------- the fast path and the general one
def _peak(w: np.ndarray, rate: float, t0: float, tof: float, window: tuple[float, float]) -> float:
    """The largest |w| over ``window`` (s) after ``tof``, on the waveform's own clock: from the sample nearest
    ``tof + window[0]`` (clipped at 0), ``(window[1] - window[0])·rate`` samples (the definition, §4)."""
    a = max(int(np.rint((tof + window[0] - t0) * rate)), 0)
    return float(np.abs(w[a : a + max(int(round((window[1] - window[0]) * rate)), 1)]).max())


def _check_against_the_waveforms(got: ScanAssembly, messages) -> None:
    """Every step's energies, echo peaks (and, on each RISE_STRIDE-th step, the peaks just before) and DC
    levels against its own waveforms, by capsule id, each on its own clock."""
    from lelsonar.signal.energy import ECHO_PEAK_WINDOW, PRE_ECHO_WINDOW

    row = {c: i for i, c in enumerate(sorted(s.capsule_id for s in messages[1].sensors))}
    for m in messages[1:-1]:
        for s in m.sensors:
            i, w = row[s.capsule_id], s.waveform
            v = codec.unpack_waveform(w)
            assert got.sensor_energy[m.step, i] == pytest.approx(
                (v.astype(np.float64) ** 2).sum() / w.sample_rate, rel=1e-12
            )
            if not s.echo_valid:
                assert np.isnan(got.echo_amplitude[m.step, i])
                continue
            assert got.echo_amplitude[m.step, i] == _peak(v, w.sample_rate, w.t0, s.time_of_flight, ECHO_PEAK_WINDOW)
            if m.step % RISE_STRIDE == 0:
                assert got.pre_echo_peak[m.step, i] == _peak(v, w.sample_rate, w.t0, s.time_of_flight, PRE_ECHO_WINDOW)
                assert got.dc_level[m.step, i] == pytest.approx(abs(v.astype(np.float64).mean()), rel=1e-12)
            else:
                assert np.isnan(got.pre_echo_peak[m.step, i])


def _count_general(monkeypatch) -> list:
    calls = []
    general = ScanAssembly._in_capsule_order
    monkeypatch.setattr(ScanAssembly, "_in_capsule_order", lambda self, *a: calls.append(1) or general(self, *a))
    return calls


def test_the_acquisition_services_samples_take_the_fast_path(scan, monkeypatch):
    """Capsules in the ScanStart's order, float32 waveforms of one length on one clock: one pass, and every
    value what the waveforms give."""
    general = _count_general(monkeypatch)
    got = _assemble(_copy(scan))
    assert general == [] and got.energy_mismatches == 0
    _check_against_the_waveforms(got, scan)


def test_another_writers_order_and_ids_take_the_general_path_to_the_same_values(scan, monkeypatch):
    """The same readings in reverse order under ids 10.. (the carried energies reversed with them): matched by
    id, the same arrays as the fast path's, bit for bit."""
    messages = _copy(scan)
    for c in messages[0].capsules:
        c.capsule_id += 10
    for m in messages[1:-1]:
        for s in m.sensors:
            s.capsule_id += 10
        m.sensors.reverse()
        e = list(m.sensor_energy)[::-1]
        del m.sensor_energy[:]
        m.sensor_energy.extend(e)
    general = _count_general(monkeypatch)
    got = _assemble(messages)
    assert len(general) == len(messages) - 2 and got.energy_mismatches == 0
    _check_against_the_waveforms(got, messages)
    fast = _assemble(_copy(scan))
    for name in (
        "distance",
        "sensor_energy",
        "echo_amplitude",
        "pre_echo_peak",
        "dc_level",
        "range_tof_ratio",
        "step_energy",
        "expected_energy",
        "ratio",
    ):
        np.testing.assert_array_equal(getattr(got, name), getattr(fast, name), err_msg=name)


def test_a_clock_per_capsule_takes_the_general_path_and_each_waveforms_own_clock(scan, monkeypatch):
    """Capsule 1's waveforms start 0.1 ms later and capsule 2's are labelled at another rate, the energies
    carried at each capsule's own rate: accepted (no mismatch), and the peaks found on each one's clock.  An
    energy worked out at capsule 0's rate is found out."""
    messages = _copy(scan)
    for m in messages[1:-1]:
        m.sensors[1].waveform.t0 += 1e-4
        m.sensors[2].waveform.sample_rate *= 1.25
        e = list(m.sensor_energy)
        e[2] /= 1.25  # eq. (10) at the rate the waveform now states
        del m.sensor_energy[:]
        m.sensor_energy.extend(e)
    wrong = messages[40]
    e = list(wrong.sensor_energy)
    e[2] *= 1.25  # as if all four were on capsule 0's clock
    del wrong.sensor_energy[:]
    wrong.sensor_energy.extend(e)
    general = _count_general(monkeypatch)
    got = _assemble(messages)
    assert len(general) == len(messages) - 2
    assert got.energy_mismatches == 1
    _check_against_the_waveforms(got, messages)
