"""The service's observer that draws everything in Rerun, and the sinks it writes to."""

from __future__ import annotations

import os
import shutil
import socket
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import rerun as rr

from lelsonar import codec, poses
from lelsonar.errors import ConfigError
from lelsonar.geometry import beam_heading
from lelsonar.reconstruct.estimate import fit as F
from lelsonar.reconstruct.estimate import wire
from lelsonar.reconstruct.estimate.pipeline import DEFAULT_METHOD
from lelsonar.reconstruct.estimate.results import PlaneFit, PlaneResult, ScanReconstruction
from lelsonar.reconstruct.stream.assembly import ScanAssembly, StepView
from lelsonar.reconstruct.stream.partial import Partial
from lelsonar.sim import preset
from lelsonar.sim.scan import true_planes
from lelsonar.view.rerun_log import (
    ScanLogger,
    SubsetView,
    default_blueprint,
    make_recording,
)
from lelsonar.view.rerun_surfaces import log_surfaces
from lelsonar.view.rerun_world import log_scan_pose, log_world_truth


class RerunObserver:
    """Implements :class:`lelsonar.reconstruct.stream.service.Observer` on one recording.

    Parameters
    ----------
    rec : rerun.RecordingStream
    main_method : str
        Whose subsets (corrected points, inliers) are drawn.
    truth : list of (label, normal, offset, corners), optional
        True planes to draw (simulated scenes).
    """

    def __init__(self, rec: rr.RecordingStream, main_method: str, truth=None, world: dict | None = None) -> None:
        self.rec = rec
        self.main_method = main_method
        self.truth = truth
        self.world = world  # a simulated world (truth_world metadata), drawn once
        self._loggers: dict[tuple[str, int], ScanLogger] = {}
        self._last: ScanLogger | None = None

    def _logger(self, scan: ScanAssembly) -> ScanLogger:
        log = self._loggers.get(scan.key)
        if log is None:
            log = self._loggers[scan.key] = ScanLogger(self.rec, *scan.key, main_method=self.main_method)
        self._last = log
        return log

    def scan_started(self, scan: ScanAssembly) -> None:
        s = scan.start
        log = self._logger(scan)
        log.scan_started(
            s.start_time_ns,
            s.gamma_start,
            s.gamma_stop,
            s.steps,
            scan.geometry.capsules_in_array_frame(),
            f"scan {s.scan_id} of {s.scanner_id}: {s.steps} steps, device {s.device or 'unknown'}, "
            f"c = {s.sound_speed:.1f} m/s",
        )
        if self.truth:
            log.truth(self.truth)
        if self.world is not None:
            log_world_truth(self.rec, self.world)
            self.world = None
        if s.HasField("pose"):
            pose = poses.scan_pose(s)
            log_scan_pose(
                self.rec, s.scanner_id, s.scan_id, pose.position, beam_heading(pose.orientation), pose.frame_id
            )

    def step(self, scan: ScanAssembly, view: StepView, energy: float, expected: float, ratio: float) -> None:
        self._logger(scan).step(
            view.step,
            view.time_ns,
            view.gamma,
            raw_points=scan.raw_points(view.step),
            capsule_positions=scan.geometry.capsule_positions(view.gamma),
            waveforms=view.waveforms,
            sample_rate=view.sample_rate,
            t0=view.t0,
            energy=energy,
            expected_energy=expected,
            ratio=ratio,
        )

    def estimate(
        self,
        scan: ScanAssembly,
        message: codec.Reconstruction,
        results: dict[str, ScanReconstruction] | None,
        partial: Partial,
    ) -> None:
        final = results is not None
        crit = message.critical_step if message.HasField("critical_step") else None
        if results is not None:
            main = results[self.main_method]
            planes = [p for r in results.values() for p in r.planes]
            edge = main.edge
            subsets = self._final_subsets(scan, main)
        else:
            planes = [p for p in (partial.plane_a, partial.plane_b) if p is not None]
            edge = None
            subsets = [
                self._subset(d, p)
                for d, p in ((partial.data_a, partial.plane_a), (partial.data_b, partial.plane_b))
                if d is not None
            ]
        step = int(message.last_step)
        self._logger(scan).estimate(
            step,
            int(scan.time_ns[step]),
            planes,
            edge,
            [s for s in subsets if s],
            crit,
            float(scan.gamma[crit]) if crit is not None else None,
            final,
        )
        if final and (message.surfaces or message.corners or message.edges or message.unexplained):
            # At the time the logger just set: the final estimate's.
            log_surfaces(self.rec, self._logger(scan).scan_world, message)
        if final and message.HasField("accounting"):
            self._logger(scan).accounting(
                wire.status_name(message), wire.accounting_text(message.accounting), list(message.missing_steps)
            )

    def event(self, level: str, text: str, time_ns: int | None = None) -> None:
        if self._last is not None:
            self._last.event(level, text, time_ns)
        else:
            self.rec.log("log/service", rr.TextLog(text, level=level.upper()))

    @staticmethod
    def _subset(data: F.PlaneData | None, plane: PlaneResult | None) -> SubsetView | None:
        if data is None or data.n == 0:
            return None
        mask = plane.inlier_mask if isinstance(plane, PlaneFit) and plane.n_points == data.n else np.ones(data.n, bool)
        return SubsetView(data.label, np.asarray(data.points), np.asarray(mask))

    def _final_subsets(self, scan: ScanAssembly, main: ScanReconstruction) -> list[SubsetView | None]:
        # The points each plane was fitted on, as reconstruct() chose them.
        return [self._subset(main.data_a, main.plane_a), self._subset(main.data_b, main.plane_b)]


