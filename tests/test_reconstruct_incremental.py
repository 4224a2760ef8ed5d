"""Provisional estimates: O(new samples), warm-started, the guard only when the trust check fails,
rate-limited per scan in scan time."""

from __future__ import annotations

import numpy as np
import pytest

from lelsonar import codec
from lelsonar.errors import ConfigError
from lelsonar.reconstruct.estimate import wire
from lelsonar.reconstruct.estimate.correct import AXIS_Z
from lelsonar.reconstruct.estimate.incremental import (
    FACING_MARGIN,
    RETRY_GROWTH,
    IncrementalPlane,
    ransac_iterations,
)
from lelsonar.reconstruct.estimate.pipeline import FitOptions, fit_plane
from lelsonar.reconstruct.estimate.results import PlaneFit
from lelsonar.reconstruct.stream.config import ReconstructConfig
from lelsonar.reconstruct.stream.service import ReconstructionService
from lelsonar.sim import preset

from .conftest import assert_matches_the_scene, scene_truth, simulated_messages, type_name


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
    return [e for e in estimates if wire.status_name(e) == "provisional"]


def test_provisional_updates_are_incremental_and_the_guard_stays_idle_on_a_clean_scan(scan_messages):
    service = ReconstructionService(ReconstructConfig(provisional_period=0))
    seen = []

    class Spy:
        def scan_started(self, scan):
            pass

        def step(self, *a):
            pass

        def event(self, *a):
            pass

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


