"""The ingest's fast path reads a ``Sample`` payload as ``protobuf`` does, or leaves it to ``protobuf``.

Differential tests against the parser (upb), the truth: on valid messages of every shape (any header, any
number of readings in any order, every waveform encoding, energies packed or not, unknown fields) and on their
bytes mutated (flipped, cut, spliced, a field sent twice), whatever :mod:`lelsonar.reconstruct.stream.fastwire`
reads is bit for bit what the parsed message holds, and it reads nothing from bytes the parser refuses.
"""

from __future__ import annotations

import struct

import numpy as np
from google.protobuf.message import DecodeError
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from lelsonar import codec
from lelsonar.reconstruct.stream import assembly
from lelsonar.reconstruct.stream.assembly import ScanAssembly
from lelsonar.reconstruct.stream.fastwire import GROW, UNREAD, read_sample, sample_header
from lelsonar.reconstruct.stream.ingest import Ingest, Rejected
from lelsonar.reconstruct.stream.step_features import AGREED
from lelsonar.v1 import scan_pb2

from .conftest import simulated_messages

FLOAT32 = scan_pb2.WAVEFORM_ENCODING_FLOAT32_LE
SETTINGS = settings(max_examples=200, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])

doubles = st.floats(allow_nan=True, allow_infinity=True, width=64)


@st.composite
def waveforms(draw, n: int | None = None, rate: float | None = None, t0: float | None = None):
    encoding = draw(st.sampled_from([FLOAT32, FLOAT32, FLOAT32, scan_pb2.WAVEFORM_ENCODING_INT16_LE, 0]))
    count = draw(st.integers(0, 12)) if n is None else n
    size = 4 * count if encoding == FLOAT32 and draw(st.booleans()) else draw(st.integers(0, 48))
    return scan_pb2.Waveform(
        encoding=encoding,
        data=draw(st.binary(min_size=size, max_size=size)),
        sample_count=count,
        sample_rate=draw(doubles) if rate is None else rate,
        t0=draw(doubles) if t0 is None else t0,
    )


@st.composite
def samples(draw) -> tuple[codec.Sample, list[int], int, float, float]:
    """A ``Sample`` of any shape, and a layout (capsule ids, waveform length, clock) it may or may not be on."""
    k = draw(st.integers(1, 5))
    ids = sorted(draw(st.lists(st.integers(0, 2**32 - 1), min_size=k, max_size=k, unique=True)))
    n = draw(st.integers(0, 10))
    rate, t0 = draw(doubles), draw(doubles)
    on_layout = draw(st.booleans())
    sensors = []
    for i in range(draw(st.integers(0, k + 1)) if not on_layout else k):
        capsule = ids[i] if on_layout and i < k else draw(st.integers(0, 2**32 - 1))
        wave = draw(waveforms(n, rate, t0) if on_layout else waveforms())
        if on_layout:
            wave.encoding, wave.data = FLOAT32, draw(st.binary(min_size=4 * n, max_size=4 * n))
        sensors.append(
            scan_pb2.SensorReading(
                capsule_id=capsule,
                echo_valid=draw(st.booleans()),
                time_of_flight=draw(doubles),
                distance=draw(doubles),
                waveform=wave,
            )
        )
    sample = codec.Sample(
        schema_version=draw(st.integers(0, 2**32 - 1)),
        scanner_id=draw(st.text(max_size=12)),
        scan_id=draw(st.integers(0, 2**64 - 1)),
        step=draw(st.integers(0, 2**32 - 1)),
        acquisition_time_ns=draw(st.integers(-(2**63), 2**63 - 1)),
        gamma_commanded=draw(doubles),
        gamma_measured=draw(doubles),
        sensors=sensors,
        sensor_energy=draw(st.lists(doubles, max_size=k + 2)),
    )
    if draw(st.booleans()):
        motor = scan_pb2.MotorStatus(load=draw(doubles), voltage=draw(doubles), temperature=draw(doubles))
        sample.motor.CopyFrom(motor)
    return sample, ids, n, rate, t0


