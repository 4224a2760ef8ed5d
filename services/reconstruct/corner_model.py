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
    "edge_range_terms",
    "echo_residuals",
    "assign_echoes",
    "edge_shared_shares",
    "edge_implied_offsets",
    "edge_alternatives",
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


def edge_range_terms(normal_a: np.ndarray, offset_a: float, normal_b: np.ndarray, offset_b: float,
                     capsule: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """The range of the double bounce from the edge of two walls, in closed form (design notes §8).

    Two reflections in a dihedral of interior angle ``opening`` rotate the
    capsule's image by ``2·opening`` about the edge, so the echo returns from
    ``ρ·sin(opening)``, ρ the capsule's distance to the edge line — exactly ρ
    for a 90° corner, which retro-reflects.  With ``a = h_a − n_a·p_c`` and
    ``b = h_b − n_b·p_c`` the capsule's distances to the walls and
    ``c = n_a·n_b``, the vector from the capsule to the edge is
    ``v = α n_a + β n_b`` with ``α + βc = a``, ``αc + β = b``, so
    ``ρ² = |v|² = (a² + b² − 2abc)/(1 − c²)``; the opening's sine is
    ``√(1 − c²)``, so the double bounce returns from ``√(a² + b² − 2abc)``.

    Returns
    -------
    a, b : (N,) arrays, m
    c : float
    range : (N,) array
        ``ρ·sin(opening) = √(a² + b² − 2abc)``, m.
    """
    da = offset_a - capsule @ normal_a
    db = offset_b - capsule @ normal_b
    c = float(normal_a @ normal_b)
    return da, db, c, np.sqrt(np.maximum(da * da + db * db - 2.0 * c * da * db, 0.0))


def _edge_range_residuals(wall_a: Wall, wall_b: Wall, capsule: np.ndarray, distance: np.ndarray,
                          min_sine: float = 1e-9) -> np.ndarray:
    """The double bounce's range residual ``d − ρ·sin(opening)`` (m, :func:`edge_range_terms`).

    ``inf`` for walls within ``min_sine`` of parallel: no edge, no double bounce.
    """
    *_, c, rng = edge_range_terms(wall_a.normal, wall_a.offset, wall_b.normal, wall_b.offset, capsule)
    if 1.0 - c * c < min_sine * min_sine:
        return np.full(distance.shape, np.inf)
    return distance - rng


def echo_residuals(wall_a: Wall, wall_b: Wall, pts: ScanPoints, beam_half_angle: float,
                   min_angle: float = np.deg2rad(20.0)) -> np.ndarray:
    """Range residual of every echo under each part of the model, (3, N), m: wall a, wall b, the edge.

    A wall's is the mirror-echo condition ``n·p_c + d − h``, the edge's
    ``d − ρ·sin(opening)`` (:func:`edge_range_terms`).  ``inf`` where that
    part cannot have returned the echo: a wall whose normal lies beyond
    ``beam_half_angle`` of the boresight, an edge whose direction from the
    capsule (``v = α n_a + β n_b``, ``α = (a − bc)/(1 − c²)``,
    ``β = (b − ac)/(1 − c²)``) does, or no edge at all (walls within
    ``min_angle`` of parallel, as :func:`edge_line`).
    """
    n = pts.n
    normals = np.array([wall_a.normal, wall_b.normal]).T
    facing = pts.beam @ normals  # (N, 2): boresight · n_a, boresight · n_b
    cos_t = np.cos(beam_half_angle)
    a, b, c, rng = edge_range_terms(wall_a.normal, wall_a.offset, wall_b.normal, wall_b.offset, pts.capsule)
    r = np.full((3, n), np.inf)
    r[0] = np.where(facing[:, 0] >= cos_t, pts.distance - a, np.inf)
    r[1] = np.where(facing[:, 1] >= cos_t, pts.distance - b, np.inf)
    s2 = 1.0 - c * c
    if s2 >= np.sin(min_angle) ** 2:
        # boresight · v/|v| ≥ cos_t, multiplied through by |v|·(1 − c²) = √q·√(1 − c²) ≥ 0.
        toward = (a - b * c) * facing[:, 0] + (b - a * c) * facing[:, 1]
        r[2] = np.where(toward >= cos_t * np.sqrt(s2) * rng, pts.distance - rng, np.inf)
    return r


def assign_echoes(wall_a: Wall, wall_b: Wall, pts: ScanPoints, tolerance: float,
                  beam_half_angle: float, edge_tolerance: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Give each echo to the model that explains it best, within ``tolerance``.

    A wall can explain an echo only if its normal is within ``beam_half_angle``
    of the boresight, the edge only if the edge is (:func:`echo_residuals`); an
    echo no model explains within ``tolerance`` (m) is an outlier.
    ``edge_tolerance`` (default ``tolerance``) applies to the edge: wider while
    the walls are still rough, since a pitch error δ moves the edge by about ``h·δ``.

    Returns
    -------
    labels : (N,) int array
    residuals : (N,) array, m (NaN for outliers)
    """
    r = echo_residuals(wall_a, wall_b, pts, beam_half_angle)
    best = np.argmin(np.abs(r), axis=0)
    res = r[best, np.arange(pts.n)]
    tol = np.where(best == ECHO_EDGE, tolerance if edge_tolerance is None else edge_tolerance, tolerance)
    labels = np.where(np.abs(res) <= tol, best, ECHO_OUTLIER)
    return labels, np.where(labels == ECHO_OUTLIER, np.nan, res)


def edge_shared_shares(model: CornerModel, pts: ScanPoints, beam_half_angle: float) -> tuple[float, float, float]:
    """Share of each part's echoes that another part of the model explains as well, within tolerance.

    For a wall the other part is the edge; for the edge it is either wall.  A
    wall's mirror echoes and the corner's double bounces differ in range by
    ``ρ·sin(opening) − (h − n·p_c)``, the capsule's distance to the edge less
    its distance to the wall.  Where the edge lies close to the foot of the
    wall's normal (a near wall beside a far one, an opening far from 90°),
    that difference falls inside the assignment tolerance and the two
    explanations cannot be told apart: a wall's offset may rest on corner
    echoes, and an "edge" may be a wall's own echoes that tie nothing together.

    Returns
    -------
    The shares of the echoes labelled :data:`ECHO_WALL_A`, :data:`ECHO_WALL_B`
    and :data:`ECHO_EDGE`, in that order (indexable by the labels); 0 for a
    label without echoes, and all 0 for a model without an edge.
    """
    if edge_line(model.wall_a, model.wall_b) is None:
        return 0.0, 0.0, 0.0
    close = np.abs(echo_residuals(model.wall_a, model.wall_b, pts, beam_half_angle)) <= model.tolerance
    shares = []
    for label, shared in ((ECHO_WALL_A, close[2]), (ECHO_WALL_B, close[2]), (ECHO_EDGE, close[0] | close[1])):
        mask = model.labels == label
        shares.append(float(np.mean(shared[mask])) if np.any(mask) else 0.0)
    return shares[0], shares[1], shares[2]


def edge_implied_offsets(other: Wall, normal: np.ndarray, capsule: np.ndarray, distance: np.ndarray) -> np.ndarray:
    """Offset of the wall facing ``normal`` that would make each echo a double bounce off its edge with ``other``, m.

    The inverse of :func:`edge_range_terms` for one wall (design notes §8):
    with ``a`` the capsule's distance to ``other`` and ``c`` the normals' dot
    product, a double bounce returns from ``d = √(a² + x² − 2acx)``, so the
    capsule's distance to the wall is ``x = ac + √(d² − a²(1 − c²))`` (the
    root beyond the edge's foot) and the offset is ``x + n·p_c``.
    """
    a = other.offset - capsule @ other.normal
    c = float(other.normal @ normal)
    x = a * c + np.sqrt(np.maximum(distance * distance - a * a * (1.0 - c * c), 0.0))
    return x + capsule @ normal


def edge_alternatives(model: CornerModel, pts: ScanPoints, beam_half_angle: float, min_points: int = 8
                      ) -> tuple[tuple[float, int], tuple[float, int]]:
    """How well the other explanation of each wall's echoes, as the corner's double bounces, does.

    Where the edge lies near the foot of a wall's normal (a far wall beside a
    near one), the double bounces return a few centimetres from where that
    wall's mirror echoes would, and vary with the capsule almost as they do:
    the corner cluster passes for the wall, and the model's own edge
    (:func:`edge_shared_shares`) then lies beside the cluster, not on it.  The
    alternative keeps the other wall and this wall's normal and moves this wall
    to the median offset at which its echoes are the edge's
    (:func:`edge_implied_offsets`); every echo is then assigned afresh.  When
    the alternative's edge takes most of the wall's echoes and it explains
    about as many echoes as the model does, the ranges cannot tell the wall
    from the cluster.  A real wall beside a real corner cluster is told apart:
    the alternative moves the wall past the cluster, whose echoes it then
    leaves unexplained.

    Returns
    -------
    For wall a, then wall b: the share of its echoes the alternative's edge
    explains, and how many more echoes the model explains than the
    alternative (``(0.0, 0)`` for a wall with fewer than ``min_points``
    echoes, or no edge).
    """
    out = []
    explained = int(np.count_nonzero(model.labels != ECHO_OUTLIER))
    walls = (model.wall_a, model.wall_b)
    for k in (ECHO_WALL_A, ECHO_WALL_B):
        mk = model.labels == k
        if np.count_nonzero(mk) < min_points or edge_line(*walls) is None:
            out.append((0.0, 0))
            continue
        h = fast_median(edge_implied_offsets(walls[1 - k], walls[k].normal, pts.capsule[mk], pts.distance[mk]))
        pair = list(walls)
        pair[k] = Wall(walls[k].normal, float(h))
        labels, _ = assign_echoes(pair[0], pair[1], pts, model.tolerance, beam_half_angle)
        out.append((float(np.mean(labels[mk] == ECHO_EDGE)), explained - int(np.count_nonzero(labels != ECHO_OUTLIER))))
    return out[0], out[1]


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
    # Bin k holds lo + k·bin_width ≤ w < lo + (k + 1)·bin_width (the top bin its right end too).
    counts = np.bincount(np.minimum(((w - lo) / bin_width).astype(np.intp), nb - 1), minlength=nb)
    padded = np.concatenate([[0], counts, [0]])
    smooth = padded[:-2] + padded[1:-1] + padded[2:]  # np.convolve(np.pad(counts, 1), [1, 1, 1], "valid"): exact counts
    left = np.concatenate([[-1], smooth[:-1]])
    right = np.concatenate([smooth[1:], [-1]])
    peaks = np.flatnonzero((smooth >= left) & (smooth > right) & (smooth >= min_count))
    peaks = peaks[np.argsort(-smooth[peaks], kind="stable")][:max_bands]
    centres = []
    for p in peaks:
        c = lo + (p + 0.5) * bin_width
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


def joint_residuals(wall_a: Wall, wall_b: Wall, pts: ScanPoints, labels: np.ndarray) -> np.ndarray:
    """Range residuals (m) of the labelled echoes under their models: wall a, wall b, then the edge."""
    ma, mb, me = labels == ECHO_WALL_A, labels == ECHO_WALL_B, labels == ECHO_EDGE
    return np.concatenate([pts.capsule[ma] @ wall_a.normal + pts.distance[ma] - wall_a.offset,
                           pts.capsule[mb] @ wall_b.normal + pts.distance[mb] - wall_b.offset,
                           _edge_range_residuals(wall_a, wall_b, pts.capsule[me], pts.distance[me])])


def joint_gauss_newton(wall_a: Wall, wall_b: Wall, pts: ScanPoints, labels: np.ndarray, *, iterations: int = 3,
                       covariance: bool = True, trials: int = 6,
                       min_sine: float = 1e-9) -> tuple[tuple[Wall, Wall], np.ndarray]:
    """Least squares of all labelled echoes over both walls at once (6 parameters).

    Each wall is ``n = normalise(n₀ + u₁e₁ + u₂e₂)``, ``h``; the edge echoes tie
    the two walls together through their intersection, which pins down the
    pitch that each wall's own echoes (a few-cm lever arm) barely constrain.
    Levenberg-damped Gauss-Newton (up to ``trials`` dampings, ×10 each) with
    the exact Jacobian: ``∂r/∂u = p_c·e``, ``∂r/∂h = −1`` for the mirror rows,
    and for the edge rows ``r = d − √q``, ``q = a² + b² − 2abc``
    (:func:`edge_range_terms`), ``∂r/∂u_a = (p_c·e)(a − bc)/√q + (ab/√q)(n_b·e)``,
    ``∂r/∂h_a = −(a − bc)/√q`` and the same for wall b with a and b swapped.

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
    cov = np.full((6, 6), np.inf)
    if m < 7:
        return (wall_a, wall_b), cov
    lo_e = na_ + nb_

    def residuals(w: _Pair) -> np.ndarray:
        r = np.empty(m)
        r[:na_] = pa @ w[0] + da - w[1]
        r[na_:lo_e] = pb @ w[2] + db - w[3]
        if ne_:
            *_, c, rng = edge_range_terms(*w, pe)
            r[lo_e:] = de - rng if 1.0 - c * c >= min_sine * min_sine else np.inf
        return r

    def jacobian(w: _Pair) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
        basis = (np.array(_tangent(w[0])).T, np.array(_tangent(w[2])).T)  # (3, 2): e₁, e₂ of each wall
        jac = np.empty((m, 6))
        jac[:na_, 0:2] = pa @ basis[0]
        jac[:na_, 2] = -1.0
        jac[:na_, 3:6] = 0.0
        jac[na_:lo_e, 0:3] = 0.0
        jac[na_:lo_e, 3:5] = pb @ basis[1]
        jac[na_:lo_e, 5] = -1.0
        if ne_:
            a, b, c, rng = edge_range_terms(*w, pe)
            inv = 1.0 / np.maximum(rng, 1e-12)
            ga, gb, gab = (a - b * c) * inv, (b - a * c) * inv, a * b * inv
            jac[lo_e:, 0:2] = (pe @ basis[0]) * ga[:, None] + gab[:, None] * (w[2] @ basis[0])
            jac[lo_e:, 2] = -ga
            jac[lo_e:, 3:5] = (pe @ basis[1]) * gb[:, None] + gab[:, None] * (w[0] @ basis[1])
            jac[lo_e:, 5] = -gb
        return jac, basis

    def moved(w: _Pair, dz: np.ndarray, basis: tuple[np.ndarray, np.ndarray]) -> _Pair:
        n_a = w[0] + basis[0] @ dz[0:2]
        n_b = w[2] + basis[1] @ dz[3:5]
        return n_a / np.sqrt(n_a @ n_a), w[1] + float(dz[2]), n_b / np.sqrt(n_b @ n_b), w[3] + float(dz[5])

    w: _Pair = (wall_a.normal, float(wall_a.offset), wall_b.normal, float(wall_b.offset))
    lam = 1e-6
    r = residuals(w)
    for _ in range(iterations):
        if not np.all(np.isfinite(r)):
            return (wall_a, wall_b), cov
        jac, basis = jacobian(w)
        jtj, g, c0 = jac.T @ jac, jac.T @ r, float(r @ r)
        damping = np.diag(np.diag(jtj) + 1e-12)
        accepted = False
        for _attempt in range(trials):
            try:
                dz = np.linalg.solve(jtj + lam * damping, -g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            trial = moved(w, dz, basis)
            r1 = residuals(trial)
            if np.all(np.isfinite(r1)) and float(r1 @ r1) <= c0:
                w, r, lam, accepted = trial, r1, max(lam / 10, 1e-9), True
                break
            lam *= 10
        if not accepted:
            break
    walls = (Wall(w[0], w[1]), Wall(w[2], w[3]))
    if not covariance:
        return walls, cov
    jac, _ = jacobian(w)
    try:
        cov = float(r @ r) / (m - 6) * np.linalg.inv(jac.T @ jac)
    except np.linalg.LinAlgError:
        pass
    return walls, cov


#: Two walls as arrays: normal and offset of wall a, then of wall b.
_Pair = tuple[np.ndarray, float, np.ndarray, float]


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
