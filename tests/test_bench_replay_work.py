"""The replay bench's account of where a replay's time goes: CPU per scan, and the best the cores allow."""

from __future__ import annotations

import pytest

from lelsonar.tools import bench_recording


def test_the_work_table_splits_the_children_cpu_per_scan_and_bounds_the_replay(monkeypatch):
    monkeypatch.setattr("os.cpu_count", lambda: 2)
    # 10 scans: floor 16 ms a scan; read 12, the ingest stage 2 more, the finals 10 more.
    row = {"scans": 10, "floor_cpu": 0.160, "read_cpu": 0.120, "ingest_cpu": 0.140, "inline_cpu": 0.240}
    title, headers, rows, notes = bench_recording.replay_work([row])
    assert headers[-1] == "best on 2 cores: one scan / many"
    ((scans, floor, read, ingest, finals, work, best),) = rows
    assert (scans, floor, read, ingest, finals) == ("10", "16.0", "12.0", "2.0", "10.0")
    assert work == f"{24 / 16:.2f}×"
    one, many = (float(x.rstrip("×")) for x in best.split(" / "))
    assert one == pytest.approx(16 / (14 / 2 + 10), abs=0.005)  # the last final after the reading
    assert many == pytest.approx(2 * 16 / 24, abs=0.005)
