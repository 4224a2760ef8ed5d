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
* **A scan the solver refuses.**  Where GTSAM finds the system a scan's walls make indeterminate (an
  observation whose covariance is too ill-conditioned for the solver, say), the map is rebuilt from the scans
  before it and that scan enters with its pose and odometry only: its walls and features are left out, and a
  note says so.  The map goes on; only a scan whose pose alone is refused stops it.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from lelsonar.errors import InvalidMessageError
from lelsonar.map import graph
from lelsonar.map.config import CHI2_2_999, FusionConfig, MapUpdateError
from lelsonar.map.features import fuse_features, horizontal_corners, placement_sigma, wall_corners
from lelsonar.map.fused_walls import checked_placement, fused_wall, wall_verdict
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
    sensor_points_to_world,
    wall_placement_sigma,
    world_pose_covariance,
)
from lelsonar.map.result import FusedMap, FusedPose, FusedWall
from lelsonar.map.tracks import Seen, Track, best_seen, gate, precision_rank

__all__ = ["CHI2_2_999", "FusionConfig", "MapUpdateError", "WallMapper", "wall_placement_sigma"]


class _Refused(Exception):
    """GTSAM refused a scan's update (its message's first line in ``reason``); the mapper is rebuilt after it."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


#: A wall is redone for a read when its line or a pose that saw it moved more than this (m or rad): ISAM2 itself
#: stops carrying an update further where it changes a variable by less (its wildfire threshold).
READ_TOLERANCE = 1e-3


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
        self._graph_tracks: list[Track] = []
        self._isam_walls = 0  # graph walls already in ISAM2 (the newer ones arrived with the scan being added)
        self._flagged_tracks: list[Track] = []
        self._next_id = 0
        self._step: tuple[np.ndarray, np.ndarray] | None = None  # (Ad(u⁻¹), Q) of the scan being added
        self._features: list[tuple[int, int, FeatureObservation]] = []  # (scan_id, pose index, FeatureObservation)
        self.notes: list[str] = []
        self._failed: str | None = None
        self._read_cache: dict[int, tuple] = {}  # wall id → what its last unpolished read took and gave
        self._fused: list[ScanObservation] = []  # each scan as it entered the map: what a rebuild replays

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
        """Fuse one scan: its pose, its odometry step, its walls and features (one ISAM2 update).

        A scan whose walls the solver refuses enters with its pose only, with a note (see the module docstring).

        Raises
        ------
        MapUpdateError
            The solver refused the scan's pose as well: the map takes no more scans.
        """
        if self._failed is not None:
            raise MapUpdateError(f"the map takes no more scans: {self._failed}; start a new map")
        if scan.scan_id in self._scan_ids:
            raise InvalidMessageError(f"scan {scan.scan_id} is already in the map (scan ids must be unique)")
        try:
            self._fuse(scan)
        except _Refused as refused:
            self._rebuild_without_surfaces(scan, refused.reason)

    def _rebuild_without_surfaces(self, scan: ScanObservation, reason: str) -> None:
        """The map again from the scans before ``scan``, then ``scan``'s pose alone; the note says why."""
        bare = dataclasses.replace(scan, walls=(), features=())
        fresh = WallMapper(self.config)
        try:
            for s in (*self._fused, bare):
                fresh._fuse(s)  # the same updates as before, in the same order, but the last
        except _Refused as refused:
            self._failed = f"scan {scan.scan_id} made the graph unsolvable ({refused.reason})"
            raise MapUpdateError(self._failed) from None
        notes = self.notes  # (a rebuild does not say again what earlier ones left out)
        self.__dict__.update(fresh.__dict__)
        self.notes = notes + [n for n in fresh.notes if n not in notes]
        self.notes.append(
            f"scan {scan.scan_id}: its walls ({len(scan.walls)}) and features ({len(scan.features)}) left out of the "
            f"map, with them the solver refused the graph ({reason}); its pose is kept"
        )

    def _fuse(self, scan: ScanObservation) -> None:
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

        touched: list[Track] = []
        used: set[int] = set()
        for obs in sorted(scan.walls, key=lambda w: QUALITIES.index(w.quality)):
            seen = Seen(scan.scan_id, k, obs)
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
            raise _Refused(first) from None
        self._fused.append(scan)
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
    def _associate_good(
        self,
        seen: Seen,
        pose: np.ndarray,
        pose_cov: np.ndarray,
        used: set[int],
    ) -> Track:
        obs = seen.obs
        measured = obs.line
        points = sensor_points_to_world(pose, obs.extent)
        d2, gap, nu = gate(self._graph_tracks, measured, obs.covariance, pose, pose_cov, points)
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
            track = Track(id=self._new_id(), index=index, seen=[])
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

    def _mark_conflicts(self, track: Track, d2: np.ndarray, gap: np.ndarray, nu: np.ndarray) -> None:
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

    def _associate_flagged(self, seen: Seen, pose: np.ndarray, pose_cov: np.ndarray) -> Track | None:
        """Attach a flagged observation to the wall it agrees with, or keep it as a flagged wall of its own; the
        flagged wall it joins enters the graph once it has been seen from two scans (:meth:`_promote`), and is
        returned then."""
        obs = seen.obs
        points = sensor_points_to_world(pose, obs.extent)
        for tracks in (self._graph_tracks, self._flagged_tracks):
            d2, gap, nu = gate(tracks, obs.line, obs.covariance, pose, pose_cov, points)
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
                if precision_rank(obs) < precision_rank(best_seen(track.flagged[:-1]).obs):
                    self._place_flagged(track, pose, pose_cov, obs, points)
                return self._promote(track)
        track = Track(id=self._new_id(), index=-1, seen=[], flagged=[seen])
        self._place_flagged(track, pose, pose_cov, obs, points)
        self._flagged_tracks.append(track)
        return None

    @staticmethod
    def _place_flagged(
        track: Track, pose: np.ndarray, pose_cov: np.ndarray, obs: WallObservation, points: np.ndarray
    ) -> None:
        """A flagged wall outside the graph takes the line of its most precise observation, through its pose."""
        track.line = line_in_world(pose, obs.line)
        j_pose, j_obs = world_jacobians(pose, obs.line)
        track.covariance = j_pose @ world_pose_covariance(pose, pose_cov) @ j_pose.T + j_obs @ obs.covariance @ j_obs.T
        track.interval = interval_on_line(track.line, points)

    def _promote(self, track: Track) -> Track | None:
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

    def _adopt_flagged(self, track: Track) -> None:
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

    def _constrain(self, track: Track, seen: Seen) -> None:
        """A flagged observation attached to a wall of the graph ties its pose to it (``flagged_constrain``)."""
        if seen.obs.quality in self.config.flagged_constrain:
            self._graph.add_observation(seen.pose_index, track.index, seen.obs.line, seen.obs.covariance, robust=True)

    def _new_id(self) -> int:
        self._next_id += 1
        return self._next_id - 1

    @staticmethod
    def _interval_from_points(line: np.ndarray, points: np.ndarray) -> tuple[float, float]:
        return interval_on_line(line, points)

    def _interval(self, track: Track, seen: list[Seen]) -> tuple[float, float]:
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
        cfg = self.config
        use_polish = cfg.polish if polished is None else polished
        notes = list(self.notes)
        if use_polish:
            try:
                solution = self._graph.solve(polished=True)
                poses_local = [solution.pose(i) for i in range(len(self._poses))]
                pose_covs = [solution.pose_marginal(i) for i in range(len(self._poses))]
                lines = {t.index: solution.wall(t.index) for t in self._graph_tracks}
                covs = {t.index: solution.wall_marginal(t.index) for t in self._graph_tracks}
            except RuntimeError as exc:
                # GTSAM's multifrontal Cholesky refuses a pivot small against the largest in its front, which a
                # well-posed graph of poses loose in odometry and walls tight in range can show; the incremental
                # solver's estimate and marginals, computed scan by scan, stand.
                said = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
                notes.append(f"map not polished over the whole graph ({said}): the estimate as the scans left it")
                use_polish = False
        if not use_polish:
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
                first = best_seen(t.flagged)
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
                    verdict = wall_verdict(t, line, poses_local, by_id, cfg.gate_chi2)
                    wall = checked_placement(
                        fused_wall(t, line, cov, poses_local, verdict, self._heights, self._origin, cfg.join_gap),
                        cfg.good_tolerance,
                    )
                else:
                    best = min(QUALITIES.index(s.obs.quality) for s in t.flagged)
                    reasons = tuple(f"scan {s.scan_id}: {r}" for s in t.flagged for r in s.obs.reasons) or (
                        f"seen only {QUALITIES[best]}",
                    )
                    wall = fused_wall(
                        t, line, cov, poses_local, (QUALITIES[best], reasons), self._heights, self._origin, cfg.join_gap
                    )
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
            notes=tuple(notes),
            views=tuple(views),
            view_scans=tuple(view_scans),
            horizontal=tuple(horizontal_corners(seen_features)),
        )
