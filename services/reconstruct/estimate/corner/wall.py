"""Each wall's final plane and its per-wall checks: refined on its own echoes (:func:`corner_wall`), or fitted
alone where the model found one wall (:func:`single_wall`), and the echoes that are its own
(:func:`wall_echoes`)."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from lelsonar.errors import InternalError
from lelsonar.geometry import ArrayGeometry
from lelsonar.reconstruct.estimate import fit as F
from lelsonar.reconstruct.estimate.corner.model import (
    CornerModel,
    ScanPoints,
    Wall,
    band_offsets,
    echo_residuals,
    mirror_residuals,
)
from lelsonar.reconstruct.estimate.corner.pitch import (
    amplitude_pitch,
    fixed_pitch_wall,
)
from lelsonar.reconstruct.estimate.estimators import diagnostics
from lelsonar.reconstruct.estimate.options import FitOptions
from lelsonar.reconstruct.estimate.quality import (
    assess_plane,
    unexplained_finding,
)
from lelsonar.reconstruct.estimate.results import PlaneFit, PlaneResult
from lelsonar.signal.compiled import kernel
from lelsonar.signal.energy import ECHO_PEAK_WINDOW


class WallFit(NamedTuple):
    """A wall of the joint model refined on its own echoes (:func:`corner_wall`).

    Attributes
    ----------
    plane : PlaneFit or FitFailure
    joint_direction : bool
        Its direction is the joint fit's: neither its amplitudes nor the corrected points placed it.
    against_joint : bool
        Its echoes' amplitudes put its direction beyond what the joint fit's σ allows: the joint fit is off.
    """

    plane: PlaneResult
    joint_direction: bool
    against_joint: bool


def corner_wall(
    data: F.PlaneData,
    wall: Wall,
    wall_se: tuple[float, float],
    opts: FitOptions,
    t0: float,
    note: str,
    amplitude: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None,
    flags: list[str],
    edge_is_walls: bool = False,
    max_disagreement: float = np.deg2rad(10.0),
    walk_se=lambda: 0.0,
    tie_suspect: bool = False,
    common_roll: float = 0.0,
) -> WallFit:
    """One wall of the joint model, refined on its own echoes (:class:`WallFit`).

    With the echoes' own amplitudes, the wall's direction in the rotation
    plane comes from where they are strongest (:func:`amplitude_pitch`) and
    its yaw and offset from the ranges (:func:`fixed_pitch_wall`): unbiased
    whatever the tilt, and as precise as the corrected points on axis-aligned
    walls.  It is kept only if it agrees with the joint model's direction
    (unbiased, if imprecise) within ``opts.tilt_test_sigma`` of their combined
    standard error: a later echo leaking into the amplitudes would pull the
    peak off the wall's normal.

    Without them (no waveforms, or the peak outside the sweep): the
    paper-corrected points (§4) give the most precise normal when the wall is
    axis-aligned; the joint model (mirror and edge echoes together) is
    unbiased whatever the tilt.  If the LS normal of the corrected points
    (eq. 15) agrees with the joint normal within ``opts.tilt_test_sigma`` of the
    joint standard error, keep it with the offset from the mirror-echo
    condition, and standard errors the joint model's at least (the corrected
    points cannot see a tilt below that, so their own covariance would
    overclaim); otherwise keep the joint wall with the joint model's standard
    errors (its edge echoes tie the direction; the wall's own echoes alone
    would overstate them).

    ``amplitude`` holds the wall's echoes as ``(gamma, peak amplitude,
    distance, capsules)``, or None.  Reasons to call the plane unreliable are
    appended to ``flags``: corrected points and joint fit more than
    ``max_disagreement`` (rad) apart both as they are and with the corrected
    points turned about x by ``common_roll`` (rad: the L's roll as the other
    wall's joint fit shows it, which the corrected points cannot see); a direction that rests on the joint fit
    while the model's edge echoes are mostly a wall's as well
    (``edge_is_walls``: the edge that ties the walls' directions together
    was not identified).  ``walk_se()`` (rad, :func:`~lelsonar.reconstruct.estimate.corner.pitch.walk_stderr`;
    asked only here) is added in quadrature to the joint normal's
    standard error where the direction rests on the ranges (the amplitudes place it free of any walk).
    ``tie_suspect``: the other wall's echoes may be the corner cluster's, so the edge that ties this wall's
    direction to it may be wrong; the joint wall then reports the standard errors of its own echoes at
    least (the joint covariance assumes the tie).

    Besides the plane it says whether the plane's direction is the joint fit's and whether the wall's
    amplitudes contradict the joint fit (:class:`WallFit`): the edge ties the two walls' joint directions
    together, so a joint fit one wall contradicts may have turned the other wall too.
    """
    mask = np.ones(data.n, dtype=bool)
    se_joint, se_h_joint = wall_se
    fitted = None
    against_joint = False
    if amplitude is not None and (pitch := amplitude_pitch(*amplitude[:3])) is not None:
        phi, phi_se = pitch
        fitted, se_n, se_h = fixed_pitch_wall(amplitude[3], amplitude[2], phi, phi_se, wall.normal)
        off = float(np.arccos(min(max(float(fitted.normal @ wall.normal), -1.0), 1.0)))
        if not (math.isfinite(se_joint) and off <= opts.tilt_test_sigma * np.hypot(se_joint, se_n)):
            fitted = None
            if math.isfinite(se_joint):
                against_joint = True
                # The amplitudes are the only sensor of the wall's direction in the rotation plane that a
                # common roll cannot fool; a joint fit they contradict has not found that direction.
                flags.append(
                    f"its echoes are strongest at γ = {np.rad2deg(phi):.1f}°, {np.rad2deg(off):.1f}° from "
                    f"the joint fit's normal (over {opts.tilt_test_sigma:g}σ)"
                )
    if fitted is not None:
        diag = diagnostics(
            "corner model; amplitude pitch; gauss-newton",
            t0,
            notes=(
                note,
                f"echoes strongest at γ = {np.rad2deg(phi):.2f}° ± {np.rad2deg(phi_se):.2f}°: "
                "the wall's direction; yaw and offset from the ranges",
            ),
        )
        pitched = F.make_plane_fit(
            data,
            fitted.normal / fitted.offset,
            method="corner",
            inlier_mask=mask,
            diagnostics=diag,
            model="constant-depth",
            stderr=(se_n, se_h),
        )
        return WallFit(pitched, False, False)
    if edge_is_walls:
        flags.append(
            "its direction rests on edge echoes that a wall explains as well: the corner edge that ties "
            "the walls together was not identified"
        )
    theta_p = F.ls_theta(data.points)
    n_p = theta_p / np.linalg.norm(theta_p)
    walk = walk_se()
    se_n, se_h = float(np.hypot(se_joint, walk)), se_h_joint
    angle = float(np.arccos(min(max(float(n_p @ wall.normal), -1.0), 1.0)))
    # The test is the joint fit's own: a walk that may have turned it does not make the roll-blind
    # corrected points more likely right; it only widens what either may miss by.
    agree = math.isfinite(se_joint) and angle <= opts.tilt_test_sigma * se_joint
    # The corrected points take the wall's direction in the rotation plane from the axis they assume (§4; a
    # roll ρ of the wall moves them by r·ρ only, r the capsules' few-cm lever): on an L rolled about x they
    # sit the roll from the truth whatever the data.  So they disagree with the joint fit only if they do both
    # as they are (no roll) and turned by the L's roll as the other wall shows it: a wall turned apart from
    # the other (one taken for the corner cluster) still disagrees.
    # n_p turned about x by the roll: lelsonar.geometry.rotation_x's turn written out as one dot product on floats
    # (its one-angle path still builds a matrix and an array for the product)
    c, s = math.cos(common_roll), math.sin(common_roll)
    (p_x, p_y, p_z), (n_x, n_y, n_z) = n_p.tolist(), wall.normal.tolist()
    turned_cos = p_x * n_x + (c * p_y - s * p_z) * n_y + (s * p_y + c * p_z) * n_z
    turned = math.acos(min(max(turned_cos, -1.0), 1.0))
    apart = min(angle, turned)
    if agree:
        h = float(np.mean(data.capsules @ n_p + data.distance))
        theta, model = n_p / h, "paper"
    else:
        theta, model = wall.normal / wall.offset, "constant-depth"
        if apart > max_disagreement:
            # Neither can be trusted: a wall tilted this far is outside what the corrected points describe,
            # and a joint fit this far off its axis has likely taken the edge's echoes for the wall's.
            flags.append(
                f"its direction is ambiguous: the corrected points and the joint fit differ by "
                f"{np.rad2deg(angle):.1f}°, and by {np.rad2deg(turned):.1f}° "
                f"allowing for the {np.rad2deg(common_roll):.1f}° roll the other wall shows"
            )
    verdict = "corrected-points normal, mirror-echo offset" if agree else "joint-model wall"
    diag = diagnostics(
        "corner model; lstsq",
        t0,
        notes=(
            note,
            f"joint normal {np.rad2deg(angle):.2f}° from the "
            f"corrected-points normal ({np.rad2deg(apart):.2f}° allowing for "
            f"the L's roll; joint σ {np.rad2deg(se_n):.2f}°, of "
            f"which {np.rad2deg(walk):.2f}° for a walk with the "
            "echoes' amplitude) -> " + verdict,
        ),
    )
    fit = F.make_plane_fit(data, theta, method="corner", inlier_mask=mask, diagnostics=diag, model=model)
    if isinstance(fit, PlaneFit) and math.isfinite(se_n) and math.isfinite(se_h):
        if agree or tie_suspect:
            # The corrected points cannot see a roll below the joint fit's σ: their own covariance overclaims.
            # A joint wall tied to a suspect wall: the joint σ assumes a tie that may be wrong.
            se_n, se_h = max(fit.normal_stderr, se_n), max(fit.offset_stderr, se_h)
        # Else the joint wall's σ is the joint fit's: the edge's echoes tie its direction to the other wall's,
        # which the covariance of its own echoes alone (the direction through the capsules' few-cm radial
        # lever, eq. 9) leaves out, overstating it up to tens of degrees.
        fit = fit.replace_scalars(normal_stderr=se_n, offset_stderr=se_h)
    return WallFit(fit, not agree, against_joint)


def single_wall(
    pts: ScanPoints,
    gamma: np.ndarray,
    distance: np.ndarray,
    geometry: ArrayGeometry,
    label: str,
    axis: np.ndarray,
    opts: FitOptions,
    echo_amplitude: np.ndarray | None,
    t0: float,
) -> tuple[PlaneFit, F.PlaneData] | None:
    """One wall on its own, where the joint model found no pair of walls (a sweep that sees one wall only).

    The densest band of mirror-implied positions in the wall's window gives its echoes (assigned at the joint
    model's tolerances, loosest first); its direction in the rotation plane comes from where they are
    strongest (:func:`amplitude_pitch`), its yaw and offset from the ranges (:func:`fixed_pitch_wall`).  No
    edge ties it to anything, so without the amplitude peak inside the sweep there is no single-wall plane
    (None: the caller keeps its fallback).
    """
    if echo_amplitude is None:
        return None
    cos_t = np.cos(opts.corner_beam_half_angle)
    seen = pts.beam @ axis >= cos_t
    bands = band_offsets(pts.capsule[seen] @ axis + pts.distance[seen], max_bands=1, min_count=opts.min_points)
    if bands.size == 0 or bands[0] <= 0:
        return None
    amp = np.asarray(echo_amplitude, dtype=np.float64)[pts.step, pts.capsule_index]
    wall, se_n, se_h, m, phi = Wall(np.asarray(axis, dtype=np.float64), float(bands[0])), np.inf, np.inf, None, None
    tol = opts.corner_tolerance
    for t in (2.5 * tol, 1.5 * tol, tol):
        m = (pts.beam @ wall.normal >= cos_t) & (np.abs(mirror_residuals(wall, pts)) <= t)
        if np.count_nonzero(m) < opts.min_points:
            return None
        pitch = amplitude_pitch(pts.gamma[m], amp[m], pts.distance[m])
        if pitch is None:
            return None
        phi = pitch
        wall, se_n, se_h = fixed_pitch_wall(pts.capsule[m], pts.distance[m], pitch[0], pitch[1], wall.normal)
    if m is None or phi is None:
        raise InternalError("single_wall: the loop over the tolerances placed no wall (it runs at least once)")
    sel = np.full(distance.shape, np.nan)
    sel[pts.step[m], pts.capsule_index[m]] = pts.distance[m]
    data = F.plane_data(geometry, gamma, sel, np.unique(pts.step[m]), label, axis)
    diag = diagnostics(
        "corner model, one wall; amplitude pitch; gauss-newton",
        t0,
        notes=(
            f"no pair of walls: wall {label} alone on {int(np.count_nonzero(m))} echoes of its band",
            f"echoes strongest at γ = {np.rad2deg(phi[0]):.2f}° ± "
            f"{np.rad2deg(phi[1]):.2f}°: the wall's direction; yaw and offset from "
            "the ranges",
        ),
    )
    fit = F.make_plane_fit(
        data,
        wall.normal / wall.offset,
        method="corner",
        inlier_mask=np.ones(data.n, dtype=bool),
        diagnostics=diag,
        model="constant-depth",
        stderr=(se_n, se_h),
    )
    if not isinstance(fit, PlaneFit):
        return None
    unexplained = float(np.mean(~m[seen])) if np.any(seen) else 0.0
    return assess_plane(fit, gamma, edge_echoes=0, findings=unexplained_finding(unexplained)), data


#: Range the echo's amplitude window (:data:`~lelsonar.signal.energy.ECHO_PEAK_WINDOW`) spans beyond
#: the echo's own, m: half its length times a speed of sound at the warm end of a lab's (35 °C, ~352 m/s).
ECHO_WINDOW_RANGE = ECHO_PEAK_WINDOW[1] * 352.0 / 2.0


def edge_in_echo_window(
    model: CornerModel, pts: ScanPoints, beam_half_angle: float, residuals: np.ndarray | None = None
) -> np.ndarray:
    """Mask of the echoes whose amplitude window also holds the corner's double bounce.

    The double bounce returns from ``ρ·sin(opening)`` (eq. of
    :func:`~lelsonar.reconstruct.estimate.corner.model.edge_range_terms`), never nearer
    than either wall, and as strongly as a wall at that range; a far wall's mirror echo where the boresight also
    faces the edge is
    followed by it within centimetres, inside the window whose peak
    :func:`~lelsonar.signal.energy.echo_amplitude` takes.  That peak is
    then the corner's, and it pulls :func:`amplitude_pitch` toward the edge's
    direction.  ``residuals``: the model walls' :func:`~lelsonar.reconstruct.estimate.corner.model.echo_residuals`,
    if the caller has them.
    """
    if residuals is None:
        residuals = echo_residuals(model.wall_a, model.wall_b, pts, beam_half_angle)
    gap = -residuals[2]  # ρ·sin(opening) − d; inf: no edge
    return np.isfinite(gap) & (gap <= ECHO_WINDOW_RANGE)


def wall_echoes(
    labels: np.ndarray, k: int, leaks: np.ndarray, pts: ScanPoints, echo_amp: np.ndarray | None
) -> tuple[
    tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None
]:
    """The echoes labelled ``k``, as :func:`~lelsonar.reconstruct.estimate.fit.plane_data_of` takes them (capsules
    ``(n, 1, 3)``, boresights, ranges ``(n, 1)``, steps), and for :func:`corner_wall` the ``(γ, amplitude,
    range, capsule)`` of those whose amplitude window holds no double bounce (None without amplitudes)."""
    found = _gather_wall(
        labels,
        k,
        leaks,
        pts.step,
        pts.gamma,
        pts.capsule,
        pts.distance,
        pts.beam,
        np.zeros(0) if echo_amp is None else echo_amp,
        echo_amp is not None,
    )
    return found[:4], (None if echo_amp is None else found[4:])


@kernel
def _gather_wall(
    labels: np.ndarray,
    k: int,
    leaks: np.ndarray,
    step: np.ndarray,
    gamma: np.ndarray,
    capsule: np.ndarray,
    distance: np.ndarray,
    beam: np.ndarray,
    amplitude: np.ndarray,
    with_amplitude: bool,
):
    """:func:`wall_echoes` as one kernel (the same rows as boolean indexing, in order)."""
    n = 0
    n_own = 0
    for i in range(labels.shape[0]):
        if labels[i] == k:
            n += 1
            if with_amplitude and not leaks[i]:
                n_own += 1
    caps = np.empty((n, 1, 3))
    bm = np.empty((n, 3))
    dist = np.empty((n, 1))
    st = np.empty(n, dtype=np.intp)
    g_own = np.empty(n_own)
    a_own = np.empty(n_own)
    d_own = np.empty(n_own)
    c_own = np.empty((n_own, 3))
    j = 0
    o = 0
    for i in range(labels.shape[0]):
        if labels[i] != k:
            continue
        for u in range(3):
            caps[j, 0, u] = capsule[i, u]
            bm[j, u] = beam[i, u]
        dist[j, 0] = distance[i]
        st[j] = step[i]
        j += 1
        if with_amplitude and not leaks[i]:
            g_own[o], a_own[o], d_own[o] = gamma[i], amplitude[i], distance[i]
            for u in range(3):
                c_own[o, u] = capsule[i, u]
            o += 1
    return caps, bm, dist, st, g_own, a_own, d_own, c_own
