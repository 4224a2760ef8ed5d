"""Codec round trips and the typed errors of every bad payload."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from lelsonar import codec
from lelsonar.errors import (
    DecodeError,
    InvalidIdentifierError,
    InvalidMessageError,
    NonFiniteValueError,
    PayloadTooLargeError,
    SchemaVersionError,
    TruncatedDataError,
)
from lelsonar.keys import ScannerKeys, validate_identifier, validate_prefix

from .conftest import make_sample, make_scan_start

finite_f32 = st.floats(-1e3, 1e3, allow_nan=False, width=32)


@settings(max_examples=60, deadline=None)
@given(arrays(np.float32, st.integers(0, 5000), elements=finite_f32), st.floats(1e3, 1e7), st.floats(-1, 1))
def test_float32_waveform_round_trips_exactly(volts, fs, t0):
    w = codec.pack_waveform(volts, fs, t0)
    back = codec.unpack_waveform(codec.Waveform.FromString(w.SerializeToString()))
    assert back.dtype == np.float32
    np.testing.assert_array_equal(back, volts)


@settings(max_examples=60, deadline=None)
@given(arrays(np.float32, st.integers(1, 3000), elements=st.floats(-3, 3, width=32)))
def test_int16_waveform_round_trips_within_half_a_count(volts):
    scale = 3.0 / 32767
    back = codec.unpack_waveform(codec.pack_waveform(volts, 2e5, int16_scale=scale))
    # Half a count of quantisation, plus the float32 rounding of the result.
    assert np.all(np.abs(back.astype(np.float64) - volts) <= scale / 2 + np.spacing(np.abs(volts)))
    assert len(codec.pack_waveform(volts, 2e5, int16_scale=scale).data) == 2 * volts.size


@settings(max_examples=30, deadline=None)
@given(
    st.integers(0, codec.DEFAULT_LIMITS.max_steps - 1),
    st.integers(0, 2**63),
    st.from_regex(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,20}", fullmatch=True),
)
def test_sample_round_trips_through_bytes(step, scan_id, scanner):
    s = make_sample(step=step, scanner_id=scanner, scan_id=scan_id)
    back = codec.decode(s.SerializeToString(), codec.Sample)
    assert back == s
    assert codec.type_from_encoding(codec.encoding_name(back)) is codec.Sample


def test_every_contract_message_round_trips():
    for msg in (
        make_scan_start(),
        make_sample(),
        codec.ScanEnd(schema_version=1, scanner_id="s1", scan_id=7, status=1),
    ):
        assert codec.decode(msg.SerializeToString(), type(msg)) == msg


def test_wrong_schema_version_is_rejected():
    s = make_sample()
    s.schema_version = 2
    with pytest.raises(SchemaVersionError, match="schema version 2"):
        codec.decode(s.SerializeToString(), codec.Sample)


@pytest.mark.parametrize("message_type", [codec.Sample, codec.ScanStart, codec.ScanEnd, codec.Reconstruction])
def test_random_bytes_are_a_decode_error(message_type):
    rng = np.random.default_rng(1)
    for _ in range(50):
        payload = rng.bytes(int(rng.integers(1, 400)))
        with pytest.raises(DecodeError):  # every one of them, not just the first
            codec.decode(payload, message_type)


def test_oversize_payload_is_rejected_before_parsing():
    limits = codec.DecodeLimits(max_payload_bytes=1000)
    with pytest.raises(PayloadTooLargeError, match="exceeds the limit"):
        codec.decode(make_sample().SerializeToString(), codec.Sample, limits)


def test_huge_declared_waveform_length_is_rejected():
    s = make_sample()
    s.sensors[1].waveform.sample_count = 10**9
    with pytest.raises(PayloadTooLargeError, match="declares 1000000000 samples"):
        codec.decode(s.SerializeToString(), codec.Sample)


def test_truncated_waveform_is_rejected():
    s = make_sample()
    s.sensors[2].waveform.data = s.sensors[2].waveform.data[:-3]
    with pytest.raises(TruncatedDataError, match=r"sensors\[2\]"):
        codec.decode(s.SerializeToString(), codec.Sample)


@pytest.mark.parametrize("field", ["distance", "time_of_flight"])
def test_nan_range_is_rejected(field):
    s = make_sample()
    setattr(s.sensors[0], field, math.nan)
    with pytest.raises(NonFiniteValueError, match="finite"):
        codec.decode(s.SerializeToString(), codec.Sample)


def test_nan_waveform_sample_is_rejected():
    s = make_sample()
    v = codec.unpack_waveform(s.sensors[3].waveform).copy()
    v[10] = np.nan
    s.sensors[3].waveform.CopyFrom(codec.pack_waveform(v, 2e5))
    with pytest.raises(NonFiniteValueError, match="NaN"):
        codec.decode(s.SerializeToString(), codec.Sample)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("sensor", [0, 1, 3])
def test_a_non_finite_sample_in_any_waveform_is_rejected_and_named(sensor, bad):
    # The float32 waveforms of a Sample are checked in one pass; the error still names the culprit,
    # also when another capsule's waveform is int16 (not part of that pass).
    s = make_sample()
    s.sensors[2].waveform.CopyFrom(
        codec.pack_waveform(codec.unpack_waveform(s.sensors[2].waveform), 2e5, int16_scale=1e-3)
    )
    v = codec.unpack_waveform(s.sensors[sensor].waveform).copy()
    v[-1] = bad
    s.sensors[sensor].waveform.CopyFrom(codec.pack_waveform(v, 2e5))
    with pytest.raises(NonFiniteValueError, match=rf"sensors\[{sensor}\].waveform holds NaN"):
        codec.decode(s.SerializeToString(), codec.Sample)
    v[-1] = 0.0
    s.sensors[sensor].waveform.CopyFrom(codec.pack_waveform(v, 2e5))
    assert codec.decode(s.SerializeToString(), codec.Sample) == s


def test_valid_echo_needs_a_positive_range():
    s = make_sample()
    s.sensors[0].distance = -1.0
    with pytest.raises(InvalidMessageError, match="marked valid"):
        codec.decode(s.SerializeToString(), codec.Sample)


def test_unknown_encoding_names_the_expected_ones():
    with pytest.raises(InvalidMessageError, match="lelsonar.v1.Sample"):
        codec.type_from_encoding("application/json")


@pytest.mark.parametrize("bad", ["", "a/b", "a*", "$x", "a#", "q?", "x" * 65, "-lead", "sp ace"])
def test_invalid_scanner_ids_are_rejected(bad):
    with pytest.raises(InvalidIdentifierError):
        validate_identifier(bad)
    s = make_sample()
    s.scanner_id = bad
    with pytest.raises(InvalidMessageError):
        codec.decode(s.SerializeToString(), codec.Sample)


def test_key_expressions():
    keys = ScannerKeys("robot7/lelsonar", "scanner-1")
    assert keys.sample == "robot7/lelsonar/scanner-1/sample"
    assert keys.scan == "robot7/lelsonar/scanner-1/scan"
    assert keys.planes == "robot7/lelsonar/scanner-1/planes"
    assert keys.alive("acquire") == "robot7/lelsonar/scanner-1/alive/acquire"
    assert ScannerKeys().sample == "lelsonar/*/sample"
    assert ScannerKeys().scanner_of("lelsonar/abc/sample") == "abc"
    with pytest.raises(InvalidIdentifierError):
        validate_prefix("robot7//lelsonar")
    with pytest.raises(InvalidIdentifierError):
        ScannerKeys(scanner_id="a/b")


# The Sample validator screens each sensor with a few comparisons and one sum (finite only if every term is),
# and falls back to the exact field-by-field checks for anything the screen does not pass.  Both directions:
# every bad field is still refused with its own typed error, and valid extremes the screen cannot vouch for
# (sums that overflow, int16 data) are still accepted.
def _set(s: codec.Sample, path: str, value) -> None:
    *parents, name = path.split(".")
    obj = s
    for p in parents:
        obj = obj[int(p)] if p.isdigit() else getattr(obj, p)
    setattr(obj, name, value)


@pytest.mark.parametrize(
    ("path", "value", "error", "match"),
    [
        ("gamma_measured", math.inf, NonFiniteValueError, "gamma"),
        ("motor.voltage", math.nan, NonFiniteValueError, "motor"),
        ("sensors.1.time_of_flight", -math.inf, NonFiniteValueError, r"sensors\[1\].time_of_flight"),
        ("sensors.2.waveform.t0", math.nan, NonFiniteValueError, r"sensors\[2\].waveform.t0"),
        ("sensors.3.waveform.sample_rate", math.inf, NonFiniteValueError, r"sensors\[3\].waveform.sample_rate"),
        ("sensors.3.waveform.sample_rate", 0.0, InvalidMessageError, r"sensors\[3\].waveform.sample_rate must be"),
        ("sensors.0.waveform.sample_count", 63, TruncatedDataError, r"sensors\[0\]"),
        ("sensors.0.waveform.encoding", 7, InvalidMessageError, "unknown encoding"),
        ("sensors.1.distance", 100.0, InvalidMessageError, r"sensors\[1\] is marked valid"),
        (
            "sensors.1.time_of_flight",
            -1e-3,
            InvalidMessageError,
            r"sensors\[1\] is marked valid",
        ),  # 0: unset, the distance is there
    ],
)
def test_every_sensor_field_is_still_checked(path, value, error, match):
    s = make_sample()
    _set(s, path, value)
    with pytest.raises(error, match=match):
        codec.decode(s.SerializeToString(), codec.Sample)


def test_valid_extremes_the_screen_cannot_vouch_for_are_accepted():
    s = make_sample()
    # Finite numbers whose sums overflow (the screen's sum of a sensor's numbers), and the largest float32.
    s.sensors[0].waveform.t0 = 1.7e308
    s.sensors[0].waveform.sample_rate = 1.7e308
    s.gamma_commanded, s.gamma_measured = 1.7e308, 1.7e308
    v = codec.unpack_waveform(s.sensors[1].waveform).copy()
    v[:] = 3e38  # finite float32; Σ w² overflows float32
    s.sensors[1].waveform.CopyFrom(codec.pack_waveform(v, 2e5))
    # A sensor without an echo may carry any finite range; an int16 waveform goes the exact way.
    s.sensors[2].echo_valid, s.sensors[2].distance, s.sensors[2].time_of_flight = False, -5.0, 0.0
    s.sensors[3].waveform.CopyFrom(
        codec.pack_waveform(codec.unpack_waveform(s.sensors[3].waveform), 2e5, int16_scale=1e-3)
    )
    assert codec.decode(s.SerializeToString(), codec.Sample) == s
    # ... int16 data whose scale was left unset (0) is read as counts, and a negative scale still refused.
    s.sensors[3].waveform.scale = 0.0
    decoded = codec.decode(s.SerializeToString(), codec.Sample)
    np.testing.assert_array_equal(
        codec.unpack_waveform(decoded.sensors[3].waveform),
        np.frombuffer(s.sensors[3].waveform.data, dtype="<i2").astype(np.float32),
    )
    s.sensors[3].waveform.scale = -1e-3
    with pytest.raises(InvalidMessageError, match=r"sensors\[3\].waveform.scale must be positive"):
        codec.decode(s.SerializeToString(), codec.Sample)
