"""lelsonar demo: the whole system as separate processes over Zenoh on loopback.

router ─ acquire (emulated AX-12 and sensor board, through the real drivers)
       ─ reconstruct (live, incremental; writes the Rerun recording)
       ─ planner (a remote consumer: latest estimate, then updates)

Then it prints the final planes next to the truth, in the paper's units (cm, °)
and its equation style (eq. 16–19, 23–24), and says how to open the viewer.
It writes OUT/scan.mcap and OUT/scan.rrd, and refuses to replace them unless
given --overwrite.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

from lelsonar.cli.values import count


def register(sub: argparse._SubParsersAction) -> None:
    from lelsonar.cli.paths import add_overwrite_argument
    from lelsonar.sim import preset_names

    p = sub.add_parser(
        "demo",
        help="run acquire, reconstruct and planner over Zenoh and compare LS, LEL and truth",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--out", type=Path, default=Path("out"), metavar="DIR", help="output directory (default: out)")
    p.add_argument(
        "--preset", default="paper-test1", choices=preset_names(), help="simulated scene (default: paper-test1)"
    )
    p.add_argument(
        "--device",
        default="emulated",
        choices=("emulated", "sim"),
        help="emulated devices through the real drivers (default), or the simulator directly",
    )
    p.add_argument("--seed", type=count, default=0, help="seed of the simulated acoustics (default: 0)")
    p.add_argument(
        "--world",
        metavar="FILE|NAME",
        help="tour a world instead (a world file, an example's name: maze, or FAMILY:SEED: maze:3): the map grows "
        "scan by scan, the planner prints the route out, and OUT/<world>.rrd and .png show them",
    )
    p.add_argument(
        "--robot-radius", type=float, default=0.15, metavar="M", help="with --world: the route keeps this from walls"
    )
    p.add_argument(
        "--scan-every",
        type=float,
        default=0.5,
        metavar="M",
        help="with --world: the rover scans every M metres on its way between the world's poses (0: at the poses "
        "alone; default: 0.5)",
    )
    add_overwrite_argument(p)
    p.add_argument(
        "--secure",
        type=Path,
        metavar="DIR",
        help="run everything over mutual TLS with per-role access control, with the certificates in DIR "
        "(made now for scanner1 if DIR holds no CA)",
    )
    p.set_defaults(run=run_demo)


def _free_tcp_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run_demo(args: argparse.Namespace) -> int:
    if args.world is not None:
        from lelsonar.cli.demo_maze import run_maze_demo

        return run_maze_demo(args)

    from lelsonar.cli.paths import output_dir, output_file
    from lelsonar.cli.warm_up import ensure_compiled
    from lelsonar.errors import LelsonarError
    from lelsonar.net.transport import ZenohSettings, open_session
    from lelsonar.sim import preset
    from lelsonar.sim.scan import true_planes
    from lelsonar.view import present

    console = present.console()
    out: Path = output_dir(args.out, what="--out")
    mcap, rrd = out / "scan.mcap", out / "scan.rrd"
    for path in (mcap, rrd):
        output_file(path, overwrite=args.overwrite, what="demo output")
    overwrite = ["--overwrite"] if args.overwrite else []
    ensure_compiled()  # here, with its progress bar: the reconstructor below has a minute to come up
    endpoint = f"{'tls' if args.secure else 'tcp'}/127.0.0.1:{_free_tcp_port()}"
    secure_flags = ["--secure", str(args.secure)] if args.secure else []
    link = ["--mode", "client", "--connect", endpoint, *secure_flags]
    watcher = ZenohSettings(mode="client", connect=(endpoint,))
    if args.secure:
        from lelsonar.net.secure import PLANNER, SecureDir, init, secure_settings

        if not SecureDir(args.secure).ca_cert.exists():
            init(args.secure, ["scanner1"])
            console.print(f"[dim]created a CA and role certificates in {args.secure}")
        watcher = secure_settings(watcher, args.secure, PLANNER)  # watching liveliness is a planner's right
    lelsonar = [sys.executable, "-m", "lelsonar"]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    truth = {p.label: (p.normal, p.offset) for p in true_planes(preset(args.preset))}

    console.rule(
        f"lelsonar demo — scene {args.preset}, device {args.device}, Zenoh on {endpoint}"
        + (" (mutual TLS + access control)" if args.secure else "")
    )
    t_start = time.monotonic()
    procs: list[subprocess.Popen] = []

    def spawn(name: str, argv: list[str], **kw) -> subprocess.Popen:
        proc = subprocess.Popen(lelsonar + argv, env=env, text=True, **kw)
        procs.append(proc)
        console.print(f"[dim]started {name} (pid {proc.pid}): lelsonar {' '.join(argv)}")
        return proc

    try:
        router = spawn("router", ["router", "--listen", endpoint, *secure_flags], stdout=subprocess.PIPE)
        if router.stdout is None or "listening" not in (router.stdout.readline() or ""):
            console.print("[red]the Zenoh router did not start")
            return 1
        with open_session(watcher) as session:
            ready = threading.Event()
            seen: set[str] = set()

            def on_token(sample) -> None:
                seen.add(str(sample.key_expr).rsplit("/", 1)[-1])
                if {"reconstruct", "planner"} <= seen:
                    ready.set()

            session.liveliness().declare_subscriber("lelsonar/*/alive/*", on_token, history=True)
            recon = spawn(
                "reconstruct",
                [
                    "reconstruct",
                    "--json",
                    "--until-scans",
                    "1",
                    "--rrd",
                    str(rrd),
                    "--compare",
                    "ls,paper,fcm-ransac",
                    "--truth-preset",
                    args.preset,
                    *overwrite,
                    *link,
                ],
                stdout=subprocess.PIPE,
                stderr=subprocess.DEVNULL,
            )
            planner = spawn(
                "planner",
                ["planner", "--json", "--until-final", "1", "--timeout", "120", *link],
                stdout=subprocess.PIPE,
                stderr=subprocess.DEVNULL,
            )
            with console.status("waiting for reconstruct and planner to listen (each loads its kernels first)…"):
                up = ready.wait(60)
            if not up:
                console.print(f"[red]reconstruct and planner did not come up (seen: {sorted(seen)})")
                return 1
            acquire = spawn(
                "acquire",
                [
                    "acquire",
                    "--device",
                    args.device,
                    "--preset",
                    args.preset,
                    "--seed",
                    str(args.seed),
                    "--out",
                    str(out),
                    "--mcap-name",
                    mcap.name,
                    "--serve-log-for",
                    "2",
                    *overwrite,
                    *link,
                ],
            )
            if acquire.wait(300) != 0:
                console.print("[red]acquisition failed")
                return 1
            planner_out, _ = planner.communicate(timeout=120)
            recon.communicate(timeout=120)
    except (LelsonarError, subprocess.TimeoutExpired) as exc:
        console.print(f"[red]demo failed: {exc}")
        return 1
    finally:
        for proc in reversed(procs):
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
        for proc in procs:
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()

    finals = [json.loads(line) for line in planner_out.splitlines() if line.startswith("{")]
    finals = [f for f in finals if f["status"].startswith("final")]
    if not finals:
        console.print("[red]the planner received no final estimate")
        return 1
    final = present.from_json(finals[-1])
    console.print(
        present.planes_table(
            final,
            truth,
            title=f"Final estimate received by the planner (critical angle {final.critical_angle * 57.29578:.1f}°)",
        )
    )
    _print_equations(console, final, truth)
    elapsed = time.monotonic() - t_start
    console.print(
        f"\nwrote {mcap} ({mcap.stat().st_size / 1e6:.1f} MB) and {rrd} ({rrd.stat().st_size / 1e6:.1f} MB)"
        f" in {elapsed:.1f} s"
    )
    console.print(f"open the live reconstruction:  [bold]{Path(sys.executable).parent / 'rerun'} {rrd}[/]")
    console.print(f"open the raw recording:        [bold]{Path(sys.executable).parent / 'rerun'} {mcap}[/]")
    return 0


def _print_equations(console, final, truth) -> None:
    """The paper's way of writing the planes (cm), method by method, then who wins."""
    import numpy as np

    from lelsonar.reconstruct.estimate.pipeline import DEFAULT_METHOD
    from lelsonar.view import present

    methods = sorted({p.method for p in final.planes}, key=lambda m: (m != "ls", m != "paper", m))
    console.print("\nPlanes as the paper writes them (cm; ideal: y = 157, z = 106):")
    for m in methods:
        for eq in present.plane_equations(final, m):
            console.print(f"  {m:>14}:  {eq}")
    errors: dict[str, list[float]] = {}
    for p in final.planes:
        if p.label in truth:
            n = np.array([p.normal.x, p.normal.y, p.normal.z])
            errors.setdefault(p.method, []).append(present.angle_deg(n, truth[p.label][0]))
    if "ls" in errors and DEFAULT_METHOD in errors:
        ls, best = max(errors["ls"]), max(errors[DEFAULT_METHOD])
        verdict = "beats" if best < ls else "does NOT beat"
        console.print(f"\n{DEFAULT_METHOD} {verdict} least squares: worst normal error {best:.2f}° against {ls:.2f}°")
