"""``lelsonar bench estimators --provisional``: the CPU of each provisional refit by the steps a scan holds.

Each preset's scan (seeded) goes through a :class:`~lelsonar.reconstruct.stream.service.ReconstructionService`
with provisional estimates on, its samples stamped 20 ms apart (50 Hz), one ``handle`` at a time.  The
thread CPU of every ``handle`` is measured; the calls that published a provisional estimate are the
refits.  The **floor** is the median CPU of the same run's ``handle`` calls that published nothing
(ingesting a sample: what every call pays), so ``refit − floor`` is the provisional estimate's own
cost.  Per quarter of the schedule the refit was made in: the median refit µs and its ratio to the
floor.  Per scan: the refits, how plane b's were made (O(new points) updates, refreshes on doubling,
exact fits — and of these, the untrusted ones, whose next try waits for more echoes of the beams
facing the wall), the CPU of the refits in which an exact fit of plane a (at the corner's confirmation)
or b ran, and the share of all the scan's refit CPU spent in those.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass, field

import numpy as np

from lelsonar import codec
from lelsonar.reconstruct.estimate import wire
from lelsonar.reconstruct.stream.config import ReconstructConfig
from lelsonar.reconstruct.stream.service import ReconstructionService
from lelsonar.sim import preset_names
from lelsonar.tools.bench import machine
from lelsonar.tools.bench_recording import scan_messages

__all__ = ["add_provisional_arguments", "run_provisional"]

STEP_NS = 20_000_000  # 50 Hz
QUARTERS = 4


def add_provisional_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``--provisional`` flags of ``lelsonar bench estimators``."""
    parser.add_argument(
        "--provisional",
        action="store_true",
        help="instead: the CPU of each provisional refit by the steps the scan holds, per preset",
    )
    parser.add_argument("--provisional-seeds", type=int, default=5, help="seeds per preset with --provisional")


@dataclass
class _Scan:
    refits: list[tuple[float, float]] = field(default_factory=list)  # (share of the schedule held, CPU µs)
    idle_us: list[float] = field(default_factory=list)  # CPU µs of handle calls that published nothing
    exact_us: list[float] = field(default_factory=list)  # CPU µs of the refits in which an exact fit (a or b) ran
    updates: int = 0
    refreshes: int = 0
    exact: int = 0
    untrusted: int = 0


class _Counts:
    """An observer keeping plane b's exact-fit count after each estimate."""

    def __init__(self) -> None:
        self.exact = 0
        self.stats: object = None

    def scan_started(self, scan: object) -> None:
        self.exact = 0

    def step(self, *args: object) -> None:
        pass

    def event(self, *args: object) -> None:
        pass

    def estimate(self, scan: object, message: object, results: object, partial: object) -> None:
        a, b = getattr(partial, "inc_a", None), getattr(partial, "inc_b", None)
        self.exact = (a.stats.exact if a is not None else 0) + (b.stats.exact if b is not None else 0)
        if b is not None:
            self.stats = b.stats


def _one(preset_name: str, seed: int) -> _Scan:
    messages = scan_messages(preset_name, None, seed)
    t0 = 1_700_000_000_000_000_000
    for m in messages:
        if isinstance(m, codec.Sample):
            m.acquisition_time_ns = t0 + m.step * STEP_NS
    steps = len(messages) - 2
    counts = _Counts()
    service = ReconstructionService(ReconstructConfig(), observer=counts)
    out = _Scan()
    for m in messages[:-1]:  # (not the ScanEnd: the final is not a provisional refit)
        payload = m.SerializeToString()
        name = m.DESCRIPTOR.full_name
        before = counts.exact
        c0 = time.thread_time_ns()
        published = service.handle(name, payload)
        us = (time.thread_time_ns() - c0) / 1e3
        if not isinstance(m, codec.Sample):
            continue
        prov = [e for e in published if wire.status_name(e) == "provisional"]
        if prov:
            out.refits.append(((max(e.last_step for e in prov) + 1) / steps, us / len(prov)))
            if counts.exact > before:
                out.exact_us.append(us)
        else:
            out.idle_us.append(us)
    st = counts.stats
    if st is not None:
        out.updates, out.refreshes = st.updates, st.refreshes  # type: ignore[attr-defined]
        out.exact, out.untrusted = st.exact, st.untrusted  # type: ignore[attr-defined]
    return out


def run_provisional(args: argparse.Namespace) -> int:
    """Print the table (see the module's docstring)."""
    presets = [s for s in args.scenes if s in preset_names()] or list(preset_names())
    seeds = range(args.first_seed, args.first_seed + args.provisional_seeds)
    _one(presets[0], seeds[0])  # warm-up: the kernels' first calls
    print(f"provisional refits, thread CPU per handle call ({machine()}); 50 Hz, seeds {seeds.start}..{seeds.stop - 1}")
    print(
        "floor: median CPU of the same run's handle calls that published nothing (ingesting a sample); "
        "refit µs (×floor) by the quarter of the schedule held"
    )
    head = f"{'preset':12s} {'floor µs':>8s} " + " ".join(f"{f'q{q + 1}':>14s}" for q in range(QUARTERS))
    head += f" {'refits':>6s} {'updates':>7s} {'refresh':>7s} {'exact':>5s} {'untrusted':>9s} {'exact ms':>9s}"
    head += f" {'scan ms':>8s} {'in exact':>8s}"
    print(head)
    for name in presets:
        scans = [_one(name, s) for s in seeds]
        floor = float(np.median([u for s in scans for u in s.idle_us]))
        cells = []
        for q in range(QUARTERS):
            us = [u for s in scans for share, u in s.refits if q / QUARTERS < share <= (q + 1) / QUARTERS]
            cells.append(f"{np.median(us):7.0f} ({np.median(us) / floor:4.1f}×)" if us else f"{'—':>14s}")
        exact_ms = [u / 1e3 for s in scans for u in s.exact_us]
        total_ms = [sum(u for _, u in s.refits) / 1e3 for s in scans]
        print(
            f"{name:12s} {floor:8.0f} "
            + " ".join(f"{c:>14s}" for c in cells)
            + f" {np.mean([len(s.refits) for s in scans]):6.1f} {np.mean([s.updates for s in scans]):7.1f}"
            + f" {np.mean([s.refreshes for s in scans]):7.1f} {np.mean([s.exact for s in scans]):5.1f}"
            + f" {np.mean([s.untrusted for s in scans]):9.1f}"
            + (f" {np.median(exact_ms):9.1f}" if exact_ms else f" {'—':>9s}")
            + f" {np.mean(total_ms):8.1f} {sum(sum(s.exact_us) for s in scans) / 1e3 / sum(total_ms):8.0%}"
        )
    print(
        "(per scan, means over the seeds: refits; plane b's updates, refreshes, exact and untrusted exact fits; "
        "exact ms: median CPU of a refit in which an exact fit of plane a or b ran; scan ms: all the scan's "
        "refits; in exact: their share in those refits)"
    )
    return 0
