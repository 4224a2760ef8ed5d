"""``lelsonar bench stress-worlds``: the extractor and the map on worlds outside the families.

Each class of :mod:`lelsonar.tools.stress_worlds` (oblique, acute and obtuse corners, thin walls,
boxes turned, tiny, large, touching walls and in clutter, narrow and wide rooms, heights, acoustics,
reflectivities, odometry, the rig, all mixed) is drawn ``--seeds`` times for each mount.  In process,
every sweep is reconstructed as of record and the tour mapped (:mod:`lelsonar.tools.stress_world_score`
says what counts as a failure).  Through the CLI, ``--cli N`` of those worlds are written as world
files and run as a user runs them: ``acquire --device sim --world FILE``, then ``reconstruct --source
X.mcap --json`` on each recording and ``map --source … --json`` on the tour; a traceback, an exit code
other than the documented ones, or a line that is no JSON is a crash, and the map's good walls are
scored against the world's faces as in process.

The table: per class, the counts of each failure; the failure lines follow.  Exit 1 when anything
claimed good while wrong, or crashed.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from lelsonar.sim.world import MOUNTS
from lelsonar.sim.world_geometry import build_model
from lelsonar.tools.map_worlds import MATCH_ANGLE, MATCH_DISTANCE, sweep, vertical_faces
from lelsonar.tools.stress_world_score import COUNTS, WorldScore, estimate_of, score_world, world_run
from lelsonar.tools.stress_worlds import STRESS_CLASSES, draw_stress_world, stress_world_data, world_toml

#: What counts against the estimate (the rest are totals).
FAILURES = tuple(c for c in COUNTS if c not in ("sweeps", "good surfaces", "features", "map good walls"))
#: Exit codes the CLI documents: 0 ok, 1 no result / a plane missing, 2 a typed error.
DOCUMENTED_EXIT = (0, 1, 2)
#: Seconds one CLI command may take before it counts as hung.
CLI_TIMEOUT = 600.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--classes", default="all", help="comma-separated stress classes, or all")
    parser.add_argument("--seeds", type=int, default=2, help="worlds per class and mount (seeds F..F+N-1)")
    parser.add_argument("--first-seed", type=int, default=0, help="F: the first seed")
    parser.add_argument("--mount", choices=(*MOUNTS, "both"), default="both", help="the scanner's mount")
    parser.add_argument("--max-poses", type=int, default=3, help="sweeps per world (its first poses; 0: all)")
    parser.add_argument(
        "--cli", type=int, default=2, help="worlds run through acquire → reconstruct → map as subprocesses"
    )
    parser.add_argument("--show", type=int, default=40, help="failure lines to print (default: %(default)s)")
    parser.add_argument(
        "--amplitude-noise",
        type=float,
        default=0.0,
        help="the receiver's relative echo amplitude noise in the in-process tours (world files do not carry it)",
    )


def _cli(args: list[str], cwd: Path) -> tuple[int, str, str]:
    # The installed entry point, as a user runs it.
    cmd = [str(Path(sys.executable).with_name("lelsonar")), *args]
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    try:
        done = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, timeout=CLI_TIMEOUT, env=env)
    except subprocess.TimeoutExpired:
        return -1, "", f"timed out after {CLI_TIMEOUT:g} s"
    return done.returncode, done.stdout, done.stderr


def _cli_problem(what: str, rc: int, out: str, err: str, *, json_out: bool) -> str | None:
    if "Traceback" in err or "Traceback" in out:
        return f"{what}: a traceback (exit {rc}): {err.strip().splitlines()[-1] if err.strip() else ''}"
    if rc not in DOCUMENTED_EXIT:
        return f"{what}: exit {rc}: {err.strip()[:200]}"
    if rc == 2 and len(err.strip().splitlines()) != 1:
        return f"{what}: an error of {len(err.strip().splitlines())} lines"
    if json_out and rc == 0:
        for line in out.strip().splitlines():
            try:
                json.loads(line)
            except json.JSONDecodeError:
                return f"{what}: a line that is no JSON: {line[:120]!r}"
    return None


def cli_world(cls: str, seed: int, mount: str, workdir: Path) -> WorldScore:
    """One world through the CLI: acquire, reconstruct each recording, map the tour; scored."""
    score = WorldScore(cls, seed, f"{mount} (CLI)")
    data = stress_world_data(cls, seed, mount)
    world_file = workdir / f"{cls}-{seed}-{mount}.toml"
    world_file.write_text(world_toml(data))
    out_dir = workdir / f"{cls}-{seed}-{mount}"
    rc, out, err = _cli(
        [
            "acquire",
            "--device",
            "sim",
            "--world",
            str(world_file),
            "--out",
            str(out_dir),
            "--no-zenoh",
            "--seed",
            str(seed),
            "--serve-log-for",
            "0",
        ],
        workdir,
    )
    if (problem := _cli_problem("acquire", rc, out, err, json_out=False)) or rc != 0:
        score.fail("crash", problem or f"acquire: exit {rc}: {err.strip()[:200]}")
        return score
    files = sorted(out_dir.glob("*.mcap"), key=lambda f: int(f.stem.rsplit("-", 1)[-1]) if "-" in f.stem else 1)
    run = world_run(draw_stress_world(cls, seed, mount), seed)
    for index, f in enumerate(files):
        rc, out, err = _cli(["reconstruct", "--source", str(f), "--json"], workdir)
        score.counts["sweeps"] += 1
        if problem := _cli_problem(f"reconstruct {f.name}", rc, out, err, json_out=True):
            score.fail("crash", problem)
            continue
        finals = [doc for doc in map(json.loads, out.strip().splitlines()) if "surfaces" in doc]
        if finals:
            _compare_replay(score, f.name, finals[-1], estimate_of(sweep(run, index)))
    rc, out, err = _cli(["map", "--source", *map(str, files), "--json"], workdir)
    if problem := _cli_problem("map", rc, out, err, json_out=True):
        score.fail("crash", problem)
        return score
    if rc == 0 and out.strip():
        _score_map_json(score, json.loads(out.strip().splitlines()[-1]), draw_stress_world(cls, seed, mount))
    return score


def _compare_replay(score: WorldScore, name: str, doc: dict, estimate) -> None:
    """The replay's surfaces against the same sweep reconstructed in process (scored there): the same verdicts
    and planes within a millimetre, or the in-process score says nothing of what a user gets."""
    quality = {"PLANE_QUALITY_GOOD": "good", "PLANE_QUALITY_DEGRADED": "degraded"}
    replay = sorted(
        (quality.get(str(s["plane"].get("quality")), str(s["plane"].get("quality")).lower()), s["plane"]["offset"])
        for s in doc.get("surfaces", [])
    )
    mine = sorted((s.quality, s.offset) for s in estimate.surfaces.surfaces)
    score.counts["good surfaces"] += sum(q == "good" for q, _ in replay)
    same = len(replay) == len(mine) and all(
        a[0].endswith(b[0]) and abs(a[1] - b[1]) <= 1e-3 for a, b in zip(replay, mine, strict=True)
    )
    if not same:
        score.fail("replay ≠ in process", f"{name}: replay {replay} vs in process {mine}")


def _score_map_json(score: WorldScore, doc: dict, world) -> None:
    """The map's good walls against the world's faces: each lies on one (within the match limits) and within 2 cm.

    ``map --json`` is in the frame of the first pose's odometry, which the sim's odometry starts at the
    true first pose: the world frame.
    """
    faces = vertical_faces(build_model(world))
    for wall in doc.get("walls", []):
        if wall.get("quality") != "good":
            continue
        score.counts["map good walls"] += 1
        n = np.array([wall["normal"]["x"], wall["normal"]["y"]], float)
        n = n / max(float(np.linalg.norm(n)), 1e-12)
        ext = np.array([[p["x"], p["y"]] for p in wall.get("extent", [])], float).reshape(-1, 2)
        mid = ext.mean(axis=0) if len(ext) else n * float(wall["offset"])
        best = math.inf
        for _i, c, nt, half in faces:
            angle = math.acos(min(1.0, abs(float(n @ nt))))
            along = abs(float((mid - c) @ np.array([-nt[1], nt[0]])))
            if angle <= MATCH_ANGLE and along <= half + MATCH_DISTANCE:
                pts = ext if len(ext) else mid[None, :]
                best = min(best, float(np.max(np.abs((pts - c) @ nt))))
        if best > MATCH_DISTANCE:
            score.fail("map good on no face", f"CLI map wall normal {n.round(3).tolist()} offset {wall['offset']:.2f}")
        elif best > 0.02:
            score.fail("map good-but-off", f"CLI map wall {100 * best:.1f} cm off its face (no oracle map here)")


def run(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.table import Table

    from lelsonar.errors import ConfigError
    from lelsonar.tools.bench import machine, progress

    classes = STRESS_CLASSES if args.classes == "all" else tuple(c.strip() for c in args.classes.split(","))
    for c in classes:
        if c not in STRESS_CLASSES:
            raise ConfigError(f"unknown stress class {c!r}; choose from {', '.join(STRESS_CLASSES)}")
    mounts = MOUNTS if args.mount == "both" else (args.mount,)
    jobs = [(c, s, m) for c in classes for m in mounts for s in range(args.first_seed, args.first_seed + args.seeds)]
    scores: list[WorldScore] = []
    for cls, seed, mount in progress(jobs, "stress worlds"):
        try:
            world = draw_stress_world(cls, seed, mount)
        except ConfigError as exc:
            ws = WorldScore(cls, seed, mount)
            ws.fail("crash", f"draw: {exc}")
            scores.append(ws)
            continue
        scores.append(score_world(cls, seed, mount, world, args.max_poses, amplitude_noise=args.amplitude_noise))
    cli_jobs = jobs[:: max(1, len(jobs) // max(args.cli, 1))][: args.cli] if args.cli > 0 else []
    with tempfile.TemporaryDirectory(prefix="lelsonar-stress-") as tmp:
        for cls, seed, mount in progress(cli_jobs, "through the CLI"):
            scores.append(cli_world(cls, seed, mount, Path(tmp)))

    console = Console(width=220)
    table = Table(
        title=f"stress worlds ({', '.join(mounts)}; seeds {args.first_seed}–{args.first_seed + args.seeds - 1}"
        + (f"; amplitude noise {100 * args.amplitude_noise:g} %" if args.amplitude_noise else "")
        + f") — {machine()}"
    )
    table.add_column("class")
    for col in COUNTS:
        table.add_column(col, justify="right")
    groups = [*classes, "CLI"]
    for g in groups:
        mine = [s for s in scores if (s.cls == g and "CLI" not in s.mount) or (g == "CLI" and "CLI" in s.mount)]
        if not mine:
            continue
        table.add_row(g, *(str(sum(s.counts[c] for s in mine)) for c in COUNTS))
    table.add_row("total", *(str(sum(s.counts[c] for s in scores)) for c in COUNTS))
    console.print(table)
    lines = [line for s in scores for line in s.failures]
    for line in lines[: args.show]:
        console.print(line, markup=False)
    if len(lines) > args.show:
        console.print(f"… and {len(lines) - args.show} more failure lines")
    return 1 if any(s.counts[c] for s in scores for c in FAILURES) else 0
