"""`lelsonar acquire`: scan, record every message to MCAP, publish it on Zenoh.

The scanner, the Zenoh session and each recording are opened in ``with``
blocks, so a fault, SIGINT or SIGTERM still leaves finished MCAP files, closed
ports and the servo's torque off.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import threading
import time
from collections.abc import Callable
from contextlib import ExitStack, nullcontext
from dataclasses import dataclass
from pathlib import Path

import zenoh as zenoh_lib
from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TaskID,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

from lelsonar import codec
from lelsonar.acquire.backends import open_scanner
from lelsonar.acquire.config import AcquireConfig
from lelsonar.acquire.log_server import LogServer, Receipts, ScanLog
from lelsonar.acquire.odometry import OdometryFollower
from lelsonar.acquire.rig import serial_setup
from lelsonar.acquire.scan_loop import ScanIdentity, ScanOutput, ScanPublisher, gamma_schedule, run_scan
from lelsonar.acquire.scanner import ScannerInfo
from lelsonar.acquire.world_scans import WorldReplay, prepare_world
from lelsonar.energy_model import EnergyModel
from lelsonar.errors import RecordingError
from lelsonar.keys import ScannerKeys
from lelsonar.log.recording import McapRecorder, free_space
from lelsonar.net.transport import ZenohSettings, open_session
from lelsonar.sim import SimConfig, default_energy_model, preset
from lelsonar.sim.scan import true_planes

_log = logging.getLogger(__name__)

#: V per count when waveforms travel as int16: ±5 V full scale, finer than a 12-bit ADC.
INT16_SCALE = 5.0 / 32767


def sim_truth(sim: SimConfig) -> list:
    """The true planes of a simulated scene, as the recording draws them."""
    return [(p.label, p.normal, p.offset, p.corners) for p in true_planes(sim)]


def sim_config(cfg: AcquireConfig) -> SimConfig:
    """The preset, with the schedule and geometry overrides of ``cfg``."""
    sim = preset(cfg.preset)
    if cfg.steps is not None:
        sim = dataclasses.replace(sim, steps=cfg.steps)
    if cfg.gamma_start is not None:
        sim = dataclasses.replace(sim, gamma_start=cfg.gamma_start)
    if cfg.gamma_stop is not None:
        sim = dataclasses.replace(sim, gamma_stop=cfg.gamma_stop)
    if cfg.radial_offset is not None:
        sim = dataclasses.replace(sim, geometry=dataclasses.replace(sim.geometry, radial_offset=cfg.radial_offset))
    return sim


def energy_model(cfg: AcquireConfig) -> EnergyModel:
    if cfg.energy_model is not None:
        return cfg.energy_model
    return default_energy_model()


#: Bytes a step takes on disk besides its waveforms (the sample's numbers, its pose, points and scalars).
STEP_OVERHEAD_BYTES = 16 * 1024


def scan_bytes(steps: int, info: ScannerInfo) -> int:
    """An upper estimate of a scan's recording: every waveform uncompressed, float32, plus each step's views."""
    return steps * (info.geometry.n_capsules * info.window_samples * 4 + STEP_OVERHEAD_BYTES)


def check_space(directory: Path, steps: int, info: ScannerInfo) -> None:
    """Refuse to start a scan whose recording would not fit in ``directory``.

    Raises
    ------
    RecordingError
        One line naming the directory, its free space and the space a scan needs.
    """
    free = free_space(directory)
    needed = scan_bytes(steps, info)
    if free is not None and free < needed:
        raise RecordingError(
            f"not enough space to record a scan in {directory}: {free / 2**20:.1f} MiB free, a scan of {steps} "
            f"steps needs up to {needed / 2**20:.1f} MiB; free some space or give another --out directory"
        )


#: s, the longest ``acquire`` serves its log after the scans while a reconstructor still lacks a scan's final.
SERVE_LOG_MAX = 120.0


def serve_log(
    receipts: Receipts,
    scan_ids: list[int],
    serve_for: float,
    stop: threading.Event,
    *,
    longest: float = SERVE_LOG_MAX,
    clock=time.monotonic,
) -> None:
    """Serve for ``serve_for`` s, then on while a reconstructor may still ask for one of ``scan_ids`` (a
    partition hides it for a while: its final has not come back), at most ``longest`` s in all."""
    start = clock()
    while not stop.wait(min(0.2, serve_for) if serve_for > 0 else 0.2):
        waited = clock() - start
        if waited >= max(serve_for, longest):
            _log.warning("stopped serving the log after %.0f s; a reconstructor may still lack a scan", waited)
            return
        if waited >= serve_for and not any(receipts.wanted(s) for s in scan_ids):
            return


def _quietly(what: str, fn: Callable[[], object]) -> None:
    """Run a Zenoh clean-up step; after a partition it may fail, which must not crash acquire."""
    try:
        fn()
    except zenoh_lib.ZError as exc:
        _log.warning("%s failed (the network may be down; the recording is complete): %s", what, exc)


def _advance(progress: Progress, task: TaskID) -> Callable[[int, float], None]:
    """``run_scan``'s ``on_step``: one step more on ``task``, showing the measured γ."""

    def on_step(_step: int, gamma: float) -> None:
        progress.update(task, advance=1, gamma=math.degrees(gamma))

    return on_step


