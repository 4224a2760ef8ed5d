"""How the map associates and fuses walls (:class:`FusionConfig`), and the error of a graph that cannot be solved."""

from __future__ import annotations

import math
from dataclasses import dataclass

from lelsonar.errors import ConfigError, LelsonarError

#: χ² with 2 degrees of freedom at 0.999.
CHI2_2_999 = 13.8155


class MapUpdateError(LelsonarError):
    """The factor graph could not take a scan (an ill-posed system): the map takes no more scans, and what it
    had before is the last map published."""


@dataclass(frozen=True)
class FusionConfig:
    """How walls are associated and fused.

    Parameters
    ----------
    gate_chi2 : float
        Largest Mahalanobis distance² of an observation from a wall it joins (χ²₂; 13.8 is p = 0.999).
    max_gap : float
        Largest gap, m, between an observation's stretch and a wall's along the wall for it to join; none by
        default.  Sonar sees a wall only near the foot of its perpendicular, so scans from different places
        see stretches of one wall metres apart; the line is one either way, and the wall keeps its observed
        pieces apart (``join_gap``).
    join_gap : float
        A wall's observed stretches closer than this, m, are one piece of the floor plan; farther apart, the
        space between stays unknown (an opening the scans did not see closed).
    conflict_distance, conflict_angle : float
        An observation outside the gate of a wall it overlaps, but nearer than these (m, rad), is the same
        surface seen in disagreement: it becomes its own wall and both are marked.  Farther, it is another
        surface (a box in front of a wall).
    first_pose_sigma : (float, float, float)
        σ of the first pose's prior ``(x, y, heading)`` where the source gives no covariance.
    default_step_sigma : (float, float, float)
        σ of an odometry step where the source gives no covariance at all.
    step_sigma_floor : (float, float, float)
        Smallest σ of an odometry step (a source that reports none or a constant one).
    corner_reach : float
        The farthest, m, a scan's own corner may lie from two walls' crossing to vouch that they meet there;
        a corner (of two walls, or a scan's own) the map places worse than this at 3σ is none
        (:func:`lelsonar.map.features.wall_corners`).
    good_tolerance : float
        A wall of good evidence is good only if the map places its whole observed stretch within this, m, at
        3σ (its marginal in the map's frame, the poses' uncertainty included); else it is degraded, and says
        how well it is placed.
    relinearize_threshold : float
        ISAM2 relinearizes a variable whose update exceeds this (m or rad).
    relinearize_skip : int
        ISAM2 looks for variables to relinearize every this many updates.
    polish : bool
        A map as read (:meth:`WallMapper.snapshot`) is first converged by Levenberg–Marquardt over the whole
        graph; off, it is ISAM2's estimate (cheaper to read after every scan on a large map).
    flagged_constrain : tuple of str
        Flagged observations of these verdicts, once they agree with a wall of good evidence (within its
        gate), tie their pose to it in the graph with their own covariance and Huber's loss: a degraded
        wall still places the robot.  They never open a wall of the graph nor make one good.  An
        ``unreliable`` observation's own σ is what its verdict disowns, so by default it ties no pose.
    """

    gate_chi2: float = CHI2_2_999
    max_gap: float = math.inf
    join_gap: float = 0.3
    conflict_distance: float = 0.15
    conflict_angle: float = math.radians(10.0)
    first_pose_sigma: tuple[float, float, float] = (1e-3, 1e-3, 1e-3)
    default_step_sigma: tuple[float, float, float] = (0.05, 0.05, math.radians(2.0))
    step_sigma_floor: tuple[float, float, float] = (1e-3, 1e-3, 1e-3)
    corner_reach: float = 0.3
    good_tolerance: float = 0.02
    relinearize_threshold: float = 0.1
    relinearize_skip: int = 10
    polish: bool = True
    flagged_constrain: tuple[str, ...] = ("degraded",)

    def __post_init__(self) -> None:
        for name in (
            "gate_chi2",
            "max_gap",
            "join_gap",
            "conflict_distance",
            "conflict_angle",
            "corner_reach",
            "good_tolerance",
        ):
            v = getattr(self, name)
            if not ((math.isfinite(v) or name == "max_gap") and v >= 0):
                raise ConfigError(f"map {name} must be a finite number ≥ 0, got {v!r}")
        if not (isinstance(self.relinearize_skip, int) and self.relinearize_skip >= 1):
            raise ConfigError(f"map relinearize_skip must be an integer ≥ 1, got {self.relinearize_skip!r}")
        for name in ("first_pose_sigma", "default_step_sigma", "step_sigma_floor"):
            v = getattr(self, name)
            if len(v) != 3 or not all(math.isfinite(x) and x > 0 for x in v):
                raise ConfigError(f"map {name} must be three σ > 0 (m, m, rad), got {v!r}")
