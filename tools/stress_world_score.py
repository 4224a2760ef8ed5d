"""One stress world toured, reconstructed as of record, mapped and scored: the work item of ``bench stress-worlds``.

Each pose's sweep is simulated as ``acquire --device sim --world`` seeds it and reconstructed by
:func:`~lelsonar.reconstruct.estimate.record.reconstruct_scan` (the final of record, as ``reconstruct
--source`` computes it); its message goes to the map's adapter and :class:`~lelsonar.map.fusion.WallMapper`
fuses the tour, beside the oracle map (:mod:`lelsonar.tools.map_worlds`).  What counts against the
estimate:

* **surface good-but-failed**: a surface claiming good whose trace error is > 2 cm and > 3× its oracle's
  (what its own true echoes allow, :func:`lelsonar.tools.surface_oracle.oracle_error`);
* **false good**: a good surface whose readings are no surface's mirror echoes;
* **bearing > 3σ**: a good surface whose bearing is off by more than three times its own σ and more than
  :data:`BEARING_FLOOR` (the σ's shape, a wall placed well in range but not in bearing);
* **L plane good-but-wrong**: one of the L's two planes of record claiming good while no seen wall lies
  within 2 cm and 3× its oracle of it;
* **feature > 3σ**: a corner or edge whose point is off its true line by more than three times its σ in
  that direction and more than 2 cm;
* **map good-but-off** / **map good on no face**: as ``bench map`` scores them;
* **crash**: anything raised.
"""

from __future__ import annotations

import math
import traceback
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lelsonar.acquire.world_scans import WorldRun
from lelsonar.map.from_reconstruction import scan_from_reconstruction
from lelsonar.map.fusion import FusionConfig
from lelsonar.reconstruct.estimate import wire
from lelsonar.reconstruct.estimate.pipeline import DEFAULT_METHOD
from lelsonar.reconstruct.estimate.record import RecordOptions, reconstruct_scan
from lelsonar.reconstruct.estimate.results import PlaneFit
from lelsonar.reconstruct.estimate.waveform_input import scan_input_of_waveforms
from lelsonar.signal.energy import echo_amplitude
from lelsonar.sim.acoustics import Receiver
from lelsonar.sim.odometry import simulate_odometry
from lelsonar.sim.scan import EchoSource
from lelsonar.sim.world import World
from lelsonar.sim.world_geometry import ElementKind, build_model
from lelsonar.sim.world_render import WorldScan, world_rig
from lelsonar.tools.bench_map import false_good
from lelsonar.tools.map_worlds import (
    ENERGY_MODEL,
    TourResult,
    fuse,
    oracle_message,
    scan_start,
    score_wall,
    sweep,
    vertical_faces,
)
from lelsonar.tools.surface_oracle import oracle_error, trace_error, true_plane
from lelsonar.tools.surface_scores import feature_offset, score_scan

#: A claim is wrong only past this (m), and past 3× its oracle.
ERROR_FLOOR = 0.02
#: A bearing off by more than 3σ counts only past this (rad): below it no planner cares.
BEARING_FLOOR = math.radians(0.5)
#: A mirror with at least this many true echoes is seen (the oracle can fit it).
MIN_ECHOES = 20

COUNTS = (
    "sweeps",
    "good surfaces",
    "surface good-but-failed",
    "false good",
    "bearing > 3σ",
    "L good-but-wrong",
    "features",
    "feature > 3σ",
    "map good walls",
    "map good-but-off",
    "map good on no face",
    "replay ≠ in process",
    "crash",
)


@dataclass
class WorldScore:
    """What one world scored: counts by :data:`COUNTS` and one line per failure."""

    cls: str
    seed: int
    mount: str
    counts: dict[str, int] = field(default_factory=lambda: dict.fromkeys(COUNTS, 0))
    failures: list[str] = field(default_factory=list)

    def fail(self, key: str, line: str) -> None:
        self.counts[key] += 1
        self.failures.append(f"{self.cls} seed {self.seed} {self.mount}: {key}: {line}")


