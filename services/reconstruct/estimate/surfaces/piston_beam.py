"""The sweep's beam as a piston: its ``ka`` and σ, from the amplitude profiles of the regions that hold their peak.

Every echo of a rotating transceiver follows ``D(γ − β)²`` across γ.  The piston's ``ka`` comes from the same
sweep's uncut regions (:func:`sweep_beam`), fitted with the piston over their whole profiles: a parabola fitted
over a top alone overstates ``ka`` by a few %, which on a far flank is degrees.  The fits themselves are
:func:`~.piston.piston_lm`'s: every profile of a sweep's planes in one compiled Levenberg–Marquardt call.

Pure functions: no I/O, no state.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lelsonar.reconstruct.estimate.surfaces.beam_pattern import PLATEAU, amplitude_jump
from lelsonar.reconstruct.estimate.surfaces.measurement import Measured, step_table
from lelsonar.reconstruct.estimate.surfaces.piston import Profiles, piston_lm
from lelsonar.signal.directivity import PISTON_FIRST_NULL

__all__ = [
    "MODEL_MISFIT",
    "SweepBeam",
    "log_profile",
    "piston_fit",
    "piston_fits",
    "sweep_beam",
]

#: Fewest steps with an amplitude a piston fit of a whole profile needs (three parameters, and their residuals).
MIN_PROFILE_STEPS = 8
#: How far under its peak a profile is fitted, in log amplitude: 20 dB, clear of the first null and sidelobe.
MAIN_LOBE_TOP = math.log(10.0)
#: A profile's residual σ over its amplitude noise beyond which the piston does not describe the beam.
MODEL_MISFIT = 3.0


@dataclass(frozen=True)
class SweepBeam:
    """The sweep's beam as a piston: ``ka`` and its σ, from its uncut regions' amplitude profiles."""

    ka: float
    ka_stderr: float
    n_regions: int


def log_profile(gamma: np.ndarray, amplitude: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The steps with an unclipped echo, in γ order: γ and ``log A`` (a plateau of three or more steps at the
    region's largest value is the receiver clipping: those steps are lower bounds and are left out)."""
    g = np.asarray(gamma, dtype=np.float64)
    a = np.asarray(amplitude, dtype=np.float64)
    ok = np.isfinite(a) & (a > 0)
    if ok.any():
        top = a >= (1.0 - PLATEAU) * float(np.max(a[ok]))
        if np.count_nonzero(top & ok) >= 3:
            ok &= ~top
    g, la = g[ok], np.log(a[ok])
    order = np.argsort(g)
    return g[order], la[order]


