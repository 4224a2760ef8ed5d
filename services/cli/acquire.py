"""`lelsonar acquire`: flags and TOML → :class:`AcquireConfig` → scans."""

from __future__ import annotations

import argparse
import math
import signal
import threading
import tomllib
from pathlib import Path

from lelsonar.cli.values import count
from lelsonar.errors import ConfigError

#: TOML keys (table [acquire]) and the flags that override them; angles in degrees, lengths in m.
_TOML_KEYS = {
    "scanner_id": str,
    "prefix": str,
    "device": str,
    "preset": str,
    "steps": int,
    "gamma_start_deg": float,
    "gamma_stop_deg": float,
    "radial_offset": float,
    "motor_port": str,
    "sensor_port": str,
    "out_dir": str,
    "mcap_name": str,
    "record": bool,
    "scans": int,
    "interval": float,
    "seed": int,
    "waveform_int16": bool,
    "compression": str,
    "energy_phi": list,
    "fsync": bool,
    "serve_log_for": float,
    "pipeline": bool,
    "world": str,
}


def register(sub: argparse._SubParsersAction) -> None:
    from lelsonar.acquire.backends import DEVICES
    from lelsonar.cli.paths import add_overwrite_argument
    from lelsonar.cli.secure import add_secure_argument
    from lelsonar.net.transport import add_zenoh_arguments
    from lelsonar.sim import preset_names

    p = sub.add_parser(
        "acquire",
        help="scan: drive the motor and sensor board, record to MCAP, publish on Zenoh",
        description="Run scans with the real drivers on hardware (--device serial), the real drivers on "
        "emulated devices (--device emulated, the default) or the simulator directly (--device sim). "
        "Every message is recorded to MCAP whether or not anyone subscribes; SIGINT/SIGTERM finish "
        "the current step, send ScanEnd(aborted) and close the file properly. Flags override the "
        "[acquire] table of --config.",
    )
    p.add_argument(
        "--config",
        type=Path,
        metavar="FILE.toml",
        help=f"TOML rig file (examples/rig.toml): an [acquire] table with keys {', '.join(_TOML_KEYS)}, "
        "and the rig tables [array] [servo] [sensor_board] [air] [energy_model] [schedule] that "
        "--device serial takes everything from",
    )
    p.add_argument("--scanner-id", help="scanner id in key expressions and messages (default: scanner1)")
    p.add_argument("--device", choices=DEVICES, help="what to drive (default: emulated)")
    p.add_argument(
        "--preset", choices=preset_names(), help="simulated scene and default schedule (default: paper-test1)"
    )
    p.add_argument(
        "--world",
        type=Path,
        metavar="FILE.toml",
        help="--device sim: scan a world (docs/worlds.md) at each of its poses, one recording per pose, "
        "each ScanStart with the odometry's pose",
    )
    p.add_argument("--steps", type=int, help="angle steps per scan (default: the preset's)")
    p.add_argument("--gamma-start", type=float, metavar="DEG", help="first angle, degrees (default: the preset's)")
    p.add_argument("--gamma-stop", type=float, metavar="DEG", help="last angle, degrees (default: the preset's)")
    p.add_argument("--radial-offset", type=float, metavar="M", help="capsule faces from the rotation axis, m")
    p.add_argument("--motor-port", help="serial device of the AX-12 (device serial), e.g. /dev/ttyUSB0")
    p.add_argument("--sensor-port", help="serial device of the sensor board (device serial), e.g. /dev/ttyACM0")
    p.add_argument("--out", type=Path, dest="out_dir", metavar="DIR", help="directory for recordings (default: out)")
    p.add_argument(
        "--mcap-name",
        metavar="NAME.mcap",
        help="recording file name (default: scan.mcap; several scans add -N); an existing one is refused "
        "unless --overwrite",
    )
    add_overwrite_argument(p)
    p.add_argument(
        "--no-record", dest="record", action="store_false", default=None, help="do not write an MCAP file (Zenoh only)"
    )
    p.add_argument("--no-zenoh", action="store_true", help="do not publish (record only)")
    p.add_argument("--scans", type=int, help="number of scans (default: 1)")
    p.add_argument("--interval", type=float, metavar="S", help="seconds between scans (default: 0)")
    p.add_argument("--seed", type=count, help="seed of the simulated acoustics (default: 0)")
    p.add_argument(
        "--int16",
        dest="waveform_int16",
        action="store_true",
        default=None,
        help="send waveforms as int16 plus a scale (half the bytes of float32)",
    )
    p.add_argument("--compression", choices=("zstd", "lz4", "none"), help="MCAP chunk compression (default: zstd)")
    p.add_argument(
        "--fsync",
        action="store_true",
        default=None,
        help="fsync the recording after every step, so it survives a power cut too (every step is "
        "always written to the OS before it is published; `lelsonar bench recording` measures "
        "the cost)",
    )
    p.add_argument(
        "--energy-phi",
        nargs=3,
        type=float,
        metavar=("PHI0", "PHI1", "PHI2"),
        help="energy model of eq. (12) in SI units (default: the simulator's calibration; see `lelsonar calibrate`)",
    )
    p.add_argument(
        "--serve-log-for",
        type=float,
        metavar="S",
        help="keep answering log queries (<prefix>/<scanner>/log/<scan_id>) for S seconds after the "
        "last scan, so reconstructors that missed steps recover them (default: 10; 0: only "
        "while scanning)",
    )
    p.add_argument(
        "--no-pipeline",
        dest="pipeline",
        action="store_false",
        default=None,
        help="one step after the other: do not move the servo while the board sends the last shot "
        "(`lelsonar bench acquire` compares the two)",
    )
    add_zenoh_arguments(p, default_mode="peer")
    add_secure_argument(p)
    p.set_defaults(run=run_acquire, _own_config_table=True)  # [acquire] and the rig tables: config_from_args


