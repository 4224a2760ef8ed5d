"""Corners and edges: where they lie and how well (their σ), and edges heard by part of the capsule stack only."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lelsonar.reconstruct.estimate.surfaces import extract_surfaces
from lelsonar.reconstruct.estimate.surfaces.confirm import LONE
from lelsonar.reconstruct.estimate.surfaces.measurement import unit_normal
from lelsonar.reconstruct.estimate.surfaces.placement import echo_point, pair_line_point, with_range
from lelsonar.reconstruct.estimate.surfaces.results import OFF_FAN
from lelsonar.sim.scan import EchoSource
from lelsonar.sim.world_geometry import ElementKind
from lelsonar.sim.world_render import pose_frame
from lelsonar.tools.surface_scores import majority, world_sweep
from tests.test_surfaces import GAMMA, GEOMETRY, Echoes


def _line_point(params: np.ndarray) -> np.ndarray:
    """Two planes' point nearest the origin, by hand: X = a n_a + b n_b with n_a·X = h_a, n_b·X = h_b."""
    na, nb = unit_normal(params[0], params[1]), unit_normal(params[3], params[4])
    c = float(na @ nb)
    a, b = np.linalg.solve(np.array([[1.0, c], [c, 1.0]]), np.array([params[2], params[5]]))
    return a * na + b * nb


def test_a_pair_corners_covariance_is_the_scatter_of_its_planes_intersection():
    # Two walls meeting at 100°, each with its own σ in bearing, tilt and offset, and a correlation.
    params = np.array([0.2, 0.05, 1.2, 0.2 + math.radians(100.0), -0.03, 1.6])
    sd = np.array([0.02, 0.03, 0.004, 0.015, 0.02, 0.006])
    corr = np.eye(6)
    corr[0, 3] = corr[3, 0] = 0.5
    cov6 = corr * np.outer(sd, sd)
    point, cov = pair_line_point(params, cov6)
    assert np.allclose(point, _line_point(params), atol=1e-9)
    rng = np.random.default_rng(1)
    draws = np.array([_line_point(p) for p in rng.multivariate_normal(params, cov6, size=4000)])
    empirical = np.cov(draws.T)
    # Linearised against sampled: each σ within 10 % (σ small against the curvature of the intersection).
    assert np.sqrt(np.diag(cov)) == pytest.approx(np.sqrt(np.diag(empirical)), rel=0.1)


def test_parallel_planes_have_no_line():
    assert pair_line_point(np.array([0.0, 0.0, 1.0, 0.05, 0.0, 2.0]), np.eye(6) * 1e-6) is None


def test_a_range_to_the_corner_narrows_it_along_the_ray_only():
    point = np.array([0.0, 1.0, 1.0])
    cov = np.diag([1e-4, 4e-4, 4e-4])
    rho = float(np.linalg.norm(point))
    new_point, new_cov = with_range(point, cov, rho + 0.01, 0.004)
    ray = point / rho
    across = np.array([0.0, 1.0, -1.0]) / math.sqrt(2.0)
    # Along the ray: the two σ combined as independent Gaussians (1/σ² add); across it and along x: as before.
    prior = float(ray @ cov @ ray)
    assert float(ray @ new_cov @ ray) == pytest.approx(1 / (1 / prior + 1 / 0.004**2), rel=1e-6)
    assert float(across @ new_cov @ across) == pytest.approx(float(across @ cov @ across), rel=1e-6)
    assert new_cov[0, 0] == pytest.approx(cov[0, 0])
    assert float(ray @ (new_point - point)) == pytest.approx(0.01 * prior / (prior + 0.004**2), rel=1e-6)


def _echo_point_scatter(rho, s_rho, beta, s_beta, tilt, s_tilt, n=200_000, seed=3):
    """Points ``ρ u(β, t)`` drawn with Gaussian range, bearing and tilt, less the claimed point."""
    rng = np.random.default_rng(seed)
    r = rho + s_rho * rng.standard_normal(n)
    b = beta + s_beta * rng.standard_normal(n)
    t = tilt + s_tilt * rng.standard_normal(n)
    pts = r[:, None] * np.stack([np.sin(t), np.cos(t) * np.cos(b), np.cos(t) * np.sin(b)], axis=1)
    return pts - rho * unit_normal(beta, tilt)


