"""The ingest stage's one pass a sample (``step_features.place_step``) refuses, counts and computes what decoding
and the NumPy code before it did: the truth each time is ``codec.decode``'s verdict on the same payload, or
NumPy's own arithmetic on the same samples."""

from __future__ import annotations

import numpy as np
import pytest

from lelsonar import codec
from lelsonar.errors import NonFiniteValueError
from lelsonar.reconstruct.stream.assembly import ScanAssembly
from lelsonar.reconstruct.stream.fastwire import read_sample, sample_header
from lelsonar.reconstruct.stream.ingest import Accepted, Ingest, Rejected
from lelsonar.reconstruct.stream.step_features import PER_CAPSULE, PER_STEP, dc_levels, settle_step
from lelsonar.signal.energy import EnergyModel, energy_ratio, median_range, total_energy
from lelsonar.v1 import scan_pb2

from .conftest import simulated_messages


@pytest.fixture(scope="module")
def scan():
    return simulated_messages("paper-test1", seed=7, steps=24)


def _name(m) -> str:
    return m.DESCRIPTOR.full_name


def _opened(start, samples) -> tuple[Ingest, ScanAssembly]:
    """An ingest with ``start``'s scan open and ``samples`` accepted (the fast path's layout then known), and
    that scan."""
    ingest = Ingest()
    ingest.accept(_name(start), start.SerializeToString())
    (routed,) = ingest.scans.values()
    for m in samples:
        (ev,) = ingest.accept(_name(m), m.SerializeToString())
        assert isinstance(ev, Accepted)
    return ingest, routed


def _with_nan(sample, step: int | None = None):
    bad = type(sample)()
    bad.CopyFrom(sample)
    if step is not None:
        bad.step = step
    w = bad.sensors[2].waveform
    v = np.frombuffer(w.data, dtype="<f4").copy()
    v[123] = np.nan
    w.data = v.tobytes()
    return bad


@pytest.mark.parametrize("kind", range(5))
@pytest.mark.parametrize("n", [1, 7, 8, 9, 127, 128, 129, 3500, 8193])
def test_dc_levels_are_numpys_mean_bit_for_bit(n, kind):
    rng = np.random.default_rng(1000 * kind + n)
    w = [
        rng.standard_normal((4, n)),  # a float32 dynamic range: summed in order
        np.round(rng.standard_normal((4, n)) * 500) * (3.3 / 4096),  # ADC codes in volts: summed exactly
        rng.integers(-2048, 2048, (4, n)) * 2.0**-11 + 0.25,  # with an offset
        np.where(rng.random((4, n)) < 0.5, 1e-40, 0.0),  # subnormal
        rng.standard_normal((4, n)) * 1e30,
    ][kind].astype(np.float32)
    got = np.zeros(4)
    dc_levels(w, got)
    np.testing.assert_array_equal(got, np.abs(w.mean(axis=-1, dtype=np.float64)))


@pytest.mark.parametrize("k", [1, 2, 3, 5, 6, 9])
def test_dc_levels_of_rows_summed_exactly_and_in_order_side_by_side_are_numpys(k):
    """Rows that cannot be summed exactly are summed in order four at a time: any count of them, among rows that
    can, each its own mean."""
    rng = np.random.default_rng(k)
    n = 3500
    exact = rng.random(k) < 0.5
    w = np.where(
        exact[:, None],
        np.round(rng.standard_normal((k, n)) * 500) * (3.3 / 4096),
        rng.standard_normal((k, n)) + rng.standard_normal(k)[:, None],
    ).astype(np.float32)
    got = np.full(k, -1.0)
    dc_levels(w, got)
    np.testing.assert_array_equal(got, np.abs(w.mean(axis=-1, dtype=np.float64)))