def preset_truth(name: str) -> list[tuple[str, np.ndarray, float, np.ndarray]]:
    """The true planes of a simulator preset, as the logger draws them."""
    return [(p.label, p.normal, p.offset, p.corners) for p in true_planes(preset(name))]


def rerun_viewer() -> str:
    """The Rerun viewer to spawn: the one installed beside this Python, else the first on PATH.

    Raises
    ------
    ConfigError
        No viewer, or no display for it to open on (the viewer would fail after a long wait).
    """
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise ConfigError(
            "--spawn needs a display (DISPLAY and WAYLAND_DISPLAY are unset); save the recording with "
            "--rrd FILE.rrd, or serve it with --serve PORT and connect a viewer from another machine"
        )
    beside = Path(sys.executable).with_name("rerun")
    found = str(beside) if beside.exists() else shutil.which("rerun")
    if found is None:
        raise ConfigError("--spawn: no Rerun viewer found (pip install rerun-sdk puts `rerun` beside python)")
    return found


def check_port_free(host: str, port: int) -> None:
    """Refuse a port something else listens on, before the server starts (it would only log the failure).

    Raises
    ------
    ConfigError
        The address is in use or cannot be bound.
    """
    if not 0 <= port <= 65535:
        raise ConfigError(f"--serve port must be in [0, 65535], got {port}")
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the server binds
        try:
            s.bind((host, port))
        except OSError as exc:
            raise ConfigError(
                f"cannot serve Rerun on {host}:{port}: {exc.strerror}; pick another --serve port"
            ) from None


@contextmanager
def open_rerun(
    *,
    rrd: Path | None = None,
    serve_port: int | None = None,
    serve_bind: str = "127.0.0.1",
    spawn: bool = False,
    application_id: str = "lelsonar",
    truth_preset: str | None = None,
    main_method: str | None = None,
    truth_world: dict | None = None,
) -> Iterator[RerunObserver]:
    """One explicit recording with the chosen sinks and the default blueprint; flushed on exit."""

    viewer = rerun_viewer() if spawn else None  # checked before anything starts
    if serve_port is not None:
        check_port_free(serve_bind, serve_port)
    rec = make_recording(application_id)
    blueprint = default_blueprint()
    sinks: list[rr.FileSink | rr.GrpcServerSink | rr.GrpcSink] = []
    if rrd is not None:
        Path(rrd).parent.mkdir(parents=True, exist_ok=True)
        sinks.append(rr.FileSink(str(rrd)))
    if serve_port is not None:
        sinks.append(rr.GrpcServerSink(bind_ip=serve_bind, port=serve_port))  # a viewer connects to us
    if viewer is not None:
        rr.spawn(connect=False, executable_path=viewer, recording=rec)
        sinks.append(rr.GrpcSink())
    rec.set_sinks(*sinks, default_blueprint=blueprint)
    try:
        yield RerunObserver(
            rec, main_method or DEFAULT_METHOD, preset_truth(truth_preset) if truth_preset else None, truth_world
        )
    finally:
        rec.flush()
        rec.disconnect()
