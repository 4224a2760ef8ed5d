"""A face that ends between the capsules is no line across the stack: those whose foot falls on it hear its
mirror (a straight profile along the stack), the rest its end's edge (a hyperbola tangent to it), so its ranges
curve as neither one target does."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lelsonar.reconstruct.estimate.surfaces.evidence import across_stack, bend_of_one_target
from lelsonar.reconstruct.estimate.surfaces.fitting import bent_as_two_targets
from lelsonar.reconstruct.estimate.surfaces.regions import Region
from lelsonar.reconstruct.estimate.surfaces.results import SurfaceOptions
from lelsonar.reconstruct.estimate.surfaces.stack import stack_fits
from tests.measured_regions import hand_measured

CAPSULES = np.array([-0.12, -0.04, 0.04, 0.12])
NOISE = 0.002  # one reading's range σ, m
STEPS = 100


def _face_ranges(h: float, lean: float, end: float | None) -> np.ndarray:
    """Each capsule's range to a face at ``h`` whose normal leans ``lean`` (rad) along the stack, ending at ``end``
    along it (m, the face's own coordinate; None: no end): its mirror where the capsule's foot falls on it, else
    the distance to its end's edge (a line across the stack)."""
    n_x, n_w = math.sin(lean), math.cos(lean)
    mirror = h - CAPSULES * n_x
    if end is None:
        return mirror
    along = CAPSULES * n_w  # each capsule's foot, along the face
    edge = np.hypot(mirror, along - end)
    return np.where(along <= end, mirror, edge)


def _measured(per_capsule: np.ndarray, seed: int):
    rng = np.random.default_rng(seed)
    steps = np.arange(STEPS)
    rows = np.repeat(steps, CAPSULES.size)
    capsules = np.tile(np.arange(CAPSULES.size), STEPS)
    d = np.tile(per_capsule, STEPS) + rng.normal(0.0, NOISE, rows.size)
    positions = np.zeros((rows.size, 3))
    positions[:, 0] = CAPSULES[capsules]
    _, (quad, quad_cov, _) = stack_fits(positions[:, 0], rows, d)
    region = Region(steps=steps, rows=rows, capsules=capsules, cut_before=False, cut_after=False)
    return hand_measured(
        region,
        bearing=0.0,
        depth=float(np.min(np.median(d.reshape(STEPS, -1), axis=0))),
        span=(-0.3, 0.3),
        step=0.006,
        positions=positions,
        ranges=d,
        curvature=float(quad[1]),
        curvature_stderr=math.sqrt(float(quad_cov[1, 1])),
    )


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_face_ending_between_the_capsules_is_no_line_across_the_stack(seed):
    # A box face 0.72 m away leaning 9° along the stack, ending 2 cm short of the middle: the fitted
    # curvature lies within half of a line's 1/(2ρ), which alone would call it a line across the stack.
    m = _measured(_face_ranges(0.72, math.radians(9.0), -0.02), seed)
    line = 1.0 / (2.0 * m.depth)
    assert m.curvature > 4 * m.curvature_stderr and abs(m.curvature - line) < 0.5 * line
    opts = SurfaceOptions()
    assert bend_of_one_target(m) > opts.curvature_sigmas
    assert not across_stack(m, opts)
    assert bent_as_two_targets(m, opts.curvature_sigmas)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_one_target_bends_alike_across_the_stack(seed):
    opts = SurfaceOptions()
    # A line across the stack 0.72 m away, its nearest point 5 cm along the stack: a line across it still.
    line = _measured(np.hypot(0.72, CAPSULES - 0.05), seed)
    assert across_stack(line, opts)
    assert bend_of_one_target(line) < opts.curvature_sigmas
    # The same face without an end: a plane, straight along the stack.
    face = _measured(_face_ranges(0.72, math.radians(9.0), None), seed)
    assert not across_stack(face, opts)
    assert bend_of_one_target(face) < opts.curvature_sigmas
    assert not bent_as_two_targets(face, opts.curvature_sigmas)
