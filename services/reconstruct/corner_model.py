"""The whole L explains every echo: a joint model of both walls and their edge.

The paper splits the scan at the energy peak and fits each half on its own,
treating the corner's double-bounce echoes as outliers.  That breaks when a
half holds more corner echoes than wall echoes (a sweep that covers little of
a wall, a far wall, a corner at an unusual angle): the corner echoes all share
one range, the distance to the edge, so the mirror-echo condition fits them for
*any* normal and LEL locks onto them (its breakdown point is 35–45 % one-sided
outliers, design notes §9).

Here the corner echoes are signal.  Two walls ``n_a·x = h_a``, ``n_b·x = h_b``
predict every echo a capsule at ``p_c`` can return (design notes §8):

* a mirror echo from wall ``k`` at range ``h_k − n_k·p_c``, if the wall's normal
  lies within the beam;
* the double bounce from the edge where the walls meet, at the distance from
  ``p_c`` to that line, if the edge lies within the beam;
* or an outlier.

Hypotheses are the dense bands of the mirror-implied wall position
``w = n₀·p_c + d`` (``n₀`` the paper's assumed axis of each wall, §4), so no
random sampling is needed and the result is deterministic.  Each pair of bands
is refined by alternating assignment (each echo to the model that explains it
best) and a joint Gauss-Newton over both walls, the edge's echoes tying them
together, then scored with the MSAC cost over *all* echoes.  The true pair explains the wall echoes of both walls and the
corner cluster through the edge; a pair that mistakes the corner cluster for a
wall leaves the real wall's echoes unexplained and its edge explains nothing.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from lelsonar.geometry import ArrayGeometry, boresight, rotation_x

from .fit import fast_median

__all__ = [
    "ScanPoints",
    "Wall",
    "CornerModel",
    "scan_points",
    "mirror_residuals",
    "edge_line",
    "edge_residuals",
    "assign_echoes",
    "edge_shared_share",
    "joint_residuals",
    "joint_gauss_newton",
    "band_offsets",
    "fit_corner_model",
    "ECHO_WALL_A",
    "ECHO_WALL_B",
    "ECHO_EDGE",
    "ECHO_OUTLIER",
]

ECHO_WALL_A, ECHO_WALL_B, ECHO_EDGE, ECHO_OUTLIER = 0, 1, 2, -1


@dataclass(frozen=True)
class ScanPoints:
    """Every valid echo of a scan, flattened.

    Attributes
    ----------
    step : (N,) int array
    capsule_index : (N,) int array
    gamma : (N,) array, rad
    capsule : (N, 3) array
        Capsule position ``p_c`` of the echo, m.
    distance : (N,) array
        Range ``d``, m.
    beam : (N, 3) array
        Unit boresight.
    """

    step: np.ndarray
    capsule_index: np.ndarray
    gamma: np.ndarray
    capsule: np.ndarray
    distance: np.ndarray
    beam: np.ndarray

    @property
    def n(self) -> int:
        return int(self.distance.shape[0])


@dataclass(frozen=True)
class Wall:
    """A plane ``normal · x = offset`` (unit normal away from the scanner, m)."""

    normal: np.ndarray
    offset: float


@dataclass(frozen=True)
class CornerModel:
    """The best joint explanation of a scan's echoes.

    Attributes
    ----------
    wall_a, wall_b : Wall
    labels : (N,) int array
        :data:`ECHO_WALL_A`, :data:`ECHO_WALL_B`, :data:`ECHO_EDGE` or
        :data:`ECHO_OUTLIER` for each echo of the :class:`ScanPoints`.
    residuals : (N,) array
        Range residual of each echo under its label's model, m (NaN for outliers).
    tolerance : float
        Inlier tolerance of the final assignment, m.
    cost : float
        MSAC cost of the final walls over all echoes (m²), lower is better.
    hypotheses : int
        Band pairs tried.
    covariance : (6, 6) array
        Of the tangent-plane tilt ``(u₁, u₂)`` (rad) and offset (m) of wall a,
        then wall b, from the joint least squares (``inf`` where unconstrained).
    outside : (bool, bool)
        Whether the joint fit of wall a / b wanted to leave the ``max_tilt``
        window around its nominal axis (the wall returned is held inside it,
        so it is not the best fit: see :func:`fit_corner_model`).
    """

    wall_a: Wall
    wall_b: Wall
    labels: np.ndarray
    residuals: np.ndarray
    tolerance: float
    cost: float
    hypotheses: int
    covariance: np.ndarray
    outside: tuple[bool, bool] = (False, False)

    def wall_stderr(self, k: int) -> tuple[float, float]:
        """RMS tilt (rad) and offset standard error (m) of wall ``k`` (0 = a, 1 = b)."""
        c = self.covariance[3 * k:3 * k + 3, 3 * k:3 * k + 3]
        if not np.all(np.isfinite(c)):
            return float("inf"), float("inf")
        return float(np.sqrt(max(c[0, 0] + c[1, 1], 0.0))), float(np.sqrt(max(c[2, 2], 0.0)))

    def count(self, label: int) -> int:
        return int(np.count_nonzero(self.labels == label))


def scan_points(geometry: ArrayGeometry, gamma: np.ndarray, distance: np.ndarray) -> ScanPoints:
    """Flatten the valid echoes of a scan (finite, positive ranges)."""
    g = np.asarray(gamma, dtype=np.float64)
    d = np.asarray(distance, dtype=np.float64)
    pc = geometry.capsule_positions(g)
    b = np.broadcast_to(boresight(g)[:, None, :], pc.shape)
    ok = np.isfinite(d) & (d > 0)
    steps = np.broadcast_to(np.arange(g.shape[0])[:, None], d.shape)
    caps = np.broadcast_to(np.arange(d.shape[1])[None, :], d.shape)
    gg = np.broadcast_to(g[:, None], d.shape)
    return ScanPoints(steps[ok].astype(np.intp), caps[ok].astype(np.intp), gg[ok], pc[ok], d[ok], b[ok])


def mirror_residuals(wall: Wall, pts: ScanPoints) -> np.ndarray:
    """Residual of the mirror-echo condition ``n·p_c + d − h`` of every echo, m (design notes §8)."""
    return pts.capsule @ wall.normal + pts.distance - wall.offset


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    # np.cross costs ~20 µs of argument handling per call; this is on the solver's hot path.  Python floats
    # round exactly as NumPy scalars do, at a fraction of the cost per operation.
    a0, a1, a2 = np.asarray(a).tolist()
    b0, b1, b2 = np.asarray(b).tolist()
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


def edge_line(wall_a: Wall, wall_b: Wall, min_angle: float = np.deg2rad(20.0)
              ) -> tuple[np.ndarray, np.ndarray] | None:
    """Point (nearest the origin) and unit direction of the line where two walls meet.

    With ``e = n_a × n_b`` the point is ``(h_a (n_b × e) + h_b (e × n_a)) / |e|²``.
    None if the walls are within ``min_angle`` of parallel (no corner).
    """
    e = _cross(wall_a.normal, wall_b.normal)
    s2 = float(e @ e)
    if s2 < np.sin(min_angle) ** 2:
        return None
    # h_a (n_b × e) + h_b (e × n_a), element by element in Python floats: the NumPy expression's roundings.
    ha, hb = wall_a.offset, wall_b.offset
    point = np.array([(ha * u + hb * v) / s2 for u, v in zip(_cross(wall_b.normal, e).tolist(),
                                                              _cross(e, wall_a.normal).tolist())])
    return point, e / np.sqrt(s2)


def edge_residuals(point: np.ndarray, direction: np.ndarray, pts: ScanPoints,
                   opening: float = np.pi / 2) -> tuple[np.ndarray, np.ndarray]:
    """Range residual of the double bounce, ``d − ρ·sin(opening)`` (m), and the unit direction to the edge.

    Two reflections in a dihedral of interior angle ``opening`` rotate the
    capsule's image by ``2·opening`` about the edge, so the echo returns from
    ``ρ·sin(opening)``, ρ the capsule's distance to the edge line — exactly ρ
    for a 90° corner, which retro-reflects (design notes §8).
    """
    rel = point - pts.capsule
    perp = rel - (rel @ direction)[:, None] * direction  # np.outer, the same products
    dist = np.sqrt(np.einsum("ij,ij->i", perp, perp))
    return pts.distance - dist * np.sin(opening), perp / np.maximum(dist, 1e-9)[:, None]


def _edge_range_residuals(wall_a: Wall, wall_b: Wall, capsule: np.ndarray, distance: np.ndarray) -> np.ndarray:
    return _edge_range_residuals_many(((wall_a, wall_b),), capsule, distance)[0]


def _edge_range_residuals_many(pairs: tuple[tuple[Wall, Wall], ...], capsule: np.ndarray,
                               distance: np.ndarray) -> np.ndarray:
    """:func:`edge_residuals`' range residual under each pair of walls, (len(pairs), N), m.

    One pass over the echoes for all pairs (the Jacobian's six forward differences).  Row ``k``
    is bit for bit what the pair alone gives: stacked ``matmul`` and ``einsum`` form each
    echo's products and sums exactly as the 2-D ones do.
    """
    points, directions, sines, parallel = [], [], [], []
    for k, (wall_a, wall_b) in enumerate(pairs):
        line = edge_line(wall_a, wall_b, min_angle=0.0)
        if line is None:  # parallel walls: no edge, no double bounce
            parallel.append(k)
            line = (np.zeros(3), np.zeros(3))
        points.append(line[0])
        directions.append(line[1])
        sines.append(np.sin(_opening(wall_a, wall_b)))
    rel = np.array(points)[:, None, :] - capsule[None, :, :]
    t = (rel @ np.array(directions)[:, :, None])[:, :, 0]
    dist2 = np.einsum("kij,kij->ki", rel, rel) - t * t
    out = distance - np.sqrt(np.maximum(dist2, 0.0)) * np.array(sines)[:, None]
    if parallel:
        out[parallel] = np.inf
    return out


def _opening(wall_a: Wall, wall_b: Wall) -> float:
    """Interior angle of the dihedral that holds the scanner (both normals point out of it), rad."""
    c = min(max(float(wall_a.normal @ wall_b.normal), -1.0), 1.0)  # np.clip, without its dispatch
    return float(np.pi - np.arccos(c))


def assign_echoes(wall_a: Wall, wall_b: Wall, pts: ScanPoints, tolerance: float,
                  beam_half_angle: float, edge_tolerance: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Give each echo to the model that explains it best, within ``tolerance``.

    A wall can explain an echo only if its normal is within ``beam_half_angle``
    of the boresight, the edge only if the edge is; an echo no model explains
    within ``tolerance`` (m) is an outlier.  ``edge_tolerance`` (default
    ``tolerance``) applies to the edge: wider while the walls are still rough,
    since a pitch error δ moves the edge by about ``h·δ``.

    Returns
    -------
    labels : (N,) int array
    residuals : (N,) array, m (NaN for outliers)
    """
    cos_t = np.cos(beam_half_angle)
    r = np.full((3, pts.n), np.inf)
    for k, wall in enumerate((wall_a, wall_b)):
        rk = mirror_residuals(wall, pts)
        r[k] = np.where(pts.beam @ wall.normal >= cos_t, rk, np.inf)
    line = edge_line(wall_a, wall_b)
    if line is not None:
        re, u = edge_residuals(*line, pts, _opening(wall_a, wall_b))
        r[2] = np.where(np.einsum("ij,ij->i", pts.beam, u) >= cos_t, re, np.inf)
    best = np.argmin(np.abs(r), axis=0)
    res = r[best, np.arange(pts.n)]
    tol = np.where(best == ECHO_EDGE, tolerance if edge_tolerance is None else edge_tolerance, tolerance)
    labels = np.where(np.abs(res) <= tol, best, ECHO_OUTLIER)
    return labels, np.where(labels == ECHO_OUTLIER, np.nan, res)


def edge_shared_share(model: CornerModel, pts: ScanPoints, label: int, beam_half_angle: float) -> float:
    """Share of the echoes labelled ``label`` that another part of the model explains as well, within tolerance.

    For a wall the other part is the edge; for :data:`ECHO_EDGE` it is either
    wall.  A wall's mirror echoes and the corner's double bounces differ in
    range by ``ρ·sin(opening) − (h − n·p_c)``, the capsule's distance to the
    edge less its distance to the wall.  Where the edge lies close to the foot
    of the wall's normal (a near wall beside a far one, an opening far from
    90°), that difference falls inside the assignment tolerance and the two
    explanations cannot be told apart: a wall's offset may rest on corner
    echoes, and an "edge" may be a wall's own echoes that tie nothing together.

    Returns 0 for a label without echoes or a model without an edge.
    """
    mask = model.labels == label
    line = edge_line(model.wall_a, model.wall_b)
    if not np.any(mask) or line is None:
        return 0.0
    sub = ScanPoints(pts.step[mask], pts.capsule_index[mask], pts.gamma[mask], pts.capsule[mask],
                     pts.distance[mask], pts.beam[mask])
    cos_t = np.cos(beam_half_angle)
    if label == ECHO_EDGE:
        shared = np.zeros(sub.n, dtype=bool)
        for wall in (model.wall_a, model.wall_b):
            shared |= (sub.beam @ wall.normal >= cos_t) & (np.abs(mirror_residuals(wall, sub)) <= model.tolerance)
        return float(np.mean(shared))
    re, u = edge_residuals(*line, sub, _opening(model.wall_a, model.wall_b))
    seen = np.einsum("ij,ij->i", sub.beam, u) >= cos_t
    return float(np.mean(seen & (np.abs(re) <= model.tolerance)))


def _msac_cost(residuals: np.ndarray, tolerance: float) -> float:
    r = np.where(np.isfinite(residuals), residuals, tolerance)
    return float(np.sum(np.minimum(r * r, tolerance * tolerance)))


def band_offsets(w: np.ndarray, *, bin_width: float = 0.01, max_bands: int = 4, min_count: int = 6) -> np.ndarray:
    """Centres of the densest bands of mirror-implied wall positions ``w`` (m), densest first.

    A wall seen near face-on puts its echoes at ``w ≈ h`` whatever the step;
    the corner cluster makes a band at the edge's distance.  Peaks of the
    smoothed histogram (bins of ``bin_width``) with at least ``min_count``
    echoes, each refined as the median of ``w`` within 2 bins (the smoothing
    turns a one-bin spike into a three-bin plateau whose right end is the peak).
    """
    w = np.asarray(w, dtype=np.float64)
    w = w[np.isfinite(w)]
    if w.size < min_count:
        return np.zeros(0)
    lo, hi = float(w.min()), float(w.max())
    nb = max(int(np.ceil((hi - lo) / bin_width)), 1)
    counts, edges = np.histogram(w, bins=nb, range=(lo, lo + nb * bin_width))
    padded = np.concatenate([[0], counts, [0]])
    smooth = padded[:-2] + padded[1:-1] + padded[2:]  # np.convolve(np.pad(counts, 1), [1, 1, 1], "valid"): exact counts
    left = np.concatenate([[-1], smooth[:-1]])
    right = np.concatenate([smooth[1:], [-1]])
    peaks = np.flatnonzero((smooth >= left) & (smooth > right) & (smooth >= min_count))
    peaks = peaks[np.argsort(-smooth[peaks], kind="stable")][:max_bands]
    centres = []
    for p in peaks:
        c = 0.5 * (edges[p] + edges[p + 1])
        near = np.abs(w - c) <= 2.0 * bin_width
        if np.any(near):
            centres.append(fast_median(w[near]))
    return np.asarray(centres)


def _tangent(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    helper = np.zeros(3)
    helper[int(np.argmin(np.abs(n)))] = 1.0
    e1 = _cross(n, helper)
    e1 /= np.sqrt(e1 @ e1)
    return e1, _cross(n, e1)


def _moved(wall: Wall, z: np.ndarray, basis: tuple[np.ndarray, np.ndarray]) -> Wall:
    # Element by element in Python floats: the same roundings as the NumPy expression
    # wall.normal + z[0] * basis[0] + z[1] * basis[1], at a fraction of its dispatch cost.
    z0, z1, z2 = np.asarray(z).tolist()
    n = np.array([w + z0 * b0 + z1 * b1 for w, b0, b1 in zip(wall.normal.tolist(), basis[0].tolist(),
                                                              basis[1].tolist())])
    return Wall(n / np.sqrt(n @ n), wall.offset + z2)


def joint_residuals(wall_a: Wall, wall_b: Wall, pts: ScanPoints, labels: np.ndarray) -> np.ndarray:
    """Range residuals (m) of the labelled echoes under their models: wall a, wall b, then the edge."""
    ma, mb, me = labels == ECHO_WALL_A, labels == ECHO_WALL_B, labels == ECHO_EDGE
    return np.concatenate([pts.capsule[ma] @ wall_a.normal + pts.distance[ma] - wall_a.offset,
                           pts.capsule[mb] @ wall_b.normal + pts.distance[mb] - wall_b.offset,
                           _edge_range_residuals(wall_a, wall_b, pts.capsule[me], pts.distance[me])])


def joint_gauss_newton(wall_a: Wall, wall_b: Wall, pts: ScanPoints, labels: np.ndarray, *, iterations: int = 3,
                       step: float = 1e-7, covariance: bool = True) -> tuple[tuple[Wall, Wall], np.ndarray]:
    """Least squares of all labelled echoes over both walls at once (6 parameters).

    Each wall is ``n = normalise(n₀ + u₁e₁ + u₂e₂)``, ``h``; the edge echoes tie
    the two walls together through their intersection, which pins down the
    pitch that each wall's own echoes (a few-cm lever arm) barely constrain.
    Levenberg-damped Gauss-Newton; the mirror rows' Jacobian is exact
    (``∂r/∂u = p_c·e``, ``∂r/∂h = −1``), the edge rows' by forward differences.

    Returns the walls and the (6, 6) covariance of ``(u₁, u₂, h)`` of wall a
    then wall b (``σ² (JᵀJ)⁻¹``, σ² from the residuals; ``inf`` if
    unconstrained or not asked for with ``covariance=False``).
    """
    ma, mb, me = labels == ECHO_WALL_A, labels == ECHO_WALL_B, labels == ECHO_EDGE
    pa, da = pts.capsule[ma], pts.distance[ma]
    pb, db = pts.capsule[mb], pts.distance[mb]
    pe, de = pts.capsule[me], pts.distance[me]
    na_, nb_, ne_ = len(da), len(db), len(de)
    m = na_ + nb_ + ne_
    walls = [wall_a, wall_b]
    eye = np.eye(3)

    def residuals(wa: Wall, wb: Wall) -> np.ndarray:
        return np.concatenate([pa @ wa.normal + da - wa.offset, pb @ wb.normal + db - wb.offset,
                               _edge_range_residuals(wa, wb, pe, de)])

    def residuals_many(pairs: list[tuple[Wall, Wall]]) -> list[np.ndarray]:
        # residuals() of each pair, bit for bit, the edge rows of all pairs in one pass.
        edge = _edge_range_residuals_many(tuple(pairs), pe, de)
        return [np.concatenate([pa @ wa.normal + da - wa.offset, pb @ wb.normal + db - wb.offset, edge[k]])
                for k, (wa, wb) in enumerate(pairs)]

    def jacobian(wa: Wall, wb: Wall, r: np.ndarray) -> tuple[np.ndarray, list]:
        basis = [_tangent(wa.normal), _tangent(wb.normal)]
        jac = np.zeros((m, 6))
        for k, (p, lo, hi) in enumerate(((pa, 0, na_), (pb, na_, na_ + nb_))):
            jac[lo:hi, 3 * k] = p @ basis[k][0]
            jac[lo:hi, 3 * k + 1] = p @ basis[k][1]
            jac[lo:hi, 3 * k + 2] = -1.0
        if ne_:
            re = r[na_ + nb_:]
            pairs = []
            for j in range(6):
                k, z = divmod(j, 3)
                moved = [wa, wb]
                moved[k] = _moved(moved[k], step * eye[z], basis[k])
                pairs.append(tuple(moved))
            jac[na_ + nb_:, :] = ((_edge_range_residuals_many(tuple(pairs), pe, de) - re) / step).T
        return jac, basis

    cov = np.full((6, 6), np.inf)
    if m < 7:
        return (wall_a, wall_b), cov
    lam = 1e-6
    r = residuals(*walls)
    for _ in range(iterations):
        if not np.all(np.isfinite(r)):
            return (wall_a, wall_b), cov
        jac, basis = jacobian(walls[0], walls[1], r)
        jtj, g, c0 = jac.T @ jac, jac.T @ r, float(r @ r)
        accepted = False
        for attempt in range(6):
            if attempt == 1:
                # The first damping failed (near convergence, usually all six do): the remaining five trials
                # do not depend on each other's outcome, so they are formed in one pass, then taken in order.
                batch = _damped_trials(jtj, g, lam, 5, walls, basis, residuals_many)
                if batch is not None:
                    for trial, r1, lam_k in batch:
                        if np.all(np.isfinite(r1)) and float(r1 @ r1) <= c0:
                            walls, r, lam, accepted = trial, r1, max(lam_k / 10, 1e-9), True
                            break
                    break
            try:
                dz = np.linalg.solve(jtj + lam * np.diag(np.diag(jtj) + 1e-12), -g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            trial = [_moved(walls[0], dz[:3], basis[0]), _moved(walls[1], dz[3:], basis[1])]
            r1 = residuals(*trial)
            if np.all(np.isfinite(r1)) and float(r1 @ r1) <= c0:
                walls, r, lam, accepted = trial, r1, max(lam / 10, 1e-9), True
                break
            lam *= 10
        if not accepted:
            break
    if not covariance:
        return (walls[0], walls[1]), cov
    jac, _ = jacobian(walls[0], walls[1], r)
    try:
        cov = float(r @ r) / (m - 6) * np.linalg.inv(jac.T @ jac)
    except np.linalg.LinAlgError:
        pass
    return (walls[0], walls[1]), cov


def _damped_trials(jtj: np.ndarray, g: np.ndarray, lam: float, count: int, walls: list[Wall],
                   basis: list[tuple[np.ndarray, np.ndarray]],
                   residuals_many: Callable[[list[tuple[Wall, Wall]]], list[np.ndarray]]
                   ) -> list[tuple[list[Wall], np.ndarray, float]] | None:
    """The Levenberg steps of :func:`joint_gauss_newton` for damping ``lam``, ``10·lam``, … (``count`` of them).

    Each as the one-at-a-time loop forms it (the same damping products, ``np.linalg.solve``
    per matrix of the stack): ``(walls, residuals, damping)`` in order.  None if a damped
    matrix is singular (the caller takes the trials one at a time, skipping it).
    """
    lams = []
    for _ in range(count):
        lams.append(lam)
        lam *= 10
    diag = np.diag(np.diag(jtj) + 1e-12)
    try:
        dz = np.linalg.solve(np.stack([jtj + lk * diag for lk in lams]), np.broadcast_to(-g, (count, g.size))[..., None])
    except np.linalg.LinAlgError:
        return None
    trials = [[_moved(walls[0], d[:3, 0], basis[0]), _moved(walls[1], d[3:, 0], basis[1])] for d in dz]
    return [(t, r1, lk) for t, r1, lk in zip(trials, residuals_many([tuple(t) for t in trials]), lams)]


def _refine(wall_a: Wall, wall_b: Wall, pts: ScanPoints, tolerances: tuple[tuple[float, float], ...],
            beam_half_angle: float, min_points: int, axes: tuple[np.ndarray, np.ndarray],
            max_tilt: float) -> tuple[Wall, Wall]:
    for tol, tol_edge in tolerances:
        labels, _ = assign_echoes(wall_a, wall_b, pts, tol, beam_half_angle, tol_edge)
        for k in (ECHO_WALL_A, ECHO_WALL_B):
            if np.count_nonzero(labels == k) < min_points:
                labels = np.where(labels == k, ECHO_OUTLIER, labels)  # too few to move this wall
        (na, nb), _ = joint_gauss_newton(wall_a, wall_b, pts, labels, iterations=1, covariance=False)
        # Keep each wall within max_tilt of its nominal axis: beyond, the solver is chasing the other
        # wall's or the edge's echoes.
        if na.normal @ axes[0] >= np.cos(max_tilt) and na.offset > 0:
            wall_a = na
        if nb.normal @ axes[1] >= np.cos(max_tilt) and nb.offset > 0:
            wall_b = nb
    return wall_a, wall_b


def fit_corner_model(pts: ScanPoints, axis_a: np.ndarray, axis_b: np.ndarray, *,
                     beam_half_angle: float = np.deg2rad(50.0), tolerance: float = 0.02,
                     max_bands: int = 3, max_refined: int = 4, min_points: int = 8,
                     max_tilt: float = np.deg2rad(15.0), good_enough: float = 0.02,
                     recentre: int = 3, significance: float = 3.0) -> CornerModel | None:
    """The two walls and their edge that best explain all the echoes.

    Parameters
    ----------
    pts : ScanPoints
    axis_a, axis_b : (3,) arrays
        The walls' nominal normals (the paper's ``y`` and ``z``); hypotheses
        start there and are refined freely.
    beam_half_angle : float
        rad.  Largest angle between a boresight and a wall normal (or the
        direction to the edge) at which an echo is accepted; wide, since it
        only rules explanations out.
    tolerance : float
        m.  Inlier tolerance of the scoring (MSAC) and the final assignment:
        several times the range noise plus what a few degrees of tilt spread.
    max_bands : int
        Bands tried per wall.
    max_refined : int
        Band pairs refined (the lowest-cost ones at the loosest tolerance).
    min_points : int
        Fewest echoes a wall is refitted on.
    max_tilt : float
        rad.  Largest angle between a wall's normal and its nominal axis.
    good_enough : float
        Stop trying band pairs once one leaves at most this share of the
        echoes unexplained.
    significance : float
        A joint fit beyond ``max_tilt`` counts as leaving the window only if
        its angle from the axis exceeds this many of its standard errors
        (else the ranges cannot place the wall and the window stands).
    recentre : int
        How many times the nominal axes may follow a joint fit that leaves
        them by more than ``max_tilt``.  A common roll of the L about the
        rotation axis (a robot not square to the corner) moves both walls off
        the paper's axes together; the ranges still see it through the
        capsules' radial lever arm, so the joint fit points there.  When both
        walls' fits turn the same way (their rolls about x within ``max_tilt``
        of each other), both axes are turned about x by the mean roll and the
        model refitted; the refit is kept only if it explains the echoes
        better (lower MSAC cost over all echoes).  Walls pulled apart — one
        onto the corner cluster, which looks like a wall facing the edge —
        are not followed.

    Returns
    -------
    CornerModel, or None if neither wall has a band of echoes.  ``outside``
    says which walls' joint fit still wanted to leave the ``max_tilt`` window
    (their returned walls are held at the window and their covariance is
    ``inf``: the model cannot place them).
    """
    cos_t = np.cos(beam_half_angle)
    axis_a = np.asarray(axis_a, dtype=np.float64) / np.linalg.norm(axis_a)
    axis_b = np.asarray(axis_b, dtype=np.float64) / np.linalg.norm(axis_b)
    candidates = []
    for axis in (axis_a, axis_b):
        seen = pts.beam @ axis >= cos_t
        w = pts.capsule[seen] @ axis + pts.distance[seen]
        candidates.append([Wall(np.asarray(axis, dtype=np.float64), float(h))
                           for h in band_offsets(w, max_bands=max_bands, min_count=min_points) if h > 0])
    hyps = [(a, b) for a in candidates[0] for b in candidates[1]]
    if not hyps:
        return None
    schedule = ((2.5 * tolerance, 8 * tolerance), (1.5 * tolerance, 3 * tolerance), (tolerance, tolerance))
    if len(hyps) > max_refined:
        # Rank by the MSAC cost at the loosest stage (the nominal normals are off by up to the tilt), refine the best.
        loose = [_msac_cost(assign_echoes(a, b, pts, schedule[0][0], beam_half_angle, schedule[0][1])[1],
                            schedule[0][0]) for a, b in hyps]
        hyps = [hyps[i] for i in np.argsort(loose, kind="stable")[:max_refined]]
    best: tuple[float, Wall, Wall, np.ndarray, np.ndarray] | None = None
    for a, b in hyps:
        wa, wb = _refine(a, b, pts, schedule, beam_half_angle, min_points, (axis_a, axis_b), max_tilt)
        labels, res = assign_echoes(wa, wb, pts, tolerance, beam_half_angle)
        cost = _msac_cost(res, tolerance)
        if best is None or cost < best[0]:
            best = (cost, wa, wb, labels, res)
        if np.count_nonzero(labels == ECHO_OUTLIER) <= good_enough * pts.n:
            break  # the most promising pair already explains (nearly) every echo: no other can do better
    cost, wa, wb, labels, res = best  # the assignment is a pure function of the walls: kept, not redone
    (fa, fb), cov = joint_gauss_newton(wa, wb, pts, labels, iterations=2)
    outside = tuple(_leaves_window(f, axis, cov[3 * k:3 * k + 2, 3 * k:3 * k + 2], max_tilt, significance)
                    for k, (f, axis) in enumerate(((fa, axis_a), (fb, axis_b))))
    if fa.normal @ axis_a >= np.cos(max_tilt) and fb.normal @ axis_b >= np.cos(max_tilt):
        wa, wb = fa, fb
        labels, res = assign_echoes(wa, wb, pts, tolerance, beam_half_angle)
    elif any(outside):
        # The covariance belongs to (fa, fb), not to the walls held at the window: it would overclaim.
        cov = np.full((6, 6), np.inf)
    model = CornerModel(wa, wb, labels, res, tolerance, _msac_cost(res, tolerance), len(hyps), cov, outside)
    roll_a, roll_b = _roll(fa.normal, axis_a), _roll(fb.normal, axis_b)
    # Only a turn of the whole L moves the axes: both walls turning the same way by about as much.  Walls
    # pulled apart (one onto the corner cluster, which looks like a wall facing the edge) stay flagged.
    if any(outside) and recentre > 0 and abs(roll_a - roll_b) <= max_tilt:
        rho = 0.5 * (roll_a + roll_b)
        turn = rotation_x(rho)
        moved = fit_corner_model(pts, turn @ axis_a, turn @ axis_b, beam_half_angle=beam_half_angle,
                                 tolerance=tolerance, max_bands=max_bands, max_refined=max_refined,
                                 min_points=min_points, max_tilt=max_tilt, good_enough=good_enough,
                                 recentre=recentre - 1, significance=significance)
        if moved is not None and moved.cost < model.cost:
            return moved
    return model


def _leaves_window(wall: Wall, axis: np.ndarray, tilt_cov: np.ndarray, max_tilt: float, significance: float) -> bool:
    """Whether a fitted wall lies beyond ``max_tilt`` of its axis *and* the echoes say so.

    A wall whose tilt the ranges barely constrain (capsules almost on the axis: no lever arm) can land
    anywhere; its departure is evidence only if it exceeds ``significance`` times its own standard error.
    """
    angle = float(np.arccos(np.clip(wall.normal @ axis, -1.0, 1.0)))
    se = float(np.sqrt(max(tilt_cov[0, 0] + tilt_cov[1, 1], 0.0))) if np.all(np.isfinite(tilt_cov)) else np.inf
    return angle > max_tilt and angle > significance * se


def _roll(normal: np.ndarray, axis: np.ndarray) -> float:
    """Signed angle about x from ``axis`` to ``normal``, both projected onto the rotation plane (y, z), rad."""
    return float(np.angle(complex(normal[1], normal[2]) * complex(axis[1], -axis[2])))
