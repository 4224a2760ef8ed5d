"""Provisional estimates on a live stream: stale ones shed, and refits behind a short backlog run at once."""

from __future__ import annotations

import pytest

from lelsonar import codec
from lelsonar.reconstruct.estimate import wire
from lelsonar.reconstruct.stream.config import ReconstructConfig
from lelsonar.reconstruct.stream.service import ReconstructionService

from .conftest import simulated_messages, type_name

TRANSIT_NS = 2_000_000  # a sample's transit to the service when nothing holds it


@pytest.fixture(scope="module")
def scan_messages():
    return simulated_messages("paper-test1", seed=3)


def comparable(msg: codec.Reconstruction) -> codec.Reconstruction:
    """The estimate without its wall-clock fields."""
    m = codec.Reconstruction()
    m.CopyFrom(msg)
    m.ClearField("stamp_ns")
    m.ClearField("timings")
    return m


def provisional(estimates) -> list[codec.Reconstruction]:
    return [e for e in estimates if not wire.is_terminal(e)]


def live_feed(service: ReconstructionService, messages, delay_ns) -> list[list[codec.Reconstruction]]:
    """Each message handled at its acquisition time + the transit + ``delay_ns(step)``, on the service's wall
    clock; the estimates of each."""
    wall = [0]
    service.wall_ns = lambda: wall[0]
    out = []
    for m in messages:
        if isinstance(m, codec.Sample):
            wall[0] = m.acquisition_time_ns + TRANSIT_NS + delay_ns(m.step)
        out.append(service.handle(type_name(m), m.SerializeToString()))
    return out


def test_a_provisional_due_on_a_sample_that_waited_too_long_is_shed_and_counted(scan_messages):
    config = ReconstructConfig(provisional_period=0)
    late = range(120, 140)  # these steps waited in transit past the deadline
    waited = int(3 * config.provisional_deadline * 1e9)
    live = ReconstructionService(config)
    per_message = live_feed(live, scan_messages, lambda step: waited if step in late else 0)
    steps = [m.step if isinstance(m, codec.Sample) else None for m in scan_messages]
    published_late = [e for s, out in zip(steps, per_message) if s in late for e in provisional(out)]
    assert published_late == []
    # Counted as the estimates they stand for: one a refit_every steps, not one a sample.
    assert len(late) // config.refit_every - 1 <= live.stats.provisionals_stale <= len(late) // config.refit_every + 1
    assert live.stats_dict()["provisionals_stale"] == live.stats.provisionals_stale
    # Fresh again: estimates follow at once, with every step so far.
    after = [e for s, out in zip(steps, per_message) if s is not None and s >= late.stop for e in provisional(out)]
    assert after and after[0].last_step < late.stop + config.refit_every
    # Without the wall clock (a replay) the same stream publishes them all; the final is the same.
    replay = ReconstructionService(config)
    replayed = [replay.handle(type_name(m), m.SerializeToString()) for m in scan_messages]
    assert [e for s, out in zip(steps, replayed) if s in late for e in provisional(out)]
    assert replay.stats.provisionals_stale == 0
    (final_live,) = [e for out in per_message for e in out if wire.is_terminal(e)]
    (final_replay,) = [e for out in replayed for e in out if wire.is_terminal(e)]
    assert comparable(final_live) == comparable(final_replay)


def test_a_scanner_clock_offset_is_not_a_delay(scan_messages):
    """Staleness is what a sample waited beyond its scan's quickest, not the scanner's clock against ours."""
    config = ReconstructConfig(provisional_period=0)
    live = ReconstructionService(config)
    offset = 5_000_000_000  # the scanner's clock 5 s behind this host's
    per_message = live_feed(live, scan_messages, lambda step: offset)
    replay = ReconstructionService(config)
    replayed = [replay.handle(type_name(m), m.SerializeToString()) for m in scan_messages]
    assert live.stats.provisionals_stale == 0
    assert [comparable(e) for out in per_message for e in provisional(out)] == [
        comparable(e) for out in replayed for e in provisional(out)
    ]


def test_behind_a_short_backlog_a_refit_runs_at_once_and_its_exact_fits_wait(scan_messages):
    now = [0.0]
    config = ReconstructConfig(provisional_period=0)
    service = ReconstructionService(config, clock=lambda: now[0])
    alone = ReconstructionService(config)
    inline, caught_up, plain = [], [], []
    for k, m in enumerate(scan_messages):
        payload = m.SerializeToString()
        plain += alone.handle(type_name(m), payload)
        drained = k % 8 == 7  # payloads wait behind the others: the backlog drains every 8
        out = service.handle(type_name(m), payload, fits_wait=not drained)
        if isinstance(m, codec.Sample):
            # Estimated at once, of the sample just handled: not deferred to the next drain.
            assert all(e.last_step == m.step for e in provisional(out))
        inline += out
        if drained:
            caught_up += service.catch_up()  # the exact fits that waited
    assert service.stats.provisionals_shed == 0
    # As many estimates as without a backlog, but those waiting for plane a's first exact fit (up to a drain:
    # 8 payloads, 2 refits).
    assert len(provisional(inline)) >= len(provisional(plain)) - 8 // config.refit_every
    while service.has_deferred:
        caught_up += service.catch_up()
    (final,) = [e for e in inline + caught_up if wire.is_terminal(e)]
    (final_plain,) = [e for e in plain if wire.is_terminal(e)]
    assert comparable(final) == comparable(final_plain)
