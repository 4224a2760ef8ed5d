"""``lelsonar bench fleet --stages``: where one reconstructor's time goes, in this process, without Zenoh.

N scanners' scans (one simulated scan, encoded once, given each scanner's ids and a 50 Hz scan clock with
the scanners' phases spread over the period) are interleaved in acquisition order and handed to one
:class:`~lelsonar.reconstruct.stream.service.ReconstructionService`, as the live worker hands them when it
keeps up (no backlog: every provisional refit inline).  Each ``handle`` call's thread CPU is put in the
stage it ran:

- a sample that produced no estimate (decode, validation, assembly: the ingest);
- a sample that produced a provisional estimate, split into the exact fits made inside it (the
  provisional method from scratch, :func:`~lelsonar.reconstruct.estimate.pipeline.fit_plane` as
  :class:`~lelsonar.reconstruct.estimate.incremental.IncrementalPlane` calls it) and the rest (the
  O(new samples) update, the verdict, the message);
- a ScanEnd that produced the final (every method from scratch).

The floor is the worker's budget: one core over the offered samples (1e6 / (N × rate) µs a sample); the
table gives each stage's µs per sample beside it, the longest calls (a call is a stall of the stream: no
sample is handled meanwhile), and how many scanners one core could hold at ``--rate`` with everything,
without the finals (run elsewhere), and without the provisional exact fits too.  What runs outside
``handle`` in a live worker (the Zenoh receive, the channel) is not here: ``bench fleet`` measures it.
"""

from __future__ import annotations

import argparse
import itertools
import os
import statistics
import time
from collections import defaultdict, deque
from collections.abc import Callable
from dataclasses import replace
from typing import Any

from lelsonar.errors import ConfigError

#: The scan clock's origin (ns): a payload's time in :func:`interleaved` is its acquisition time less this.
T0 = 1_700_000_000_000_000_000
#: µs of the live worker's own CPU per sample outside ``handle`` (the Zenoh receive, the channel, the doorbell),
#: as ``bench fleet`` measures it at 100 scanners: the queue model charges it to every payload.
OUTSIDE_US = 50.0

#: A handle call longer than this holds the stream past the latency target's share: counted.
STALL_MS = 20.0

STAGES = ("ingest", "provisional update", "provisional exact fits", "final")

#: The queue model's rows: finals elsewhere or not, and the service's config fields set otherwise (A/B of the
#: provisional policy against the default config: the exact fits in the pool; no staleness deadline; refits deferred
#: behind any backlog, caught up 10 ms at a time).
MODEL_CASES: tuple[tuple[bool, str, dict[str, Any]], ...] = (
    (False, "", {}),
    (True, "", {}),
    (True, ", exact fits in the pool (fits_in_pool)", {"fits_in_pool": True}),
    (True, ", no provisional_deadline", {"provisional_deadline": 0.0}),
    (
        True,
        ", refits deferred behind any backlog, 10 ms catch-up",
        {"provisional_backlog": 0, "provisional_budget": 0.01},
    ),
)


def interleaved(preset: str, scanners: int, scans: int, rate: float, steps: int = 0) -> list[tuple[float, str, bytes]]:
    """(s from the first message, type name, payload) of ``scanners`` × ``scans`` scans in acquisition order, at
    ``rate`` Hz each."""
    from lelsonar.tools.bench_ingest_live import build_scan

    start, samples, end = build_scan(preset)
    if steps:
        samples = samples[:steps]
        end.samples_sent = len(samples)
    period = int(round(1e9 / rate))
    t0 = T0
    events: list[tuple[int, int, str, bytes]] = []
    for s in range(scanners):
        sid = f"s{s:03d}"
        phase = s * period // scanners
        for k in range(scans):
            base = t0 + phase + k * (len(samples) + 5) * period
            start.scanner_id, start.scan_id, start.start_time_ns = sid, k + 1, base
            events.append((base, 0, start.DESCRIPTOR.full_name, start.SerializeToString()))
            for i, sample in enumerate(samples):
                sample.scanner_id, sample.scan_id = sid, k + 1
                sample.acquisition_time_ns = base + (i + 1) * period
                events.append((sample.acquisition_time_ns, 1, sample.DESCRIPTOR.full_name, sample.SerializeToString()))
            end.scanner_id, end.scan_id, end.end_time_ns = sid, k + 1, base + (len(samples) + 1) * period + 1
            events.append((end.end_time_ns, 2, end.DESCRIPTOR.full_name, end.SerializeToString()))
    events.sort(key=lambda e: (e[0], e[1]))
    return [((t - t0) * 1e-9, name, payload) for t, _, name, payload in events]


