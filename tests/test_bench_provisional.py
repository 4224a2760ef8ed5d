"""The provisional-refit row of ``lelsonar bench estimators --provisional``."""

from __future__ import annotations

import argparse

import pytest

from lelsonar.tools import bench_estimators
from lelsonar.tools.bench_provisional import QUARTERS


@pytest.mark.slow
def test_the_provisional_row_prints_its_floor_and_counts_the_exact_fits(capsys):
    parser = argparse.ArgumentParser()
    bench_estimators.add_arguments(parser)
    args = parser.parse_args(["--provisional", "--provisional-seeds", "1", "--scenes", "paper-test1"])
    assert bench_estimators.run(args) == 0
    out = capsys.readouterr().out
    assert "floor: median CPU" in out
    (row,) = [line.split() for line in out.splitlines() if line.startswith("paper-test1")]
    floor = float(row[1])
    assert floor > 0
    # After the quarters' cells: refits, updates, refreshes, exact, untrusted, exact ms, scan ms, share.
    refits, updates, refreshes, exact, untrusted = (float(x) for x in row[-8:-3])
    # Plane b's first estimate is an exact fit, and an untrusted one is an exact fit too.
    assert refits > updates + exact and exact >= 1 and untrusted <= exact and refreshes >= 0
    assert row[-1].endswith("%") and 0 < float(row[-1][:-1]) <= 100
    header = next(line for line in out.splitlines() if line.startswith("preset"))
    for name in [f"q{q + 1}" for q in range(QUARTERS)] + ["refits", "exact ms", "scan ms", "in exact"]:
        assert name in header
