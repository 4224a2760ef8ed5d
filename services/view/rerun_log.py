"""Rerun timeline logging of the reconstruction: what engineers look at while a scan runs.

Everything goes through one explicit :class:`rerun.RecordingStream` that the
caller creates (:func:`make_recording`) and gives sinks to (``rec.save``,
``rec.serve_grpc``, ``rec.spawn`` or ``rec.set_sinks``).  Nothing here touches
Rerun's global recording.

What is shown (the paper's Figs. 3–15):

* the world (a 3D view): the array's pose, the raw points of eq. (9) so far,
  the current beams, the corrected points of each subset with the outliers
  flagged, the plane patches and normals of every method (LS, LEL, ...), the
  corner edge, the critical direction and the true planes;
* the energy ``E^γ`` and its expectation ``E0(d_m)`` (Figs. 4–5), the ratio
  ``R`` with the critical step marked (Fig. 6);
* the four waveforms of the current step;
* the sorted fitting errors ``e_i`` of each plane (Figs. 12–13);
* a text log of events (scan start, critical step, failures, final result).

Timelines
---------
``step``
    Sequence: the step index of the scan.  The default timeline.
``gamma_cdeg``
    Sequence: the measured rotation γ in hundredths of a degree,
    ``round(degrees(γ) · 100)``.  A sequence (not a duration) because γ is an
    angle, not a time; hundredths keep the AX-12's ≈0.29° resolution.  It is
    monotonic for a scan in one direction; a scan that turns the other way
    simply runs backwards on it.
``acq_time``
    Timestamp: the acquisition time of the sample (``Sample.acquisition_time_ns``).
    The only timeline on which several scans of one recording follow each other.

Entity paths
------------
Every path starts at ``root`` (``"/"`` by default) and then one of the fixed
groups ``world``, ``plots``, ``log`` — so one :func:`default_blueprint` fits
any number of scans — followed by the scanner and the scan, so that several
scans (and scanners) in one recording never write to the same entity::

    world                                          ViewCoordinates RIGHT_HAND_Z_UP (static)
    world/{scanner}/array                          Transform3D, rotation γ about x
    world/{scanner}/array/capsules                 Points3D in the array frame (static)
    world/{scanner}/array/boresight                Arrows3D, the beam direction (static)
    world/{scanner}/truth/{label}                  Mesh3D, the true planes (static, grey)
    world/{scanner}/scans/{scan}/raw               Points3D, all raw points so far (eq. 9)
    world/{scanner}/scans/{scan}/beams             Arrows3D, capsule → echo of the current step
    world/{scanner}/scans/{scan}/corrected/{label} Points3D, outliers red and bigger
    world/{scanner}/scans/{scan}/planes/{method}/{label}         Mesh3D patch
    world/{scanner}/scans/{scan}/planes/{method}/{label}/normal  Arrows3D, labelled with the verdict
    world/{scanner}/scans/{scan}/planes/{method}/{label}/quality LineStrips3D outline: green good,
                                                   amber degraded, red unreliable
    world/{scanner}/scans/{scan}/planes/{method}/{label}/uncertainty/offset_band  the patch at ±2σ_h
    world/{scanner}/scans/{scan}/planes/{method}/{label}/uncertainty/normal_cone  Arrows3D at 2σ_n
    world/{scanner}/scans/{scan}/edge              LineStrips3D, labelled with its ± mm
    world/{scanner}/scans/{scan}/critical          LineStrips3D, the critical direction
    plots/energy/{scanner}/{scan}                  Scalars [E^γ, E0(d_m)]
    plots/ratio/{scanner}/{scan}/R                 Scalars
    plots/ratio/{scanner}/{scan}/critical          Scalars, one diamond per critical step found
    plots/waveforms/{scanner}/{scan}               LineStrips2D, one strip per capsule
    plots/errors/{label}/{scanner}/{scan}/{method} BarChart of the sorted e_i
    log/{scanner}/{scan}                           TextLog

``{scan}`` is ``scan_{scan_id}``; ids are escaped with
:func:`rerun.escape_entity_path_part`.  The error plots are grouped by plane
label first so that the blueprint can give plane a and plane b a view each.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Sequence

import numpy as np
import rerun as rr

from lelsonar.draw.palette import METHOD_COLORS, method_color
from lelsonar.errors import ConfigError
from lelsonar.reconstruct.estimate.results import EdgeLine, FitFailure, PlaneFit
from lelsonar.view.rerun_layout import (
    ANGLE_TIMELINE,
    STEP_TIMELINE,
    TIME_TIMELINE,
    default_blueprint,
    join_path,
    make_recording,
)
from lelsonar.view.rerun_planes import log_edge, log_plane_fit, log_true_plane
from lelsonar.view.rerun_shapes import (
    SubsetView,
    WaveformStrips,
    capsule_name,
    centidegrees,
    final_estimate_text,
)

__all__ = [
    "STEP_TIMELINE",
    "ANGLE_TIMELINE",
    "TIME_TIMELINE",
    "METHOD_COLORS",
    "method_color",
    "make_recording",
    "default_blueprint",
    "SubsetView",
    "ScanLogger",
]

#: Per-method colours (RGB); methods not listed get a stable colour from the palette.
_PALETTE = [(230, 200, 40), (120, 120, 255), (255, 110, 110), (140, 220, 220), (200, 160, 100)]
_SUBSET_COLORS = {"a": (60, 120, 240), "b": (160, 70, 210)}
_OUTLIER_RGB = (235, 40, 40)
_RAW_RGB = (200, 200, 200)
_BEAM_RGB = (250, 220, 90)
_CAPSULE_RGB = (255, 200, 0)
_CRITICAL_RGB = (235, 40, 40)
_WAVEFORM_COLORS = [(255, 140, 0), (40, 190, 70), (60, 140, 255), (220, 60, 200)]
_POINT_RADIUS = 0.008  # m
_OUTLIER_RADIUS = 0.016  # m: twice as big, so outliers stand out among inliers
_LEVELS = {
    "trace": rr.TextLogLevel.TRACE,
    "debug": rr.TextLogLevel.DEBUG,
    "info": rr.TextLogLevel.INFO,
    "warn": rr.TextLogLevel.WARN,
    "warning": rr.TextLogLevel.WARN,
    "error": rr.TextLogLevel.ERROR,
    "critical": rr.TextLogLevel.CRITICAL,
}


class ScanLogger:
    """Logs one scan of one scanner to a recording, step by step.

    Parameters
    ----------
    rec : rerun.RecordingStream
        The recording; several loggers (scans, scanners) may share it.
    scanner_id : str
    scan_id : int
    root : str
        Prefix of every entity path (see the module doc); give the same one to
        :func:`default_blueprint`.
    waveform_spacing : float
        Vertical distance between the capsules' waveform baselines, V.
    waveform_points : int or None
        Longer waveforms are drawn as their min/max envelope with about this
        many vertices (``None``: every sample).  At 200 kHz a 40 kHz echo has
        five samples a cycle, so at any screen width the trace is its envelope
        anyway; full 3500-sample windows would make waveforms ~95 % of the file.
    main_method : str or None
        The estimator of record: only its planes carry a text label in 3D (the compared methods'
        would sit on top of it); None labels every method's.

    Notes
    -----
    Cost: :meth:`step` makes six log calls (pose, raw points, beams, waveforms,
    energy, ratio).  The raw points are logged as the whole
    cloud received so far, at every step, so that the latest-at view of any
    timeline shows the scan up to the cursor without a blueprint time range
    (which would also pile up every past plane estimate, and needs exact
    entity paths the blueprint cannot know for a recording of many scans).
    Serialisation cost does not depend on the number of points here; the file
    grows by about 12 bytes · points so far per step (≈1.2 MB for 220 steps).

    Several scans in one recording write to different entities.  On the
    ``step`` and ``gamma_cdeg`` timelines they overlay (handy to compare two
    scans; hide one in the blueprint panel otherwise); on ``acq_time`` they
    follow each other, and an earlier scan's last state stays drawn.

    Not thread-safe: call one logger from one thread (Rerun's time cursor is
    per thread, and each method sets all of its timelines itself).
    """

    def __init__(
        self,
        rec: rr.RecordingStream,
        scanner_id: str,
        scan_id: int,
        *,
        root: str = "/",
        waveform_spacing: float = 1.0,
        waveform_points: int | None = 1000,
        main_method: str | None = None,
    ) -> None:
        if not (np.isfinite(waveform_spacing) and waveform_spacing > 0):
            raise ConfigError(f"waveform_spacing must be > 0 V, got {waveform_spacing!r}")
        if waveform_points is not None and waveform_points < 16:
            raise ConfigError(f"waveform_points must be >= 16 or None, got {waveform_points!r}")
        self.waveform_points = waveform_points
        self.main_method = main_method
        self.rec = rec
        self.scanner_id = str(scanner_id)
        self.scan_id = int(scan_id)
        self.root = root
        self.waveform_spacing = float(waveform_spacing)
        scanner = rr.escape_entity_path_part(self.scanner_id)
        scan = f"scan_{self.scan_id}"
        self._scanner, self._scan = scanner, scan
        self.world = join_path(root, "world")
        self.array = join_path(root, "world", scanner, "array")
        self.scan_world = join_path(root, "world", scanner, "scans", scan)
        self.energy = join_path(root, "plots", "energy", scanner, scan)
        self.ratio = join_path(root, "plots", "ratio", scanner, scan, "R")
        self.critical = join_path(root, "plots", "ratio", scanner, scan, "critical")
        self.waveforms = join_path(root, "plots", "waveforms", scanner, scan)
        self.log_path = join_path(root, "log", scanner, scan)

        self._cloud = np.empty((0, 3), dtype=np.float32)
        self._n_cloud = 0
        self._seen: set[int] = set()
        self._gamma: dict[int, float] = {}
        self._t_ns: dict[int, int] = {}
        self._ratio: dict[int, float] = {}
        self._clock: tuple[int | None, float | None, int | None] = (None, None, None)
        self._marked_critical: int | None = None
        self._reported: dict[str, str] = {}  # what was last said about each plane/edge failure
        self._drawn: set[tuple[str, str]] = set()  # (method, label) patches on screen
        self._strips = WaveformStrips(self.waveform_spacing, waveform_points)

        rec.log(self.world, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        rec.log(
            self.energy,
            rr.SeriesLines(names=["E^γ, V²·s", "E0(d_m), V²·s"], colors=[(60, 140, 255), (160, 160, 160)]),
            static=True,
        )
        rec.log(self.ratio, rr.SeriesLines(names="R", colors=(255, 140, 0)), static=True)
        rec.log(
            self.critical,
            rr.SeriesPoints(names="critical step", colors=_CRITICAL_RGB, markers="diamond", marker_sizes=8.0),
            static=True,
        )
        # Styles that never change are static, so step() sends only positions.
        rec.log(f"{self.scan_world}/raw", rr.Points3D.from_fields(colors=_RAW_RGB, radii=0.006), static=True)
        rec.log(f"{self.scan_world}/beams", rr.Arrows3D.from_fields(colors=_BEAM_RGB, radii=0.002), static=True)

    # -- time -----------------------------------------------------------------

    def _at(self, step: int | None, gamma: float | None, t_ns: int | None) -> None:
        """Set exactly the given timelines (and clear any others left on this thread)."""
        rec = self.rec
        rec.reset_time()
        if step is not None:
            rec.set_time(STEP_TIMELINE, sequence=int(step))
        if gamma is not None and math.isfinite(gamma):
            rec.set_time(ANGLE_TIMELINE, sequence=centidegrees(gamma))
        if t_ns is not None:
            rec.set_time(TIME_TIMELINE, timestamp=np.datetime64(int(t_ns), "ns"))
        self._clock = (step, gamma, t_ns)

    # -- scan -----------------------------------------------------------------

    def scan_started(
        self,
        t_ns: int,
        gamma_start: float,
        gamma_stop: float,
        steps: int,
        capsule_positions_array_frame: np.ndarray,
        info_text: str,
    ) -> None:
        """Log the scan's constants and a start event.

        Parameters
        ----------
        t_ns : int
            Start time of the scan, ns since the epoch.
        gamma_start, gamma_stop : float
            Rotation range, rad.
        steps : int
            Planned number of steps.
        capsule_positions_array_frame : (k, 3) array
            Capsule positions in the array frame, m.
        info_text : str
            Free text for the event log (software, sound speed, ...).
        """
        rec = self.rec
        # Copies: Rerun would otherwise keep a view of the caller's array until it flushes.
        caps = np.array(capsule_positions_array_frame, dtype=np.float64).reshape(-1, 3)
        k = caps.shape[0]
        names = [capsule_name(i) for i in range(k)]
        rec.log(
            f"{self.array}/capsules", rr.Points3D(caps, radii=0.012, colors=_CAPSULE_RGB, labels=names), static=True
        )
        centre = caps.mean(axis=0) if k else np.zeros(3)
        rec.log(
            f"{self.array}/boresight",
            rr.Arrows3D(origins=[centre], vectors=[[0.0, 0.3, 0.0]], colors=_CAPSULE_RGB, radii=0.004),
            static=True,
        )
        colors = [_WAVEFORM_COLORS[i % len(_WAVEFORM_COLORS)] for i in range(k)]
        rec.log(self.waveforms, rr.LineStrips2D.from_fields(labels=names, colors=colors), static=True)

        self._at(0, gamma_start, t_ns)
        text = (
            f"scan {self.scan_id} of {self.scanner_id} started: γ {math.degrees(gamma_start):.1f}° → "
            f"{math.degrees(gamma_stop):.1f}° in {steps} steps, {k} capsules"
        )
        if info_text:
            text += f"\n{info_text}"
        rec.log(self.log_path, rr.TextLog(text, level=rr.TextLogLevel.INFO))

    def step(
        self,
        step: int,
        t_ns: int,
        gamma: float,
        raw_points: np.ndarray,
        capsule_positions: np.ndarray,
        waveforms: np.ndarray,
        sample_rate: float,
        t0: float,
        energy: float,
        expected_energy: float,
        ratio: float,
    ) -> None:
        """Log one step: array pose, raw points so far, beams, waveforms, E^γ, E0(d_m), R.

        Parameters
        ----------
        step : int
        t_ns : int
            Acquisition time, ns since the epoch.
        gamma : float
            Measured rotation, rad.
        raw_points : (k, 3) array
            This step's points of eq. (9), world frame, m; rows with a NaN (no
            echo) are dropped.
        capsule_positions : (k, 3) array
            The capsules in the world frame at this step, m (beam origins).
        waveforms : (k, n) array
            Echo waveforms, V.
        sample_rate : float
            Hz.
        t0 : float
            Time of the first waveform sample after the ping, s.
        energy, expected_energy, ratio : float
            ``E^γ`` (eq. 11), ``E0(d_m)`` (eq. 12), both V²·s, and ``R``.
        """
        rec = self.rec
        step = int(step)
        self._at(step, gamma, t_ns)
        self._gamma[step] = float(gamma)
        self._t_ns[step] = int(t_ns)
        self._ratio[step] = float(ratio)

        if math.isfinite(gamma):  # an unread encoder leaves the pose where it was
            # Rotation about x by γ, parent (world) from child (array): p_world = R_x(γ) p_array.
            half = 0.5 * float(gamma)
            rec.log(
                self.array, rr.Transform3D(quaternion=rr.Quaternion(xyzw=[math.sin(half), 0.0, 0.0, math.cos(half)]))
            )

        pts = np.asarray(raw_points, dtype=np.float64).reshape(-1, 3)
        echo = np.isfinite(pts).all(axis=1)
        pts = pts[echo]
        if step not in self._seen:  # a repeated step is drawn once
            self._seen.add(step)
            self._append_cloud(pts)
        rec.log(f"{self.scan_world}/raw", rr.Points3D(self._cloud[: self._n_cloud]))
        origins = np.asarray(capsule_positions, dtype=np.float64).reshape(-1, 3)[echo]
        # Logged even when empty so the last step's beams do not linger.
        rec.log(f"{self.scan_world}/beams", rr.Arrows3D(origins=origins, vectors=pts - origins))

        w = np.asarray(waveforms, dtype=np.float32)
        if w.ndim == 2 and w.shape[1] > 0 and sample_rate > 0:
            rec.log(self.waveforms, rr.LineStrips2D(self._strips(w, float(sample_rate), float(t0))))

        rec.log(self.energy, rr.Scalars([energy, expected_energy]))
        rec.log(self.ratio, rr.Scalars(ratio))

    def _append_cloud(self, pts: np.ndarray) -> None:
        # Rerun holds zero-copy views of logged slices until it flushes: only ever write
        # rows past the logged ones, and grow into a new buffer, never in place.
        n = self._n_cloud + pts.shape[0]
        if n > self._cloud.shape[0]:
            grown = np.empty((max(n, 2 * self._cloud.shape[0], 256), 3), dtype=np.float32)
            grown[: self._n_cloud] = self._cloud[: self._n_cloud]
            self._cloud = grown
        self._cloud[self._n_cloud : n] = pts
        self._n_cloud = n

    # -- estimates ------------------------------------------------------------

    def estimate(
        self,
        step: int,
        t_ns: int,
        planes: Sequence[PlaneFit | FitFailure],
        edge: EdgeLine | FitFailure | None,
        subsets: Sequence[SubsetView],
        critical_step: int | None,
        critical_gamma: float | None,
        final: bool,
    ) -> None:
        """Log an estimate made after ``step``: planes, edge, corrected points, errors, critical step.

        Parameters
        ----------
        step : int
            The last step the estimate used (its position on the timelines).
        t_ns : int
            Acquisition time of that step, ns.
        planes : sequence of PlaneFit or FitFailure
            Any number of methods.  A failure (which names no method) takes
            down the old patches of its label that this estimate did not
            redraw, and is reported once as a warning (again when final).
        edge : EdgeLine, FitFailure or None
            ``None`` leaves the edge as it was.
        subsets : sequence of SubsetView
            Corrected points per plane label, with their inlier masks.
        critical_step : int or None
        critical_gamma : float or None
            γ of the critical step, rad.
        final : bool
            Whether this is the scan's final estimate (logged as an event).
        """
        rec = self.rec
        step = int(step)
        self._at(step, self._gamma.get(step), t_ns)

        for sub in subsets:
            inl = sub.inlier_mask
            ok = np.isfinite(sub.points).all(axis=1)
            base = _SUBSET_COLORS.get(sub.label, _PALETTE[zlib.crc32(sub.label.encode()) % len(_PALETTE)])
            colors = np.where(inl[ok, None], np.array(base, np.uint8), np.array(_OUTLIER_RGB, np.uint8))
            radii = np.where(inl[ok], _POINT_RADIUS, _OUTLIER_RADIUS).astype(np.float32)
            rec.log(
                f"{self.scan_world}/corrected/{rr.escape_entity_path_part(sub.label)}",
                rr.Points3D(sub.points[ok], colors=colors, radii=radii),
            )

        fits = [p for p in planes if isinstance(p, PlaneFit)]
        fitted = {(p.method, p.label) for p in fits}
        if final:  # the final planes only: the provisional estimates' patches go
            for method, label in sorted(self._drawn - fitted):
                self._clear_plane(method, label)
        for p in fits:
            self._log_plane(p)
            self._drawn.add((p.method, p.label))
        for f in planes:
            if isinstance(f, FitFailure):
                # A FitFailure does not name its method: take down every patch of that
                # label this estimate did not redraw, so no stale plane stays on screen.
                for method, label in sorted(self._drawn):
                    if label == f.label and (method, label) not in fitted:
                        self._clear_plane(method, label)
                self._note_failure(f"plane/{f.label}", f"plane {f.label} not fitted: {f}", final)

        if isinstance(edge, EdgeLine):
            self._reported.pop("edge", None)
            self._log_edge(edge, fits)
        elif isinstance(edge, FitFailure):
            rec.log(f"{self.scan_world}/edge", rr.Clear(recursive=False))
            self._note_failure("edge", f"edge: {edge}", final)

        if critical_step is not None and critical_gamma is not None and math.isfinite(critical_gamma):
            self._log_critical(int(critical_step), float(critical_gamma), final)

        if final:
            untrusted = any(isinstance(p, PlaneFit) and p.quality in ("degraded", "unreliable") for p in planes)
            rec.log(
                self.log_path,
                rr.TextLog(
                    final_estimate_text(self.scan_id, step, planes, edge),
                    level=rr.TextLogLevel.WARN if untrusted else rr.TextLogLevel.INFO,
                ),
            )

    def accounting(self, status: str, text: str, missing_steps: Sequence[int] = ()) -> None:
        """One TextLog line with where every sample of the scan went (WARN when steps are missing)."""
        line = f"accounting ({status}): {text}"
        if len(missing_steps):
            shown = ", ".join(str(int(s)) for s in list(missing_steps)[:40])
            line += f"; missing steps {shown}{' …' if len(missing_steps) > 40 else ''}"
        self.rec.log(
            self.log_path, rr.TextLog(line, level=rr.TextLogLevel.WARN if len(missing_steps) else rr.TextLogLevel.INFO)
        )

    def _clear_plane(self, method: str, label: str) -> None:
        self.rec.log(self._plane_path(method, label), rr.Clear(recursive=True))
        self.rec.log(self._errors_path(method, label), rr.Clear(recursive=False))
        self._drawn.discard((method, label))

    def _plane_path(self, method: str, label: str) -> str:
        return f"{self.scan_world}/planes/{rr.escape_entity_path_part(method)}/{rr.escape_entity_path_part(label)}"

    def _log_plane(self, p: PlaneFit) -> None:
        log_plane_fit(self.rec, self._plane_path(p.method, p.label), p, self.main_method)
        self.rec.log(
            self._errors_path(p.method, p.label), rr.BarChart(p.sorted_residuals, color=method_color(p.method))
        )

    def _errors_path(self, method: str, label: str) -> str:
        return join_path(
            self.root,
            "plots",
            "errors",
            rr.escape_entity_path_part(label),
            self._scanner,
            self._scan,
            rr.escape_entity_path_part(method),
        )

    def _note_failure(self, key: str, text: str, final: bool) -> None:
        """A plane or edge not fitted: a warning on the final estimate; before it, an expected state (the
        beams have not reached wall b yet), said once at DEBUG level."""
        if self._reported.get(key) == text and not final:
            return
        self._reported[key] = text
        level = rr.TextLogLevel.WARN if final else rr.TextLogLevel.DEBUG
        self.rec.log(self.log_path, rr.TextLog(("final: " if final else "so far: ") + text, level=level))

    def _log_edge(self, edge: EdgeLine, fits: Sequence[PlaneFit]) -> None:
        log_edge(self.rec, f"{self.scan_world}/edge", edge, fits)

    def _log_critical(self, critical_step: int, critical_gamma: float, final: bool) -> None:
        rec = self.rec
        c, s = math.cos(critical_gamma), math.sin(critical_gamma)
        # The critical direction as a fan line from the axis, at the array's ends.
        rec.log(
            f"{self.scan_world}/critical",
            rr.LineStrips3D(
                [[[x, 0.0, 0.0], [x, 2.5 * c, 2.5 * s]] for x in (-0.15, 0.15)],
                colors=_CRITICAL_RGB,
                radii=0.002,
                labels=[f"critical γ = {math.degrees(critical_gamma):.1f}°", ""],
            ),
        )
        if critical_step == self._marked_critical and not final:
            return
        clock = self._clock
        r = self._ratio.get(critical_step)
        if critical_step != self._marked_critical and r is not None and math.isfinite(r):
            # The marker goes on R at the critical step itself, back in time.
            self._at(critical_step, critical_gamma, self._t_ns.get(critical_step))
            rec.log(self.critical, rr.Scalars(r))
            self._at(*clock)
        self._marked_critical = critical_step
        r_text = f", R = {r:.3g}" if r is not None else ""
        rec.log(
            self.log_path,
            rr.TextLog(
                f"{'final ' if final else ''}critical step {critical_step} at γ = "
                f"{math.degrees(critical_gamma):.2f}°{r_text}",
                level=rr.TextLogLevel.INFO,
            ),
        )

    # -- truth and events -----------------------------------------------------

    def truth(self, planes: Sequence[tuple[str, np.ndarray, float, np.ndarray]]) -> None:
        """Log the true planes as static grey patches.

        Parameters
        ----------
        planes : sequence of (label, normal, offset, corners)
            ``normal`` (3,) unit, ``offset`` m, ``corners`` (4, 3) in order
            around the patch, m.
        """
        for label, normal, offset, corners in planes:
            path = join_path(self.root, "world", self._scanner, "truth", rr.escape_entity_path_part(label))
            log_true_plane(self.rec, path, label, normal, offset, corners)

    def event(self, level: str, text: str, t_ns: int | None = None) -> None:
        """Log a text event at the current step.

        Parameters
        ----------
        level : str
            ``"trace"``, ``"debug"``, ``"info"``, ``"warn"``/``"warning"``,
            ``"error"`` or ``"critical"`` (any case); anything else is passed
            through upper-cased.
        text : str
        t_ns : int or None
            Acquisition time; ``None`` uses that of the last logged step.
        """
        step, gamma, last_t = self._clock
        self._at(step, gamma, last_t if t_ns is None else t_ns)
        lvl = _LEVELS.get(level.lower(), level.upper())
        self.rec.log(self.log_path, rr.TextLog(text, level=lvl))
