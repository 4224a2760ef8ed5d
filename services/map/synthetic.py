"""Synthetic worlds for the map's tests and bench: wall segments seen from known poses, with the noise
each observation states (seeded), and odometry that drifts as its covariance says.

This is an oracle observer, not the acoustic simulator: a wall answers where the foot of the
perpendicular from the scanner falls on it (a specular reflector), within range and unoccluded, and
its observed patch is the stretch within the beam's half-width of that foot.  It checks the fusion
against independent truth; the physics of the echoes are the simulator's job.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lelsonar.map.lines import wrap
from lelsonar.map.observation import Pose2D, ScanObservation, WallObservation


@dataclass(frozen=True)
class NoiseModel:
    """σ of what a scan reports and of the odometry's steps.

    Parameters
    ----------
    bearing : float
        σ of a wall's normal azimuth, rad.
    range_floor, range_per_m : float
        σ of a wall's offset, ``range_floor + range_per_m · distance``, m.
    step_xy_per_m, step_heading_per_m : float
        σ of an odometry step per metre travelled (m/m, rad/m).
    step_floor_xy, step_floor_heading : float
        σ of any odometry step, m and rad.
    """

    bearing: float = math.radians(1.0)
    range_floor: float = 0.003
    range_per_m: float = 0.002
    step_xy_per_m: float = 0.03
    step_heading_per_m: float = math.radians(2.0)
    step_floor_xy: float = 0.005
    step_floor_heading: float = math.radians(0.3)


@dataclass(frozen=True)
class World:
    """Wall segments ``(n, 2, 2)`` (m) and the poses ``(k, 3)`` ``(x, y, ψ)`` where the robot scans."""

    segments: np.ndarray
    poses: np.ndarray
    exit: np.ndarray | None = None  # a point outside the walls the robot should reach, m


def _cross2(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _blocked(origin: np.ndarray, targets: np.ndarray, segments: np.ndarray, skip: int) -> np.ndarray:
    """Whether the segment from ``origin`` to each target crosses a wall other than ``skip``."""
    p = origin
    r = targets - p  # (t, 2)
    q = segments[:, 0]  # (n, 2)
    s = segments[:, 1] - segments[:, 0]
    denom = _cross2(r[:, None, :], s[None, :, :])  # (t, n)
    qp = q[None, :, :] - p
    with np.errstate(divide="ignore", invalid="ignore"):
        t = _cross2(qp, s[None, :, :]) / denom
        u = _cross2(qp, r[:, None, :]) / denom
    hit = (np.abs(denom) > 1e-12) & (t > 1e-6) & (t < 1 - 1e-6) & (u >= 0) & (u <= 1)
    hit[:, skip] = False
    return hit.any(axis=1)


def true_observations(
    world: World, pose: np.ndarray, *, max_range: float = 4.0, half_beam: float = math.radians(35.0)
) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """The walls a scanner at ``pose`` sees: ``(segment index, true (θ_s, ρ_s), patch end points (2, 2) world)``."""
    out = []
    origin = pose[:2]
    for i, (a, b) in enumerate(world.segments):
        d = b - a
        length = float(np.hypot(*d))
        t = d / length
        u = float((origin - a) @ t)
        foot = a + u * t
        dist = float(np.hypot(*(foot - origin)))
        if not (0.0 <= u <= length) or dist > max_range or dist < 0.05:
            continue
        if _blocked(origin, foot[None, :], world.segments, i)[0]:
            continue
        half = dist * math.tan(half_beam)
        ends = np.array([a + max(0.0, u - half) * t, a + min(length, u + half) * t])
        # Trim the patch to what is in view: sample it, keep the visible run around the foot.
        samples = np.linspace(ends[0], ends[1], 21)
        visible = ~_blocked(origin, samples, world.segments, i)
        if not visible[10]:
            continue
        lo = hi = 10
        while lo > 0 and visible[lo - 1]:
            lo -= 1
        while hi < 20 and visible[hi + 1]:
            hi += 1
        n = (foot - origin) / dist  # away from the scanner
        theta_w = math.atan2(n[1], n[0])
        rho_w = float(n @ foot)
        theta_s = wrap(theta_w - pose[2])
        rho_s = rho_w - float(n @ origin)
        out.append((i, np.array([theta_s, rho_s]), np.array([samples[lo], samples[hi]])))
    return out


def observe_world(
    world: World,
    noise: NoiseModel,
    rng: np.random.Generator,
    *,
    max_range: float = 4.0,
    flagged: dict[tuple[int, int], tuple[str, np.ndarray]] | None = None,
) -> tuple[list[ScanObservation], list[list[int]], np.ndarray]:
    """Every scan of the world, as the map takes it.

    Parameters
    ----------
    flagged : dict, optional
        ``(pose index, segment index) → (quality, bias of (θ_s, ρ_s))``: that observation is reported
        with this verdict and biased (what a flagged surface looks like).

    Returns
    -------
    scans : list of ScanObservation
    seen : list of list of int
        The segment index of each scan's walls, in order.
    odometry : (k, 3) array
        The odometry poses reported.
    """
    flagged = flagged or {}
    scans, seen = [], []
    odo = world.poses[0].copy()
    cov = np.diag([1e-6, 1e-6, 1e-6])
    odometry = []
    for k, pose in enumerate(world.poses):
        step_cov = None
        if k > 0:
            prev = world.poses[k - 1]
            c, s = math.cos(prev[2]), math.sin(prev[2])
            dxy = np.array([[c, s], [-s, c]]) @ (pose[:2] - prev[:2])
            step = np.array([dxy[0], dxy[1], wrap(pose[2] - prev[2])])
            dist = float(np.hypot(*dxy))
            sxy = noise.step_floor_xy + noise.step_xy_per_m * dist
            sh = noise.step_floor_heading + noise.step_heading_per_m * dist
            step_cov = np.diag([sxy**2, sxy**2, sh**2])
            measured = step + rng.multivariate_normal(np.zeros(3), step_cov)
            c, s = math.cos(odo[2]), math.sin(odo[2])
            # Odometry composes the measured step onto its own estimate: its error grows.
            jac = np.array(
                [[1, 0, -s * measured[0] - c * measured[1]], [0, 1, c * measured[0] - s * measured[1]], [0, 0, 1]]
            )
            rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
            cov = jac @ cov @ jac.T + rot @ step_cov @ rot.T
            odo = np.array(
                [
                    odo[0] + c * measured[0] - s * measured[1],
                    odo[1] + s * measured[0] + c * measured[1],
                    wrap(odo[2] + measured[2]),
                ]
            )
        odometry.append(odo.copy())
        walls, ids = [], []
        for i, truth, patch in true_observations(world, pose, max_range=max_range):
            sr = noise.range_floor + noise.range_per_m * truth[1]
            obs_cov = np.diag([noise.bearing**2, sr**2])
            z = truth + rng.multivariate_normal(np.zeros(2), obs_cov)
            quality, reasons = "good", tuple[str, ...]()
            if (k, i) in flagged:
                quality, bias = flagged[(k, i)]
                z = z + bias
                reasons = ("synthetic: flagged",)
            c, s = math.cos(pose[2]), math.sin(pose[2])
            local = (patch - pose[:2]) @ np.array([[c, -s], [s, c]])
            extent = np.column_stack([np.repeat(local, 2, axis=0), np.tile([-0.2, 0.2], 2)])
            walls.append(
                WallObservation(
                    normal=np.array([math.cos(z[0]), math.sin(z[0]), 0.0]),
                    offset=float(z[1]),
                    covariance=obs_cov,
                    extent=extent,
                    quality=quality,
                    reasons=reasons,
                    label=f"s{i}",
                )
            )
            ids.append(i)
        scans.append(
            ScanObservation(
                scan_id=k + 1,
                pose=Pose2D(float(odo[0]), float(odo[1]), float(odo[2]), z=0.3, covariance=cov.copy()),
                walls=tuple(walls),
                step_covariance=step_cov,
            )
        )
        seen.append(ids)
    return scans, seen, np.array(odometry)


def room(width: float = 4.0, depth: float = 3.0) -> World:
    """A rectangular room with a loop of poses inside."""
    corners = np.array([[0, 0], [width, 0], [width, depth], [0, depth]], float)
    segments = np.array([[corners[i], corners[(i + 1) % 4]] for i in range(4)])
    m = 0.8
    poses = np.array(
        [
            [m, m, 0.0],
            [width / 2, m, 0.0],
            [width - m, m, math.pi / 2],
            [width - m, depth - m, math.pi],
            [width / 2, depth - m, math.pi],
            [m, depth - m, -math.pi / 2],
            [m, m + 0.1, 0.0],
        ]
    )
    return World(segments=segments, poses=poses)


def maze(cells: int, rng: np.random.Generator, cell: float = 1.0, *, tour: bool = False) -> World:
    """A perfect maze of ``cells × cells`` (seeded depth-first carving), its exit on the east side, and
    the poses along the way from the south-west cell to the exit (cell centres, facing the way on).
    With ``tour``, the poses walk the whole maze instead (the carving's depth-first walk, back-tracking
    included: every cell is seen, corridors twice).

    Collinear walls that touch are one segment, as built walls are.
    """
    n = cells
    east = np.ones((n, n), bool)  # wall on the east side of cell (i, j): i = column, j = row
    north = np.ones((n, n), bool)
    visited = np.zeros((n, n), bool)
    stack = [(0, 0)]
    visited[0, 0] = True
    walk = [(0, 0)]
    while stack:
        i, j = stack[-1]
        options = [
            (i + di, j + dj)
            for di, dj in ((1, 0), (-1, 0), (0, 1), (0, -1))
            if 0 <= i + di < n and 0 <= j + dj < n and not visited[i + di, j + dj]
        ]
        if not options:
            stack.pop()
            if stack:
                walk.append(stack[-1])
            continue
        a, b = options[int(rng.integers(len(options)))]
        if a != i:
            east[min(a, i), j] = False
        else:
            north[i, min(b, j)] = False
        visited[a, b] = True
        stack.append((a, b))
        walk.append((a, b))
    exit_row = int(rng.integers(n))
    east[n - 1, exit_row] = False
    # The path from (0, 0) to the exit cell, breadth-first over open sides.
    prev: dict[tuple[int, int], tuple[int, int] | None] = {(0, 0): None}
    queue = [(0, 0)]
    while queue:
        i, j = queue.pop(0)
        for di, dj in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            a, b = i + di, j + dj
            if not (0 <= a < n and 0 <= b < n) or (a, b) in prev:
                continue
            open_ = (not east[min(a, i), j]) if di else (not north[i, min(b, j)])
            if open_:
                prev[(a, b)] = (i, j)
                queue.append((a, b))
    path = [(n - 1, exit_row)]
    while (back := prev[path[-1]]) is not None:
        path.append(back)
    path.reverse()
    if tour:
        path = walk
    poses = []
    for k, (i, j) in enumerate(path):
        nxt = path[k + 1] if k + 1 < len(path) else (i + 1, j)
        heading = math.atan2(nxt[1] - j, nxt[0] - i)
        poses.append([(i + 0.5) * cell, (j + 0.5) * cell, heading])
    segments = []
    # Vertical walls: the west boundary and each east side; horizontal: the south boundary and each north side.
    for i in range(-1, n):
        col = np.ones(n, bool) if i == -1 else east[i]
        segments += _runs(col, lambda a, b, x=(i + 1) * cell: [[x, a * cell], [x, b * cell]])
    for j in range(-1, n):
        row = np.ones(n, bool) if j == -1 else north[:, j]
        segments += _runs(row, lambda a, b, y=(j + 1) * cell: [[a * cell, y], [b * cell, y]])
    return World(
        segments=np.array(segments, float),
        poses=np.array(poses),
        exit=np.array([(n + 0.6) * cell, (exit_row + 0.5) * cell]),
    )


def _runs(flags: np.ndarray, make) -> list:
    out, start = [], None
    for k, f in enumerate(list(flags) + [False]):
        if f and start is None:
            start = k
        elif not f and start is not None:
            out.append(make(start, k))
            start = None
    return out


def truth_of(world: World, wall) -> tuple[int, np.ndarray]:
    """The true segment a fused wall lies on, and that segment's line ``(θ, ρ)`` oriented as the wall's normal.

    The segment nearest one of the wall's observed pieces (the middle of a piece to the segment), among
    those facing the same way; a wall joined across an opening has pieces on collinear segments, which
    share one line.
    """
    mids = np.array([seg.mean(axis=0) for seg in wall.piece_segments])
    best, best_d, best_line = -1, math.inf, np.zeros(2)
    for i, (a, b) in enumerate(world.segments):
        d = b - a
        n = np.array([-d[1], d[0]]) / math.hypot(*d)
        if n @ wall.normal[:2] < 0:
            n = -n
        line = np.array([math.atan2(n[1], n[0]), float(n @ a)])
        t = np.clip((mids - a) @ d / (d @ d), 0.0, 1.0)
        dist = float(np.min(np.hypot(*(a + t[:, None] * d - mids).T)))
        cost = dist + abs(wrap(line[0] - wall.line[0]))
        if cost < best_d:
            best, best_d, best_line = i, cost, line
    return best, best_line


def true_corners(world: World, tol: float = 1e-6) -> np.ndarray:
    """Where two walls meet at an angle (an end of one on the other), on the floor plane: (k, 2)."""
    out = []
    segs = world.segments
    for i, (a, b) in enumerate(segs):
        for j, (c, d) in enumerate(segs):
            if i == j:
                continue
            u, v = b - a, d - c
            if abs(u[0] * v[1] - u[1] * v[0]) < tol * np.hypot(*u) * np.hypot(*v):
                continue  # parallel walls never make a corner
            for p in (a, b):  # an end of wall i on wall j
                t = float((p - c) @ v / (v @ v))
                if -tol <= t <= 1 + tol and np.hypot(*(c + t * v - p)) < tol:
                    out.append(p)
    return np.unique(np.round(np.array(out).reshape(-1, 2), 9), axis=0)
