"""The reconstruction of record: what a scan's estimate is, wherever it is computed.

:func:`reconstruct_scan` is the one function that turns a scan (:class:`ScanInput`) into the estimate
that is published, recorded, replayed, reviewed, exported and benchmarked (:class:`ScanEstimate`).
The live service calls it for every provisional and terminal estimate, a replay of the log calls it
through the same service (so a live final equals the replay's), and the benches call it on simulated
scans.  It does not read a scan assembly: :mod:`lelsonar.reconstruct.stream.scan_input` turns one into
a :class:`ScanInput`, which is where the writer's ranges are repaired.

Final (``options.provisional`` False), from scratch, on the whole scan:

1. the method of record and each compared method run on it
   (:func:`lelsonar.reconstruct.estimate.pipeline.reconstruct`: the critical step from ``R``,
   eq. 10-12, the split, the corrected points, eq. 9, and each plane's own verdict);
2. where echoes after the board's noise triggers were recovered, the method of record runs once more
   on the board's own readings, and a plane the recovered echoes turn away from that fit is unreliable;
3. the verdict (:func:`~lelsonar.reconstruct.estimate.quality.published_verdicts`): the sweep's own
   evidence on the planes of record (:func:`~lelsonar.reconstruct.estimate.surface_check.surface_finding`:
   echoes as weak as a diffraction that the sweep's surfaces hold as an edge, ranges curved along the capsule
   stack, or echoes whose region is not centred on the plane's foot are no wall's), the scan's writer
   findings on every plane, the recovered echoes' check on the planes of record, and each compared plane
   cross-checked against the plane of record of its wall;
4. every surface of the sweep, beside the L's planes: the planes, concave corners and convex edges of
   its regions of constant depth (:func:`~lelsonar.reconstruct.estimate.surfaces.extract_surfaces`, on
   the same repaired ranges of record and their echoes' amplitudes), the writer findings on each
   surface's verdict too, and a surface next to steps the scan is missing degraded.

The provisional variant is documented on :func:`reconstruct_scan`.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from types import MappingProxyType
from typing import overload

import numpy as np

from lelsonar.errors import ConfigError
from lelsonar.geometry import ArrayGeometry
from lelsonar.reconstruct.estimate import fit as F
from lelsonar.reconstruct.estimate.correct import AXIS_Y, AXIS_Z
from lelsonar.reconstruct.estimate.incremental import ExactFit, IncrementalPlane
from lelsonar.reconstruct.estimate.options import FitOptions
from lelsonar.reconstruct.estimate.pipeline import DEFAULT_METHOD, METHODS, corner_edge, reconstruct
from lelsonar.reconstruct.estimate.quality import DEGRADED, add_findings, published_verdicts
from lelsonar.reconstruct.estimate.results import (
    EdgeLine,
    FailureReason,
    FitFailure,
    PlaneFit,
    PlaneResult,
    ScanReconstruction,
)
from lelsonar.reconstruct.estimate.split import critical_step
from lelsonar.reconstruct.estimate.surface_check import surface_finding
from lelsonar.reconstruct.estimate.surfaces import SurfaceSet, extract_surfaces
from lelsonar.signal.energy import EnergyModel

__all__ = [
    "ScanInput",
    "RecordOptions",
    "ProvisionalState",
    "ScanEstimate",
    "reconstruct_scan",
    "provisional_method",
    "with_findings",
]

#: A writer finding: the verdict it imposes on every plane (None: named, no plane suffers) and its text.
Finding = tuple[str | None, str]


@dataclass(frozen=True, eq=False)
class ScanInput:
    """One scan as the reconstruction of record reads it: the received steps, in schedule order.

    Parameters
    ----------
    geometry : ArrayGeometry
    energy_model : EnergyModel
        ``E0(d)`` of eq. (12).
    steps : (n,) int array
        The schedule index of each row (increasing).
    gamma : (n,) array
        Rotation of each row, rad.
    distance : (n, n_capsules) array
        The ranges of record, m (NaN: no echo), repaired where the writer needed it.
    sensor_energy : (n, n_capsules) or (n,) array, optional
        ``E_i^γ`` (eq. 10) or the step totals ``E^γ`` (eq. 11), V²·s; a final needs it.
    echo_amplitude : (n, n_capsules) array, optional
        Peak amplitude of each capsule's first echo alone, V (NaN: none), matching ``distance``.
    own_distance, own_amplitude : arrays like ``distance``, optional
        The board's own readings, its noise triggers left out, where echoes after those triggers
        were recovered into ``distance``: the recovered echoes' check refits on them.  None: nothing
        was recovered.
    writer_problems : tuple of (level or None, text)
        What the scan's writer left unset or stated otherwise than the contract; a level is the
        verdict the problem imposes on every plane.
    ratio : (n,) array, optional
        ``R`` of each row (eq. 12) as the stream keeps it; the provisional variant looks for the
        corner's peak in it.
    n_schedule : int
        Steps of the scan's schedule (0: ``steps[-1] + 1``).
    newest_ns : int
        Acquisition time of the newest step, ns (the provisional rate limit runs in scan time).
    """

    geometry: ArrayGeometry
    energy_model: EnergyModel
    steps: np.ndarray
    gamma: np.ndarray
    distance: np.ndarray
    sensor_energy: np.ndarray | None = None
    echo_amplitude: np.ndarray | None = None
    own_distance: np.ndarray | None = None
    own_amplitude: np.ndarray | None = None
    writer_problems: tuple[Finding, ...] = ()
    ratio: np.ndarray | None = None
    n_schedule: int = 0
    newest_ns: int = 0

    def __post_init__(self) -> None:
        rows = {len(self.steps), len(self.gamma), len(self.distance)}
        if len(rows) != 1:
            raise ConfigError(
                f"steps, gamma and distance must have one row per step, got {len(self.steps)}, "
                f"{len(self.gamma)} and {len(self.distance)}"
            )

    @classmethod
    def of_scan(
        cls,
        gamma: np.ndarray,
        distance: np.ndarray,
        sensor_energy: np.ndarray,
        geometry: ArrayGeometry,
        energy_model: EnergyModel,
        *,
        echo_amplitude: np.ndarray | None = None,
    ) -> ScanInput:
        """A whole scan given as arrays (every step received, no writer to repair): a simulated one."""
        g = np.asarray(gamma)
        return cls(
            geometry,
            energy_model,
            np.arange(g.shape[0]),
            g,
            distance,
            sensor_energy=sensor_energy,
            echo_amplitude=echo_amplitude,
        )


@dataclass(frozen=True)
class RecordOptions:
    """How a scan is reconstructed.

    Parameters
    ----------
    method : str
        The estimator of record (a key of ``pipeline.METHODS``).
    compare_methods : tuple of str
        Also run on a final, published next to ``method`` and cross-checked against it.
    fit : FitOptions
    provisional : bool
        The cheaper variant of :func:`reconstruct_scan` for a scan still arriving.
    confirm_steps : int
        Provisional: steps that must follow the R peak before the corner is trusted.
    confirm_ratio : float
        Provisional: the peak must exceed this multiple of the median R so far.
    provisional_period : float
        Provisional: s of scan time between two estimates of one scan (0: no limit).
    """

    method: str = DEFAULT_METHOD
    compare_methods: tuple[str, ...] = ()
    fit: FitOptions = field(default_factory=FitOptions)
    provisional: bool = False
    confirm_steps: int = 6
    confirm_ratio: float = 1.5
    provisional_period: float = 0.08

    def __post_init__(self) -> None:
        for name in (self.method, *self.compare_methods):
            if name not in METHODS:
                raise ConfigError(f"unknown method {name!r}; choose from {', '.join(sorted(METHODS))}")


_FINAL = RecordOptions()


def provisional_method(method: str) -> str:
    """The method of the provisional refits, which fit one half at a time: ``method``, or ``"adaptive"``
    when that is a scan-level method (``"corner"``), which runs on the whole scan at the end."""
    return method if METHODS[method].fit_plane else "adaptive"


@dataclass
class ProvisionalState:
    """What the provisional variant keeps between the estimates of one scan in progress."""

    critical: int | None = None  # confirmed critical step (schedule index)
    data_a: F.PlaneData | None = None  # the points behind plane_a / plane_b
    data_b: F.PlaneData | None = None
    plane_a: PlaneResult | None = None
    plane_b: PlaneResult | None = None
    #: Steps received at the last refit (before the corner: the last look for it).
    steps_at_fit: int = 0
    #: acquisition_time_ns of the newest step at the last provisional estimate (the per-scan rate limit).
    provisional_ns: int = 0
    #: The provisional planes, re-estimated in O(new points) (:mod:`lelsonar.reconstruct.estimate.incremental`).
    inc_a: IncrementalPlane | None = None
    inc_b: IncrementalPlane | None = None

    @property
    def fits_wanted(self) -> bool:
        """An exact fit of a plane is due and waits for a call without ``fits_wait`` (or to be handed out)."""
        return any(inc is not None and inc.fit_wanted for inc in (self.inc_a, self.inc_b))

    def take_fits(self) -> list[tuple[IncrementalPlane, ExactFit]]:
        """Hand out the exact fits due (:meth:`IncrementalPlane.take_fit`), to run elsewhere
        (:func:`~lelsonar.reconstruct.estimate.incremental.exact_fit`); :meth:`fitted` takes each result.
        Meanwhile each plane keeps its estimate, as with ``fits_wait`` (none is given while plane a's first fit
        is away)."""
        return [(inc, inc.take_fit()) for inc in (self.inc_a, self.inc_b) if inc is not None and inc.fit_wanted]

    def fitted(self, inc: IncrementalPlane, fit: PlaneResult) -> bool:
        """Take the result of ``inc``'s exact fit handed out by :meth:`take_fits`: the plane's estimate from
        now on (the next estimate of the scan has it).  False if ``inc`` is not one of this scan's planes."""
        if inc is self.inc_a:
            self.plane_a, self.data_a = inc.fitted(fit), inc.last_data
        elif inc is self.inc_b:
            self.plane_b, self.data_b = inc.fitted(fit), inc.last_data
        else:
            return False
        return True


