"""A region cut where its echo is still at its top: its peak may lie past the cut, as far as the fall toward its
other, fading end allows (the piston falls at least as fast as its parabola), not only up to the cut end."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lelsonar.reconstruct.estimate.surfaces.features import cut_peak
from lelsonar.reconstruct.estimate.surfaces.regions import Region
from tests.measured_regions import hand_measured

#: The beam's curvature in log amplitude (1/rad²): a piston of ka ≈ 5, two-way.
BEAM_K = 6.0


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_peak_at_a_cut_ends_top_may_lie_past_the_cut(seed):
    # An edge at 122.3° heard from 124.8° (a nearer echo cuts the region there) to 130.7°, where its echo fades
    # under the receiver's threshold; the amplitudes with 1 % noise.  The fitted vertex sits 1.6° inside the cut.
    rng = np.random.default_rng(seed)
    source = math.radians(122.3)
    gamma = np.radians(np.linspace(124.8, 130.7, 7))
    amplitude = np.exp(-BEAM_K * (gamma - source) ** 2 + 0.01 * rng.standard_normal(gamma.size))
    steps = np.arange(gamma.size)
    region = Region(
        steps=steps, rows=steps, capsules=np.zeros(steps.size, dtype=np.intp), cut_before=True, cut_after=False
    )
    m = hand_measured(
        region,
        bearing=math.radians(126.4),
        depth=2.14,
        span=(float(gamma[0]), float(gamma[-1])),
        step=float(gamma[1] - gamma[0]),
        bearing_source="amplitude peak",
        bearing_stderr=math.radians(0.6),
        step_amplitude=amplitude,
    )
    placed, why = cut_peak(m, gamma, BEAM_K)
    assert why
    assert abs(placed.bearing - source) <= 3.0 * placed.bearing_stderr
    # Not wider than the beam allows: the bound lies no farther than the fading end's reach.
    assert placed.bearing_stderr < math.radians(5.0)
