"""The live reconstruction: incremental estimates per scan, from any source.

Everything enters through :meth:`ReconstructionService.handle` as (type name,
payload bytes), whether it came from Zenoh or from an MCAP file, so live and
replayed data take the same path and give the same final estimate.

Per scan (paper §4–5, made incremental):

1. after each sample, E^γ, E0(d_m) and R are updated;
2. once the critical peak is *confirmed* — R at its maximum is well above the
   scan's typical R and enough steps have followed it — plane a (the subset
   before the peak) is estimated;
3. as later samples arrive, plane b is re-estimated every ``refit_every``
   steps, warm-started from its previous estimate — but while a backlog waits
   (``handle(..., busy=True)``) only every ``max_provisional_delay``, so a
   burst costs one refit, not one per sample;
4. at ``ScanEnd`` (once its samples are in) or after ``scan_timeout`` of
   silence, the whole scan is reconstructed from scratch with the chosen
   method and the comparison methods, and published as final.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from lelsonar import codec
from lelsonar.errors import ConfigError
from lelsonar.reconstruct import fit as F
from lelsonar.reconstruct import wire
from lelsonar.reconstruct.assembly import ScanAssembly, StepView
from lelsonar.reconstruct.correct import AXIS_Y, AXIS_Z
from lelsonar.reconstruct.ingest import Accepted, Ingest, Rejected, ScanKey
from lelsonar.reconstruct.pipeline import DEFAULT_METHOD, METHODS, FitOptions, corner_edge, fit_plane, reconstruct
from lelsonar.reconstruct.quality import cross_check
from lelsonar.reconstruct.results import FitFailure, PlaneFit, PlaneResult, ScanReconstruction
from lelsonar.reconstruct.split import critical_step

_log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ReconstructConfig:
    """How the service estimates.

    Parameters
    ----------
    method : str
        The estimator of record (a key of ``pipeline.METHODS``).
    compare_methods : tuple of str
        Also run at the end of each scan, published next to ``method``.
    refit_every : int
        Steps between provisional re-estimates of plane b.
    confirm_steps : int
        Steps that must follow the R peak before it is trusted.
    confirm_ratio : float
        The peak must exceed this multiple of the median R so far.
    provisional : bool
        Publish provisional estimates while a scan arrives (off for a batch replay,
        whose finals do not depend on them).
    max_provisional_delay : float
        s; under a backlog, a scan still gets a provisional estimate this often.
    scan_timeout : float
        s of silence after which an open scan is finalised (marked FINAL_TIMEOUT).
    end_grace : float
        s to wait, after ScanEnd, for samples still in flight.
    limits : DecodeLimits
    """

    method: str = DEFAULT_METHOD
    compare_methods: tuple[str, ...] = ("ls",)
    refit_every: int = 4
    confirm_steps: int = 6
    confirm_ratio: float = 1.5
    provisional: bool = True
    max_provisional_delay: float = 0.25
    keep_finals: int = 1024
    scan_timeout: float = 10.0
    end_grace: float = 1.0
    limits: codec.DecodeLimits = codec.DEFAULT_LIMITS

    def __post_init__(self) -> None:
        for name in (self.method, *self.compare_methods):
            if name not in METHODS:
                raise ConfigError(f"unknown method {name!r}; choose from {', '.join(sorted(METHODS))}")
        if self.refit_every < 1 or self.confirm_steps < 1:
            raise ConfigError("refit_every and confirm_steps must be >= 1")
        if not (self.scan_timeout > 0 and self.end_grace >= 0 and self.confirm_ratio >= 1):
            raise ConfigError("scan_timeout must be > 0 s, end_grace >= 0 s and confirm_ratio >= 1")


class Observer(Protocol):
    """Receives what the service sees and decides (e.g. the Rerun logger)."""

    def scan_started(self, scan: ScanAssembly) -> None: ...

    def step(self, scan: ScanAssembly, view: StepView, energy: float, expected: float, ratio: float) -> None: ...

    def estimate(self, scan: ScanAssembly, message: codec.Reconstruction,
                 results: dict[str, ScanReconstruction] | None, partial: "Partial") -> None: ...

    def event(self, level: str, text: str, time_ns: int | None = None) -> None: ...


@dataclass
class Partial:
    """The incremental state of one scan."""

    critical: int | None = None        # confirmed critical step (schedule index)
    data_a: F.PlaneData | None = None   # the points behind plane_a / plane_b
    data_b: F.PlaneData | None = None
    plane_a: PlaneResult | None = None
    plane_b: PlaneResult | None = None
    steps_at_fit: int = 0
    estimated_at: float = 0.0
    last_activity: float = 0.0
    ended_at: float | None = None


@dataclass
class ServiceStats:
    estimates: int = 0
    finals: int = 0
    timeouts: int = 0  # rejected input is counted by error type in ingest.rejected


def _compared(plane: PlaneResult, method: str, main: ScanReconstruction) -> PlaneResult:
    """A compared method's plane, checked against the method of record's; a failure names its method.

    A compared method that fails is reported, never silently dropped; one
    that disagrees with a good plane of record is degraded (it may have
    locked onto the corner cluster, which its own residuals cannot show).
    """
    if not isinstance(plane, PlaneFit):
        return FitFailure(plane.reason, f"{method}: {plane.detail}", plane.label, plane.n_points)
    reference = main.plane_a if plane.label == "a" else main.plane_b
    return cross_check(plane, reference) if isinstance(reference, PlaneFit) else plane


class ReconstructionService:
    """Turns a stream of contract payloads into Reconstruction messages."""

    def __init__(self, config: ReconstructConfig = ReconstructConfig(), *,
                 publish: Callable[[codec.Reconstruction], None] | None = None,
                 observer: Observer | None = None, clock: Callable[[], float] = time.monotonic) -> None:
        self.config = config
        self.ingest = Ingest(limits=config.limits)
        self._publish = publish
        self._observer = observer
        self._clock = clock
        self._partials: dict[ScanKey, Partial] = {}
        self._pending_since: dict[ScanKey, float] = {}  # samples held while their ScanStart is missing
        self._options = FitOptions()
        # Provisional refits fit one half at a time; a scan-level method of record ("corner") runs at the end.
        self._plane_method = self.config.method if METHODS[self.config.method].fit_plane else "adaptive"
        #: The newest estimate per scanner (what a `get` on the planes key returns).
        self.latest: dict[str, codec.Reconstruction] = {}
        #: Final estimates, per scan, in the order they were made.
        self.finals: dict[ScanKey, codec.Reconstruction] = {}  # the newest keep_finals
        self.stats = ServiceStats()

    # --- input ---------------------------------------------------------------------------
    def handle(self, type_name: str, payload: bytes, *, busy: bool = False) -> list[codec.Reconstruction]:
        """Apply one payload; return the estimates it produced (also published).

        ``busy``: more payloads are already waiting, so a provisional refit can wait
        for them (see ``max_provisional_delay``); :meth:`tick` catches up.
        """
        out: list[codec.Reconstruction] = []
        for event in self.ingest.accept(type_name, payload):
            if isinstance(event, Rejected):
                self._event("WARNING", f"rejected input ({event.error}): {event.detail}")
                continue
            out += self._on_accepted(event, busy)
        for key in self.ingest.pending:
            self._pending_since.setdefault(key, self._clock())
        return out

    def tick(self) -> list[codec.Reconstruction]:
        """Catch up on deferred provisional estimates; finalise scans whose ScanEnd came
        (after the grace) or that went silent."""
        now = self._clock()
        out: list[codec.Reconstruction] = []
        for key, p in list(self._partials.items()):
            scan = self.ingest.scans.get(key)
            if scan is None:
                continue
            out += self._provisional(scan, p)
            if p.ended_at is not None and now - p.ended_at >= self.config.end_grace:
                out.append(self._finalise(scan, p, "final"))
            elif p.ended_at is None and now - p.last_activity >= self.config.scan_timeout:
                self._event("WARNING", f"scan {key} silent for {self.config.scan_timeout:.1f} s without a "
                                       "ScanEnd; finalising it as FINAL_TIMEOUT")
                self.stats.timeouts += 1
                out.append(self._finalise(scan, p, "final_timeout"))
        for key, since in list(self._pending_since.items()):
            if key not in self.ingest.pending:
                del self._pending_since[key]  # its ScanStart came
            elif now - since >= self.config.scan_timeout:
                # Samples whose ScanStart never came are dropped, and counted, after the same timeout.
                del self._pending_since[key]
                for rej in self.ingest.drop_pending(key):
                    self._event("WARNING", f"rejected input ({rej.error}): {rej.detail}")
        return out

    def finish(self) -> list[codec.Reconstruction]:
        """End of input (a replay reached the end of its file): finalise every open scan now."""
        out = []
        for key, p in list(self._partials.items()):
            scan = self.ingest.scans.get(key)
            if scan is not None:
                status = "final" if scan.end is not None else "final_timeout"
                if status == "final_timeout":
                    self._event("WARNING", f"scan {key} has no ScanEnd; finalised as FINAL_TIMEOUT")
                    self.stats.timeouts += 1
                out.append(self._finalise(scan, p, status))
        return out

    # --- the incremental estimate ---------------------------------------------------------
    def _on_accepted(self, event: Accepted, busy: bool) -> list[codec.Reconstruction]:
        scan = event.scan
        p = self._partials.setdefault(scan.key, Partial())
        p.last_activity = self._clock()
        if event.kind == "start":
            if self._observer:
                self._observer.scan_started(scan)
            self._event("INFO", f"scan {scan.key} started: {scan.start.steps} steps", scan.start.start_time_ns)
            return []
        if event.kind == "end":
            p.ended_at = self._clock()
            end = scan.end
            self._event("INFO", f"scan {scan.key} ended ({'complete' if end.status == 1 else 'aborted'}"
                                f"{': ' + end.reason if end.reason else ''}), {end.samples_sent} samples",
                        end.end_time_ns)
            return [self._finalise(scan, p, "final")] if scan.complete else []
        step = event.step
        if self._observer and scan.latest is not None and scan.latest.step == step:
            self._observer.step(scan, scan.latest, float(scan.step_energy[step]),
                                float(scan.expected_energy[step]), float(scan.ratio[step]))
        if p.ended_at is not None and scan.complete:
            return [self._finalise(scan, p, "final")]
        if busy and self._clock() - p.estimated_at < self.config.max_provisional_delay:
            return []  # the backlog's later samples will be in the next refit
        return self._provisional(scan, p)

    def _provisional(self, scan: ScanAssembly, p: Partial) -> list[codec.Reconstruction]:
        """Confirm the corner, then (re)fit plane b when enough new steps have come."""
        if not self.config.provisional:
            return []
        steps, _, _, ratio = scan.arrays()
        if p.critical is None:
            peak = critical_step(ratio, self._options.critical_peak_fraction)  # the rule reconstruct() uses
            if peak is None or len(steps) - 1 - peak < self.config.confirm_steps:
                return []
            if ratio[peak] < self.config.confirm_ratio * float(np.median(ratio)):
                return []
            p.critical = int(steps[peak])
            self._event("INFO", f"scan {scan.key}: critical step {p.critical} confirmed at "
                                f"γ = {np.rad2deg(scan.gamma[p.critical]):.1f}°", int(scan.time_ns[p.critical]))
            p.data_a = self._plane_data(scan, "a", p.critical)
            p.plane_a = fit_plane(p.data_a, self._plane_method, options=self._options)
        elif len(steps) - p.steps_at_fit < self.config.refit_every:
            return []
        p.estimated_at = self._clock()
        t0 = time.perf_counter()
        warm = p.plane_b.theta if isinstance(p.plane_b, PlaneFit) else None
        p.data_b = self._plane_data(scan, "b", p.critical)
        p.plane_b = fit_plane(p.data_b, self._plane_method, warm_start=warm, options=self._options)
        p.steps_at_fit = len(steps)
        fit_s = time.perf_counter() - t0
        edge = corner_edge(p.plane_a, p.plane_b)
        msg = wire.reconstruction_message(
            scan.start.scanner_id, scan.start.scan_id, status="provisional", last_step=int(steps[-1]),
            samples_used=len(steps), critical_step=p.critical, critical_angle=float(scan.gamma[p.critical]),
            planes=(p.plane_a, p.plane_b), edge=edge, timings=(0.0, fit_s, fit_s))
        if self._observer:
            self._observer.estimate(scan, msg, None, p)
        return [self._emit(msg)]

    def _plane_data(self, scan: ScanAssembly, label: str, critical: int) -> F.PlaneData:
        steps = np.flatnonzero(scan.received)
        chosen = steps[steps < critical] if label == "a" else steps[steps > critical]
        return F.plane_data(scan.geometry, scan.gamma, scan.distance, chosen, label,
                            AXIS_Y if label == "a" else AXIS_Z)

    def _finalise(self, scan: ScanAssembly, p: Partial, status: str) -> codec.Reconstruction:
        steps, gamma, distance, _ = scan.arrays()
        results: dict[str, ScanReconstruction] = {}
        for method in (self.config.method, *self.config.compare_methods):
            # From scratch, no warm start: the final estimate depends only on the data.
            results[method] = reconstruct(gamma, distance, scan.sensor_energy[steps], scan.geometry,
                                          scan.energy_model, method, options=self._options)
        main = results[self.config.method]
        crit = int(steps[main.critical_step]) if main.critical_step is not None else None
        planes: list[PlaneResult] = [main.plane_a, main.plane_b]
        for method in self.config.compare_methods:
            planes += [_compared(pl, method, main) for pl in results[method].planes]
        t = main.timings
        msg = wire.reconstruction_message(
            scan.start.scanner_id, scan.start.scan_id, status=status,
            last_step=int(steps[-1]) if len(steps) else 0, samples_used=len(steps), critical_step=crit,
            critical_angle=main.critical_angle if crit is not None else 0.0, planes=planes, edge=main.edge,
            timings=(t.segmentation, t.fit, t.total))
        self.finals[scan.key] = msg
        while len(self.finals) > self.config.keep_finals:
            self.finals.pop(next(iter(self.finals)))
        self.stats.finals += 1
        summary = "; ".join(
            f"{pl.method} {pl.label}: n=({pl.normal.x:+.3f},{pl.normal.y:+.3f},{pl.normal.z:+.3f}) "
            f"h={pl.offset * 100:.1f} cm" for pl in msg.planes if pl.method == self.config.method)
        self._event("INFO" if not msg.failures else "WARNING",
                    f"scan {scan.key} {status.replace('_', ' ')}: {summary or 'no plane'}"
                    + (f"; failures: {'; '.join(msg.failures)}" if msg.failures else ""))
        if self._observer:
            self._observer.estimate(scan, msg, results, p)
        self._emit(msg)
        # The scan is done: forget its state; a straggler is then rejected as late.
        self._partials.pop(scan.key, None)
        self.ingest.close(scan.key)
        return msg

    def _emit(self, msg: codec.Reconstruction) -> codec.Reconstruction:
        self.latest[msg.scanner_id] = msg
        self.stats.estimates += 1
        if self._publish is not None:
            self._publish(msg)
        return msg

    def _event(self, level: str, text: str, time_ns: int | None = None) -> None:
        getattr(_log, level.lower(), _log.info)(text)
        if self._observer:
            self._observer.event(level, text, time_ns)
