"""The figures of a ``lelsonar bench fleet`` run: one case's result from its workers' reports, and a case's
summary over its runs (medians of the figures, sums of the failures).

The worker's CPU per sample is split by where its processing thread spent it: inside ``handle``, ``tick`` and
``catch_up`` (the refits and finals that waited for a backlog), and the rest ("outside": Zenoh's receive, the
channel, the doorbell, the group's filter, the planes server).
"""

from __future__ import annotations

import statistics
import time
from collections import Counter
from typing import Any

from lelsonar.tools.bench_fleet_worker import TIMED_CALLS


def pct(values: list[float], q: float) -> float | None:
    if not values:
        return None
    v = sorted(values)
    return v[min(len(v) - 1, int(round(q / 100 * (len(v) - 1))))]


def case_result(
    reports: list[dict | None],
    finals: dict[tuple[str, int], list[str]],
    pub: dict | None,
    *,
    expected: int,
    killed: str | None,
    router_cpu: tuple[float | None, float | None, float],
    steps: int,
    t_start: float,
) -> dict[str, Any]:
    """One run's figures: the workers' ``reports`` (None: one that did not report), the terminal statuses
    of each scan (``finals``), the publishers' combined report, the router's CPU (before, after, over wall s)."""
    router_cpu0, router_cpu1, router_wall = router_cpu
    finished: list[dict] = [r for r in reports if r is not None]
    processed = [x / 1e6 for r in finished for x in r["processed_ns"]]
    provisional = [x / 1e6 for r in finished for x in r["provisional_ns"]]
    firsts = [r["first"] for r in finished if r["first"] is not None]
    lasts = [r["last"] for r in finished if r["last"] is not None]
    samples = sum(r["samples"] for r in finished)
    statuses = [s for v in finals.values() for s in v]
    return {
        "kill_one": killed,
        "expected_finals": expected,
        "scans_with_final": len(finals),
        "duplicated_finals": sum(len(v) - 1 for v in finals.values()),
        "incomplete_finals": sum(1 for s in statuses if not s.startswith("final:") or not s.endswith(":0"))
        + (expected - len(finals)),
        "handled_per_s": (samples - 1) / (max(lasts) - min(firsts))
        if len(firsts) and max(lasts) > min(firsts)
        else 0.0,
        "samples_processed": samples,
        # Samples the doorbell handed to an idle worker: each cost a wake-up of two threads.
        "doorbell_per_sample": sum(r.get("doorbell_rings", 0) for r in finished) / samples if samples else None,
        "processed_ms": {"p50": pct(processed, 50), "p99": pct(processed, 99)},
        "provisional_ms": {"p50": pct(provisional, 50), "p99": pct(provisional, 99), "n": len(provisional)},
        "cpu_per_worker": {r["member"]: r["cpu_s"] / r["wall_s"] for r in finished},
        # Over the window each was busy: a worker from its first live sample handled to its last (read at
        # most every 10 ms), the
        # publisher over its puts, the router over the publisher's puts.
        "busy_cpu": {
            **{
                r["member"]: r["busy_cpu_s"] / r["busy_wall_s"]
                for r in finished
                if r.get("busy_cpu_s") is not None and r["busy_wall_s"] > 0
            },
            **({"publisher": pub["cpu_s"] / pub["wall_s"]} if pub and pub.get("wall_s") else {}),
            **(
                {"router": (router_cpu1 - router_cpu0) / router_wall}
                if router_cpu0 is not None and router_cpu1 is not None and router_wall > 0
                else {}
            ),
        },
        "adopted": {r["member"]: r["group"].get("scans adopted", 0) for r in finished},
        "dropped_other_member": {r["member"]: r["group"].get("dropped: other member", 0) for r in finished},
        "recovered": {r["member"]: r["service"]["samples"]["recovered"] for r in finished},
        # Every provisional due and not published: shed under a backlog, or stale (its sample waited too long).
        "shed": {
            r["member"]: r["service"].get("provisionals_shed", 0) + r["service"].get("provisionals_stale", 0)
            for r in finished
        },
        "stale": {r["member"]: r["service"].get("provisionals_stale", 0) for r in finished},
        # Provisional exact fits that came back from the final pool (the rest ran on the samples' thread).
        "fits_from_pool": {r["member"]: r["service"].get("provisional_fits", {}).get("from_pool", 0) for r in finished},
        "statuses": dict(Counter(statuses)),
        "recovery": {r["member"]: r["service"]["recovery"] for r in finished},
        "rejected": {r["member"]: r["service"]["rejected"] for r in finished},
        "worker_errors": {r["member"]: r["errors"] for r in finished},
        "publisher": pub,
        "cpu_per_sample_us": {r["member"]: cpu_per_sample(r) for r in finished},
        "threads_cpu_s": {r["member"]: r.get("threads_cpu_s", {}) for r in finished},
        # The worst over the workers: the longest handle and tick, and the calls over STALL_MS.
        "longest_ms": {k: max((r["longest_call_ms"][k] for r in finished), default=None) for k in TIMED_CALLS},
        "stalls": {k: sum(r["stalls"][k] for r in finished) for k in TIMED_CALLS},
        "refit_us": refit_cost([x for r in finished for x in r["refits"]], steps),
        "elapsed_s": time.monotonic() - t_start,
    }