def _unknown_field(number: int, value: bytes) -> bytes:
    """A length-delimited field this build does not know (``number`` < 16, ``value`` < 128 bytes: one-byte
    varints)."""
    return bytes([(number << 3) | 2, len(value)]) + value


def _bits(x: float) -> bytes:
    return struct.pack("<d", x)


def _check(payload: bytes, ids: list[int], n: int, rate: float, t0: float) -> None:
    """What the fast path reads of ``payload`` (its header, then its body, as the ingest reads them) against what
    the parser reads of it."""
    try:
        truth = codec.Sample.FromString(payload)
    except DecodeError:
        truth = None
    header = sample_header(payload)
    if header is None:
        return  # left to the parser: the ingest reads a body only after its header (its scanner id UTF-8)
    k = len(ids)
    values = np.zeros(6 * k + 5)
    values[: 2 * k] = [rate, t0] * k
    waves = np.zeros((k, n), np.float32)
    carried = read_sample(payload, header[-1], np.array(ids, np.int64), values, waves)
    if carried < 0:
        return  # the header alone routes, and nothing is placed on it: the body's walk decides
    assert truth is not None, "read a payload the parser refuses"
    assert header[:5] == (truth.schema_version, truth.scanner_id, truth.scan_id, truth.step, truth.acquisition_time_ns)
    sensors = list(truth.sensors)
    assert [s.capsule_id for s in sensors] == ids
    for s in sensors:
        w = s.waveform
        assert (w.encoding, w.sample_count, len(w.data)) == (FLOAT32, n, 4 * n)
        assert _bits(w.sample_rate) == _bits(rate) and _bits(w.t0) == _bits(t0)
    ranges, _, data = codec.sample_readings(sensors)
    m = truth.motor
    expected = [truth.gamma_measured, truth.gamma_commanded, m.load, m.voltage, m.temperature, *ranges]
    energy = list(truth.sensor_energy)
    assert carried == len(energy)
    expected += energy[:k]
    got = values[2 * k : 2 * k + len(expected)]
    assert got.tobytes() == np.array(expected, np.float64).tobytes()
    assert waves.tobytes() == b"".join(data)


@SETTINGS
@given(samples(), st.booleans(), st.binary(max_size=6))
def test_valid_messages_are_read_as_the_parser_reads_them(drawn, unknown: bool, extra: bytes):
    sample, ids, n, rate, t0 = drawn
    payload = sample.SerializeToString() + (_unknown_field(15, extra) if unknown else b"")
    _check(payload, ids, n, rate, t0)
    # A plainly encoded sample on its scan's layout is always read: the fast path is the path.
    on_layout = [s.capsule_id for s in sample.sensors] == ids and all(
        s.waveform.encoding == FLOAT32
        and s.waveform.sample_count == n
        and len(s.waveform.data) == 4 * n
        and _bits(s.waveform.sample_rate) == _bits(rate)
        and _bits(s.waveform.t0) == _bits(t0)
        for s in sample.sensors
    )
    k = len(ids)
    values = np.zeros(6 * k + 5)
    values[: 2 * k] = [rate, t0] * k
    header = sample_header(payload)
    assert header is not None
    read = read_sample(payload, header[-1], np.array(ids, np.int64), values, np.zeros((k, n), np.float32))
    assert (read >= 0) == on_layout


@SETTINGS
@given(samples(), st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 255)), min_size=1, max_size=4))
def test_mutated_bytes_are_read_as_the_parser_reads_them_or_left_to_it(drawn, flips):
    sample, ids, n, rate, t0 = drawn
    payload = bytearray(sample.SerializeToString())
    for at, value in flips:
        if payload:
            payload[at % len(payload)] = value
    _check(bytes(payload), ids, n, rate, t0)


