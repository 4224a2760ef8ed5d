"""`lelsonar bench map`: the map on the world families against the truth and against an oracle map, and its
update time per scan against its size.

* **Worlds** (``--worlds``): each family's worlds toured pose by pose through the simulator, the surface
  extractor and the map's adapter, fused, and scored (:mod:`lelsonar.tools.map_worlds`), on the development
  seeds ``0..N−1`` and, apart, on held-out seeds (``--holdout``): wall normal and offset errors of the walls
  seen in at least two scans (median, p95) against the truth and against the oracle map (the same fusion fed
  least squares on each mirror's true echoes), walls claiming good while off by more than 2 cm and more than
  3× the oracle map's wall on the same face, corners, and the poses after fusion against odometry alone.
* **Timing** (synthetic): seeded mazes toured end to end with the map's oracle observer
  (:mod:`lelsonar.map.synthetic`), the update time per scan by map size, the budget row at ``--walls`` walls.

A module with ``add_arguments(parser)`` and ``run(args) -> int``.
"""

from __future__ import annotations

import argparse
import math
import statistics
import time

#: First held-out seed: far from the development seeds.
HOLDOUT_BASE = 1000


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from lelsonar.cli.executor import add_ray_argument

    parser.add_argument("--worlds", default="all", help="world families, comma-separated, all, or none")
    parser.add_argument("--seeds", type=int, default=3, help="development worlds per family, seeds 0..N-1")
    parser.add_argument(
        "--holdout",
        type=int,
        default=0,
        help=f"held-out worlds per family, seeds {HOLDOUT_BASE}.. (reported apart; default: %(default)s)",
    )
    parser.add_argument("--jobs", type=int, default=None, help="worker processes (default: one per core)")
    add_ray_argument(parser)
    parser.add_argument("--cells", type=int, default=18, help="synthetic maze side in cells (default: %(default)s)")
    parser.add_argument("--timing-seeds", type=int, default=1, help="synthetic mazes for the timing rows")
    parser.add_argument(
        "--budget", type=float, default=20.0, help="target ms a scan with --walls walls (default: %(default)s)"
    )
    parser.add_argument("--walls", type=int, default=200, help="map size the budget is for (default: %(default)s)")


def _floor_update_times(odometry_steps) -> list[float]:
    """The solver's own cost: the same ISAM2 stream of poses with odometry only (no walls, no association)."""
    import numpy as np

    from lelsonar.map import graph
    from lelsonar.map.fusion import FusionConfig
    from lelsonar.map.lines import pose_compose

    solver = graph.MapGraph(FusionConfig().relinearize_threshold, FusionConfig().relinearize_skip)
    times = []
    pose = np.zeros(3)
    for k, (step, cov) in enumerate(odometry_steps):
        if k == 0:
            solver.add_prior(0, pose, np.eye(3) * 1e-6)
        else:
            pose = pose_compose(pose, step)
            solver.add_odometry(k - 1, k, step, cov)
        solver.add_pose(k, pose)
        c = time.process_time()
        solver.update()
        solver.pose_marginal(k)
        times.append(time.process_time() - c)
    return times


def _pct(values, q: float) -> float:
    import numpy as np

    return float(np.percentile(values, q)) if len(values) else math.nan


