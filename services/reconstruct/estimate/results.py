"""Typed results of the reconstruction: one plane, a failure, the corner edge, a scan.

Every result is a frozen, validated dataclass.  NumPy arrays held by a result
are copied and made read-only, so a result can be shared between threads and
cached without anyone changing it under the reader's feet.

Conventions (see :mod:`lelsonar.geometry`): world frame, metres and radians.
A plane is ``n · x = h`` with ``n`` a unit normal pointing away from the
scanner (``h > 0``); the paper's parameter vector is ``θ = n / h`` so that
``θ · v = 1`` (eq. 1).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Set as AbstractSet
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from lelsonar.errors import ConfigError

if TYPE_CHECKING:  # fit.py builds its results from this module
    from lelsonar.reconstruct.estimate.fit import PlaneData

__all__ = [
    "FailureReason",
    "FitFailure",
    "SolverDiagnostics",
    "PlaneFit",
    "EdgeLine",
    "Timings",
    "ScanReconstruction",
    "PlaneResult",
]


def _frozen_array(
    obj: object, name: str, shape: tuple[int | None, ...] | None = None, dtype: type = np.float64, finite: bool = True
) -> np.ndarray:
    """Copy ``getattr(obj, name)`` into a read-only array and write it back."""
    a: np.ndarray = np.array(getattr(obj, name), dtype=dtype, copy=True)
    if shape is not None:
        if a.ndim != len(shape) or any(s is not None and s != t for s, t in zip(shape, a.shape)):
            raise ConfigError(f"{type(obj).__name__}.{name} must have shape {shape}, got {a.shape}")
    if finite and a.dtype.kind == "f" and not np.isfinite(a).all():
        raise ConfigError(f"{type(obj).__name__}.{name} must be finite, got {a!r}")
    a.setflags(write=False)
    object.__setattr__(obj, name, a)
    return a


class FailureReason(enum.StrEnum):
    """Why a plane could not be estimated."""

    TOO_FEW_POINTS = "too few points"
    DEGENERATE_GEOMETRY = "degenerate geometry"
    SOLVER_FAILED = "solver failed"


@dataclass(frozen=True)
class FitFailure:
    """A plane (or edge) that could not be estimated.  Never a silent NaN.

    Parameters
    ----------
    reason : FailureReason
    detail : str
        What exactly was wrong, for logs and the wire's ``failures`` field.
    label : str
        ``"a"``, ``"b"`` or ``"edge"``.
    n_points : int
        Valid points that were available.
    """

    reason: FailureReason
    detail: str
    label: str = ""
    n_points: int = 0

    def __post_init__(self) -> None:
        if not isinstance(self.reason, FailureReason):
            raise ConfigError(f"FitFailure.reason must be a FailureReason, got {self.reason!r}")
        if self.n_points < 0:
            raise ConfigError(f"FitFailure.n_points must be >= 0, got {self.n_points}")

    @property
    def ok(self) -> bool:
        return False

    def __str__(self) -> str:
        who = f"plane {self.label}: " if self.label in ("a", "b") else (f"{self.label}: " if self.label else "")
        return f"{who}{self.reason.value} ({self.detail})"


@dataclass(frozen=True)
class SolverDiagnostics:
    """How a fit was computed.

    Parameters
    ----------
    solver : str
        E.g. ``"lstsq"``, ``"nelder-mead x6"``, ``"bfgs"``, ``"ransac"``.
    starts : int
        Number of starting points tried (the paper uses six, §5.2).
    iterations : int
        Iterations summed over all starts and stages.
    evaluations : int
        Cost evaluations summed over all starts and stages.
    time_s : float
        Wall time of the whole plane fit, s.
    converged : bool
        Whether the solver of the final stage reported convergence.
    notes : tuple of str
        Stage log, e.g. guard decisions (``"guard: switched to ..."``).
    """

    solver: str
    starts: int = 1
    iterations: int = 0
    evaluations: int = 0
    time_s: float = 0.0
    converged: bool = True
    notes: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if self.starts < 0 or self.iterations < 0 or self.evaluations < 0:
            raise ConfigError("solver counters must be non-negative")
        if not (math.isfinite(self.time_s) and self.time_s >= 0):  # (as Timings: seconds are real numbers)
            raise ConfigError(f"time_s must be finite and >= 0, got {self.time_s}")
        object.__setattr__(self, "notes", tuple(str(n) for n in self.notes))


@dataclass(frozen=True)
class PlaneFit:
    """One estimated plane ``n · x = h`` (θ = n / h, θ · v = 1, eq. 1).

    Parameters
    ----------
    label : str
        ``"a"`` (seen before the critical step, face-on at γ ≈ 0) or ``"b"``.
    method : str
        Registry name of the estimator.
    normal : (3,) array
        Unit normal pointing away from the scanner.
    offset : float
        ``h`` in m, > 0.
    entropy : float
        The LEL cost ``H`` (eq. 6) of the final parameters over *all* the
        subset's points, in [0, 1].
    sigma_relative : float
        The paper's σ = 1.4826·MAD of ``e_i = v_i · θ − 1`` (eq. 20–22) over
        the inliers, unitless.
    sigma : float
        Metric σ = 1.4826·MAD of the point-to-plane distances of the inliers, m
        (= ``sigma_relative · h``).
    inlier_mask : (n_points,) bool array
        Points of the subset the final fit accepted, in subset order.
    sorted_residuals : (n_points,) array
        All ``e_i`` (eq. 20) sorted ascending — the data of the paper's
        Figs. 12–13.
    theta_covariance : (3, 3) array
        Covariance of θ from the inlier residuals, 1/m².
    normal_stderr : float
        Standard error of the normal's direction, rad (root of the trace of the
        normal's covariance, i.e. the RMS tilt).
    offset_stderr : float
        Standard error of ``h``, m.
    patch : (4, 3) array
        Corners of the observed patch: the bounding rectangle, in the plane, of
        the inliers' foot points, m.
    diagnostics : SolverDiagnostics
    quality : str
        The trust verdict, ``"good"``, ``"degraded"`` or ``"unreliable"``
        (:mod:`lelsonar.reconstruct.estimate.quality`); ``""`` until assessed.
    quality_reasons : tuple of str
        Why it is not good.
    """

    label: str
    method: str
    normal: np.ndarray
    offset: float
    entropy: float
    sigma_relative: float
    sigma: float
    inlier_mask: np.ndarray
    sorted_residuals: np.ndarray
    theta_covariance: np.ndarray
    normal_stderr: float
    offset_stderr: float
    patch: np.ndarray
    diagnostics: SolverDiagnostics = field(default_factory=lambda: SolverDiagnostics("unknown"))
    quality: str = ""
    quality_reasons: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        self._check_scalars()
        n = _frozen_array(self, "normal", (3,))
        if abs(float(np.sqrt(n @ n)) - 1.0) > 1e-9:  # |n| as np.linalg.norm computes it
            raise ConfigError(f"PlaneFit.normal must be a unit vector, |n| = {np.linalg.norm(n)}")
        mask = _frozen_array(self, "inlier_mask", (None,), dtype=bool)
        res = _frozen_array(self, "sorted_residuals", (mask.shape[0],))
        if (res[1:] < res[:-1]).any():
            raise ConfigError("PlaneFit.sorted_residuals must be sorted ascending")
        cov = _frozen_array(self, "theta_covariance", (3, 3))
        # np.allclose(cov, cov.T, rtol=1e-9, atol=1e-15) for a finite cov, written out: every fit and every
        # replace validates, and np.allclose's generality costs more than the check.
        if not np.all(np.abs(cov - cov.T) <= 1e-15 + 1e-9 * np.abs(cov.T)):
            raise ConfigError("PlaneFit.theta_covariance must be symmetric")
        _frozen_array(self, "patch", (4, 3))

    def _check_scalars(self, names: AbstractSet[str] | None = None) -> None:
        """Validate (and normalise) the fields that are not arrays: what :meth:`replace_scalars` may change.

        ``names``: only these fields (those a replacement changed; the others were checked when this
        plane was made); None: all of them.  Checked in :data:`_SCALAR_CHECKS`' order, whichever are asked.
        """
        for name, check in _SCALAR_CHECKS:
            if names is None or name in names:
                check(self)

    @classmethod
    def from_owned(
        cls,
        label: str,
        method: str,
        normal: np.ndarray,
        offset: float,
        entropy: float,
        sigma_relative: float,
        sigma: float,
        inlier_mask: np.ndarray,
        sorted_residuals: np.ndarray,
        theta_covariance: np.ndarray,
        normal_stderr: float,
        offset_stderr: float,
        patch: np.ndarray,
        diagnostics: SolverDiagnostics,
    ) -> PlaneFit:
        """Wrap fields valid by construction whose arrays nothing else holds (what ``make_plane_fit`` builds).

        Every check of ``__init__`` holds already — a unit normal and ``h > 0`` from a finite ``θ``,
        MAD σ and H of finite residuals, residuals fresh from ``np.sort``, a covariance symmetrised
        and found finite, float64 arrays of the right shapes — and the arrays are fresh: they are
        made read-only in place rather than copied and checked again on every fit (the fit's hot
        path; :meth:`__init__` stays the boundary for everyone else).
        """
        obj = object.__new__(cls)
        for a in (normal, inlier_mask, sorted_residuals, theta_covariance, patch):
            a.setflags(write=False)
        obj.__dict__.update(
            label=label,
            method=method,
            normal=normal,
            offset=float(offset),
            entropy=float(min(entropy, 1.0)),
            sigma_relative=float(sigma_relative),
            sigma=float(sigma),
            inlier_mask=inlier_mask,
            sorted_residuals=sorted_residuals,
            theta_covariance=theta_covariance,
            normal_stderr=float(normal_stderr),
            offset_stderr=float(offset_stderr),
            patch=patch,
            diagnostics=diagnostics,
            quality="",
            quality_reasons=(),
        )
        return obj

    def replace_scalars(self, **changes: object) -> PlaneFit:
        """``dataclasses.replace(self, **changes)`` for fields that are not arrays, without copying the arrays.

        ``changes`` may set any field but ``normal``, ``inlier_mask``, ``sorted_residuals``,
        ``theta_covariance`` and ``patch`` (e.g. the trust verdict, a fallback's name, the standard
        errors).  The changed fields are validated as the constructor validates them (the others were when
        this plane was made); the arrays,
        frozen and validated when this plane was made, are shared with it, not copied and checked again.
        """
        if not changes.keys() <= _SCALARS:
            raise ConfigError(
                f"PlaneFit.replace_scalars changes only {sorted(_SCALARS)}, not {sorted(changes.keys() - _SCALARS)}"
            )
        obj = object.__new__(PlaneFit)
        obj.__dict__.update(self.__dict__)
        obj.__dict__.update(changes)
        obj._check_scalars(changes.keys())  # the unchanged fields were checked when this plane was made
        return obj

    @property
    def ok(self) -> bool:
        return True

    @property
    def theta(self) -> np.ndarray:
        """The paper's parameter vector ``θ = n / h`` (eq. 1), 1/m."""
        return self.normal / self.offset

    @property
    def n_points(self) -> int:
        return int(self.inlier_mask.shape[0])

    @property
    def n_inliers(self) -> int:
        return int(np.count_nonzero(self.inlier_mask))

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Signed distances ``n · x − h`` of ``points`` (..., 3) to the plane, m."""
        return np.asarray(points, dtype=float) @ self.normal - self.offset


PlaneResult = PlaneFit | FitFailure


def _check_quality(p: PlaneFit) -> None:
    if p.quality not in ("", "good", "degraded", "unreliable"):
        raise ConfigError(f"PlaneFit.quality must be good, degraded or unreliable, got {p.quality!r}")


def _check_method(p: PlaneFit) -> None:
    if not isinstance(p.method, str):
        raise ConfigError(f"PlaneFit.method must be a str, got {p.method!r}")


def _check_diagnostics(p: PlaneFit) -> None:
    if not isinstance(p.diagnostics, SolverDiagnostics):
        raise ConfigError(f"PlaneFit.diagnostics must be SolverDiagnostics, got {type(p.diagnostics).__name__}")


def _check_quality_reasons(p: PlaneFit) -> None:
    object.__setattr__(p, "quality_reasons", tuple(str(r) for r in p.quality_reasons))


def _check_offset(p: PlaneFit) -> None:
    if not (math.isfinite(p.offset) and p.offset > 0):  # (scalars: math's test, not a ufunc's)
        raise ConfigError(f"PlaneFit.offset must be finite and > 0 m, got {p.offset}")
    object.__setattr__(p, "offset", float(p.offset))


def _check_entropy(p: PlaneFit) -> None:
    if not (0.0 <= p.entropy <= 1.0 + 1e-12):
        raise ConfigError(f"PlaneFit.entropy must be in [0, 1], got {p.entropy}")
    object.__setattr__(p, "entropy", float(min(p.entropy, 1.0)))


def _check_non_negative(name: str):
    def check(p: PlaneFit) -> None:
        v = getattr(p, name)
        if not (math.isfinite(v) and v >= 0):
            raise ConfigError(f"PlaneFit.{name} must be finite and >= 0, got {v}")
        object.__setattr__(p, name, float(v))

    return check


def _check_label(p: PlaneFit) -> None:
    if p.label not in ("a", "b"):
        raise ConfigError(f"PlaneFit.label must be 'a' or 'b', got {p.label!r}")


#: :meth:`PlaneFit._check_scalars`' checks, field by field, in the order they run (each normalises its field).
_SCALAR_CHECKS = (
    ("quality", _check_quality),
    ("method", _check_method),
    ("diagnostics", _check_diagnostics),
    ("quality_reasons", _check_quality_reasons),
    ("offset", _check_offset),
    ("entropy", _check_entropy),
    *((name, _check_non_negative(name)) for name in ("sigma_relative", "sigma", "normal_stderr", "offset_stderr")),
    ("label", _check_label),
)

#: The fields :meth:`PlaneFit.replace_scalars` may change: all but the arrays.
_SCALARS = frozenset(
    {
        "label",
        "method",
        "offset",
        "entropy",
        "sigma_relative",
        "sigma",
        "normal_stderr",
        "offset_stderr",
        "diagnostics",
        "quality",
        "quality_reasons",
    }
)


@dataclass(frozen=True)
class EdgeLine:
    """The corner edge: the line where the two planes meet.

    Parameters
    ----------
    point : (3,) array
        The point of the line closest to the origin, m.
    direction : (3,) array
        Unit direction, ``n_a × n_b`` normalised.
    angle : float
        Angle between the two planes' normals, rad (π/2 for the paper's corner).
    point_stderr : float
        Standard error of the point across the line, m (first order, from the
        planes' standard errors; NaN if unknown).
    direction_stderr : float
        Standard error of the direction, rad.
    """

    point: np.ndarray
    direction: np.ndarray
    angle: float
    point_stderr: float = float("nan")
    direction_stderr: float = float("nan")

    def __post_init__(self) -> None:
        _frozen_array(self, "point", (3,))
        d = _frozen_array(self, "direction", (3,))
        if abs(float(np.linalg.norm(d)) - 1.0) > 1e-9:
            raise ConfigError("EdgeLine.direction must be a unit vector")
        if not (np.isfinite(self.angle) and 0.0 <= self.angle <= np.pi):
            raise ConfigError(f"EdgeLine.angle must be in [0, π], got {self.angle}")
        object.__setattr__(self, "angle", float(self.angle))

    @classmethod
    def from_owned(
        cls, point: np.ndarray, direction: np.ndarray, angle: float, point_stderr: float, direction_stderr: float
    ) -> EdgeLine:
        """Wrap fields valid by construction whose arrays nothing else holds (what ``corner_edge`` builds).

        The caller guarantees the checks of ``__init__``: a finite ``point``, a unit ``direction`` and an
        ``angle`` in [0, π], as fresh float64 arrays of shape (3,) that it hands over.  The arrays are made
        read-only in place rather than copied and checked again (the fit's hot path; ``__init__`` stays
        the boundary for everyone else).
        """
        obj = object.__new__(cls)
        for a in (point, direction):
            a.setflags(write=False)
        obj.__dict__.update(
            point=point,
            direction=direction,
            angle=float(angle),
            point_stderr=point_stderr,
            direction_stderr=direction_stderr,
        )
        return obj

    @property
    def ok(self) -> bool:
        return True


@dataclass(frozen=True)
class Timings:
    """Wall times of one reconstruction, s (the wire's ``ComputeTimings``)."""

    segmentation: float
    fit_a: float
    fit_b: float
    total: float

    def __post_init__(self) -> None:
        for name in ("segmentation", "fit_a", "fit_b", "total"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):  # (seconds are real numbers: math's test, not a ufunc's)
                raise ConfigError(f"Timings.{name} must be finite and >= 0 s, got {v}")

    @property
    def fit(self) -> float:
        return self.fit_a + self.fit_b


@dataclass(frozen=True)
class ScanReconstruction:
    """What :func:`lelsonar.reconstruct.estimate.pipeline.reconstruct` returns for one (partial) scan.

    Parameters
    ----------
    method : str
    n_steps : int
        Steps in the input.
    critical_step : int or None
        Index of the step with the largest ``R`` (§4), ``None`` if there is
        none (no valid step) — the wire leaves it unset.
    critical_angle : float
        γ of the critical step, rad (NaN only when ``critical_step`` is None).
    plane_a, plane_b : PlaneFit or FitFailure
        ``a`` is the plane seen before the corner (the subset at smaller γ).
    edge : EdgeLine or FitFailure
    timings : Timings
    data_a, data_b : lelsonar.reconstruct.estimate.fit.PlaneData or None
        The points each plane was fitted on, in the order its ``inlier_mask``
        indexes (the energy split's halves, or the echoes the joint corner
        model gave each wall).  Step indices are those of the input arrays.
    """

    method: str
    n_steps: int
    critical_step: int | None
    critical_angle: float
    plane_a: PlaneResult
    plane_b: PlaneResult
    edge: EdgeLine | FitFailure
    timings: Timings
    data_a: PlaneData | None = None
    data_b: PlaneData | None = None

    def __post_init__(self) -> None:
        if self.n_steps < 0:
            raise ConfigError("n_steps must be >= 0")
        if self.critical_step is not None:
            if not 0 <= self.critical_step < max(self.n_steps, 1):
                raise ConfigError(f"critical_step {self.critical_step} outside [0, {self.n_steps})")
            if not math.isfinite(self.critical_angle):
                raise ConfigError("critical_angle must be finite when critical_step is set")
        for name in ("plane_a", "plane_b"):
            if not isinstance(getattr(self, name), (PlaneFit, FitFailure)):
                raise ConfigError(f"{name} must be a PlaneFit or a FitFailure")
        if not isinstance(self.edge, (EdgeLine, FitFailure)):
            raise ConfigError("edge must be an EdgeLine or a FitFailure")

    @property
    def planes(self) -> tuple[PlaneResult, PlaneResult]:
        return (self.plane_a, self.plane_b)

    @property
    def failures(self) -> tuple[str, ...]:
        """Human-readable reasons, one per failed item (the wire's ``failures``)."""
        return tuple(str(x) for x in (self.plane_a, self.plane_b, self.edge) if isinstance(x, FitFailure))
