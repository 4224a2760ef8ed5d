"""Gaps, recovery decisions, INCOMPLETE and bounded state in the service itself (no network, a fake clock)."""

from __future__ import annotations

import pytest

from lelsonar import codec
from lelsonar.acquire.log_server import ScanLog, parse_parameters
from lelsonar.errors import ConfigError, InvalidIdentifierError
from lelsonar.keys import MAX_LOG_STEPS_PER_QUERY, ScannerKeys, validate_scan_id
from lelsonar.reconstruct.estimate import wire
from lelsonar.reconstruct.stream.config import ReconstructConfig
from lelsonar.reconstruct.stream.recovery import RecoveryRequest, selectors, step_ranges
from lelsonar.reconstruct.stream.service import ReconstructionService
from lelsonar.view import present

from .conftest import make_sample, make_scan_start, simulated_messages, type_name

STEPS = 120


@pytest.fixture(scope="module")
def scan():
    return simulated_messages("paper-test1", seed=8, steps=STEPS)


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def feed(service, messages, origin="live"):
    out = []
    for m in messages:
        out += service.handle(type_name(m), m.SerializeToString(), origin=origin)
    return out


def terminal(estimates):
    return [e for e in estimates if wire.is_terminal(e)]


def test_without_recovery_a_gap_is_incomplete_never_final(scan):
    clock = Clock()
    service = ReconstructionService(ReconstructConfig(provisional=False, end_grace=1.0), clock=clock)
    gap = {5, 6, 90}
    assert terminal(feed(service, [m for m in scan if not (isinstance(m, codec.Sample) and m.step in gap)])) == []
    clock.t = 0.9
    assert service.tick() == []
    clock.t = 1.1
    (est,) = service.tick()
    assert wire.status_name(est) == "incomplete" and list(est.missing_steps) == sorted(gap)
    a = est.accounting
    assert (a.published, a.received_live, a.recovered, a.missing) == (STEPS, STEPS - 3, 0, 3)
    # A straggler after the verdict is rejected as late and counted, never silently lost.
    feed(service, [scan[1 + 5]])
    assert service.ingest.rejected["LateMessage"] == 1


def test_recovery_is_asked_at_scan_end_retried_a_bounded_number_of_times_then_incomplete(scan):
    clock = Clock()
    asked: list[RecoveryRequest] = []
    config = ReconstructConfig(provisional=False, recovery_attempts=3, recovery_interval=0.5)
    service = ReconstructionService(config, clock=clock, recover=lambda r: asked.append(r) or True)
    feed(service, [m for m in scan if not (isinstance(m, codec.Sample) and m.step in (7, 8))])
    assert asked == [RecoveryRequest("s1", 1, steps=(7, 8))]
    out = []
    for t in (0.4, 0.5, 0.9, 1.4, 1.5, 3.4):
        clock.t = t
        out += service.tick()
    assert len(asked) == 3 and out == []  # three attempts, 0.5 s then 1 s apart (the wait doubles)
    clock.t = 3.5  # the last one had its 2 s to answer
    (est,) = service.tick()
    assert wire.status_name(est) == "incomplete" and list(est.missing_steps) == [7, 8]


def test_recovered_steps_complete_the_scan_as_final(scan):
    clock = Clock()
    asked: list[RecoveryRequest] = []
    service = ReconstructionService(
        ReconstructConfig(provisional=False), clock=clock, recover=lambda r: asked.append(r) or True
    )
    feed(service, [m for m in scan if not (isinstance(m, codec.Sample) and m.step == 40)])
    (final,) = terminal(feed(service, [scan[1 + 40]], origin="recovered"))
    assert wire.status_name(final) == "final" and not final.missing_steps
    a = final.accounting
    assert (a.published, a.received_live, a.recovered, a.duplicates, a.missing) == (STEPS, STEPS - 1, 1, 0, 0)


def test_silent_scan_asks_for_the_rest_and_its_scan_end_then_times_out_with_missing_steps(scan):
    clock = Clock()
    asked: list[RecoveryRequest] = []
    config = ReconstructConfig(
        provisional=False, scan_timeout=5.0, recovery_after=1.0, recovery_attempts=2, recovery_interval=1.0
    )
    service = ReconstructionService(config, clock=clock, recover=lambda r: asked.append(r) or True)
    feed(service, scan[: 1 + 100])
    clock.t = 0.5
    service.tick()
    assert asked == []
    clock.t = 1.0
    service.tick()
    assert asked[0].want_end and asked[0].steps == tuple(range(100, STEPS))
    clock.t = 2.5
    service.tick(busy=True)  # behind on a backlog: silence is ours, not the scanner's
    assert len(asked) == 1
    clock.t = 3.0
    assert service.tick() == [] and len(asked) == 2
    clock.t = 4.9
    assert service.tick() == []  # the budget is spent, but the scan is not silent for scan_timeout yet
    clock.t = 5.0
    (est,) = service.tick()
    assert wire.status_name(est) == "final_timeout" and len(asked) == 2
    assert list(est.missing_steps) == list(range(100, STEPS)) and est.accounting.missing == STEPS - 100


def test_first_sample_of_an_unknown_scan_asks_for_its_start_and_earlier_steps():
    asked: list[RecoveryRequest] = []
    service = ReconstructionService(ReconstructConfig(provisional=False), recover=lambda r: asked.append(r) or True)
    service.handle(type_name(codec.Sample()), make_sample(step=3).SerializeToString())
    assert asked == [RecoveryRequest("s1", 7, steps=(0, 1, 2), want_start=True)]
    feed(service, [make_scan_start(steps=5)], origin="recovered")
    scan = service.ingest.scans[("s1", 7)]
    assert scan.n_received == 1 and scan.n_recovered == 0  # the held live sample is placed, as live


