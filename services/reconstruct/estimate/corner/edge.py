"""Whether a corner model's edge and its walls can be told apart: echoes two parts explain alike, and the
other explanation of each wall's echoes as the corner's double bounces (design of the verdict's edge findings)."""

from __future__ import annotations

import math

import numpy as np

from lelsonar.reconstruct.estimate.corner.model import (
    ECHO_EDGE,
    ECHO_OUTLIER,
    ECHO_WALL_A,
    ECHO_WALL_B,
    CornerModel,
    ScanPoints,
    Wall,
    assign_labels,
    echo_residuals,
    edge_line,
)
from lelsonar.reconstruct.estimate.robust import fast_median
from lelsonar.signal.compiled import kernel


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

    The inverse of :func:`edge_range_terms` for one wall:
    with ``a`` the capsule's distance to ``other`` and ``c`` the normals' dot
    product, a double bounce returns from ``d = √(a² + x² − 2acx)``, so the
    capsule's distance to the wall is ``x = ac + √(d² − a²(1 − c²))`` (the
    root beyond the edge's foot) and the offset is ``x + n·p_c``.
    """
    return edge_implied_offsets_of(
        np.asarray(other.normal, dtype=np.float64),
        float(other.offset),
        np.asarray(normal, dtype=np.float64),
        np.asarray(capsule, dtype=np.float64),
        np.asarray(distance, dtype=np.float64),
    )


@kernel
def edge_implied_offsets_of(
    other_normal: np.ndarray, other_offset: float, normal: np.ndarray, capsule: np.ndarray, distance: np.ndarray
) -> np.ndarray:
    """:func:`edge_implied_offsets` on float arrays (a kernel)."""
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
        implied = edge_implied_offsets_of(normal_b, offset_b, normal_a, capsule[mk], distance[mk])
    else:
        implied = edge_implied_offsets_of(normal_a, offset_a, normal_b, capsule[mk], distance[mk])
    h = fast_median(implied)
    if k == ECHO_WALL_A:
        moved, _ = assign_labels(capsule, distance, beam, normal_a, h, normal_b, offset_b, cos_t, tolerance, tolerance)
    else:
        moved, _ = assign_labels(capsule, distance, beam, normal_a, offset_a, normal_b, h, cos_t, tolerance, tolerance)
    as_edge = np.count_nonzero(moved[mk] == ECHO_EDGE) / n_k
    return float(as_edge), int(np.count_nonzero(labels != ECHO_OUTLIER) - np.count_nonzero(moved != ECHO_OUTLIER))
