"""Unexplained echoes: a third surface's say nothing against the walls; a wall's that the model missed do.

The scene is an L (wall a 3 m ahead, wall b 1.2 m above) with a floor 0.45 m
below the axis that backscatters diffusely along every beam pointing down,
swept from −40° to 100°; each reading is the first of the echoes its beam
receives (mirror echoes and the edge's double bounce within the beam's lobe,
the floor's along the beam).  Which echo came from which surface is the
scene's truth, not the model's.
"""

from __future__ import annotations

import numpy as np
import pytest

from lelsonar.reconstruct.estimate.corner.model import (
    ECHO_OUTLIER,
    ECHO_WALL_A,
    ECHO_WALL_B,
    ScanPoints,
    Wall,
    assign_echoes,
    echo_residuals,
    mirror_residuals,
)
from lelsonar.reconstruct.estimate.quality import (
    DEGRADED,
    GOOD,
    UNRELIABLE,
    QualityLimits,
    unexplained_finding,
)
from lelsonar.reconstruct.estimate.unexplained import echoes_against_walls

H_A, H_B, FLOOR = 3.0, 1.2, 0.45  # m: walls y = H_A, z = H_B; floor z = −FLOOR
LOBE = np.deg2rad(12.0)  # the rig's beam: no echo from further off its axis
MODEL_LOBE, TOLERANCE, MIN_POINTS = np.deg2rad(50.0), 0.02, 8  # the corner model's defaults (FitOptions)
WALL_A, WALL_B, EDGE, FLOOR_ECHO = 1, 2, 3, 4


@pytest.fixture(scope="module")
def scene() -> tuple[ScanPoints, np.ndarray]:
    """The scan's echoes and, for each, the surface that returned it (the scene's truth)."""
    gamma = np.deg2rad(np.arange(-40.0, 100.0, 0.5))
    xs, r = np.array([-0.12, -0.04, 0.04, 0.12]), 0.03
    steps, caps = np.meshgrid(np.arange(gamma.size), np.arange(xs.size), indexing="ij")
    steps, caps = steps.ravel(), caps.ravel()
    g = gamma[steps]
    beam = np.stack([np.zeros_like(g), np.cos(g), np.sin(g)], axis=1)
    p = np.stack([xs[caps], r * np.cos(g), r * np.sin(g)], axis=1)
    a, b = H_A - p[:, 1], H_B - p[:, 2]  # distances to the walls (mirror echoes)
    to_edge = np.stack([np.zeros_like(g), a, b], axis=1)
    edge = np.linalg.norm(to_edge, axis=1)  # 90° corner: the double bounce returns from ρ
    down = -np.sin(g)
    ranges = np.stack(
        [
            np.where(beam[:, 1] >= np.cos(LOBE), a, np.inf),
            np.where(beam[:, 2] >= np.cos(LOBE), b, np.inf),
            np.where(np.einsum("ij,ij->i", to_edge, beam) >= np.cos(LOBE) * edge, edge, np.inf),
            np.where(down > 0.05, (FLOOR + p[:, 2]) / np.maximum(down, 0.05), np.inf),
        ]
    )
    first = np.argmin(ranges, axis=0)
    d = ranges[first, np.arange(g.size)]
    ok = np.isfinite(d)
    pts = ScanPoints(steps[ok], caps[ok], g[ok], p[ok], d[ok], beam[ok])
    return pts, (first + 1)[ok]


def _against(pts: ScanPoints, wall_a: Wall, wall_b: Wall) -> tuple[np.ndarray, np.ndarray]:
    labels, _ = assign_echoes(wall_a, wall_b, pts, TOLERANCE, MODEL_LOBE)
    residuals = echo_residuals(wall_a, wall_b, pts, MODEL_LOBE)[:2]
    cosines = np.stack([pts.beam @ wall_a.normal, pts.beam @ wall_b.normal])
    own = np.stack([labels == ECHO_WALL_A, labels == ECHO_WALL_B])
    return labels, echoes_against_walls(residuals, cosines, own, labels == ECHO_OUTLIER, MIN_POINTS)