def test_a_forged_scan_start_costs_nothing_until_its_samples_come():
    limit = codec.DEFAULT_LIMITS.max_steps
    service = ReconstructionService()
    feed(service, [make_scan_start(steps=limit)])
    scan = service.ingest.scans[("s1", 7)]
    assert len(scan.received) <= 256 and scan.distance.nbytes <= 256 * 4 * 8
    feed(service, [make_sample(step=limit - 1)])
    assert scan.received[limit - 1] and scan.n_received == 1
    too_many = make_scan_start(scan_id=8, steps=limit + 1)
    feed(service, [too_many])
    assert service.ingest.rejected["InvalidMessageError"] == 1 and ("s1", 8) not in service.ingest.scans


def test_every_message_of_a_thousand_scanners_is_accounted_for_within_the_bounds():
    n = 1000
    clock = Clock()
    config = ReconstructConfig(provisional=False, max_scans=16, max_scanners=8, scan_timeout=5.0)
    service = ReconstructionService(config, clock=clock)
    starts = [make_scan_start(scanner_id=f"id{i}", scan_id=1, steps=3) for i in range(n)]
    ends = [
        codec.ScanEnd(schema_version=1, scanner_id=f"id{i}", scan_id=1, status=1, samples_sent=0, steps_planned=3)
        for i in range(n)
    ]
    feed(service, starts)
    out = terminal(feed(service, ends))
    assert len(service.ingest.scans) == 0 and len(service.latest) == 8
    assert len(out) == 16  # the 16 scans the table held
    # (and each scanner's last valid ScanStart, kept to compare its next one with)
    assert service.ingest.evicted == {
        "open scan forgotten (max_scans)": n - 16,
        "scanner start forgotten (max_scans)": n - 16,
    }
    # The ScanEnds of the forgotten scans wait for a ScanStart that never comes, then are counted.
    assert service.ingest.n_pending == n - 16 and not service.ingest.rejected
    clock.t = 5.0
    service.tick()
    assert service.ingest.rejected == {"UnknownScan": n - 16} and service.ingest.n_pending == 0
    assert service.stats.evicted == {"latest estimate of a scanner forgotten (max_scanners)": 16 - 8}


def test_log_keys_queries_and_the_served_log_are_validated_and_bounded():
    keys = ScannerKeys("robot7/lelsonar", "rig")
    assert keys.log(42) == "robot7/lelsonar/rig/log/42"
    assert keys.scan_of_log_key("robot7/lelsonar/rig/log/42") == ("rig", 42)
    for bad in ("-1", "4*", "1 2", str(2**64), "", "١٢"):
        with pytest.raises(InvalidIdentifierError):
            validate_scan_id(bad)
    assert parse_parameters("steps=3-9;start=1") == ((3, 9), True, False)
    for bad in ("steps=9-3", "steps=a-b", f"steps=0-{MAX_LOG_STEPS_PER_QUERY}", "start=yes"):
        with pytest.raises(ConfigError):
            parse_parameters(bad)
    assert step_ranges([5, 1, 2, 3, 9, 10], 2) == [(1, 2), (3, 3), (5, 5), (9, 10)]
    sel = selectors(ScannerKeys("lelsonar", "*"), RecoveryRequest("rig", 4, (1, 2, 3), True, True), 64)
    assert [s for s, *_ in sel] == ["lelsonar/rig/log/4?steps=1-3;start=1;end=1"]

    clock = Clock()
    log = ScanLog(max_scans=2, keep_for=10.0, clock=clock)
    for sid in (1, 2, 3):
        log.add(make_scan_start(scan_id=sid))
        log.add(make_sample(step=0, scan_id=sid))
    assert log.scan_ids == [2, 3] and log.evicted == {"more scans than max_scans": 1}
    log.add(codec.ScanEnd(schema_version=1, scanner_id="s1", scan_id=3, status=1, samples_sent=1))
    assert [c for c, _ in log.lookup(3, (0, 5), True, True)] == [codec.ScanStart, codec.Sample, codec.ScanEnd]
    clock.t = 10.5
    assert log.lookup(3, (0, 0), False, False) is None and log.evicted["ended longer ago than keep_for"] == 1


def test_planes_publishers_are_bounded_and_the_planner_table_shows_the_accounting():
    from lelsonar.net.transport import ZenohSettings, open_session
    from lelsonar.reconstruct.estimate import wire
    from lelsonar.reconstruct.stream.sources import PlanesServer

    acc = wire.accounting_message(
        published=184, received_live=170, recovered=10, duplicates=2, rejected={"InvalidMessageError": 1}, missing=4
    )
    msgs = [
        wire.reconstruction_message(
            sid,
            5,
            status="incomplete",
            last_step=183,
            samples_used=180,
            critical_step=None,
            critical_angle=0.0,
            planes=[],
            edge=None,
            timings=(0, 0, 0),
            missing_steps=[3, 4, 5, 90],
            accounting=acc,
        )
        for sid in ("a", "b", "c")
    ]
    caption = present.planes_table(msgs[0]).caption
    assert "published 184, live 170, recovered 10, duplicates 2, rejected 1" in caption
    assert caption.endswith("missing 4; missing steps 3-5, 90")
    with open_session(ZenohSettings(mode="peer", connect=(), listen=())) as session:  # isolated
        server = PlanesServer(session, ScannerKeys("lelsonar", "*"), {}, max_publishers=2)
        for m in msgs:
            server.publish(m)
        assert list(server._publishers) == ["b", "c"]
        assert server.evicted == {"planes publisher undeclared (max_publishers)": 1}
        server.close()
