"""The floor ``bench surfaces`` measures a plane against: what the surface's own true echoes allow.

The oracle is told which readings are the mirror's echoes (the simulator's ``echo_index``), never where the
mirror is.  With them it does what a practitioner would:

* **least squares on their ranges** (:func:`~lelsonar.reconstruct.estimate.constant_depth.constant_depth_ls`,
  the mirror condition ``n · p_c + d = h``), started from the echoes' own beams (their mean direction, no tilt,
  the median depth along it).  Gauss-Newton on that near-linear problem reaches one minimum from any start,
  the truth's included.  Seen near the foot of its perpendicular, a wall's ranges pin its offset and tilt but
  barely its bearing (the capsules move across the beam only by their radial offset), so this fit's bearing
  error is the range noise magnified: large on most walls, by chance tiny on a few;
* **the beam pattern's bearing** of their amplitudes (:func:`~lelsonar.reconstruct.estimate.surfaces.regions.
  bearing_from_amplitude`, the peak of ``D(γ − β)²`` across γ), a measurement of the bearing with its own σ,
  weighed with the ranges in one least squares over (bearing, tilt, offset) where the two bearings agree
  within 3 σ of their difference (where they do not, one of them is fooled and the ranges alone stand).

Its error is the trace error of that fit (:func:`trace_error`); the ranges' fit alone is kept beside it
(``range_ls``) for reading.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lelsonar.reconstruct.estimate.constant_depth import constant_depth_ls
from lelsonar.reconstruct.estimate.surfaces.beam_pattern import bearing_from_amplitude
from lelsonar.sim.scan import EchoSource
from lelsonar.sim.world_render import WorldScan, pose_frame

__all__ = ["OracleError", "bearing_tilt", "oracle_error", "oracle_plane", "trace_error", "true_plane", "TRACE_HALF"]

#: Half the length of wall trace the error is measured over, m.
TRACE_HALF = 0.5
#: The smallest range σ the oracle weighs its ranges with, m (a perfect fit's residuals say nothing of it).
RANGE_SIGMA_FLOOR = 1e-4


def true_plane(scan: WorldScan, element: int) -> tuple[np.ndarray, float]:
    """The mirror element's plane in the array frame, normal pointing away from the scanner."""
    model = scan.model
    surf = model.surfaces[model.elements[element].surfaces[0]]
    rot, tr = pose_frame(scan.rig, scan.pose)
    n = rot.T @ surf.normal
    h = float(surf.normal @ (surf.center - tr))
    if h < 0:
        n, h = -n, -h
    return n, h


def trace_error(normal: np.ndarray, offset: float, n_true: np.ndarray, h_true: float) -> float:
    """Largest distance of the fitted plane from the true one over the true trace ±TRACE_HALF of the foot, m.

    The trace runs in the fan (perpendicular to the stack x and to the normal).
    """
    foot = h_true * n_true
    along = np.cross(np.array([1.0, 0.0, 0.0]), n_true)
    nrm = float(np.linalg.norm(along))
    along = along / nrm if nrm > 1e-9 else np.array([0.0, 1.0, 0.0])
    pts = foot[None, :] + np.array([-TRACE_HALF, 0.0, TRACE_HALF])[:, None] * along[None, :]
    return float(np.max(np.abs(pts @ normal - offset)))


def bearing_tilt(normal: np.ndarray) -> tuple[float, float]:
    """A normal's bearing in the fan and tilt along the stack, rad (the surfaces' convention)."""
    return math.atan2(float(normal[2]), float(normal[1])), math.asin(max(-1.0, min(1.0, float(normal[0]))))