@pytest.mark.parametrize(
    "s_beta,s_tilt",
    # A sure direction; a bearing unsure by a region's reach; an unsure tilt; both unsure, the bearing unknown.
    [(0.01, 0.05), (0.4, 0.02), (0.05, 0.3), (0.3, 0.3), (0.8, 0.4)],
)
def test_an_echo_points_covariance_is_the_second_moment_of_where_its_target_may_lie(s_beta, s_tilt):
    # The target lies on the sphere |X| = ρ in a direction known to (σ_β, σ_t): in every direction, the claimed
    # covariance is the scatter of such targets about the claimed point (the arcs' sagittas too, which move a
    # target whose bearing is unsure by a region's reach off the tangent plane), within the sampling's noise
    # and the second-order terms' neglect.
    rho, s_rho, beta, tilt = 2.0, 0.003, 0.4, 0.3
    point, cov = echo_point(rho, s_rho, beta, s_beta, tilt, s_tilt)
    assert point == pytest.approx(rho * unit_normal(beta, tilt))
    dev = _echo_point_scatter(rho, s_rho, beta, s_beta, tilt, s_tilt)
    empirical = dev.T @ dev / len(dev)
    dirs = np.random.default_rng(0).standard_normal((200, 3))
    dirs /= np.linalg.norm(dirs, axis=1)[:, None]
    ratio = np.einsum("ij,jk,ik->i", dirs, cov, dirs) / np.einsum("ij,jk,ik->i", dirs, empirical, dirs)
    assert ratio.min() > 0.9 and ratio.max() < 1.15


def test_a_sure_echo_points_sigma_is_the_range_along_the_ray_and_each_angle_across_it():
    point, cov = echo_point(2.0, 0.003, 0.4, 1e-4, 0.3, 1e-4)
    u = unit_normal(0.4, 0.3)
    e_b = (unit_normal(0.4 + 1e-7, 0.3) - u) / 1e-7
    e_t = (unit_normal(0.4, 0.3 + 1e-7) - u) / 1e-7
    assert float(u @ cov @ u) == pytest.approx(0.003**2, rel=1e-3)
    # A bearing step moves the point by ρ cos t dβ, a tilt step by ρ dt.
    assert float(e_b @ cov @ e_b) / float(e_b @ e_b) == pytest.approx((2.0 * math.cos(0.3) * 1e-4) ** 2, rel=1e-3)
    assert float(e_t @ cov @ e_t) / float(e_t @ e_t) == pytest.approx((2.0 * 1e-4) ** 2, rel=1e-5)


def test_an_edge_only_the_nearest_capsule_hears_beside_a_farther_wall_is_found_and_says_its_kind_is_open():
    # A wall 2.5 m ahead, every capsule hears it; a vertical edge 0.6 m away and 0.3 m along the stack, weak
    # (diffraction), is over the threshold only in the capsule nearest it, which hears it first.
    e = Echoes(seed=5)
    e.plane(0.0, 2.5)
    x0 = 0.3
    e.across_line(np.array([x0, 0.6, 0.0]), np.array([0.0, 0.0, 1.0]), gain=0.4)
    ranges = e.ranges()
    near = np.nanmin(ranges, axis=0) < 1.0
    assert near.sum() == 1  # the premise: one capsule of the stack hears the edge
    result = extract_surfaces(GAMMA, ranges, GEOMETRY, amplitude=e.amp)
    found = [f for f in (*result.edges, *result.corners) if f.depth < 1.0]
    assert len(found) == 1
    f = found[0]
    # Off the fan on the beam's flank, its amplitude is only a lower bound of its peak: strength cannot say
    # corner or edge.
    assert not f.settled and any(OFF_FAN in r for r in f.reasons)
    assert f.capsules is not None and set(f.capsules.tolist()) == {int(np.flatnonzero(near)[0])}
    # Its point is off the true line by no more than 3 σ in that direction (one capsule: no tilt of its own).
    off = f.point - np.array([x0, 0.6, 0.0])
    off[2] = 0.0
    dist = float(np.linalg.norm(off))
    sigma = math.sqrt(float(off @ f.covariance @ off)) / dist
    assert dist <= 3 * sigma
    # The wall is good on its own echoes; an edge off the fan says nothing of its extent, so nothing confirms it a
    # plane.
    assert any(
        s.offset == pytest.approx(2.5, abs=0.01) and s.own_quality == "good" and s.reasons == (LONE,)
        for s in result.surfaces
    )


