"""`lelsonar simulate` and `lelsonar calibrate`.

``simulate`` runs a preset and prints what it produced (optionally a figure
like the paper's Figs. 3, 4 and 6).  ``calibrate`` runs the paper's six-shot
energy calibration (§4) against the simulator, or, with ``--manual``, fits
distance/energy pairs typed in (one ``distance_m energy_V2s`` pair a line on
stdin).  Hardware calibration plugs in as another shot source
(:class:`lelsonar.sim.calibrate.EnergyShotSource`).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from lelsonar.cli.values import count
from lelsonar.errors import ConfigError

#: The figure formats ``--plot`` writes, by suffix.
PLOT_SUFFIXES = (".png", ".pdf", ".svg")


def register(sub: argparse._SubParsersAction) -> None:
    from lelsonar.cli.paths import add_overwrite_argument
    from lelsonar.sim.presets import preset_names
    from lelsonar.sim.scenes import FAMILIES

    p = sub.add_parser("simulate", help="simulate a scan of an L-shaped corner (physics-based)")
    p.add_argument(
        "--preset", default="paper-test1", choices=preset_names(), help="scene and scan (default: %(default)s)"
    )
    p.add_argument(
        "--family",
        choices=FAMILIES,
        help="draw the scene from a benchmark scene family instead of a preset (with --seed)",
    )
    p.add_argument("--seed", type=count, default=0, help="random seed; the same seed gives the same bytes")
    p.add_argument(
        "--mcap",
        metavar="OUT.mcap",
        help="also record the scan as `lelsonar acquire --device sim` would, with the rig's calibrated "
        "energy model; `lelsonar reconstruct --source OUT.mcap --json` reconstructs it",
    )
    p.add_argument("--plot", metavar="FILE.png", help="write a figure of points, energies and R (.png, .pdf or .svg)")
    add_overwrite_argument(p)
    p.add_argument(
        "--world",
        type=Path,
        metavar="FILE.toml",
        help="simulate a world (docs/worlds.md) at each of its poses instead of an L; --plot draws the world, "
        "the poses, the path and each sweep's echoes",
    )
    p.set_defaults(run=_simulate)

    c = sub.add_parser("calibrate", help="fit the energy model E0(d) from six face-on shots (paper §4)")
    c.add_argument(
        "--preset",
        default="paper-test1",
        choices=preset_names(),
        help="simulator configuration to calibrate (default: %(default)s)",
    )
    c.add_argument("--seed", type=count, default=0, help="random seed of the simulated shots")
    c.add_argument(
        "--distances", type=float, nargs="+", metavar="M", help="wall distances in m (default: six from 0.9 to 1.8)"
    )
    c.add_argument(
        "--manual", action="store_true", help="read 'distance_m energy_V2s' pairs from stdin instead of simulating"
    )
    c.add_argument(
        "--device",
        choices=("sim", "serial"),
        default="sim",
        help="sim: the simulator (default); serial: guide six face-on shots on the real rig of "
        "--config and write φ into its [energy_model] table",
    )
    c.add_argument(
        "--config",
        type=Path,
        metavar="RIG.toml",
        help="the rig file (examples/rig.toml): ports, servo, board, air; --device serial rewrites its [energy_model]",
    )
    c.add_argument("--motor-port", help="override [servo].port")
    c.add_argument("--sensor-port", help="override [sensor_board].port")
    c.add_argument("--dry-run", action="store_true", help="--device serial: fit and print, leave the file alone")
    c.add_argument(
        "--force",
        action="store_true",
        help="--device serial: write the fit even when the board's range disagrees with a typed distance "
        "beyond the noise model (a wall moved, a typo)",
    )
    c.set_defaults(run=_calibrate, _own_config_table=True)


def _check_outputs(args: argparse.Namespace) -> None:
    from lelsonar.cli.paths import output_file

    if args.mcap:
        output_file(args.mcap, overwrite=args.overwrite, what="--mcap file")
    if args.plot:
        if Path(args.plot).suffix.lower() not in PLOT_SUFFIXES:
            raise ConfigError(f"--plot writes {', '.join(PLOT_SUFFIXES)} files, got {args.plot}")
        output_file(args.plot, overwrite=args.overwrite, what="--plot file")
        if args.mcap and Path(args.mcap).resolve() == Path(args.plot).resolve():
            raise ConfigError("--mcap and --plot must be different files")


def _simulate(args: argparse.Namespace) -> int:
    from lelsonar.signal.energy import energy_ratio
    from lelsonar.sim.calibrate import default_energy_model
    from lelsonar.sim.presets import preset
    from lelsonar.sim.scan import EchoSource, simulate_scan

    _check_outputs(args)
    from lelsonar.cli.warm_up import ensure_compiled

    ensure_compiled()
    if args.world is not None:
        return _simulate_world(args)
    if args.family:
        from lelsonar.sim.scenes import simulate_family_scene

        fs = simulate_family_scene(args.family, args.seed)
        scan, model, name = fs.scan, fs.energy_model, f"family {args.family}"
        print(fs.draw.description)
    else:
        scan = simulate_scan(preset(args.preset), seed=args.seed)
        model, name = default_energy_model(), f"preset {args.preset}"
    ratio = energy_ratio(scan.step_energy(), scan.distance, model)
    k = int(np.argmax(ratio))
    counts = np.bincount(scan.truth.echo_source.ravel().astype(int), minlength=len(EchoSource))
    print(
        f"{name}, seed {args.seed}: {scan.n_steps} steps × {scan.geometry.n_capsules} capsules, "
        f"{scan.waveforms.shape[-1]} samples at {scan.sample_rate / 1e3:.0f} kS/s, c = {scan.sound_speed:.1f} m/s"
    )
    print("echo that set the TOF: " + ", ".join(f"{s.name.lower()} {counts[s]}" for s in EchoSource if counts[s]))
    print(
        f"critical angle {np.degrees(scan.truth.critical_angle):.2f}° (step {scan.truth.critical_step}); "
        f"argmax R step {k} at {np.degrees(scan.gamma_measured[k]):.2f}°"
    )
    for plane in scan.truth.planes:
        n = plane.normal
        print(f"plane {plane.label}: n = ({n[0]:+.4f}, {n[1]:+.4f}, {n[2]:+.4f}), n·p = {plane.offset:.4f} m")
    if args.mcap:
        from lelsonar.acquire.simulated import record_scan

        meta = {"family": args.family or "", "preset": "" if args.family else args.preset, "seed": str(args.seed)}
        end = record_scan(scan, args.mcap, model, scan_id=args.seed + 1, metadata=meta)
        print(f"recorded {end.samples_sent} samples to {args.mcap}")
    if args.plot:
        from lelsonar.sim.plot import save_scan_figure

        print(f"wrote {save_scan_figure(scan, args.plot)}")
    return 0


def _simulate_world(args: argparse.Namespace) -> int:
    import math

    from lelsonar.sim.odometry import simulate_odometry
    from lelsonar.sim.scan import EchoSource
    from lelsonar.sim.world import load_world
    from lelsonar.sim.world_geometry import ElementKind, build_model
    from lelsonar.sim.world_render import simulate_world_scan

    if args.mcap or args.family:
        raise ConfigError("--world runs alone: record its scans with `lelsonar acquire --device sim --world FILE`")
    world = load_world(args.world)
    model = build_model(world)
    kinds = {k.name.lower(): sum(e.kind == k for e in model.elements) for k in ElementKind}
    print(
        f"world {world.name}: {len(world.walls)} walls, {len(world.boxes)} boxes, {len(model.surfaces)} surfaces; "
        + ", ".join(f"{n} {k}" for k, n in kinds.items())
        + f"; {world.scanner.mount} mount at {world.scanner.height:g} m"
    )
    scans = []
    for i, pose in enumerate(world.poses):
        scan = simulate_world_scan(model, i, seed=np.random.default_rng([args.seed, i]), with_waveforms=False)
        scans.append(scan)
        counts = np.bincount(scan.echo_source.ravel().astype(int), minlength=len(EchoSource))
        print(
            f"pose {i + 1} (x {pose.x:g} m, y {pose.y:g} m, heading {math.degrees(pose.heading):g}°): "
            f"{scan.n_steps} steps; echo that set the TOF: "
            + ", ".join(f"{s.name.lower()} {counts[s]}" for s in EchoSource if counts[s])
        )
    if args.plot:
        from lelsonar.sim.world_plot import save_world_figure

        odometry = simulate_odometry(world.poses, world.odometry)
        print(f"wrote {save_world_figure(model, scans, args.plot, odometry)}")
    return 0


def _calibrate(args: argparse.Namespace) -> int:
    from lelsonar.signal.energy import fit_energy_model
    from lelsonar.sim.calibrate import PAPER_CALIBRATION_DISTANCES, CalibrationResult, calibrate_simulator
    from lelsonar.sim.presets import preset

    if args.device == "serial":
        return _calibrate_serial(args)
    if args.manual:
        d, e = _read_pairs(sys.stdin)
        result = CalibrationResult(distances=d, energies=e, model=fit_energy_model(d, e))
        origin = "typed shots"
    else:
        distances = tuple(args.distances) if args.distances else PAPER_CALIBRATION_DISTANCES
        result = calibrate_simulator(preset(args.preset), seed=args.seed, distances=distances)
        origin = f"simulator preset {args.preset}, seed {args.seed}"
    m = result.model
    print(f"energy calibration (paper §4, eq. 12–14) from {origin}:")
    print("   d (m)    E (V²·s)    fit (V²·s)   misfit")
    for d, e, r in zip(result.distances, result.energies, result.residuals()):
        print(f"  {d:6.3f}  {e:10.4e}  {m.expected_energy(d):10.4e}  {r:+7.2%}")
    print(f"phi0 = {m.phi0:.6g} 1/(V²·s·m²)\nphi1 = {m.phi1:.6g} 1/(V²·s·m)\nphi2 = {m.phi2:.6g} 1/(V²·s)")
    print(f"valid for d in [{m.d_min:.3f}, {m.d_max:.3f}] m")
    return 0


def _calibrate_serial(args: argparse.Namespace) -> int:
    from lelsonar.acquire.calibrate_rig import calibrate_serial
    from lelsonar.sim.calibrate import PAPER_CALIBRATION_DISTANCES

    if args.config is None:
        raise ConfigError("calibrate --device serial needs the rig file: --config rig.toml (see examples/rig.toml)")
    distances = tuple(args.distances) if args.distances else PAPER_CALIBRATION_DISTANCES

    def ask(prompt: str) -> str:
        print(prompt, end="", flush=True)
        line = sys.stdin.readline()
        if not line:
            raise ConfigError("no answer on stdin; the rig file is unchanged")
        return line

    shots, m = calibrate_serial(
        args.config,
        distances,
        ask,
        print,
        motor_port=args.motor_port,
        sensor_port=args.sensor_port,
        write=not args.dry_run,
        force=args.force,
    )
    print("   d (m)    E (V²·s)    fit (V²·s)   misfit")
    for s in shots:
        fit = m.expected_energy(s.distance)
        print(f"  {s.distance:6.3f}  {s.energy:10.4e}  {fit:10.4e}  {s.energy / fit - 1:+7.2%}")
    print(f"phi = [{m.phi0:.6g}, {m.phi1:.6g}, {m.phi2:.6g}], valid for d in [{m.d_min:.3f}, {m.d_max:.3f}] m")
    print(f"{'would write' if args.dry_run else 'wrote'} [energy_model] in {args.config}")
    return 0


def _read_pairs(stream) -> tuple[np.ndarray, np.ndarray]:
    """Parse 'distance energy' lines (blank lines and '#' comments ignored)."""
    pairs = []
    for lineno, line in enumerate(stream, 1):
        text = line.split("#", 1)[0].strip()
        if not text:
            continue
        parts = text.replace(",", " ").split()
        try:
            if len(parts) != 2:
                raise ValueError
            pairs.append((float(parts[0]), float(parts[1])))
        except ValueError:
            raise ConfigError(f"line {lineno}: expected 'distance_m energy_V2s', got {line.strip()!r}") from None
    if not pairs:
        raise ConfigError("no 'distance_m energy_V2s' pairs on stdin")
    arr = np.array(pairs)
    return arr[:, 0], arr[:, 1]