def run_timing(args: argparse.Namespace) -> int:
    """The synthetic timing rows and the synthetic walls' accuracy; 1 when over the budget."""
    import os

    import numpy as np

    from lelsonar.map.fusion import FusionConfig, WallMapper
    from lelsonar.map.lines import pose_between, wrap
    from lelsonar.map.synthetic import NoiseModel, maze, observe_world, true_corners, truth_of
    from lelsonar.tools.bench import machine, progress

    # (walls in the map before the update, wall-clock s, CPU s of this process): on a shared host the CPU
    # time is the update's own cost, the wall-clock time adds the other processes' share of the cores.
    updates: list[tuple[int, float, float, float]] = []  # … and the CPU s of reading the map after it
    floor: list[float] = []
    snapshots: list[float] = []
    wall_rows: list[tuple[float, float, float, float, str]] = []  # |Δθ|, |Δρ|, z_θ, z_ρ, quality (seen ≥ 2)
    once = 0
    corner_errors: list[float] = []
    pose_fused, pose_odo, head_fused, head_odo = [], [], [], []
    for seed in progress(range(args.timing_seeds), "mazes"):
        world = maze(args.cells, np.random.default_rng(seed), tour=True)
        scans, _, odometry = observe_world(world, NoiseModel(), np.random.default_rng(1000 + seed))
        # Collinear walls apart by more than 2 m are kept apart here, as a map of that many walls needs: the
        # synthetic maze's cell walls line up across the maze.
        mapper = WallMapper(FusionConfig(max_gap=2.0))
        for scan in scans:
            n = mapper.walls
            t, c = time.perf_counter(), time.process_time()
            mapper.add_scan(scan)
            wall_s, cpu_s = time.perf_counter() - t, time.process_time() - c
            c = time.process_time()
            mapper.snapshot(polished=False)  # what the live mapper publishes after each scan
            updates.append((n, wall_s, cpu_s, time.process_time() - c))
        steps = [(np.zeros(3), np.eye(3))] + [
            (pose_between(a.pose.vector, b.pose.vector), b.step_covariance)
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
        f"{args.timing_seeds} synthetic mazes of {args.cells}×{args.cells} cells toured ({len(updates)} scans); "
        f"floor = an ISAM2 update of the same poses with odometry only: {floor_ms:.2f} ms CPU"
    )
    print(
        f"\n{'walls in map':>14} {'scans':>6} {'CPU med ms':>11} {'CPU p90 ms':>11} {'wall med ms':>12} "
        f"{'CPU × floor':>12} {'read med ms':>12}"
    )
    top = max(u[0] for u in updates)
    for lo in range(0, top + 50, 50):
        rows = [(1e3 * w, 1e3 * c, 1e3 * r) for n, w, c, r in updates if lo <= n < lo + 50]
        if rows:
            cpu = [c for _, c, _ in rows]
            med = statistics.median(cpu)
            print(
                f"{f'{lo}–{lo + 49}':>14} {len(rows):>6} {med:11.2f} {_pct(cpu, 90):11.2f} "
                f"{statistics.median(w for w, _, _ in rows):12.2f} {med / floor_ms:12.1f} "
                f"{statistics.median(r for _, _, r in rows):12.2f}"
            )
    near = [(1e3 * c, 1e3 * r) for n, _, c, r in updates if abs(n - args.walls) <= 25]
    verdict = 0
    if near:
        med = statistics.median(c for c, _ in near)
        ok = med <= args.budget
        verdict = 0 if ok else 1
        print(
            f"at {args.walls} ± 25 walls: median {med:.2f} ms CPU a scan ({len(near)} scans): "
            f"{'within' if ok else 'OVER'} the {args.budget:g} ms budget; reading the map after it (as the live "
            f"mapper publishes it, unpolished): median {statistics.median(r for _, r in near):.2f} ms"
        )
    else:
        print(f"no update with {args.walls} ± 25 walls in the map: raise --cells")
    print(
        f"polished map (LM over the graph, marginals, verdicts, corners): {1e3 * statistics.median(snapshots):.1f} ms"
    )

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


def _oracle_by_face(result) -> dict[int, float]:
    """The oracle map's best trace error on each true face."""
    out: dict[int, float] = {}
    for w in result.oracle_walls:
        if w.face >= 0:
            out[w.face] = min(out.get(w.face, math.inf), w.trace)
    return out


def false_good(result) -> list:
    """Walls claiming good while off by > 2 cm and > 3× the oracle map's on the same face (0 where it has none)."""
    oracle = _oracle_by_face(result)
    return [
        w
        for w in result.walls
        if w.quality == "good" and w.face >= 0 and w.trace > 0.02 and w.trace > 3.0 * oracle.get(w.face, 0.0)
    ]


def _row(family: str, which: str, results: list) -> list[str]:
    import numpy as np

    seen = [w for r in results for w in r.walls if w.scans >= 2 and w.face >= 0]
    oracle = [w for r in results for w in r.oracle_walls if w.scans >= 2 and w.face >= 0]
    ang = [math.degrees(w.angle) for w in seen]
    off = [100 * w.offset for w in seen]
    o_ang = [math.degrees(w.angle) for w in oracle]
    o_off = [100 * w.offset for w in oracle]
    corners = [100 * c for r in results for c in r.corners]
    n_corners = len(corners)
    on_truth = sum(r.corners_true for r in results)
    kind_ok = sum(r.corners_kind for r in results)
    corners_seen = sum(r.corners_seen for r in results)
    found = sum(r.corners_found for r in results)
    fused = np.array([p for r in results for p in r.pose_fused]).reshape(-1, 2)
    odo = np.array([p for r in results for p in r.pose_odometry]).reshape(-1, 2)
    upd = [1e3 * c for r in results for _, c in r.updates]
    bad = sum(len(false_good(r)) for r in results)
    unmatched = sum(r.unmatched_good for r in results)

    def pair(v: list[float], fmt: str = ".2f") -> str:
        return f"{_pct(v, 50):{fmt}} / {_pct(v, 95):{fmt}}" if v else "–"

    ratio = (
        f"{_pct(ang, 95) / max(_pct(o_ang, 95), 1e-9):.1f} / {_pct(off, 95) / max(_pct(o_off, 95), 1e-9):.1f}"
        if seen and oracle
        else "–"
    )
    return [
        family,
        which,
        str(len(results)),
        f"{len(seen)} ({sum(w.quality == 'good' for w in seen)})",
        pair(ang),
        pair(off),
        f"{len(oracle)}",
        pair(o_ang),
        pair(o_off),
        ratio,
        f"{bad} / {unmatched}",
        pair(corners, ".1f"),
        f"{on_truth}/{n_corners} ({kind_ok}) / {found}/{corners_seen}",
        f"{100 * _pct(fused[:, 0], 50):.1f} / {100 * _pct(odo[:, 0], 50):.1f}" if len(fused) else "–",
        f"{math.degrees(_pct(fused[:, 1], 50)):.2f} / {math.degrees(_pct(odo[:, 1], 50)):.2f}" if len(fused) else "–",
        f"{_pct(upd, 50):.1f}",
    ]


