"""Corners and edges as features: each where its planes or its own echo put it, along its line.

A concave corner of two fitted planes lies on their line, with their covariance (:mod:`.placement`); any other
corner or edge where its own echo comes from, off the fan by its stack slope's tilt.  Its direction: along the
two planes' line, along its one plane across the ray to it (that plane's end), across the fan for a line across
the stack, else along the stack.
"""

from __future__ import annotations

import math

import numpy as np

from lelsonar.reconstruct.estimate.normals import cross3
from lelsonar.reconstruct.estimate.surfaces.joint import JointWall
from lelsonar.reconstruct.estimate.surfaces.measurement import Measured, unit_normal
from lelsonar.reconstruct.estimate.surfaces.placement import echo_point, line_direction, pair_line_point, with_range
from lelsonar.reconstruct.estimate.surfaces.results import Feature, Surface, SurfaceOptions

__all__ = ["Kind", "place_features"]

#: A classified region: its kind ("corner" or "edge"), why, and the regions (indices) it ties to.
Kind = tuple[str, list[str], list[int]]


def _feature(
    kind: str,
    label: str,
    m: Measured,
    direction: np.ndarray,
    surfaces: tuple[str, ...],
    reasons: list[str],
    opts: SurfaceOptions,
    placed: tuple[np.ndarray, np.ndarray] | None = None,
) -> Feature:
    """``placed``: the point and its covariance where the planes it joins put it; else its own echo's point,
    off the fan by its stack slope's tilt (with one capsule, anywhere within the beam's half-width)."""
    if placed is None:
        tilt_se = m.tilt_stderr if math.isfinite(m.tilt_stderr) else opts.beyond_cut / math.sqrt(3.0)
        placed = echo_point(m.depth, m.depth_stderr, m.bearing, m.bearing_stderr, m.tilt, tilt_se)
    return Feature(
        kind=kind,
        label=label,
        point=placed[0],
        direction=direction,
        covariance=placed[1],
        bearing=m.bearing,
        depth=m.depth,
        surfaces=surfaces,
        reasons=tuple(reasons),
        steps=m.region.steps.copy(),
        n_echoes=m.region.n_echoes,
        rows=m.region.rows.copy(),
        capsules=m.region.capsules.copy(),
    )


def _pair_placement(
    ia: int, ib: int, m: Measured, surface_of: dict[int, Surface], joint: dict[int, JointWall]
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """A pair corner's line from its two fitted planes: its nearest point, that point's covariance (the
    planes' full covariance through the intersection) and its direction."""
    sa, sb = surface_of.get(ia), surface_of.get(ib)
    if sa is None or sb is None:
        return None
    params = np.array([sa.bearing, sa.tilt, sa.offset, sb.bearing, sb.tilt, sb.offset])
    ja, jb = joint.get(ia), joint.get(ib)
    tied = ja is not None and jb is not None and ja.full is not None
    if ja is not None and jb is not None and ja.full is not None:
        idx = [3 * ja.index + k for k in range(3)] + [3 * jb.index + k for k in range(3)]
        cov6 = ja.full[np.ix_(idx, idx)]
    else:
        cov6 = np.zeros((6, 6))
        cov6[:3, :3], cov6[3:, 3:] = sa.covariance, sb.covariance
    line = pair_line_point(params, cov6)
    if line is None:
        return None
    point, cov = line
    if not tied:
        # The walls fitted apart: the corner's own double-bounce range is a measurement they did not use.
        point, cov = with_range(point, cov, m.depth, m.depth_stderr)
    return point, cov, line_direction(params)


def place_features(
    measured: list[Measured],
    kinds: dict[int, Kind],
    across_lines: set[int],
    surface_of: dict[int, Surface],
    joint: dict[int, JointWall],
    opts: SurfaceOptions,
) -> tuple[list[Feature], list[Feature]]:
    """The corners and the edges, each where its planes or its own echo put it, along its line.

    Parameters
    ----------
    measured : list of Measured
        Every region of the sweep, placed as its kind says.
    kinds : dict
        The kind of each region that is no plane, by index into ``measured``.
    across_lines : set of int
        The regions that are lines across the fan.
    surface_of : dict
        The fitted plane of each region that is one.
    joint : dict
        Each wall fitted with its concave corners (:func:`~.fitting.joint_fit`).
    opts : SurfaceOptions

    Returns
    -------
    corners, edges : list of Feature
        Labelled ``c1, c2, …`` and ``e1, e2, …`` in region order.
    """
    corners: list[Feature] = []
    edges: list[Feature] = []
    stack_axis = np.array([1.0, 0.0, 0.0])
    for i, (kind, reasons, ties) in sorted(kinds.items()):
        m = measured[i]
        tied = tuple(surface_of[j].label for j in ties if j in surface_of)
        located: tuple[np.ndarray, np.ndarray] | None = None
        if i in across_lines:
            direction = cross3(stack_axis, unit_normal(m.bearing))
        elif len(ties) >= 2:
            pair_line = _pair_placement(ties[0], ties[1], m, surface_of, joint)
            if pair_line is not None:
                located, direction = (pair_line[0], pair_line[1]), pair_line[2]
            else:
                a, b = measured[ties[0]], measured[ties[1]]
                direction = cross3(unit_normal(a.bearing, a.tilt), unit_normal(b.bearing, b.tilt))
        elif len(ties) == 1:
            # A plane's end: a line in that plane, square to the ray to its nearest point (where it answers).
            pj = measured[ties[0]]
            direction = cross3(unit_normal(pj.bearing, pj.tilt), unit_normal(m.bearing, m.tilt))
            if float(np.linalg.norm(direction)) < math.sin(opts.foot_separation):
                direction = stack_axis
        else:
            direction = stack_axis  # along the stack: a line the fan crosses
        direction = direction / max(float(np.linalg.norm(direction)), 1e-12)
        if direction[int(np.argmax(np.abs(direction)))] < 0:
            direction = -direction
        out = corners if kind == "corner" else edges
        out.append(_feature(kind, f"{kind[0]}{len(out) + 1}", m, direction, tied, reasons, opts, located))
    return corners, edges
