"""The ingest pass's exact shortcuts give what the one-sample-at-a-time arithmetic gives, bit for bit: extremes
compared as integers (``signal.extrema``), DC levels summed in any order where that is exact, and float32 sums
of squares within the bound the energy check allows for any order (``stream.step_features``)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lelsonar.reconstruct.stream.step_features import (
    STREAM_CHUNK,
    exact_mean,
    row_sums,
    streamed_sums,
    sum_of_squares,
)
from lelsonar.signal.compiled import kernel
from lelsonar.signal.extrema import extent, float32_of_bits, largest_magnitude


@kernel
def _extent_one_at_a_time(row, a, b):
    lo = hi = row[a]
    for j in range(a, b):
        lo, hi = min(lo, row[j]), max(hi, row[j])
    return float(lo), float(hi)


@kernel
def _peak_one_at_a_time(row, a, b):
    peak = abs(row[a])
    for j in range(a + 1, b):
        v = abs(row[j])
        if v > peak:
            peak = v
    return float(peak)


SPECIAL = np.array(
    [0.0, -0.0, np.inf, -np.inf, np.nan, -np.nan, 1e-45, -1e-45, 1.1754942e-38, -1.1754942e-38, 3.4028235e38, 1.0],
    np.float32,
)


def _rows(rng, count: int):
    """Runs of every kind: numbers, special values (NaN of either sign among them), every magnitude, any bits."""
    for i in range(count):
        m = int(rng.integers(1, 70))
        kind = i % 4
        if kind == 0:
            row = rng.standard_normal(m)
        elif kind == 1:
            row = rng.choice(SPECIAL, m)
        elif kind == 2:
            row = rng.standard_normal(m) * 10.0 ** rng.integers(-45, 38, m)
        else:
            row = rng.integers(0, 2**32, m, dtype=np.uint64).astype(np.uint32).view(np.float32)
        yield row.astype(np.float32)


def _same(x: float, y: float) -> bool:
    return x == y or (math.isnan(x) and math.isnan(y))


def test_extremes_compared_as_integers_are_the_ones_compared_as_floats():
    rng = np.random.default_rng(11)
    for row in _rows(rng, 4000):
        a = int(rng.integers(0, row.size))
        b = int(rng.integers(a + 1, row.size + 1))
        (lo, hi), (lo1, hi1) = extent(row, a, b), _extent_one_at_a_time(row, a, b)
        assert _same(lo, lo1) and _same(hi, hi1), (row[a:b], lo, hi, lo1, hi1)
        assert _same(largest_magnitude(row, a, b), _peak_one_at_a_time(row, a, b)), row[a:b]


def test_a_bit_pattern_is_read_as_its_number():
    patterns = np.random.default_rng(2).integers(0, 2**32, 20000, dtype=np.uint64).astype(np.uint32)
    numbers = patterns.view(np.float32)
    for p, x in zip(patterns[~np.isnan(numbers)].tolist(), numbers[~np.isnan(numbers)].tolist()):
        y = float32_of_bits(p)
        assert y == x and math.copysign(1.0, y) == math.copysign(1.0, x)


def _bits(n: int) -> int:
    return max(n - 1, 0).bit_length()


@pytest.mark.parametrize("n", [2, 3, 100, 3500, 4096, 4097])
def test_a_sum_taken_in_any_order_is_used_exactly_where_every_order_gives_the_same(n):
    """At the edge the bound draws (29 − b binades between the largest sample and the smallest nonzero one, n ≤
    2^b) the mean is taken from the sum in any order, one binade beyond it is left to the exact routes; either
    way the DC level is NumPy's mean to the bit."""
    rng = np.random.default_rng(n)
    span = 29 - _bits(n)
    for extra, used in ((0, True), (1, False)):
        for _ in range(20):
            # full 24-bit mantissas from the top binade down to ``span + extra`` binades below it
            exponents = rng.integers(-span - extra, 1, n)
            exponents[0], exponents[-1] = 0, -span - extra
            row = (rng.choice([-1.0, 1.0], n) * rng.uniform(1.0, 2.0, n) * 2.0**exponents).astype(np.float32)
            squares, total, top, low = row_sums(row)
            mean = exact_mean(total, top, low, n)
            truth = abs(row.mean(dtype=np.float64))
            if used:
                assert mean == truth
            else:
                assert math.isnan(mean)
            assert squares == pytest.approx(float((row.astype(np.float64) ** 2).sum()), rel=2 * (n + 1) * 2.0**-24)


