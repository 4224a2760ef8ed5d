"""What a sweep must show before one of its planes may claim good: evidence only a plane gives, and a σ that
places its trace within the accuracy a good surface promises.

Two tests on top of each plane's own verdict (:func:`~lelsonar.reconstruct.estimate.quality.assess_plane`):

* **confirmation**.  In one sweep, a lone region of constant depth is what a mirror, a concave corner's double
  bounce and an edge's diffraction all give.  Each answers at one range while it is in the beam, with the beam
  pattern's amplitudes across γ.  A point-like reflector at range ``ρ`` differs from a mirror at depth ``ρ`` only
  by ``r² sin²(γ − β)/(2ρ)`` in the capsules' radial offset ``r`` (a fraction of a millimetre), and a corner
  retro-reflects as strongly as a wall, an edge as strongly as its gain makes it.  A plane is confirmed only by
  what a lone reflector cannot give: a feature the sweep ties to it by a test (its end found on its trace at
  its own bearing, its concave corner with another plane at their double-bounce range, its double bounce with
  a surface across the fan).  A target whose bearing nothing determined, set on the trace where its depth
  crosses it, confirms nothing: a box's far edges lie on the trace of its near edge taken for a plane.
  Without a confirmation the plane is degraded, and says why.
* **accuracy**.  A good surface is placed within :data:`ACCURACY` over :data:`TRACE_REACH` either side of its
  foot at two σ: ``2 √(σ_h² + (L σ_n)²) ≤ ACCURACY`` with ``σ_n`` its normal's σ (bearing and tilt) and ``σ_h``
  its offset's.  A wall well placed in range can be poorly placed in bearing; past that bound it is degraded.

The verdict before these tests stays on the surface (:attr:`~.results.Surface.fit_quality`): it is what the
surface's own echoes say of its plane, which the L planes of record are checked against.

Pure functions: no I/O, no state.
"""

from __future__ import annotations

import math
from dataclasses import replace

from lelsonar.reconstruct.estimate.quality import DEGRADED, GOOD, add_findings
from lelsonar.reconstruct.estimate.results import PlaneFit
from lelsonar.reconstruct.estimate.surfaces.results import Surface

__all__ = ["ACCURACY", "TRACE_REACH", "LONE", "confirm_surfaces", "trace_stderr"]

#: m: what a good surface promises: its trace within this of the wall's, at two σ.
ACCURACY = 0.02
#: m: over this far either side of its foot (the patch a planner uses of a wall it faced).
TRACE_REACH = 0.5

#: The reason a plane nothing else in the sweep ties is not good.
LONE = (
    "a lone echo at one range: nothing else in the sweep (its end on its trace, a corner it shares with another "
    "plane, its double bounce with the floor or ceiling) confirms a plane, and a concave corner's or an edge's "
    "echo looks the same"
)


def trace_stderr(surface: Surface, reach: float = TRACE_REACH) -> float:
    """σ of the surface's trace ``reach`` from its foot, m: ``√(σ_h² + (reach · σ_n)²)``.

    Parameters
    ----------
    surface : Surface
        Its plane's ``normal_stderr`` (rad, bearing and tilt together) and ``offset_stderr`` (m).
    reach : float
        m along the trace from the foot.
    """
    sn, sh = surface.plane.normal_stderr, surface.plane.offset_stderr
    if not (math.isfinite(sn) and math.isfinite(sh)):
        return math.inf
    return math.hypot(sh, reach * math.tan(min(sn, 0.5 * math.pi - 1e-9)))


def confirm_surfaces(surfaces: list[Surface], confirmed: set[str]) -> list[Surface]:
    """Each surface, degraded where the sweep does not confirm it a plane or its σ does not place its trace
    within :data:`ACCURACY` (see the module).

    Parameters
    ----------
    surfaces : list of Surface
        The sweep's planes with their own verdicts.
    confirmed : set of str
        Labels of the planes a feature of the sweep ties by a test a lone reflector does not pass: its own
        bearing found on the plane's trace, a double-bounce range, a line along the stack explaining the
        ranges.  A region whose bearing nothing determined, set on a plane's trace where its depth crosses it,
        is placed there, not found there: it confirms nothing.

    Returns
    -------
    The surfaces in order, each with ``fit_quality`` set to its own verdict.
    """
    out = []
    for s in surfaces:
        own = s.quality
        findings: list[tuple[str, str]] = []
        if own == GOOD and s.label not in confirmed:
            findings.append((DEGRADED, LONE))
        se = trace_stderr(s)
        if own == GOOD and 2.0 * se > ACCURACY:
            findings.append(
                (
                    DEGRADED,
                    f"its trace {100 * TRACE_REACH:.0f} cm from its foot is known to ±{100 * 2 * se:.1f} cm at 2 σ "
                    f"(normal ±{math.degrees(s.plane.normal_stderr):.2f}°, offset ±{1000 * s.plane.offset_stderr:.1f}"
                    f" mm): more than the {100 * ACCURACY:.0f} cm a good surface promises",
                )
            )
        plane = add_findings(s.plane, tuple(findings))
        out.append(replace(s, plane=plane if isinstance(plane, PlaneFit) else s.plane, fit_quality=own))
    return out
