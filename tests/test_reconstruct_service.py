"""The reconstruction service: incremental estimates, ordering, bad input, timeouts."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lelsonar import codec
from lelsonar.reconstruct.estimate import wire
from lelsonar.reconstruct.stream.config import ReconstructConfig
from lelsonar.reconstruct.stream.final_pool import PoolStats
from lelsonar.reconstruct.stream.final_worker import Done
from lelsonar.reconstruct.stream.service import ReconstructionService

from .conftest import assert_matches_the_scene, simulated_messages, type_name


@pytest.fixture(scope="module")
def scan_messages():
    return simulated_messages("paper-test1", seed=3)


def feed(service: ReconstructionService, messages) -> list[codec.Reconstruction]:
    out = []
    for m in messages:
        out += service.handle(type_name(m), m.SerializeToString())
    return out


def finals(estimates):
    return [e for e in estimates if wire.status_name(e).startswith("final")]


def comparable(msg: codec.Reconstruction) -> codec.Reconstruction:
    """The estimate without its wall-clock fields and its accounting (how the samples came)."""
    m = codec.Reconstruction()
    m.CopyFrom(msg)
    m.ClearField("stamp_ns")
    m.ClearField("timings")
    m.ClearField("accounting")
    return m


def test_provisional_estimates_then_one_final(scan_messages):
    # The simulator stamps its steps with the wall clock as fast as it computes them, so the per-scan
    # rate limit (scan time) is off here; test_provisional_estimates_are_rate_limited_in_scan_time tests it.
    service = ReconstructionService(ReconstructConfig(provisional_period=0))
    estimates = feed(service, scan_messages)
    provisional = [e for e in estimates if wire.status_name(e) == "provisional"]
    assert provisional, "no provisional estimate before the end of the scan"
    assert all(p.HasField("critical_step") for p in provisional)
    # Provisional estimates follow the scan: later ones use more samples.
    used = [p.samples_used for p in provisional]
    assert used == sorted(used) and used[0] < used[-1]
    (final,) = finals(estimates)
    assert final.samples_used == 184
    assert {(p.label, p.method) for p in final.planes} >= {("a", service.config.method), ("b", service.config.method)}
    assert final.HasField("corner_edge")
    assert service.latest["s1"] == final
    # Accurate against the scene (planes, critical angle, corner edge), not just well formed;
    # and so is the last provisional estimate.
    assert_matches_the_scene(final, service.config.method)
    assert_matches_the_scene(provisional[-1], service.provisional_method)
    # Every plane a planner receives carries a verdict, provisional ones included.
    assert all(
        pl.quality == codec.QUALITY["good"]
        for est in (provisional[-1], final)
        for pl in est.planes
        if pl.method in (service.provisional_method, service.config.method)
    )


def test_final_estimate_does_not_depend_on_arrival_order(scan_messages):
    in_order = finals(feed(ReconstructionService(), scan_messages))
    start, samples, end = scan_messages[0], scan_messages[1:-1], scan_messages[-1]
    rng = np.random.default_rng(7)
    shuffled = [samples[i] for i in rng.permutation(len(samples))]
    # Samples before their ScanStart, duplicates, and the end before the last samples.
    mixed = shuffled[:5] + [start] + shuffled[5:150] + shuffled[20:23] + [end] + shuffled[150:] + shuffled[:10]
    service = ReconstructionService()
    out_of_order = finals(feed(service, mixed))
    assert len(out_of_order) == 1
    assert comparable(out_of_order[0]) == comparable(in_order[0])
    assert service.ingest.rejected == {"DuplicateSample": 3, "LateMessage": 10}
    acc = out_of_order[0].accounting
    assert (acc.published, acc.received_live, acc.recovered, acc.duplicates, acc.missing) == (184, 184, 0, 3, 0)


def test_malformed_payloads_are_counted_and_valid_samples_keep_flowing(scan_messages):
    service = ReconstructionService()
    good = [m.SerializeToString() for m in scan_messages]
    sample_type = type_name(codec.Sample())
    rng = np.random.default_rng(0)

    def mutated(fn):
        s = codec.Sample.FromString(good[20])
        fn(s)
        return s.SerializeToString()

    bad = [
        rng.bytes(300),  # random bytes
        mutated(lambda s: setattr(s, "schema_version", 9)),  # wrong schema version
        mutated(lambda s: setattr(s.sensors[0].waveform, "data", s.sensors[0].waveform.data[:-8])),  # truncated
        mutated(lambda s: setattr(s.sensors[1], "distance", math.nan)),  # NaN range
        mutated(lambda s: setattr(s.sensors[2].waveform, "sample_count", 2**31)),  # huge declared length
    ]
    for i, payload in enumerate(good):
        service.handle(type_name(scan_messages[i]), payload)
        if i == 30:
            for b in bad:
                assert service.handle(sample_type, b) == []
    assert service.ingest.rejected == {
        "DecodeError": 1,
        "SchemaVersionError": 1,
        "TruncatedDataError": 1,
        "NonFiniteValueError": 1,
        "PayloadTooLargeError": 1,
    }
    assert len(service.finals) == 1 and next(iter(service.finals.values())).samples_used == 184


def test_samples_of_an_unknown_scan_are_dropped_and_counted_on_timeout(scan_messages):
    now = [0.0]
    service = ReconstructionService(ReconstructConfig(scan_timeout=5.0), clock=lambda: now[0])
    stray = codec.Sample.FromString(scan_messages[10].SerializeToString())
    stray.scan_id = 999
    service.handle(type_name(stray), stray.SerializeToString())
    assert service.ingest.n_pending == 1 and not service.ingest.rejected
    now[0] = 6.0
    service.tick()
    assert service.ingest.rejected["UnknownScan"] == 1 and service.ingest.n_pending == 0
    end = codec.ScanEnd.FromString(scan_messages[-1].SerializeToString())
    end.scan_id = 998
    service.handle(type_name(end), end.SerializeToString())  # held too: a late start may still recover it
    assert service.ingest.n_pending == 1
    now[0] = 12.0
    service.tick()
    assert service.ingest.rejected["UnknownScan"] == 2 and service.ingest.n_pending == 0


def test_scan_without_scan_end_is_finalised_on_timeout(scan_messages):
    now = [0.0]
    service = ReconstructionService(ReconstructConfig(scan_timeout=3.0), clock=lambda: now[0])
    estimates = feed(service, scan_messages[:-1])
    assert not finals(estimates)
    now[0] = 2.9
    assert service.tick() == []
    now[0] = 3.1
    (final,) = service.tick()
    assert wire.status_name(final) == "final_timeout"
    assert final.samples_used == 184 and service.stats.timeouts == 1
    assert service.tick() == []  # finalised once


def test_several_scanners_are_kept_apart():
    a = simulated_messages("paper-test1", seed=1, scanner_id="left", steps=120)
    b = simulated_messages("tilted", seed=2, scanner_id="right", steps=120)
    service = ReconstructionService()
    interleaved = [m for pair in zip(a, b) for m in pair]
    got = {g.scanner_id: g for g in finals(feed(service, interleaved))}
    assert set(got) == {"left", "right"}
    assert set(service.latest) == {"left", "right"}
    # Each scanner's estimate is of its own scene: the same alone as interleaved.
    for scanner_id, messages in (("left", a), ("right", b)):
        (alone,) = finals(feed(ReconstructionService(), messages))
        assert comparable(got[scanner_id]) == comparable(alone)


def test_a_backlog_costs_one_refit_not_one_per_sample(scan_messages):
    now = [0.0]
    service = ReconstructionService(ReconstructConfig(provisional_period=0), clock=lambda: now[0])
    start, samples = scan_messages[0], scan_messages[1:-1]
    service.handle(type_name(start), start.SerializeToString())
    burst = []
    for m in samples[:120]:
        burst += service.handle(type_name(m), m.SerializeToString(), busy=True)
    assert burst == []  # the clock did not move: everything waited for the backlog
    (caught_up,) = service.tick()
    assert wire.status_name(caught_up) == "provisional" and caught_up.samples_used == 120
    now[0] = 0.3  # past max_provisional_delay: a busy service still lets the samples go first ...
    more = []
    for m in samples[120:130]:
        more += service.handle(type_name(m), m.SerializeToString(), busy=True)
    assert more == []
    (behind,) = service.tick(busy=True)  # ... and a tick catches up within its budget, backlog or not
    assert wire.status_name(behind) == "provisional" and behind.samples_used == 130


def _deferred_scans(now):
    """Three scanners whose provisional refits all waited for a backlog at ``now[0]``."""
    service = ReconstructionService(ReconstructConfig(provisional_period=0), clock=lambda: now[0])
    scans = {sid: simulated_messages("paper-test1", seed=k, scanner_id=sid) for k, sid in enumerate("abc")}
    for messages in scans.values():
        service.handle(type_name(messages[0]), messages[0].SerializeToString())
    return service, scans


@pytest.mark.parametrize("catch_up", ["tick", "catch_up"])
def test_catching_up_on_deferred_refits_stops_at_its_budget_oldest_first(monkeypatch, catch_up):
    now = [0.0]
    service, scans = _deferred_scans(now)
    for sid in "bc":
        for m in scans[sid][1:100]:
            service.handle(type_name(m), m.SerializeToString(), busy=True)
    now[0] = 0.1  # scanner a refits now: the newest estimate; b and c still wait from before
    for m in scans["a"][1:100]:
        service.handle(type_name(m), m.SerializeToString())
    for messages in scans.values():
        for m in messages[100:110]:
            service.handle(type_name(m), m.SerializeToString(), busy=True)
    refit, real = [], service._provisional

    def slow_refit(scan, p, **kw):  # each refit takes 60 % of the budget on the service's clock
        refit.append((scan.key[0], kw.get("fits_wait", False)))
        now[0] += 0.6 * service.config.provisional_budget
        return real(scan, p, **kw)

    monkeypatch.setattr(service, "_provisional", slow_refit)
    later = service.tick if catch_up == "tick" else service.catch_up
    # The two oldest refits, without their exact fits: b's and c's corners are confirmed, and their plane a's
    # first fit waits (no estimate to give yet); the budget ran out before a's refit.
    assert later() == [] and refit == [("b", True), ("c", True)]
    assert service.has_deferred
    # a's refit publishes at once; then the fits that wait, oldest scan first, as far as the budget goes.
    second = later()
    assert refit[2:] == [("a", True), ("b", False)] and [e.scanner_id for e in second] == ["a", "b"]
    assert service.has_deferred
    third = later()
    assert refit[4:] == [("c", False)] and [e.scanner_id for e in third] == ["c"] and not service.has_deferred
    # Each estimate caught up on names the newest step its scan holds.
    for e in (*second, *third):
        assert e.last_step == scans[e.scanner_id][109].step


def test_a_scan_completed_under_a_backlog_gets_its_final_once_it_drains_and_the_same_final():
    now = [0.0]
    messages = simulated_messages("paper-test1", seed=3, scanner_id="a")
    busy = ReconstructionService(ReconstructConfig(provisional=False), clock=lambda: now[0])
    for m in messages:
        assert busy.handle(type_name(m), m.SerializeToString(), busy=True) == []  # the samples come first
    assert busy.has_deferred and not busy.finals
    # A straggling copy of a step while its final waits: late, as after any final (no second final).
    again = messages[-2]
    assert busy.handle(type_name(again), again.SerializeToString(), busy=True) == []
    assert busy.ingest.rejected["LateMessage"] == 1
    (final,) = busy.catch_up()
    assert wire.status_name(final) == "final" and not busy.has_deferred
    alone = ReconstructionService(ReconstructConfig(provisional=False))
    (expected,) = [e for m in messages for e in alone.handle(type_name(m), m.SerializeToString())]
    assert final.planes == expected.planes and final.corner_edge == expected.corner_edge
    assert final.surfaces == expected.surfaces and final.failures == expected.failures
    assert final.accounting == expected.accounting


def test_a_final_that_waited_stays_behind_its_scanners_newer_estimate():
    now = [0.0]
    first = simulated_messages("paper-test1", seed=3, scanner_id="a")
    second = simulated_messages("paper-test1", seed=4, scanner_id="a", scan_id=2)
    service = ReconstructionService(ReconstructConfig(provisional_period=0), clock=lambda: now[0])
    for m in first:
        service.handle(type_name(m), m.SerializeToString(), busy=True)
    newer = []
    for m in second[:120]:  # the next scan's estimates, made while the first one's final waits
        newer += service.handle(type_name(m), m.SerializeToString())
    assert newer and all(e.scan_id == 2 for e in newer)
    (final,) = [e for e in service.catch_up() if wire.is_terminal(e)]
    assert final.scan_id == 1 and service.finals[("a", 1)] is final
    # Ranked when its scan completed: the scanner's latest is still the newer scan's estimate.
    assert service.latest["a"].scan_id == 2


class _HeldPool:
    """A final pool of one worker and no queue, whose jobs finish when the test says."""

    workers = capacity = 1

    def __init__(self):
        self.stats, self.jobs, self.done, self.tickets = PoolStats(), [], [], 0

    @property
    def unfinished(self):
        return len(self.jobs)

    def submit(self, fn, *args):
        self.tickets += 1
        self.jobs.append((self.tickets - 1, fn, args))
        return self.tickets - 1

    def finish_one(self):
        ticket, fn, args = self.jobs.pop(0)
        self.done.append(Done(ticket, fn(*args)))

    def ready(self):
        out, self.done = self.done, []
        return out

    def drain(self):
        while self.jobs:
            self.finish_one()
        return self.ready()


def test_finals_that_waited_for_a_backlog_wait_for_room_in_the_pool_too():
    now = [0.0]
    service = ReconstructionService(ReconstructConfig(provisional=False), clock=lambda: now[0])
    pool = _HeldPool()
    service.use_pool(pool)  # type: ignore[arg-type]
    for sid in "ab":
        for m in simulated_messages("paper-test1", seed=3, scanner_id=sid):
            service.handle(type_name(m), m.SerializeToString(), busy=True)
    assert service.catch_up() == [] and len(pool.jobs) == 1  # a's final in the pool; b's waits for room
    assert service.has_deferred and service.catch_up() == [] and len(pool.jobs) == 1
    pool.finish_one()
    (a,) = service.catch_up()  # a's final comes back, and b's goes to the pool
    assert (a.scanner_id, wire.status_name(a)) == ("a", "final") and len(pool.jobs) == 1
    assert not service.has_deferred
    (b,) = service.finish()
    assert (b.scanner_id, wire.status_name(b)) == ("b", "final") and pool.stats.inline == 0


def test_a_new_scan_under_a_backlog_defers_its_first_refits_too():
    now = [1000.0]  # a monotonic clock: far from 0
    service, scans = _deferred_scans(now)
    messages = scans["a"][1:110]
    assert feed_busy(service, messages) == []  # its corner confirmed meanwhile, but no refit inline
    assert service.has_deferred
    (caught_up,) = service.tick()
    assert not wire.is_terminal(caught_up) and caught_up.last_step == messages[-1].step
    # Without a backlog the same scan gets its provisional estimates on the way.
    alone, _ = _deferred_scans(now)
    assert [e for e in feed(alone, messages) if not wire.is_terminal(e)]


def feed_busy(service: ReconstructionService, messages) -> list[codec.Reconstruction]:
    out = []
    for m in messages:
        out += service.handle(type_name(m), m.SerializeToString(), busy=True)
    return out


def test_a_busy_service_sheds_stale_provisional_refits_and_counts_them():
    now = [0.0]
    service, scans = _deferred_scans(now)
    for messages in scans.values():
        for m in messages[1:100]:
            service.handle(type_name(m), m.SerializeToString(), busy=True)
    now[0] = 3 * service.config.max_provisional_delay  # still behind, long after they were deferred
    assert service.tick(busy=True) == []
    assert service.stats.provisionals_shed == 3 and not service.has_deferred
    (final,) = finals(feed(service, scans["a"][100:]))  # the final is never shed
    assert final.samples_used == scans["a"][-1].samples_sent
