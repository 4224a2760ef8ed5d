"""Walls fused across scans: data association, the factor graph, and verdicts that carry over.

:class:`WallMapper` takes one :class:`~lelsonar.map.observation.ScanObservation` at a time
(:meth:`WallMapper.add_scan`: one ISAM2 update a scan, not a rebuild) and gives the map on demand
(:meth:`WallMapper.snapshot`).

* **Association.**  Each good wall observation is compared with every wall of the map through the
  predicted pose: the Mahalanobis distance of the innovation on ``(θ, ρ)`` (pose, wall and observation
  covariances), gated at ``gate_chi2``, and the gap between the observed stretch and the wall's.  The
  nearest wall within the gate takes it; no two observations of one scan go to one wall.
* **Verdicts carry over.**  Only good observations enter the graph, so only good evidence moves the poses
  and the walls.  Degraded and unreliable observations are attached to a fused wall they agree with, or
  kept as walls of their own with their own verdict: a wall seen once and flagged stays flagged.
  An observation that overlaps a wall and lies near it but outside the gate is another wall, and both
  are marked as disagreeing: never averaged into a wall that does not exist.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from lelsonar.errors import ConfigError, InvalidMessageError, LelsonarError
from lelsonar.map import graph
from lelsonar.map.features import fuse_features, wall_corners
from lelsonar.map.lines import (
    interval_on_line,
    line_in_world,
    mahalanobis2,
    measurement_jacobians,
    pose_between,
    pose_compose,
    pose_inverse_adjoint,
    world_jacobians,
    wrap,
)
from lelsonar.map.observation import QUALITIES, FeatureObservation, ScanObservation, WallObservation
from lelsonar.map.result import FusedMap, FusedPose, FusedWall

#: χ² with 2 degrees of freedom at 0.999.
CHI2_2_999 = 13.8155

#: A wall is redone for a read when its line or a pose that saw it moved more than this (m or rad): ISAM2 itself
#: stops carrying an update further where it changes a variable by less (its wildfire threshold).
READ_TOLERANCE = 1e-3


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
        Two walls make a corner where their lines cross within this distance of both stretches, m.
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
        gate), tie their pose to it in the graph with their own covariance and Huber's loss: a wall whose
        bearing the scan could not pin still places the robot in range.  They never open a wall of the
        graph nor make one good.
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
    flagged_constrain: tuple[str, ...] = ("degraded", "unreliable")

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


@dataclass
class _Seen:
    """One observation of a wall: which scan, its pose's index, the observation."""

    scan_id: int
    pose_index: int
    obs: WallObservation


@dataclass
class _Track:
    """A wall of the map while it grows.  ``index`` ≥ 0: in the graph (good evidence); −1: flagged only."""

    id: int
    index: int
    seen: list[_Seen]
    flagged: list[_Seen] = field(default_factory=list)
    conflicts: dict[int, str] = field(default_factory=dict)  # other wall id → what differs
    line: np.ndarray = field(default_factory=lambda: np.zeros(2))  # local frame
    covariance: np.ndarray = field(default_factory=lambda: np.eye(2))
    interval: tuple[float, float] = (0.0, 0.0)