@SETTINGS
@given(samples(), st.integers(0, 10**6), st.integers(0, 10**6), st.sampled_from(["cut", "splice", "twice"]))
def test_cut_spliced_or_repeated_fields_are_read_as_the_parser_reads_them_or_left_to_it(drawn, a, b, how):
    sample, ids, n, rate, t0 = drawn
    payload = sample.SerializeToString()
    if how == "cut":
        payload = payload[: a % (len(payload) + 1)]
    elif how == "splice":
        i, j = sorted((a % (len(payload) + 1), b % (len(payload) + 1)))
        payload = payload[:i] + payload[j:] + payload[i:j]
    else:  # a field sent again at the end: the parser keeps the last (or merges), the fast path leaves it
        payload += codec.Sample(step=b, gamma_measured=float(a), scanner_id="x").SerializeToString()
    _check(payload, ids, n, rate, t0)


def test_a_header_field_after_the_body_leaves_the_payload_to_the_parser():
    """The header is read up to the first other field; one sent again after the body (the parser keeps the
    last) is the body's walk's refusal, and the ingest then places the sample where the parser puts it."""
    start, *samples, _ = simulated_messages()
    ingest = Ingest()
    name = codec.Sample.DESCRIPTOR.full_name
    for m in (start, samples[0], samples[1]):
        ingest.accept(m.DESCRIPTOR.full_name, m.SerializeToString())
    sample = samples[2]
    moved = samples[5].step
    payload = sample.SerializeToString() + codec.Sample(step=moved).SerializeToString()
    header = sample_header(payload)
    assert header is not None and header[3] == sample.step  # the first step: what the header routes on
    k = len(sample.sensors)
    n = sample.sensors[0].waveform.sample_count
    values = np.zeros(6 * k + 5)
    w = sample.sensors[0].waveform
    values[: 2 * k] = [w.sample_rate, w.t0] * k
    ids = np.array(sorted(s.capsule_id for s in sample.sensors), np.int64)
    assert read_sample(payload, header[-1], ids, values, np.zeros((k, n), np.float32)) == -1
    (event,) = ingest.accept(name, payload)
    assert event.kind == "sample" and event.step == moved == codec.Sample.FromString(payload).step
    scan = event.scan
    assert scan.received[moved] and not scan.received[sample.step]


def placed_from_payloads(monkeypatch) -> list:
    """What each call of the assembly's fast path returns, in order (its status, carried energies, step)."""
    calls: list = []
    place_wire = assembly.place_wire
    monkeypatch.setattr(assembly, "place_wire", lambda *a: calls.append(place_wire(*a)) or calls[-1])
    return calls


def test_waveforms_read_where_they_lie_at_every_alignment_are_the_parsed_ones(monkeypatch):
    """The fast path reads each waveform where it lies in the payload, whatever its bytes' alignment (an unknown
    field of 0–3 bytes after the header shifts them): the scan's arrays are bit for bit those of the same
    payloads parsed by upb and placed from the messages."""
    start, *samples, end = simulated_messages()
    payloads = []
    for i, m in enumerate(samples):
        payload = m.SerializeToString()
        body = sample_header(payload)[-1]
        payloads.append(payload[:body] + _unknown_field(15, bytes(i % 4)) + payload[body:])
    data_at = {payloads[i].find(m.sensors[0].waveform.data) % 4 for i, m in enumerate(samples)}
    assert data_at == {0, 1, 2, 3}
    read_in_place = placed_from_payloads(monkeypatch)
    scans = []
    for fast in (True, False):
        ingest = Ingest(fast_path=fast)
        ingest.accept(start.DESCRIPTOR.full_name, start.SerializeToString())
        for payload in payloads:
            (event,) = ingest.accept(codec.Sample.DESCRIPTOR.full_name, payload)
            assert event.kind == "sample"
        assert not ingest.rejected
        (scan,) = ingest.scans.values()
        scans.append(scan)
    read, parsed = scans
    assert len(read_in_place) == len(samples) - 1  # all but the first
    assert UNREAD not in [status for status, _, _ in read_in_place]
    for name in ("distance", "sensor_energy", "echo_amplitude", "pre_echo_peak", "dc_level", "range_tof_ratio"):
        assert getattr(read, name).tobytes() == getattr(parsed, name).tobytes(), name
    for name in ("gamma", "step_energy", "expected_energy", "ratio", "time_ns", "received"):
        assert getattr(read, name).tobytes() == getattr(parsed, name).tobytes(), name
    assert_same_windows(read, parsed)
    np.testing.assert_array_equal(read.latest.waveforms, parsed.latest.waveforms)