def _world_feature(family: str, seed: int, pose: int, element: int, mount: str):
    model, scan, _, result = world_sweep(family, seed, pose, mount)
    mine = [f for f in (*result.corners, *result.edges) if majority(scan, f.steps, f)[0] == element]
    return scan, model, mine


def _off_line(scan, model, f, element: int) -> tuple[float, float]:
    """The feature point's distance from the element's true line and its σ in that direction, m."""
    rot, tr = pose_frame(scan.rig, scan.pose)
    el = model.elements[element]
    d = (el.p1 - el.p0) / np.linalg.norm(el.p1 - el.p0)
    p = rot @ f.point + tr
    off = (p - el.p0) - ((p - el.p0) @ d) * d
    dist = float(np.linalg.norm(off))
    r = rot.T @ (off / dist)
    return dist, math.sqrt(float(r @ f.covariance @ r))


def test_a_box_top_edge_in_a_vertical_fan_heard_by_part_of_the_stack_is_found_within_its_sigma():
    # Boxes world 7, pose 0, vertical fan: the box's top edge (element 111) answers two capsules only, the
    # wall behind it the others.  Found, placed within its σ, and its kind left open (never a wrong one).
    scan, model, mine = _world_feature("boxes", 7, 0, 111, "paper")
    assert model.elements[111].kind == ElementKind.EDGE
    ok = np.isfinite(scan.distance) & (scan.echo_index == 111) & (scan.echo_source != EchoSource.DIFFUSE)
    assert ok.sum(axis=1).max() < scan.distance.shape[1]  # the premise: never the whole stack
    assert mine and all((f.kind == "edge" or not f.settled) and f.capsules is not None for f in mine)
    for f in mine:
        dist, sigma = _off_line(scan, model, f, 111)
        assert dist <= max(3 * sigma, 0.02)


def test_a_ceiling_corner_behind_the_foot_is_placed_on_the_side_of_its_own_steps():
    # Maze world 0, pose 0, vertical fan: the corner of the ceiling with the wall behind (element 71) is
    # heard past the ceiling's foot on the far side; its bearing on the ceiling's trace is that side's.
    scan, model, mine = _world_feature("maze", 0, 0, 71, "paper")
    assert mine and all(f.kind == "corner" for f in mine)
    for f in mine:
        dist, sigma = _off_line(scan, model, f, 71)
        assert dist <= max(3 * sigma, 0.02)


def test_a_target_part_of_the_stack_hears_does_not_end_a_walls_trace_before_its_corner():
    # L room world 25, pose 0, vertical fan: an edge off the fan, heard by part of the stack, lies between the
    # wall's foot and the wall's corner (element 16) along its trace; the corner is still the wall's end.
    scan, model, mine = _world_feature("l_room", 25, 0, 16, "paper")
    assert model.elements[16].kind == ElementKind.DIHEDRAL
    assert mine and all(f.kind == "corner" and f.settled for f in mine)


def test_two_edges_side_by_side_at_one_range_are_two_edges():
    # Corridor world 8, pose 1, horizontal fan: a thin wall's two vertical ends (elements 27 and 26) answer
    # at one range on adjacent steps; the amplitude steps where one's beam pattern hands over to the other's.
    scan, model, first = _world_feature("corridor", 8, 1, 27, "fan")
    _, _, second = _world_feature("corridor", 8, 1, 26, "fan")
    assert model.elements[27].kind == model.elements[26].kind == ElementKind.EDGE
    assert first and second and all(f.kind == "edge" for f in (*first, *second))
    assert not {f.label for f in first} & {f.label for f in second}


def test_a_corner_whose_range_is_not_its_planes_lines_is_placed_by_its_own_echo():
    # Boxes world 8, pose 0, vertical fan: a wall split into two pieces a few degrees apart, their line 3.1 m off,
    # and the box's corner (element 29) at 2.7 m at the range the classification tied to them.  A double bounce
    # comes back from its line's nearest point: 37 cm apart, it is not theirs, and it says so.
    scan, model, mine = _world_feature("boxes", 8, 0, 29, "paper")
    assert model.elements[29].kind == ElementKind.DIHEDRAL
    assert mine
    for f in mine:
        dist, sigma = _off_line(scan, model, f, 29)
        assert dist <= max(3 * sigma, 0.02)
    assert any(any("its echo comes from" in r for r in f.reasons) for f in mine)
