"""What the surface extractor returns and the options it takes: planes, corners and edges of one sweep."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from lelsonar.errors import ConfigError
from lelsonar.reconstruct.estimate.quality import QualityLimits
from lelsonar.reconstruct.estimate.results import PlaneFit

__all__ = ["SurfaceOptions", "Surface", "Feature", "SurfaceSet", "UNSETTLED", "OFF_FAN"]

#: In a feature's reasons when its echoes cannot settle corner against edge (its kind is then only a placeholder).
UNSETTLED = "kind not settled: its echo's strength is unknown (its peak lies outside the sweep or under a nearer echo)"

#: Beside it for a target only part of the capsule stack hears: off the fan, on the beam's flank.
OFF_FAN = (
    "heard by part of the capsule stack only, so off the fan on the beam's flank: its echo's strength is only a "
    "lower bound of its peak"
)


@dataclass(frozen=True)
class SurfaceOptions:
    """Where the extractor draws its lines.

    Parameters
    ----------
    range_tolerance : float
        m: a region's steadiness (:func:`~.regions.find_regions`).
    max_gap, min_steps : int
        As :func:`~.regions.find_regions`.
    on_trace : float
        m: a region's point lies on a plane's trace within this (plus 3 σ of both).
    foot_separation : float
        rad: a region this close in bearing to a plane is that plane's own echo, not its end.
    weak_echo : float
        An echo below this share of the sweep's strongest at its range (a mirror's or a corner's, up to
        1.5× a mirror's) diffracts (an edge, about 0.2× a mirror's).
    absorption_db_per_m : float
        Air absorption at 40 kHz, to compare amplitudes at different ranges.
    curvature_sigmas : float
        The stack's curvature must stand this many σ above 0 to call a line across the stack.
    beyond_cut : float
        rad: how far past a cut end of its region a target may lie (about the beam's half-width).
    joint_corners : bool
        Fit the walls that meet at concave corners together with their corners (the joint corner model).
    limits : QualityLimits
    """

    range_tolerance: float = 0.015
    max_gap: int = 2
    min_steps: int = 3
    on_trace: float = 0.03
    foot_separation: float = math.radians(8.0)
    weak_echo: float = 0.35
    absorption_db_per_m: float = 1.3
    curvature_sigmas: float = 4.0
    beyond_cut: float = math.radians(40.0)
    joint_corners: bool = True
    limits: QualityLimits = field(default_factory=QualityLimits)

    def __post_init__(self) -> None:
        if not (self.range_tolerance > 0 and self.on_trace > 0 and self.foot_separation > 0):
            raise ConfigError("SurfaceOptions: range_tolerance, on_trace and foot_separation must be > 0")
        if not (0 < self.weak_echo < 1 and self.curvature_sigmas > 0 and self.absorption_db_per_m >= 0):
            raise ConfigError("SurfaceOptions: weak_echo in (0, 1), curvature_sigmas > 0, absorption >= 0")


@dataclass(frozen=True, eq=False)
class Surface:
    """A planar segment: its fit (plane, observed patch, σ, verdict with reasons) and its σ's shape.

    Attributes
    ----------
    label : str
        ``s1``, ``s2`` … in sweep order.
    plane : PlaneFit
        Normal, offset, patch, residual σ, standard errors and verdict (its ``label`` is the
        fit's slot, not the surface's name).
    bearing, tilt : float
        rad: the normal's direction in the fan and out of it (along the stack).
    covariance : (3, 3) array
        Over (bearing rad, tilt rad, offset m).
    bearing_source : str
        ``"amplitude peak"``, ``"region centre"`` or ``"undetermined"``.
    steps : (k,) int array
    n_echoes : int
    rows, capsules : (n_echoes,) int arrays, optional
        Its readings: step and capsule of each (a region seen by some capsules only shares its steps
        with a nearer target's in the others).
    fit_quality : str
        The verdict its own echoes give its plane, before the sweep is asked to confirm it a plane
        (:mod:`~lelsonar.reconstruct.estimate.surfaces.confirm`); empty: the same as ``quality``.
    """

    label: str
    plane: PlaneFit
    bearing: float
    tilt: float
    covariance: np.ndarray
    bearing_source: str
    steps: np.ndarray
    n_echoes: int
    rows: np.ndarray | None = None
    capsules: np.ndarray | None = None
    fit_quality: str = ""

    @property
    def normal(self) -> np.ndarray:
        return self.plane.normal

    @property
    def offset(self) -> float:
        return float(self.plane.offset)

    @property
    def quality(self) -> str:
        return self.plane.quality

    @property
    def reasons(self) -> tuple[str, ...]:
        return tuple(self.plane.quality_reasons)

    @property
    def own_quality(self) -> str:
        """The verdict of its plane on its own echoes (``fit_quality``, else ``quality``)."""
        return self.fit_quality or self.quality


@dataclass(frozen=True, eq=False)
class Feature:
    """A concave corner or a convex (diffracting) edge: a line through ``point``.

    Attributes
    ----------
    kind : {"corner", "edge"}
    label : str
    point : (3,) array
        m, array frame.
    direction : (3,) array
        Unit direction of the line.
    covariance : (3, 3) array
        Of ``point``, m².
    bearing, depth : float
        rad, m: where the region of constant depth put it.
    surfaces : tuple of str
        Labels of the planes it ends or joins.
    reasons : tuple of str
        The evidence for its class.
    steps : (k,) int array
    n_echoes : int
    rows, capsules : (n_echoes,) int arrays, optional
        Its readings: step and capsule of each (a target only part of the stack hears shares its steps
        with a farther one's in the other capsules).
    """

    kind: str
    label: str
    point: np.ndarray
    direction: np.ndarray
    covariance: np.ndarray
    bearing: float
    depth: float
    surfaces: tuple[str, ...]
    reasons: tuple[str, ...]
    steps: np.ndarray
    n_echoes: int
    rows: np.ndarray | None = None
    capsules: np.ndarray | None = None

    @property
    def settled(self) -> bool:
        """Whether its evidence settles its kind (else ``kind`` is a placeholder and a reason says so)."""
        return not any(UNSETTLED in r for r in self.reasons)


@dataclass(frozen=True, eq=False)
class SurfaceSet:
    """What one sweep saw.

    Attributes
    ----------
    surfaces : tuple of Surface
    corners, edges : tuple of Feature
    n_echoes : int
        Readings of the scan.
    unexplained : dict of str to int
        Readings in no region, by why (their share of ``n_echoes`` is the name's).
    """

    surfaces: tuple[Surface, ...]
    corners: tuple[Feature, ...]
    edges: tuple[Feature, ...]
    n_echoes: int
    unexplained: dict[str, int]

    @property
    def n_unexplained(self) -> int:
        return int(sum(self.unexplained.values()))

    def unexplained_shares(self) -> dict[str, float]:
        """Each cause's share of the scan's readings."""
        n = max(self.n_echoes, 1)
        return {k: v / n for k, v in self.unexplained.items()}