def assert_same_windows(read: ScanAssembly, parsed: ScanAssembly) -> None:
    """The timing windows the two scans hold are bit for bit the same: where each starts (``_timing_at``, NaN: none
    kept), and each kept window (those the scan reads; a window not kept is never written, nor read)."""
    assert read._timing_rate == parsed._timing_rate
    assert read._timing_windows.shape == parsed._timing_windows.shape
    assert read._timing_at.tobytes() == parsed._timing_at.tobytes()
    kept = np.isfinite(parsed._timing_at)
    assert read._timing_windows[kept].tobytes() == parsed._timing_windows[kept].tobytes()


def test_a_payload_that_starts_as_the_last_one_but_routes_elsewhere_is_left_to_the_parser():
    """The bytes that routed a key's last sample route the next one that starts with them, unless it names its
    scan again after them (the parser keeps the last value): that one goes where the parser puts it.  A scan
    closed routes nothing more: its samples are late."""
    start, *samples, _ = simulated_messages()
    other = codec.ScanStart.FromString(start.SerializeToString())
    other.scan_id = start.scan_id + 1
    name = codec.Sample.DESCRIPTOR.full_name
    ingest = Ingest()
    for m in (start, other):
        ingest.accept(m.DESCRIPTOR.full_name, m.SerializeToString(), key_scanner="s1")
    for m in samples[:3]:
        (event,) = ingest.accept(name, m.SerializeToString(), key_scanner="s1")
        assert event.kind == "sample" and event.scan.start.scan_id == start.scan_id
    again = codec.Sample(scan_id=other.scan_id).SerializeToString()
    routed = sample_header(samples[0].SerializeToString())[-2]
    assert routed
    third, fourth = samples[3].SerializeToString(), samples[4].SerializeToString()
    for moved in (third + again, fourth[:routed] + again + fourth[routed:]):
        assert moved[:routed] == samples[0].SerializeToString()[:routed]
        truth = codec.Sample.FromString(moved)
        assert truth.scan_id == other.scan_id
        (event,) = ingest.accept(name, moved, key_scanner="s1")
        assert event.kind == "sample" and event.scan.start.scan_id == other.scan_id
        assert event.step == truth.step and event.scan.received[truth.step]
    ingest.close(("s1", start.scan_id))
    (event,) = ingest.accept(name, samples[5].SerializeToString(), key_scanner="s1")
    assert isinstance(event, Rejected) and event.error == "LateMessage"


def test_a_step_beyond_the_rows_held_grows_the_scan_and_is_read_from_its_payload(monkeypatch):
    """The scan's arrays grow with the highest step that arrives: a sample read from its payload whose step lies
    beyond them has them grown first, then is placed where the parser puts it, as the same sample parsed."""
    start, *samples, _ = simulated_messages()
    start.steps = 3 * ScanAssembly.INITIAL_ROWS
    far = codec.Sample.FromString(samples[2].SerializeToString())
    far.step = start.steps - 1
    read_in_place = placed_from_payloads(monkeypatch)
    scans = []
    for fast in (True, False):
        ingest = Ingest(fast_path=fast)
        for m in (start, samples[0], samples[1], far):
            (event,) = ingest.accept(m.DESCRIPTOR.full_name, m.SerializeToString())
            assert not isinstance(event, Rejected)
        (scan,) = ingest.scans.values()
        assert scan.received[far.step] and len(scan.received) == start.steps
        scans.append(scan)
    assert [status for status, _, _ in read_in_place] == [AGREED, GROW, AGREED]
    read, parsed = scans
    for name in ("distance", "sensor_energy", "echo_amplitude", "dc_level", "gamma", "ratio", "time_ns", "received"):
        assert getattr(read, name).tobytes() == getattr(parsed, name).tobytes(), name


