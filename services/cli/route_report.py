"""What the planner says about a map and its route: the walls it may trust, the route out and what it runs
through, or why there is none (for ``lelsonar planner --map`` and ``lelsonar demo --world``)."""

from __future__ import annotations

from rich.console import Console
from rich.table import Table
from shapely.geometry import LineString, Point

from lelsonar.map import floorplan
from lelsonar.map.result import FusedMap


def walls_table(fused: FusedMap) -> Table:
    """The walls of good evidence: verdict, σ, how many scans, how much of them was seen, and why not good."""
    table = Table(title="walls of good evidence", title_justify="left", show_edge=False, pad_edge=False)
    for col in ("wall", "verdict", "offset ± σ", "scans", "seen", "why not good"):
        table.add_column(col, justify="right" if col in ("wall", "scans", "seen") else "left")
    for w in fused.walls:
        if w.good_observations == 0:
            continue
        seen = sum(hi - lo for lo, hi in w.pieces)
        why = "; ".join(w.reasons) if w.quality != "good" else ""
        table.add_row(
            str(w.id),
            w.quality,
            f"{w.offset:.3f} ± {100 * w.offset_stderr:.1f} cm",
            str(len(w.scans)),
            f"{seen:.2f} m",
            why,
        )
    return table


def print_map(console: Console, fused: FusedMap, key: str) -> None:
    """The map's walls, by evidence and verdict, as the planner got it on ``key``."""
    evidence = [w for w in fused.walls if w.good_observations > 0]
    flagged = len(fused.walls) - len(evidence)
    console.print(
        f"the planner got the map on {key}: {len(evidence)} walls of good evidence "
        f"({sum(w.quality == 'good' for w in evidence)} good), {flagged} seen only flagged, "
        f"{len(fused.corners)} corners, {len(fused.poses)} poses",
        highlight=False,
    )
    if evidence:
        console.print(walls_table(fused))
    if flagged:
        console.print(
            f"{flagged} walls were seen only flagged (echoes whose bearing no sweep pinned: corners, wall ends): "
            "they are obstacles to the route all the same",
            highlight=False,
        )
    for note in fused.notes:
        console.print(f"note: {note}", highlight=False)


def why_no_route(fused: FusedMap, begin: tuple[float, float], plan: floorplan.PlanConfig) -> str:
    """Why :func:`~lelsonar.map.floorplan.route` found no way out from ``begin``."""
    if floorplan.route(fused, begin, None, plan, through_closed_gaps=True) is not None:
        return (
            "every way out crosses a wall where no scan saw through it: between two pieces the scans saw, or on "
            "to the corner that ends it (the tour saw no exit; a longer one might)"
        )
    return f"every way out is closed by a wall piece the robot cannot pass {plan.robot_radius:g} m from"


def print_route(
    console: Console,
    fused: FusedMap,
    begin: tuple[float, float],
    path: list[tuple[float, float]] | None,
    plan: floorplan.PlanConfig,
) -> None:
    """The route out, its length, what it runs through and relies on, and the frontier; or why there is none."""
    if path is None:
        why = why_no_route(fused, begin, plan)
        console.print(f"[red]no route out of the map from ({begin[0]:.2f}, {begin[1]:.2f}): {why}")
        return
    summary = floorplan.summarise_route(fused, path, plan)
    console.print(
        f"route out (robot radius {plan.robot_radius:g} m, {summary.length:.2f} m): "
        + " → ".join(f"({x:.2f}, {y:.2f})" for x, y in path),
        highlight=False,
    )
    beside = ", ".join(f"{n} {q}" for q, n in summary.beside.items() if n)
    console.print(
        f"it runs {summary.length - summary.unseen:.2f} m through space the scans saw free and "
        f"{summary.unseen:.2f} m through space no scan saw; it passes {summary.clearance:.2f} m from the nearest "
        f"wall piece (wall {summary.nearest_wall}); the walls beside it: {beside or 'none'}",
        highlight=False,
    )
    if summary.frontier is None:
        console.print("the exit is seen: the route ends in free space the scans saw", highlight=False)
    else:
        fx, fy = summary.frontier
        line = LineString(path)
        beyond = line.length - line.project(Point(fx, fy))
        console.print(
            f"the exit is not seen yet: the last {beyond:.2f} m of the route, from ({fx:.2f}, {fy:.2f}), run "
            "through space no scan saw free; the rover would explore that frontier first",
            highlight=False,
        )
