"""lelsonar emulate: an AX-12 and a sensor board on two ptys, until SIGINT/SIGTERM.

Both emulators run as threads of this process.  The sensor board sees the
angle the emulated servo is at.  Point the real drivers (or any serial tool)
at the printed paths.
"""

from __future__ import annotations

import argparse
import json
import math
import signal
import sys
import threading

import numpy as np

from lelsonar.acquire.devices import ax12
from lelsonar.acquire.devices.link import AX12_BUS, SENSOR_BOARD_USB
from lelsonar.acquire.emulate.ax12_emulator import AX12EmulatorConfig
from lelsonar.acquire.emulate.rig import emulated_rig
from lelsonar.acquire.emulate.sensor_board_emulator import (
    SensorBoardEmulatorConfig,
    ShotSource,
    echo_shot_source,
    sim_shot_source,
)
from lelsonar.cli.values import count
from lelsonar.errors import ConfigError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "emulate",
        help="run an emulated AX-12 and sensor board on ptys",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--source",
        choices=("auto", "sim", "echo"),
        default="auto",
        help="what the board hears: the acoustic simulator, a fixed wall, or sim if installed (default)",
    )
    p.add_argument("--preset", default="paper-test1", help="simulator preset (default: %(default)s)")
    p.add_argument("--echo-distance", type=float, default=1.0, metavar="M", help="wall range for --source echo")
    p.add_argument("--seed", type=count, default=0, help="seed of the simulator and the fault generators")
    p.add_argument("--motor-id", type=int, default=1, metavar="ID", help="the AX-12's bus id (default: 1)")
    p.add_argument("--return-delay", type=int, default=0, help="Return Delay Time, 2 µs units (datasheet default 250)")
    p.add_argument("--zero-raw", type=int, default=ax12.CENTER_RAW, help="raw position of γ = 0")
    p.add_argument("--start-gamma", type=float, default=0.0, metavar="DEG", help="servo angle at power-on, γ degrees")
    p.add_argument("--corrupt-p", type=float, default=0.0, help="probability of a bit flip in an ACQ frame")
    p.add_argument("--garbage-p", type=float, default=0.0, help="probability of garbage before a frame")
    p.add_argument("--no-realtime", action="store_true", help="answer FIRE at once instead of after the window")
    p.add_argument(
        "--unpaced",
        action="store_true",
        help="move bytes as fast as the ptys take them, instead of at the links' rates (the AX-12 bus "
        "at 1 Mbps, the board on USB full speed)",
    )
    p.add_argument("--json", action="store_true", help="print only the paths, as one JSON line on stdout (for scripts)")
    p.set_defaults(run=run)


def _shot_source(args: argparse.Namespace) -> tuple[ShotSource, str]:
    if args.source in ("auto", "sim"):
        try:
            from lelsonar import sim

            preset = sim.preset(args.preset)
        except (ImportError, AttributeError) as exc:
            if args.source == "sim":
                raise ConfigError(f"the simulator is not available ({exc}); use --source echo") from exc
        else:
            return sim_shot_source(preset, np.random.default_rng(args.seed)), f"sim:{args.preset}"
    return echo_shot_source(args.echo_distance, seed=args.seed), f"echo:{args.echo_distance}m"


def run(args: argparse.Namespace) -> int:
    source, source_name = _shot_source(args)
    start_raw = ax12.raw_from_gamma(math.radians(args.start_gamma), args.zero_raw)
    motor_config = AX12EmulatorConfig(
        motor_id=args.motor_id,
        return_delay=args.return_delay,
        initial_position=start_raw,
        seed=args.seed,
        link=None if args.unpaced else AX12_BUS,
    )
    board_config = SensorBoardEmulatorConfig(
        realtime=not args.no_realtime,
        corrupt_probability=args.corrupt_p,
        garbage_probability=args.garbage_p,
        seed=args.seed,
        link=None if args.unpaced else SENSOR_BOARD_USB,
    )
    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        with emulated_rig(source, motor_config, board_config, zero_raw=args.zero_raw) as rig:
            pace = "unpaced" if args.unpaced else "paced"
            if args.json:
                print(json.dumps({**rig.paths, "motor_id": args.motor_id, "source": source_name}))
            else:
                print(f"AX-12 (id {args.motor_id}, 1 Mbps, {pace}): {rig.motor.path}")
                print(
                    f"sensor board ({source_name}, {'unpaced' if args.unpaced else SENSOR_BOARD_USB.describe()}): "
                    f"{rig.board.path}"
                )
            print("running; Ctrl-C to stop", file=sys.stderr)
            sys.stdout.flush()
            while not stop.wait(0.5):  # a bounded wait keeps signal delivery prompt
                if not (rig.motor.running and rig.board.running):
                    break  # leaving the block stops both and raises the thread's failure
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return 0