@pytest.mark.parametrize("k", range(1, 17))
def test_a_steps_energy_ratio_is_numpys_bit_for_bit(k):
    """E^γ, E0(d_m) and R of each step as it is placed (settle_step) are total_energy's and energy_ratio's
    (NumPy over the whole scan) to the bit: ranges with gaps (no echo), ties, inside and outside the model's
    interval; energies over many decades (where the order of the additions shows)."""
    rng = np.random.default_rng(k)
    steps = 300
    scale = 10.0 ** rng.integers(1, 5, (steps, 1))
    distance = np.round(rng.uniform(0.3, 3.0, (steps, k)) * scale) / scale  # ties where coarsely rounded
    distance[rng.random((steps, k)) < 0.3] = np.nan
    distance[:5] = np.nan  # steps without a range: R 0, E0 not written
    energy = rng.random((steps, k)) * 10.0 ** rng.uniform(-12, 0, (steps, k))
    energy[7] = 0.0
    model = EnergyModel(3.1e6, -1.2e6, 8.0e5, d_min=0.9, d_max=1.8)
    per_capsule = np.full((len(PER_CAPSULE), steps, k), np.nan)
    per_capsule[PER_CAPSULE.index("distance")] = distance
    per_capsule[PER_CAPSULE.index("sensor_energy")] = energy
    per_step = np.zeros((len(PER_STEP), steps))
    scan = np.array([343.0, 2e5, model.phi0, model.phi1, model.phi2, model.d_min, model.d_max])
    for step in range(steps):
        settle_step(per_capsule, per_step, step, scan)
    expected = np.zeros(steps)
    step_energy = total_energy(energy)
    ratio = energy_ratio(step_energy, distance, model, expected=expected)
    got = dict(zip(PER_STEP, per_step))
    assert got["step_energy"].tobytes() == step_energy.tobytes()
    assert got["expected_energy"].tobytes() == expected.tobytes()
    assert got["ratio"].tobytes() == ratio.tobytes()
    assert (ratio[:5] == 0).all() and (ratio[5:] > 0).any()
    # E0 against the model's own NumPy (clip, then the quadratic of eq. 12), which no kernel shares.
    d_m = median_range(distance)
    ranged = np.isfinite(d_m)
    assert expected[ranged].tobytes() == model.expected_energy(d_m[ranged]).tobytes()
    assert ratio[ranged].tobytes() == (step_energy[ranged] / model.expected_energy(d_m[ranged])).tobytes()


def test_non_finite_samples_are_refused_as_decoding_refuses_them_whatever_else_is_wrong(scan):
    """A NaN sample on a scan's fast path, for a step already placed, beyond the schedule, or on another
    scanner's key: refused as NonFiniteValueError (what codec.decode says of it), counted once, never as the
    scan's, and nothing of it placed."""
    start, samples = scan[0], scan[1:-1]
    ingest, routed = _opened(start, samples[:4])
    cases = [
        (_with_nan(samples[5]), {}),
        (_with_nan(samples[2]), {}),
        (_with_nan(samples[6], step=4000), {}),
        (_with_nan(samples[7]), {"key_scanner": "another"}),
    ]
    for i, (bad, kwargs) in enumerate(cases, 1):
        payload = bad.SerializeToString()
        with pytest.raises(NonFiniteValueError) as truth:
            codec.decode(payload, codec.Sample)
        (ev,) = ingest.accept(_name(bad), payload, **kwargs)
        assert isinstance(ev, Rejected) and (ev.error, ev.detail) == ("NonFiniteValueError", str(truth.value))
        assert ingest.rejected == {"NonFiniteValueError": i}
    assert not routed.rejected and routed.duplicates == 0
    assert routed.n_received == 4 and not routed.received[5:].any()
    # the same steps, finite, are placed
    for m in samples[4:8]:
        (ev,) = ingest.accept(_name(m), m.SerializeToString())
        assert isinstance(ev, Accepted) and ev.step == m.step