def cpu_per_sample(report: dict) -> dict[str, float] | None:
    """A worker's CPU per live sample, µs: all its threads over the window it was busy ("total"), its
    processing thread inside each of :data:`~lelsonar.tools.bench_fleet_worker.TIMED_CALLS`, and the rest
    ("outside": Zenoh's receive, the channel, the doorbell, the group's filter, the planes server)."""
    n, total = report["samples"], report.get("busy_cpu_s")
    if not n or total is None:
        return None
    inside = report["thread_cpu_s"]
    out = {"total": total * 1e6 / n, **{k: inside.get(k, 0.0) * 1e6 / n for k in TIMED_CALLS}}
    out["outside"] = out["total"] - sum(out[k] for k in TIMED_CALLS)
    return out


#: A worker's CPU per sample: all its threads, inside each timed call, the rest.
CPU_PARTS = ("total", *TIMED_CALLS, "outside")

#: Provisional refits' cost is shown by the quarter of the scan its steps reach.
REFIT_BINS = 4


def refit_cost(refits: list[tuple[int, float]], steps: int) -> dict[str, float | None]:
    """Median µs of CPU per provisional refit (the call that made it), by the quarter of the scan held then:
    flat when a refit costs O(new samples), rising when it costs O(steps so far)."""
    out: dict[str, float | None] = {}
    for b in range(REFIT_BINS):
        lo, hi = b * steps // REFIT_BINS + 1, (b + 1) * steps // REFIT_BINS
        cost = [us for held, us in refits if lo <= held <= hi]
        out[f"{lo}-{hi}"] = statistics.median(cost) if cost else None
    return out


def behind(pub: dict | None) -> str:
    """What the publishers' schedule says of a run: nothing (kept), held back by BLOCK, or invalid."""
    pub = pub or {}
    if pub.get("kept_up"):
        return ""
    if pub.get("held_back"):
        return f" behind: held back inside put {pub['blocked_s']:.1f} s (BLOCK: the workers did not keep up)"
    return " BEHIND on their own: run invalid"


def summarise(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """One case over its runs: medians of the figures, sums of the failures (every run kept in "runs")."""

    def med(values):
        values = [v for v in values if v is not None]
        return statistics.median(values) if values else None

    out: dict[str, Any] = {"runs": runs, "kill_one": runs[0]["kill_one"], "expected_finals": runs[0]["expected_finals"]}
    out["handled_per_s"] = med([r["handled_per_s"] for r in runs])
    out["doorbell_per_sample"] = med([r.get("doorbell_per_sample") for r in runs])
    for key in ("processed_ms", "provisional_ms"):
        out[key] = {q: med([r[key][q] for r in runs]) for q in ("p50", "p99")}
    out["scans_with_final"] = min(r["scans_with_final"] for r in runs)
    out["incomplete_finals"] = sum(r["incomplete_finals"] for r in runs)
    out["duplicated_finals"] = sum(r["duplicated_finals"] for r in runs)
    members = sorted({m for r in runs for m in r["cpu_per_worker"]})
    out["cpu_per_worker"] = {m: med([r["cpu_per_worker"].get(m) for r in runs]) for m in members}
    procs = sorted({m for r in runs for m in r["busy_cpu"]})
    out["busy_cpu"] = {m: med([r["busy_cpu"].get(m) for r in runs]) for m in procs}
    pubs = [r["publisher"] for r in runs if r["publisher"]]
    out["publisher"] = {
        k: med([p[k] for p in pubs]) for k in (pubs[0] if pubs else {}) if k not in ("kept_up", "held_back", "valid")
    }
    if pubs:
        for flag in ("kept_up", "held_back", "valid"):
            out["publisher"][flag] = len(pubs) == len(runs) and all(p[flag] for p in pubs)
    out["cpu_per_sample_us"] = {
        m: {k: med([(r["cpu_per_sample_us"].get(m) or {}).get(k) for r in runs]) for k in CPU_PARTS} for m in members
    }
    out["threads_cpu_s"] = {
        m: {k: med([r["threads_cpu_s"].get(m, {}).get(k) for r in runs]) for k in runs[0]["threads_cpu_s"].get(m, {})}
        for m in members
    }
    bins = runs[0]["refit_us"]
    out["refit_us"] = {b: med([r["refit_us"].get(b) for r in runs]) for b in bins}
    out["longest_ms"] = {
        k: max((r["longest_ms"][k] for r in runs if r["longest_ms"][k] is not None), default=None) for k in TIMED_CALLS
    }
    out["stalls"] = {k: sum(r["stalls"][k] for r in runs) for k in TIMED_CALLS}
    out["adopted"] = {m: med([r["adopted"].get(m, 0) for r in runs]) for m in members}
    out["statuses"] = dict(sum((Counter(r["statuses"]) for r in runs), Counter()))
    for key in ("recovered", "dropped_other_member", "shed", "stale", "fits_from_pool"):
        out[key] = {m: med([r[key].get(m, 0) for r in runs]) for m in members}
    return out
