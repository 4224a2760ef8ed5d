"""``lelsonar bench fleet --capacity``: how many scanners one reconstructor keeps up with.

The offered rate is raised rung by rung — N scanners × ``--rate`` samples/s, N from the
ladder, one worker, no failover — until a rung does not hold (the rungs up to
``TARGET_SCANNERS`` are measured whatever: their p99 is the target's).  A rung holds when the worker
handles at least ``HOLD_SHARE`` of the offered rate (live samples processed, from the first to
the last) and every scan gets exactly one complete final.  The capacity is the largest N that
holds, reported with its p99 put → provisional estimate published; the table also shows that
p99 at every rung (50 and 100 scanners among them by default), against ``TARGET_P99_MS``.

The scanners are spread over publisher processes (:mod:`lelsonar.tools.bench_fleet_publisher`); a
rung whose publishers could not keep their own schedule is invalid, not "does not hold": there the
offered rate was not offered (publishers held back inside their puts by congestion control BLOCK
are the worker's doing: that rung is valid, and does not hold).  The ladder stops at an invalid
rung, and the capacity found (the rungs below) is a lower bound.  Each rung also shows the
worker's CPU per sample, inside ``handle``, ``tick`` and ``catch_up`` and outside them.
"""

from __future__ import annotations

import argparse
import copy
import os
import statistics
from collections.abc import Callable

from lelsonar.reconstruct.stream.config import ReconstructConfig
from lelsonar.tools.bench_fleet_results import CPU_PARTS
from lelsonar.tools.bench_fleet_worker import TIMED_CALLS

#: Scanner counts tried by ``--capacity`` with no N given.
CAPACITY_LADDER = (10, 25, 50, 75, 100, 150)
#: A rung holds when the worker handles this share of the offered rate (scanners × rate) and every scan
#: gets one complete final.
HOLD_SHARE = 0.98
#: Target: one reconstructor holds this many scanners, with p99 put → provisional within TARGET_P99_MS.
TARGET_SCANNERS = 100
TARGET_P99_MS = 50.0

HEADERS = (
    "scanners",
    "offered samples/s",
    "put samples/s",
    "handled samples/s",
    "handled / offered",
    "put→processed p50 / p99 ms",
    "put→provisional p50 / p99 ms",
    "finals complete",
    "publisher took / schedule s",
    "worker CPU busy",
    "µs/sample all / handle / tick / catch_up / outside",
    "holds",
)


def rung(args: argparse.Namespace, scanners: int, run_case: Callable, summarise: Callable) -> dict:
    """One steady run of ``scanners`` scanners on one worker; the summary, and whether it holds."""
    case = copy.copy(args)
    case.scanners, case.workers, case.failover = scanners, 1, "off"
    res = summarise([run_case(case, kill_one=False) for _ in range(args.repeat)])
    offered = scanners * args.rate
    pub = res["publisher"] or {}
    res["scanners"] = scanners
    res["offered"] = offered
    res["share"] = res["handled_per_s"] / offered if offered else 0.0
    res["publisher_kept_up"] = bool(pub.get("kept_up"))
    # Publishers held back by BLOCK (the worker's back-pressure) make a valid rung that does not hold.
    res["valid"] = bool(pub.get("valid"))
    # Samples actually put per second.
    res["put_rate"] = pub["samples"] / pub["wall_s"] if pub.get("wall_s") else 0.0
    res["complete"] = (
        res["scans_with_final"] == res["expected_finals"]
        and not res["incomplete_finals"]
        and not res["duplicated_finals"]
    )
    res["holds"] = res["publisher_kept_up"] and res["share"] >= HOLD_SHARE and res["complete"]
    return res


def provisional_rate(res: dict) -> tuple[float, float]:
    """Provisional estimates published a second per scanner over the publishers' schedule, and the share of
    the refits due that were shed (shed / (shed + published)): the p99 stands beside both, so a p99 bought by
    shedding shows."""
    runs = res.get("runs") or []
    published = statistics.median(r["provisional_ms"]["n"] for r in runs) if runs else 0
    shed = sum(res["shed"].values())
    schedule = (res["publisher"] or {}).get("schedule_s") or float("nan")
    rate = published / res["scanners"] / schedule if res["scanners"] else float("nan")
    return rate, shed / (shed + published) if shed + published else 0.0


def _ms(d: dict) -> str:
    return " / ".join("—" if d.get(k) is None else f"{d[k]:.0f}" for k in ("p50", "p99"))


def row(res: dict) -> tuple[str, ...]:
    pub = res["publisher"] or {}
    busy = [v for m, v in res["busy_cpu"].items() if m.startswith("w") and v is not None]
    verdict = (
        "yes"
        if res["holds"]
        else "no"
        if res["publisher_kept_up"]
        else "no (publishers held back by BLOCK)"
        if res["valid"]
        else "invalid: publishers behind"
    )
    cpu = [v for v in res["cpu_per_sample_us"].values() if v and v.get("total") is not None]
    return (
        str(res["scanners"]),
        f"{res['offered']:.0f}",
        f"{res['put_rate']:.0f}",
        f"{res['handled_per_s']:.0f}",
        f"{res['share']:.2f}",
        _ms(res["processed_ms"]),
        _ms(res["provisional_ms"]),
        f"{res['scans_with_final']} / {res['expected_finals']}" + ("" if res["complete"] else " (!)"),
        f"{pub.get('wall_s', float('nan')):.1f} / {pub.get('schedule_s', float('nan')):.1f}",
        " ".join(f"{100 * v:.0f}%" for v in busy),
        " ".join(" / ".join(f"{v[k]:.0f}" for k in CPU_PARTS) for v in cpu),
        verdict,
    )