@dataclass(frozen=True, eq=False)
class ScanEstimate:
    """The estimate of record of one scan (the wire message is built from it by
    :func:`lelsonar.reconstruct.estimate.wire.estimate_message`).

    Parameters
    ----------
    method : str
        The method of record.
    compare_methods : tuple of str
    provisional : bool
    last_step : int
        The highest schedule step used (0 for none).
    samples_used : int
        Steps in the estimate.
    critical_step : int or None
        Schedule index of the critical step.
    critical_angle : float
        γ there, rad (0 without one).
    planes : tuple of PlaneFit or FitFailure
        The planes of record, then each compared method's, their verdicts applied.
    edge : EdgeLine or FitFailure
    timings : (segmentation, fit, total), s
        Of the method of record; on a final, ``total`` also holds the extraction of the surfaces.
    results : mapping of method → ScanReconstruction
        Each method's own reconstruction, before the scan's verdict (empty for a provisional).
    notes : tuple of str
        What the scan's writer left unset or stated otherwise than the contract.
    failures : tuple of str
        Failure lines beyond the planes' and the edge's (the notes, when the method of record has no
        plane: the first thing to fix).
    surfaces : SurfaceSet or None
        Every surface, corner and edge of the sweep, on a final only.  A provisional estimate says
        nothing of surfaces (None): the regions of constant depth are only known once the sweep has
        passed them, and a consumer that acts on them waits for the terminal estimate.
    """

    method: str
    compare_methods: tuple[str, ...]
    provisional: bool
    last_step: int
    samples_used: int
    critical_step: int | None
    critical_angle: float
    planes: tuple[PlaneResult, ...]
    edge: EdgeLine | FitFailure
    timings: tuple[float, float, float]
    results: Mapping[str, ScanReconstruction] = field(default_factory=lambda: MappingProxyType({}))
    notes: tuple[str, ...] = ()
    failures: tuple[str, ...] = ()
    surfaces: SurfaceSet | None = None

    def planes_of(self, method: str) -> tuple[PlaneResult, ...]:
        """The published planes of ``method`` (the method of record or a compared method), verdicts
        applied: :attr:`planes` holds each method's two in turn."""
        order = (self.method, *self.compare_methods)
        if method not in order:
            raise ConfigError(f"{method!r} is neither the method of record nor a compared method of this estimate")
        n = len(self.planes) // len(order)
        i = order.index(method)
        return self.planes[i * n : (i + 1) * n]

    def as_published(self) -> dict[str, ScanReconstruction]:
        """Each method's reconstruction with its planes as published (verdicts applied), for what draws or
        exports them beside the message: the points each plane was fitted on come with it."""
        out = {}
        for method, rec in self.results.items():
            a, b = self.planes_of(method)
            out[method] = replace(rec, plane_a=a, plane_b=b)
        return out


