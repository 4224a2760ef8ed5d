"""One world of a family toured, mapped and scored: the work item of ``lelsonar bench map --worlds``.

For each pose of the world (:func:`lelsonar.sim.worlds.draw_world`) one sweep is simulated with
waveforms and reconstructed as the reconstructor does it (the final ``Reconstruction`` of record, its
surfaces, corners and edges filled); the pose comes as the acquirer announces it
(:meth:`lelsonar.acquire.world_scans.WorldRun.pose_message`: the sim's own odometry, with its
covariance).  The map's adapter (:func:`lelsonar.map.from_reconstruction.scan_from_reconstruction`)
turns both into its observation, and :class:`~lelsonar.map.fusion.WallMapper` fuses the tour.

The **oracle map** is the same fusion fed the oracle's per-scan fits: for every mirror the sweep saw
with at least ``min_echoes`` true echoes, least squares on those echoes started at the truth
(:func:`oracle_fit`, as ``bench surfaces`` scores its oracle), with the covariance of that fit, verdict good.

Scored against the world: each fused wall matched to the true face it lies on (sign-free, within
:data:`MATCH_ANGLE` and :data:`MATCH_DISTANCE`), its normal error, its offset error (the true face's
distance from the middle of the fused stretch) and its trace error (the largest distance over the fused
stretch's ends); corners against the walls' true meeting points; poses against the truth and the odometry.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lelsonar import codec
from lelsonar.acquire.world_scans import WorldRun
from lelsonar.cli.demo_maze import sweep_reconstruction
from lelsonar.map.from_reconstruction import scan_from_reconstruction
from lelsonar.map.fusion import FusionConfig, WallMapper
from lelsonar.map.lines import wrap
from lelsonar.map.observation import ScanObservation
from lelsonar.map.result import FusedMap, FusedWall
from lelsonar.reconstruct.estimate.constant_depth import constant_depth_ls
from lelsonar.reconstruct.estimate.normals import tangent_basis
from lelsonar.sim import default_energy_model
from lelsonar.sim.odometry import simulate_odometry
from lelsonar.sim.scan import EchoSource
from lelsonar.sim.world_geometry import ElementKind, WorldModel, build_model
from lelsonar.sim.world_render import WorldScan, simulate_world_scan, world_rig
from lelsonar.sim.worlds import draw_world
from lelsonar.tools.surface_oracle import true_plane
from lelsonar.v1 import reconstruction_pb2 as pb

#: A map corner is on a true corner within this distance, m.
CORNER_MATCH = 0.10
#: A fused wall lies on a true face within this angle (rad) and distance (m) of it.
MATCH_ANGLE = math.radians(15.0)
MATCH_DISTANCE = 0.25
#: ``E0(d)`` the simulated acquirer announces (what the reconstruction of record uses).
ENERGY_MODEL = default_energy_model()
#: Readings of a mirror for the oracle to fit it.
MIN_ORACLE_ECHOES = 20
#: Smallest σ of a range, m (the oracle's covariance when its residuals are smaller than the noise can be).
RANGE_SIGMA_FLOOR = 1e-3


@dataclass(frozen=True)
class WallScore:
    """One fused wall against the truth."""

    face: int  # the true surface it lies on, −1: none
    scans: int
    quality: str
    angle: float  # rad
    offset: float  # m, the true face's distance from the middle of the fused stretch
    trace: float  # m, the largest distance over the fused stretch's ends
    normal_stderr: float
    offset_stderr: float


@dataclass
class TourResult:
    """What one world's tour scored, for the map of record and the oracle map."""

    family: str
    seed: int
    walls: list[WallScore] = field(default_factory=list)
    oracle_walls: list[WallScore] = field(default_factory=list)
    corners: list[float] = field(default_factory=list)  # m, fused corner to the nearest true one
    corners_true: int = 0  # map corners within CORNER_MATCH of a true vertical junction
    corners_kind: int = 0  # … of a kind that one has there
    corners_seen: int = 0  # true corners whose two faces the map holds as walls of good evidence
    corners_found: int = 0  # … with a map corner within CORNER_MATCH
    pose_fused: list[tuple[float, float]] = field(default_factory=list)  # (m, rad) per pose after the first
    pose_odometry: list[tuple[float, float]] = field(default_factory=list)
    updates: list[tuple[int, float]] = field(default_factory=list)  # (walls in the map before, CPU s)
    unmatched_good: int = 0  # good fused walls on no true face