def test_a_floors_echoes_do_not_count_against_the_true_walls(scene):
    pts, source = scene
    labels, against = _against(pts, Wall(np.array([0.0, 1.0, 0.0]), H_A), Wall(np.array([0.0, 0.0, 1.0]), H_B))
    unexplained = labels == ECHO_OUTLIER
    lim = QualityLimits()
    # The floor's echoes are what the true walls leave unexplained, more than makes a scan unreliable today.
    assert np.all(source[unexplained] == FLOOR_ECHO)
    assert np.mean(unexplained) > lim.unreliable_unexplained
    assert not np.any(against)
    share = float(np.mean(unexplained))
    assert unexplained_finding(share)[0][0] == UNRELIABLE
    level, reason = unexplained_finding(share, against=0.0)[0]
    assert level == GOOD and f"{100 * share:.0f} %" in reason


def test_a_model_that_took_the_corner_cluster_for_wall_a_is_still_told_by_wall_as_echoes(scene):
    """Wall a put where the corner's double bounces imply a mirror wall: the real wall's echoes, nearer face-on
    than the cluster's, are left unexplained in front of it, and they count against the model."""
    pts, source = scene
    cluster = source == EDGE
    wrong_a = Wall(
        np.array([0.0, 1.0, 0.0]),
        float(np.median(mirror_residuals(Wall(np.array([0.0, 1.0, 0.0]), 0.0), pts)[cluster])),
    )
    labels, against = _against(pts, wrong_a, Wall(np.array([0.0, 0.0, 1.0]), H_B))
    assert np.mean(source[labels == ECHO_WALL_A] == EDGE) > 0.9  # the model's wall a is the cluster
    missed = (labels == ECHO_OUTLIER) & (source == WALL_A)
    assert np.count_nonzero(missed) > 0
    # Every echo of the real wall a closer to face-on than the cluster's counts against; no floor echo that the
    # cluster's beams did not cover does.
    nearest_cluster = np.sort(pts.beam[labels == ECHO_WALL_A, 1])[-MIN_POINTS]
    assert np.all(against[missed & (pts.beam[:, 1] > nearest_cluster)])
    share = np.count_nonzero(against) / pts.n
    assert share > QualityLimits().unreliable_unexplained
    assert unexplained_finding(float(np.mean(labels == ECHO_OUTLIER)), against=share)[0][0] == UNRELIABLE


def test_an_echo_behind_a_wall_counts_only_within_the_angle_the_wall_answered_at():
    """Behind the wall (later than its mirror echo): against where the wall answered beams as far off its normal,
    not beyond (a narrow beam hears nothing of a wall 40° off axis, and the floor answers instead).  In front of
    it: against only nearer face-on than the wall's ``min_face_on`` most face-on echoes."""
    own_cos = [1.0, 0.99, 0.98, 0.97, 0.96, 0.95, 0.94, 0.93, 0.92, 0.91]
    cos = np.array([own_cos + [0.995, 0.935, 0.925, 0.5]])
    own = np.array([[True] * 10 + [False] * 4])
    unexplained = ~own[0]
    behind = np.array([[0.0] * 10 + [0.3] * 4])
    assert echoes_against_walls(behind, cos, own, unexplained, 8).tolist() == [False] * 10 + [True, True, True, False]
    assert echoes_against_walls(-behind, cos, own, unexplained, 8).tolist() == [False] * 10 + [True, True, False, False]
    # A wall of fewer echoes than min_face_on clears nothing in front of it; an echo facing no wall never counts.
    assert echoes_against_walls(-behind, cos, own, unexplained, 11).tolist() == [False] * 10 + [True] * 4
    assert not echoes_against_walls(np.full((1, 14), np.inf), cos, own, unexplained, 8).any()


def test_the_level_rests_on_the_share_against_the_walls_and_the_whole_share_is_named():
    lim = QualityLimits()
    for against, level in ((0.0, GOOD), (0.1, DEGRADED), (0.2, UNRELIABLE)):
        found = unexplained_finding(0.3, lim, against=against)
        assert [f[0] for f in found] == [level] and "30 % of the scan's echoes" in found[0][1]
    assert unexplained_finding(0.3, lim)[0][0] == UNRELIABLE
    assert unexplained_finding(0.03, lim, against=0.0) == ()