def _main_lobe_top(g: np.ndarray, la: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A profile's steps within 20 dB of its peak (:data:`MAIN_LOBE_TOP`): a strong near echo stays over the
    receiver's threshold into the nulls and the first sidelobe (35 dB down, two-way), where no smooth lobe
    describes it."""
    if not g.size:
        return g, la
    top = la >= float(la.max()) - MAIN_LOBE_TOP
    return g[top], la[top]


def piston_fits(
    profiles: list[tuple[np.ndarray, np.ndarray]], bearing: np.ndarray, ka0: np.ndarray
) -> list[tuple[float, float] | None]:
    """:func:`piston_fit` of several profiles, fitted together (:func:`~.piston.piston_lm`).

    Parameters
    ----------
    profiles : list of (γ, log A)
        Each profile's unclipped steps in γ order (``log_profile``).
    bearing, ka0 : (R,) arrays
        Each profile's start.

    Returns
    -------
    Per profile, ``(ka, σ)`` or None, as :func:`piston_fit` gives them.
    """
    out: list[tuple[float, float] | None] = [None] * len(profiles)
    tops = [_main_lobe_top(*profile) for profile in profiles]
    rows = [i for i, (g, _la) in enumerate(tops) if g.size >= MIN_PROFILE_STEPS and ka0[i] > 0]
    if not rows:
        return out
    p = Profiles.pack([tops[i] for i in rows])
    fit = piston_lm(
        p, np.asarray(bearing, dtype=np.float64)[rows], np.asarray(ka0, dtype=np.float64)[rows], free_ka=True
    )
    inside = ~np.any(p.w & (fit.ka[:, None] * np.abs(np.sin(p.g - fit.bearing[:, None])) >= PISTON_FIRST_NULL), axis=1)
    s2 = fit.cost / np.maximum(p.n - 3, 1)
    noise = p.noise()
    with np.errstate(invalid="ignore"):
        misfit = np.isfinite(noise) & (noise > 0) & (np.sqrt(s2) > MODEL_MISFIT * noise)
    # ka's variance: the last diagonal entry of (JᵀJ)⁻¹, its cofactor over its determinant, at the residuals' scale.
    a = np.einsum("rki,rkj->rij", fit.jacobian, fit.jacobian)
    with np.errstate(divide="ignore", invalid="ignore"):
        var = s2 * (a[:, 0, 0] * a[:, 1, 1] - a[:, 0, 1] * a[:, 1, 0]) / np.linalg.det(a)
    for j, i in enumerate(rows):
        if fit.ok[j] and fit.ka[j] > 0 and inside[j] and not misfit[j] and np.isfinite(var[j]):
            out[i] = float(fit.ka[j]), math.sqrt(max(float(var[j]), 0.0))
    return out


def piston_fit(gamma: np.ndarray, amplitude: np.ndarray, bearing: float, ka0: float) -> tuple[float, float] | None:
    """``ka`` of the piston whose two-way pattern ``A = P·D(γ − β)²`` fits one whole echo profile, and its σ.

    Least squares in ``log A`` over ``(log P, β, ka)`` (:func:`piston_lm`), from the region's bearing and a
    first ``ka``, over the steps within 20 dB of the region's peak (:data:`MAIN_LOBE_TOP`).

    Parameters
    ----------
    gamma, amplitude : (k,) arrays
        An uncut region's steps' γ (rad) and echo amplitudes (NaN: none).
    bearing : float
        The region's bearing, rad (its centre or its peak).
    ka0 : float
        A first guess of ``ka``.

    Returns
    -------
    (ka, σ), or None when too few steps have an amplitude, the fit leaves the main lobe, or its residuals
    exceed the amplitudes' own noise by more than :data:`MODEL_MISFIT` (no piston).
    """
    return piston_fits([log_profile(gamma, amplitude)], np.array([bearing]), np.array([ka0]))[0]


def sweep_beam(measured: list[Measured], gamma: np.ndarray, amplitude: np.ndarray, ka0: float) -> SweepBeam | None:
    """The sweep's piston ``ka``, from its planes' regions that hold their echo's peak and the profile about it:
    their bearing their centre or their peak (a clipped top left out), one beam pattern (no amplitude jump, and
    no end where another echo at a like range took over: it sums into the profile there).
    A mirror's echo follows the beam alone; a corner's or an edge's adds its own change with the angle, so only
    planes are passed.

    Each region's steps' median profile gives its ``ka``; each capsule's own profile gives one too, started
    from its region's.  Another echo summed into the amplitude window (a wall's double bounce with the floor,
    a few mm deeper) bends a profile smoothly, which its residuals do not show, and it adds with a phase that
    differs from capsule to capsule (their paths differ by wavelengths): the capsules' ``ka`` spread by as much
    as the summing bends them.  The regions are fitted together (:func:`piston_fits`), then their capsules.

    Parameters
    ----------
    measured : list of Measured
        The sweep's planes.
    gamma : (n_steps,) array
        The sweep's γ, rad.
    amplitude : (n_steps, n_capsules) array
        The sweep's echo amplitudes, V (NaN: none).
    ka0 : float
        A first guess (``2√k`` of the sweep's beam curvature ``k``).

    Returns
    -------
    The median of the regions' ``ka``; its σ the largest of the capsules' spread (standard deviation over every
    region's capsules, not shrunk by their count: a bent profile is biased, not noisy), the regions' spread and
    the median of their own fits' σ.  None when no region gives one.
    """
    regions = [
        m
        for m in measured
        if m.bearing_source in ("region centre", "amplitude peak")
        and not any(m.handed_over)
        and amplitude_jump(gamma[m.region.steps], m.step_amplitude) is None
    ]
    if not regions:
        return None
    steps = [gamma[m.region.steps] for m in regions]
    fits = piston_fits(
        [log_profile(g, m.step_amplitude) for g, m in zip(steps, regions, strict=True)],
        np.array([m.bearing for m in regions]),
        np.full(len(regions), ka0),
    )
    kas = [f[0] for f in fits if f is not None]
    ses = [f[1] for f in fits if f is not None]
    if not kas:
        return None
    own, starts = [], []
    for g, m, f in zip(steps, regions, fits, strict=True):
        if f is None:
            continue
        table = step_table(m.region, amplitude)
        for c in range(table.shape[1]):
            own.append(log_profile(g, table[:, c]))
            starts.append((m.bearing, f[0]))
    start = np.array(starts).reshape(-1, 2)
    capsules = [f[0] for f in piston_fits(own, start[:, 0], start[:, 1]) if f is not None]
    spread = max(
        float(np.std(kas, ddof=1)) if len(kas) >= 2 else 0.0,
        float(np.std(capsules, ddof=1)) if len(capsules) >= 2 else 0.0,
    )
    return SweepBeam(ka=float(np.median(kas)), ka_stderr=max(spread, float(np.median(ses))), n_regions=len(kas))