def world_run(world: World, seed: int, amplitude_noise: float = 0.0) -> WorldRun:
    """The acquirer's set-up of a world: model, rig and the sim's odometry of the tour; ``amplitude_noise``: the
    receiver's relative echo amplitude noise (the simulator's default receiver otherwise)."""
    receiver = Receiver(amplitude_noise=amplitude_noise) if amplitude_noise else None
    return WorldRun(
        path=Path(world.name),
        world=world,
        model=build_model(world),
        rig=world_rig(world, receiver=receiver),
        odometry=simulate_odometry(world.poses, world.odometry),
        seed=int(seed),
    )


def estimate_of(scan: WorldScan):
    """The sweep's final estimate of record (the L planes and every surface, corner and edge)."""
    return reconstruct_scan(scan_input_of_waveforms(scan, ENERGY_MODEL), RecordOptions())


def _seen_mirrors(scan: WorldScan) -> list[int]:
    model = scan.model
    ok = np.isfinite(scan.distance) & (scan.echo_source != EchoSource.DIFFUSE) & (scan.echo_index >= 0)
    counts = np.bincount(scan.echo_index[ok].ravel(), minlength=len(model.elements))
    return [k for k, el in enumerate(model.elements) if el.kind == ElementKind.MIRROR and counts[k] >= MIN_ECHOES]


def _wrap_half(a: float) -> float:
    """An angle difference modulo π (a normal's sign is free), in [−π/2, π/2]."""
    return (a + math.pi / 2) % math.pi - math.pi / 2


def _majority(
    scan: WorldScan, steps: np.ndarray, rows: np.ndarray | None = None, capsules: np.ndarray | None = None
) -> int:
    """The element most of an item's readings are (its own readings where it has them, else its steps')."""
    at: tuple[np.ndarray, ...] = (steps,) if rows is None or capsules is None else (rows, capsules)
    idx = scan.echo_index[at].ravel()
    ok = np.isfinite(scan.distance[at].ravel()) & (idx >= 0) & (scan.echo_source[at].ravel() != EchoSource.DIFFUSE)
    if not ok.any():
        return -1
    vals, counts = np.unique(idx[ok], return_counts=True)
    return int(vals[int(np.argmax(counts))])


def _score_sweep(score: WorldScore, scan: WorldScan, estimate, pose: int) -> None:
    surfaces = estimate.surfaces
    amplitude = echo_amplitude(scan.waveforms, scan.sample_rate, scan.t0, scan.tof)
    rec = score_scan(score.cls, scan, surfaces, seed=score.seed, min_echoes=MIN_ECHOES, amplitude=amplitude)
    where = f"pose {pose}"
    for p in rec.planes:
        if p.quality == "good" and p.error > ERROR_FLOOR and p.error > 3 * p.oracle:
            score.fail(
                "surface good-but-failed",
                f"{where} element {p.element} ({p.kind}): {100 * p.error:.1f} cm (oracle {100 * p.oracle:.1f} cm), "
                f"{math.degrees(p.angle):.1f}°",
            )
    score.counts["good surfaces"] += sum(s.quality == "good" for s in surfaces.surfaces)
    for _ in range(rec.false_good):
        score.fail("false good", f"{where}: a good surface on no mirror's echoes")
    # The σ's shape: bearing against the truth in the fan.
    for s in surfaces.surfaces:
        if s.quality != "good":
            continue
        k = _majority(scan, s.steps)
        if k < 0 or scan.model.elements[k].kind != ElementKind.MIRROR:
            continue
        n_true, _ = true_plane(scan, k)
        err = abs(_wrap_half(s.bearing - math.atan2(n_true[2], n_true[1])))
        sigma = math.sqrt(max(float(s.covariance[0, 0]), 0.0))
        if err > 3 * sigma and err > BEARING_FLOOR:
            score.fail(
                "bearing > 3σ",
                f"{where} {s.label} element {k}: bearing off {math.degrees(err):.2f}° with σ "
                f"{math.degrees(sigma):.2f}° ({s.bearing_source})",
            )
    # The L's planes of record: good only when some seen wall is there.
    seen = _seen_mirrors(scan)
    for plane in estimate.planes_of(estimate.method):
        if not isinstance(plane, PlaneFit) or plane.quality != "good":
            continue
        best = math.inf
        for k in seen:
            n_true, h_true = true_plane(scan, k)
            err = trace_error(plane.normal, plane.offset, n_true, h_true)
            if err <= max(ERROR_FLOOR, 3 * oracle_error(scan, k, amplitude).error):
                best = 0.0
                break
            best = min(best, err)
        if best > 0:
            score.fail(
                "L good-but-wrong", f"{where} L plane {plane.label}: {100 * best:.1f} cm from the nearest seen wall"
            )
    _score_features(score, scan, surfaces, where)