def _sensor_points_to_world(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return points[:, :2] @ np.array([[c, s], [-s, c]]) + pose[:2]


class WallMapper:
    """The incremental wall map (see the module docstring)."""

    def __init__(self, config: FusionConfig | None = None) -> None:
        self.config = config or FusionConfig()
        self._graph = graph.MapGraph(self.config.relinearize_threshold, self.config.relinearize_skip)
        self._origin = np.zeros(2)  # world position of the local frame's origin (the first pose)
        self._odometry: list[np.ndarray] = []  # (x, y, ψ) world, per scan
        self._odometry_cov: list[np.ndarray | None] = []
        self._scan_ids: list[int] = []
        self._heights: list[float] = []
        self._poses: list[np.ndarray] = []  # current estimate, local
        self._pose_cov: np.ndarray = np.eye(3)  # marginal of the newest pose (body frame)
        self._pose_covs: list[np.ndarray] = []  # each pose's marginal when it was the newest (body frame)
        self._graph_tracks: list[_Track] = []
        self._isam_walls = 0  # graph walls already in ISAM2 (the newer ones arrived with the scan being added)
        self._flagged_tracks: list[_Track] = []
        self._next_id = 0
        self._step: tuple[np.ndarray, np.ndarray] | None = None  # (Ad(u⁻¹), Q) of the scan being added
        self._features: list[tuple[int, int, FeatureObservation]] = []  # (scan_id, pose index, FeatureObservation)
        self.notes: list[str] = []
        self._failed: str | None = None
        self._read_cache: dict[int, tuple] = {}  # wall id → what its last unpolished read took and gave

    # ------------------------------------------------------------------ properties
    @property
    def scans(self) -> int:
        return len(self._poses)

    @property
    def walls(self) -> int:
        """Walls in the map (in the graph and flagged ones)."""
        return len(self._graph_tracks) + len(self._flagged_tracks)

    # ------------------------------------------------------------------ update
    def add_scan(self, scan: ScanObservation) -> None:
        """Fuse one scan: its pose, its odometry step, its walls and features (one ISAM2 update)."""
        if self._failed is not None:
            raise MapUpdateError(f"the map takes no more scans: {self._failed}; start a new map")
        if scan.scan_id in self._scan_ids:
            raise InvalidMessageError(f"scan {scan.scan_id} is already in the map (scan ids must be unique)")
        for note in scan.notes:
            if note not in self.notes:
                self.notes.append(note)
        k = len(self._poses)
        odo = scan.pose.vector
        if k == 0:
            self._origin = odo[:2].copy()
            predicted = np.array([0.0, 0.0, odo[2]])
            if scan.pose.covariance is not None and np.linalg.eigvalsh(scan.pose.covariance).min() > 0:
                cov = np.array(scan.pose.covariance)
            else:
                cov = np.diag(np.square(self.config.first_pose_sigma))
            self._graph.add_prior(0, predicted, cov)
            pose_cov = cov
        else:
            step = pose_between(self._odometry[-1], odo)
            q = self._step_covariance(scan)
            predicted = pose_compose(self._poses[-1], step)
            self._graph.add_odometry(k - 1, k, step, q)
            ad = pose_inverse_adjoint(step)
            pose_cov = ad @ self._pose_cov @ ad.T + q
            self._step = (ad, q)
        self._graph.add_pose(k, predicted)
        self._odometry.append(odo)
        self._odometry_cov.append(None if scan.pose.covariance is None else np.array(scan.pose.covariance))
        self._scan_ids.append(scan.scan_id)
        self._heights.append(scan.pose.z)
        self._poses.append(predicted)

        touched: list[_Track] = []
        used: set[int] = set()
        for obs in sorted(scan.walls, key=lambda w: QUALITIES.index(w.quality)):
            seen = _Seen(scan.scan_id, k, obs)
            if obs.quality == "good":
                track = self._associate_good(seen, predicted, pose_cov, used)
                touched.append(track)
            else:
                self._associate_flagged(seen, predicted, pose_cov)
        self._features.extend((scan.scan_id, k, f) for f in scan.features)

        try:
            self._graph.update()
        except RuntimeError as exc:  # GTSAM's indeterminate or ill-conditioned system
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            self._failed = f"scan {scan.scan_id} made the graph unsolvable ({first})"
            raise MapUpdateError(self._failed) from None
        self._isam_walls = len(self._graph_tracks)
        self._poses = [self._graph.pose(i) for i in range(k + 1)]
        for t in self._graph_tracks:
            t.line = self._graph.wall(t.index)
        self._pose_cov = self._graph.pose_marginal(k)
        self._pose_covs.append(self._pose_cov)
        for t in touched:
            t.covariance = self._graph.wall_marginal(t.index)
            t.interval = self._interval(t, t.seen)

    def _step_covariance(self, scan: ScanObservation) -> np.ndarray:
        cfg = self.config
        if scan.step_covariance is not None:
            return np.array(scan.step_covariance) + np.diag(np.square(cfg.step_sigma_floor))
        previous_cov = self._odometry_cov[-1]
        if scan.pose.covariance is not None and previous_cov is None and len(self._odometry_cov) == 1:
            previous_cov = np.zeros((3, 3))  # the first pose gave none: the odometry starts there, exact
        if scan.pose.covariance is not None and previous_cov is not None:
            return graph.step_covariance_from_poses(
                self._odometry[-1],
                scan.pose.vector,
                previous_cov,
                scan.pose.covariance,
                np.asarray(cfg.step_sigma_floor),
            )
        note = (
            "odometry gave no covariance: each step taken as σ = "
            f"{cfg.default_step_sigma[0]:g} m, {cfg.default_step_sigma[1]:g} m, {cfg.default_step_sigma[2]:.3g} rad"
        )
        if note not in self.notes:
            self.notes.append(note)
        return np.diag(np.square(cfg.default_step_sigma))

    # ------------------------------------------------------------------ association
    def _gate(
        self,
        tracks: list[_Track],
        measured: np.ndarray,
        meas_cov: np.ndarray,
        pose: np.ndarray,
        pose_cov: np.ndarray,
        points: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Mahalanobis d², the gap between stretches (m), and the innovation, of one observation to each track.

        The innovation is taken in the sensor frame: ``ν = h(pose, wall) − z`` with
        ``S = H_p P H_pᵀ + H_l C H_lᵀ + R`` (the pose's, the wall's and the observation's covariances).
        """
        n = len(tracks)
        if n == 0:
            return np.zeros(0), np.zeros(0), np.zeros((0, 2))
        lines = np.array([t.line for t in tracks])
        covs = np.array([t.covariance for t in tracks])
        x, y, psi = pose
        theta = lines[:, 0]
        c, s = np.cos(theta), np.sin(theta)
        a = theta - psi
        nu = np.empty((n, 2))
        nu[:, 0] = np.remainder(a - measured[0] + np.pi, 2 * np.pi) - np.pi
        nu[:, 1] = lines[:, 1] - (c * x + s * y) - measured[1]
        h_pose = np.zeros((n, 2, 3))
        h_pose[:, 0, 2] = -1.0
        h_pose[:, 1, 0] = -np.cos(a)
        h_pose[:, 1, 1] = -np.sin(a)
        h_line = np.zeros((n, 2, 2))
        h_line[:, 0, 0] = 1.0
        h_line[:, 1, 0] = x * s - y * c
        h_line[:, 1, 1] = 1.0
        big_s = h_pose @ pose_cov @ h_pose.transpose(0, 2, 1) + h_line @ covs @ h_line.transpose(0, 2, 1) + meas_cov
        d2 = np.einsum("ni,ni->n", nu, np.linalg.solve(big_s, nu[..., None])[..., 0])
        # The observed stretch on each wall's line, against the wall's own stretch.
        tangents = np.stack([-s, c], axis=1)
        feet = lines[:, 1:2] * np.stack([c, s], axis=1)
        along = np.einsum("nkj,nj->nk", points[None, :, :] - feet[:, None, :], tangents)
        lo, hi = along.min(axis=1), along.max(axis=1)
        intervals = np.array([t.interval for t in tracks])
        gap = np.maximum(lo - intervals[:, 1], intervals[:, 0] - hi)
        return d2, gap, nu

    def _associate_good(
        self,
        seen: _Seen,
        pose: np.ndarray,
        pose_cov: np.ndarray,
        used: set[int],
    ) -> _Track:
        obs = seen.obs
        measured = obs.line
        points = _sensor_points_to_world(pose, obs.extent)
        d2, gap, nu = self._gate(self._graph_tracks, measured, obs.covariance, pose, pose_cov, points)
        ok = (d2 < self.config.gate_chi2) & (gap <= self.config.max_gap)
        for i in np.flatnonzero(ok):
            if self._graph_tracks[i].id in used:
                ok[i] = False
        self._refine(d2, ok, nu, pose, obs.covariance)
        ok &= d2 < self.config.gate_chi2
        if ok.any():
            track = self._graph_tracks[int(np.argmin(np.where(ok, d2, np.inf)))]
        else:
            index = len(self._graph_tracks)
            track = _Track(id=self._new_id(), index=index, seen=[])
            track.line = line_in_world(pose, measured)
            j_pose, j_obs = world_jacobians(pose, measured)
            track.covariance = j_pose @ _world_pose_cov(pose, pose_cov) @ j_pose.T + j_obs @ obs.covariance @ j_obs.T
            track.interval = self._interval_from_points(track.line, points)
            self._graph.add_wall(index, track.line)
            self._mark_conflicts(track, d2, gap, nu)
            self._graph_tracks.append(track)
            self._adopt_flagged(track)
        track.seen.append(seen)
        used.add(track.id)
        self._graph.add_observation(seen.pose_index, track.index, measured, obs.covariance)
        return track

    def _refine(
        self, d2: np.ndarray, candidates: np.ndarray, nu: np.ndarray, pose: np.ndarray, meas_cov: np.ndarray
    ) -> None:
        """Recompute ``d2`` in place for the candidate walls with the joint covariance of the previous pose and
        the wall.

        The marginals alone ignore that a pose and a wall seen from near it drifted together: after a long
        way both are uncertain in the world, much less so relative to each other, and the gate built from
        the marginals would let in a parallel wall a corridor away.
        """
        if self._step is None:
            return
        ad, q = self._step
        prev = len(self._poses) - 2
        for i in np.flatnonzero(candidates):
            track = self._graph_tracks[i]
            p_pp, p_pw, p_ww = self._graph.pose_wall_joint(prev, track.index)
            cov = np.block([[ad @ p_pp @ ad.T + q, ad @ p_pw], [(ad @ p_pw).T, p_ww]])
            h_pose, h_line = measurement_jacobians(pose, track.line)
            h = np.hstack([h_pose, h_line])
            d2[i] = mahalanobis2(nu[i], h @ cov @ h.T + meas_cov)

    def _mark_conflicts(self, track: _Track, d2: np.ndarray, gap: np.ndarray, nu: np.ndarray) -> None:
        """Walls the new one overlaps and lies near, outside their gate: the same surface, disagreeing."""
        cfg = self.config
        near = (
            (d2 >= cfg.gate_chi2)
            & (gap <= 0.0)
            & (np.abs(nu[:, 0]) < cfg.conflict_angle)
            & (np.abs(nu[:, 1]) < cfg.conflict_distance)
        )
        for i in np.flatnonzero(near).tolist():
            other = self._graph_tracks[i]
            what = (
                f"{math.degrees(abs(nu[i, 0])):.2g}° and {100 * abs(nu[i, 1]):.2g} cm apart ({math.sqrt(d2[i]):.1f}σ)"
            )
            track.conflicts[other.id] = what
            other.conflicts[track.id] = what

    def _associate_flagged(self, seen: _Seen, pose: np.ndarray, pose_cov: np.ndarray) -> None:
        obs = seen.obs
        points = _sensor_points_to_world(pose, obs.extent)
        for tracks in (self._graph_tracks, self._flagged_tracks):
            d2, gap, nu = self._gate(tracks, obs.line, obs.covariance, pose, pose_cov, points)
            ok = (d2 < self.config.gate_chi2) & (gap <= self.config.max_gap)
            if tracks is self._graph_tracks:
                ok &= np.array([t.index < self._isam_walls for t in tracks], bool)
                self._refine(d2, ok, nu, pose, obs.covariance)
                ok &= d2 < self.config.gate_chi2
            if ok.any():
                track = tracks[int(np.argmin(np.where(ok, d2, np.inf)))]
                track.flagged.append(seen)
                if tracks is self._graph_tracks:
                    self._constrain(track, seen)
                return
        track = _Track(id=self._new_id(), index=-1, seen=[], flagged=[seen])
        track.line = line_in_world(pose, obs.line)
        j_pose, j_obs = world_jacobians(pose, obs.line)
        track.covariance = j_pose @ _world_pose_cov(pose, pose_cov) @ j_pose.T + j_obs @ obs.covariance @ j_obs.T
        track.interval = self._interval_from_points(track.line, points)
        self._flagged_tracks.append(track)

    def _adopt_flagged(self, track: _Track) -> None:
        """Flagged walls that agree with a new wall of good evidence become its flagged observations."""
        keep = []
        for f in self._flagged_tracks:
            d2 = _line_distance2(f.line, f.covariance, track.line, track.covariance)
            gap = (
                max(f.interval[0] - track.interval[1], track.interval[0] - f.interval[1])
                if abs(wrap(f.line[0] - track.line[0])) < math.pi / 2
                else math.inf
            )
            if d2 < self.config.gate_chi2 and gap <= self.config.max_gap:
                track.flagged.extend(f.flagged)
                for seen in f.flagged:
                    self._constrain(track, seen)
            else:
                keep.append(f)
        self._flagged_tracks = keep

    def _constrain(self, track: _Track, seen: _Seen) -> None:
        """A flagged observation attached to a wall of the graph ties its pose to it (``flagged_constrain``)."""
        if seen.obs.quality in self.config.flagged_constrain:
            self._graph.add_observation(seen.pose_index, track.index, seen.obs.line, seen.obs.covariance, robust=True)

    def _new_id(self) -> int:
        self._next_id += 1
        return self._next_id - 1

    @staticmethod
    def _interval_from_points(line: np.ndarray, points: np.ndarray) -> tuple[float, float]:
        return interval_on_line(line, points)

    def _interval(self, track: _Track, seen: list[_Seen]) -> tuple[float, float]:
        """The hull of the observations' stretches, through the current poses, on the wall's current line."""
        pts = np.concatenate([_sensor_points_to_world(self._poses[s.pose_index], s.obs.extent) for s in seen])
        return self._interval_from_points(track.line, pts)

    # ------------------------------------------------------------------ the map
    def snapshot(self, polished: bool | None = None) -> FusedMap:
        """The map now, world frame: walls with GTSAM marginals and verdicts, corners, edges, poses.

        ``polished`` (default: the config's ``polish``): converged over the whole graph with its marginals;
        otherwise ISAM2's estimate with each marginal as last computed (cheap enough after every scan)."""
        if self._failed is not None:
            raise MapUpdateError(f"no map: {self._failed}")
        if not self._poses:
            return FusedMap(walls=(), features=(), poses=(), notes=tuple(self.notes))
        use_polish = self.config.polish if polished is None else polished
        if use_polish:
            solution = self._graph.solve(polished=True)
            poses_local = [solution.pose(i) for i in range(len(self._poses))]
            pose_covs = [solution.pose_marginal(i) for i in range(len(self._poses))]
            lines = {t.index: solution.wall(t.index) for t in self._graph_tracks}
            covs = {t.index: solution.wall_marginal(t.index) for t in self._graph_tracks}
        else:
            # ISAM2's estimate as the last update left it, and each marginal as it was last computed (the newest
            # pose's, the walls a scan touched): new evidence only narrows a marginal, so an older one is the
            # wider, and no marginal of the whole graph is recomputed for a read.
            poses_local = list(self._poses)
            pose_covs = list(self._pose_covs)
            lines = {t.index: t.line for t in self._graph_tracks}
            covs = {t.index: t.covariance for t in self._graph_tracks}
        by_id = {t.id: t for t in self._graph_tracks}
        world_local = np.array(poses_local)
        origin = np.array([self._origin[0], self._origin[1], 0.0])
        # Unpolished reads after every scan redo only the walls whose inputs moved: a wall's line or σ, the poses
        # that saw it, its observations or its disagreements (ISAM2 leaves most of a large map untouched).
        reuse = not use_polish
        fresh: dict[int, tuple] = {}
        walls: list[FusedWall] = []
        views: list[np.ndarray] = []
        view_scans: list[int] = []
        for t in self._graph_tracks + self._flagged_tracks:
            everything = t.seen + t.flagged
            ref = world_local[[s.pose_index for s in everything]]
            if t.index >= 0:
                line, cov = lines[t.index], covs[t.index]
                key = (
                    len(t.seen),
                    len(t.flagged),
                    tuple(sorted((o, len(by_id[o].seen) if o in by_id else 0) for o in t.conflicts)),
                )
            else:
                first = t.flagged[0]
                pose = poses_local[first.pose_index]
                line = line_in_world(pose, first.obs.line)
                j_pose, j_obs = world_jacobians(pose, first.obs.line)
                cov = j_pose @ _world_pose_cov(pose, pose_covs[first.pose_index]) @ j_pose.T
                cov = cov + j_obs @ first.obs.covariance @ j_obs.T
                key = (0, len(t.flagged), ())
            hit = self._read_cache.get(t.id) if reuse else None
            if (
                hit is not None
                and hit[0] == key
                and float(np.abs(hit[1] - ref).max()) <= READ_TOLERANCE
                and float(np.abs(hit[2] - line).max()) <= READ_TOLERANCE
                and float(np.abs(hit[3] - cov).max()) <= 1e-6 * float(np.abs(cov).max())
            ):
                wall, its_views = hit[4], hit[5]
            else:
                if t.index >= 0:
                    wall = self._placed(
                        self._fused(t, line, cov, poses_local, self._verdict(t, line, poses_local, by_id))
                    )
                else:
                    best = min(QUALITIES.index(s.obs.quality) for s in t.flagged)
                    reasons = tuple(f"scan {s.scan_id}: {r}" for s in t.flagged for r in s.obs.reasons) or (
                        f"seen only {QUALITIES[best]}",
                    )
                    wall = self._fused(t, line, cov, poses_local, (QUALITIES[best], reasons))
                its_views = _views(everything, ref + origin)
            fresh[t.id] = (key, ref, np.array(line), np.array(cov), wall, its_views)
            walls.append(wall)
            views.extend(its_views)
            view_scans.extend(s.scan_id for s in everything)
        if reuse:
            self._read_cache = fresh
        walls.sort(key=lambda w: w.id)
        poses = tuple(
            FusedPose(
                scan_id=self._scan_ids[i],
                x=float(p[0] + self._origin[0]),
                y=float(p[1] + self._origin[1]),
                z=self._heights[i],
                heading=wrap(float(p[2])),
                covariance=_world_pose_cov(p, pose_covs[i]),
                odometry=tuple(float(v) for v in self._odometry[i]),  # type: ignore[arg-type]
            )
            for i, p in enumerate(poses_local)
        )
        world_poses = [np.array([p.x, p.y, p.heading]) for p in poses]
        observed = [(sid, world_poses[k], self._heights[k], f) for sid, k, f in self._features]
        # Corners where walls of good evidence meet: a flagged wall's line may be degrees off, and its crossings
        # with others land anywhere.
        placed = [w for w in walls if w.good_observations > 0]
        features = wall_corners(placed, self.config.corner_reach) + fuse_features(observed)
        return FusedMap(
            walls=tuple(walls),
            features=tuple(features),
            poses=poses,
            notes=tuple(self.notes),
            views=tuple(views),
            view_scans=tuple(view_scans),
        )

    def _placed(self, wall: FusedWall) -> FusedWall:
        """A good wall the map places less well than ``good_tolerance`` (3σ over its stretch) is degraded."""
        if wall.quality != "good":
            return wall
        sigma = wall_placement_sigma(wall)
        if 3.0 * sigma <= self.config.good_tolerance:
            return wall
        reason = (
            f"placed to ±{100 * sigma:.1f} cm (1σ) over its stretch in the map's frame, more than "
            f"{100 * self.config.good_tolerance / 3:.2g} cm: the poses that saw it are that uncertain"
        )
        return replace(wall, quality="degraded", reasons=wall.reasons + (reason,))

    def _verdict(
        self, t: _Track, line: np.ndarray, poses: list[np.ndarray], by_id: dict[int, _Track]
    ) -> tuple[str, tuple[str, ...]]:
        """A wall of good evidence stays good unless its observations disagree with it or with each other."""
        reasons = []
        if t.seen:
            # Each observation's residual against the fused wall, all at once (graph.wall_error's model).
            p = np.array([poses[s.pose_index] for s in t.seen])
            z = np.array([s.obs.line for s in t.seen])
            c = np.array([s.obs.covariance for s in t.seen])
            theta, rho = float(line[0]), float(line[1])
            e = np.stack(
                [
                    np.remainder(theta - p[:, 2] - z[:, 0] + np.pi, 2 * np.pi) - np.pi,
                    rho - (math.cos(theta) * p[:, 0] + math.sin(theta) * p[:, 1]) - z[:, 1],
                ],
                axis=1,
            )
            d2 = np.einsum("ni,ni->n", e, np.linalg.solve(c, e[..., None])[..., 0])
            for s, v in zip(t.seen, d2.tolist()):
                if v > self.config.gate_chi2:
                    reasons.append(f"scan {s.scan_id}'s observation is {math.sqrt(v):.1f}σ from the fused wall")
        for other_id, what in sorted(t.conflicts.items()):
            other = by_id.get(other_id)
            n_other = len(other.seen) if other is not None else 0
            if not (len(t.seen) >= 2 and len(t.seen) > n_other):
                reasons.append(f"disagrees with wall {other_id} on the same surface: {what}; kept apart, not averaged")
        return ("good" if not reasons else "degraded"), tuple(reasons)

    def _fused(
        self,
        t: _Track,
        line_local: np.ndarray,
        cov_local: np.ndarray,
        poses: list[np.ndarray],
        verdict: tuple[str, tuple[str, ...]],
    ) -> FusedWall:
        everything = t.seen + t.flagged
        pts, starts = _observed_points(everything, np.asarray(poses))
        theta_l = float(line_local[0])
        along = (pts - float(line_local[1]) * np.array([math.cos(theta_l), math.sin(theta_l)])) @ np.array(
            [-math.sin(theta_l), math.cos(theta_l)]
        )
        spans = sorted(zip(np.minimum.reduceat(along, starts).tolist(), np.maximum.reduceat(along, starts).tolist()))
        pieces = [list(spans[0])]
        for lo, hi in spans[1:]:
            if lo - pieces[-1][1] <= self.config.join_gap:
                pieces[-1][1] = max(pieces[-1][1], hi)
            else:
                pieces.append([lo, hi])
        zs = np.concatenate([s.obs.extent[:, 2] + self._heights[s.pose_index] for s in everything])
        # Local → world: ρ_w = ρ_l + n(θ)·o, so dρ_w/dθ = −sin θ o_x + cos θ o_y.
        theta = wrap(float(line_local[0]))
        ox, oy = self._origin
        b = -math.sin(theta) * ox + math.cos(theta) * oy
        j = np.array([[1.0, 0.0], [b, 1.0]])
        line_world = np.array([theta, line_local[1] + math.cos(theta) * ox + math.sin(theta) * oy])
        return FusedWall(
            id=t.id,
            line=line_world,
            covariance=j @ cov_local @ j.T,
            interval=(pieces[0][0] + b, max(p[1] for p in pieces) + b),
            pieces=tuple((lo + b, hi + b) for lo, hi in pieces),
            z_range=(float(zs.min()), float(zs.max())),
            quality=verdict[0],
            reasons=verdict[1],
            scans=tuple(dict.fromkeys(s.scan_id for s in everything)),
            good_observations=len(t.seen),
            flagged_observations=len(t.flagged),
        )


def wall_placement_sigma(wall: FusedWall) -> float:
    """The largest σ, m, of the wall's position across its line over its observed stretch.

    A point ``s`` along the line from its foot moves across it by ``δρ − s δθ``: its variance is
    ``C_ρρ − 2 s C_θρ + s² C_θθ``, largest at an end of the stretch.
    """
    c = wall.covariance
    return math.sqrt(max(max(float(c[1, 1] - 2 * s * c[0, 1] + s * s * c[0, 0]) for s in wall.interval), 0.0))


def _observed_points(seen: list[_Seen], poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The observations' patch points (k, 2) through their poses ``(x, y, ψ)`` (indexed by pose index), and
    where each observation's points start."""
    counts = [len(s.obs.extent) for s in seen]
    ext = np.concatenate([s.obs.extent[:, :2] for s in seen])
    p = poses[[s.pose_index for s in seen]][np.repeat(np.arange(len(seen)), counts)]
    c, sn = np.cos(p[:, 2]), np.sin(p[:, 2])
    pts = np.stack([c * ext[:, 0] - sn * ext[:, 1] + p[:, 0], sn * ext[:, 0] + c * ext[:, 1] + p[:, 1]], axis=1)
    return pts, np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(int)


def _views(seen: list[_Seen], poses: np.ndarray) -> list[np.ndarray]:
    """Each observation's echo paths: the triangle from its scanner to its patch's two ends along the wall.

    ``poses`` are the observations' own world poses, one a row.
    """
    counts = np.array([len(s.obs.extent) for s in seen])
    owner = np.repeat(np.arange(len(seen)), counts)
    ext = np.concatenate([s.obs.extent[:, :2] for s in seen])
    p = poses[owner]
    c, sn = np.cos(p[:, 2]), np.sin(p[:, 2])
    pts = np.stack([c * ext[:, 0] - sn * ext[:, 1] + p[:, 0], sn * ext[:, 0] + c * ext[:, 1] + p[:, 1]], axis=1)
    theta = p[:, 2] + np.array([s.obs.line[0] for s in seen])[owner]
    along = -np.sin(theta) * pts[:, 0] + np.cos(theta) * pts[:, 1]
    order = np.lexsort((along, owner))
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(int)
    first, last = pts[order[starts]], pts[order[starts + counts - 1]]
    return list(np.stack([poses[:, :2], first, last], axis=1))


def _world_pose_cov(pose: np.ndarray, body_cov: np.ndarray) -> np.ndarray:
    """A Pose2 marginal (body-frame tangent) turned to world axes ``(x, y, ψ)``."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    r = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return r @ body_cov @ r.T


def _line_distance2(a: np.ndarray, ca: np.ndarray, b: np.ndarray, cb: np.ndarray) -> float:
    """Mahalanobis d² between two wall lines of the same frame (independent errors)."""
    d = np.array([wrap(float(a[0] - b[0])), float(a[1] - b[1])])
    return float(d @ np.linalg.solve(ca + cb, d))