@dataclass(frozen=True, eq=False)
class OracleFit:
    """Least squares on one mirror's true echoes, in the array frame."""

    normal: np.ndarray
    offset: float
    bearing: float
    tilt: float
    covariance: np.ndarray  # (3, 3) over (bearing, tilt, offset)
    patch: np.ndarray  # (2, 3): the ends of the echoes' reflection points along the fan
    n_echoes: int


def oracle_fit(scan: WorldScan, element: int, *, sigma_floor: float = RANGE_SIGMA_FLOOR) -> OracleFit:
    """LS (:func:`~lelsonar.reconstruct.estimate.constant_depth.constant_depth_ls`) on the mirror's true echoes,
    started at the truth, with its covariance ``σ² (AᵀA)⁻¹`` carried to (bearing, tilt, offset).

    ``A`` is the fit's design in the sphere's tangent plane at the solution (rows ``(p·e₁, p·e₂, −1)``)
    and ``σ`` the residuals' (at least ``sigma_floor``).  Bearing ``atan2(n_z, n_y)`` and tilt
    ``asin(n_x)``, as the ``SurfaceEstimate`` has them.
    """
    n_true, h_true = true_plane(scan, element)
    rows, caps = np.nonzero(_true_echoes(scan, element))
    p = scan.geometry.capsule_positions(scan.gamma_measured[rows])[np.arange(rows.size), caps]
    d = scan.distance[rows, caps]
    n, h, _ = constant_depth_ls(p, d, n_true, h_true)
    e1, e2 = tangent_basis(n)
    a = np.stack([p @ e1, p @ e2, -np.ones_like(d)], axis=1)
    r = p @ n + d - h
    dof = max(len(d) - 3, 1)
    sigma2 = max(float(r @ r) / dof, sigma_floor**2)
    cov_u = sigma2 * np.linalg.pinv(a.T @ a)
    ny, nz, nx = float(n[1]), float(n[2]), float(n[0])
    db = np.array([0.0, -nz, ny]) / max(ny * ny + nz * nz, 1e-12)
    dt = np.array([1.0, 0.0, 0.0]) / max(math.sqrt(max(1.0 - nx * nx, 0.0)), 1e-12)
    jac = np.array([[db @ e1, db @ e2, 0.0], [dt @ e1, dt @ e2, 0.0], [0.0, 0.0, 1.0]])
    points = p + d[:, None] * n[None, :]
    along = np.cross(np.array([1.0, 0.0, 0.0]), n)
    along = along / max(float(np.linalg.norm(along)), 1e-12)
    s = points @ along
    patch = points[[int(np.argmin(s)), int(np.argmax(s))]]
    return OracleFit(
        normal=n,
        offset=float(h),
        bearing=math.atan2(nz, ny),
        tilt=math.asin(max(-1.0, min(1.0, nx))),
        covariance=jac @ cov_u @ jac.T,
        patch=patch,
        n_echoes=int(len(d)),
    )


def world_run(family: str, seed: int) -> WorldRun:
    """The acquirer's set-up of a drawn world: model, rig, and the sim's odometry of the tour."""
    world = draw_world(family, seed)
    return WorldRun(
        path=Path(f"{family}-{seed}"),
        world=world,
        model=build_model(world),
        rig=world_rig(world),
        odometry=simulate_odometry(world.poses, world.odometry),
        seed=int(seed),
    )


def sweep(run: WorldRun, index: int) -> WorldScan:
    """Pose ``index``'s sweep, seeded as ``acquire --device sim --world`` seeds it."""
    return simulate_world_scan(run.model, index, rig=run.rig, seed=np.random.default_rng([run.seed, index]))


def scan_start(run: WorldRun, index: int, scanner_id: str = "sim") -> codec.ScanStart:
    """The ``ScanStart`` the acquirer announces for pose ``index`` (its odometry pose)."""
    start = codec.ScanStart(scanner_id=scanner_id, scan_id=index + 1)
    start.pose.CopyFrom(run.pose_message(index))
    return start


