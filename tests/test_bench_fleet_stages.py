"""`lelsonar bench fleet --stages`: every handle call is put in one stage, in the order a live worker sees them."""

from __future__ import annotations

import time

from lelsonar import codec
from lelsonar.tools.bench_fleet_stages import STAGES, interleaved, measure, summary


def test_interleaved_scans_come_in_acquisition_order_each_scanner_in_step_order():
    payloads = interleaved("paper-test1", scanners=3, scans=2, rate=50.0, steps=12)
    assert len(payloads) == 3 * 2 * (12 + 2)
    times, steps = [], {}
    for _, name, payload in payloads:
        if name.endswith("Sample"):
            m = codec.Sample.FromString(payload)
            times.append(m.acquisition_time_ns)
            key = (m.scanner_id, m.scan_id)
            assert m.step == steps.get(key, -1) + 1  # no step skipped or reordered within a scan
            steps[key] = m.step
    assert times == sorted(times) and len(steps) == 6 and set(steps.values()) == {11}


def test_every_call_is_in_one_stage_and_each_scan_gets_its_final():
    scanners = 2
    payloads = interleaved("paper-test1", scanners=scanners, scans=1, rate=50.0)
    result = measure(payloads)
    calls = result["calls"]
    # A provisional call is counted twice (its update and its exact fits), every other call once.
    assert len(calls["ingest"]) + len(calls["provisional update"]) + len(calls["final"]) == len(payloads)
    assert len(calls["provisional exact fits"]) == len(calls["provisional update"]) > 0
    assert result["finals"] == len(calls["final"]) == scanners
    assert any(x > 0 for x in calls["provisional exact fits"])  # the probe saw the exact fits
    s = summary(result, scanners, 50.0)
    assert set(s["us_per_sample"]) == set(STAGES) and all(v >= 0 for v in s["us_per_sample"].values())
    assert s["total_us"] == sum(s["us_per_sample"].values()) and s["budget_us"] == 1e6 / (scanners * 50.0)


def test_the_queue_model_handles_every_payload_on_its_virtual_clock():
    from lelsonar.tools.bench_fleet_stages import OUTSIDE_US, queue_model

    payloads = interleaved("paper-test1", scanners=2, scans=1, rate=50.0)
    samples = sum(name.endswith("Sample") for _, name, _ in payloads)
    r = queue_model(payloads, finals_elsewhere=True)
    assert r["finals"] == 2 and len(r["processed_s"]) == samples
    # Every sample waits at least the receive path's charge, and nothing is handled before it arrives.
    assert min(r["processed_s"]) >= OUTSIDE_US * 1e-6
    assert r["provisional_s"] and min(r["provisional_s"]) >= 0
    assert 0 < r["busy"] < 1  # two scanners leave the worker idle most of the time


def test_the_queue_model_clock_runs_inside_a_call_with_or_without_a_pool(monkeypatch):
    from lelsonar.reconstruct.stream.service import ReconstructionService
    from lelsonar.tools.bench_fleet_stages import queue_model

    payloads = interleaved("paper-test1", scanners=1, scans=1, rate=50.0)
    seen: list[float] = []
    tick = ReconstructionService.tick

    def spinning_tick(self, **kw):  # what the service's clock says across a call that spends CPU
        t0 = self._clock()
        c = time.thread_time()
        while time.thread_time() - c < 0.002:
            pass
        seen.append(self._clock() - t0)
        return tick(self, **kw)

    monkeypatch.setattr(ReconstructionService, "tick", spinning_tick)
    for elsewhere in (False, True):
        seen.clear()
        queue_model(payloads, finals_elsewhere=elsewhere)
        assert seen and min(seen) >= 0.0015


def test_the_capacity_table_puts_the_share_shed_and_the_rate_published_beside_the_p99():
    from lelsonar.tools.bench_fleet_capacity import provisional_rate

    # 2 runs (median 3000 published), 100 scanners over a 6 s schedule, 1000 shed of the 4000 refits due.
    res = {
        "runs": [{"provisional_ms": {"n": 2000}}, {"provisional_ms": {"n": 4000}}],
        "shed": {"w0": 1000},
        "publisher": {"schedule_s": 6.0},
        "scanners": 100,
    }
    assert provisional_rate(res) == (5.0, 0.25)
