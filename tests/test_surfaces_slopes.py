"""Each step's slope along the stack, compiled: the NumPy formulas' numbers to the bit.

:func:`~lelsonar.reconstruct.estimate.surfaces.slopes.step_slopes` runs as one kernel.  The reference here is
the same formulas in NumPy (``np.bincount``'s sums per step, ``np.sum`` of the pooled squares): slopes, σ and
``Σ(x − x̄)²`` must match exactly on seeded regions, steps of one to four capsules, steps without a spread
along the stack, and regions long enough that the pooled sum is added pairwise.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from lelsonar.reconstruct.estimate.surfaces.regions import Region
from lelsonar.reconstruct.estimate.surfaces.slopes import step_slopes

CAPSULE_X = np.array([-0.12, -0.04, 0.04, 0.12])


def _reference(steps, rows, x, d, min_readings):
    k = steps.size
    pos = np.searchsorted(steps, rows)
    n = np.bincount(pos, minlength=k).astype(float)
    with np.errstate(invalid="ignore", divide="ignore"):
        mx = np.bincount(pos, weights=x, minlength=k) / n
        md = np.bincount(pos, weights=d, minlength=k) / n
        sxx = np.bincount(pos, weights=(x - mx[pos]) ** 2, minlength=k)
        sxd = np.bincount(pos, weights=(x - mx[pos]) * (d - md[pos]), minlength=k)
        slopes = np.where((n >= max(min_readings, 2)) & (sxx > 0), sxd / sxx, np.nan)
        resid = d - md[pos] - np.nan_to_num(slopes[pos]) * (x - mx[pos])
    dof = float(np.sum(np.maximum(n - 2, 0)))
    if not dof > 0:
        return slopes, np.full(k, np.nan), sxx
    noise = math.sqrt(float(np.sum(np.where(n[pos] > 2, resid * resid, 0.0))) / dof)
    with np.errstate(divide="ignore"):
        return slopes, np.where(np.isfinite(slopes), noise / np.sqrt(sxx), np.nan), sxx


def _region(rng: np.random.Generator, k: int, max_capsules: int, same_x: bool):
    """A region of ``k`` steps, each with 1..``max_capsules`` capsules' readings of a tilted plane plus noise."""
    rows, capsules = [], []
    for s in range(k):
        heard = np.sort(rng.choice(4, size=int(rng.integers(1, max_capsules + 1)), replace=False))
        rows.extend([s + 10] * heard.size)
        capsules.extend(heard.tolist())
    rows_a, caps_a = np.array(rows), np.array(capsules)
    x = np.zeros(rows_a.size) if same_x else CAPSULE_X[caps_a]
    positions = np.stack([x, np.cos(rows_a * 0.01), np.sin(rows_a * 0.01)], axis=1)
    d = 1.2 + 0.05 * x + rng.normal(0.0, 0.002, rows_a.size)
    region = Region(np.arange(10, 10 + k), rows_a, caps_a, False, False)
    return SimpleNamespace(region=region, positions=positions, ranges=d)


@pytest.mark.parametrize("min_readings", [2, 3])
@pytest.mark.parametrize(
    ("k", "max_capsules", "same_x"), [(5, 4, False), (40, 4, False), (200, 4, False), (30, 2, False), (12, 4, True)]
)
def test_step_slopes_match_numpy_bit_for_bit(k, max_capsules, same_x, min_readings):
    rng = np.random.default_rng(k * 10 + max_capsules)
    m = _region(rng, k, max_capsules, same_x)
    got = step_slopes(m, min_readings=min_readings)
    want = _reference(m.region.steps, m.region.rows, m.positions[:, 0], m.ranges, min_readings)
    for g, w in zip(got, want, strict=True):
        assert g.dtype == w.dtype and g.shape == w.shape
        assert g.tobytes() == w.tobytes()
