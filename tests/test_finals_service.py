"""Finals estimated in the pool's workers are the finals estimated on the stream's thread: bit for bit, in
the order their scans were closed, with the same accounting and findings; never lost to a killed worker;
dropped only when their source fails, and then counted."""

from __future__ import annotations

import dataclasses
import os
import signal

import numpy as np
import pytest

from lelsonar import codec
from lelsonar.reconstruct.estimate import wire
from lelsonar.reconstruct.stream.config import ReconstructConfig
from lelsonar.reconstruct.stream.final_pool import FinalPool
from lelsonar.reconstruct.stream.replay import replay_mcap
from lelsonar.reconstruct.stream.service import ReconstructionService
from lelsonar.v1.scan_pb2 import SCAN_STATUS_ABORTED

from . import foreign_scenes as fs
from .conftest import QuietObserver, estimate_only, simulated_messages, type_name

STEPS = 90


@pytest.fixture(scope="module")
def scans():
    """Three scans of two scanners, the last aborted after 60 steps (a finding the stream adds)."""
    a = simulated_messages("paper-test1", seed=1, scanner_id="a", scan_id=1, steps=STEPS)
    b = simulated_messages("paper-test1", seed=2, scanner_id="b", scan_id=7, steps=STEPS)
    c = simulated_messages("paper-test1", seed=3, scanner_id="a", scan_id=2, steps=STEPS)
    end = c[-1]
    end.status, end.samples_sent, end.reason = SCAN_STATUS_ABORTED, 60, "stopped"
    return [*a, *b, *c[:61], end]


class Points(QuietObserver):
    """An observer keeping what a terminal estimate hands it: the planes' points travel back for it."""

    def __init__(self) -> None:
        self.results: list[dict] = []

    def estimate(self, scan, message, results, partial) -> None:
        if results is not None:
            self.results.append(results)


#: Fields that are the clock's, not the estimate's.
CLOCK = ("timings", "time_s")


def differences(a, b, path: str = ""):
    """Where two results differ, field by field, arrays bit for bit (NaN equal to NaN), the clock aside."""
    if dataclasses.is_dataclass(a) and not isinstance(a, type):
        for f in dataclasses.fields(a):
            if f.name not in CLOCK:
                yield from differences(getattr(a, f.name), getattr(b, f.name), f"{path}.{f.name}")
    elif isinstance(a, np.ndarray):
        if not (a.dtype == b.dtype and np.array_equal(a, b, equal_nan=True)):
            yield path
    elif isinstance(a, (list, tuple)):
        if len(a) != len(b):
            yield path
        for i, (x, y) in enumerate(zip(a, b)):
            yield from differences(x, y, f"{path}[{i}]")
    elif isinstance(a, float):
        if not (a == b or (a != a and b != b)):
            yield path
    elif a != b:
        yield path


def ready_pool(workers: int) -> FinalPool:
    pool = FinalPool(workers)
    assert pool.wait_ready(600), "the final workers did not start"
    return pool


def feed(service: ReconstructionService, messages) -> list[codec.Reconstruction]:
    out = []
    for m in messages:
        out += service.handle(type_name(m), m.SerializeToString())
    return out + service.finish()


def test_finals_from_workers_are_the_inline_ones_bit_for_bit_in_scan_order(scans):
    inline_points, pooled_points = Points(), Points()
    inline = feed(ReconstructionService(ReconstructConfig(provisional=False), observer=inline_points), scans)
    service = ReconstructionService(ReconstructConfig(provisional=False), observer=pooled_points)
    pool = ready_pool(2)
    try:
        service.use_pool(pool)
        pooled = feed(service, scans)
        service.use_pool(None)
    finally:
        pool.close()
    assert [(m.scanner_id, m.scan_id) for m in pooled] == [("a", 1), ("b", 7), ("a", 2)]
    assert [wire.status_name(m) for m in pooled] == ["final", "final", "aborted"]
    assert [estimate_only(m) for m in pooled] == [estimate_only(m) for m in inline]
    assert pooled[2].aborted_reason == "stopped" and any(
        "partial sweep" in r for p in pooled[2].planes for r in p.quality_reasons
    )
    # (a final no worker has taken when the input ends is estimated by the caller, which would otherwise wait)
    assert service.stats_dict()["finals_pool"]["in_workers"] >= 1 and service.stats.finals == 3
    # The observer gets each method's reconstruction, points and all, as the inline estimate gives them.
    for a, b in zip(inline_points.results, pooled_points.results, strict=True):
        assert a.keys() == b.keys()
        for method in a:
            assert not list(differences(a[method], b[method])), method
    assert service.latest["a"].scan_id == 2  # the scanner's newest estimate is its last scan's