def test_the_arguments_kept_for_a_scan_follow_its_arrays_and_limits(monkeypatch):
    """The fast path keeps a scan's arguments while its arrays and limits stay: as the arrays grow (a few rows at
    first), by the fast path or by the parser's (a sample that sends its step twice, at each row count, and the
    step before it after it), and under limits of another object partway (equal, and then a schedule beyond them),
    every sample is still read from its payload into the scan's current arrays, bit for bit those of the payloads
    parsed."""
    monkeypatch.setattr(ScanAssembly, "INITIAL_ROWS", 3)
    start, *samples, _ = simulated_messages()
    samples = [m for m in samples if m.step < start.steps - 1]  # (within the last limits' schedule)
    twice = {3, 6, 12, 24, 48}  # row counts reached by the parser (a step field sent twice); 96 by the fast path
    # The step before each comes after it, into the grown arrays (where the arguments of before would lose it).
    samples.sort(key=lambda m: m.step + 1.5 if m.step + 1 in twice else m.step)
    payloads = []
    for m in samples:
        payload = m.SerializeToString()
        if m.step in twice:
            routed = sample_header(payload)[-2]
            payload = payload[:routed] + codec.Sample(step=m.step).SerializeToString() + payload[routed:]
        payloads.append(payload)
    read_in_place = placed_from_payloads(monkeypatch)
    scans = []
    for fast in (True, False):
        ingest = Ingest(fast_path=fast)
        ingest.accept(start.DESCRIPTOR.full_name, start.SerializeToString())
        for i, payload in enumerate(payloads):
            if i == len(samples) // 3:
                ingest.limits = codec.DecodeLimits(**vars(codec.DEFAULT_LIMITS))  # equal, another object
            if i == 2 * len(samples) // 3:  # a schedule beyond the limits: each step checked against them
                ingest.limits = codec.DecodeLimits(**{**vars(codec.DEFAULT_LIMITS), "max_steps": start.steps - 1})
            (event,) = ingest.accept(codec.Sample.DESCRIPTOR.full_name, payload)
            assert event.kind == "sample", event
        assert not ingest.rejected
        (scan,) = ingest.scans.values()
        scans.append(scan)
    read, parsed = scans
    assert len(read.received) > 3 * ScanAssembly.INITIAL_ROWS  # grown, more than once
    statuses = [status for status, _, _ in read_in_place]
    assert statuses.count(GROW) >= 1 and statuses.count(UNREAD) == len(twice)
    assert len(statuses) - statuses.count(GROW) == len(samples) - 1  # all but the first, once each
    for name in ("distance", "sensor_energy", "echo_amplitude", "dc_level", "gamma", "ratio", "time_ns", "received"):
        assert getattr(read, name).tobytes() == getattr(parsed, name).tobytes(), name
    assert read._timing_windows.tobytes() == parsed._timing_windows.tobytes()


def _scan_pair(start, samples, **first_changes) -> list[tuple[str, bytes]]:
    """Payloads of two scans of one scanner: ``start`` and ``samples``, then the same as the next scan, its first
    sample with ``first_changes`` to each of its waveforms."""
    out = [(start.DESCRIPTOR.full_name, start.SerializeToString())]
    out += [(m.DESCRIPTOR.full_name, m.SerializeToString()) for m in samples]
    start.scan_id += 1
    out.append((start.DESCRIPTOR.full_name, start.SerializeToString()))
    for i, m in enumerate(samples):
        m = codec.Sample.FromString(m.SerializeToString())
        m.scan_id = start.scan_id
        if i == 0:
            for name, value in first_changes.items():
                for sensor in m.sensors:
                    setattr(sensor.waveform, name, value)
        out.append((m.DESCRIPTOR.full_name, m.SerializeToString()))
    return out


