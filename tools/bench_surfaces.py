"""``lelsonar bench surfaces``: every surface of a sweep against the world simulator's truth.

For each world family (:mod:`lelsonar.sim.worlds`), seed and pose, one sweep is
simulated with waveforms, the echo amplitudes are read off them
(:func:`lelsonar.signal.energy.echo_amplitude`), and
:func:`lelsonar.reconstruct.estimate.surfaces.extract_surfaces` runs on the
measured γ and ranges.  The truth is the simulator's: which element set each
reading (``echo_index``) and the true pose.

Per class (plane, corner, edge):

* **found / seen** (recall): truth elements with at least ``--min-echoes``
  readings that some extracted item of any class claims (its majority element);
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
import time
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from lelsonar.reconstruct.estimate.surfaces import Feature, Surface, SurfaceOptions, SurfaceSet, extract_surfaces
from lelsonar.signal.energy import echo_amplitude
from lelsonar.sim.scan import EchoSource
from lelsonar.sim.scenes import FAMILIES as L_FAMILIES
from lelsonar.sim.scenes import simulate_family_scene
from lelsonar.sim.world import MOUNTS
from lelsonar.sim.world_geometry import ElementKind, WorldModel, build_model
from lelsonar.sim.world_render import WorldScan, pose_frame, simulate_world_scan
from lelsonar.sim.worlds import WORLD_FAMILIES, draw_world
from lelsonar.tools.surface_oracle import bearing_tilt, oracle_error, trace_error, true_plane

if TYPE_CHECKING:
    from rich.console import Console

#: The class each element kind should be extracted as.
TRUE_CLASS = {
    ElementKind.MIRROR: "plane",
    ElementKind.DIHEDRAL: "corner",
    ElementKind.TRIHEDRAL: "corner",
    ElementKind.EDGE: "edge",
}
#: What the bench calls a feature whose kind its evidence does not settle.
UNKNOWN = "unknown"
#: Extractions timed per sweep (the median is its time; the first call of a process also loads the kernels).
TIMING_REPEATS = 3


@dataclass(frozen=True)
class PlaneRecord:
    """One extracted plane matched to its true surface."""

    family: str
    seed: int
    pose: int
    element: int
    quality: str
    error: float  # m
    oracle: float  # m
    angle: float  # rad
    n_true_echoes: int
    wall: bool = False  # a wall of the room (not a box's face)
    kind: str = "wall"  # the true surface's kind: wall, box, floor or ceiling
    own_share: float = float("nan")  # the surface's readings that are this element's own echoes
    flagged: bool = False  # not good, with its reasons
    range_noise: float = 0.0  # m, σ of one range (the receiver's timing noise): errors under it are noise
    mount: str = "fan"
    bearing_z: float = float("nan")  # (fitted − true bearing) / the claimed bearing σ
    offset_z: float = float("nan")  # (fitted − true offset) / the claimed offset σ
    bearing_error: float = float("nan")  # rad, fitted − true bearing
    range_ls: float = float("nan")  # m, the ranges' least squares alone on the true echoes (for reading)

    @property
    def within_oracle(self) -> bool:
        """Within 3× its oracle, or within one range's σ (the clutter criterion: estimated from its own echoes)."""
        return self.error <= max(3 * self.oracle, self.range_noise)


@dataclass(frozen=True)
class ScanRecord:
    """What one sweep's extraction scored."""

    planes: list[PlaneRecord]
    seen: dict[str, int]  # class -> truth elements seen
    found: dict[str, int]  # class -> of those, claimed by an item of any class
    right: dict[str, int]  # class -> of those, claimed only with the right class
    false: dict[str, int]  # class -> extracted items of that class with another majority
    extracted: dict[str, int]
    unexplained_share: float
    false_good: int  # extracted planes claiming good whose echoes are no surface's mirror
    extract_s: float = float("nan")  # the extraction's CPU time on this sweep, s (median of TIMING_REPEATS)
    seen_kind: dict[str, int] | None = None  # surface kind -> mirrors seen
    found_kind: dict[str, int] | None = None  # surface kind -> of those, claimed as a plane
    good_planes: int = 0  # extracted planes claiming good
    good_off_every: int = 0  # of those, off every true mirror of the world by > 2 cm (false good)
    good_off_details: tuple[str, ...] = ()  # one line per such plane
    missed: tuple[str, ...] = ()  # one line per mirror seen but claimed by no plane
    unknown: dict[str, int] | None = None  # class -> of those found, claimed only as right or kind not settled
    features: tuple[tuple[str, float, float], ...] = ()  # (kind, m off its true line, its σ there) per right feature