@dataclass
class AcquisitionReport:
    ends: list[codec.ScanEnd]
    paths: list
    publish_failures: int
    log_stats: dict | None = None
    #: Samples published while no subscriber matched their key (nobody received them live).
    unmatched: int = 0

    @property
    def ok(self) -> bool:
        return bool(self.ends) and all(e.status == 1 for e in self.ends)


def run_acquisition(
    cfg: AcquireConfig, zenoh: ZenohSettings | None, stop: threading.Event, console: Console | None = None
) -> AcquisitionReport:
    """Run ``cfg.scans`` scans; return what happened.  Never leaves a file unfinished."""
    console = console or Console(stderr=True)
    world = prepare_world(cfg.world, cfg.seed, steps=cfg.steps) if cfg.world is not None else None
    if cfg.device == "serial":  # the rig file and flags only, never a simulator preset
        setup, sim = serial_setup(cfg), None
        schedule = gamma_schedule(setup.gamma_start, setup.gamma_stop, setup.steps)
        model = setup.energy_model
    elif world is not None:  # one simulated sweep per pose, each its own scanner
        sim = None
        schedule = world.schedule
        model = energy_model(cfg)
    else:
        sim = sim_config(cfg)
        schedule = gamma_schedule(sim.gamma_start, sim.gamma_stop, sim.steps)
        model = energy_model(cfg)
    keys = ScannerKeys(cfg.prefix, cfg.scanner_id)
    report = AcquisitionReport([], [], 0)
    log: ScanLog | None = None
    receipts: Receipts | None = None
    with ExitStack() as stack:
        publisher = None
        server = None
        follower = None
        if zenoh is not None:
            log = ScanLog(keep_for=max(cfg.serve_log_for, SERVE_LOG_MAX))
            session = stack.enter_context(open_session(zenoh))
            token = session.liveliness().declare_token(keys.alive("acquire"))
            stack.callback(_quietly, "undeclaring the liveliness token", token.undeclare)
            # Serve the log before the first scan: a reconstructor may ask as soon as it sees a sample.
            server = stack.enter_context(LogServer(session, keys, log))
            receipts = Receipts(session, keys)
            stack.callback(receipts.close)
            publisher = ScanPublisher(session, keys)
            stack.callback(_quietly, "undeclaring the publishers", publisher.close)
            if world is None and cfg.rig is not None and cfg.rig.get("mount.kind") is not None:
                # A robot's scanner: each scan carries the pose its odometry publishes, through the mount.
                follower = OdometryFollower(session, keys, max_age=cfg.rig.get("mount.odometry_max_age", 1.0))
                stack.callback(_quietly, "undeclaring the odometry subscriber", follower.close)
        with nullcontext(None) if world is not None else open_scanner(cfg, sim) as opened:
            for index in range(cfg.scans):
                scan_id = time.time_ns() // 1000  # unique per scanner, readable as a start time in µs
                path = cfg.mcap_path(index) if cfg.record else None
                scanner = world.scanner(index) if world is not None else opened
                assert scanner is not None  # open_scanner yields one whenever there is no world
                if follower is not None and cfg.rig is not None:
                    pose, why = follower.pose_for_scan(cfg.rig.get("mount.kind"), cfg.rig.get("mount.height", 0.0))
                    scanner.info = dataclasses.replace(scanner.info, pose=pose)
                    if why:
                        console.print(f"acquire: {why}")
                meta = cfg.as_metadata()
                if world is not None and isinstance(scanner, WorldReplay):
                    meta |= world.metadata(index, scanner.scan)  # the truth, never on the wire
                if path:
                    check_space(path.parent, len(schedule), scanner.info)
                with ExitStack() as scan_stack:
                    recorder = (
                        scan_stack.enter_context(
                            McapRecorder(
                                path,
                                compression=cfg.compression,
                                metadata=meta,
                                fsync=cfg.fsync,
                                truth=None if sim is None else sim_truth(sim),  # simulated scenes only
                            )
                        )
                        if path
                        else None
                    )
                    output = ScanOutput(recorder, publisher, scan_log=log)
                    progress = scan_stack.enter_context(
                        Progress(
                            TextColumn(f"scan {index + 1}/{cfg.scans}"),
                            BarColumn(),
                            MofNCompleteColumn(),
                            TextColumn("γ {task.fields[gamma]:>6.1f}°"),
                            TimeElapsedColumn(),
                            TextColumn("ETA"),
                            TimeRemainingColumn(),
                            console=console,
                            transient=False,
                        )
                    )
                    task = progress.add_task("scan", total=len(schedule), gamma=math.degrees(schedule[0]))
                    end = run_scan(
                        scanner,
                        schedule,
                        ScanIdentity(cfg.scanner_id, scan_id),
                        model,
                        output,
                        stop,
                        on_step=_advance(progress, task),
                        int16_scale=INT16_SCALE if cfg.waveform_int16 else None,
                    )
                    report.publish_failures += output.publish_failures
                unmatched = publisher.take_unmatched() if publisher is not None else 0
                report.unmatched += unmatched
                report.ends.append(end)
                if path:
                    report.paths.append(path)
                status = "complete" if end.status == 1 else f"ABORTED ({end.reason})"
                if world is not None:
                    p = world.world.poses[index]
                    status += f" at pose {index + 1} (x {p.x:g} m, y {p.y:g} m, heading {math.degrees(p.heading):g}°)"
                recorded = ""
                if path:
                    recorded = (
                        f"; what was recorded is in {path} (lelsonar info / recover read it)"
                        if output.recording_failure
                        else f"; recorded to {path}"
                    )
                console.print(
                    f"scan {scan_id}: {status}; {end.samples_sent}/{end.steps_planned} samples, "
                    f"{end.echoes_missing} readings without echo" + recorded,
                    highlight=False,
                    soft_wrap=True,
                )
                if unmatched:
                    console.print(
                        f"acquire: warning: {unmatched} of {end.samples_sent} samples of scan {scan_id} were "
                        "published while no subscriber matched (nobody received them live); a reconstructor "
                        "gets them from the log while it is served (--serve-log-for) or from the recording",
                        highlight=False,
                        soft_wrap=True,
                    )
                if end.status != 1 or stop.is_set():
                    break
                if index + 1 < cfg.scans and stop.wait(cfg.interval):
                    break
        if server is not None and receipts is not None and cfg.serve_log_for > 0 and not stop.is_set():
            # The scanner is released (torque off); keep answering reconstructors that missed steps.
            _log.info(
                "serving the log of the last scans for %.1f s (--serve-log-for; Ctrl-C ends it)", cfg.serve_log_for
            )
            console.print(
                f"acquire: serving the log of the last scans for {cfg.serve_log_for:g} s, longer while a "
                f"reconstructor has not finalised them (at most {max(cfg.serve_log_for, SERVE_LOG_MAX):g} s; "
                "--serve-log-for; Ctrl-C ends it)",
                soft_wrap=True,
            )
            serve_log(receipts, [e.scan_id for e in report.ends], cfg.serve_log_for, stop)
        if server is not None:
            report.log_stats = dict(server.stats)
    return report