@overload
def reconstruct_scan(scan: ScanInput, options: RecordOptions = ..., state: None = None) -> ScanEstimate: ...


@overload
def reconstruct_scan(
    scan: ScanInput, options: RecordOptions, state: ProvisionalState, *, fits_wait: bool = False
) -> ScanEstimate | None: ...


def reconstruct_scan(
    scan: ScanInput, options: RecordOptions = _FINAL, state: ProvisionalState | None = None, *, fits_wait: bool = False
) -> ScanEstimate | None:
    """The estimate of record of ``scan`` (paper §4-5); see the module's docstring for the final.

    The final always returns an estimate (failures are typed in it); the provisional variant returns None
    while it has none to give.

    **Provisional** (``options.provisional``, a scan still arriving; ``state`` carries what the
    previous calls of the same scan left) is the same estimate made cheaper.  It:

    - confirms the corner first: the critical step (the rule of the final, on the stream's ``R``) only
      once ``confirm_steps`` steps follow the peak and it exceeds ``confirm_ratio`` × the median R;
      before that, and within ``provisional_period`` of scan time of the last estimate, it returns
      None (no estimate);
    - fits each half on its own with :func:`provisional_method` (a scan-level method of record such as
      ``"corner"`` runs only on the whole scan), warm-started and in O(new points)
      (:class:`~lelsonar.reconstruct.estimate.incremental.IncrementalPlane`), not from scratch;
    - skips the compared methods and their cross-checks, the recovered echoes' check and the writer's
      findings, and reads the ranges as received (``scan`` is not repaired);
    - with ``fits_wait`` (the stream has samples waiting), runs no exact fit: a plane whose exact fit is due
      keeps its last estimate (:attr:`ProvisionalState.fits_wanted`), and none is given while plane a's
      first fit waits; the next call without ``fits_wait`` runs them on every step so far, first of all.

    Why skipping is safe: a provisional estimate is never a scan's answer.  It says PROVISIONAL, and
    every scan ends in exactly one terminal estimate (final, incomplete or final timeout) made from
    scratch by the final branch, on the whole repaired scan with every check; nothing of a provisional
    estimate (state, warm starts, verdicts) enters it, so a final is the same with or without them (a
    replay runs none).  What a provisional verdict does not promise: it is the plane's own on the steps
    so far, without the writer's findings and the recovered echoes' check, which only lower verdicts
    (a provisional "good" can end "degraded" or "unreliable").  A consumer that acts on a verdict waits
    for the terminal estimate.

    Parameters
    ----------
    scan : ScanInput
    options : RecordOptions
    state : ProvisionalState
        Required with ``options.provisional`` (updated in place); unused otherwise.
    fits_wait : bool
        Provisional: the exact fits due wait for a call without it (see above).

    Raises
    ------
    ConfigError
        Malformed inputs, or a provisional call without a state.
    """
    if options.provisional:
        if state is None:
            raise ConfigError("a provisional reconstruction needs the scan's ProvisionalState")
        return _provisional(scan, options, state, fits_wait)
    return _final(scan, options)


