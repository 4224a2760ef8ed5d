"""The replay bench's account of where a replay's time goes: CPU per scan, and the best the cores allow."""

from __future__ import annotations

import pytest

from lelsonar.tools import bench_recording, bench_replay


def test_the_work_table_splits_the_children_cpu_per_scan_and_bounds_the_replay(monkeypatch):
    monkeypatch.setattr("os.cpu_count", lambda: 2)
    # 10 scans: floor 16 ms a scan; read 12, the ingest stage 2 more, the finals 10 more.
    row = {"scans": 10, "floor_cpu": 0.160, "read_cpu": 0.120, "ingest_cpu": 0.140, "inline_cpu": 0.240}
    row["replay_thread_cpu"] = 0.150  # (its decompression on another thread)
    title, headers, rows, notes = bench_recording.replay_work([row])
    assert headers[-1] == "best on 2 cores: one scan / many"
    ((scans, floor, read, ingest, finals, own, work, best),) = rows
    assert (scans, floor, read, ingest, finals, own) == ("10", "16.0", "12.0", "2.0", "10.0", "15.0")
    assert work == f"{24 / 16:.2f}×"
    one, many = (float(x.rstrip("×")) for x in best.split(" / "))
    assert one == pytest.approx(16 / (14 / 2 + 10), abs=0.005)  # the last final after the reading
    assert many == pytest.approx(2 * 16 / 24, abs=0.005)


def test_a_short_file_is_replayed_by_more_children_so_every_median_stands_on_as_many_scans():
    assert bench_replay.runs_for(1, 1) == bench_replay.SHORT_FILE_RUNS
    assert bench_replay.runs_for(2, 1) == -(-bench_replay.SHORT_FILE_RUNS // 2)
    assert bench_replay.runs_for(100, 1) == 1
    assert bench_replay.runs_for(100, 5) == 5  # --rss-runs, where it asks for more


def test_the_replays_plans_are_printed_most_common_first():
    assert bench_replay.plans_text({(0, 0): 1, (0, 1): 8}) == "0 w + 1 t ×8, 0 w + 0 t ×1"


def test_the_floor_and_the_read_children_warm_up_then_read_every_sample(tmp_path):
    from lelsonar.log.recording import McapRecorder

    from .conftest import simulated_messages

    path = tmp_path / "one.mcap"
    msgs = simulated_messages(steps=12)
    with McapRecorder(path) as rec:
        for m in msgs:
            rec.write(m)
    samples = len(msgs) - 2
    for warm in (True, False):
        assert bench_replay.time_floor(path, warm)[1] == samples
        assert bench_replay.time_read(path, warm)[1] == samples