def run_capacity(args: argparse.Namespace, run_case: Callable, summarise: Callable, command_line: Callable) -> int:
    """The ladder, with :mod:`lelsonar.tools.bench_fleet`'s ``run_case``, ``summarise`` and ``command_line``."""
    from rich.console import Console
    from rich.table import Table

    from lelsonar.tools import bench_markdown
    from lelsonar.tools.bench import machine

    ladder = sorted(set(args.capacity or CAPACITY_LADDER))
    console = Console(width=max(Console().width, 160))
    load0 = os.getloadavg()
    results = []
    for n in ladder:
        console.print(f"capacity: {n} scanners × {args.rate:g} Hz …", highlight=False)
        res = rung(args, n, run_case, summarise)
        results.append(res)
        if not res["valid"]:
            break  # a higher rate would not be offered either
        if not res["holds"] and n >= TARGET_SCANNERS:
            break  # past what one reconstructor keeps up with (the target's rungs are measured whatever)
    held = []
    for r in results:  # the largest N below which every rung held too
        if not r["holds"]:
            break
        held.append(r)
    best = held[-1] if held else None
    load1 = os.getloadavg()
    title = f"bench fleet --capacity: one reconstructor, N scanners × {args.rate:g} Hz, {args.scans} scans each" + (
        f" (medians of {args.repeat} runs)" if args.repeat > 1 else ""
    )
    rows = [row(r) for r in results]
    notes = [
        f"floor: the offered rate, N scanners × {args.rate:g} samples/s; a rung holds when the worker handles ≥ "
        f"{HOLD_SHARE} of it and every scan gets one complete final; past {TARGET_SCANNERS} scanners the ladder "
        "stops at the first that does not",
        (
            f"capacity: {best['scanners']} scanners ({best['handled_per_s']:.0f} samples/s handled), p99 "
            f"put→provisional {_ms(best['provisional_ms']).split(' / ')[1]} ms (target ≤ {TARGET_P99_MS:.0f} ms)"
            if best
            else f"capacity: below {ladder[0]} scanners"
        )
        + (
            "; a lower bound: the publishers fell behind their schedule at the next rung (invalid)"
            if results and not results[-1]["holds"] and not results[-1]["valid"]
            else ""
        )
        + ("; every rung held" if results and results[-1]["holds"] else ""),
        "p99 put→provisional: "
        + ", ".join(f"{r['scanners']} scanners {_ms(r['provisional_ms']).split(' / ')[1]} ms" for r in results)
        + f" (target ≤ {TARGET_P99_MS:.0f} ms at {TARGET_SCANNERS})",
        "provisional refit µs (median, the call that made it) by steps held: "
        + "; ".join(
            f"{r['scanners']} scanners "
            + " ".join(f"{b}: {'—' if v is None else f'{v:.0f}'}" for b, v in r["refit_us"].items())
            for r in results
        ),
        "longest handle / tick / catch_up, ms CPU (calls over 20 ms): "
        + ", ".join(
            f"{r['scanners']} scanners "
            + " / ".join(
                "—" if r["longest_ms"][k] is None else f"{r['longest_ms'][k]:.0f} ({r['stalls'][k]})"
                for k in TIMED_CALLS
            )
            for r in results
        ),
        "samples that woke an idle worker (the doorbell: two threads' wake-up each): "
        + ", ".join(
            f"{r['scanners']} scanners "
            + ("—" if r.get("doorbell_per_sample") is None else f"{100 * r['doorbell_per_sample']:.0f} %")
            for r in results
        ),
        "provisionals shed (under a backlog), and published a second per scanner (at most "
        f"{1 / ReconstructConfig().provisional_period:g}): "
        + ", ".join(
            f"{r['scanners']} scanners {sum(r['shed'].values()):g} shed ({sum(r['stale'].values()):g} stale) "
            f"({100 * provisional_rate(r)[1]:.0f} % of those due), {provisional_rate(r)[0]:.1f}/s published, "
            f"{sum(r.get('fits_from_pool', {}).values()):g} exact fits made in the final pool"
            for r in results
        ),
        f"command: {command_line(args)}",
        f"machine: {machine()}; load average before {load0[0]:.2f} {load0[1]:.2f} {load0[2]:.2f}, after "
        f"{load1[0]:.2f} {load1[1]:.2f} {load1[2]:.2f} (2 cores shared with other work: figures are of this run)",
    ]
    table = Table(title=title)
    for i, h in enumerate(HEADERS):
        table.add_column(h, justify="left" if i in (0, len(HEADERS) - 1) else "right")
    for cells in rows:
        table.add_row(*cells)
    console.print(table)
    for note in notes:
        console.print(note, highlight=False)
    bench_markdown.write(args.markdown, [bench_markdown.table(title, HEADERS, rows, notes)])
    at_target = next((r for r in held if r["scanners"] >= TARGET_SCANNERS), None)
    p99 = at_target["provisional_ms"]["p99"] if at_target is not None else None
    ok = p99 is not None and p99 <= TARGET_P99_MS
    console.print(
        f"target: ≥ {TARGET_SCANNERS} scanners held with p99 put→provisional ≤ {TARGET_P99_MS:.0f} ms: "
        + ("[green]PASS[/]" if ok else "[red]MISS[/]")
    )
    return 0 if ok else 1
