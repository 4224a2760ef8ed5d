"""`lelsonar bench map`: the map's update time per scan against its size, its walls against the truth, and
its poses against odometry alone, on seeded synthetic mazes toured end to end.

The worlds are the map's oracle observer (:mod:`lelsonar.map.synthetic`): each wall observation drawn from
the covariance it states, odometry drifting as its covariance says.  A module with ``add_arguments(parser)``
and ``run(args) -> int``.
"""

from __future__ import annotations

import argparse
import math
import statistics
import time


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--cells", type=int, default=16, help="maze side in cells (default: %(default)s)")
    parser.add_argument("--seeds", type=int, default=2, help="mazes, seeds 0..N-1 (default: %(default)s)")
    parser.add_argument(
        "--budget", type=float, default=20.0, help="target ms a scan with --walls walls (default: %(default)s)"
    )
    parser.add_argument("--walls", type=int, default=200, help="map size the budget is for (default: %(default)s)")


def _floor_update_times(odometry_steps) -> list[float]:
    """The solver's own cost: the same ISAM2 stream of poses with odometry only (no walls, no association)."""
    import gtsam
    import numpy as np

    from lelsonar.map import graph
    from lelsonar.map.fusion import FusionConfig

    isam = graph.isam2(FusionConfig().relinearize_threshold, FusionConfig().relinearize_skip)
    times = []
    pose = gtsam.Pose2()
    for k, (step, cov) in enumerate(odometry_steps):
        factors, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if k == 0:
            factors.add(graph.prior_factor(0, pose, np.eye(3) * 1e-6))
        else:
            pose = pose.compose(step)
            factors.add(graph.odometry_factor(k - 1, k, step, cov))
        values.insert(graph.pose_key(k), pose)
        c = time.process_time()
        isam.update(factors, values)
        isam.calculateEstimate()
        isam.marginalCovariance(graph.pose_key(k))
        times.append(time.process_time() - c)
    return times


def _pct(values, q: float) -> float:
    import numpy as np

    return float(np.percentile(values, q)) if len(values) else math.nan


