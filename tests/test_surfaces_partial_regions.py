"""A target part of the capsule stack hears drifts with the radial offset as any other: its readings are one
region over a wide beam, as a wall's are, and a target at another depth still stands apart."""

from __future__ import annotations

import math

import numpy as np

from lelsonar.reconstruct.estimate.surfaces.flanks import partial_regions
from lelsonar.reconstruct.estimate.surfaces.regions import Region
from lelsonar.reconstruct.estimate.surfaces.results import SurfaceOptions

#: m: the capsules' distance from the rotation axis.
OFFSET = 0.03
#: m: the stack's length (four capsules 8 cm apart) plus the range tolerance, as the extractor's spread.
SPREAD = 0.24 + SurfaceOptions().range_tolerance


def _edge_beside_a_wall(rng: np.random.Generator, *, far_after: float | None = None):
    """A wide beam (58°) sweeping an edge 0.385 m from the axis at bearing 13.8° that only capsules 0 and 1
    hear, ``ρ − r·cos(γ − β)`` plus 2 mm of noise, while capsules 2 and 3 hear a wall 1.2 m away on every
    step (the region held already); past ``far_after`` (rad) the edge's capsules hear a target 4 cm deeper."""
    gamma = np.arange(math.radians(-100.0), math.radians(130.0), math.radians(0.879))
    rho, beta = 0.385, math.radians(13.8)
    d = np.empty((gamma.size, 4))
    d[:, :2] = rho - OFFSET * np.cos(gamma - beta)[:, None] + rng.normal(0.0, 0.002, (gamma.size, 2))
    d[(gamma < math.radians(-68.6)) | (gamma > math.radians(96.7)), :2] = np.nan  # the edge's echo fades
    if far_after is not None:
        d[gamma > far_after, :2] += 0.04
    d[:, 2:] = 1.2 + rng.normal(0.0, 0.002, (gamma.size, 2))
    steps = np.arange(gamma.size, dtype=np.intp)
    wall = Region(
        steps=steps,
        rows=np.repeat(steps, 2),
        capsules=np.tile(np.array([2, 3], dtype=np.intp), gamma.size),
        cut_before=True,
        cut_after=True,
    )
    return gamma, d, wall


def test_a_partial_targets_drift_over_a_wide_beam_is_one_region():
    gamma, d, wall = _edge_beside_a_wall(np.random.default_rng(26))
    opts = SurfaceOptions()
    assert len(partial_regions(d, [wall], opts, SPREAD)) > 1  # without the drift taken off: split
    (region,) = partial_regions(d, [wall], opts, SPREAD, gamma=gamma, radial_offset=OFFSET)
    heard = np.flatnonzero(np.isfinite(d[:, :2]).any(axis=1))
    assert region.steps.tolist() == heard.tolist()
    assert region.n_echoes == np.count_nonzero(np.isfinite(d[:, :2]))
    assert set(region.capsules.tolist()) == {0, 1}
    assert not region.cut_before and not region.cut_after


def test_a_partial_target_at_another_depth_past_the_drift_stays_apart():
    far = math.radians(87.6)
    gamma, d, wall = _edge_beside_a_wall(np.random.default_rng(26), far_after=far)
    regions = partial_regions(d, [wall], SurfaceOptions(), SPREAD, gamma=gamma, radial_offset=OFFSET)
    assert len(regions) >= 2
    assert all(not (gamma[r.steps] > far).any() or (gamma[r.steps] > far).all() for r in regions)