def _normal(bearing: float, tilt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``n(β, t)`` and its derivatives along β and t."""
    cb, sb, ct, st = math.cos(bearing), math.sin(bearing), math.cos(tilt), math.sin(tilt)
    return (
        np.array([st, ct * cb, ct * sb]),
        np.array([0.0, -ct * sb, ct * cb]),
        np.array([ct, -st * cb, -st * sb]),
    )


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def weighted_plane_ls(
    capsules: np.ndarray,
    distance: np.ndarray,
    start: tuple[float, float, float],
    range_sigma: float,
    bearing: tuple[float, float] | None = None,
    *,
    max_iter: int = 50,
    tol: float = 1e-12,
) -> tuple[float, float, float, np.ndarray]:
    """Least squares over (bearing β, tilt t, offset h) of the mirror condition, with a bearing measurement.

    Minimises ``Σ ((n(β, t) · p_i + d_i − h) / σ_r)² + ((β − β_m) / σ_m)²`` by Gauss-Newton, where
    ``n(β, t) = (sin t, cos t cos β, cos t sin β)``.

    Parameters
    ----------
    capsules : (N, 3) array
        Each reading's capsule position, m.
    distance : (N,) array
        Ranges, m.
    start : (β, t, h)
        rad, rad, m.
    range_sigma : float
        σ_r of one range, m.
    bearing : (β_m, σ_m) or None
        The bearing measurement, rad; None: the ranges alone.

    Returns
    -------
    β, t, h and their covariance ``(JᵀJ)⁻¹`` (3 × 3) at the solution.
    """
    p = np.asarray(capsules, dtype=np.float64)
    d = np.asarray(distance, dtype=np.float64)
    b, t, h = start
    jac = np.zeros((d.size + 1, 3))
    for _ in range(max_iter):
        n, dn_b, dn_t = _normal(b, t)
        res = np.empty(d.size + 1)
        res[:-1] = (p @ n + d - h) / range_sigma
        jac[:-1, 0] = (p @ dn_b) / range_sigma
        jac[:-1, 1] = (p @ dn_t) / range_sigma
        jac[:-1, 2] = -1.0 / range_sigma
        if bearing is None:
            res[-1] = 0.0
            jac[-1] = 0.0
        else:
            res[-1] = _wrap(b - bearing[0]) / bearing[1]
            jac[-1] = (1.0 / bearing[1], 0.0, 0.0)
        z, *_ = np.linalg.lstsq(jac, -res, rcond=None)
        b, t, h = b + float(z[0]), t + float(z[1]), h + float(z[2])
        if float(np.abs(z).max()) < tol:
            break
    return _wrap(b), t, h, np.linalg.pinv(jac.T @ jac)


@dataclass(frozen=True)
class OracleError:
    """The oracle's trace errors, m: its fit's, and the ranges' least squares alone (for reading)."""

    error: float
    range_ls: float
    used_beam: bool  # the beam pattern's bearing weighed in


def _true_echoes(scan: WorldScan, element: int) -> tuple[np.ndarray, np.ndarray]:
    mask = (scan.echo_index == element) & (scan.echo_source != EchoSource.DIFFUSE) & np.isfinite(scan.distance)
    rows, caps = np.nonzero(mask)
    return rows, caps


def oracle_plane(
    scan: WorldScan, element: int, amplitude: np.ndarray | None = None
) -> tuple[np.ndarray, float, np.ndarray, float, bool]:
    """The oracle's plane of one mirror from its true echoes (the module's docstring says how).

    Parameters
    ----------
    scan : WorldScan
    element : int
        The mirror element.
    amplitude : (n_steps, n_capsules) array, optional
        Each echo's peak amplitude (:func:`lelsonar.signal.energy.echo_amplitude`); without it the ranges
        alone.

    Returns
    -------
    normal, offset (the oracle's fit), the ranges' LS normal and offset, and whether the beam pattern's
    bearing was weighed in.
    """
    rows, caps = _true_echoes(scan, element)
    p = scan.geometry.capsule_positions(scan.gamma_measured[rows])[np.arange(rows.size), caps]
    d = scan.distance[rows, caps]
    g = scan.gamma_measured[rows]
    # A truth-free start: the echoes' beams' mean direction, no tilt, the median depth along it.
    b0 = math.atan2(float(np.mean(np.sin(g))), float(np.mean(np.cos(g))))
    n0, _, _ = _normal(b0, 0.0)
    n_ls, h_ls, _ = constant_depth_ls(p, d, n0, float(np.median(d + p @ n0)))
    if amplitude is None or rows.size < 4:
        return n_ls, h_ls, n_ls, h_ls, False
    resid = p @ n_ls + d - h_ls
    sigma = max(math.sqrt(float(resid @ resid) / max(rows.size - 3, 1)), RANGE_SIGMA_FLOOR)
    b_ls, t_ls = bearing_tilt(n_ls)
    _, _, _, cov = weighted_plane_ls(p, d, (b_ls, t_ls, h_ls), sigma, max_iter=1)
    # Each step's echo amplitude: the median over the capsules that hold this mirror's echo.
    steps, at = np.unique(rows, return_inverse=True)
    amp = amplitude[rows, caps]
    per_step = np.array([float(np.median(amp[at == k])) for k in range(steps.size)])
    beam = bearing_from_amplitude(scan.gamma_measured[steps], per_step)
    if beam is None or not beam[1] > 0:
        return n_ls, h_ls, n_ls, h_ls, False
    if abs(_wrap(beam[0] - b_ls)) > 3.0 * math.hypot(beam[1], math.sqrt(max(float(cov[0, 0]), 0.0))):
        return n_ls, h_ls, n_ls, h_ls, False
    b, t, h, _ = weighted_plane_ls(p, d, (beam[0], t_ls, h_ls), sigma, beam)
    return _normal(b, t)[0], h, n_ls, h_ls, True


def oracle_error(scan: WorldScan, element: int, amplitude: np.ndarray | None = None) -> OracleError:
    """The oracle's trace errors for one mirror (:func:`oracle_plane`), m."""
    n_true, h_true = true_plane(scan, element)
    n, h, n_ls, h_ls, used = oracle_plane(scan, element, amplitude)
    return OracleError(trace_error(n, h, n_true, h_true), trace_error(n_ls, h_ls, n_true, h_true), used)