def test_squares_that_overflow_float32_are_not_refused_and_the_energy_is_recomputed(scan):
    """Finite samples of 1e25 V: their float32 squares overflow, which is no reason to refuse them; the carried
    energy cannot be checked in float32, so it is recomputed (eq. 10 in float64) and counted."""
    start, sample = scan[0], scan[3]
    big = type(sample)()
    big.CopyFrom(sample)
    w = big.sensors[0].waveform
    v = np.frombuffer(w.data, dtype="<f4").copy()
    v[:10] = 1e25
    w.data = v.tobytes()
    truth = (v.astype(np.float64) ** 2).sum() / w.sample_rate
    e = list(big.sensor_energy)
    e[0] = truth
    del big.sensor_energy[:]
    big.sensor_energy.extend(e)
    codec.decode(big.SerializeToString(), codec.Sample)  # valid
    ingest = Ingest()
    ingest.accept(_name(start), start.SerializeToString())
    (ev,) = ingest.accept(_name(big), big.SerializeToString())
    assert isinstance(ev, Accepted)
    assert ingest.energy_mismatches == 1
    assert ev.scan.sensor_energy[big.step, 0] == pytest.approx(truth, rel=1e-12)


def _tag(field: int, wire_type: int) -> bytes:
    return bytes([(field << 3) | wire_type])  # (fields below 16)


def _faults(sample) -> dict:
    """Ways a sample breaks the contract, each as a payload (what a writer could send)."""
    import struct

    def changed(change):
        bad = type(sample)()
        bad.CopyFrom(sample)
        change(bad)
        return bad.SerializeToString()

    def sensor(i, **fields):
        return lambda m: [setattr(m.sensors[i], k, v) for k, v in fields.items()]

    def wave(i, **fields):
        return lambda m: [setattr(m.sensors[i].waveform, k, v) for k, v in fields.items()]

    def int16(m):
        w = m.sensors[2].waveform
        w.CopyFrom(codec.pack_waveform(codec.unpack_waveform(w), w.sample_rate, w.t0, int16_scale=-1e-4))

    plain = sample.SerializeToString()
    return {
        "range beyond 100 m": changed(sensor(1, distance=150.0)),
        "NaN range": changed(sensor(2, distance=float("nan"))),
        "negative time of flight": changed(sensor(0, time_of_flight=-1e-3)),
        "no range on a valid echo": changed(sensor(3, distance=0.0, time_of_flight=0.0)),
        "infinite motor load": changed(lambda m: setattr(m.motor, "load", float("inf"))),
        "NaN gamma": changed(lambda m: setattr(m, "gamma_measured", float("nan"))),
        "truncated waveform": changed(wave(3, data=sample.sensors[3].waveform.data[:-4])),
        "oversized waveform": changed(wave(1, sample_count=70_000)),
        "unknown encoding": changed(wave(0, encoding=7)),
        "zero sample rate": changed(wave(0, sample_rate=0.0)),
        "infinite t0": changed(wave(0, t0=float("inf"))),
        "int16 of negative scale": changed(int16),
        "step beyond max_steps": changed(lambda m: setattr(m, "step", 5000)),
        "NaN sample": _with_nan(sample).SerializeToString(),
        # on the wire: what the parser keeps of a field sent twice is the last value
        "NaN gamma sent again": plain + _tag(7, 1) + struct.pack("<d", float("nan")),
        "a fifth reading, of a NaN range": plain
        + codec.Sample(
            sensors=[scan_pb2.SensorReading(capsule_id=4, echo_valid=True, distance=float("nan"))]
        ).SerializeToString(),
    }


@pytest.mark.parametrize("fault", list(_faults(simulated_messages("paper-test1", seed=7, steps=24)[5])))
def test_a_sample_on_a_scans_fast_path_is_refused_as_decoding_refuses_it(scan, fault):
    """A sample for an open scan whose layout is known is read from its payload and checked in the pass that
    places it; whatever it breaks is refused with codec.decode's error and words (the culprit named), counted as
    the ingest's and never the scan's, and nothing of it placed; the same step, valid, is placed after."""
    start, samples = scan[0], scan[1:-1]
    payload = _faults(samples[4])[fault]
    with pytest.raises(codec.DecodeError) as truth:
        codec.decode(payload, codec.Sample)
    ingest, routed = _opened(start, samples[:4])
    (ev,) = ingest.accept(_name(samples[4]), payload)
    assert isinstance(ev, Rejected) and (ev.error, ev.detail) == (type(truth.value).__name__, str(truth.value))
    assert ingest.rejected == {type(truth.value).__name__: 1} and not routed.rejected
    assert routed.n_received == 4 and not routed.received[4:].any() and routed.energy_mismatches == 0
    (ev,) = ingest.accept(_name(samples[4]), samples[4].SerializeToString())
    assert isinstance(ev, Accepted) and ev.step == samples[4].step and routed.n_received == 5