def load_toml(path: Path) -> dict:
    """The [acquire] table of a TOML file, type-checked."""
    try:
        with open(path, "rb") as f:
            table = tomllib.load(f).get("acquire", {})
    except FileNotFoundError:
        raise ConfigError(f"config file {path} does not exist") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path} is not valid TOML: {exc}") from None
    for key, value in table.items():
        kind = _TOML_KEYS.get(key)
        if kind is None:
            raise ConfigError(f"{path}: unknown key {key!r} in [acquire]; known: {', '.join(_TOML_KEYS)}")
        if not isinstance(value, kind) and not (kind is float and isinstance(value, int)):
            raise ConfigError(f"{path}: [acquire].{key} must be of type {kind.__name__}, got {value!r}")
    return table


def config_from_args(args: argparse.Namespace):
    from lelsonar.acquire.config import AcquireConfig
    from lelsonar.acquire.rig import load_rig
    from lelsonar.energy_model import EnergyModel

    values = load_toml(args.config) if args.config else {}
    rig = load_rig(args.config) if args.config else None
    if rig is not None and rig.values.get("schedule"):
        clash = [
            k for k in ("steps", "gamma_start_deg", "gamma_stop_deg") if k in values and k in rig.values["schedule"]
        ]
        if clash:
            raise ConfigError(f"{args.config}: {', '.join(clash)} given in both [acquire] and [schedule]; keep one")
        values.update(rig.values["schedule"])  # the schedule applies to every device
    for key in (
        "scanner_id",
        "device",
        "preset",
        "steps",
        "radial_offset",
        "motor_port",
        "sensor_port",
        "out_dir",
        "mcap_name",
        "record",
        "scans",
        "interval",
        "seed",
        "waveform_int16",
        "compression",
        "fsync",
        "serve_log_for",
        "pipeline",
    ):
        if getattr(args, key, None) is not None:
            values[key] = getattr(args, key)
    if args.prefix:
        values["prefix"] = args.prefix
    if getattr(args, "world", None) is not None:
        values["world"] = args.world
    if values.get("world") is not None:
        from lelsonar.sim.world import load_world

        if "scans" in values:
            raise ConfigError("--scans does not apply with --world: the world's [[pose]] entries set the scans")
        values["scans"] = len(load_world(values["world"]).poses)
    for name in ("gamma_start", "gamma_stop"):
        deg = getattr(args, name) if getattr(args, name) is not None else values.pop(f"{name}_deg", None)
        values.pop(f"{name}_deg", None)
        if deg is not None:
            values[name] = math.radians(deg)
    phi = args.energy_phi or values.pop("energy_phi", None)
    values.pop("energy_phi", None)
    if phi is not None:
        if len(phi) != 3:
            raise ConfigError("energy_phi needs three numbers: phi0 phi1 phi2")
        values["energy_model"] = EnergyModel(*map(float, phi))
    return AcquireConfig(**values, rig=rig)


def run_acquire(args: argparse.Namespace) -> int:
    from lelsonar.acquire.service import run_acquisition
    from lelsonar.net.transport import zenoh_settings_from_args
    from lelsonar.view import present

    cfg = config_from_args(args)
    check_recordings(cfg, overwrite=args.overwrite)
    if cfg.device != "serial":  # the simulated acoustics run the kernels
        from lelsonar.cli.warm_up import ensure_compiled

        ensure_compiled()
    zenoh = None if args.no_zenoh else zenoh_settings_from_args(args)
    if zenoh is not None and args.secure is not None:
        from lelsonar.net.secure import acquire_role, secure_settings

        # A client of the secure router: only the router's access rules let it publish, and only its own keys.
        zenoh = secure_settings(zenoh, args.secure, acquire_role(cfg.scanner_id), cfg.prefix)
    stop = threading.Event()
    interrupted = threading.Event()

    def on_signal(signum, _frame) -> None:
        if signum == signal.SIGINT:
            interrupted.set()
        stop.set()

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, on_signal)
    console = present.console(stderr=True)
    if zenoh is not None:
        console.print(f"acquire: publishing on {cfg.prefix}/{cfg.scanner_id}/{{sample,scan}} ({zenoh.describe()})")
    report = run_acquisition(cfg, zenoh, stop, console)
    if report.log_stats:
        console.print(
            f"acquire: the log answered {report.log_stats.get('queries', 0)} queries with "
            f"{report.log_stats.get('replies', 0)} messages; other outcomes: "
            f"{ {k: v for k, v in report.log_stats.items() if k not in ('queries', 'replies')} }",
            highlight=False,
        )
    if report.paths:
        console.print(f"open the recording with: rerun {' '.join(str(p) for p in report.paths)}")
    if report.ok:  # Ctrl-C while serving the log after complete scans ends that service: done
        return 0
    return 130 if interrupted.is_set() else 1


def check_recordings(cfg, *, overwrite: bool) -> None:
    """The files this run will write: refused before the first step if one exists (without --overwrite),
    if a file stands where the folder should be, or if the folder is not writable."""
    from lelsonar.cli.paths import output_dir, output_file

    if not cfg.record:
        return
    output_dir(cfg.out_dir, what="--out")
    for index in range(cfg.scans):
        output_file(cfg.mcap_path(index), overwrite=overwrite, what="recording")
