"""The whole L explains every echo: a joint model of both walls and their edge.

The paper splits the scan at the energy peak and fits each half on its own,
treating the corner's double-bounce echoes as outliers.  That breaks when a
half holds more corner echoes than wall echoes (a sweep that covers little of
a wall, a far wall, a corner at an unusual angle): the corner echoes all share
one range, the distance to the edge, so the mirror-echo condition fits them for
*any* normal and LEL locks onto them (its breakdown point is 35–45 % one-sided
outliers).

Here the corner echoes are signal.  Two walls ``n_a·x = h_a``, ``n_b·x = h_b``
predict every echo a capsule at ``p_c`` can return:

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
together, then scored with the MSAC cost over *all* echoes.  The true pair explains the wall echoes of both walls
and the
corner cluster through the edge; a pair that mistakes the corner cluster for a
wall leaves the real wall's echoes unexplained and its edge explains nothing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lelsonar.geometry import ArrayGeometry, boresight
from lelsonar.reconstruct.estimate.normals import cross3
from lelsonar.reconstruct.estimate.robust import fast_median
from lelsonar.signal.compiled import kernel
from lelsonar.signal.summation import pairwise_sum

__all__ = [
    "ScanPoints",
    "Wall",
    "CornerModel",
    "scan_points",
    "mirror_residuals",
    "mirror_rows",
    "edge_line",
    "edge_range_terms",
    "echo_residuals",
    "assign_echoes",
    "band_offsets",
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
    """Residual of the mirror-echo condition ``n·p_c + d − h`` of every echo, m."""
    return mirror_rows(pts.capsule, pts.distance, wall.normal, wall.offset)


def mirror_rows(capsule: np.ndarray, distance: np.ndarray, normal: np.ndarray, offset: float) -> np.ndarray:
    """``n·p_c + d − h`` of each echo at capsule position ``capsule`` (N, 3) and range ``distance`` (N,), m."""
    return capsule @ normal + distance - offset


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
    """The range of the double bounce from the edge of two walls, in closed form.

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
MIN_EDGE_SINE2 = float(np.sin(np.deg2rad(20.0)) ** 2)


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
def echo_residual(
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
        r[0, i], r[1, i], r[2, i] = echo_residual(
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
    return assign_labels(
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
def assign_labels(
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
    edge = s2 >= MIN_EDGE_SINE2
    cos_edge = cos_t * np.sqrt(s2)
    labels = np.empty(n, dtype=np.intp)
    res = np.empty(n)
    r = np.empty(3)
    for i in range(n):
        # :func:`echo_residuals`' column i, echo by echo
        r[0], r[1], r[2] = echo_residual(
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


@kernel
def msac_cost(residuals: np.ndarray, tolerance: float) -> float:
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
    return band_offsets_of(np.asarray(w, dtype=np.float64), float(bin_width), int(max_bands), int(min_count))


@kernel
def band_offsets_of(w: np.ndarray, bin_width: float, max_bands: int, min_count: int) -> np.ndarray:
    """:func:`band_offsets` of a float array (a kernel: the search calls it on each axis)."""
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
