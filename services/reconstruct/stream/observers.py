"""Several observers on one service: the Rerun and Foxglove views side by side."""

from __future__ import annotations

from lelsonar import codec
from lelsonar.reconstruct.stream.assembly import ScanAssembly, StepView


class ObserverGroup:
    """Implements :class:`lelsonar.reconstruct.stream.service.Observer` by calling each observer in turn."""

    def __init__(self, observers) -> None:
        self.observers = list(observers)

    def scan_started(self, scan: ScanAssembly) -> None:
        for o in self.observers:
            o.scan_started(scan)

    def step(self, scan: ScanAssembly, view: StepView, energy: float, expected: float, ratio: float) -> None:
        for o in self.observers:
            o.step(scan, view, energy, expected, ratio)

    def estimate(self, scan: ScanAssembly, message: codec.Reconstruction, results, partial) -> None:
        for o in self.observers:
            o.estimate(scan, message, results, partial)

    def event(self, level: str, text: str, time_ns: int | None = None) -> None:
        for o in self.observers:
            o.event(level, text, time_ns)


def combine(*observers):
    """None, the one observer given, or a group of them (``None`` entries are skipped)."""
    present = [o for o in observers if o is not None]
    if not present:
        return None
    return present[0] if len(present) == 1 else ObserverGroup(present)