def sigma_scores(surf: Surface, n_true: np.ndarray, h_true: float) -> tuple[float, float, float]:
    """How far the surface's bearing and offset are from the truth in its own claimed σ, and the bearing error.

    Returns
    -------
    (bearing error / σ_bearing, offset error / σ_offset, bearing error rad); NaN where the σ is not positive.
    """
    b_true, _ = bearing_tilt(n_true)
    db = (surf.bearing - b_true + math.pi) % (2 * math.pi) - math.pi
    dh = surf.offset - h_true
    sb = math.sqrt(max(float(surf.covariance[0, 0]), 0.0))
    sh = math.sqrt(max(float(surf.covariance[2, 2]), 0.0))
    return (db / sb if sb > 0 else float("nan")), (dh / sh if sh > 0 else float("nan")), db


def nearest_mirror(scan: WorldScan, surf: Surface) -> tuple[int, float]:
    """The world's true mirror nearest the fitted plane (smallest trace error), whatever its echoes: (element, m)."""
    best = (-1, float("inf"))
    for k, el in enumerate(scan.model.elements):
        if el.kind != ElementKind.MIRROR:
            continue
        n_true, h_true = true_plane(scan, k)
        err = trace_error(surf.normal, surf.offset, n_true, h_true)
        if err < best[1]:
            best = (k, err)
    return best


def feature_offset(scan: WorldScan, f: Feature, element: int) -> tuple[float, float]:
    """How far a feature's point lies from its element's true line (a vertex: from the feature's line through
    it), m, and the feature's σ in that direction (0 distance: σ 0)."""
    rot, tr = pose_frame(scan.rig, scan.pose)
    el = scan.model.elements[element]
    p = rot @ f.point + tr
    if el.kind == ElementKind.TRIHEDRAL:
        u = rot @ f.direction
        off = (el.p0 - p) - ((el.p0 - p) @ u) * u
    else:
        d = el.p1 - el.p0
        d = d / max(float(np.linalg.norm(d)), 1e-12)
        off = (p - el.p0) - ((p - el.p0) @ d) * d
    dist = float(np.linalg.norm(off))
    if not dist > 0:
        return 0.0, 0.0
    r = rot.T @ (off / dist)
    return dist, math.sqrt(max(float(r @ f.covariance @ r), 0.0))


def majority(scan: WorldScan, steps: np.ndarray, surf: Surface | Feature | None = None) -> tuple[int, int]:
    """The element most of an item's readings are (its own readings if it has them, else its steps')."""
    if surf is not None and surf.rows is not None and surf.capsules is not None:
        idx = scan.echo_index[surf.rows, surf.capsules]
        ok = np.isfinite(scan.distance[surf.rows, surf.capsules]) & (idx >= 0)
    else:
        idx = scan.echo_index[steps].ravel()
        ok = np.isfinite(scan.distance[steps].ravel()) & (idx >= 0)
    if not ok.any():
        return -1, 0
    vals, counts = np.unique(idx[ok], return_counts=True)
    k = int(np.argmax(counts))
    return int(vals[k]), int(counts[k])


def _element_kind(model: WorldModel, k: int, scan: WorldScan, steps: np.ndarray) -> str | None:
    """The class of element k, None for a diffuse echo or no element."""
    if k < 0 or k >= len(model.elements):
        return None
    # A diffuse slot carries its surface's index as element index: tell by the source of those readings.
    src = scan.echo_source[steps].ravel()
    idx = scan.echo_index[steps].ravel()
    if np.count_nonzero((idx == k) & (src == EchoSource.DIFFUSE)) > np.count_nonzero(
        (idx == k) & (src != EchoSource.DIFFUSE)
    ):
        return None
    return TRUE_CLASS[model.elements[k].kind]