def measure(payloads: list[tuple[float, str, bytes]], *, provisional: bool = True) -> dict[str, Any]:
    """Run the payloads through a fresh service; each handle call's thread CPU by stage (s), and the
    provisional refits' (steps held, µs)."""
    from lelsonar.reconstruct.estimate import incremental, wire
    from lelsonar.reconstruct.stream.config import ReconstructConfig
    from lelsonar.reconstruct.stream.service import ReconstructionService

    exact = [0.0]
    fit_plane = incremental.fit_plane

    def timed_fit(*a, **kw):  # the bench's probe of the exact fits, not a change of them
        c = time.thread_time()
        try:
            return fit_plane(*a, **kw)
        finally:
            exact[0] += time.thread_time() - c

    service = ReconstructionService(ReconstructConfig(provisional=provisional))
    calls: dict[str, list[float]] = defaultdict(list)
    refits: list[tuple[int, float]] = []
    samples = 0
    clock = time.thread_time
    incremental.fit_plane = timed_fit
    try:
        for _, type_name, payload in payloads:
            exact[0] = 0.0
            c = clock()
            out = service.handle(type_name, payload)
            spent = clock() - c
            if any(wire.is_terminal(m) for m in out):
                calls["final"].append(spent)
            elif out:
                calls["provisional exact fits"].append(exact[0])
                calls["provisional update"].append(spent - exact[0])
                refits.extend((int(m.last_step) + 1, 1e6 * spent / len(out)) for m in out)
            else:
                calls["ingest"].append(spent)
            samples += type_name.endswith("Sample")
    finally:
        incremental.fit_plane = fit_plane
    return {"calls": dict(calls), "refits": refits, "samples": samples, "finals": service.stats.finals}


class ModelPool:
    """The final pool of the queue model: one worker process of its own core, running its jobs in order.

    A job runs at :meth:`submit`, on this thread (its thread CPU is the pool's, :attr:`cpu`, not the model
    worker's), and its result is handed back (:meth:`ready`) once the virtual clock passes the job's end: the
    end of the job before it, or its submission, plus its CPU.  The service sees a pool of one worker whose
    room is ``capacity`` jobs, as :class:`~lelsonar.reconstruct.stream.final_pool.FinalPool`'s.
    """

    workers = 1

    def __init__(self, clock: Callable[[], float], capacity: int) -> None:
        from lelsonar.reconstruct.stream.final_pool import PoolStats

        self.capacity = capacity
        self.stats = PoolStats()
        self.cpu = 0.0  # CPU of the jobs run inside the model worker's call under way (reset by the model)
        self._clock = clock
        self._free_at = 0.0
        self._held: deque = deque()  # (end, Done), in submission order
        self._tickets = itertools.count()

    @property
    def unfinished(self) -> int:
        now = self._clock()
        return sum(1 for end, _ in self._held if end > now)

    def due(self) -> bool:
        """Whether a result is back (the live worker is woken for it)."""
        return bool(self._held) and self._held[0][0] <= self._clock()

    def submit(self, fn: Callable[..., Any], *args: Any) -> int:
        from lelsonar.reconstruct.stream.final_worker import Done

        ticket = next(self._tickets)
        at = self._clock()
        c = time.thread_time()
        try:
            done = Done(ticket, fn(*args))
        except Exception as exc:  # noqa: BLE001 - handed back with the job, as a worker does
            done = Done(ticket, error=exc)
        spent = time.thread_time() - c
        self.cpu += spent
        self._free_at = max(at, self._free_at) + spent
        self._held.append((self._free_at, done))
        self.stats.submitted += 1
        self.stats.pooled += 1
        return ticket

    def ready(self) -> list:
        out = []
        while self.due():
            out.append(self._held.popleft()[1])
        return out

    def drain(self) -> list:
        out = [done for _, done in self._held]
        self._held.clear()
        return out