def _final(scan: ScanInput, options: RecordOptions) -> ScanEstimate:
    if scan.sensor_energy is None:
        raise ConfigError("a final reconstruction needs the scan's sensor_energy")
    steps = np.asarray(scan.steps)
    results: dict[str, ScanReconstruction] = {}
    for method in (options.method, *options.compare_methods):
        # From scratch, no warm start: the final estimate depends only on the data.
        results[method] = reconstruct(
            scan.gamma,
            scan.distance,
            scan.sensor_energy,
            scan.geometry,
            scan.energy_model,
            method,
            options=options.fit,
            echo_amplitude=scan.echo_amplitude,
        )
    main = results[options.method]
    without = None
    if scan.own_distance is not None:
        # Echoes recovered after noise triggers: the same walls fitted on the board's own readings alone must
        # agree within their σ (one more fit, only on such scans).
        without = {
            pl.label: pl
            for pl in reconstruct(
                scan.gamma,
                scan.own_distance,
                scan.sensor_energy,
                scan.geometry,
                scan.energy_model,
                options.method,
                options=options.fit,
                echo_amplitude=scan.own_amplitude,
            ).planes
        }
    findings = tuple((level, text) for level, text in scan.writer_problems if level is not None)
    t0 = time.perf_counter()
    extracted = extract_surfaces(scan.gamma, scan.distance, scan.geometry, amplitude=scan.echo_amplitude)
    surfaces = _unobserved(extracted, steps, max(scan.n_schedule, int(steps[-1]) + 1 if len(steps) else 0))
    extract_s = time.perf_counter() - t0
    # Each L plane against the surface of its own echoes, whose bearing is the beam pattern's, and against an
    # edge's diffraction (before the compared methods are checked against the planes of record).
    record = tuple(
        add_findings(
            pl,
            surface_finding(
                pl, data, surfaces, gamma=scan.gamma, distance=scan.distance, amplitude=scan.echo_amplitude
            ),
        )
        for pl, data in zip(main.planes, (main.data_a, main.data_b), strict=True)
    )
    compared = tuple((method, results[method].planes) for method in options.compare_methods)
    planes = published_verdicts(record, compared, findings=findings, without=without)
    notes = tuple(text for _, text in scan.writer_problems)
    crit = int(steps[main.critical_step]) if main.critical_step is not None else None
    t = main.timings
    return ScanEstimate(
        method=options.method,
        compare_methods=options.compare_methods,
        provisional=False,
        last_step=int(steps[-1]) if len(steps) else 0,
        samples_used=len(steps),
        critical_step=crit,
        critical_angle=main.critical_angle if crit is not None else 0.0,
        planes=planes,
        edge=main.edge,
        timings=(t.segmentation, t.fit, t.total + extract_s),  # the total with the surfaces' extraction
        results=MappingProxyType(results),
        notes=notes,
        failures=notes if not all(isinstance(pl, PlaneFit) for pl in main.planes) else (),
        surfaces=_surface_findings(surfaces, findings),
    )