def _own_share(scan: WorldScan, steps: np.ndarray, element: int, surf: Surface | None = None) -> float:
    """Of the surface's readings (else those in its steps), the share that are the element's own echoes."""
    at: tuple[np.ndarray, ...] = (steps,)
    if surf is not None and surf.rows is not None and surf.capsules is not None:
        at = (surf.rows, surf.capsules)
    ok = np.isfinite(scan.distance[at])
    own = ok & (scan.echo_index[at] == element) & (scan.echo_source[at] != EchoSource.DIFFUSE)
    n_ok = int(np.count_nonzero(ok))
    return int(np.count_nonzero(own)) / max(n_ok, 1)


def score_scan(
    family: str,
    scan: WorldScan,
    result: SurfaceSet,
    *,
    seed: int = 0,
    min_echoes: int = 20,
    amplitude: np.ndarray | None = None,
) -> ScanRecord:
    """Match the extracted items to the truth of one sweep; ``amplitude``: the echoes' (the oracle's beam bearing)."""
    model = scan.model
    valid = np.isfinite(scan.distance) & (scan.echo_source != EchoSource.DIFFUSE)
    counts = np.bincount(scan.echo_index[valid & (scan.echo_index >= 0)].ravel(), minlength=len(model.elements))
    seen_el = {k for k in range(len(model.elements)) if counts[k] >= min_echoes}
    classes = ("plane", "corner", "edge")
    seen = {c: 0 for c in classes}
    for k in seen_el:
        seen[TRUE_CLASS[model.elements[k].kind]] += 1
    claimed: dict[int, set[str]] = {}
    false = {c: 0 for c in classes}
    extracted = {"plane": len(result.surfaces), "corner": len(result.corners), "edge": len(result.edges)}
    planes: list[PlaneRecord] = []
    false_good = 0
    good_planes = 0
    off_every: list[str] = []
    placed: list[tuple[str, float, float]] = []
    items: list[tuple[str, np.ndarray, Surface | None, Feature | None]] = [
        ("plane", s.steps, s, None) for s in result.surfaces
    ]
    items += [(f.kind if f.settled else UNKNOWN, f.steps, None, f) for f in (*result.corners, *result.edges)]
    for cls, steps, surf, feature in items:
        k, _ = majority(scan, steps, surf if surf is not None else feature)
        truth = _element_kind(model, k, scan, steps)
        if cls != UNKNOWN and (truth is None or truth != cls):
            false[cls] += 1
            false_good += int(surf is not None and surf.quality == "good")
        if truth is not None:
            claimed.setdefault(k, set()).add(cls)
        if feature is not None and truth == feature.kind:
            placed.append((feature.kind, *feature_offset(scan, feature, k)))
        if surf is not None and surf.quality == "good":
            # Every good plane against the nearest true mirror of the world, not only its echoes' majority.
            good_planes += 1
            near, near_err = nearest_mirror(scan, surf)
            if near_err > 0.02:
                off_every.append(
                    f"{family} seed {seed} pose {scan.pose_index} {surf.label}: {100 * near_err:.1f} cm from the "
                    f"nearest true mirror (element {near}), majority element {k}"
                )
        if surf is not None and truth == "plane":
            n_true, h_true = true_plane(scan, k)
            err = trace_error(surf.normal, surf.offset, n_true, h_true)
            ang = math.acos(min(1.0, abs(float(surf.normal @ n_true))))
            true_surface = model.surfaces[model.elements[k].surfaces[0]]
            label = true_surface.label
            bz, hz, db = sigma_scores(surf, n_true, h_true)
            oracle = oracle_error(scan, k, amplitude)
            planes.append(
                PlaneRecord(
                    family,
                    seed,
                    scan.pose_index,
                    k,
                    surf.quality,
                    err,
                    oracle.error,
                    ang,
                    int(counts[k]),
                    wall=label.startswith("wall"),
                    own_share=_own_share(scan, steps, k, surf),
                    flagged=surf.quality != "good" and bool(surf.reasons),
                    range_noise=scan.rig.receiver.tof_jitter,
                    kind=true_surface.kind,
                    mount=scan.rig.mount,
                    bearing_z=bz,
                    offset_z=hz,
                    bearing_error=db,
                    range_ls=oracle.range_ls,
                )
            )
    found = {c: 0 for c in classes}
    right = {c: 0 for c in classes}
    unknown = {c: 0 for c in classes}
    for k in seen_el:
        c = TRUE_CLASS[model.elements[k].kind]
        if k in claimed:
            found[c] += 1
            right[c] += int(claimed[k] == {c})
            unknown[c] += int(UNKNOWN in claimed[k] and claimed[k] <= {c, UNKNOWN})
    seen_kind: dict[str, int] = {}
    found_kind: dict[str, int] = {}
    for k in seen_el:
        if model.elements[k].kind == ElementKind.MIRROR:
            kind = model.surfaces[model.elements[k].surfaces[0]].kind
            seen_kind[kind] = seen_kind.get(kind, 0) + 1
            found_kind[kind] = found_kind.get(kind, 0) + int("plane" in claimed.get(k, set()))
    missed = tuple(
        f"{family} seed {seed} pose {scan.pose_index} element {k} "
        f"({model.surfaces[model.elements[k].surfaces[0]].kind}, {int(counts[k])} echoes): "
        + (f"claimed as {', '.join(sorted(claimed[k]))}" if k in claimed else "in no item's majority")
        for k in sorted(seen_el)
        if model.elements[k].kind == ElementKind.MIRROR and "plane" not in claimed.get(k, set())
    )
    share = result.n_unexplained / max(result.n_echoes, 1)
    return ScanRecord(
        planes,
        seen,
        found,
        right,
        false,
        extracted,
        share,
        false_good,
        seen_kind=seen_kind,
        found_kind=found_kind,
        good_planes=good_planes,
        good_off_every=len(off_every),
        good_off_details=tuple(off_every),
        missed=missed,
        unknown=unknown,
        features=tuple(placed),
    )


