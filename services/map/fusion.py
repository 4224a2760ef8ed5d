"""Walls fused across scans: data association, the factor graph, and verdicts that carry over.

:class:`WallMapper` takes one :class:`~lelsonar.map.observation.ScanObservation` at a time
(:meth:`WallMapper.add_scan`: one ISAM2 update a scan, not a rebuild) and gives the map on demand
(:meth:`WallMapper.snapshot`).

* **Association.**  Each good wall observation is compared with every wall of the map through the
  predicted pose: the Mahalanobis distance of the innovation on ``(θ, ρ)`` (pose, wall and observation
  covariances), gated at ``gate_chi2`` (and, where configured, the gap between the observed stretch and the
  wall's).  The nearest wall within the gate takes it; no two observations of one scan go to one wall.
* **Verdicts carry over.**  Only good observations make a wall good.  Degraded and unreliable observations
  are attached to a fused wall they agree with (there they tie their pose to it with their own σ and
  Huber's loss: a wall whose bearing a scan could not pin still places the robot in range), or kept as
  walls of their own with their own verdict: a wall seen once and flagged stays flagged.  A flagged wall
  seen from two scans enters the graph the same way, so it corrects the poses no good wall links, and
  stays flagged.  An observation that overlaps a wall and lies near it but outside the gate is another
  wall, and both are marked as disagreeing: never averaged into a wall that does not exist.  A wall of good
  evidence that the map places less well than ``good_tolerance`` (the poses' uncertainty) is degraded, and
  says so.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from lelsonar.errors import InvalidMessageError
from lelsonar.map import graph
from lelsonar.map.config import CHI2_2_999, FusionConfig, MapUpdateError
from lelsonar.map.features import fuse_features, horizontal_corners, placement_sigma, wall_corners
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
from lelsonar.map.placement import (
    line_distance2,
    observation_views,
    observed_points,
    sensor_points_to_world,
    wall_placement_sigma,
    world_pose_covariance,
)
from lelsonar.map.result import FusedMap, FusedPose, FusedWall

__all__ = ["CHI2_2_999", "FusionConfig", "MapUpdateError", "WallMapper", "wall_placement_sigma"]

#: A wall is redone for a read when its line or a pose that saw it moved more than this (m or rad): ISAM2 itself
#: stops carrying an update further where it changes a variable by less (its wildfire threshold).
READ_TOLERANCE = 1e-3


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


def _precision_rank(obs: WallObservation) -> tuple[int, float]:
    """How an observation ranks to place a flagged wall: the better verdict, then the smaller σ of its bearing."""
    return QUALITIES.index(obs.quality), float(obs.covariance[0, 0])


def _best(seen: list[_Seen]) -> _Seen:
    return min(seen, key=lambda s: _precision_rank(s.obs))


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
                promoted = self._associate_flagged(seen, predicted, pose_cov)
                if promoted is not None:
                    touched.append(promoted)
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
            t.interval = self._interval(t, t.seen or t.flagged)

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
        points = sensor_points_to_world(pose, obs.extent)
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
            track.covariance = (
                j_pose @ world_pose_covariance(pose, pose_cov) @ j_pose.T + j_obs @ obs.covariance @ j_obs.T
            )
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

    def _associate_flagged(self, seen: _Seen, pose: np.ndarray, pose_cov: np.ndarray) -> _Track | None:
        """Attach a flagged observation to the wall it agrees with, or keep it as a flagged wall of its own; the
        flagged wall it joins enters the graph once it has been seen from two scans (:meth:`_promote`), and is
        returned then."""
        obs = seen.obs
        points = sensor_points_to_world(pose, obs.extent)
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
                    return None
                if _precision_rank(obs) < _precision_rank(_best(track.flagged[:-1]).obs):
                    self._place_flagged(track, pose, pose_cov, obs, points)
                return self._promote(track)
        track = _Track(id=self._new_id(), index=-1, seen=[], flagged=[seen])
        self._place_flagged(track, pose, pose_cov, obs, points)
        self._flagged_tracks.append(track)
        return None

    @staticmethod
    def _place_flagged(
        track: _Track, pose: np.ndarray, pose_cov: np.ndarray, obs: WallObservation, points: np.ndarray
    ) -> None:
        """A flagged wall outside the graph takes the line of its most precise observation, through its pose."""
        track.line = line_in_world(pose, obs.line)
        j_pose, j_obs = world_jacobians(pose, obs.line)
        track.covariance = j_pose @ world_pose_covariance(pose, pose_cov) @ j_pose.T + j_obs @ obs.covariance @ j_obs.T
        track.interval = interval_on_line(track.line, points)

    def _promote(self, track: _Track) -> _Track | None:
        """A flagged wall seen from two scans enters the graph: its observations tie their poses to it (robustly,
        with their own σ: a wall whose bearing the scans could not pin still places the robots in range), and
        poses seen by no wall of good evidence are corrected.  It stays flagged: only good evidence makes a wall
        good."""
        constraining = [s for s in track.flagged if s.obs.quality in self.config.flagged_constrain]
        if len({s.scan_id for s in constraining}) < 2:
            return None
        self._flagged_tracks.remove(track)
        track.index = len(self._graph_tracks)
        self._graph.add_wall(track.index, track.line)
        for s in constraining:
            self._graph.add_observation(s.pose_index, track.index, s.obs.line, s.obs.covariance, robust=True)
        self._graph_tracks.append(track)
        self._adopt_flagged(track)
        return track

    def _adopt_flagged(self, track: _Track) -> None:
        """Flagged walls that agree with a new wall of good evidence become its flagged observations."""
        keep = []
        for f in self._flagged_tracks:
            d2 = line_distance2(f.line, f.covariance, track.line, track.covariance)
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
        pts = np.concatenate([sensor_points_to_world(self._poses[s.pose_index], s.obs.extent) for s in seen])
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
                first = _best(t.flagged)
                pose = poses_local[first.pose_index]
                line = line_in_world(pose, first.obs.line)
                j_pose, j_obs = world_jacobians(pose, first.obs.line)
                cov = j_pose @ world_pose_covariance(pose, pose_covs[first.pose_index]) @ j_pose.T
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
                if t.seen:
                    wall = self._placed(
                        self._fused(t, line, cov, poses_local, self._verdict(t, line, poses_local, by_id))
                    )
                else:
                    best = min(QUALITIES.index(s.obs.quality) for s in t.flagged)
                    reasons = tuple(f"scan {s.scan_id}: {r}" for s in t.flagged for r in s.obs.reasons) or (
                        f"seen only {QUALITIES[best]}",
                    )
                    wall = self._fused(t, line, cov, poses_local, (QUALITIES[best], reasons))
                its_views = observation_views(
                    [s.obs.extent for s in everything], [float(s.obs.line[0]) for s in everything], ref + origin
                )
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
                covariance=world_pose_covariance(p, pose_covs[i]),
                odometry=tuple(float(v) for v in self._odometry[i]),  # type: ignore[arg-type]
            )
            for i, p in enumerate(poses_local)
        )
        world_poses = [np.array([p.x, p.y, p.heading]) for p in poses]
        observed = [(sid, world_poses[k], self._heights[k], f) for sid, k, f in self._features]
        placed_by = [placement_sigma(poses[k].covariance, float(np.hypot(*f.point[:2]))) for _, k, f in self._features]
        # Corners where walls of good evidence meet: a flagged wall's line may be degrees off, and its crossings
        # with others land anywhere.
        placed = [w for w in walls if w.good_observations > 0]
        seen_features = fuse_features(observed, placed_by)
        corners, rest = wall_corners(placed, self.config.corner_reach, seen_features)
        return FusedMap(
            walls=tuple(walls),
            features=tuple(corners + rest),
            poses=poses,
            notes=tuple(self.notes),
            views=tuple(views),
            view_scans=tuple(view_scans),
            horizontal=tuple(horizontal_corners(seen_features)),
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
        pts, starts = observed_points(
            [s.obs.extent for s in everything], [s.pose_index for s in everything], np.asarray(poses)
        )
        theta_l = float(line_local[0])
        along = (pts - float(line_local[1]) * np.array([math.cos(theta_l), math.sin(theta_l)])) @ np.array(
            [-math.sin(theta_l), math.cos(theta_l)]
        )
        spans = sorted(
            zip(
                np.minimum.reduceat(along, starts).tolist(),
                np.maximum.reduceat(along, starts).tolist(),
                (s.scan_id for s in everything),
            )
        )
        pieces = [[spans[0][0], spans[0][1]]]
        piece_scans = [[spans[0][2]]]
        for lo, hi, scan_id in spans[1:]:
            if lo - pieces[-1][1] <= self.config.join_gap:
                pieces[-1][1] = max(pieces[-1][1], hi)
                piece_scans[-1].append(scan_id)
            else:
                pieces.append([lo, hi])
                piece_scans.append([scan_id])
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
            piece_scans=tuple(tuple(dict.fromkeys(ids)) for ids in piece_scans),
        )
