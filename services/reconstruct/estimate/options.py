"""What every estimator shares: the tunables (:class:`FitOptions`) and a scan-level result (:class:`ScanFit`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lelsonar.errors import ConfigError
from lelsonar.reconstruct.estimate import fit as F
from lelsonar.reconstruct.estimate.results import EdgeLine, FitFailure, PlaneResult

__all__ = ["FitOptions", "ScanFit"]


@dataclass(frozen=True)
class FitOptions:
    """Tunables shared by the methods.

    Parameters
    ----------
    prefilter_fraction : float
        The pre-filter keeps ``|e| ≤ fraction · max|e|`` (§5.3: 10 %).
    min_points : int
        Fewer valid points in a subset give ``FitFailure(TOO_FEW_POINTS)``.
    guard : bool
        Run the outlier-cluster guard in the fast LEL methods.
    beam_half_angle : float
        rad.  The mirror-echo condition: a fitted normal further than this from
        every boresight of the subset cannot have produced the subset's echoes.
    inlier_tolerance : float
        m.  A point is an inlier of a candidate plane within this distance
        (guard and RANSAC).  ~3–5× the range noise.
    min_inlier_fraction : float
        The guard distrusts a LEL minimum with fewer inliers than this.
    lel_starts : {"ls", "six"}
        Starts of the fast LEL: θ_LS only (plus the warm start), or the paper's
        six (§5.2).
    tilt_test_sigma : float
        ``"adaptive"`` switches to the constant-depth model when the corrected
        points' normal is this many σ away from it.
    critical_peak_fraction : float
        0 takes the paper's argmax of ``R`` as the critical step; ``f > 0`` the
        centroid of the top ``f`` of the R peak
        (:func:`lelsonar.reconstruct.estimate.split.critical_step`).  On 50 seeds each of
        paper-test1/2, tilted and an 8°-pitched L, 4 % put the step within ±1
        of the truth in every scan, the argmax in 57 % overall; on an L rolled
        5° both sit 4–5 steps from the geometric truth (the R plateau moves
        with the walls' normals).
    seed : int
        Seeds the RANSAC/FCM generators (baseline and guard).
    ransac_iterations : int
    """

    prefilter_fraction: float = 0.1
    min_points: int = 8
    guard: bool = True
    beam_half_angle: float = float(np.deg2rad(35.0))
    inlier_tolerance: float = 0.01
    min_inlier_fraction: float = 0.5
    lel_starts: str = "ls"
    tilt_test_sigma: float = 3.0
    critical_peak_fraction: float = 0.04
    seed: int = 0
    ransac_iterations: int = 200
    corner_beam_half_angle: float = float(np.deg2rad(50.0))
    corner_tolerance: float = 0.02

    def __post_init__(self) -> None:
        if not 0 < self.prefilter_fraction <= 1:
            raise ConfigError(f"prefilter_fraction must be in (0, 1], got {self.prefilter_fraction}")
        if self.min_points < 4:
            raise ConfigError(f"min_points must be >= 4, got {self.min_points}")
        if not 0 < self.beam_half_angle < np.pi / 2:
            raise ConfigError(f"beam_half_angle must be in (0, π/2) rad, got {self.beam_half_angle}")
        if not self.inlier_tolerance > 0:
            raise ConfigError(f"inlier_tolerance must be > 0 m, got {self.inlier_tolerance}")
        if not 0 <= self.min_inlier_fraction <= 1:
            raise ConfigError(f"min_inlier_fraction must be in [0, 1], got {self.min_inlier_fraction}")
        if self.lel_starts not in ("ls", "six"):
            raise ConfigError(f"lel_starts must be 'ls' or 'six', got {self.lel_starts!r}")
        if not 0 <= self.critical_peak_fraction < 1:
            raise ConfigError(f"critical_peak_fraction must be in [0, 1), got {self.critical_peak_fraction}")
        if self.ransac_iterations < 1:
            raise ConfigError("ransac_iterations must be >= 1")


@dataclass(frozen=True)
class ScanFit:
    """What a scan-level method (``Method.fit_scan``) returns.

    Parameters
    ----------
    plane_a, plane_b : PlaneFit or FitFailure
    data_a, data_b : PlaneData or None
        The points each plane was fitted on (its ``inlier_mask`` indexes them).
    critical_step : int or None
        Replaces the energy peak's critical step; None keeps it.
    edge : EdgeLine or FitFailure or None
        ``corner_edge(plane_a, plane_b)`` if the method has it already; None: the pipeline computes it.
    """

    plane_a: PlaneResult
    plane_b: PlaneResult
    data_a: F.PlaneData | None = None
    data_b: F.PlaneData | None = None
    critical_step: int | None = None
    edge: EdgeLine | FitFailure | None = None