def queue_model(
    payloads: list[tuple[float, str, bytes]],
    *,
    finals_elsewhere: bool,
    outside_us: float = OUTSIDE_US,
    tick_s: float = 0.1,
    provisional: bool = True,
    fields: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """One live worker with a core of its own, fed each payload at its acquisition time.

    The worker's loop is :class:`~lelsonar.reconstruct.stream.sources.LiveSource`'s: take the oldest waiting
    payload and handle it (``fits_wait`` while more wait, ``busy`` past ``provisional_backlog``), ``tick`` every
    ``tick_s``, ``catch_up`` when nothing waits, ``collect`` when the pool has results back.
    Each call takes the thread CPU it measures here, plus ``outside_us`` a payload, on a virtual clock the
    service reads too (its deferrals, budgets and rate limits run on it).  ``finals_elsewhere``: the service
    has a final pool (:class:`ModelPool`: a worker process on a core of its own) for its finals (their input,
    range repair included, and their reconstruction) and, with ``fits_in_pool``, its provisional exact fits;
    what runs there costs the worker nothing, and comes back when the pool's worker is done with it.  Once the
    last payload is handled the worker catches up on what waits, as an idle live worker does.  Returns put →
    processed and put → provisional latencies (s), the worker's busy share, and the provisional refits shed
    (under a backlog, or stale: the service's wall clock is the virtual one).  ``fields``: fields of the
    default :class:`~lelsonar.reconstruct.stream.config.ReconstructConfig` to set otherwise (an A/B of a policy).
    """
    from lelsonar.reconstruct.estimate import wire
    from lelsonar.reconstruct.stream.config import ReconstructConfig
    from lelsonar.reconstruct.stream.service import ReconstructionService

    now = [0.0]
    started: list[float] = []  # thread CPU at the start of the call under way: the clock runs inside a call too

    def clock() -> float:
        inside = time.thread_time() - started[0] - (pool.cpu if pool is not None else 0.0) if started else 0.0
        return now[0] + inside

    config = replace(ReconstructConfig(provisional=provisional), **(fields or {}))
    pool = ModelPool(clock, 2 * ModelPool.workers + 2 + config.max_scans) if finals_elsewhere else None
    service = ReconstructionService(config, clock=clock)
    service.wall_ns = lambda: T0 + int(clock() * 1e9)  # the payloads' acquisition times are T0 + their time
    service.use_pool(pool)  # type: ignore[arg-type]
    processed: list[float] = []
    provisionals: list[float] = []
    busy_s = 0.0

    def run(step: Callable[..., list], *args, **kwargs) -> None:
        nonlocal busy_s
        if pool is not None:
            pool.cpu = 0.0
        c = time.thread_time()
        started[:] = [c]
        try:
            out = step(*args, **kwargs)
        finally:
            started.clear()
        spent = time.thread_time() - c - (pool.cpu if pool is not None else 0.0)
        now[0] += spent
        busy_s += spent
        for m in out:
            scan = service.ingest.scans.get((m.scanner_id, m.scan_id))
            if not wire.is_terminal(m) and scan is not None:
                provisionals.append(now[0] - (int(scan.time_ns[m.last_step]) - T0) * 1e-9)

    waiting: deque = deque()
    i, n, last_tick = 0, len(payloads), 0.0

    def arrive() -> None:
        nonlocal i
        while i < n and payloads[i][0] <= now[0]:
            waiting.append(payloads[i])
            i += 1

    while i < n or waiting:
        if not waiting:
            now[0] = max(now[0], payloads[i][0])  # idle until the next payload
        arrive()
        if pool is not None and pool.due():
            run(service.collect)  # the pool woke the worker: its results are taken between payloads
        t, type_name, payload = waiting.popleft()
        now[0] += outside_us * 1e-6
        busy_s += outside_us * 1e-6
        arrive()
        run(
            service.handle,
            type_name,
            payload,
            busy=len(waiting) > service.config.provisional_backlog,
            fits_wait=bool(waiting),
        )
        if type_name.endswith("Sample"):
            processed.append(now[0] - t)
        arrive()
        if now[0] - last_tick >= tick_s:
            last_tick = now[0]
            run(service.tick, busy=bool(waiting))
        elif service.has_deferred and not waiting:
            run(service.catch_up)
    while service.has_deferred:  # idle after the last payload: what waits is caught up
        run(service.catch_up)
    run(service.collect, wait=True)
    span = now[0] - payloads[0][0] if payloads else 0.0
    return {
        "processed_s": processed,
        "provisional_s": provisionals,
        "busy": busy_s / span if span > 0 else 0.0,
        "shed": service.stats.provisionals_shed + service.stats.provisionals_stale,
        "stale": service.stats.provisionals_stale,
        "finals": service.stats.finals,
    }


def summary(result: dict[str, Any], scanners: int, rate: float) -> dict[str, Any]:
    """µs per sample by stage, the longest calls, and the scanners one core could hold."""
    n = max(result["samples"], 1)
    calls = result["calls"]
    per = {s: 1e6 * sum(calls.get(s, [])) / n for s in STAGES}
    handle = [v for s in STAGES if s != "provisional exact fits" for v in calls.get(s, [])]
    refit_calls = [u + x for u, x in zip(calls.get("provisional update", []), calls.get("provisional exact fits", []))]
    streamed = calls.get("ingest", []) + refit_calls  # every call but the finals
    total = sum(per.values())
    without_finals = total - per["final"]
    without_exact = without_finals - per["provisional exact fits"]
    return {
        "us_per_sample": per,
        "total_us": total,
        "budget_us": 1e6 / (scanners * rate),
        "longest_ms": 1e3 * max(handle, default=0.0),
        "longest_streamed_ms": 1e3 * max(streamed, default=0.0),
        "over_stall": sum(v * 1e3 > STALL_MS for v in handle),
        "over_stall_streamed": sum(v * 1e3 > STALL_MS for v in streamed),
        "p99_streamed_ms": 1e3 * _quantile(streamed, 0.99),
        "final_ms": 1e3 * statistics.median(calls["final"]) if calls.get("final") else None,
        "exact_fits": sum(x > 0 for x in calls.get("provisional exact fits", [])),
        "refits": len(refit_calls),
        "holds": {
            k: 1e6 / (v * rate) if v > 0 else None
            for k, v in (
                ("all", total),
                ("without finals", without_finals),
                ("without finals and exact fits", without_exact),
            )
        },
        "finals": result["finals"],
    }


def _quantile(values: list[float], q: float) -> float:
    if not values:
        return 0.0
    v = sorted(values)
    return v[min(len(v) - 1, int(q * (len(v) - 1)))]


def run_stages(args: argparse.Namespace, refit_cost: Callable[[list, int], dict]) -> int:
    from rich.console import Console
    from rich.table import Table

    from lelsonar.cli.warm_up import exercise_kernels
    from lelsonar.tools.bench import machine

    if args.scanners < 1 or args.scans < 1 or args.repeat < 1 or not args.rate > 0:
        raise ConfigError("--stages: --scanners, --scans and --repeat must be >= 1 and --rate > 0")
    console = Console()
    exercise_kernels()
    payloads = interleaved(args.preset, args.scanners, args.scans, args.rate, args.steps)
    steps = sum(1 for _, name, _ in payloads if name.endswith("Sample")) // (args.scanners * args.scans)
    load = os.getloadavg()
    runs = [measure(payloads, provisional=not args.no_provisional) for _ in range(args.repeat)]
    sums = [summary(r, args.scanners, args.rate) for r in runs]

    def med(get) -> float:
        values = [get(s) for s in sums]
        values = [v for v in values if v is not None]
        return statistics.median(values) if values else float("nan")

    command = (
        f"lelsonar bench fleet --stages --scanners {args.scanners} --rate {args.rate:g} --scans {args.scans} "
        f"--repeat {args.repeat}" + (" --no-provisional" if args.no_provisional else "")
    )
    table = Table(
        title=f"bench fleet --stages: one service, {args.scanners} scanners × {args.rate:g} Hz, {steps} steps a scan, "
        f"in this process (medians of {args.repeat})"
    )
    table.add_column("stage")
    table.add_column("µs / sample", justify="right")
    table.add_column("share of the budget", justify="right")
    budget = sums[0]["budget_us"]
    for stage in STAGES:
        us = med(lambda s, stage=stage: s["us_per_sample"][stage])
        table.add_row(stage, f"{us:.0f}", f"{us / budget:.2f}")
    total = med(lambda s: s["total_us"])
    table.add_row("all (thread CPU in handle)", f"{total:.0f}", f"{total / budget:.2f}")
    table.add_row("floor: the budget, one core / offered samples", f"{budget:.0f}", "1.00")
    console.print(
        f"command: {command}\nmachine: {machine()}\nload average before: {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}",
        highlight=False,
    )
    console.print(table)
    facts = Table(title="stalls, and what one core could hold (medians)")
    facts.add_column("")
    facts.add_column("", justify="right")
    facts.add_row(
        "provisional refits (calls that made one) / with an exact fit",
        f"{med(lambda s: s['refits']):.0f} / {med(lambda s: s['exact_fits']):.0f}",
    )
    facts.add_row("a final, ms", f"{med(lambda s: s['final_ms']):.1f}")
    facts.add_row(
        f"longest call, ms (calls over {STALL_MS:g} ms)",
        f"{med(lambda s: s['longest_ms']):.1f} ({med(lambda s: s['over_stall']):.0f})",
    )
    facts.add_row(
        f"without the finals: longest, p99 ms (over {STALL_MS:g} ms)",
        f"{med(lambda s: s['longest_streamed_ms']):.1f}, {med(lambda s: s['p99_streamed_ms']):.2f} "
        f"({med(lambda s: s['over_stall_streamed']):.0f})",
    )
    for k in ("all", "without finals", "without finals and exact fits"):
        facts.add_row(
            f"scanners × {args.rate:g} Hz one core holds at 100 % busy: {k}", f"{med(lambda s, k=k: s['holds'][k]):.0f}"
        )
    cost = refit_cost(runs[0]["refits"], steps)
    facts.add_row(
        "provisional refit µs (median) by steps held",
        " ".join(f"{b}: {'—' if v is None else f'{v:.0f}'}" for b, v in cost.items()),
    )
    console.print(facts)
    model = Table(
        title=f"queue model: one worker on a core of its own, fed at the scan clock, {OUTSIDE_US:g} µs a payload "
        "outside handle (medians)"
    )
    for col in (
        "finals",
        "busy",
        "put→processed p50 / p99 ms",
        "put→provisional p50 / p99 ms",
        "published",
        "shed (of which stale)",
    ):
        model.add_column(col, justify="left" if col == "finals" else "right")
    for elsewhere, label, fields in MODEL_CASES:
        queued = [
            queue_model(payloads, finals_elsewhere=elsewhere, provisional=not args.no_provisional, fields=fields)
            for _ in range(args.repeat)
        ]

        def ms(key: str, q: float, queued=queued) -> str:
            return f"{statistics.median(1e3 * _quantile(r[key], q) for r in queued):.1f}"

        model.add_row(
            ("in a pool of one worker (input and reconstruction)" if elsewhere else "inline") + label,
            f"{statistics.median(r['busy'] for r in queued):.2f}",
            f"{ms('processed_s', 0.5)} / {ms('processed_s', 0.99)}",
            f"{ms('provisional_s', 0.5)} / {ms('provisional_s', 0.99)}",
            f"{statistics.median(len(r['provisional_s']) for r in queued):.0f}",
            f"{statistics.median(r['shed'] for r in queued):.0f} ({statistics.median(r['stale'] for r in queued):.0f})",
        )
    console.print(model)
    load = os.getloadavg()
    console.print(
        f"load average after: {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}; finals "
        f"{runs[0]['finals']} of {args.scanners * args.scans}",
        highlight=False,
    )
    return 0 if runs[0]["finals"] == args.scanners * args.scans else 1
