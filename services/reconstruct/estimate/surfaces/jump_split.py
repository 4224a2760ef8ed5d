"""A region holding two targets at one range, one taking over from the other: split where its amplitude jumps.

A box's face and its own convex edge beyond the face's end answer at one range; the amplitude hands over from
one beam pattern to another there (:func:`~.beam_pattern.amplitude_jump`), so the region holds one flank of
each.

Pure functions: no I/O, no state.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from lelsonar.geometry import ArrayGeometry
from lelsonar.reconstruct.estimate.quality import DEGRADED
from lelsonar.reconstruct.estimate.surfaces.beam_pattern import amplitude_jump
from lelsonar.reconstruct.estimate.surfaces.measurement import Measured, measure_region
from lelsonar.reconstruct.estimate.surfaces.regions import subregion
from lelsonar.reconstruct.estimate.surfaces.results import SurfaceOptions

__all__ = ["split_jump"]


def split_jump(
    m: Measured,
    gamma: np.ndarray,
    distance: np.ndarray,
    amplitude: np.ndarray | None,
    geometry: ArrayGeometry,
    opts: SurfaceOptions,
) -> list[Measured] | None:
    """A region whose echo amplitude steps as no one beam pattern does: two targets at one range, one taking
    over from the other (:func:`~.beam_pattern.amplitude_jump`), such as a box's face and its own convex edge
    beyond the face's end.  Split at the jump, each piece cut on the jump's side (the other target's echo ends
    it there, :attr:`~.measurement.Measured.handed_over`), when each keeps ``min_steps``.

    A region cut by a nearer echo or the sweep's end may hold a jump too: one echo's flank alone, its peak past
    the cut, still changes between two steps by no more than ``2 R |Δγ| / L`` (a parabola's slope over a span
    wholly on one side of its vertex is at most twice its mean), inside :func:`~.beam_pattern.amplitude_jump`'s
    bound.  The pieces keep the region's own cuts on their outer sides.

    Returns
    -------
    The two pieces in sweep order, or None (no jump, or a piece too short).
    """
    r = m.region
    if amplitude is None:
        return None
    g = gamma[r.steps]
    jump = amplitude_jump(g, m.step_amplitude)
    if jump is None:
        return None
    k = int(np.searchsorted(g, jump[0])) if g[-1] > g[0] else 0
    if not opts.min_steps <= k <= r.steps.size - opts.min_steps:
        return None
    pieces = (subregion(r, r.steps[:k], r.cut_before, True), subregion(r, r.steps[k:], True, r.cut_after))
    why = (
        DEGRADED,
        f"two echoes at one range: the echo amplitude steps at γ {math.degrees(jump[0]):.1f}° as no one beam "
        "pattern does, so the region is split there and each part is cut where the other's echo takes over",
    )
    out = [measure_region(p, gamma, distance, amplitude, geometry, opts, step=m.step) for p in pieces]
    handed = ((m.handed_over[0], True), (True, m.handed_over[1]))
    return [replace(x, findings=(*x.findings, why), handed_over=h) for x, h in zip(out, handed, strict=True)]