def _score_features(score: WorldScore, scan: WorldScan, surfaces, where: str) -> None:
    classes = {"corner": (ElementKind.DIHEDRAL, ElementKind.TRIHEDRAL), "edge": (ElementKind.EDGE,)}
    for f in (*surfaces.corners, *surfaces.edges):
        k = _majority(scan, f.steps, f.rows, f.capsules)
        if k < 0 or scan.model.elements[k].kind not in classes[f.kind]:
            continue
        score.counts["features"] += 1
        dist, sigma = feature_offset(scan, f, k)
        if dist > ERROR_FLOOR and dist > 3 * sigma:
            score.fail(
                "feature > 3σ",
                f"{where} {f.kind} {f.label} element {k}: {100 * dist:.1f} cm off, σ {100 * sigma:.1f} cm",
            )


def score_world(
    cls: str, seed: int, mount: str, world: World, max_poses: int = 0, *, amplitude_noise: float = 0.0
) -> WorldScore:
    """Tour ``world``, reconstruct each sweep as of record, map the tour, and score everything
    (``amplitude_noise``: as :func:`world_run`)."""
    score = WorldScore(cls, seed, mount)
    try:
        run = world_run(world, seed, amplitude_noise)
    except Exception as exc:  # a valid world file must never fail: any exception is a bug to count
        score.fail("crash", f"set-up: {_short(exc)}")
        return score
    observed, oracle = [], []
    n = len(world.poses) if max_poses <= 0 else min(max_poses, len(world.poses))
    for index in range(n):
        try:
            scan = sweep(run, index)
            estimate = estimate_of(scan)
            score.counts["sweeps"] += 1
            _score_sweep(score, scan, estimate, index)
            msg = wire.estimate_message(estimate, "sim", index + 1, status="final")
            start = scan_start(run, index)
            observed.append(scan_from_reconstruction(msg, start, DEFAULT_METHOD))
            oracle.append(scan_from_reconstruction(oracle_message(scan, index + 1), start, DEFAULT_METHOD))
        except Exception as exc:
            score.fail("crash", f"pose {index}: {_short(exc)}")
    try:
        fused, _ = fuse(observed, FusionConfig())
        fused_oracle, _ = fuse(oracle, FusionConfig())
        faces = vertical_faces(run.model)
        tour = TourResult(cls, seed)
        tour.walls = [score_wall(w, faces) for w in fused.walls]
        tour.oracle_walls = [score_wall(w, faces) for w in fused_oracle.walls]
        score.counts["map good walls"] += sum(w.quality == "good" for w in tour.walls)
        for w in false_good(tour):
            score.fail(
                "map good-but-off",
                f"face {w.face}: {100 * w.trace:.1f} cm, {math.degrees(w.angle):.1f}°, {w.scans} scans",
            )
        for w, fw in zip(tour.walls, fused.walls, strict=True):
            if w.face < 0 and w.quality == "good":
                score.fail(
                    "map good on no face",
                    f"wall {fw.id} θ {math.degrees(fw.line[0]):.1f}° ρ {fw.line[1]:.2f} m, scans {list(fw.scans)}",
                )
    except Exception as exc:
        score.fail("crash", f"map: {_short(exc)}")
    return score


def _short(exc: BaseException) -> str:
    frame = traceback.extract_tb(exc.__traceback__)[-1] if exc.__traceback__ else None
    at = f" at {Path(frame.filename).name}:{frame.lineno}" if frame else ""
    return f"{type(exc).__name__}: {exc}{at}"
