"""Live, with a final pool, a provisional exact fit runs in the pool's workers: the same fit on the same points,
its plane's estimate kept meanwhile, and the finals untouched."""

from __future__ import annotations

import numpy as np
import pytest

from lelsonar import codec
from lelsonar.reconstruct.estimate import wire
from lelsonar.reconstruct.estimate.correct import AXIS_Z
from lelsonar.reconstruct.estimate.incremental import IncrementalPlane, exact_fit
from lelsonar.reconstruct.estimate.pipeline import FitOptions
from lelsonar.reconstruct.estimate.results import PlaneFit
from lelsonar.reconstruct.stream.config import ReconstructConfig
from lelsonar.reconstruct.stream.final_pool import PoolStats
from lelsonar.reconstruct.stream.final_worker import Done
from lelsonar.reconstruct.stream.service import ReconstructionService

from .conftest import estimate_only, simulated_messages, type_name


@pytest.fixture(scope="module")
def scan_messages():
    return simulated_messages("paper-test1", seed=5)


class HeldPool:
    """A pool of one worker whose jobs run only when the test lets them (:meth:`release`), in order."""

    workers = 1
    capacity = 1000

    def __init__(self) -> None:
        self.stats = PoolStats()
        self.jobs: list = []
        self.done: list[Done] = []
        self.tickets = 0
        self.names: list[str] = []

    @property
    def unfinished(self) -> int:
        return len(self.jobs)

    def submit(self, fn, *args) -> int:
        ticket, self.tickets = self.tickets, self.tickets + 1
        self.jobs.append((ticket, fn, args))
        self.names.append(fn.__name__)
        return ticket

    def release(self) -> None:
        self.done += [Done(t, fn(*args)) for t, fn, args in self.jobs]
        self.jobs.clear()

    def ready(self) -> list[Done]:
        out, self.done = self.done, []
        return out

    def drain(self) -> list[Done]:
        self.release()
        return self.ready()


def _live(pool) -> ReconstructionService:
    # No staleness (the test's clock is not the scan's), no rate limit: every refit is due.
    service = ReconstructionService(ReconstructConfig(provisional_period=0, provisional_deadline=0, fits_in_pool=True))
    service.wall_ns = lambda: 0  # a live source's
    service.use_pool(pool)
    return service


def test_an_exact_fit_handed_out_is_the_one_made_at_once_on_the_same_points(scan_messages):
    service = ReconstructionService(ReconstructConfig(provisional=False))
    for m in scan_messages[:-1]:
        service.handle(type_name(m), m.SerializeToString())
    (scan,) = service.ingest.scans.values()
    steps = np.flatnonzero(scan.received)
    face_on = steps[np.sin(scan.gamma[steps]) >= np.cos(FitOptions().beam_half_angle)]
    now = IncrementalPlane(scan.geometry, "b", AXIS_Z, "adaptive", FitOptions(), scan.start.steps)
    away = IncrementalPlane(scan.geometry, "b", AXIS_Z, "adaptive", FitOptions(), scan.start.steps)
    now.update(scan.gamma, scan.distance, face_on[:16])
    assert away.update(scan.gamma, scan.distance, face_on[:16], exact=False) is None and away.fit_wanted
    job = away.take_fit()
    assert away.fit_away and not away.fit_wanted
    # Meanwhile: no estimate yet, no fit, and the steps added wait uncomputed.
    computed = away.n
    assert away.update(scan.gamma, scan.distance, face_on[16:20]) is None
    assert away.n == computed and away.stats.exact == 0
    fitted = away.fitted(exact_fit(job))
    assert isinstance(fitted, PlaneFit) and isinstance(now.plane, PlaneFit) and not away.fit_away
    assert np.array_equal(fitted.normal, now.plane.normal) and fitted.offset == now.plane.offset
    # The steps that waited are taken by the next update, against the fitted plane.
    away.update(scan.gamma, scan.distance, face_on[:0])
    assert away.n > computed and away.stats.exact == 1


def test_live_with_a_pool_the_exact_fits_run_there_and_the_stream_publishes_meanwhile(scan_messages):
    pool = HeldPool()
    service = _live(pool)
    published: list[codec.Reconstruction] = []
    for m in scan_messages[:-1]:
        published += service.handle(type_name(m), m.SerializeToString())
        if not pool.jobs:
            continue
        # Plane a's first fit is away: nothing is published for the scan until it is back.
        (p,) = service._partials.values()
        assert p.inc_a is not None and (p.inc_a.fit_away or p.inc_a.stats.exact)
        if p.inc_a.fit_away:
            assert not [e for e in published if wire.status_name(e) == "provisional"]
        pool.release()
        published += service.collect()
    (p,) = service._partials.values()
    provisional = [e for e in published if wire.status_name(e) == "provisional"]
    assert provisional and any(len(e.planes) == 2 for e in provisional)
    # Every exact fit ran in the pool, none on the stream's thread.
    fits = p.inc_a.stats.exact + p.inc_b.stats.exact
    assert fits >= 2 and p.inc_a.stats.fits_away + p.inc_b.stats.fits_away == fits
    assert service.stats.fits_from_pool == fits == pool.names.count("exact_fit")
    assert isinstance(p.inc_b.plane, PlaneFit)
    # The final is the one a service without a pool makes, bit for bit.
    service.handle(type_name(scan_messages[-1]), scan_messages[-1].SerializeToString())
    (final,) = [e for e in service.collect(wait=True) if wire.is_terminal(e)]
    alone = ReconstructionService(ReconstructConfig(provisional_period=0))
    out = []
    for m in scan_messages:
        out += alone.handle(type_name(m), m.SerializeToString())
    (expected,) = [e for e in out if wire.is_terminal(e)]
    assert estimate_only(final) == estimate_only(expected)


def test_fits_away_when_the_pool_goes_are_due_again_and_made_here(scan_messages):
    pool = HeldPool()
    service = _live(pool)
    for m in scan_messages[:-1]:
        service.handle(type_name(m), m.SerializeToString())
        if pool.jobs:
            break
    (p,) = service._partials.values()
    assert p.inc_a is not None and p.inc_a.fit_away
    service.use_pool(None, drain=False)  # the source failed: the pool's jobs are lost
    assert p.inc_a.fit_wanted and not p.inc_a.fit_away and service.has_deferred
    service.catch_up()
    assert p.inc_a.stats.exact == 1 and not p.inc_a.fit_wanted and not service.has_deferred