def surfaces_message(scan: WorldScan, scan_id: int, scanner_id: str = "sim") -> codec.Reconstruction:
    """The sweep's final reconstruction of record, its surfaces, corners and edges filled, as the
    reconstructor publishes it (:func:`lelsonar.cli.demo_maze.sweep_reconstruction`)."""
    return sweep_reconstruction(scan, scanner_id, scan_id, ENERGY_MODEL)


def _true_echoes(scan: WorldScan, element: int) -> np.ndarray:
    return (scan.echo_index == element) & (scan.echo_source != EchoSource.DIFFUSE) & np.isfinite(scan.distance)


def oracle_message(scan: WorldScan, scan_id: int, scanner_id: str = "sim") -> codec.Reconstruction:
    """The oracle's per-scan fits as a ``Reconstruction``: LS on each seen mirror's true echoes, verdict good."""
    msg = pb.Reconstruction(scanner_id=scanner_id, scan_id=scan_id, status=pb.ESTIMATE_STATUS_FINAL)
    model = scan.model
    n_echoes = 0
    for k, el in enumerate(model.elements):
        if el.kind != ElementKind.MIRROR or model.surfaces[el.surfaces[0]].kind not in ("wall", "box"):
            continue
        mask = _true_echoes(scan, k)
        if np.count_nonzero(mask) < MIN_ORACLE_ECHOES:
            continue
        fit = oracle_fit(scan, k, sigma_floor=RANGE_SIGMA_FLOOR)
        n_echoes += fit.n_echoes
        plane = pb.PlaneEstimate(
            label=f"o{k}",
            method="oracle",
            offset=fit.offset,
            normal_stderr=math.sqrt(fit.covariance[0, 0] + fit.covariance[1, 1]),
            offset_stderr=math.sqrt(fit.covariance[2, 2]),
            quality=pb.PLANE_QUALITY_GOOD,
            point_count=fit.n_echoes,
            inlier_count=fit.n_echoes,
        )
        plane.normal.x, plane.normal.y, plane.normal.z = (float(v) for v in fit.normal)
        for p in fit.patch:
            v = plane.patch.add()
            v.x, v.y, v.z = (float(c) for c in p)
        item = msg.surfaces.add(
            label=f"o{k}", bearing=fit.bearing, tilt=fit.tilt, bearing_source="oracle", echo_count=fit.n_echoes
        )
        item.plane.CopyFrom(plane)
        item.covariance.extend(float(v) for v in fit.covariance.ravel())
    msg.surface_echo_count = max(n_echoes, 1)
    return msg


def vertical_faces(model: WorldModel) -> list[tuple[int, np.ndarray, np.ndarray, float]]:
    """Vertical faces of the world: (surface index, centre xy, normal xy, half length)."""
    out = []
    for i, s in enumerate(model.surfaces):
        if s.kind in ("wall", "box") and abs(float(s.normal[2])) < 1e-6:
            out.append((i, s.center[:2].copy(), s.normal[:2] / np.linalg.norm(s.normal[:2]), float(s.half_u)))
    return out


def score_wall(wall: FusedWall, faces) -> WallScore:
    """A fused wall against the true face it lies on (the nearest within the match limits)."""
    seg = wall.segment
    mid = seg.mean(axis=0)
    n = wall.normal[:2]
    best = None
    for i, c, nt, half in faces:
        cos = abs(float(n @ nt))
        angle = math.acos(min(1.0, cos))
        dist = abs(float((mid - c) @ nt))
        along = abs(float((mid - c) @ np.array([-nt[1], nt[0]])))
        if angle <= MATCH_ANGLE and dist <= MATCH_DISTANCE and along <= half + MATCH_DISTANCE:
            if best is None or dist < best[2]:
                trace = float(np.max(np.abs((seg - c) @ nt)))
                best = (i, angle, dist, trace)
    face, angle, dist, trace = best if best is not None else (-1, math.nan, math.nan, math.nan)
    return WallScore(face, len(wall.scans), wall.quality, angle, dist, trace, wall.normal_stderr, wall.offset_stderr)