def run_scan(family: str, seed: int, pose: int, model: WorldModel, options: SurfaceOptions | None = None) -> ScanRecord:
    """Simulate, extract and score one sweep."""
    scan = simulate_world_scan(model, pose, seed=seed * 1000 + pose)
    amp = echo_amplitude(scan.waveforms, scan.sample_rate, scan.t0, scan.tof)
    times = []
    for _ in range(TIMING_REPEATS):
        t0 = time.process_time()  # CPU time: the host's other work does not count
        result = extract_surfaces(scan.gamma_measured, scan.distance, scan.geometry, amplitude=amp, options=options)
        times.append(time.process_time() - t0)
    return replace(score_scan(family, scan, result, seed=seed, amplitude=amp), extract_s=float(np.median(times)))


def l_scan_errors(family: str, seed: int) -> dict[bool, list[tuple[float, str]]]:
    """The L scan's two walls as surfaces, with the joint corner model off (False) and on (True).

    Each true wall is matched to the surface whose steps' echoes are mostly that wall's; its trace error (m)
    and verdict, or nothing when no surface holds it.
    """
    fs = simulate_family_scene(family, seed)
    sc = fs.scan
    amp = echo_amplitude(sc.waveforms, sc.sample_rate, sc.t0, sc.tof)
    out: dict[bool, list[tuple[float, str]]] = {}
    for joint in (False, True):
        res = extract_surfaces(
            sc.gamma_measured, sc.distance, sc.geometry, amplitude=amp, options=SurfaceOptions(joint_corners=joint)
        )
        found = []
        for plane, src in zip(sc.truth.planes[:2], (EchoSource.PLANE_A, EchoSource.PLANE_B), strict=True):
            mine = [s for s in res.surfaces if np.mean(sc.truth.echo_source[s.steps] == src) > 0.5]
            errs = [(trace_error(s.normal, s.offset, plane.normal, plane.offset), s.quality) for s in mine]
            if errs:
                found.append(min(errs))
        out[joint] = found
    return out


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

    families = WORLD_FAMILIES if args.worlds == "all" else tuple(f.strip() for f in args.worlds.split(","))
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
        "settled; walls: the room's walls (not boxes' faces), good "
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
        "corners found/seen (right, unknown)",
        "edges found/seen (right, unknown)",
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
            f"{tot('found', 'corner')}/{tot('seen', 'corner')} ({tot('right', 'corner')}, {tot('unknown', 'corner')})",
            f"{tot('found', 'edge')}/{tot('seen', 'edge')} ({tot('right', 'edge')}, {tot('unknown', 'edge')})",
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
    for family, p in neither:
        console.print(
            f"wall good but over 3× its oracle and the range noise ({mount} mount): {family} seed {p.seed} "
            f"pose {p.pose} element {p.element}: "
            f"{100 * p.error:.2f} cm (oracle {100 * p.oracle:.2f} cm), own echoes {100 * p.own_share:.0f} %"
        )
    return bad_total