def with_findings(estimate: ScanEstimate, findings: tuple[tuple[str, str], ...]) -> ScanEstimate:
    """``estimate`` with ``findings`` (verdict level, text) on every plane and every surface: what the
    stream knows of a scan beyond its data (a sweep stopped early, copies that conflicted)."""
    if not findings:
        return estimate
    return replace(
        estimate,
        planes=tuple(add_findings(pl, findings) for pl in estimate.planes),
        surfaces=_surface_findings(estimate.surfaces, findings),
    )


def _surface_findings(surfaces: SurfaceSet | None, findings: tuple[tuple[str, str], ...]) -> SurfaceSet | None:
    """The writer's or the stream's findings on each surface's verdict, as on the planes of record."""
    if surfaces is None or not findings:
        return surfaces
    out = []
    for s in surfaces.surfaces:
        plane = add_findings(s.plane, findings)
        out.append(replace(s, plane=plane) if isinstance(plane, PlaneFit) else s)
    return replace(surfaces, surfaces=tuple(out))


def _unobserved(surfaces: SurfaceSet, steps: np.ndarray, n_schedule: int) -> SurfaceSet:
    """Each surface whose region of constant depth borders or spans steps the scan is missing, degraded and
    said why.

    The extractor reads the received rows in order: it cannot tell a missing step from a step without an
    echo, so a region that ends at a gap may really go on (its centre, hence its bearing, and its extent
    are then not the wall's) and one across a gap joins steps that were never seen together.
    """
    if not surfaces.surfaces or len(steps) == n_schedule:
        return surfaces
    missing = np.ones(n_schedule, dtype=bool)
    missing[steps] = False
    # Each run of missing steps, as (first, last).
    edges = np.diff(np.concatenate(([0], missing.astype(np.int8), [0])))
    runs = list(zip(np.flatnonzero(edges == 1).tolist(), (np.flatnonzero(edges == -1) - 1).tolist()))
    out = []
    for s in surfaces.surfaces:
        first, last = int(steps[int(s.steps.min())]), int(steps[int(s.steps.max())])
        near = [(a, b) for a, b in runs if a <= last + 1 and b >= first - 1]
        if near:
            n = sum(b - a + 1 for a, b in near)
            listed = ", ".join(str(a) if a == b else f"{a}-{b}" for a, b in near)
            text = (
                f"step{'s' if n > 1 else ''} {listed} of the scan {'are' if n > 1 else 'is'} missing at or inside "
                "its region of constant depth: its bearing and extent may not be the wall's"
            )
            plane = add_findings(s.plane, ((DEGRADED, text),))
            s = replace(s, plane=plane) if isinstance(plane, PlaneFit) else s
        out.append(s)
    return replace(surfaces, surfaces=tuple(out))