def true_junctions(model: WorldModel) -> list[tuple[np.ndarray, str, tuple[int, ...]]]:
    """Plan-view vertical junctions of the world: (point, ``concave`` | ``convex`` | ``edge``, faces)."""
    out = []
    for el in model.elements:
        if el.kind in (ElementKind.DIHEDRAL, ElementKind.EDGE) and abs(float(el.p1[2] - el.p0[2])) > 1e-6:
            kind = "concave" if el.kind == ElementKind.DIHEDRAL else ("convex" if len(el.surfaces) == 2 else "edge")
            out.append((np.asarray(el.p0[:2], float), kind, tuple(el.surfaces)))
    return out


def score_corners(out: TourResult, fused: FusedMap, scores: list[WallScore], model: WorldModel) -> None:
    """The map's corners against the world's vertical junctions: how many lie on one (and of its kind), and how
    many of the corners whose two faces the map holds as good walls it found."""
    truth = true_junctions(model)
    if not truth:
        return
    points = np.array([t[0] for t in truth])
    for f in fused.corners:
        d = np.hypot(*(points - f.point[:2]).T)
        if float(d.min()) <= CORNER_MATCH:
            out.corners_true += 1
            near = [truth[k][1] for k in np.flatnonzero(d <= CORNER_MATCH)]
            out.corners_kind += f.kind in near or (f.kind == "convex" and "edge" in near)
    good_faces = {s.face for s, w in zip(scores, fused.walls) if s.face >= 0 and w.good_observations > 0}
    found = np.array([f.point[:2] for f in fused.corners]).reshape(-1, 2)
    for xy, kind, faces in truth:
        if kind != "edge" and set(faces) <= good_faces:
            out.corners_seen += 1
            out.corners_found += bool(len(found)) and float(np.hypot(*(found - xy).T).min()) <= CORNER_MATCH


def true_corners(model: WorldModel) -> np.ndarray:
    """Plan-view points where two true faces at least 30° apart meet (k, 2)."""
    pts = []
    for el in model.elements:
        if el.kind in (ElementKind.DIHEDRAL, ElementKind.EDGE, ElementKind.TRIHEDRAL):
            if abs(float(el.p1[2] - el.p0[2])) > 1e-6 or el.kind == ElementKind.TRIHEDRAL:
                pts.append(el.p0[:2])
    return np.array(pts).reshape(-1, 2)


def fuse(observations: list[ScanObservation], config: FusionConfig) -> tuple[FusedMap, list[tuple[int, float]]]:
    """The tour fused in order; each update's (walls in the map before it, CPU s)."""
    mapper = WallMapper(config)
    updates = []
    for obs in observations:
        n = mapper.walls
        t = time.process_time()
        mapper.add_scan(obs)
        updates.append((n, time.process_time() - t))
    return mapper.snapshot(), updates


def tour(family: str, seed: int, method: str = "lel") -> TourResult:
    """Simulate, extract, fuse and score one world's tour, for the map of record and the oracle map."""
    run = world_run(family, seed)
    observed, oracle = [], []
    for index in range(len(run.world.poses)):
        scan = sweep(run, index)
        start = scan_start(run, index)
        observed.append(scan_from_reconstruction(surfaces_message(scan, index + 1), start, method))
        oracle.append(scan_from_reconstruction(oracle_message(scan, index + 1), start, method))
    config = FusionConfig()
    fused, updates = fuse(observed, config)
    fused_oracle, _ = fuse(oracle, config)
    faces = vertical_faces(run.model)
    out = TourResult(family, seed, updates=updates)
    out.walls = [score_wall(w, faces) for w in fused.walls]
    score_corners(out, fused, out.walls, run.model)
    out.oracle_walls = [score_wall(w, faces) for w in fused_oracle.walls]
    out.unmatched_good = sum(1 for s in out.walls if s.face < 0 and s.quality == "good")
    corners = true_corners(run.model)
    for f in fused.corners:
        if len(corners):
            out.corners.append(float(np.min(np.hypot(*(corners - f.point[:2]).T))))
    for p, truth, odo in zip(fused.poses[1:], run.world.poses[1:], run.odometry[1:]):
        out.pose_fused.append((math.hypot(p.x - truth.x, p.y - truth.y), abs(wrap(p.heading - truth.heading))))
        out.pose_odometry.append((math.hypot(odo.x - truth.x, odo.y - truth.y), abs(wrap(odo.heading - truth.heading))))
    return out
