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
together, then scored with the MSAC cost over *all* echoes.  The true pair explains
the wall echoes of both walls and the corner cluster through the edge; a pair that mistakes the corner cluster for a
wall leaves the real wall's echoes unexplained and its edge explains nothing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lelsonar.geometry import ArrayGeometry, boresight, rotation_x
from lelsonar.reconstruct.estimate.fit import cross3, fast_median, tangent_basis, vector_norm
from lelsonar.reconstruct.estimate.lel import pairwise_sum
from lelsonar.signal.compiled import kernel

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
    "joint_residuals_arrays",
    "joint_gauss_newton_arrays",
    "labelled_order",
    "lu_solve",
    "roll_angle",
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
        # On Python floats (a 3×3 block: NumPy's calls would cost more than the arithmetic).
        c = self.covariance[3 * k : 3 * k + 3, 3 * k : 3 * k + 3].tolist()
        if not all(math.isfinite(x) for row in c for x in row):
            return float("inf"), float("inf")
        return math.sqrt(max(c[0][0] + c[1][1], 0.0)), math.sqrt(max(c[2][2], 0.0))

    def count(self, label: int) -> int:
        return int(np.count_nonzero(self.labels == label))


def scan_points(geometry: ArrayGeometry, gamma: np.ndarray, distance: np.ndarray) -> ScanPoints:
    """Flatten the valid echoes of a scan (finite, positive ranges)."""
    g = np.asarray(gamma, dtype=np.float64)
    d = np.ascontiguousarray(distance, dtype=np.float64)
    beam = boresight(g)
    return ScanPoints(*_valid_echoes(g, d, geometry.capsule_positions(g, beam), beam))


