"""A plane is not good on ranges that curve along the capsule stack as a line across it does: far away, a wall's
junction with a floor slopes along the stack as a tilted wall would, and only the curvature tells them apart."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lelsonar.reconstruct.estimate.surfaces.fitting import curved_as_a_line
from lelsonar.reconstruct.estimate.surfaces.regions import Region
from tests.measured_regions import hand_measured


def _fitted_curvature(x: np.ndarray, d: np.ndarray) -> tuple[float, float]:
    """Least squares ``d = a + b x + c x²`` over readings at capsule offsets ``x``: ``c`` and its σ."""
    design = np.stack([np.ones_like(x), x, x * x], axis=1)
    coef, *_ = np.linalg.lstsq(design, d, rcond=None)
    resid = d - design @ coef
    cov = np.linalg.inv(design.T @ design) * float(resid @ resid) / (d.size - 3)
    return float(coef[2]), math.sqrt(float(cov[2, 2]))


@pytest.mark.parametrize(("line", "expected"), [(True, True), (False, False)])
def test_ranges_curved_as_a_far_lines_are_said_to_be_maybe_a_line(line, expected):
    # 5.3 m away, 0.3 m below the fan: the junction answers from √(ρ² + (x − z)²) at each capsule offset x along the
    # stack, the plane tilted to the same slope from a straight profile.  500 readings at 2 mm noise give the
    # curvature to ±0.014/m; the line's is 1/(2ρ') ≈ 0.094/m.
    rng = np.random.default_rng(3)
    rho, z = 5.3, -0.3
    x = np.tile(np.array([-0.12, -0.04, 0.04, 0.12]), 125)
    if line:
        d = np.sqrt(rho * rho + (x - z) ** 2)
    else:
        slope = -z / math.hypot(rho, z)
        d = math.hypot(rho, z) + slope * x
    d = d + rng.normal(0.0, 0.002, x.size)
    c, sc = _fitted_curvature(x, d)
    steps = np.arange(125)
    region = Region(
        steps=steps, rows=np.repeat(steps, 4), capsules=np.tile(np.arange(4), 125), cut_before=False, cut_after=False
    )
    m = hand_measured(
        region,
        bearing=0.0,
        depth=float(np.median(d)),
        span=(-0.2, 0.2),
        step=0.001,
        curvature=c,
        curvature_stderr=sc,
    )
    assert bool(curved_as_a_line(m)) == expected, (c, sc)