def test_the_limits_hold_on_a_scans_fast_path(scan):
    """A sample not validated is placed only within the limits it is checked against (the steps, the capsules,
    the waveform's length), which a ScanStart validated under other limits does not bound: otherwise it is left
    to the caller to validate (-1 from add_payload, None from add), and nothing of it is placed."""
    start, samples = scan[0], scan[1:-1]
    sample = samples[4]
    n, k = sample.sensors[0].waveform.sample_count, len(sample.sensors)
    for limits in (
        codec.DecodeLimits(max_steps=sample.step),
        codec.DecodeLimits(max_sensors=k - 1),
        codec.DecodeLimits(max_waveform_samples=n - 1),
    ):
        with pytest.raises(codec.DecodeError):
            codec.validate_body(sample, limits)
        routed = ScanAssembly(start)
        for m in samples[:4]:
            assert routed.add(m)
        payload, time_ns = sample.SerializeToString(), sample.acquisition_time_ns
        body = sample_header(payload)[-1]
        assert routed.add_payload(payload, body, sample.step, time_ns, "live", limits) == -1
        assert routed.add(sample, limits=limits) is None
        assert routed.n_received == 4 and not routed.received[4:].any()
        assert routed.add_payload(payload, body, sample.step, time_ns, "live", codec.DEFAULT_LIMITS) == sample.step
        assert routed.received[sample.step]


def _varied(sample) -> list:
    """Valid variants of a sample, some on the fast path's layout and some not."""

    def changed(change):
        m = type(sample).FromString(sample.SerializeToString())
        change(m)
        return m

    return [
        sample,
        changed(lambda m: setattr(m.sensors[1], "echo_valid", False)),
        changed(lambda m: setattr(m.sensors[0], "distance", -0.0)),
        changed(lambda m: m.ClearField("sensor_energy")),
        changed(lambda m: m.sensor_energy.append(1.0)),
        changed(lambda m: m.ClearField("motor")),
        changed(lambda m: setattr(m, "gamma_measured", 0.0)),
        changed(lambda m: setattr(m.motor, "error_bits", 5)),
        changed(lambda m: setattr(m.sensors[0].waveform, "scale", 3.0)),
        changed(lambda m: setattr(m.sensors[2], "capsule_id", 7)),  # not the layout: ids
        changed(lambda m: setattr(m.sensors[2].waveform, "t0", m.sensors[2].waveform.t0 + 1e-6)),  # clocks
        changed(lambda m: setattr(m.sensors[3].waveform, "encoding", 2)),  # encodings
        changed(lambda m: m.sensors.reverse()),  # order
        changed(lambda m: m.sensors.pop()),  # count
        changed(lambda m: m.sensors[0].ClearField("waveform")),
    ]