@kernel
def _valid_echoes(
    gamma: np.ndarray, distance: np.ndarray, capsules: np.ndarray, beam: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:class:`ScanPoints`' arrays: the echoes with a finite positive range, step-major (as boolean indexing)."""
    n_steps, n_caps = distance.shape
    n = 0
    for i in range(n_steps):
        for j in range(n_caps):
            if np.isfinite(distance[i, j]) and distance[i, j] > 0:
                n += 1
    step = np.empty(n, dtype=np.intp)
    capsule = np.empty(n, dtype=np.intp)
    g = np.empty(n)
    p = np.empty((n, 3))
    d = np.empty(n)
    b = np.empty((n, 3))
    k = 0
    for i in range(n_steps):
        for j in range(n_caps):
            if np.isfinite(distance[i, j]) and distance[i, j] > 0:
                step[k], capsule[k], g[k], d[k] = i, j, gamma[i], distance[i, j]
                for u in range(3):
                    p[k, u] = capsules[i, j, u]
                    b[k, u] = beam[i, u]
                k += 1
    return step, capsule, g, p, d, b


def mirror_residuals(wall: Wall, pts: ScanPoints) -> np.ndarray:
    """Residual of the mirror-echo condition ``n·p_c + d − h`` of every echo, m (design notes §8)."""
    return pts.capsule @ wall.normal + pts.distance - wall.offset


def edge_line(wall_a: Wall, wall_b: Wall, min_angle: float = np.deg2rad(20.0)) -> tuple[np.ndarray, np.ndarray] | None:
    """Point (nearest the origin) and unit direction of the line where two walls meet.

    With ``e = n_a × n_b`` the point is ``(h_a (n_b × e) + h_b (e × n_a)) / |e|²``.
    None if the walls are within ``min_angle`` of parallel (no corner).
    """
    point, direction, ok = _edge_line(
        np.asarray(wall_a.normal, dtype=np.float64),
        float(wall_a.offset),
        np.asarray(wall_b.normal, dtype=np.float64),
        float(wall_b.offset),
        math.sin(min_angle) ** 2,
    )
    return (point, direction) if ok else None


@kernel
def _edge_line(
    normal_a: np.ndarray, offset_a: float, normal_b: np.ndarray, offset_b: float, min_sine2: float
) -> tuple[np.ndarray, np.ndarray, bool]:
    """:func:`edge_line` on arrays (``min_sine2`` the sine² of its ``min_angle``); False: no edge."""
    e = cross3(normal_a, normal_b)
    s2 = e[0] * e[0] + e[1] * e[1] + e[2] * e[2]
    if s2 < min_sine2:
        return np.zeros(3), np.zeros(3), False
    u = cross3(normal_b, e)
    v = cross3(e, normal_a)
    point = np.empty(3)
    for j in range(3):  # h_a (n_b × e) + h_b (e × n_a), element by element
        point[j] = (offset_a * u[j] + offset_b * v[j]) / s2
    return point, e / np.sqrt(s2), True


@kernel
def edge_range_terms(
    normal_a: np.ndarray, offset_a: float, normal_b: np.ndarray, offset_b: float, capsule: np.ndarray
) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
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

    A kernel (:mod:`~lelsonar.signal.compiled`): the solver evaluates it
    at every step.

    Returns
    -------
    a, b : (N,) arrays, m
    c : float
    range : (N,) array
        ``ρ·sin(opening) = √(a² + b² − 2abc)``, m.
    """
    n = capsule.shape[0]
    da = np.empty(n)
    db = np.empty(n)
    rng = np.empty(n)
    c = normal_a[0] * normal_b[0] + normal_a[1] * normal_b[1] + normal_a[2] * normal_b[2]
    for i in range(n):
        a = offset_a - (capsule[i, 0] * normal_a[0] + capsule[i, 1] * normal_a[1] + capsule[i, 2] * normal_a[2])
        b = offset_b - (capsule[i, 0] * normal_b[0] + capsule[i, 1] * normal_b[1] + capsule[i, 2] * normal_b[2])
        da[i] = a
        db[i] = b
        rng[i] = np.sqrt(max(a * a + b * b - 2.0 * c * a * b, 0.0))
    return da, db, c, rng


#: ``sin²`` of the smallest angle between two walls that still makes an edge (as :func:`edge_line`'s default).
_MIN_EDGE_SINE2 = float(np.sin(np.deg2rad(20.0)) ** 2)


def echo_residuals(
    wall_a: Wall, wall_b: Wall, pts: ScanPoints, beam_half_angle: float, min_angle: float = np.deg2rad(20.0)
) -> np.ndarray:
    """Range residual of every echo under each part of the model, (3, N), m: wall a, wall b, the edge.

    A wall's is the mirror-echo condition ``n·p_c + d − h``, the edge's
    ``d − ρ·sin(opening)`` (:func:`edge_range_terms`).  ``inf`` where that
    part cannot have returned the echo: a wall whose normal lies beyond
    ``beam_half_angle`` of the boresight, an edge whose direction from the
    capsule (``v = α n_a + β n_b``, ``α = (a − bc)/(1 − c²)``,
    ``β = (b − ac)/(1 − c²)``) does, or no edge at all (walls within
    ``min_angle`` of parallel, as :func:`edge_line`).
    """
    return _echo_residuals(
        pts.capsule,
        pts.distance,
        pts.beam,
        wall_a.normal,
        float(wall_a.offset),
        wall_b.normal,
        float(wall_b.offset),
        math.cos(beam_half_angle),
        math.sin(min_angle) ** 2,
    )


@kernel
def _echo_residual(
    capsule: np.ndarray,
    distance: np.ndarray,
    beam: np.ndarray,
    i: int,
    normal_a: np.ndarray,
    offset_a: float,
    normal_b: np.ndarray,
    offset_b: float,
    c: float,
    cos_t: float,
    edge: bool,
    cos_edge: float,
) -> tuple[float, float, float]:
    """:func:`echo_residuals` of echo ``i``: wall a, wall b, the edge (``c = n_a·n_b``; ``edge``: the walls
    make one; ``cos_edge = cos_t·√(1 − c²)``).  :func:`edge_range_terms`' ``a``, ``b`` and range echo by
    echo, as the assignment of every stage takes them (no arrays allocated)."""
    p0, p1, p2 = capsule[i, 0], capsule[i, 1], capsule[i, 2]
    a = offset_a - (p0 * normal_a[0] + p1 * normal_a[1] + p2 * normal_a[2])
    b = offset_b - (p0 * normal_b[0] + p1 * normal_b[1] + p2 * normal_b[2])
    rng = np.sqrt(max(a * a + b * b - 2.0 * c * a * b, 0.0))
    fa = beam[i, 0] * normal_a[0] + beam[i, 1] * normal_a[1] + beam[i, 2] * normal_a[2]
    fb = beam[i, 0] * normal_b[0] + beam[i, 1] * normal_b[1] + beam[i, 2] * normal_b[2]
    ra = distance[i] - a if fa >= cos_t else np.inf
    rb = distance[i] - b if fb >= cos_t else np.inf
    # boresight · v/|v| ≥ cos_t, multiplied through by |v|·(1 − c²) = √q·√(1 − c²) ≥ 0.
    re = distance[i] - rng if edge and (a - b * c) * fa + (b - a * c) * fb >= cos_edge * rng else np.inf
    return ra, rb, re


@kernel
def _echo_residuals(
    capsule: np.ndarray,
    distance: np.ndarray,
    beam: np.ndarray,
    normal_a: np.ndarray,
    offset_a: float,
    normal_b: np.ndarray,
    offset_b: float,
    cos_t: float,
    min_sine2: float,
) -> np.ndarray:
    """:func:`echo_residuals` on arrays: ``cos_t`` the beam's half angle's cosine, ``min_sine2`` the edge's sin²."""
    n = distance.shape[0]
    c = normal_a[0] * normal_b[0] + normal_a[1] * normal_b[1] + normal_a[2] * normal_b[2]
    s2 = 1.0 - c * c
    edge = s2 >= min_sine2
    cos_edge = cos_t * np.sqrt(s2)
    r = np.empty((3, n))
    for i in range(n):
        r[0, i], r[1, i], r[2, i] = _echo_residual(
            capsule, distance, beam, i, normal_a, offset_a, normal_b, offset_b, c, cos_t, edge, cos_edge
        )
    return r


def assign_echoes(
    wall_a: Wall,
    wall_b: Wall,
    pts: ScanPoints,
    tolerance: float,
    beam_half_angle: float,
    edge_tolerance: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
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
    return _assign(
        pts.capsule,
        pts.distance,
        pts.beam,
        wall_a.normal,
        float(wall_a.offset),
        wall_b.normal,
        float(wall_b.offset),
        np.cos(beam_half_angle),
        float(tolerance),
        float(tolerance if edge_tolerance is None else edge_tolerance),
    )


@kernel
def _assign(
    capsule: np.ndarray,
    distance: np.ndarray,
    beam: np.ndarray,
    normal_a: np.ndarray,
    offset_a: float,
    normal_b: np.ndarray,
    offset_b: float,
    cos_t: float,
    tolerance: float,
    edge_tolerance: float,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`assign_echoes` on arrays (``cos_t`` the beam's half angle's cosine)."""
    n = distance.shape[0]
    c = normal_a[0] * normal_b[0] + normal_a[1] * normal_b[1] + normal_a[2] * normal_b[2]
    s2 = 1.0 - c * c
    edge = s2 >= _MIN_EDGE_SINE2
    cos_edge = cos_t * np.sqrt(s2)
    labels = np.empty(n, dtype=np.intp)
    res = np.empty(n)
    r = np.empty(3)
    for i in range(n):
        # :func:`echo_residuals`' column i, echo by echo
        r[0], r[1], r[2] = _echo_residual(
            capsule, distance, beam, i, normal_a, offset_a, normal_b, offset_b, c, cos_t, edge, cos_edge
        )
        # np.argmin of |r|: the first smallest, or the first NaN.
        best = 0
        for k in (1, 2):
            if np.isnan(abs(r[best])):
                break
            if np.isnan(abs(r[k])) or abs(r[k]) < abs(r[best]):
                best = k
        x = r[best]
        if abs(x) <= (edge_tolerance if best == ECHO_EDGE else tolerance):
            labels[i] = best
            res[i] = x
        else:
            labels[i] = ECHO_OUTLIER
            res[i] = np.nan
    return labels, res


def edge_shared_shares(
    model: CornerModel, pts: ScanPoints, beam_half_angle: float, residuals: np.ndarray | None = None
) -> tuple[float, float, float]:
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
    label without echoes, and all 0 for a model without an edge.  ``residuals``: the model walls'
    :func:`echo_residuals`, if the caller has them.
    """
    if edge_line(model.wall_a, model.wall_b) is None:
        return 0.0, 0.0, 0.0
    if residuals is None:
        residuals = echo_residuals(model.wall_a, model.wall_b, pts, beam_half_angle)
    return _shared_shares(model.labels, residuals, float(model.tolerance))


@kernel
def _shared_shares(labels: np.ndarray, residuals: np.ndarray, tolerance: float) -> tuple[float, float, float]:
    """:func:`edge_shared_shares` from the model's labels and :func:`echo_residuals`."""
    count = np.zeros(3)
    shared = np.zeros(3)
    for i in range(labels.shape[0]):
        k = labels[i]
        if k == ECHO_WALL_A or k == ECHO_WALL_B:
            count[k] += 1.0
            if abs(residuals[ECHO_EDGE, i]) <= tolerance:
                shared[k] += 1.0
        elif k == ECHO_EDGE:
            count[k] += 1.0
            if abs(residuals[ECHO_WALL_A, i]) <= tolerance or abs(residuals[ECHO_WALL_B, i]) <= tolerance:
                shared[k] += 1.0
    out = np.zeros(3)
    for k in range(3):
        if count[k] > 0:
            out[k] = shared[k] / count[k]
    return out[0], out[1], out[2]


def edge_implied_offsets(other: Wall, normal: np.ndarray, capsule: np.ndarray, distance: np.ndarray) -> np.ndarray:
    """Offset of the wall facing ``normal`` that would make each echo a double bounce off its edge with ``other``, m.

    The inverse of :func:`edge_range_terms` for one wall (design notes §8):
    with ``a`` the capsule's distance to ``other`` and ``c`` the normals' dot
    product, a double bounce returns from ``d = √(a² + x² − 2acx)``, so the
    capsule's distance to the wall is ``x = ac + √(d² − a²(1 − c²))`` (the
    root beyond the edge's foot) and the offset is ``x + n·p_c``.
    """
    return _edge_implied_offsets(
        np.asarray(other.normal, dtype=np.float64),
        float(other.offset),
        np.asarray(normal, dtype=np.float64),
        np.asarray(capsule, dtype=np.float64),
        np.asarray(distance, dtype=np.float64),
    )


@kernel
def _edge_implied_offsets(
    other_normal: np.ndarray, other_offset: float, normal: np.ndarray, capsule: np.ndarray, distance: np.ndarray
) -> np.ndarray:
    c = other_normal[0] * normal[0] + other_normal[1] * normal[1] + other_normal[2] * normal[2]
    out = np.empty(distance.shape[0])
    for i in range(distance.shape[0]):
        p0, p1, p2 = capsule[i, 0], capsule[i, 1], capsule[i, 2]
        a = other_offset - (p0 * other_normal[0] + p1 * other_normal[1] + p2 * other_normal[2])
        x = a * c + np.sqrt(max(distance[i] * distance[i] - a * a * (1.0 - c * c), 0.0))
        out[i] = x + (p0 * normal[0] + p1 * normal[1] + p2 * normal[2])
    return out


def edge_alternatives(
    model: CornerModel, pts: ScanPoints, beam_half_angle: float, min_points: int = 8
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
    if edge_line(model.wall_a, model.wall_b) is None:
        return (0.0, 0), (0.0, 0)
    wa, wb = model.wall_a, model.wall_b
    cos_t = math.cos(beam_half_angle)
    out = [
        _edge_alternative(
            pts.capsule,
            pts.distance,
            pts.beam,
            model.labels,
            k,
            wa.normal,
            float(wa.offset),
            wb.normal,
            float(wb.offset),
            cos_t,
            float(model.tolerance),
            int(min_points),
        )
        for k in (ECHO_WALL_A, ECHO_WALL_B)
    ]
    return out[0], out[1]


@kernel
def _edge_alternative(
    capsule: np.ndarray,
    distance: np.ndarray,
    beam: np.ndarray,
    labels: np.ndarray,
    k: int,
    normal_a: np.ndarray,
    offset_a: float,
    normal_b: np.ndarray,
    offset_b: float,
    cos_t: float,
    tolerance: float,
    min_points: int,
) -> tuple[float, int]:
    """:func:`edge_alternatives` for wall ``k`` (the walls have an edge)."""
    mk = labels == k
    n_k = np.count_nonzero(mk)
    if n_k < min_points:
        return 0.0, 0
    if k == ECHO_WALL_A:
        implied = _edge_implied_offsets(normal_b, offset_b, normal_a, capsule[mk], distance[mk])
    else:
        implied = _edge_implied_offsets(normal_a, offset_a, normal_b, capsule[mk], distance[mk])
    h = fast_median(implied)
    if k == ECHO_WALL_A:
        moved, _ = _assign(capsule, distance, beam, normal_a, h, normal_b, offset_b, cos_t, tolerance, tolerance)
    else:
        moved, _ = _assign(capsule, distance, beam, normal_a, offset_a, normal_b, h, cos_t, tolerance, tolerance)
    as_edge = np.count_nonzero(moved[mk] == ECHO_EDGE) / n_k
    return float(as_edge), int(np.count_nonzero(labels != ECHO_OUTLIER) - np.count_nonzero(moved != ECHO_OUTLIER))


@kernel
def _msac_cost(residuals: np.ndarray, tolerance: float) -> float:
    """MSAC cost ``Σ min(r², t²)`` (m²), a non-finite residual costing ``t²``; summed pairwise as ``np.sum``."""
    t2 = tolerance * tolerance
    x = np.empty(residuals.shape[0])
    for i in range(residuals.shape[0]):
        r = residuals[i] if np.isfinite(residuals[i]) else tolerance
        x[i] = min(r * r, t2)
    return pairwise_sum(x, 0, x.shape[0])


def band_offsets(w: np.ndarray, *, bin_width: float = 0.01, max_bands: int = 4, min_count: int = 6) -> np.ndarray:
    """Centres of the densest bands of mirror-implied wall positions ``w`` (m), densest first.

    A wall seen near face-on puts its echoes at ``w ≈ h`` whatever the step;
    the corner cluster makes a band at the edge's distance.  Peaks of the
    smoothed histogram (bins of ``bin_width``) with at least ``min_count``
    echoes, each refined as the median of ``w`` within 2 bins (the smoothing
    turns a one-bin spike into a three-bin plateau whose right end is the peak).
    """
    return _band_offsets(np.asarray(w, dtype=np.float64), float(bin_width), int(max_bands), int(min_count))


@kernel
def _band_offsets(w: np.ndarray, bin_width: float, max_bands: int, min_count: int) -> np.ndarray:
    w = w[np.isfinite(w)]
    if w.size < min_count:
        return np.zeros(0)
    lo, hi = w.min(), w.max()
    nb = max(int(np.ceil((hi - lo) / bin_width)), 1)
    # Bin k holds lo + k·bin_width ≤ w < lo + (k + 1)·bin_width (the top bin its right end too).
    counts = np.zeros(nb + 2, dtype=np.intp)  # padded with an empty bin at each end
    for x in w:
        counts[1 + min(int((x - lo) / bin_width), nb - 1)] += 1
    smooth = counts[:-2] + counts[1:-1] + counts[2:]  # np.convolve(np.pad(counts, 1), [1, 1, 1], "valid"): exact counts
    peaks = []
    for i in range(nb):
        left = smooth[i - 1] if i > 0 else -1
        right = smooth[i + 1] if i + 1 < nb else -1
        if smooth[i] >= left and smooth[i] > right and smooth[i] >= min_count:
            peaks.append(i)
    ranked = np.array(peaks, dtype=np.intp)
    ranked = ranked[np.argsort(-smooth[ranked], kind="mergesort")][:max_bands]  # densest first, stable
    centres = np.empty(ranked.size)
    k = 0
    for p in ranked:
        c = lo + (p + 0.5) * bin_width
        near = w[np.abs(w - c) <= 2.0 * bin_width]
        if near.size:
            centres[k] = fast_median(near)
            k += 1
    return centres[:k]


def joint_residuals(wall_a: Wall, wall_b: Wall, pts: ScanPoints, labels: np.ndarray) -> np.ndarray:
    """Range residuals (m) of the labelled echoes under their models: wall a, wall b, then the edge."""
    lab = np.asarray(labels, dtype=np.intp)
    return joint_residuals_arrays(
        pts.capsule,
        pts.distance,
        labelled_order(lab),
        lab,
        np.asarray(wall_a.normal, dtype=np.float64),
        float(wall_a.offset),
        np.asarray(wall_b.normal, dtype=np.float64),
        float(wall_b.offset),
    )


@kernel
def labelled_order(labels: np.ndarray) -> np.ndarray:
    """Indices of the echoes labelled wall a, then wall b, then the edge, each in the scan's order."""
    m = 0
    for i in range(labels.shape[0]):
        if labels[i] == ECHO_WALL_A or labels[i] == ECHO_WALL_B or labels[i] == ECHO_EDGE:
            m += 1
    order = np.empty(m, dtype=np.intp)
    j = 0
    for k in (ECHO_WALL_A, ECHO_WALL_B, ECHO_EDGE):
        for i in range(labels.shape[0]):
            if labels[i] == k:
                order[j] = i
                j += 1
    return order


@kernel
def joint_residuals_arrays(
    capsule: np.ndarray,
    distance: np.ndarray,
    order: np.ndarray,
    labels: np.ndarray,
    na: np.ndarray,
    ha: float,
    nb: np.ndarray,
    hb: float,
) -> np.ndarray:
    """:func:`~lelsonar.reconstruct.estimate.corner.model.joint_residuals` of the echoes ``order`` lists (m)."""
    c = na[0] * nb[0] + na[1] * nb[1] + na[2] * nb[2]
    out = np.empty(order.shape[0])
    for o in range(order.shape[0]):
        i = order[o]
        p0, p1, p2 = capsule[i, 0], capsule[i, 1], capsule[i, 2]
        pa = p0 * na[0] + p1 * na[1] + p2 * na[2]
        pb = p0 * nb[0] + p1 * nb[1] + p2 * nb[2]
        a, b = ha - pa, hb - pb
        if labels[i] == ECHO_WALL_A:
            out[o] = pa + distance[i] - ha  # n·p_c + d − h, as mirror_residuals
        elif labels[i] == ECHO_WALL_B:
            out[o] = pb + distance[i] - hb
        elif 1.0 - c * c < 1e-18:  # walls parallel: no edge (joint_gauss_newton's min_sine²)
            out[o] = np.inf
        else:
            out[o] = distance[i] - np.sqrt(max(a * a + b * b - 2.0 * c * a * b, 0.0))
    return out


def joint_gauss_newton(
    wall_a: Wall,
    wall_b: Wall,
    pts: ScanPoints,
    labels: np.ndarray,
    *,
    iterations: int = 3,
    covariance: bool = True,
    trials: int = 6,
    min_sine: float = 1e-9,
) -> tuple[tuple[Wall, Wall], np.ndarray]:
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
    na, ha, nb, hb, cov, moved = joint_gauss_newton_arrays(
        pts.capsule,
        pts.distance,
        np.asarray(labels, dtype=np.intp),
        wall_a.normal,
        float(wall_a.offset),
        wall_b.normal,
        float(wall_b.offset),
        iterations,
        covariance,
        trials,
        min_sine,
    )
    return ((Wall(na, ha), Wall(nb, hb)) if moved else (wall_a, wall_b)), cov


@kernel
def _joint_cost(
    capsule: np.ndarray,
    distance: np.ndarray,
    labels: np.ndarray,
    na: np.ndarray,
    ha: float,
    nb: np.ndarray,
    hb: float,
    min_sine: float,
) -> tuple[float, bool]:
    """Sum of squares of the labelled echoes' range residuals (:func:`joint_residuals`), and whether all are finite."""
    # edge_range_terms' a, b and range, echo by echo (the solver's trials call this: no arrays allocated)
    c = na[0] * nb[0] + na[1] * nb[1] + na[2] * nb[2]
    edge = 1.0 - c * c >= min_sine * min_sine
    total = 0.0
    for i in range(labels.shape[0]):
        k = labels[i]
        if k != ECHO_WALL_A and k != ECHO_WALL_B and k != ECHO_EDGE:
            continue
        a = ha - (capsule[i, 0] * na[0] + capsule[i, 1] * na[1] + capsule[i, 2] * na[2])
        b = hb - (capsule[i, 0] * nb[0] + capsule[i, 1] * nb[1] + capsule[i, 2] * nb[2])
        if k == ECHO_WALL_A:
            r = distance[i] - a
        elif k == ECHO_WALL_B:
            r = distance[i] - b
        else:
            r = distance[i] - np.sqrt(max(a * a + b * b - 2.0 * c * a * b, 0.0)) if edge else np.inf
        total += r * r
    return total, np.isfinite(total)


@kernel
def _joint_normal_equations(
    capsule: np.ndarray,
    distance: np.ndarray,
    labels: np.ndarray,
    na: np.ndarray,
    ha: float,
    nb: np.ndarray,
    hb: float,
    ea1: np.ndarray,
    ea2: np.ndarray,
    eb1: np.ndarray,
    eb2: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """``JᵀJ`` and ``Jᵀr`` of the labelled echoes, with :func:`joint_gauss_newton`'s Jacobian.

    A wall's mirror rows ``(p_c·e₁, p_c·e₂, −1)`` touch only its own 3×3 block: their sums are
    kept apart from the edge rows' (which touch all six parameters) and added at the end.
    """
    c = na[0] * nb[0] + na[1] * nb[1] + na[2] * nb[2]
    # Per wall: Σx₁², Σx₁x₂, Σx₁, Σx₂², Σx₂, count, then Σx₁r, Σx₂r, Σr — scalars, echo by echo in the
    # scan's order (no per-echo array views: their reference counting cost more than the sums).
    a11 = a12 = a1 = a22 = a2 = a0 = ar1 = ar2 = ar = 0.0
    b11 = b12 = b1 = b22 = b2 = b0 = br1 = br2 = br = 0.0
    jtj = np.zeros((6, 6))
    g = np.zeros(6)
    row = np.zeros(6)
    # n_b·e (wall a's tangents) and n_a·e (wall b's): how the other wall's normal turns the edge's range.
    nb_ea1 = nb[0] * ea1[0] + nb[1] * ea1[1] + nb[2] * ea1[2]
    nb_ea2 = nb[0] * ea2[0] + nb[1] * ea2[1] + nb[2] * ea2[2]
    na_eb1 = na[0] * eb1[0] + na[1] * eb1[1] + na[2] * eb1[2]
    na_eb2 = na[0] * eb2[0] + na[1] * eb2[1] + na[2] * eb2[2]
    for i in range(labels.shape[0]):
        k = labels[i]
        if k != ECHO_WALL_A and k != ECHO_WALL_B and k != ECHO_EDGE:
            continue
        p0, p1, p2 = capsule[i, 0], capsule[i, 1], capsule[i, 2]
        # edge_range_terms' a and b, echo by echo (no arrays allocated)
        a = ha - (p0 * na[0] + p1 * na[1] + p2 * na[2])
        b = hb - (p0 * nb[0] + p1 * nb[1] + p2 * nb[2])
        if k == ECHO_WALL_A:
            r = distance[i] - a
            x1 = p0 * ea1[0] + p1 * ea1[1] + p2 * ea1[2]
            x2 = p0 * ea2[0] + p1 * ea2[1] + p2 * ea2[2]
            a11 += x1 * x1
            a12 += x1 * x2
            a1 += x1
            a22 += x2 * x2
            a2 += x2
            a0 += 1.0
            ar1 += x1 * r
            ar2 += x2 * r
            ar += r
        elif k == ECHO_WALL_B:
            r = distance[i] - b
            x1 = p0 * eb1[0] + p1 * eb1[1] + p2 * eb1[2]
            x2 = p0 * eb2[0] + p1 * eb2[1] + p2 * eb2[2]
            b11 += x1 * x1
            b12 += x1 * x2
            b1 += x1
            b22 += x2 * x2
            b2 += x2
            b0 += 1.0
            br1 += x1 * r
            br2 += x2 * r
            br += r
        else:
            rng = np.sqrt(max(a * a + b * b - 2.0 * c * a * b, 0.0))
            r = distance[i] - rng
            inv = 1.0 / max(rng, 1e-12)
            ga, gb, gab = (a - b * c) * inv, (b - a * c) * inv, a * b * inv
            row[0] = (p0 * ea1[0] + p1 * ea1[1] + p2 * ea1[2]) * ga + gab * nb_ea1
            row[1] = (p0 * ea2[0] + p1 * ea2[1] + p2 * ea2[2]) * ga + gab * nb_ea2
            row[2] = -ga
            row[3] = (p0 * eb1[0] + p1 * eb1[1] + p2 * eb1[2]) * gb + gab * na_eb1
            row[4] = (p0 * eb2[0] + p1 * eb2[1] + p2 * eb2[2]) * gb + gab * na_eb2
            row[5] = -gb
            for u in range(6):
                g[u] += row[u] * r
                for v in range(u, 6):
                    jtj[u, v] += row[u] * row[v]
    jtj[0, 0] += a11
    jtj[0, 1] += a12
    jtj[0, 2] -= a1
    jtj[1, 1] += a22
    jtj[1, 2] -= a2
    jtj[2, 2] += a0
    g[0] += ar1
    g[1] += ar2
    g[2] -= ar
    jtj[3, 3] += b11
    jtj[3, 4] += b12
    jtj[3, 5] -= b1
    jtj[4, 4] += b22
    jtj[4, 5] -= b2
    jtj[5, 5] += b0
    g[3] += br1
    g[4] += br2
    g[5] -= br
    for u in range(6):
        for v in range(u):
            jtj[u, v] = jtj[v, u]
    return jtj, g


@kernel
def lu_solve(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, bool]:
    """``a⁻¹ b`` (b one or more columns) by LU with partial pivoting, as LAPACK's ``gesv``.

    False if ``a`` is singular."""
    n = a.shape[0]
    lu = a.copy()
    x = b.copy()
    for k in range(n):
        p = k
        for i in range(k + 1, n):
            if abs(lu[i, k]) > abs(lu[p, k]):
                p = i
        if lu[p, k] == 0.0:
            return x, False
        if p != k:
            for j in range(n):
                lu[k, j], lu[p, j] = lu[p, j], lu[k, j]
            for j in range(x.shape[1]):
                x[k, j], x[p, j] = x[p, j], x[k, j]
        for i in range(k + 1, n):
            f = lu[i, k] / lu[k, k]
            for j in range(k + 1, n):
                lu[i, j] -= f * lu[k, j]
            for j in range(x.shape[1]):
                x[i, j] -= f * x[k, j]
    for k in range(n - 1, -1, -1):
        for j in range(x.shape[1]):
            s = x[k, j]
            for i in range(k + 1, n):
                s -= lu[k, i] * x[i, j]
            x[k, j] = s / lu[k, k]
    return x, True


@kernel
def joint_gauss_newton_arrays(
    capsule: np.ndarray,
    distance: np.ndarray,
    labels: np.ndarray,
    normal_a: np.ndarray,
    offset_a: float,
    normal_b: np.ndarray,
    offset_b: float,
    iterations: int,
    covariance: bool,
    trials: int,
    min_sine: float,
) -> tuple[np.ndarray, float, np.ndarray, float, np.ndarray, bool]:
    """:func:`joint_gauss_newton` on arrays; the last value says whether the walls moved from the start."""
    return _joint_gauss_newton_from(
        capsule,
        distance,
        labels,
        normal_a,
        offset_a,
        normal_b,
        offset_b,
        iterations,
        covariance,
        trials,
        min_sine,
        np.nan,
    )


@kernel
def _assigned_cost(labels: np.ndarray, residuals: np.ndarray) -> float:
    """:func:`_joint_cost` of the walls an assignment was made with, from its residuals (the same terms in the
    same order: :func:`_echo_residual` computes each labelled echo's residual as :func:`_joint_cost` does)."""
    total = 0.0
    for i in range(labels.shape[0]):
        k = labels[i]
        if k == ECHO_WALL_A or k == ECHO_WALL_B or k == ECHO_EDGE:
            total += residuals[i] * residuals[i]
    return total


@kernel
def _joint_gauss_newton_from(
    capsule: np.ndarray,
    distance: np.ndarray,
    labels: np.ndarray,
    normal_a: np.ndarray,
    offset_a: float,
    normal_b: np.ndarray,
    offset_b: float,
    iterations: int,
    covariance: bool,
    trials: int,
    min_sine: float,
    cost0: float,
) -> tuple[np.ndarray, float, np.ndarray, float, np.ndarray, bool]:
    """:func:`joint_gauss_newton_arrays` given the start's :func:`_joint_cost` ``cost0`` (finite; NaN: work it out)."""
    cov = np.full((6, 6), np.inf)
    na, ha, nb, hb = normal_a.copy(), offset_a, normal_b.copy(), offset_b
    m = 0
    for i in range(labels.shape[0]):
        if labels[i] == ECHO_WALL_A or labels[i] == ECHO_WALL_B or labels[i] == ECHO_EDGE:
            m += 1
    if m < 7:
        return na, ha, nb, hb, cov, False
    if np.isnan(cost0):
        c0, finite = _joint_cost(capsule, distance, labels, na, ha, nb, hb, min_sine)
    else:
        c0, finite = cost0, True
    if not finite:
        return na, ha, nb, hb, cov, False
    lam = 1e-6
    for _ in range(iterations):
        ea1, ea2 = tangent_basis(na)
        eb1, eb2 = tangent_basis(nb)
        jtj, g = _joint_normal_equations(capsule, distance, labels, na, ha, nb, hb, ea1, ea2, eb1, eb2)
        rhs = np.empty((6, 1))
        for u in range(6):
            rhs[u, 0] = -g[u]
        accepted = False
        for _attempt in range(trials):
            damped = jtj.copy()
            for u in range(6):
                damped[u, u] = jtj[u, u] + lam * (jtj[u, u] + 1e-12)
            dz, ok = lu_solve(damped, rhs)
            if not ok:
                lam *= 10
                continue
            ta = na + ea1 * dz[0, 0] + ea2 * dz[1, 0]
            ta /= np.sqrt(ta[0] * ta[0] + ta[1] * ta[1] + ta[2] * ta[2])
            tb = nb + eb1 * dz[3, 0] + eb2 * dz[4, 0]
            tb /= np.sqrt(tb[0] * tb[0] + tb[1] * tb[1] + tb[2] * tb[2])
            tha, thb = ha + dz[2, 0], hb + dz[5, 0]
            c1, finite1 = _joint_cost(capsule, distance, labels, ta, tha, tb, thb, min_sine)
            if finite1 and c1 <= c0:
                na, ha, nb, hb, c0 = ta, tha, tb, thb, c1
                lam = max(lam / 10, 1e-9)
                accepted = True
                break
            lam *= 10
        if not accepted:
            break
    if covariance:
        ea1, ea2 = tangent_basis(na)
        eb1, eb2 = tangent_basis(nb)
        jtj, _g = _joint_normal_equations(capsule, distance, labels, na, ha, nb, hb, ea1, ea2, eb1, eb2)
        inv, ok = lu_solve(jtj, np.eye(6))
        if ok:
            cov = c0 / (m - 6) * inv
    return na, ha, nb, hb, cov, True


@kernel
def _refine_walls(
    capsule: np.ndarray,
    distance: np.ndarray,
    beam: np.ndarray,
    na: np.ndarray,
    ha: float,
    nb: np.ndarray,
    hb: float,
    tolerances: np.ndarray,
    cos_t: float,
    min_points: int,
    axis_a: np.ndarray,
    axis_b: np.ndarray,
    cos_max_tilt: float,
    first_labels: np.ndarray,
    first_residuals: np.ndarray,
) -> tuple[np.ndarray, float, np.ndarray, float]:
    """Alternate assignment and one joint Gauss-Newton step at each (tolerance, edge tolerance) of ``tolerances``.

    ``first_labels``, ``first_residuals``: the first stage's assignment of the starting walls, if the caller
    made it already (empty: made here).
    """
    for s in range(tolerances.shape[0]):
        if s == 0 and first_labels.shape[0] > 0:
            labels, res = first_labels.copy(), first_residuals  # (the labels are changed below; the residuals not)
        else:
            labels, res = _assign(capsule, distance, beam, na, ha, nb, hb, cos_t, tolerances[s, 0], tolerances[s, 1])
        for k in (ECHO_WALL_A, ECHO_WALL_B):
            if np.count_nonzero(labels == k) < min_points:
                labels[labels == k] = ECHO_OUTLIER  # too few to move this wall
        fa, fha, fb, fhb, _cov, _moved = _joint_gauss_newton_from(
            capsule, distance, labels, na, ha, nb, hb, 1, False, 6, 1e-9, _assigned_cost(labels, res)
        )
        # Keep each wall within max_tilt of its nominal axis: beyond, the solver is chasing the other
        # wall's or the edge's echoes.
        if fa[0] * axis_a[0] + fa[1] * axis_a[1] + fa[2] * axis_a[2] >= cos_max_tilt and fha > 0:
            na, ha = fa, fha
        if fb[0] * axis_b[0] + fb[1] * axis_b[1] + fb[2] * axis_b[2] >= cos_max_tilt and fhb > 0:
            nb, hb = fb, fhb
    return na, ha, nb, hb


def fit_corner_model(
    pts: ScanPoints,
    axis_a: np.ndarray,
    axis_b: np.ndarray,
    *,
    beam_half_angle: float = np.deg2rad(50.0),
    tolerance: float = 0.02,
    max_bands: int = 3,
    max_refined: int = 4,
    min_points: int = 8,
    max_tilt: float = np.deg2rad(15.0),
    good_enough: float = 0.02,
    recentre: int = 3,
    significance: float = 3.0,
) -> CornerModel | None:
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
    axis_a = np.asarray(axis_a, dtype=np.float64)
    axis_a = axis_a / vector_norm(axis_a)
    axis_b = np.asarray(axis_b, dtype=np.float64)
    axis_b = axis_b / vector_norm(axis_b)
    na, ha, nb, hb, labels, res, cost, hyps, cov, out_a, out_b, fa, fb = _corner_model(
        pts.capsule,
        pts.distance,
        pts.beam,
        axis_a,
        axis_b,
        math.cos(beam_half_angle),
        float(tolerance),
        int(max_bands),
        int(max_refined),
        int(min_points),
        float(max_tilt),
        math.cos(max_tilt),
        float(good_enough),
        float(significance),
    )
    if hyps == 0:
        return None
    outside = (bool(out_a), bool(out_b))
    model = CornerModel(Wall(na, ha), Wall(nb, hb), labels, res, tolerance, cost, int(hyps), cov, outside)
    if not (any(outside) and recentre > 0):
        return model
    roll_a, roll_b = roll_angle(fa, axis_a), roll_angle(fb, axis_b)
    # Only a turn of the whole L moves the axes: both walls turning the same way by about as much.  Walls
    # pulled apart (one onto the corner cluster, which looks like a wall facing the edge) stay flagged.
    if abs(roll_a - roll_b) <= max_tilt:
        rho = 0.5 * (roll_a + roll_b)
        turn = rotation_x(rho)
        moved = fit_corner_model(
            pts,
            turn @ axis_a,
            turn @ axis_b,
            beam_half_angle=beam_half_angle,
            tolerance=tolerance,
            max_bands=max_bands,
            max_refined=max_refined,
            min_points=min_points,
            max_tilt=max_tilt,
            good_enough=good_enough,
            recentre=recentre - 1,
            significance=significance,
        )
        if moved is not None and moved.cost < model.cost:
            return moved
    return model


@kernel
def _wall_bands(
    capsule: np.ndarray,
    distance: np.ndarray,
    beam: np.ndarray,
    axis: np.ndarray,
    cos_t: float,
    max_bands: int,
    min_points: int,
) -> np.ndarray:
    """Offsets (> 0) of the densest bands of ``w = axis·p_c + d`` over the echoes whose boresight sees ``axis``."""
    n = distance.shape[0]
    w = np.empty(n)
    k = 0
    for i in range(n):
        if beam[i, 0] * axis[0] + beam[i, 1] * axis[1] + beam[i, 2] * axis[2] >= cos_t:
            w[k] = capsule[i, 0] * axis[0] + capsule[i, 1] * axis[1] + capsule[i, 2] * axis[2] + distance[i]
            k += 1
    bands = _band_offsets(w[:k], 0.01, max_bands, min_points)
    return bands[bands > 0]


@kernel
def _leaves_window(
    normal: np.ndarray, axis: np.ndarray, cov: np.ndarray, k: int, max_tilt: float, significance: float
) -> bool:
    """Whether a fitted wall lies beyond ``max_tilt`` of its axis *and* the echoes say so.

    A wall whose tilt the ranges barely constrain (capsules almost on the axis: no lever arm) can land
    anywhere; its departure is evidence only if it exceeds ``significance`` times its own standard error
    (``cov``'s tilt block of wall ``k``, 0 = a, 1 = b).
    """
    cos_angle = normal[0] * axis[0] + normal[1] * axis[1] + normal[2] * axis[2]
    angle = np.arccos(min(max(cos_angle, -1.0), 1.0))
    o = 3 * k
    c00, c01, c10, c11 = cov[o, o], cov[o, o + 1], cov[o + 1, o], cov[o + 1, o + 1]
    if np.isfinite(c00) and np.isfinite(c01) and np.isfinite(c10) and np.isfinite(c11):
        se = np.sqrt(max(c00 + c11, 0.0))
    else:
        se = np.inf
    return angle > max_tilt and angle > significance * se


@kernel
def _corner_model(
    capsule: np.ndarray,
    distance: np.ndarray,
    beam: np.ndarray,
    axis_a: np.ndarray,
    axis_b: np.ndarray,
    cos_t: float,
    tolerance: float,
    max_bands: int,
    max_refined: int,
    min_points: int,
    max_tilt: float,
    cos_max_tilt: float,
    good_enough: float,
    significance: float,
):
    """One pass of :func:`fit_corner_model` about the axes ``axis_a``, ``axis_b`` (unit), as a kernel.

    Hypotheses are the pairs of the walls' bands (:func:`band_offsets`); beyond ``max_refined`` of them
    the lowest MSAC costs at the loosest stage are refined (alternating assignment and a joint step at
    each stage of the schedule), the best by MSAC over all echoes at ``tolerance`` kept (stopping early
    once one leaves at most ``good_enough`` of the echoes unexplained), then two joint Gauss-Newton
    iterations with the covariance.

    Returns
    -------
    normal_a, offset_a, normal_b, offset_b, labels, residuals, cost, hypotheses (0: no pair of bands),
    covariance, outside_a, outside_b, and the joint fit's normals (before the ``max_tilt`` window).
    """
    n = distance.shape[0]
    bands_a = _wall_bands(capsule, distance, beam, axis_a, cos_t, max_bands, min_points)
    bands_b = _wall_bands(capsule, distance, beam, axis_b, cos_t, max_bands, min_points)
    n_hyps = bands_a.shape[0] * bands_b.shape[0]
    if n_hyps == 0:
        empty = np.zeros(0)
        return (
            axis_a.copy(),
            0.0,
            axis_b.copy(),
            0.0,
            np.zeros(0, dtype=np.intp),
            empty,
            np.inf,
            0,
            np.full((6, 6), np.inf),
            False,
            False,
            axis_a.copy(),
            axis_b.copy(),
        )
    hyp_a = np.empty(n_hyps)
    hyp_b = np.empty(n_hyps)
    for i in range(bands_a.shape[0]):
        for j in range(bands_b.shape[0]):
            hyp_a[i * bands_b.shape[0] + j] = bands_a[i]
            hyp_b[i * bands_b.shape[0] + j] = bands_b[j]
    schedule = np.empty((3, 2))
    schedule[0, 0], schedule[0, 1] = 2.5 * tolerance, 8 * tolerance
    schedule[1, 0], schedule[1, 1] = 1.5 * tolerance, 3 * tolerance
    schedule[2, 0], schedule[2, 1] = tolerance, tolerance
    order = np.arange(n_hyps)
    # The loosest stage's assignment of each pair's starting walls, where the ranking below made it (the
    # refinement's first stage reuses it: the same walls and tolerances).
    loose_labels = np.zeros((n_hyps, 0), dtype=np.intp)
    loose_res = np.zeros((n_hyps, 0))
    if n_hyps > max_refined:
        # Rank by the MSAC cost at the loosest stage (the nominal normals are off by up to the tilt), refine the best.
        loose = np.empty(n_hyps)
        loose_labels = np.empty((n_hyps, n), dtype=np.intp)
        loose_res = np.empty((n_hyps, n))
        for h in range(n_hyps):
            loose_labels[h], loose_res[h] = _assign(
                capsule, distance, beam, axis_a, hyp_a[h], axis_b, hyp_b[h], cos_t, schedule[0, 0], schedule[0, 1]
            )
            loose[h] = _msac_cost(loose_res[h], schedule[0, 0])
        order = np.argsort(loose, kind="mergesort")[:max_refined]
    best_cost = np.inf
    wa, wha, wb, whb = axis_a.copy(), 0.0, axis_b.copy(), 0.0
    labels = np.zeros(0, dtype=np.intp)
    res = np.zeros(0)
    for h in order:
        ra, rha, rb, rhb = _refine_walls(
            capsule,
            distance,
            beam,
            axis_a.copy(),
            hyp_a[h],
            axis_b.copy(),
            hyp_b[h],
            schedule,
            cos_t,
            min_points,
            axis_a,
            axis_b,
            cos_max_tilt,
            loose_labels[h],
            loose_res[h],
        )
        lab, r = _assign(capsule, distance, beam, ra, rha, rb, rhb, cos_t, tolerance, tolerance)
        cost = _msac_cost(r, tolerance)
        if h == order[0] or cost < best_cost:
            best_cost, wa, wha, wb, whb, labels, res = cost, ra, rha, rb, rhb, lab, r
        if np.count_nonzero(lab == ECHO_OUTLIER) <= good_enough * n:
            break  # the most promising pair already explains (nearly) every echo: no other can do better
    # (the assignment is a pure function of the walls: kept, not redone)
    fa, fha, fb, fhb, cov, _moved = _joint_gauss_newton_from(
        capsule, distance, labels, wa, wha, wb, whb, 2, True, 6, 1e-9, _assigned_cost(labels, res)
    )
    out_a = _leaves_window(fa, axis_a, cov, 0, max_tilt, significance)
    out_b = _leaves_window(fb, axis_b, cov, 1, max_tilt, significance)
    if (
        fa[0] * axis_a[0] + fa[1] * axis_a[1] + fa[2] * axis_a[2] >= cos_max_tilt
        and fb[0] * axis_b[0] + fb[1] * axis_b[1] + fb[2] * axis_b[2] >= cos_max_tilt
    ):
        wa, wha, wb, whb = fa, fha, fb, fhb
        labels, res = _assign(capsule, distance, beam, wa, wha, wb, whb, cos_t, tolerance, tolerance)
    elif out_a or out_b:
        # The covariance belongs to (fa, fb), not to the walls held at the window: it would overclaim.
        cov = np.full((6, 6), np.inf)
    return (
        wa,
        wha,
        wb,
        whb,
        labels,
        res,
        _msac_cost(res, tolerance),
        min(n_hyps, max_refined),
        cov,
        out_a,
        out_b,
        fa,
        fb,
    )


def roll_angle(normal: np.ndarray, axis: np.ndarray) -> float:
    """Signed angle about x from ``axis`` to ``normal``, both projected onto the rotation plane (y, z), rad."""
    z = complex(normal[1], normal[2]) * complex(axis[1], -axis[2])
    # np.angle(z), without its array round trip (NumPy's own arctan2: math.atan2 differs in the last bit)
    return float(np.arctan2(z.imag, z.real))
