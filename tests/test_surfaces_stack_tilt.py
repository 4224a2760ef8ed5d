"""A target's tilt off the fan from its squared ranges along the capsule stack: exact for a point, a line across
the stack and a plane; a capsule that hears another target leaves the fit; no one target says so."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lelsonar.reconstruct.estimate.surfaces.stack import stack_tilt

#: The stack's capsules along the rotation axis, m, and the range noise of one reading, m.
X = np.array([-0.12, -0.04, 0.04, 0.12])
NOISE = 0.002


def _readings(target, capsules, n_steps=40, seed=0, noise=NOISE):
    """Each capsule's range to ``target(x_c, step)`` over ``n_steps`` steps, with Gaussian noise."""
    rng = np.random.default_rng(seed)
    rows = np.repeat(np.arange(n_steps), len(capsules))
    caps = np.tile(np.asarray(capsules), n_steps)
    d = np.array([target(X[c], s) for s, c in zip(rows, caps, strict=True)]) + noise * rng.standard_normal(rows.size)
    return rows, caps, d


def _sin_t(fit, depth):
    b = fit[0]
    return -b / (2.0 * depth)


@pytest.mark.parametrize("capsules", [(0, 1, 2), (0, 1, 2, 3), (1, 2, 3)])
def test_a_point_across_the_stack_is_placed_off_the_fan_exactly_from_uneven_capsules(capsules):
    # A box's edge across the stack 0.37 m away, 9 cm along the stack below the array's centre: its ranges are a
    # hyperbola along the stack, which a straight fit over uneven capsules turns into a slope tens of degrees off.
    x0, h = -0.09, 0.365
    rows, caps, d = _readings(lambda x, s: math.hypot(h + 0.001 * s, x - x0), capsules)
    depth = math.hypot(h + 0.02, x0)
    fit = stack_tilt(X, rows, caps, d, depth, NOISE)
    assert fit is not None and fit[5]
    # −b/2 is the target's offset along the stack; its σ covers the error.
    assert -fit[0] / 2 == pytest.approx(x0, abs=3 * fit[2] / 2 + 1e-4)
    assert fit[2] / 2 < 0.01


def test_a_plane_tilted_along_the_stack_gives_its_tilt():
    # A wall whose normal leans 8° off the fan, 1.5 m away: d = h − n_x x, κ = n_x².
    t = math.radians(8.0)
    rows, caps, d = _readings(lambda x, s: 1.5 - math.sin(t) * x, (0, 1, 2, 3))
    fit = stack_tilt(X, rows, caps, d, 1.5, NOISE)
    assert fit is not None and fit[5]
    sigma_sin = fit[2] / (2.0 * 1.5)
    assert _sin_t(fit, 1.5) == pytest.approx(math.sin(t), abs=3 * sigma_sin + 1e-3)


def test_two_capsules_of_uneven_side_span_both_bounds_of_the_curvature():
    # Two capsules on one side hear a line across the stack: nothing tells a point from a plane, so the slope's σ
    # spans the two bounds' slopes; the truth lies within it.
    x0, h = -0.06, 1.27
    rows, caps, d = _readings(lambda x, s: math.hypot(h, x - x0), (0, 1), noise=0.0005)
    fit = stack_tilt(X, rows, caps, d, math.hypot(h, x0), 0.0005)
    assert fit is not None and fit[1] == 0.5
    assert abs(-fit[0] / 2 - x0) <= 3 * fit[2] / 2
    # The bracket is as wide as the two bounds' difference (x₀ + x₁ of the capsules heard, over √12).
    assert fit[2] >= abs(X[0] + X[1]) / math.sqrt(12.0)


def test_a_capsule_that_hears_another_target_leaves_the_fit():
    # A first-echo receiver: the capsule at the far end of the stack does not hear the edge and reports a
    # farther one, 4 cm off the edge's hyperbola.
    x0, h = 0.12, 0.35

    def target(x, s):
        return math.hypot(h, x - x0) + (0.04 if x == X[0] else 0.0)

    rows, caps, d = _readings(target, (0, 1, 2, 3))
    depth = math.hypot(h, x0)
    fit = stack_tilt(X, rows, caps, d, depth, NOISE)
    assert fit is not None and fit[5]
    assert list(fit[3]) == [1, 2, 3]
    assert -fit[0] / 2 == pytest.approx(x0, abs=max(3 * fit[2] / 2, 1e-3))


def test_readings_no_one_target_explains_say_so():
    # Two capsules each off their own way by centimetres: no capsule's removal leaves one target's ranges.
    def target(x, s):
        return 1.0 + {X[0]: 0.03, X[1]: -0.02, X[2]: 0.025, X[3]: 0.0}[x] * (1 if s % 2 else -1)

    rows, caps, d = _readings(target, (0, 1, 2, 3))
    fit = stack_tilt(X, rows, caps, d, 1.0, NOISE)
    assert fit is not None and not fit[5]
    assert fit[4] > NOISE