def test_a_final_whose_ranges_are_repaired_in_a_worker_is_the_inline_one_bit_for_bit():
    """The range repair runs in the worker with the rest of the final, on the closed scan sent there: two
    foreign boards whose ranges it changes (a comparator whose crossing walks with the echoes' amplitude, and
    one that fires on the noise before 3 echoes in 10) give the finals the stream's thread gives."""
    walking = fs.simulate(fs.ForeignRig(seed=3, steps=150))
    walking.energy_model = fs.energy_model(walking.rig)
    noisy = fs.simulate(fs.ForeignRig(seed=3, steps=150, noise=0.007))
    messages = [
        *fs.messages(walking, scanner="walking", scan_id=1),
        *fs.messages(noisy, fs.Conventions(energy_model=False), scanner="noisy", scan_id=2),
    ]
    inline = feed(ReconstructionService(ReconstructConfig(provisional=False)), messages)
    service = ReconstructionService(ReconstructConfig(provisional=False))
    pool = ready_pool(2)
    try:
        service.use_pool(pool)
        pooled = feed(service, messages)
        service.use_pool(None)
    finally:
        pool.close()
    assert service.stats_dict()["finals_pool"]["in_workers"] == 2  # (each scan's final taken by an idle worker)
    assert [estimate_only(m) for m in pooled] == [estimate_only(m) for m in inline]
    # The repair changed both scans' ranges (their planes say so): the workers made it, not skipped it.
    walked, fired = ({r for p in m.planes for r in p.quality_reasons} for m in pooled)
    assert any("re-timed" in r for r in walked), walked
    assert any("comparator fired on noise" in r for r in fired), fired


def test_a_worker_killed_as_a_final_is_estimated_loses_nothing(scans):
    (inline,) = feed(ReconstructionService(ReconstructConfig(provisional=False)), scans[: STEPS + 2])
    service = ReconstructionService(ReconstructConfig(provisional=False))
    pool = ready_pool(1)
    try:
        service.use_pool(pool)
        for m in scans[: STEPS + 2]:  # the ScanEnd dispatches the final
            service.handle(type_name(m), m.SerializeToString())
        for pid in pool.busy_pids:
            os.kill(pid, signal.SIGKILL)
        (final,) = service.finish()
    finally:
        pool.close()
    assert estimate_only(final) == estimate_only(inline)
    assert service.stats.finals == 1


def test_finals_on_their_way_when_the_source_fails_are_dropped_and_counted(scans, caplog):
    service = ReconstructionService(ReconstructConfig(provisional=False))
    pool = ready_pool(1)
    try:
        service.use_pool(pool)
        for m in scans[: STEPS + 2]:
            service.handle(type_name(m), m.SerializeToString())
        assert service.finals_on_their_way == 1  # collected only by the next handle(), tick() or finish()
        assert service.use_pool(None, drain=False) == []
    finally:
        pool.close()
    assert service.stats_dict()["finals_pool"]["dropped"] == 1 and service.stats.finals == 0
    assert "1 finals dropped unmade" in caplog.text


@pytest.mark.slow
def test_a_replay_with_workers_gives_the_finals_of_one_without(scans, tmp_path):
    from lelsonar.log.recording import McapRecorder

    path = tmp_path / "three.mcap"
    with McapRecorder(path) as rec:
        for m in scans:
            rec.write(m)
    finals = {}
    for workers in (0, 2):
        service = ReconstructionService(ReconstructConfig(provisional=False, final_workers=workers))
        replay_mcap(path, service)
        finals[workers] = [estimate_only(m) for m in service.finals.values()]
    assert len(finals[0]) == 3 and finals[2] == finals[0]