def test_the_points_handed_out_are_read_only_views_that_later_points_leave_unchanged(scan_messages):
    service = ReconstructionService(ReconstructConfig(provisional_period=0))
    _feed(service, scan_messages[: len(scan_messages) * 3 // 4])
    (p,) = service._partials.values()
    inc = p.inc_b
    data = inc.data()
    before = data.points.copy()
    assert data.n == inc.n and not data.points.flags.writeable and not data.step.flags.writeable
    _feed(service, scan_messages[len(scan_messages) * 3 // 4 : -1])  # more points (the buffers may grow)
    assert inc.n > data.n
    np.testing.assert_array_equal(data.points, before)
    np.testing.assert_array_equal(inc.data().points[: data.n], before)


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


def test_an_exact_fit_that_waits_is_the_one_it_would_have_been_on_the_same_points(scan_messages):
    service = ReconstructionService(ReconstructConfig(provisional=False))
    _feed(service, scan_messages[:-1])
    (scan,) = service.ingest.scans.values()
    steps = np.flatnonzero(scan.received)
    face_on = steps[np.sin(scan.gamma[steps]) >= np.cos(FitOptions().beam_half_angle)]
    now = IncrementalPlane(scan.geometry, "b", AXIS_Z, "adaptive", FitOptions(), scan.start.steps)
    waits = IncrementalPlane(scan.geometry, "b", AXIS_Z, "adaptive", FitOptions(), scan.start.steps)
    now.update(scan.gamma, scan.distance, face_on[:16])
    assert now.stats.exact == 1
    # The first fit waits: no estimate yet, and steps added meanwhile wait uncomputed, with no fit.
    assert waits.update(scan.gamma, scan.distance, face_on[:10], exact=False) is None
    assert waits.fit_wanted and waits.stats.exact == 0
    computed = waits.n
    assert waits.update(scan.gamma, scan.distance, face_on[10:16], exact=False) is None
    assert waits.stats.exact == 0 and waits.stats.fits_waited == 2 and waits.n == computed
    # Then it runs on every step so far: the fit made at once on the same steps, bit for bit.
    fitted = waits.update(scan.gamma, scan.distance, face_on[:0])
    assert not waits.fit_wanted and waits.stats.exact == 1 and waits.n == now.n
    assert isinstance(fitted, PlaneFit) and isinstance(now.plane, PlaneFit)
    assert np.array_equal(fitted.normal, now.plane.normal) and fitted.offset == now.plane.offset
    # A later fit that waits keeps the estimate it has meanwhile.
    bad = scan.distance.copy()
    bad[face_on[16:21]] += 0.30  # no new point fits: the trust check fails, an exact fit is due
    assert waits.update(scan.gamma, bad, face_on[16:21], exact=False) is fitted and waits.fit_wanted


def test_under_a_constant_backlog_catching_up_publishes_every_scan_with_its_newest_step(scan_messages):
    now = [0.0]
    busy = ReconstructionService(ReconstructConfig(provisional_period=0), clock=lambda: now[0])
    caught: list = []
    for m in scan_messages[:-1]:
        busy.handle(type_name(m), m.SerializeToString(), busy=True)
        if isinstance(m, codec.Sample) and m.step % 8 == 7:
            caught += busy.catch_up()  # the backlog drains every 8 steps
            now[0] += 1.0
    (p,) = busy._partials.values()
    # Every estimate names the newest step the scan held when it was made; the exact fits ran, caught up.
    assert caught and all(e.last_step % 8 == 7 for e in caught)
    assert p.inc_a.stats.exact == 1 and p.inc_b.stats.exact >= 1 and isinstance(p.inc_b.plane, PlaneFit)
    assert not busy.has_deferred
    # Plane b late in the scan: the estimate made without any backlog, to the fit's noise.
    alone = ReconstructionService(ReconstructConfig(provisional_period=0))
    _feed(alone, scan_messages[:-1])
    (q,) = alone._partials.values()
    assert isinstance(q.inc_b.plane, PlaneFit)
    assert np.degrees(np.arccos(np.clip(p.inc_b.plane.normal @ q.inc_b.plane.normal, -1, 1))) < 0.3


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
    with pytest.raises(ConfigError, match="provisional_period"):
        ReconstructConfig(provisional_period=-1)


@pytest.mark.parametrize("preset_name", ["paper-test1", "paper-test2"])
def test_provisional_planes_match_the_scene_late_in_the_scan_and_are_never_another_surface(preset_name):
    """Against the simulator's truth: every provisional estimate of the last 15 % of the scan within the
    noise model's bounds (``assert_matches_the_scene``), and no provisional plane b, at any step, that is
    not wall b (its normal further from the truth than a wall may tilt, FACING_MARGIN) — early in the sweep
    the only plane in subset b is the corner's echoes, which must be reported as a failure, not as wall b."""
    messages = _restamped(simulated_messages(preset_name, seed=2), 20_000_000)  # 50 Hz
    service = ReconstructionService()
    prov = _provisional(_feed(service, messages))
    steps = len(messages) - 2
    late = [e for e in prov if e.last_step >= 0.85 * steps]
    assert len(late) >= 5
    for estimate in late:
        assert_matches_the_scene(estimate, service.provisional_method, preset_name)
    normal_b, h_b = scene_truth(preset_name)["b"]
    seen_b = 0
    for estimate in prov:
        for pl in estimate.planes:
            if pl.label == "b":
                seen_b += 1
                n = np.array([pl.normal.x, pl.normal.y, pl.normal.z])
                assert np.degrees(np.arccos(np.clip(n @ normal_b, -1, 1))) < np.degrees(FACING_MARGIN), (
                    f"step {estimate.last_step}: plane b {n} is not wall b {normal_b}"
                )
    assert seen_b >= len(late)


def test_no_exact_fit_of_plane_b_before_the_beams_facing_it_give_most_of_its_echoes(scan_messages):
    service = ReconstructionService(ReconstructConfig(provisional_period=0))
    _feed(service, scan_messages[:-1])
    (p,) = service._partials.values()
    st = p.inc_b.stats
    # Before the gate opens the estimate is a typed failure at no cost; after it, one untrusted try at most
    # (the corner's echoes still weigh), then the wall; then O(new points) updates.
    assert st.exact <= 2 and st.not_facing > 10 and st.updates >= 5
    assert isinstance(p.inc_b.plane, PlaneFit)


def test_doubled_points_are_reclassified_without_an_exact_fit(scan_messages):
    service = ReconstructionService(ReconstructConfig(provisional=False))
    _feed(service, scan_messages[:-1])
    (scan,) = service.ingest.scans.values()
    steps = np.flatnonzero(scan.received)
    # Wall b seen face-on: the steps whose beam is within the beam half-angle of its normal.
    face_on = steps[np.sin(scan.gamma[steps]) >= np.cos(FitOptions().beam_half_angle)]
    inc = IncrementalPlane(scan.geometry, "b", AXIS_Z, "adaptive", FitOptions(), scan.start.steps)
    inc.update(scan.gamma, scan.distance, face_on[:10])
    assert inc.stats.exact == 1 and inc._theta_ls is not None
    at_exact = inc.n
    for k in range(10, len(face_on), 4):
        inc.update(scan.gamma, scan.distance, face_on[k : k + 4])
        if inc.n >= 2 * at_exact:
            break
    assert inc.n >= 2 * at_exact
    assert inc.stats.refreshes == 1 and inc.stats.exact == 1
    # Against the scene: 5σ of the noise model's error of a mean over the inliers (as assert_matches_the_scene,
    # with the spreads of these inliers: the capsules along x, the beams' hits across).
    plane = inc.plane
    assert isinstance(plane, PlaneFit) and plane.n_inliers > 0.9 * inc.n
    normal, h = scene_truth("paper-test1")["b"]
    cfg = preset("paper-test1")
    far = float(np.hypot(scene_truth("paper-test1")["a"][1], h))
    sigma_p = float(np.hypot(cfg.receiver.tof_jitter, far * cfg.servo.position_error))
    inliers = inc.data().points[plane.inlier_mask]
    root_n = np.sqrt(plane.n_inliers)
    for k in (0, 1):
        assert abs(plane.normal[k] - normal[k]) <= 5 * sigma_p / (root_n * np.std(inliers[:, k])), plane.normal
    assert abs(plane.offset - h) <= 5 * sigma_p / root_n


@pytest.mark.parametrize("share, miss", [(0.5, 1e-3), (0.3, 1e-2), (0.8, 1e-6)])
def test_provisional_ransac_draws_are_the_fewest_that_find_the_wall(share, miss):
    n = ransac_iterations(share, miss)
    assert (1 - share**3) ** n <= miss < (1 - share**3) ** (n - 1)