def test_zeros_subnormals_and_non_finite_samples():
    n = 64
    zeros = np.zeros(n, np.float32)
    assert exact_mean(*row_sums(zeros)[1:], n) == 0.0
    tiny = np.where(np.arange(n) % 3 == 0, np.float32(1e-45), np.float32(-3e-44)).astype(np.float32)
    assert exact_mean(*row_sums(tiny)[1:], n) == abs(tiny.mean(dtype=np.float64))
    for bad in (np.nan, np.inf, -np.inf):
        row = np.ones(n, np.float32)
        row[5] = bad
        squares, total, top, low = row_sums(row)
        assert math.isnan(exact_mean(total, top, low, n))  # left to the in-order sum
        assert not math.isfinite(squares) and not math.isfinite(sum_of_squares(row))
    assert math.isnan(exact_mean(0.0, 0, 0xFFFFFFFF, 0))


def test_a_sum_of_squares_in_any_order_is_within_the_bound_of_the_energy_check():
    rng = np.random.default_rng(5)
    for n in (1, 7, 3500, 8193):
        row = (rng.standard_normal(n) * 10.0 ** rng.uniform(-3, 3)).astype(np.float32)
        exact = float((row.astype(np.float64) ** 2).sum())
        for squares in (sum_of_squares(row), row_sums(row)[0]):
            assert squares == pytest.approx(exact, rel=(n + 1) * 2.0**-24)


@pytest.mark.parametrize("n", [0, 1, STREAM_CHUNK - 1, STREAM_CHUNK, STREAM_CHUNK + 1, 3500, 4097])
def test_a_waveform_summed_in_chunks_as_its_bytes_stream_in_gives_the_sums_of_one_pass(n):
    """Read in chunks where it lies in a payload (at any byte), a waveform gives :func:`row_sums`' extremes bit for
    bit, its DC level exactly where one pass's is used, a sum of squares within the energy check's bound, and a
    non-finite sum for a non-finite sample; unlevelled, the sum of squares alone."""
    rng = np.random.default_rng(n + 1)
    for offset in (0, 1, 3):
        row = (rng.standard_normal(n) * 10.0 ** rng.uniform(-3, 3)).astype(np.float32)
        if n > 2:
            row[n // 2] = 0.0
        buf = np.zeros(offset + 4 * n + 64, np.uint8)
        buf[offset : offset + 4 * n] = row.view(np.uint8)
        squares, total, top, low = streamed_sums(buf, offset, n, True)
        whole = row_sums(row)
        assert (int(top), int(low)) == (int(whole[2]), int(whole[3]))
        mean = exact_mean(total, top, low, n)
        assert _same(mean, exact_mean(*whole[1:], n))
        if n and not math.isnan(mean):
            assert mean == abs(row.mean(dtype=np.float64))
        exact = float((row.astype(np.float64) ** 2).sum())
        assert squares == pytest.approx(exact, rel=(n + 1) * 2.0**-24)
        alone = streamed_sums(buf, offset, n, False)
        assert alone[0] == pytest.approx(exact, rel=(n + 1) * 2.0**-24) and alone[1:] == (0.0, 0, 0xFFFFFFFF)
        if n:
            row[-1] = np.nan
            buf[offset : offset + 4 * n] = row.view(np.uint8)
            for levelled in (True, False):
                assert not math.isfinite(streamed_sums(buf, offset, n, levelled)[0])