def _provisional(scan: ScanInput, options: RecordOptions, p: ProvisionalState, fits_wait: bool) -> ScanEstimate | None:
    """Confirm the corner, then (re)fit plane b on the steps new since the last estimate."""
    steps = np.asarray(scan.steps)
    if not len(steps):
        return None
    method = provisional_method(options.method)
    n_schedule = max(scan.n_schedule, int(steps[-1]) + 1)
    # The incremental planes index their points by schedule step.
    gamma = np.full(n_schedule, np.nan)
    gamma[steps] = scan.gamma
    distance = np.full((n_schedule, scan.geometry.n_capsules), np.nan)
    distance[steps] = scan.distance
    if p.critical is None:
        if scan.ratio is None:
            raise ConfigError("a provisional reconstruction needs the stream's ratio R")
        ratio = np.asarray(scan.ratio)
        p.steps_at_fit = len(steps)  # the corner's peak is looked for every refit_every steps (O(steps) each)
        peak = critical_step(ratio, options.fit.critical_peak_fraction)  # the rule reconstruct() uses
        if peak is None or len(steps) - 1 - peak < options.confirm_steps:
            return None
        if ratio[peak] < options.confirm_ratio * float(np.median(ratio)):
            return None
        p.critical = int(steps[peak])
        p.inc_a = IncrementalPlane(scan.geometry, "a", AXIS_Y, method, options.fit, n_schedule)
        p.plane_a = p.inc_a.update(gamma, distance, steps[steps < p.critical], exact=not fits_wait)
        p.data_a = p.inc_a.last_data
    elif p.inc_a is not None and p.inc_a.fit_wanted and not fits_wait:
        p.plane_a = p.inc_a.update(gamma, distance, steps[:0])  # its fit waited (plane a takes no later steps)
        p.data_a = p.inc_a.last_data
    if p.plane_a is None:
        return None  # plane a's first fit waits: nothing to give yet
    t0 = time.perf_counter()
    plane_b = None  # A fit that waited runs first, whatever the rate limit: the next estimate has it.
    if p.inc_b is not None and p.inc_b.fit_wanted and not fits_wait:
        p.plane_b = plane_b = _plane_b(p, gamma, distance, steps, False)
    if 0 < scan.newest_ns - p.provisional_ns < options.provisional_period * 1e9:
        return None  # the per-scan rate limit (scan time)
    p.provisional_ns = max(p.provisional_ns, scan.newest_ns)
    if p.inc_b is None:
        p.inc_b = IncrementalPlane(scan.geometry, "b", AXIS_Z, method, options.fit, n_schedule)
    if plane_b is None:
        plane_b = _plane_b(p, gamma, distance, steps, fits_wait)
    why = "provisional: its first fit waits for the samples the stream holds"
    p.plane_b = plane_b if plane_b is not None else FitFailure(FailureReason.DEGENERATE_GEOMETRY, why, "b", p.inc_b.n)
    p.steps_at_fit = len(steps)
    p.plane_a, p.plane_b = published_verdicts((p.plane_a, p.plane_b), (), gamma=np.asarray(scan.gamma))
    fit_s = time.perf_counter() - t0
    return ScanEstimate(
        method=method,
        compare_methods=(),
        provisional=True,
        last_step=int(steps[-1]),
        samples_used=len(steps),
        critical_step=p.critical,
        critical_angle=float(gamma[p.critical]),
        planes=(p.plane_a, p.plane_b),
        edge=corner_edge(p.plane_a, p.plane_b),
        timings=(0.0, fit_s, fit_s),
    )


def _plane_b(
    p: ProvisionalState, gamma: np.ndarray, distance: np.ndarray, steps: np.ndarray, fits_wait: bool
) -> PlaneResult | None:
    """Plane b with the received steps after the corner it has not taken yet, in O(new points) unless the trust
    check fails (an exact fit then, or with ``fits_wait`` the last estimate while it waits)."""
    assert p.inc_b is not None and p.critical is not None  # (made at the corner's confirmation)
    new = steps[~p.inc_b.included[steps]]
    plane = p.inc_b.update(gamma, distance, new[new > p.critical], exact=not fits_wait)
    p.data_b = p.inc_b.last_data
    return plane
