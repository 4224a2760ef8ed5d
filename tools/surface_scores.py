"""The scores of one sweep's extracted surfaces against the world simulator's truth.

Each extracted item is matched to the truth element most of its readings came from (``echo_index``):
per class, the truth elements seen, found and classified right and the false items (:func:`score_scan`);
per plane, its trace error beside the oracle's (:mod:`lelsonar.tools.surface_oracle`), its verdict and its
errors in its own claimed σ.  :func:`run_scan` simulates, extracts (timed) and scores one sweep of a world;
:func:`l_scan_errors` scores an L scan's two walls.  ``lelsonar bench surfaces``
(:mod:`lelsonar.tools.bench_surfaces`) tables them.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np

from lelsonar.reconstruct.estimate.surfaces import Feature, Surface, SurfaceOptions, SurfaceSet, extract_surfaces
from lelsonar.signal.energy import echo_amplitude
from lelsonar.sim.scan import EchoSource
from lelsonar.sim.scenes import simulate_family_scene
from lelsonar.sim.world_geometry import ElementKind, WorldModel, build_model
from lelsonar.sim.world_render import WorldScan, pose_frame, simulate_world_scan
from lelsonar.sim.worlds import draw_world
from lelsonar.tools.surface_oracle import bearing_tilt, oracle_error, trace_error, true_plane

#: The class each element kind should be extracted as.
TRUE_CLASS = {
    ElementKind.MIRROR: "plane",
    ElementKind.DIHEDRAL: "corner",
    ElementKind.TRIHEDRAL: "corner",
    ElementKind.EDGE: "edge",
}
#: What the bench calls a feature whose kind its evidence does not settle.
UNKNOWN = "unknown"
#: A corner or an edge is seen (its kind can be told) when at least this many capsules each hear it on
#: ``MIN_STEPS_PER_CAPSULE`` steps: one receiver's ranges say nothing of where it lies across the stack, so
#: nothing of how far off its beam's axis it is, nor how strong its echo is (Kleeman & Kuc need two).
MIN_CAPSULES = 2
MIN_STEPS_PER_CAPSULE = 3
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
    one_capsule: dict[str, int] | None = None  # class -> corners/edges with enough echoes but heard by one capsule
    features: tuple[tuple[str, float, float], ...] = ()  # (kind, m off its true line, its σ there) per right feature
    false_features: tuple[str, ...] = ()  # one line per corner or edge whose majority is another class: why it said so


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
    # Capsules that hear each element on enough steps.
    own = valid & (scan.echo_index >= 0)
    per_capsule = np.zeros((len(model.elements), scan.distance.shape[1]), dtype=np.int64)
    np.add.at(per_capsule, (scan.echo_index[own], np.nonzero(own)[1]), 1)
    capsules = np.count_nonzero(per_capsule >= MIN_STEPS_PER_CAPSULE, axis=1)
    enough = {k for k in range(len(model.elements)) if counts[k] >= min_echoes}
    lone = {k for k in enough if model.elements[k].kind != ElementKind.MIRROR and capsules[k] < MIN_CAPSULES}
    seen_el = enough - lone
    one_capsule = {c: 0 for c in ("plane", "corner", "edge")}
    for k in lone:
        one_capsule[TRUE_CLASS[model.elements[k].kind]] += 1
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
    false_lines: list[str] = []
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
            if feature is not None:
                why = feature.reasons[0] if feature.reasons else ""
                false_lines.append(
                    f"{family} seed {seed} pose {scan.pose_index} {feature.label}: {cls} on element {k} "
                    f"({truth or 'no element'}), {feature.n_echoes} echoes: {why}"
                )
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
        one_capsule=one_capsule,
        features=tuple(placed),
        false_features=tuple(false_lines),
    )


def simulated_sweep(model: WorldModel, seed: int, pose: int) -> tuple[WorldScan, np.ndarray]:
    """World ``seed``'s sweep from its ``pose``-th pose (its noise seeded by both) and its echo amplitudes."""
    scan = simulate_world_scan(model, pose, seed=seed * 1000 + pose)
    return scan, echo_amplitude(scan.waveforms, scan.sample_rate, scan.t0, scan.tof)


class WorldSweep(NamedTuple):
    """One sweep of a family's world, its echo amplitudes and the surfaces extracted from it."""

    model: WorldModel
    scan: WorldScan
    amplitude: np.ndarray
    result: SurfaceSet


def world_sweep(family: str, seed: int, pose: int, mount: str = "fan") -> WorldSweep:
    """World ``seed`` of ``family`` on ``mount``, swept from its ``pose``-th pose (:func:`simulated_sweep`), and its
    surfaces as the reconstruction extracts them."""
    model = build_model(draw_world(family, seed, mount=mount))
    scan, amp = simulated_sweep(model, seed, pose)
    return WorldSweep(
        model, scan, amp, extract_surfaces(scan.gamma_measured, scan.distance, scan.geometry, amplitude=amp)
    )


def run_scan(family: str, seed: int, pose: int, model: WorldModel, options: SurfaceOptions | None = None) -> ScanRecord:
    """Simulate, extract and score one sweep."""
    scan, amp = simulated_sweep(model, seed, pose)
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
