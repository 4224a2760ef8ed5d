"""Cheap provisional estimates of a plane while its scan arrives.

The live service re-estimates plane b as samples come.  Refitting it from
scratch each time costs O(points) with the solver's constant (fast LEL,
pre-filter, LS refit, the χ² tilt test) and, when the least-H minimum looks
suspicious, the outlier-cluster guard's RANSAC — and the scan's points grow, so
a scan pays O(n²).  :class:`IncrementalPlane` instead keeps the least-squares
sufficient statistics of the plane's inliers (``Σ v vᵀ``, ``Σ v``, ``Σ p_c``,
``Σ d``, their count) and, per update:

1. computes the corrected points of the steps added since the last estimate
   (eq. 9, §4), in one pass — and none while no fit could be tried (below);
2. gives each new point to the inliers if it lies within
   ``FitOptions.inlier_tolerance`` of the current plane, and adds it to the sums;
3. solves the 3 × 3 normal equations (eq. 15 on the inliers) for the normal,
   and takes the offset from the mirror-echo condition ``h = mean(n·p_c + d)``
   over the inliers — what ``"adaptive"`` does on an axis-aligned wall;
4. checks the update (the *trust check*): enough inliers; of the points
   since the last exact fit, at least half the share of inliers that fit
   had; the normal within the beam of a boresight (the mirror-echo
   condition) and within :data:`FACING_MARGIN` (the joint model's
   ``max_tilt``) of the wall's nominal normal; the inliers' RMS residual
   within the tolerance.

When the plane's points have doubled since the last exact fit or refresh,
every point is re-classified against the current plane and the sums are
rebuilt (a *refresh*: one vectorised pass, no solver), then judged by the same
trust check — so a scan pays O(n) in all, amortised O(new samples) per update.

An exact fit — the provisional method from scratch, warm-started from the last
estimate — runs only (a) for the first estimate, (b) when the trust check (of
an update or a refresh) fails, or (c) when the last exact fit chose the
constant-depth (tilted-wall) model, which the corrected-points sums do not
represent: then the next exact fit waits until the points have grown by half,
and the estimate stays meanwhile.  The outlier-cluster guard's RANSAC (the
expensive part) runs inside an exact fit only when its least-H minimum fails
the guard's own test (mirror-consistent, ``min_inlier_fraction`` of the points
within ``inlier_tolerance``), with the draws :func:`ransac_iterations` gives
(52); what the guard returns it has vetted.  An exact fit is trusted if its
normal faces a beam and lies within :data:`FACING_MARGIN` of the wall's
nominal normal; one that is not is published as a typed failure (a plane
55–60° off wall b is the corner's echoes, not wall b), and the next exact fit
waits until the echoes of the beams facing the wall have grown by half
(:data:`RETRY_GROWTH`).  No fit at all is tried before a beam has faced the
wall (within ``beam_half_angle`` + :data:`FACING_MARGIN` of its nominal
normal), nor, until a fit has been trusted, while the beams within
``beam_half_angle`` of its nominal normal have given less than
``min_inlier_fraction`` of its echoes: a trusted fit holds that share of the
points as the wall's, and a wall's echoes come from the beams that face it, so
before then subset b holds mostly the corner's echoes and a fit could only
fail or find them.  The estimate is then a typed failure, at no cost.

The final estimate of a scan never uses any of this: it is computed from
scratch (:func:`lelsonar.reconstruct.estimate.record.reconstruct_scan`).

Building the :class:`~lelsonar.reconstruct.estimate.results.PlaneFit` the message
carries (σ by MAD, H over all points, the observed patch, the residuals) is
one vectorised pass over the plane's points (nearly all of it per-call
overhead); the fit itself touches only the new ones.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import Literal, overload

import numpy as np

from lelsonar.errors import InternalError
from lelsonar.geometry import ArrayGeometry, boresight
from lelsonar.reconstruct.estimate import fit as F
from lelsonar.reconstruct.estimate.options import FitOptions
from lelsonar.reconstruct.estimate.pipeline import fit_plane
from lelsonar.reconstruct.estimate.results import (
    FailureReason,
    FitFailure,
    PlaneFit,
    PlaneResult,
    SolverDiagnostics,
)

__all__ = [
    "ExactFit",
    "IncrementalPlane",
    "IncrementalStats",
    "FACING_MARGIN",
    "RETRY_GROWTH",
    "RANSAC_MISS",
    "exact_fit",
    "ransac_iterations",
]

#: rad.  No exact fit is tried before some beam of the plane's points has come within
#: ``FitOptions.beam_half_angle`` + this margin of the plane's nominal normal (its correction axis):
#: the mirror-echo condition (the guard's own test) rejects any plane no beam faced, and a wall more
#: than this far off its nominal axis is beyond the joint model's ``max_tilt`` (15°) as well.  For the
#: same reason no provisional plane further than this from its nominal normal is trusted.
FACING_MARGIN = float(np.deg2rad(15.0))
#: After an exact fit that fails the trust check (the wall not yet seen face-on, typically), the next
#: one waits until the echoes of the beams facing the wall have grown by this factor; after a tilted-wall
#: verdict (no sums), until the plane's points have.
RETRY_GROWTH = 1.5
#: Probability that the guard's RANSAC, in a provisional exact fit, misses a wall holding
#: ``min_inlier_fraction`` of the points (see :func:`ransac_iterations`).
RANSAC_MISS = 1e-3


def ransac_iterations(inlier_share: float, miss: float) -> int:
    """RANSAC draws needed to draw three inliers at least once with probability ``1 − miss``.

    ``N = ⌈log(miss) / log(1 − w³)⌉`` for an inlier share ``w`` (Fischler & Bolles' bound): 52 for
    ``w = ½``, ``miss = 10⁻³``.  A provisional fit is tried only once the beams facing the wall have given
    ``min_inlier_fraction`` of the plane's echoes, so the guard's RANSAC needs no more draws than that
    share calls for (the final, from scratch, keeps ``FitOptions.ransac_iterations``); a miss costs an
    untrusted fit, retried as the wall's echoes grow.
    """
    if not (0 < inlier_share < 1 and 0 < miss < 1):
        return 1 if inlier_share >= 1 else 10**6
    return max(1, int(np.ceil(np.log(miss) / np.log1p(-(inlier_share**3)))))


@dataclass(frozen=True, eq=False)
class ExactFit:
    """An exact fit of a provisional plane, as :meth:`IncrementalPlane.take_fit` hands it out: what
    :func:`exact_fit` needs, picklable (a final pool's worker may run it)."""

    data: F.PlaneData
    method: str
    warm_start: np.ndarray | None
    options: FitOptions


def exact_fit(job: ExactFit) -> PlaneResult:
    """The provisional method from scratch on a plane's points, warm-started from its last estimate (what
    :meth:`IncrementalPlane.fitted` takes)."""
    return fit_plane(job.data, job.method, warm_start=job.warm_start, options=job.options)


@dataclass
class IncrementalStats:
    """How the provisional estimates of one plane were made."""

    calls: int = 0  # re-estimates asked for
    updates: int = 0  # O(new points) updates that passed the trust check
    exact: int = 0  # exact fits without the guard
    guarded: int = 0  # exact fits whose least-H minimum failed the guard's test (its RANSAC ran)
    trust_failures: int = 0  # incremental updates that failed the trust check (an exact fit followed)
    untrusted: int = 0  # exact fits that failed the trust check even guarded (e.g. wall b not yet face-on)
    waited: int = 0  # re-estimates that kept the last plane, waiting for more points after an untrusted fit
    not_facing: int = 0  # re-estimates skipped: no beam has faced the wall yet (a typed failure, no fit)
    refreshes: int = 0  # doublings handled by re-classifying every point, without an exact fit
    fits_waited: int = 0  # re-estimates that kept the last plane while a due exact fit waited (update's exact)
    fits_away: int = 0  # exact fits handed out (take_fit) to run elsewhere


class IncrementalPlane:
    """One plane of a scan in progress, re-estimated in O(new points).

    Parameters
    ----------
    geometry : ArrayGeometry
    label : str
        ``"a"`` or ``"b"``.
    axis : (3,) array
        The paper's assumed normal of the plane (the correction's axis).
    method : str
        The provisional method (a per-subset method of ``pipeline.METHODS``)
        used for the exact fits.
    options : FitOptions
    steps : int
        Steps of the scan's schedule.
    """

    def __init__(
        self, geometry: ArrayGeometry, label: str, axis: np.ndarray, method: str, options: FitOptions, steps: int
    ) -> None:
        self.geometry, self.label, self.axis = geometry, label, np.asarray(axis, dtype=np.float64)
        self.method, self.options = method, options
        self._fit_options = replace(
            options,
            ransac_iterations=min(
                options.ransac_iterations, ransac_iterations(options.min_inlier_fraction, RANSAC_MISS)
            ),
        )
        self.included = np.zeros(int(steps), dtype=bool)
        self.n = 0
        cap = 64
        self._v = np.empty((cap, 3))
        self._pc = np.empty((cap, 3))
        self._d = np.empty(cap)
        self._beam = np.empty((cap, 3))
        self._step = np.empty(cap, dtype=np.intp)
        self._inlier = np.zeros(cap, dtype=bool)
        self._reset_sums()
        self._theta_ls: np.ndarray | None = None  # the LS θ of the inliers; None: the next update is exact
        self._exact_at = 0  # points at the last exact fit
        self._retry_at = 0  # after an exact fit without sums: points needed before the next one
        self._retry_face_on = 0  # after an untrusted one: face-on echoes needed before the next one
        self._face_on = 0  # echoes of beams within beam_half_angle of the nominal normal
        self._offered = self._accepted = 0  # new points since the last exact fit
        self._best_beam: np.ndarray | None = None
        self._pending: list[np.ndarray] = []  # steps whose points are not computed yet
        self._pending_echoes = 0  # their echoes (an upper bound on their points)
        self._facing = -1.0  # the largest beam · axis so far
        self._seed_fraction = 1.0  # inliers / points at the last exact fit
        self.plane: PlaneResult | None = None
        #: An exact fit is due but waits for an update with ``exact`` (:meth:`update`), or to be handed out.
        self.fit_wanted = False
        #: An exact fit was handed out (:meth:`take_fit`) and its result is not back (:meth:`fitted`).
        self.fit_away = False
        #: The points behind :attr:`plane` (for observers that draw them).
        self.last_data: F.PlaneData | None = None
        self.stats = IncrementalStats()

    # --- data -------------------------------------------------------------------------------
    def _reset_sums(self) -> None:
        self._S = np.zeros((3, 3))
        self._s = np.zeros(3)
        self._P = np.zeros(3)
        self._D = 0.0
        self._k = 0

    def _add_to_sums(self, v: np.ndarray, pc: np.ndarray, d: np.ndarray) -> None:
        self._S += v.T @ v
        self._s += v.sum(axis=0)
        self._P += pc.sum(axis=0)
        self._D += float(d.sum())
        self._k += int(d.shape[0])

    def _append(self, data: F.PlaneData) -> slice:
        m = data.n
        if self.n + m > len(self._d):
            cap = max(2 * len(self._d), self.n + m)
            for name in ("_v", "_pc", "_d", "_beam", "_step", "_inlier"):
                old = getattr(self, name)
                new = np.zeros((cap, *old.shape[1:]), dtype=old.dtype)
                new[: self.n] = old[: self.n]
                setattr(self, name, new)
        sl = slice(self.n, self.n + m)
        self._v[sl], self._pc[sl], self._d[sl] = data.points, data.capsules, data.distance
        self._beam[sl], self._step[sl] = data.beam, data.step
        self._inlier[sl] = False
        self.n += m
        return sl

    def data(self) -> F.PlaneData:
        """The plane's points so far, in arrival order (read-only views: a point's row is written once)."""
        return F.PlaneData.prefix(self.label, self.axis, self.n, self._v, self._pc, self._d, self._beam, self._step)

    # --- the estimate -----------------------------------------------------------------------
    @overload
    def update(
        self, gamma: np.ndarray, distance: np.ndarray, new_steps: np.ndarray, *, exact: Literal[True] = ...
    ) -> PlaneResult: ...

    @overload
    def update(
        self, gamma: np.ndarray, distance: np.ndarray, new_steps: np.ndarray, *, exact: bool
    ) -> PlaneResult | None: ...

    def update(
        self, gamma: np.ndarray, distance: np.ndarray, new_steps: np.ndarray, *, exact: bool = True
    ) -> PlaneResult | None:
        """Add the points of ``new_steps`` (received, not added before) and re-estimate.

        ``exact`` False: an exact fit this update needs is not run but waits (:attr:`fit_wanted`), and the
        estimate kept meanwhile is returned (None before any); the points added meanwhile wait uncomputed.
        The next update with ``exact`` runs it on every point so far, as this one would have on fewer.
        """
        self.stats.calls += 1
        t0 = time.perf_counter()
        o = self.options
        new_steps = np.asarray(new_steps, dtype=np.intp)
        if len(new_steps):
            self.included[new_steps] = True
            d = np.asarray(distance, dtype=np.float64)[new_steps]
            echoes = np.count_nonzero(np.isfinite(d) & (d > 0), axis=1)
            cos_axis = boresight(np.asarray(gamma, dtype=np.float64)[new_steps]) @ self.axis
            if np.any(echoes):
                self._facing = max(self._facing, float(np.max(cos_axis[echoes > 0])))
            self._face_on += int(np.sum(echoes[cos_axis >= np.cos(o.beam_half_angle)]))
            self._pending.append(new_steps)
            self._pending_echoes += int(np.sum(echoes))
        if self.fit_away:
            self.stats.fits_waited += 1
            return self.plane  # its points wait uncomputed for the fit's result, as for a fit that waits
        if self.fit_wanted:
            if not exact:
                self.stats.fits_waited += 1
                return self.plane
            self._materialise(gamma, distance)
            return self._exact(t0)
        echoes = self.n + self._pending_echoes  # an upper bound on the points (a few beams are too oblique)
        if self._facing < np.cos(o.beam_half_angle + FACING_MARGIN):
            # The points wait (uncomputed) for a beam to face the wall: nothing to fit yet.
            return self._not_facing(
                f"no beam has come within {np.rad2deg(o.beam_half_angle + FACING_MARGIN):.0f}° of the wall's "
                "nominal normal yet (is the corner reached yet?)",
                echoes,
            )
        if (
            self._theta_ls is None
            and self._face_on < o.min_inlier_fraction * echoes
            and not isinstance(self.plane, PlaneFit)
        ):
            # A trusted fit holds min_inlier_fraction of the points (the guard's test), and a wall's echoes
            # come from the beams that face it: until those have given that share, a fit can only find the
            # corner's echoes (it fails, or its plane is far off the wall's normal).
            return self._not_facing(
                f"the beams within {np.rad2deg(o.beam_half_angle):.0f}° of the wall's nominal normal have given "
                f"{self._face_on} of its {echoes} echoes, less than the {o.min_inlier_fraction:.0%} a fit must "
                "hold",
                echoes,
            )
        if self._waiting(echoes):
            return self._last()  # not even the echoes (an upper bound on the points) are enough yet
        sl = self._materialise(gamma, distance)
        theta = self._theta_ls
        if theta is not None:
            if self.n < 2 * self._exact_at:
                trusted = self._incremental(sl, theta, t0)
            else:
                trusted = self._refresh(theta, t0)
            if trusted:
                return self._last()
            self.stats.trust_failures += 1
        elif self._waiting(self.n):
            return self._last()
        if not exact:
            # The fit waits; its update's sums (a failed trust check's included) are rebuilt by it.
            self.fit_wanted = True
            self.stats.fits_waited += 1
            return self.plane
        return self._exact(t0)

    def _last(self) -> PlaneResult:
        """The estimate kept: only asked once one was made (waiting follows a fit, a trusted update sets one)."""
        if self.plane is None:
            raise InternalError(f"plane {self.label}: the last provisional estimate was asked before any was made")
        return self.plane

    def _not_facing(self, why: str, echoes: int) -> FitFailure:
        self.stats.not_facing += 1
        self.plane = FitFailure(FailureReason.DEGENERATE_GEOMETRY, f"provisional: {why}", self.label, echoes)
        self.last_data = None
        return self.plane

    def _waiting(self, points: int) -> bool:
        """After an exact fit that gave no sums (untrusted, or a tilted wall): wait for more points, or, after
        an untrusted one, for more of the echoes of the beams facing the wall."""
        if (
            self._theta_ls is None
            and self.plane is not None
            and (points < self._retry_at or self._face_on < self._retry_face_on)
        ):
            self.stats.waited += 1
            return True
        return False

    def _materialise(self, gamma: np.ndarray, distance: np.ndarray) -> slice:
        """Compute the corrected points of the steps added since the last fit (eq. 9, §4), in one pass."""
        if not self._pending:
            return slice(self.n, self.n)
        steps = self._pending[0] if len(self._pending) == 1 else np.concatenate(self._pending)
        self._pending, self._pending_echoes = [], 0
        new = F.plane_data(self.geometry, gamma, distance, steps, self.label, self.axis)
        return self._append(new) if new.n else slice(self.n, self.n)

    def _incremental(self, sl: slice, theta: np.ndarray, t0: float) -> bool:
        """The new points only: classify them against the current plane (the inliers' LS ``theta``), add the
        inliers to the sums."""
        v, pc, d = self._v[sl], self._pc[sl], self._d[sl]
        if len(d):
            r = (v @ theta - 1.0) / np.linalg.norm(theta)
            ok = np.abs(r) <= self.options.inlier_tolerance
            self._inlier[sl] = ok
            self._add_to_sums(v[ok], pc[ok], d[ok])
            self._offered += len(d)
            self._accepted += int(np.count_nonzero(ok))
        return self._accept(self._beam[sl], t0, "incremental update")

    def _refresh(self, theta: np.ndarray, t0: float) -> bool:
        """The doubling rule, without a solver: every point re-classified against the current plane.

        Re-deriving the inliers from all the points (one vectorised pass, O(points) once per doubling:
        amortised O(1) per point) bounds the drift of a classification made against earlier planes; the
        sums are rebuilt from the new inliers and the trust check judges the result like an update whose
        new points are all the points.  Only if it fails does an exact fit run.
        """
        n = self.n
        v, pc, d = self._v[:n], self._pc[:n], self._d[:n]
        ok = np.abs((v @ theta - 1.0) / np.linalg.norm(theta)) <= self.options.inlier_tolerance
        self._reset_sums()
        self._add_to_sums(v[ok], pc[ok], d[ok])
        self._inlier[:n] = ok
        self._offered, self._accepted = n, int(np.count_nonzero(ok))
        if not self._accept(self._beam[:0], t0, "refresh (the points doubled)"):
            return False
        self.stats.refreshes += 1
        self._exact_at, self._seed_fraction = n, self._k / max(n, 1)
        self._offered = self._accepted = 0
        return True

    def _accept(self, beams: np.ndarray, t0: float, what: str) -> bool:
        """Solve the inliers' normal equations and apply the trust check; on success, the new plane."""
        o = self.options
        if self._k < max(o.min_points, 4):
            return False
        try:
            theta = np.linalg.solve(self._S, self._s)
        except np.linalg.LinAlgError:
            return False
        nt = float(np.linalg.norm(theta))
        if not (np.all(np.isfinite(theta)) and 1e-3 < nt < 1e3):
            return False
        n = theta / nt
        # The trust check: most new points fit, the normal faces a beam and stays near the wall's nominal
        # normal, the inliers sit within the tolerance.
        if self._offered >= o.min_points and self._accepted < 0.5 * self._seed_fraction * self._offered:
            return False
        if float(n @ self.axis) < np.cos(FACING_MARGIN):
            return False
        cands = beams if self._best_beam is None else np.vstack([self._best_beam[None, :], beams])
        if not F.mirror_consistent(n, cands, o.beam_half_angle) and not F.mirror_consistent(
            n, self._beam[: self.n], o.beam_half_angle
        ):
            return False
        rss = float(theta @ self._S @ theta - 2.0 * theta @ self._s + self._k)
        if not np.sqrt(max(rss, 0.0) / self._k) / nt <= o.inlier_tolerance:
            return False
        self._theta_ls = theta
        h = float((n @ self._P + self._D) / self._k)
        diag = SolverDiagnostics(
            solver="incremental: LS on the inliers' sums, mirror-echo offset",
            time_s=time.perf_counter() - t0,
            notes=(
                f"{what}: {self._k} inliers of {self.n} points; {self._accepted} of the "
                f"{self._offered} points since the last exact fit at {self._exact_at} accepted",
            ),
        )
        self.last_data = self.data()
        fit = F.make_plane_fit(
            self.last_data, n / h, method=self.method, inlier_mask=self._inlier[: self.n].copy(), diagnostics=diag
        )
        if not isinstance(fit, PlaneFit):
            return False
        self.plane = fit
        self.stats.updates += 1
        return True

    def _distrust(self, fit: PlaneResult, data: F.PlaneData) -> str:
        """Why an exact fit is not trusted ('' if it is): the guard's own acceptance test, and the tilt bound."""
        o = self.options
        if not isinstance(fit, PlaneFit):
            return "no fit"
        tilt = float(np.rad2deg(np.arccos(np.clip(fit.normal @ self.axis, -1.0, 1.0))))
        if tilt > np.rad2deg(FACING_MARGIN):
            return (
                f"its normal is {tilt:.0f}° from the wall's nominal normal, beyond the "
                f"{np.rad2deg(FACING_MARGIN):.0f}° a wall may tilt: another surface (the corner's echoes?)"
            )
        if not F.mirror_consistent(fit.normal, data.beam, o.beam_half_angle):
            return f"no beam came within {np.rad2deg(o.beam_half_angle):.0f}° of its normal"
        if not o.guard:  # the guard vetted its own pick; without it, apply its inlier test here
            k = F.inlier_count(F.metric_residuals(fit.theta, data.points), o.inlier_tolerance)
            if k < o.min_inlier_fraction * data.n:
                return f"only {k} of {data.n} points within {100 * o.inlier_tolerance:.0f} cm of it"
        return ""

    def take_fit(self) -> ExactFit:
        """Hand out the exact fit that is due (:attr:`fit_wanted`), to run elsewhere (:func:`exact_fit`) on the
        points computed so far; :meth:`fitted` takes its result.  Meanwhile the estimate stays, and the steps
        added wait uncomputed, as they do for a fit that waits."""
        if not self.fit_wanted or self.fit_away:
            raise InternalError(f"plane {self.label}: an exact fit was taken while none was due")
        self.fit_wanted, self.fit_away = False, True
        self.stats.fits_away += 1
        data = self.last_data = self.data()
        warm = self.plane.theta if isinstance(self.plane, PlaneFit) else None
        return ExactFit(data, self.method, warm, self._fit_options)

    def _exact(self, t0: float) -> PlaneResult:
        self.fit_wanted = False
        data = self.last_data = self.data()
        warm = self.plane.theta if isinstance(self.plane, PlaneFit) else None
        # The guard's RANSAC runs inside the fit only when its least-H minimum fails the guard's own test
        # (mirror-consistent, min_inlier_fraction of the points within inlier_tolerance): the fast LEL is
        # not run twice.  What the guard returns it has vetted.
        return self._apply(fit_plane(data, self.method, warm_start=warm, options=self._fit_options), data)

    def fit_lost(self) -> None:
        """The exact fit handed out will not come back (its worker pool went): it is due again."""
        if self.fit_away:
            self.fit_away, self.fit_wanted = False, True

    def fitted(self, fit: PlaneResult) -> PlaneResult:
        """Take the result of the exact fit handed out by :meth:`take_fit` (made on the points then computed,
        which are all the points computed now); returns the plane estimate."""
        if not self.fit_away or self.last_data is None:
            raise InternalError(f"plane {self.label}: an exact fit's result came while none was away")
        self.fit_away = False
        return self._apply(fit, self.last_data)

    def _apply(self, fit: PlaneResult, data: F.PlaneData) -> PlaneResult:
        """An exact fit's result on ``data`` (every point computed): trusted or not, and the sums it seeds."""
        self.stats.exact += 1
        if _guard_ran(fit):
            self.stats.guarded += 1
        why = self._distrust(fit, data)
        self.plane = fit
        self._exact_at = self.n
        self._offered = self._accepted = 0
        self._theta_ls = None
        self._reset_sums()
        self._inlier[: self.n] = False
        self._retry_at = max(self.n + 1, int(np.ceil(RETRY_GROWTH * self.n)))  # if no update can follow this fit
        self._retry_face_on = 0
        if why or not isinstance(fit, PlaneFit):  # (a failure is never trusted: its why is "no fit")
            self.stats.untrusted += 1
            # What changes the outcome is more echoes of the beams facing the wall.
            self._retry_at = self.n + 1
            self._retry_face_on = max(self._face_on + 1, int(np.ceil(RETRY_GROWTH * self._face_on)))
            if isinstance(fit, PlaneFit):  # a plane the trust check rejects is not published as this wall
                self.plane = FitFailure(
                    FailureReason.DEGENERATE_GEOMETRY,
                    f"provisional: the {self.method} fit of {data.n} points is not trusted yet: {why}",
                    self.label,
                    data.n,
                )
            return self.plane
        # Seed the sums with the fit's inliers, if the fit is the corrected-points LS of those inliers
        # (not the constant-depth plane of a tilted wall, which the sums do not represent).
        mask = fit.inlier_mask
        v = data.points[mask]
        self._add_to_sums(v, data.capsules[mask], data.distance[mask])
        try:
            theta_ls = np.linalg.solve(self._S, self._s)
        except np.linalg.LinAlgError:
            self._reset_sums()
            return fit
        n_ls = theta_ls / np.linalg.norm(theta_ls)
        if float(n_ls @ fit.normal) < np.cos(1e-6):
            self._reset_sums()  # a tilted wall: the next update is an exact fit again
            return fit
        self._inlier[: self.n] = mask
        self._seed_fraction = self._k / max(self.n, 1)
        self._theta_ls = theta_ls
        self._retry_at = 0
        self._best_beam = data.beam[int(np.argmax(data.beam @ fit.normal))]
        return fit


def _guard_ran(fit: PlaneResult) -> bool:
    """Whether the outlier-cluster guard's fallback ran in this fit (its notes, or its typed failure)."""
    if isinstance(fit, PlaneFit):
        return any(n.startswith("guard:") for n in fit.diagnostics.notes)
    return "no LEL minimum has its normal within" in fit.detail
