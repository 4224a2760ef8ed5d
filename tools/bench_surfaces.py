"""``lelsonar bench surfaces``: every surface of a sweep against the world simulator's truth.

For each world family (:mod:`lelsonar.sim.worlds`), seed and pose, one sweep is
simulated with waveforms, the echo amplitudes are read off them
(:func:`lelsonar.signal.energy.echo_amplitude`), and
:func:`lelsonar.reconstruct.estimate.surfaces.extract_surfaces` runs on the
measured γ and ranges.  The truth is the simulator's: which element set each
reading (``echo_index``) and the true pose.

Per class (plane, corner, edge):

* **found / seen** (recall): truth elements with at least ``--min-echoes``
  readings that some extracted item of any class claims (its majority element); a corner or
  an edge is seen when at least two capsules hear it (``+one capsule`` counts those one capsule
  alone hears: one receiver's ranges say nothing of where the target lies across the stack, so
  nothing of how far off the beam's axis it is nor how strong its echo is);
* **classified right**: of those, the ones every claim of which has the right class
  (mirror → plane, dihedral or trihedral → corner, edge → edge): one wrong claim beside a
  right one makes it wrong;
* **unknown**: of those, the ones claimed only by features that say their kind is not
  settled (with or beside claims of the right class): neither right nor wrong;
* **false**: extracted items whose majority reading is no element of that class
  (noise, a diffuse echo or another class); a feature whose kind is not settled claims
  no class, so it is never false;

and per plane:

* **error**: the largest distance between the fitted and the true plane over the
  true wall's trace 0.5 m either side of the foot of the perpendicular, cm (a
  bearing error shows as much as an offset error);
* **oracle**: what the surface's own true echoes allow a fit that knows which readings they are but not
  where the surface is (:mod:`lelsonar.tools.surface_oracle`): least squares on their ranges from their
  own beams' direction, with the beam pattern's bearing of their amplitudes weighed in where the two agree;
  the same error.  The ranges' least squares alone (``range LS``) is shown beside it: seen near its foot, a
  wall's ranges barely fix its bearing, so that fit's error is mostly chance;
* **failure claiming good**: verdict good while the error is > 2 cm and > 3× the oracle's;
* **clutter** (the room's walls, not the boxes' faces): good and within 3× the oracle (or one range's σ),
  or flagged not good with reasons; and the share of each wall's readings that are its own echoes;
* **extract CPU ms/sweep**: the extraction's own CPU time on each sweep (the median of a few runs, serial),
  median and p95 over the family's sweeps.

``--first-seed 10`` runs held-out worlds.  A second table runs the L families' scans
(:mod:`lelsonar.sim.scenes`, the paper mount) through the extractor with the joint corner
model off and on (``--l-seeds``): the walls' trace errors side by side, in the same run.
"""

from __future__ import annotations

import argparse
import math
from typing import TYPE_CHECKING

import numpy as np

from lelsonar.reconstruct.estimate.surfaces import SurfaceOptions
from lelsonar.sim.scenes import FAMILIES as L_FAMILIES
from lelsonar.sim.world import MOUNTS
from lelsonar.sim.world_geometry import build_model
from lelsonar.sim.worlds import draw_world, world_families
from lelsonar.tools.surface_scores import PlaneRecord, ScanRecord, l_scan_errors, run_scan

if TYPE_CHECKING:
    from rich.console import Console


def _l_scan_table(seeds: int, console: Console) -> None:
    from rich.table import Table

    table = Table(title=f"L scan (paper mount), the surfaces' two walls, joint corner model off → on ({seeds} seeds)")
    for col in ("family", "walls found", "err med cm", "err p95 cm", "err max cm", "good-but-failed (> 2 cm)"):
        table.add_column(col, justify="right")
    for family in L_FAMILIES:
        runs = [l_scan_errors(family, seed) for seed in range(seeds)]
        cells = []
        for joint in (False, True):
            errs = [100 * e for r in runs for e, _q in r[joint]]
            bad = sum(1 for r in runs for e, q in r[joint] if q == "good" and e > 0.02)
            cells.append((len(errs), _pct(errs, 50), _pct(errs, 95), max(errs, default=float("nan")), bad))
        off, on = cells
        table.add_row(
            family,
            f"{off[0]} → {on[0]} of {2 * seeds}",
            f"{off[1]:.2f} → {on[1]:.2f}",
            f"{off[2]:.2f} → {on[2]:.2f}",
            f"{off[3]:.2f} → {on[3]:.2f}",
            f"{off[4]} → {on[4]}",
        )
    console.print(table)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--worlds", default="all", help="comma-separated world families, or all")
    parser.add_argument("--seeds", type=int, default=3, help="worlds per family (seeds F..F+N-1)")
    parser.add_argument("--first-seed", type=int, default=0, help="F: the first world seed (held-out worlds: 10)")
    parser.add_argument("--max-poses", type=int, default=2, help="sweeps per world (its first poses)")
    parser.add_argument(
        "--l-seeds", type=int, default=3, help="L scans per L family for the joint corner model's A/B (0: none)"
    )
    parser.add_argument(
        "--no-joint-corners", action="store_true", help="fit each wall alone (the A/B of the joint corner model)"
    )
    parser.add_argument(
        "--mount",
        choices=(*MOUNTS, "both"),
        default="fan",
        help="the scanner's mount in the worlds: fan (horizontal), paper (vertical: a wall, the floor, the ceiling)",
    )


