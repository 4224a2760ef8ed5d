"""A region's measurement built by hand, for the surfaces tests that read only some of its fields."""

from __future__ import annotations

import math

import numpy as np

from lelsonar.reconstruct.estimate.surfaces.measurement import Measured
from lelsonar.reconstruct.estimate.surfaces.regions import Region


def hand_measured(
    region: Region, *, bearing: float, depth: float, span: tuple[float, float], step: float, **fields
) -> Measured:
    """``region`` measured at ``bearing`` (rad) and ``depth`` (m), over ``span`` (rad) with sweep ``step`` (rad).

    What ``fields`` does not set is a plain region's: no tilt, curvature or stack slope, no amplitudes, not
    clipped, every reading at ``depth`` from a capsule at the origin, a centre bearing ± 0.5°.
    """
    nan = float("nan")
    readings = region.rows.size
    values = dict(
        bearing_stderr=math.radians(0.5),
        bearing_source="region centre",
        findings=(),
        depth_stderr=0.001,
        tilt=0.0,
        tilt_stderr=math.radians(0.5),
        curvature=0.0,
        curvature_stderr=nan,
        stack_slope=0.0,
        strength=nan,
        peak=nan,
        peak_inside=False,
        exact=False,
        clipped=False,
        step_amplitude=np.full(region.steps.size, nan),
        positions=np.zeros((readings, 3)),
        ranges=np.full(readings, depth),
        stack_sigma=0.002,
    )
    values.update(fields)
    return Measured(region=region, bearing=bearing, depth=depth, span=span, step=step, **values)