def _both_ways(payloads: list[tuple[str, bytes]]) -> tuple[ScanAssembly, ScanAssembly]:
    """The second scan, of the payloads read on the fast path and of them parsed."""
    scans = []
    for fast in (True, False):
        ingest = Ingest(fast_path=fast)
        for name, payload in payloads:
            (event,) = ingest.accept(name, payload)
            assert not isinstance(event, Rejected), event
        scans.append(list(ingest.scans.values())[1])
    return scans[0], scans[1]


def _assert_same_scan(read: ScanAssembly, parsed: ScanAssembly) -> None:
    for name in ("distance", "sensor_energy", "echo_amplitude", "pre_echo_peak", "dc_level", "range_tof_ratio"):
        assert getattr(read, name).tobytes() == getattr(parsed, name).tobytes(), name
    for name in ("gamma", "step_energy", "expected_energy", "ratio", "time_ns", "received"):
        assert getattr(read, name).tobytes() == getattr(parsed, name).tobytes(), name
    assert read.layout == parsed.layout
    assert_same_windows(read, parsed)


def test_a_scans_first_sample_is_read_on_its_scanners_last_layout(monkeypatch):
    """The first sample of a scanner's next scan is read straight from its payload on the layout its last scan's
    showed (none parsed): the scan is bit for bit the one of the same payloads parsed."""
    start, *samples, _ = simulated_messages(steps=24)
    payloads = _scan_pair(start, samples)
    read_in_place = placed_from_payloads(monkeypatch)
    read, parsed = _both_ways(payloads)
    statuses = [status for status, _, _ in read_in_place]
    assert len(statuses) == 2 * len(samples) - 1 and UNREAD not in statuses  # all but the first scan's first
    assert np.isfinite(read._timing_at).sum() > len(samples)  # windows kept, compared
    _assert_same_scan(read, parsed)


def test_a_first_sample_on_another_layout_is_parsed_as_in_a_new_scan(monkeypatch):
    """A scanner's next scan whose first sample is not on its last layout (another clock) is as if no layout had
    been expected: that sample is left to the parser (nothing written), which shows the scan its own
    layout and timing windows' rate, and the scan is bit for bit the one of the same payloads parsed."""
    start, *samples, _ = simulated_messages(steps=24)
    rate = samples[0].sensors[0].waveform.sample_rate
    for change in ({"sample_rate": 2 * rate}, {"t0": 1e-6}):
        payloads = _scan_pair(codec.ScanStart.FromString(start.SerializeToString()), samples, **change)
        read_in_place = placed_from_payloads(monkeypatch)
        read, parsed = _both_ways(payloads)
        statuses = [status for status, _, _ in read_in_place]
        assert statuses[len(samples) - 1] == UNREAD  # the second scan's first sample: not on the layout expected
        assert read._timing_rate == change.get("sample_rate", rate)  # the windows' rate: that sample's, as parsed
        _assert_same_scan(read, parsed)


def test_the_layouts_kept_for_next_scans_are_bounded_and_counted():
    """The layout kept for each scanner's next scan: at most ``max_scans`` scanners, the least recent forgotten
    first and counted (a scanner forgotten has its next scan's first sample parsed, nothing else lost); the same for
    its last valid ScanStart (its next one then checked in full)."""
    start, *samples, _ = simulated_messages(steps=8)
    ingest = Ingest(max_scans=2)
    for scanner in ("a", "b", "c"):
        for m in (start, samples[0]):
            m = type(m).FromString(m.SerializeToString())
            m.scanner_id = scanner
            (event,) = ingest.accept(m.DESCRIPTOR.full_name, m.SerializeToString())
            assert not isinstance(event, Rejected)
    assert list(ingest._layouts) == ["b", "c"]
    assert ingest.evicted["scanner layout forgotten (max_scans)"] == 1
    # (and so the ScanStart each compares its next one with)
    assert list(ingest._starts) == ["b", "c"]
    assert ingest.evicted["scanner start forgotten (max_scans)"] == 1