def _pct(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float("nan")


def run(args: argparse.Namespace) -> int:
    from rich.console import Console

    families = world_families(args.worlds)
    mounts = MOUNTS if args.mount == "both" else (args.mount,)
    options = SurfaceOptions(joint_corners=not args.no_joint_corners)
    console = Console(width=200)
    bad_total = 0
    for mount in mounts:
        records = run_mount(families, mount, args.first_seed, args.seeds, args.max_poses, options)
        bad_total += _family_table(records, mount, args, console)
        _kind_table(records, mount, console)
        _sigma_table(records, mount, console)
        _feature_sigma_table(records, mount, console)
    if args.l_seeds > 0:
        _l_scan_table(args.l_seeds, console)
    console.print(
        "err: largest distance between the fitted and true plane over ±0.5 m of the true wall's trace; "
        "oracle: LS on the surface's true echoes from their own beams with their beam pattern's bearing (range LS: the "
        "ranges' LS alone); good-but-failed: good while err > 2 cm "
        "and > 3× oracle; (right, unknown): claimed only with the right class, or only as a feature whose kind is not "
        "settled; +one capsule: corners/edges with enough echoes that one capsule alone hears (not in seen: one "
        "receiver cannot tell their kind); walls: the room's walls (not boxes' faces), good "
        "within 3× their oracle (or one range's σ), or flagged not good with reasons; own echoes: share of a wall's "
        "steps' readings that are its own."
    )
    return 1 if bad_total else 0


def run_mount(
    families: tuple[str, ...], mount: str, first_seed: int, seeds: int, max_poses: int, options: SurfaceOptions
) -> dict[str, list[ScanRecord]]:
    """Every family's worlds seen with one scanner mount: the scored sweeps per family."""
    from lelsonar.tools.bench import progress

    jobs = [(f, s) for f in families for s in range(first_seed, first_seed + seeds)]
    records: dict[str, list[ScanRecord]] = {f: [] for f in families}
    for family, seed in progress(jobs, f"surfaces ({mount} mount)"):
        model = build_model(draw_world(family, seed, mount=mount))
        for pose in range(min(max_poses, len(model.world.poses))):
            records[family].append(run_scan(family, seed, pose, model, options))
    return records


def _kind_table(records: dict[str, list[ScanRecord]], mount: str, console: Console) -> None:
    """Per kind of true surface (wall, box face, floor, ceiling), over every family."""
    from rich.table import Table

    recs = [r for rs in records.values() for r in rs]
    planes = [p for r in recs for p in r.planes]
    table = Table(title=f"surfaces per kind ({mount} mount, every family)")
    for col in (
        "kind",
        "found/seen",
        "err med cm",
        "err p95 cm",
        "oracle med cm",
        "med/oracle",
        "range LS med cm",
        "good",
        "good-but-failed",
    ):
        table.add_column(col, justify="right")
    for kind in ("wall", "box", "floor", "ceiling"):
        seen = sum((r.seen_kind or {}).get(kind, 0) for r in recs)
        found = sum((r.found_kind or {}).get(kind, 0) for r in recs)
        mine = [p for p in planes if p.kind == kind]
        if not seen and not mine:
            continue
        err = [100 * p.error for p in mine]
        orc = [100 * p.oracle for p in mine]
        ratio = float(np.median(err) / max(np.median(orc), 1e-9)) if mine else float("nan")
        failed = sum(1 for p in mine if p.quality == "good" and p.error > 0.02 and p.error > 3 * p.oracle)
        table.add_row(
            kind,
            f"{found}/{seen}",
            f"{_pct(err, 50):.2f}",
            f"{_pct(err, 95):.2f}",
            f"{_pct(orc, 50):.2f}",
            f"{ratio:.2f}",
            f"{_pct([100 * p.range_ls for p in mine], 50):.2f}",
            f"{sum(p.quality == 'good' for p in mine)}/{len(mine)}",
            str(failed),
        )
    console.print(table)


def coverage(z: list[float]) -> tuple[float, float, float]:
    """The shares of scores within 1, 2 and 3 (a Gaussian's: 68.3, 95.4, 99.7 %)."""
    a = np.abs(np.asarray([v for v in z if math.isfinite(v)]))
    if not a.size:
        return float("nan"), float("nan"), float("nan")
    return tuple(float(np.mean(a <= k)) for k in (1.0, 2.0, 3.0))  # type: ignore[return-value]


def _sigma_table(records: dict[str, list[ScanRecord]], mount: str, console: Console) -> None:
    """The honesty of the good planes' σ: the share of bearing and offset errors within 1, 2, 3 claimed σ."""
    from rich.table import Table

    planes = [p for rs in records.values() for r in rs for p in r.planes if p.quality == "good"]
    table = Table(title=f"good planes' σ against the truth ({mount} mount; a Gaussian: 68 / 95 / 99.7 %)")
    for col in (
        "kind",
        "good",
        "bearing ≤1/2/3σ %",
        "bearing > 3σ",
        "max |Δβ| > 3σ °",
        "offset ≤1/2/3σ %",
        "offset > 3σ",
    ):
        table.add_column(col, justify="right")
    for kind in ("all", "wall", "box", "floor", "ceiling"):
        mine = [p for p in planes if kind in ("all", p.kind)]
        if not mine:
            continue
        bz = [p.bearing_z for p in mine]
        hz = [p.offset_z for p in mine]
        b_out = [p for p in mine if math.isfinite(p.bearing_z) and abs(p.bearing_z) > 3]
        h_out = sum(1 for v in hz if math.isfinite(v) and abs(v) > 3)
        table.add_row(
            kind,
            str(len(mine)),
            "/".join(f"{100 * v:.0f}" for v in coverage(bz)),
            str(len(b_out)),
            f"{max((abs(math.degrees(p.bearing_error)) for p in b_out), default=0.0):.2f}",
            "/".join(f"{100 * v:.0f}" for v in coverage(hz)),
            str(h_out),
        )
    console.print(table)
    for p in (p for p in planes if math.isfinite(p.bearing_z) and abs(p.bearing_z) > 3):
        console.print(
            f"good plane > 3σ in bearing ({mount} mount): {p.family} seed {p.seed} pose {p.pose} element "
            f"{p.element} ({p.kind}): Δβ {math.degrees(p.bearing_error):+.2f}° = {p.bearing_z:+.1f}σ, "
            f"err {100 * p.error:.2f} cm"
        )


def _feature_sigma_table(records: dict[str, list[ScanRecord]], mount: str, console: Console) -> None:
    """The honesty of the features' σ: each right-kind feature's distance from its true line over its σ there."""
    from rich.table import Table

    placed = [f for rs in records.values() for r in rs for f in r.features]
    table = Table(title=f"corners' and edges' σ against the truth ({mount} mount; a Gaussian: 68 / 95 / 99.7 %)")
    for col in ("kind", "features", "≤1/2/3σ %", "> 3σ", "> 3σ and > 2 cm", "off med cm", "σ med cm"):
        table.add_column(col, justify="right")
    for kind in ("corner", "edge"):
        mine = [(d, s) for k, d, s in placed if k == kind]
        if not mine:
            continue
        z = [d / s if s > 0 else (0.0 if d == 0 else math.inf) for d, s in mine]
        out = [(d, s) for (d, s), v in zip(mine, z, strict=True) if v > 3]
        table.add_row(
            kind,
            str(len(mine)),
            "/".join(f"{100 * v:.0f}" for v in coverage(z)),
            str(len(out)),
            str(sum(d > 0.02 for d, _s in out)),
            f"{100 * _pct([d for d, _s in mine], 50):.2f}",
            f"{100 * _pct([s for _d, s in mine], 50):.2f}",
        )
    console.print(table)


def _family_table(records: dict[str, list[ScanRecord]], mount: str, args: argparse.Namespace, console: Console) -> int:
    """The per-family table and its failures; returns the failures that claimed good."""
    from rich.table import Table

    from lelsonar.tools.bench import machine

    families = tuple(records)
    seeds = f"seeds {args.first_seed}–{args.first_seed + args.seeds - 1}"
    table = Table(title=f"surfaces per family ({mount} mount, {seeds}, ≤ {args.max_poses} sweeps each) — {machine()}")
    for col in (
        "family",
        "planes found/seen",
        "err med cm",
        "err p95 cm",
        "oracle med cm",
        "med/oracle",
        "angle med °",
        "good",
        "good-but-failed",
        "false planes (good)",
        "good off every true mirror > 2 cm",
        "corners found/seen (right, unknown) +one capsule",
        "edges found/seen (right, unknown) +one capsule",
        "false corners/edges",
        "unexplained",
        "walls good ≤3× oracle / flagged / neither",
        "walls' own echoes med",
        "extract CPU ms/sweep med (p95)",
    ):
        table.add_column(col, justify="right")
    bad_total = 0
    neither: list[tuple[str, PlaneRecord]] = []
    for family in families:
        recs = records[family]
        planes = [p for r in recs for p in r.planes]
        err = [100 * p.error for p in planes]
        orc = [100 * p.oracle for p in planes]
        ratio = float(np.median(err) / max(np.median(orc), 1e-9)) if planes else float("nan")
        failed_good = sum(1 for p in planes if p.quality == "good" and p.error > 0.02 and p.error > 3 * p.oracle)
        bad_total += failed_good
        # Clutter: each wall of the room (not a box's face) good and within 3× its oracle, or flagged.
        walls = [p for p in planes if p.wall]
        unclean = [p for p in walls if not ((p.quality == "good" and p.within_oracle) or p.flagged)]
        neither.extend((family, p) for p in unclean)

        def tot(attr: str, cls: str, recs: list[ScanRecord] = recs) -> int:
            return sum(getattr(r, attr)[cls] for r in recs)

        def lone(cls: str, recs: list[ScanRecord] = recs) -> int:
            return sum((r.one_capsule or {}).get(cls, 0) for r in recs)

        table.add_row(
            family,
            f"{tot('found', 'plane')}/{tot('seen', 'plane')}",
            f"{_pct(err, 50):.2f}",
            f"{_pct(err, 95):.2f}",
            f"{_pct(orc, 50):.2f}",
            f"{ratio:.2f}",
            f"{math.degrees(_pct([p.angle for p in planes], 50)):.2f}",
            f"{sum(p.quality == 'good' for p in planes)}/{len(planes)}",
            str(failed_good),
            f"{tot('false', 'plane')} ({sum(r.false_good for r in recs)} good)",
            f"{sum(r.good_off_every for r in recs)}/{sum(r.good_planes for r in recs)}",
            f"{tot('found', 'corner')}/{tot('seen', 'corner')} ({tot('right', 'corner')}, {tot('unknown', 'corner')})"
            f" +{lone('corner')}",
            f"{tot('found', 'edge')}/{tot('seen', 'edge')} ({tot('right', 'edge')}, {tot('unknown', 'edge')})"
            f" +{lone('edge')}",
            f"{tot('false', 'corner')}/{tot('false', 'edge')}",
            f"{100 * float(np.mean([r.unexplained_share for r in recs])):.0f} %",
            f"{sum(p.quality == 'good' and p.within_oracle for p in walls)} / {sum(p.flagged for p in walls)} / "
            f"{len(unclean)}",
            f"{100 * _pct([p.own_share for p in walls], 50):.0f} %",
            f"{1e3 * _pct([r.extract_s for r in recs], 50):.2f} ({1e3 * _pct([r.extract_s for r in recs], 95):.2f})",
        )
    console.print(table)
    for family in families:
        for p in (p for r in records[family] for p in r.planes):
            if p.quality == "good" and p.error > 0.02 and p.error > 3 * p.oracle:
                console.print(
                    f"failure claiming good ({mount} mount): {family} seed {p.seed} pose {p.pose} element {p.element} "
                    f"({p.kind}): "
                    f"{100 * p.error:.1f} cm (oracle {100 * p.oracle:.1f} cm), {math.degrees(p.angle):.1f}°"
                )
    for family in families:
        for line in (line for r in records[family] for line in r.good_off_details):
            console.print(f"good plane off every true mirror ({mount} mount): {line}")
        for line in (line for r in records[family] for line in r.missed):
            console.print(f"plane seen but not found ({mount} mount): {line}")
        for line in (line for r in records[family] for line in r.false_features):
            console.print(f"false feature ({mount} mount): {line}")
    for family, p in neither:
        console.print(
            f"wall good but over 3× its oracle and the range noise ({mount} mount): {family} seed {p.seed} "
            f"pose {p.pose} element {p.element}: "
            f"{100 * p.error:.2f} cm (oracle {100 * p.oracle:.2f} cm), own echoes {100 * p.own_share:.0f} %"
        )
    return bad_total