def run(args: argparse.Namespace) -> int:
    import os

    import gtsam
    import numpy as np

    from lelsonar.errors import ConfigError
    from lelsonar.map.fusion import WallMapper
    from lelsonar.map.lines import wrap
    from lelsonar.map.synthetic import NoiseModel, maze, observe_world, true_corners, truth_of
    from lelsonar.tools.bench import machine, progress

    if args.cells < 2 or args.seeds < 1:
        raise ConfigError("--cells must be ≥ 2 and --seeds ≥ 1")
    # (walls in the map before the update, wall-clock s, CPU s of this process): on a shared host the CPU
    # time is the update's own cost, the wall-clock time adds the other processes' share of the cores.
    updates: list[tuple[int, float, float]] = []
    floor: list[float] = []
    snapshots: list[float] = []
    wall_rows: list[tuple[float, float, float, float, str]] = []  # |Δθ|, |Δρ|, z_θ, z_ρ, quality (seen ≥ 2)
    once = 0
    corner_errors: list[float] = []
    pose_fused, pose_odo, head_fused, head_odo = [], [], [], []
    for seed in progress(range(args.seeds), "mazes"):
        world = maze(args.cells, np.random.default_rng(seed), tour=True)
        scans, _, odometry = observe_world(world, NoiseModel(), np.random.default_rng(1000 + seed))
        mapper = WallMapper()
        for scan in scans:
            n = mapper.walls
            t, c = time.perf_counter(), time.process_time()
            mapper.add_scan(scan)
            updates.append((n, time.perf_counter() - t, time.process_time() - c))
        steps = [(gtsam.Pose2(), np.eye(3))] + [
            (gtsam.Pose2(*a.pose.vector).between(gtsam.Pose2(*b.pose.vector)), b.step_covariance)
            for a, b in zip(scans, scans[1:])
            if b.step_covariance is not None
        ]
        floor += _floor_update_times(steps)
        t = time.perf_counter()
        m = mapper.snapshot()
        snapshots.append(time.perf_counter() - t)
        for w in m.walls:
            if len(w.scans) < 2:
                once += 1
                continue
            _, line = truth_of(world, w)
            dt, dr = abs(wrap(w.line[0] - line[0])), abs(w.line[1] - line[1])
            wall_rows.append((dt, dr, dt / w.normal_stderr, dr / w.offset_stderr, w.quality))
        corners = true_corners(world)
        for f in m.corners:
            if f.source == "walls":
                corner_errors.append(float(np.min(np.hypot(*(corners - f.point[:2]).T))))
        for p, truth, odo in zip(m.poses[1:], world.poses[1:], odometry[1:]):
            pose_fused.append(math.hypot(p.x - truth[0], p.y - truth[1]))
            pose_odo.append(math.hypot(odo[0] - truth[0], odo[1] - truth[1]))
            head_fused.append(abs(wrap(p.heading - truth[2])))
            head_odo.append(abs(wrap(odo[2] - truth[2])))

    floor_ms = 1e3 * statistics.median(floor)
    print(f"machine: {machine()}, numpy {np.__version__}, load {os.getloadavg()[0]:.1f}")
    print(
        f"{args.seeds} mazes of {args.cells}×{args.cells} cells toured ({len(updates)} scans); "
        f"floor = an ISAM2 update of the same poses with odometry only: {floor_ms:.2f} ms CPU"
    )
    print(
        f"\n{'walls in map':>14} {'scans':>6} {'CPU med ms':>11} {'CPU p90 ms':>11} {'wall med ms':>12} "
        f"{'CPU × floor':>12}"
    )
    top = max(n for n, _, _ in updates)
    for lo in range(0, top + 50, 50):
        rows = [(1e3 * w, 1e3 * c) for n, w, c in updates if lo <= n < lo + 50]
        if rows:
            cpu = [c for _, c in rows]
            med = statistics.median(cpu)
            print(
                f"{f'{lo}–{lo + 49}':>14} {len(rows):>6} {med:11.2f} {_pct(cpu, 90):11.2f} "
                f"{statistics.median(w for w, _ in rows):12.2f} {med / floor_ms:12.1f}"
            )
    near = [1e3 * c for n, _, c in updates if abs(n - args.walls) <= 25]
    verdict = 0
    if near:
        med = statistics.median(near)
        ok = med <= args.budget
        verdict = 0 if ok else 1
        print(
            f"at {args.walls} ± 25 walls: median {med:.2f} ms CPU a scan ({len(near)} scans): "
            f"{'within' if ok else 'OVER'} the {args.budget:g} ms budget"
        )
    else:
        print(f"no update with {args.walls} ± 25 walls in the map: raise --cells")
    print(f"snapshot (marginals, verdicts, corners): median {1e3 * statistics.median(snapshots):.1f} ms")

    arr = np.array([r[:4] for r in wall_rows]) if wall_rows else np.zeros((0, 4))
    good = [r for r in wall_rows if r[4] == "good"]
    claims = sum(1 for r in good if r[1] > 0.02 and r[3] > 3.0)
    print(f"\nwalls seen in ≥ 2 scans: {len(wall_rows)} ({len(good)} good); seen once: {once}")
    print(f"{'':>12} {'median':>8} {'p95':>8}")
    print(f"{'normal °':>12} {math.degrees(_pct(arr[:, 0], 50)):8.3f} {math.degrees(_pct(arr[:, 0], 95)):8.3f}")
    print(f"{'offset cm':>12} {100 * _pct(arr[:, 1], 50):8.3f} {100 * _pct(arr[:, 1], 95):8.3f}")
    print(f"{'|err|/σ θ':>12} {_pct(arr[:, 2], 50):8.2f} {_pct(arr[:, 2], 95):8.2f}")
    print(f"{'|err|/σ ρ':>12} {_pct(arr[:, 3], 50):8.2f} {_pct(arr[:, 3], 95):8.2f}")
    print(f"good walls off by > 2 cm and > 3σ: {claims}")
    print(
        f"corners where fused walls meet: {len(corner_errors)}, distance to the nearest true corner "
        f"median {100 * _pct(corner_errors, 50):.2f} cm, p95 {100 * _pct(corner_errors, 95):.2f} cm"
    )
    print(f"\n{'pose error':>12} {'fused med':>10} {'fused p95':>10} {'odom med':>10} {'odom p95':>10}")
    print(
        f"{'position cm':>12} {100 * _pct(pose_fused, 50):10.2f} {100 * _pct(pose_fused, 95):10.2f} "
        f"{100 * _pct(pose_odo, 50):10.2f} {100 * _pct(pose_odo, 95):10.2f}"
    )
    print(
        f"{'heading °':>12} {math.degrees(_pct(head_fused, 50)):10.2f} {math.degrees(_pct(head_fused, 95)):10.2f} "
        f"{math.degrees(_pct(head_odo, 50)):10.2f} {math.degrees(_pct(head_odo, 95)):10.2f}"
    )
    return verdict
