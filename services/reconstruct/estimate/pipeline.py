"""The reconstruction pipeline and its registry of methods (paper §4–5).

``reconstruct(gamma, distance, sensor_energy, geometry, energy_model, method=...)``
runs a method on a full or partial scan and gives every plane its trust
verdict (:mod:`lelsonar.reconstruct.estimate.quality`).  Per-subset methods follow the
paper's steps:

1. energy ratio ``R`` (eq. 10–12) and the critical step (§4);
2. split into the subsets before and after it;
3. data points (eq. 9) and the reflection-direction correction (§4, Fig. 7);
4. one plane per subset with the chosen method;
5. the corner edge where the two planes meet.

Scan-level methods segment the scan themselves.

What is published, recorded and benchmarked is the reconstruction of record
(:func:`lelsonar.reconstruct.estimate.record.reconstruct_scan`), which runs
:func:`reconstruct` once per method and applies the scan's verdict.

Methods (``METHODS``, name → :class:`Method`), one module per family:

:mod:`~lelsonar.reconstruct.estimate.estimators` (one subset at a time)
    ``"ls"`` — least squares on the corrected points, eq. (15);
    ``"lel-nm"`` — the paper's LEL (§5.2), six-start Nelder-Mead;
    ``"paper"`` — ``"lel-nm"``, the 10 % pre-filter, a six-start LEL refit (§5.3);
    ``"lel"`` — fast LEL (closed-form gradient and Hessian, Newton) with the
    outlier-cluster guard; ``"lel-refit-lel"``, ``"lel-refit-ls"`` — fast LEL,
    pre-filter, LEL or LS refit; ``"constant-depth"`` — the mirror-echo model
    ``n · p_c + d = h``, no axis-aligned assumption; ``"adaptive"`` —
    ``"lel-refit-ls"``'s normal with the mirror-echo offset, or the
    constant-depth plane where a χ² test shows a tilted wall.
:mod:`~lelsonar.reconstruct.estimate.corner.method` (whole scan, on :mod:`~lelsonar.reconstruct.estimate.corner.model`)
    ``"corner"`` — both walls and the edge explain every echo jointly; each
    wall is then refined on its own echoes.
:mod:`~lelsonar.reconstruct.estimate.fcm_ransac` (whole scan)
    ``"fcm-ransac"`` — the baseline of §5.4: FCM (3 clusters) + RANSAC, seeded.

:data:`DEFAULT_METHOD` is ``"corner"``, chosen by ``lelsonar bench estimators
--families all`` (``docs/estimators.md``): the energy-split methods fail where the corner's
double-bounce echoes dominate a subset or the energy peak misses the corner
(far walls, partial sweeps); the joint model does not, and matches the
corrected-points oracle on the paper's scenes.

Warm start: ``warm_start=(θ_a, θ_b)`` (either may be None) adds the previous
estimate of each plane — e.g. from the last partial scan in the live service —
as an extra LEL start of the per-subset LEL methods.  It never replaces θ_LS,
so a stale warm start cannot make the result worse in ``H``.  ``"ls"``,
``"corner"`` and ``"fcm-ransac"`` ignore it.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from types import MappingProxyType

import numpy as np

from lelsonar.errors import ConfigError
from lelsonar.geometry import ArrayGeometry, beam_points
from lelsonar.reconstruct.estimate import estimators as E
from lelsonar.reconstruct.estimate import fit as F
from lelsonar.reconstruct.estimate.corner.method import corner_edge, fit_corner
from lelsonar.reconstruct.estimate.correct import AXIS_Y, AXIS_Z, corrected_points
from lelsonar.reconstruct.estimate.estimators import PlaneEstimator
from lelsonar.reconstruct.estimate.fcm_ransac import fit_fcm_ransac
from lelsonar.reconstruct.estimate.options import FitOptions, ScanFit
from lelsonar.reconstruct.estimate.quality import assess_plane
from lelsonar.reconstruct.estimate.results import (
    FailureReason,
    FitFailure,
    PlaneFit,
    PlaneResult,
    ScanReconstruction,
    Timings,
)
from lelsonar.reconstruct.estimate.split import critical_step, split_subsets
from lelsonar.signal.compiled import kernel
from lelsonar.signal.energy import EnergyModel, energy_ratio, median_range, total_energy

__all__ = [
    "FitOptions",
    "ScanFit",
    "Method",
    "METHODS",
    "DEFAULT_METHOD",
    "register_method",
    "fit_plane",
    "corner_edge",
    "reconstruct",
]


@dataclass(frozen=True)
class Method:
    """One entry of the registry.

    Parameters
    ----------
    name : str
    summary : str
    fit_plane : callable or None
        Fits one subset (:data:`PlaneEstimator`); the pipeline splits the scan.
    fit_scan : callable or None
        Fits the whole scan itself (``"corner"`` and ``"fcm-ransac"``, which do
        their own segmentation): ``(gamma, distance, ratio, geometry, options)
        -> (plane_a, plane_b, critical_step or None)``; a critical step
        replaces the energy peak's (None keeps it).
    """

    name: str
    summary: str
    fit_plane: PlaneEstimator | None = None
    fit_scan: Callable[..., ScanFit] | None = None

    def __post_init__(self) -> None:
        if (self.fit_plane is None) == (self.fit_scan is None):
            raise ConfigError(f"method {self.name!r} needs exactly one of fit_plane and fit_scan")


_REGISTRY: dict[str, Method] = {}
#: Read-only view of the registry: method name → :class:`Method`.
METHODS: Mapping[str, Method] = MappingProxyType(_REGISTRY)


def register_method(method: Method) -> Method:
    """Add ``method`` to :data:`METHODS` (names are unique)."""
    if method.name in _REGISTRY:
        raise ConfigError(f"method {method.name!r} is already registered")
    _REGISTRY[method.name] = method
    return method


# --------------------------------------------------------------------------- registry

register_method(Method("ls", "least squares on the corrected points (eq. 15)", fit_plane=E.fit_ls))
register_method(Method("lel-nm", "paper §5.2: six-start Nelder-Mead LEL", fit_plane=E.fit_lel_nm))
register_method(
    Method("paper", "paper §5.2-5.3: six-start Nelder-Mead LEL, 10 % pre-filter, LEL refit", fit_plane=E.fit_paper)
)
register_method(Method("lel", "fast LEL (Newton, closed-form derivatives) with the cluster guard", fit_plane=E.fit_lel))
register_method(
    Method("lel-refit-lel", "fast LEL + guard, 10 % pre-filter, fast LEL refit", fit_plane=E.fit_lel_refit_lel)
)
register_method(Method("lel-refit-ls", "fast LEL + guard, 10 % pre-filter, LS refit", fit_plane=E.fit_lel_refit_ls))
register_method(
    Method(
        "constant-depth", "mirror-echo model n·p_c + d = h: LEL, pre-filter, LS refit", fit_plane=E.fit_constant_depth
    )
)
register_method(
    Method(
        "adaptive",
        "lel-refit-ls, or the constant-depth LS fit where a χ² test shows a tilted wall",
        fit_plane=E.fit_adaptive,
    )
)
register_method(
    Method(
        "corner", "joint model of both walls and the edge over all echoes, then adaptive refits", fit_scan=fit_corner
    )
)
register_method(Method("fcm-ransac", "paper §5.4 baseline: FCM (3 clusters) + RANSAC", fit_scan=fit_fcm_ransac))

#: The method :func:`reconstruct` uses by default (chosen by the benchmark).
DEFAULT_METHOD = "corner"

#: What :func:`reconstruct` fits with when given no options (frozen: one instance serves every scan).
_DEFAULT_OPTIONS = FitOptions()


# --------------------------------------------------------------------------- public API


def fit_plane(
    data: F.PlaneData,
    method: str = DEFAULT_METHOD,
    *,
    warm_start: np.ndarray | None = None,
    options: FitOptions | None = None,
) -> PlaneResult:
    """Fit one subset with a registered plane method.

    Parameters
    ----------
    data : PlaneData
        From :func:`lelsonar.reconstruct.estimate.fit.plane_data`.
    method : str
        A key of :data:`METHODS` with a ``fit_plane``.
    warm_start : (3,) array, optional
        A previous θ for this plane (extra LEL start).
    options : FitOptions, optional
    echo_amplitude : (n_steps, n_capsules) array, optional
        Peak amplitude of each capsule's first echo alone, V (NaN: none), from
        :func:`lelsonar.signal.energy.echo_amplitude`.  ``"corner"`` takes
        each wall's direction from where its echoes are strongest.
    """
    m = _method(method)
    if m.fit_plane is None:
        raise ConfigError(f"method {method!r} fits whole scans; use reconstruct()")
    return E.run_estimator(m.fit_plane, method, data, warm_start, options or FitOptions())


def _method(name: str) -> Method:
    try:
        return METHODS[name]
    except KeyError:
        raise ConfigError(f"unknown reconstruction method {name!r}; choose one of {sorted(METHODS)}") from None


def _as_method(plane: PlaneResult, method: str) -> PlaneResult:
    """A scan-level method's plane under that method's name, whichever estimator it fell back on.

    Consumers pick the plane of record by method name; a fallback is said in the diagnostics
    (and in the verdict, which the method gives it), not by a name no one asked for.
    """
    if not isinstance(plane, PlaneFit) or plane.method == method:
        return plane
    d = plane.diagnostics
    notes = (*d.notes, f"{method}: fitted by its fallback, {plane.method}")
    return plane.replace_scalars(method=method, diagnostics=replace(d, notes=notes))


def _assessed(plane: PlaneResult, gamma: np.ndarray) -> PlaneResult:
    """The plane with its trust verdict (:mod:`lelsonar.reconstruct.estimate.quality`), unless it has one."""
    if isinstance(plane, PlaneFit) and not plane.quality:
        return assess_plane(plane, gamma)
    return plane


def _validate_inputs(
    gamma: np.ndarray, distance: np.ndarray, sensor_energy: np.ndarray, geometry: ArrayGeometry
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    g = np.asarray(gamma, dtype=np.float64).ravel()
    d = np.asarray(distance, dtype=np.float64)
    e = np.asarray(sensor_energy, dtype=np.float64)
    n = g.shape[0]
    if d.shape != (n, geometry.n_capsules):
        raise ConfigError(f"distance must have shape ({n}, {geometry.n_capsules}), got {d.shape}")
    if e.shape not in ((n, geometry.n_capsules), (n,)):
        raise ConfigError(f"sensor_energy must have shape ({n}, {geometry.n_capsules}) or ({n},), got {e.shape}")
    problem = _input_problem(g, d)
    if problem == 1:
        raise ConfigError("gamma must be finite (rad)")
    if problem == 2:
        raise ConfigError("distances must be finite and >= 0 m, or NaN for no echo")
    return g, d, e


@kernel
def _input_problem(gamma: np.ndarray, distance: np.ndarray) -> int:
    """0, or what :func:`_validate_inputs` rejects first: 1 a non-finite γ, 2 an infinite or negative range."""
    for i in range(gamma.shape[0]):
        if not np.isfinite(gamma[i]):
            return 1
    for i in range(distance.shape[0]):
        for j in range(distance.shape[1]):
            x = distance[i, j]
            if np.isinf(x) or x < 0:  # (NaN, no echo, passes)
                return 2
    return 0


def range_indicator(distance: np.ndarray) -> np.ndarray:
    """The critical step's indicator where no waveform carried energy (a writer that records ranges only).

    A mirror echo's range is the wall's perpendicular distance, the double bounce's the distance to the edge,
    which is farther than either wall's (paper §4: the outliers behind the corner).  So the median range
    ``d_m`` peaks at the corner as ``R`` does (eq. 10–12 need the waveforms); 0 for steps without an echo, as
    :func:`~lelsonar.signal.energy.energy_ratio` gives them.

    Parameters
    ----------
    distance : (n_steps, n_capsules) array
        m, NaN = no echo.
    """
    return np.nan_to_num(median_range(distance), nan=0.0)


def reconstruct(
    gamma: np.ndarray,
    distance: np.ndarray,
    sensor_energy: np.ndarray,
    geometry: ArrayGeometry,
    energy_model: EnergyModel,
    method: str = DEFAULT_METHOD,
    *,
    warm_start: tuple[np.ndarray | None, np.ndarray | None] | None = None,
    options: FitOptions | None = None,
    echo_amplitude: np.ndarray | None = None,
) -> ScanReconstruction:
    """Reconstruct the two planes of an L-shaped corner from a (partial) scan (paper §4–5).

    Parameters
    ----------
    gamma : (n_steps,) array
        Measured rotation of each step, rad.
    distance : (n_steps, n_capsules) array
        Ranges, m; NaN where a capsule got no echo.
    sensor_energy : (n_steps, n_capsules) or (n_steps,) array
        Per-capsule waveform energy ``E_i^γ`` (eq. 10), V²·s, or the step
        totals ``E^γ`` (eq. 11).
    geometry : ArrayGeometry
    energy_model : EnergyModel
        ``E0(d)`` of eq. (12).
    method : str
        A key of :data:`METHODS`; :data:`DEFAULT_METHOD` by default.
    warm_start : (θ_a, θ_b), optional
        Previous estimates (1/m), either may be None; used as extra LEL
        starts (the live service passes the last partial scan's planes).
    options : FitOptions, optional

    Returns
    -------
    ScanReconstruction
        Always returns; planes or the edge that cannot be estimated are
        :class:`FitFailure` with a reason.  Works on partial scans: with the
        corner not reached yet, the critical step is the best step so far and
        the missing subset is a ``TOO_FEW_POINTS`` failure.

    Raises
    ------
    ConfigError
        On malformed inputs (shapes, non-finite angles, negative ranges) or an
        unknown method.
    """
    t0 = time.perf_counter()
    m = _method(method)
    opts = options or _DEFAULT_OPTIONS
    g, d, e = _validate_inputs(gamma, distance, sensor_energy, geometry)
    step_energy = e if e.ndim == 1 else total_energy(e)
    ratio = energy_ratio(step_energy, d, energy_model) if g.size else np.zeros(0)
    crit = critical_step(ratio, opts.critical_peak_fraction) if g.size else None
    # (a critical step means some R > 0: only without one can no waveform have carried energy)
    if crit is None and g.size and not np.any(ratio > 0):
        ratio = range_indicator(d)
        crit = critical_step(ratio, opts.critical_peak_fraction)
    warm_a, warm_b = warm_start if warm_start is not None else (None, None)
    if crit is None:
        t1 = time.perf_counter()
        fa = FitFailure(FailureReason.TOO_FEW_POINTS, "no step with an echo yet", "a", 0)
        fb = FitFailure(FailureReason.TOO_FEW_POINTS, "no step with an echo yet", "b", 0)
        return ScanReconstruction(
            method, int(g.size), None, float("nan"), fa, fb, corner_edge(fa, fb), Timings(t1 - t0, 0.0, 0.0, t1 - t0)
        )
    if m.fit_scan is not None:
        t1 = time.perf_counter()
        ee = None if echo_amplitude is None else np.asarray(echo_amplitude, dtype=np.float64).reshape(d.shape)
        sf = m.fit_scan(g, d, ratio, geometry, opts, echo_amplitude=ee)
        pa, pb = (_assessed(_as_method(p, method), g) for p in (sf.plane_a, sf.plane_b))
        crit = crit if sf.critical_step is None else sf.critical_step
        t2 = time.perf_counter()
        ta = pa.diagnostics.time_s if isinstance(pa, PlaneFit) else 0.0
        # (the planes' names and verdicts above leave their normals, offsets and errors, all the edge uses)
        edge = corner_edge(pa, pb) if sf.edge is None else sf.edge
        return ScanReconstruction(
            method,
            int(g.size),
            crit,
            float(g[crit]),
            pa,
            pb,
            edge,
            Timings(t1 - t0, ta, max(t2 - t1 - ta, 0.0), time.perf_counter() - t0),
            sf.data_a,
            sf.data_b,
        )
    split = split_subsets(g, crit)
    data_a = F.plane_data(geometry, g, d, split.steps_a, "a", AXIS_Y)
    data_b = F.plane_data(geometry, g, d, split.steps_b, "b", AXIS_Z)
    t1 = time.perf_counter()
    pa = fit_plane(data_a, method, warm_start=warm_a, options=opts)
    t2 = time.perf_counter()
    pb = fit_plane(data_b, method, warm_start=warm_b, options=opts)
    pa, pb = _assessed(pa, g), _assessed(pb, g)
    t3 = time.perf_counter()
    edge = corner_edge(pa, pb)
    return ScanReconstruction(
        method,
        int(g.size),
        crit,
        float(g[crit]),
        pa,
        pb,
        edge,
        Timings(t1 - t0, t2 - t1, t3 - t2, time.perf_counter() - t0),
        data_a,
        data_b,
    )


# Re-exported for callers that want the raw points.
__all__ += ["beam_points", "corrected_points", "split_subsets", "critical_step"]
