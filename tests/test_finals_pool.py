"""The final-estimation pool: results in submission order, the same as computed inline, bounded, and a
worker that dies loses nothing (its job runs again, and is counted)."""

from __future__ import annotations

import os
import signal
import threading

import pytest

from lelsonar.reconstruct.stream.final_pool import FinalPool
from lelsonar.reconstruct.stream.final_worker import WORKER_NICENESS
from lelsonar.reconstruct.stream.finals import auto_workers


def spin(value: int, rounds: int) -> int:
    """CPU work whose length is ``rounds``: later jobs can finish before earlier ones."""
    acc = 0
    for i in range(rounds):
        acc = (acc + i * value) % 1_000_003
    return value * value + 0 * acc


def fail(value: int) -> int:
    raise ValueError(f"bad scan {value}")


def die_once(marker: str, value: int) -> int:
    """Kills its worker the first time it runs (the marker file says it has)."""
    try:
        fd = os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
    except FileExistsError:
        return value
    os.close(fd)
    os.kill(os.getpid(), signal.SIGKILL)
    return -1


def die_in_worker(caller: int, value: int) -> int:
    """Kills every worker that runs it; returns in the caller."""
    if os.getpid() != caller:
        os.kill(os.getpid(), signal.SIGKILL)
    return value


def worker_pid(_: int) -> int:
    return os.getpid()


@pytest.fixture
def pool():
    p = FinalPool(2)
    yield p
    p.close()


def wait_ready(pool: FinalPool, workers: int) -> None:
    assert pool.wait_ready(600) and pool.ready_workers >= workers


def test_results_come_back_in_submission_order_whichever_worker_finishes_first(pool):
    wait_ready(pool, 2)
    rounds = [1_000_000, 10, 10, 500_000, 10, 10]  # the first is the longest
    tickets = [pool.submit(spin, i, r) for i, r in enumerate(rounds)]
    out = pool.drain()
    assert [d.ticket for d in out] == tickets
    assert [d.value for d in out] == [i * i for i in range(len(rounds))]
    assert pool.stats.pooled >= 1 and pool.stats.pooled + pool.stats.inline == len(rounds)


def test_without_a_ready_worker_the_caller_computes_and_order_holds():
    with FinalPool(0) as inline:
        tickets = [inline.submit(spin, i, 10) for i in range(3)]
        assert [d.value for d in inline.ready()] == [0, 1, 4] and tickets == [0, 1, 2]
        assert inline.stats.inline == 3


def test_an_error_comes_back_with_its_job_and_the_others_complete(pool):
    wait_ready(pool, 1)
    pool.submit(spin, 2, 10)
    pool.submit(fail, 7)
    pool.submit(spin, 3, 10)
    out = pool.drain()
    assert out[0].value == 4 and out[2].value == 9
    assert isinstance(out[1].error, ValueError) and "bad scan 7" in str(out[1].error)
    assert "fail" in out[1].trace and pool.stats.errors == 1


def test_a_killed_worker_s_job_runs_again_and_is_counted(pool, tmp_path):
    wait_ready(pool, 2)
    pool.submit(spin, 1, 10)
    pool.submit(die_once, str(tmp_path / "died"), 5)
    pool.submit(spin, 2, 10)
    out = pool.drain()
    assert [d.value for d in out] == [1, 5, 4]
    assert pool.stats.workers_lost == 1 and pool.stats.rerun == 1
    wait_ready(pool, 2)  # a new worker took its place


def test_a_job_that_kills_every_worker_ends_in_the_caller_never_lost(pool):
    wait_ready(pool, 2)
    woke = threading.Event()
    pool.on_ready = woke.set  # results, deaths and new workers wake the caller
    pool.submit(die_in_worker, os.getpid(), 11)
    out = pool.ready()
    while not out:  # ready() never runs a job a worker may still take: only one two workers died on
        woke.wait(30)
        woke.clear()
        out = pool.ready()
    assert [d.value for d in out] == [11]
    assert pool.stats.workers_lost == 2 and pool.stats.inline == 1


def test_a_worker_killed_from_outside_mid_job_loses_nothing(pool):
    wait_ready(pool, 2)
    pool.submit(spin, 3, 3_000_000)  # long enough to be killed while it runs
    (victim,) = pool.busy_pids
    os.kill(victim, signal.SIGKILL)
    out = pool.drain()
    assert [d.value for d in out] == [9]
    assert pool.stats.workers_lost == 1 and pool.stats.rerun == 1


def test_past_capacity_the_caller_runs_the_job_so_what_waits_stays_bounded():
    with FinalPool(1, capacity=2) as pool:
        wait_ready(pool, 1)
        most = 0
        for i in range(8):
            pool.submit(spin, i, 200_000)
            most = max(most, pool.unfinished)
        assert most <= 2
        assert [d.value for d in pool.drain()] == [i * i for i in range(8)]
        assert pool.stats.inline + pool.stats.pooled == 8


def test_workers_ignore_ctrl_c_and_close_ends_them():
    pool = FinalPool(1)
    wait_ready(pool, 1)
    pool.submit(worker_pid, 0)
    (pid,) = [d.value for d in pool.drain()]
    os.kill(pid, signal.SIGINT)  # Ctrl-C reaches the whole foreground group: the caller decides
    pool.submit(spin, 4, 10)
    assert [d.value for d in pool.drain()] == [16]
    pool.close()
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)  # reaped: gone


def test_workers_yield_the_core_to_their_caller(pool):
    wait_ready(pool, 1)
    pool.submit(os.nice, 0)
    (niceness,) = [d.value for d in pool.drain() if d.error is None]
    assert pool.stats.pooled == 1 and niceness == min(19, os.nice(0) + WORKER_NICENESS)


def test_auto_workers_leaves_the_caller_its_core():
    assert auto_workers(1) == 0 and auto_workers(2) == 1 and auto_workers(3) == 2 and auto_workers(64) == 2