def run_worlds(args: argparse.Namespace) -> int:
    """The world families' table; 1 when a wall claims good while off (see :func:`false_good`)."""
    from rich.console import Console
    from rich.table import Table

    from lelsonar.cli.executor import config_from_args, map_values
    from lelsonar.errors import ConfigError
    from lelsonar.sim.worlds import world_families
    from lelsonar.tools.bench import machine, progress
    from lelsonar.tools.map_worlds import tour

    families = world_families(args.worlds)
    if args.seeds < 0 or args.holdout < 0 or args.seeds + args.holdout < 1:
        raise ConfigError("--seeds and --holdout must be ≥ 0, and at least one world")
    sets = [("dev", range(args.seeds)), ("held-out", range(HOLDOUT_BASE, HOLDOUT_BASE + args.holdout))]
    items = [(f, s) for f in families for _, seeds in sets for s in seeds]

    def advance(stream):
        yield from progress(stream, "map tours", total=len(items))

    t0 = time.perf_counter()
    results = map_values(tour, items, config_from_args(args, "jobs"), wrap=advance)
    wall = time.perf_counter() - t0
    console = Console(width=240)
    table = Table(title=f"map on the world families — {machine()}, {wall:.0f} s")
    for col in (
        "family",
        "seeds",
        "tours",
        "walls ≥2 scans (good)",
        "normal ° med/p95",
        "offset cm med/p95",
        "oracle walls",
        "oracle normal °",
        "oracle offset cm",
        "p95 / oracle's (n, ρ)",
        "false good / good on no face",
        "corner cm med/p95",
        "corners on truth (kind) / found",
        "pose cm fused/odom",
        "heading ° fused/odom",
        "update ms",
    ):
        table.add_column(col, justify="right")
    by_key = {(r.family, r.seed): r for r in results}
    total_bad = 0
    for which, seeds in sets:
        if not len(seeds):
            continue
        for family in families:
            rs = [by_key[(family, s)] for s in seeds]
            total_bad += sum(len(false_good(r)) for r in rs)
            table.add_row(*_row(family, which, rs))
        table.add_row(*_row("all", which, [by_key[(f, s)] for f in families for s in seeds]), end_section=True)
    console.print(table)
    for r in results:
        for w in false_good(r):
            console.print(
                f"good but off: {r.family} seed {r.seed} face {w.face}: {100 * w.trace:.1f} cm, "
                f"{math.degrees(w.angle):.2f}° "
                f"(σ {100 * w.offset_stderr:.2f} cm, {math.degrees(w.normal_stderr):.2f}°)",
                highlight=False,
            )
    console.print(
        "walls seen in ≥ 2 scans and lying on a true face; offset: the true face's distance from the middle of the "
        "fused stretch; oracle: the same fusion fed LS on each mirror's true echoes; false good: good while its "
        "stretch is > 2 cm and > 3× the oracle map's off the true face; corner cm: each map corner to the nearest true "
        "vertical junction; on truth: map corners within 10 cm of one (of its kind), found: of the true corners whose "
        "two faces the map holds as good walls, those with a map corner within 10 cm; pose: median error after the "
        "first pose; "
        "update: CPU ms a scan.",
        highlight=False,
    )
    return 1 if total_bad else 0


def run(args: argparse.Namespace) -> int:
    from lelsonar.errors import ConfigError

    if args.cells < 2 or args.timing_seeds < 1:  # refused before the worlds' run, not after it
        raise ConfigError("--cells must be ≥ 2 and --timing-seeds ≥ 1")
    rc = 0
    if args.worlds != "none":
        rc |= run_worlds(args)
    rc |= run_timing(args)
    return rc