def _rewired(payload: bytes, rng) -> list[bytes]:
    """The payload encoded otherwise, or broken: fields sent twice, unknown fields, energies unpacked or in two
    runs, a reading more, truncations, flipped bits."""
    import struct

    tail = [
        _tag(7, 1) + struct.pack("<d", 0.5),
        bytes([0xF8, 0x06, 0x05]),
        _tag(15, 2) + b"\x02ab",
        _tag(15, 5) + b"abcd",
        _tag(10, 1) + struct.pack("<d", 2.5),
        _tag(6, 0) + b"\x01",
        _tag(9, 0) + b"\x01",
        _tag(8, 2) + bytes([9]) + _tag(2, 1) + struct.pack("<d", 0.25),
        codec.Sample(sensors=[scan_pb2.SensorReading(capsule_id=4)]).SerializeToString(),
    ]
    out = [payload + t for t in tail] + [
        _tag(6, 0) + b"\x01" + payload,
        codec.Sample(sensor_energy=[1.0, 2.0]).SerializeToString() + payload,
    ]
    out += [payload[:cut] for cut in (1, 7, 100, len(payload) // 2, len(payload) - 3)]
    for _ in range(40):
        b = bytearray(payload)
        j = rng.integers(min(400, len(b))) if rng.random() < 0.7 else rng.integers(len(b))
        b[j] = rng.integers(256)
        out.append(bytes(b))
    return out


def test_a_payload_is_read_bit_for_bit_as_the_parser_reads_it_or_left_to_the_parser(scan):
    """read_sample against the parser (upb), the truth: what it reads of a payload — γ, the motor, each reading's
    range, the carried energies, every waveform sample — is bit for bit what the parsed message holds, and it
    reads exactly the samples on the fast path's layout unless their encoding is not plain (a field sent twice,
    of another wire type); a payload the parser refuses never reaches it."""
    rng = np.random.default_rng(12)
    start, samples = scan[0], scan[1:-1]
    k = len(start.capsules)
    ids = np.array(sorted(c.capsule_id for c in start.capsules), np.int64)
    w0 = samples[0].sensors[0].waveform
    n = w0.sample_count
    fast_layout = [v for i in ids for v in (i, n, w0.sample_rate, w0.t0, scan_pb2.WAVEFORM_ENCODING_FLOAT32_LE, 4 * n)]
    counts = {"read": 0, "left": 0, "refused by the parser": 0}
    for sample in samples[::3]:
        plain = [m.SerializeToString() for m in _varied(sample)]
        for i, payload in enumerate(plain + _rewired(plain[0], rng)):
            try:
                m = codec.Sample.FromString(payload)
            except Exception:
                counts["refused by the parser"] += 1
                continue
            values = np.zeros(6 * k + 5)
            values[: 2 * k] = [w0.sample_rate, w0.t0] * k
            values[2 * k :] = rng.standard_normal(4 * k + 5)  # a previous sample's readings, to be overwritten
            waveforms = np.full((k, n), np.nan, np.float32)
            header = sample_header(payload)
            carried = -1 if header is None else read_sample(payload, header[-1], ids, values, waveforms)
            ranges, layout, data = codec.sample_readings(m.sensors)
            if i < len(plain):  # plainly encoded: read exactly when on the layout
                assert (carried >= 0) == (layout == fast_layout), i
            if carried < 0:
                counts["left"] += 1
                continue
            counts["read"] += 1
            assert header[:5] == (m.schema_version, m.scanner_id, m.scan_id, m.step, m.acquisition_time_ns)
            assert layout == fast_layout
            e = m.sensor_energy[:]
            assert carried == len(e)
            truth = np.array(
                [
                    m.gamma_measured,
                    m.gamma_commanded,
                    m.motor.load,
                    m.motor.voltage,
                    m.motor.temperature,
                    *ranges,
                    *e[:k],
                ],
                dtype=np.float64,
            )
            assert values[2 * k : 5 * k + 5 + min(carried, k)].tobytes() == truth.tobytes()
            assert waveforms.tobytes() == b"".join(data)
    assert min(counts.values()) > 10, counts


def test_a_live_payload_is_read_as_the_same_bytes(scan):
    """A payload as Zenoh hands it over (ZBytes) is placed as its bytes are: the same events and arrays."""
    import zenoh

    got = []
    for wrap in (bytes, zenoh.ZBytes):
        ingest = Ingest()
        events = [ev for m in scan for ev in ingest.accept(_name(m), wrap(m.SerializeToString()))]
        assert [type(ev) for ev in events] == [Accepted] * len(scan)
        got.append(events[0].scan)
    for name in ("distance", "sensor_energy", "echo_amplitude", "gamma", "ratio", "time_ns", "received"):
        assert getattr(got[0], name).tobytes() == getattr(got[1], name).tobytes(), name


def _start_faults(start) -> dict:
    """ScanStarts of a second scan of ``start``'s scanner, each breaking one check of the contract."""

    def changed(edit):
        bad = type(start)()
        bad.CopyFrom(start)
        bad.scan_id, bad.start_time_ns = start.scan_id + 1, start.start_time_ns + 1
        edit(bad)
        return bad.SerializeToString()

    def twin_ids(m):
        m.capsules[1].capsule_id = m.capsules[0].capsule_id

    return {
        "sound speed": changed(lambda m: setattr(m, "sound_speed", 1000.0)),
        "capsule position": changed(lambda m: setattr(m.capsules[2].position, "x", float("nan"))),
        "steps": changed(lambda m: setattr(m, "steps", 0)),
        "schema version": changed(lambda m: setattr(m, "schema_version", m.schema_version + 1)),
        "energy model": changed(lambda m: setattr(m.energy_model, "phi0", float("inf"))),
        "capsule ids": changed(twin_ids),
    }


def test_the_scan_of_a_repeated_scan_start_is_made_as_from_a_fresh_one(scan):
    """A scanner's ScanStarts equal but for their scan and time make scans that share what the first one's derived
    (geometry, capsule ids, speed of sound, energy model): the values a scan made from the message alone has; a
    ScanStart that differs otherwise derives its own."""
    start = scan[0]
    ingest = Ingest()
    made = []
    for scan_id, sound_speed in ((1, start.sound_speed), (2, start.sound_speed), (3, 300.0), (4, 300.0)):
        m = type(start)()
        m.CopyFrom(start)
        m.scan_id, m.start_time_ns, m.sound_speed = scan_id, scan_id, sound_speed
        (ev,) = ingest.accept(_name(start), m.SerializeToString())
        assert isinstance(ev, Accepted) and ev.scan.start == m
        fresh = ScanAssembly(m)
        assert ev.scan.geometry == fresh.geometry and ev.scan.sound_speed == fresh.sound_speed
        assert ev.scan.energy_model == fresh.energy_model
        assert ev.scan.energy_model_problem == fresh.energy_model_problem
        assert ev.scan._capsule_ids == fresh._capsule_ids and np.array_equal(ev.scan._ids, fresh._ids)
        made.append(ev.scan)
    assert made[1].description is made[0].description and made[3].description is made[2].description
    assert made[2].sound_speed == 300.0 != made[0].sound_speed


@pytest.mark.parametrize("fault", list(_start_faults(simulated_messages("paper-test1", seed=7, steps=2)[0])))
def test_a_scanners_next_scan_start_is_checked_as_decoding_checks_it(scan, fault):
    """A scanner's ScanStart equal to its last valid one but for its scan and time passes as that one did;
    one that breaks a check after it is refused with codec.decode's error and words, as it is by a fresh ingest;
    a valid one that differs otherwise is accepted and is the one compared with next; and other limits are
    checked again."""
    start = scan[0]
    payload = _start_faults(start)[fault]
    with pytest.raises(codec.DecodeError) as truth:
        codec.decode(payload, codec.ScanStart)
    ingest = Ingest()
    (ev,) = ingest.accept(_name(start), start.SerializeToString())
    assert isinstance(ev, Accepted)
    (ev,) = ingest.accept(_name(start), payload)
    assert isinstance(ev, Rejected) and (ev.error, ev.detail) == (type(truth.value).__name__, str(truth.value))
    assert ingest.rejected == {type(truth.value).__name__: 1}
    (fresh,) = Ingest().accept(_name(start), payload)
    assert (fresh.error, fresh.detail) == (ev.error, ev.detail)
    for scan_id, sound_speed in ((start.scan_id + 2, start.sound_speed), (start.scan_id + 3, 300.0)):
        next_start = type(start)()
        next_start.CopyFrom(start)
        next_start.scan_id, next_start.start_time_ns, next_start.sound_speed = scan_id, scan_id, sound_speed
        (ev,) = ingest.accept(_name(start), next_start.SerializeToString())
        assert isinstance(ev, Accepted) and ev.scan.start == next_start
    ingest.limits = codec.DecodeLimits(max_sensors=len(start.capsules) - 1)
    again = type(start)()
    again.CopyFrom(next_start)
    again.scan_id += 1
    with pytest.raises(codec.DecodeError) as truth:
        codec.decode(again.SerializeToString(), codec.ScanStart, ingest.limits)
    (ev,) = ingest.accept(_name(start), again.SerializeToString())
    assert isinstance(ev, Rejected) and (ev.error, ev.detail) == (type(truth.value).__name__, str(truth.value))
