"""Provisional estimates: O(new samples), warm-started, the guard only when the trust check fails,
rate-limited per scan in scan time (issue 12 §2)."""

from __future__ import annotations

import numpy as np
import pytest

from lelsonar import codec
from lelsonar.reconstruct import present
from lelsonar.reconstruct.correct import AXIS_Z
from lelsonar.reconstruct.incremental import RETRY_GROWTH, IncrementalPlane
from lelsonar.reconstruct.pipeline import FitOptions, fit_plane
from lelsonar.reconstruct.results import PlaneFit
from lelsonar.reconstruct.service import ReconstructConfig, ReconstructionService

from .conftest import assert_matches_the_scene, simulated_messages, type_name


@pytest.fixture(scope="module")
def scan_messages():
    return simulated_messages("paper-test1", seed=5)


def _restamped(messages, step_ns: int) -> list:
    """The same scan, its samples ``step_ns`` apart in acquisition time."""
    out = []
    for m in messages:
        c = type(m)()
        c.CopyFrom(m)
        if isinstance(c, codec.Sample):
            c.acquisition_time_ns = 1_700_000_000_000_000_000 + c.step * step_ns
        out.append(c)
    return out


def _feed(service, messages):
    out = []
    for m in messages:
        out += service.handle(type_name(m), m.SerializeToString())
    return out


def _provisional(estimates):
    return [e for e in estimates if present.status_name(e) == "provisional"]


def test_provisional_updates_are_incremental_and_the_guard_stays_idle_on_a_clean_scan(scan_messages):
    service = ReconstructionService(ReconstructConfig(provisional_period=0))
    seen = []

    class Spy:
        def scan_started(self, scan): pass
        def step(self, *a): pass
        def event(self, *a): pass

        def estimate(self, scan, message, results, partial):
            if results is None:
                seen.append(partial)

    service._observer = Spy()
    estimates = _feed(service, scan_messages)
    prov = _provisional(estimates)
    assert len(prov) > 10
    inc = seen[-1].inc_b
    # Exact fits only at the start, on doubling and on trust failures: logarithmically few; the rest are
    # O(new points) updates; the outlier-cluster guard (RANSAC) never ran on this clean scan.
    st = inc.stats
    assert st.calls == len(prov) and st.calls == st.updates + st.exact + st.waited + st.not_facing
    # Exact fits: untrusted ones (wall b not yet seen face-on) are retried only as the points grow by
    # RETRY_GROWTH; trusted ones only on doubling: logarithmically few either way.
    retries = int(np.ceil(np.log(max(inc.n, 2)) / np.log(RETRY_GROWTH)))
    assert st.exact <= 1 + retries + int(np.ceil(np.log2(max(inc.n, 2)))) + st.trust_failures
    assert st.guarded <= st.exact and st.exact < st.calls / 3
    # Plane a (clean, seen face-on) passes the guard's own test unguarded: the RANSAC fallback never ran.
    assert seen[-1].inc_a.stats.exact == 1 and seen[-1].inc_a.stats.guarded == 0
    assert_matches_the_scene(prov[-1], service.provisional_method)
    # The data drawn by observers are the points behind the plane.
    assert isinstance(inc.plane, PlaneFit) and seen[-1].data_b.n == inc.plane.n_points == inc.n


def test_the_incremental_plane_agrees_with_a_fit_from_scratch(scan_messages):
    service = ReconstructionService(ReconstructConfig(provisional_period=0))
    _feed(service, scan_messages[:-1])  # no ScanEnd: the scan stays open
    (p,) = service._partials.values()
    inc = p.inc_b
    scratch = fit_plane(inc.data(), service.provisional_method, options=FitOptions())
    assert isinstance(scratch, PlaneFit) and isinstance(inc.plane, PlaneFit)
    angle = np.degrees(np.arccos(np.clip(scratch.normal @ inc.plane.normal, -1, 1)))
    assert angle < 0.3
    assert abs(scratch.offset - inc.plane.offset) < 0.005


def test_a_failed_trust_check_falls_back_to_an_exact_fit(scan_messages):
    service = ReconstructionService(ReconstructConfig(provisional=False))
    _feed(service, scan_messages[:-1])
    (scan,) = service.ingest.scans.values()
    steps = np.flatnonzero(scan.received)
    crit = int(steps[len(steps) // 2])
    b_steps = steps[steps > crit]
    inc = IncrementalPlane(scan.geometry, "b", AXIS_Z, "adaptive", FitOptions(), scan.start.steps)
    inc.update(scan.gamma, scan.distance, b_steps[:40])
    assert inc.stats.exact == 1 and inc._theta_ls is not None
    # Then steps whose ranges are all 30 cm off the wall: no new point fits, the check fails.
    bad = scan.distance.copy()
    bad[b_steps[40:45]] += 0.30
    inc.update(scan.gamma, bad, b_steps[40:45])
    assert inc.stats.trust_failures == 1 and inc.stats.exact == 2


def test_provisional_estimates_are_rate_limited_in_scan_time(scan_messages):
    every_20ms = _provisional(_feed(ReconstructionService(), _restamped(scan_messages, 20_000_000)))
    every_5ms = _provisional(_feed(ReconstructionService(), _restamped(scan_messages, 5_000_000)))
    period = ReconstructConfig().provisional_period
    for prov, step_s in ((every_20ms, 0.02), (every_5ms, 0.005)):
        last = [e.last_step for e in prov]
        assert len(last) >= 2
        assert min(np.diff(last)) * step_s >= period - 1e-9
    # At 50 Hz the limit and refit_every (4 steps) agree; at 200 Hz the limit holds it to 12.5 a second.
    assert len(every_5ms) < len(every_20ms)
    # Deterministic: scan time, not the wall clock.
    again = _provisional(_feed(ReconstructionService(), _restamped(scan_messages, 5_000_000)))
    assert [e.last_step for e in again] == [e.last_step for e in every_5ms]
    with pytest.raises(Exception):
        ReconstructConfig(provisional_period=-1)
