"""The words of a verdict: why a plane is degraded by what the stream saw, and step lists as ranges."""

from __future__ import annotations

from collections.abc import Iterable

from lelsonar import codec
from lelsonar.reconstruct.stream.assembly import ScanAssembly


def partial_sweep_reason(end: codec.ScanEnd, planned: int) -> str:
    """A plane's reason when its sweep stopped early: how far it went, and why it stopped."""
    why = f" ({end.reason})" if end.reason else ""
    return (
        f"partial sweep: the scan was aborted after {end.samples_sent} of {planned} steps{why}; "
        "a wall may extend beyond what was swept"
    )


def conflict_reason(scan: ScanAssembly, live: bool) -> str:
    """A plane's reason when steps of its scan came twice with different content."""
    if not scan.unsettled:
        kept = f"the acquirer's log settled them ({scan.replaced} held copies replaced by the log's)"
    elif live:
        kept = f"the acquirer's log did not settle steps {ranges_text(sorted(scan.unsettled))}: the first copy was used"
    else:
        kept = (
            "without the acquirer's log (a replay, or recovery off) nothing can tell which is right: "
            "the first copy was used"
        )
    copies = "1 copy of a held step" if scan.conflicts == 1 else f"{scan.conflicts} copies of held steps"
    return f"{copies} differed from the one held (a forged or replayed step?); {kept}"


def ranges_text(steps: Iterable) -> str:
    """``3-7, 12, 40-41`` for a sorted array of steps (at most 20 runs shown)."""
    runs: list[list[int]] = []
    for s in (int(x) for x in steps):
        if runs and s == runs[-1][1] + 1:
            runs[-1][1] = s
        else:
            runs.append([s, s])
    text = ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in runs[:20])
    return text + (f", … ({len(runs) - 20} more runs)" if len(runs) > 20 else "")
