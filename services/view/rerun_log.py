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
from dataclasses import dataclass

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from lelsonar.draw.palette import METHOD_COLORS, method_color, quality_color
from lelsonar.errors import ConfigError
from lelsonar.reconstruct.estimate.results import EdgeLine, FitFailure, PlaneFit

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

STEP_TIMELINE = "step"
#: γ in hundredths of a degree (a sequence timeline, see the module doc).
ANGLE_TIMELINE = "gamma_cdeg"
TIME_TIMELINE = "acq_time"

#: Per-method colours (RGB); methods not listed get a stable colour from the palette.
_PALETTE = [(230, 200, 40), (120, 120, 255), (255, 110, 110), (140, 220, 220), (200, 160, 100)]
_PLANE_ALPHA = 110  # patches stay see-through so points behind them show
_TRUTH_RGBA = (160, 160, 160, 80)
_SUBSET_COLORS = {"a": (60, 120, 240), "b": (160, 70, 210)}
_OUTLIER_RGB = (235, 40, 40)
_RAW_RGB = (200, 200, 200)
_BEAM_RGB = (250, 220, 90)
_CAPSULE_RGB = (255, 200, 0)
_EDGE_RGB = (255, 255, 255)
_CRITICAL_RGB = (235, 40, 40)
_WAVEFORM_COLORS = [(255, 140, 0), (40, 190, 70), (60, 140, 255), (220, 60, 200)]
_POINT_RADIUS = 0.008  # m
_OUTLIER_RADIUS = 0.016  # m: twice as big, so outliers stand out among inliers
_NORMAL_LENGTH = 0.25  # m
_LEVELS = {
    "trace": rr.TextLogLevel.TRACE,
    "debug": rr.TextLogLevel.DEBUG,
    "info": rr.TextLogLevel.INFO,
    "warn": rr.TextLogLevel.WARN,
    "warning": rr.TextLogLevel.WARN,
    "error": rr.TextLogLevel.ERROR,
    "critical": rr.TextLogLevel.CRITICAL,
}


def make_recording(application_id: str = "lelsonar", recording_id: str | None = None) -> rr.RecordingStream:
    """A new recording stream without sinks.

    Parameters
    ----------
    application_id : str
        Groups recordings in the viewer.
    recording_id : str or None
        Recordings with the same id are merged by the viewer; ``None`` makes a
        fresh random one.

    Returns
    -------
    rerun.RecordingStream
        Give it sinks before logging, e.g. ``rec.save(path,
        default_blueprint=default_blueprint())``, ``rec.serve_grpc()``,
        ``rec.spawn()`` or ``rec.set_sinks(rr.FileSink(path))``; data logged
        before that is buffered.
    """
    return rr.RecordingStream(application_id, recording_id=recording_id)


def _join(root: str, *parts: str) -> str:
    """``root`` + ``parts`` as an entity path (parts are already escaped)."""
    base = "/" + root.strip("/") if root.strip("/") else ""
    return base + "/" + "/".join(parts)


def default_blueprint(root: str = "/") -> rrb.Blueprint:
    """The default layout: the world on the left, the plots in a column on the right.

    Parameters
    ----------
    root : str
        The ``root`` the :class:`ScanLogger` instances were given.

    Returns
    -------
    rerun.blueprint.Blueprint
        ``Horizontal(3D "world" | Vertical(energy, ratio R, waveforms,
        Horizontal(sorted errors a | sorted errors b), events))`` with the
        world taking 3/5 of the width, the blueprint and selection panels
        collapsed and the ``step`` timeline active.
    """

    def at(*parts: str) -> str:
        return _join(root, *parts)

    column = rrb.Vertical(
        rrb.TimeSeriesView(name="energy E^γ and E0(d_m)", origin=at("plots", "energy")),
        rrb.TimeSeriesView(name="ratio R = E^γ / E0(d_m)", origin=at("plots", "ratio")),
        rrb.Spatial2DView(
            name="waveforms of the step (ms; volts up, capsule i at i·spacing)", origin=at("plots", "waveforms")
        ),
        rrb.Horizontal(
            rrb.BarChartView(name="sorted errors e_i, plane a", origin=at("plots", "errors", "a")),
            rrb.BarChartView(name="sorted errors e_i, plane b", origin=at("plots", "errors", "b")),
        ),
        rrb.TextLogView(name="events", origin=at("log")),
        row_shares=[1.0, 1.0, 1.0, 1.0, 0.8],
    )
    return rrb.Blueprint(
        rrb.Horizontal(rrb.Spatial3DView(name="world", origin=at("world")), column, column_shares=[3.0, 2.0]),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(timeline=STEP_TIMELINE),
        auto_views=False,
    )


@dataclass(frozen=True)
class SubsetView:
    """The corrected points a fit used, for colouring.

    Parameters
    ----------
    label : str
        ``"a"`` or ``"b"``.
    points : (m, 3) array
        Corrected points, world frame, m.  Rows with a NaN are not drawn.
    inlier_mask : (m,) bool array
        ``False`` marks an outlier (drawn red and bigger).
    """

    label: str
    points: np.ndarray
    inlier_mask: np.ndarray

    def __post_init__(self) -> None:
        points = np.array(self.points, dtype=np.float64, copy=True)
        mask = np.array(self.inlier_mask, dtype=bool, copy=True)
        if points.ndim != 2 or points.shape[1] != 3:
            raise ConfigError(f"SubsetView.points must have shape (m, 3), got {points.shape}")
        if mask.shape != (points.shape[0],):
            raise ConfigError(f"SubsetView.inlier_mask must have shape ({points.shape[0]},), got {mask.shape}")
        points.setflags(write=False)
        mask.setflags(write=False)
        object.__setattr__(self, "points", points)
        object.__setattr__(self, "inlier_mask", mask)


def _cone(normal: np.ndarray, half_angle: float, n: int = 8) -> np.ndarray:
    """``n`` unit vectors at ``half_angle`` (rad) around ``normal``: the edge of its uncertainty cone."""
    helper = np.zeros(3)
    helper[int(np.argmin(np.abs(normal)))] = 1.0
    e1 = np.cross(normal, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    phi = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    a = min(float(half_angle), np.pi / 4)
    return np.cos(a) * normal[None, :] + np.sin(a) * (
        np.cos(phi)[:, None] * e1[None, :] + np.sin(phi)[:, None] * e2[None, :]
    )


def _centidegrees(gamma: float) -> int:
    return int(round(math.degrees(gamma) * 100.0))


def _min_max_envelope(w: np.ndarray, bin_: int) -> np.ndarray:
    """(k, n) → (k, 2·(n // bin_)): each bin's min then max.

    Element-wise passes over the bin's columns: numpy's ``min(axis=-1)`` over a
    short last axis is several times slower, and this runs at every step.
    """
    k, n = w.shape
    binned = w[:, : (n // bin_) * bin_].reshape(k, n // bin_, bin_)
    out = np.empty((k, n // bin_, 2), dtype=np.float32)
    lo, hi = out[:, :, 0], out[:, :, 1]
    lo[...] = binned[:, :, 0]
    hi[...] = binned[:, :, 0]
    for j in range(1, bin_):
        np.minimum(lo, binned[:, :, j], out=lo)
        np.maximum(hi, binned[:, :, j], out=hi)
    return out.reshape(k, -1)


def _capsule_name(i: int) -> str:
    # The paper names the capsules A, B, C, D (Fig. 1).
    return chr(ord("A") + i) if i < 26 else str(i)


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
    ) -> None:
        if not (np.isfinite(waveform_spacing) and waveform_spacing > 0):
            raise ConfigError(f"waveform_spacing must be > 0 V, got {waveform_spacing!r}")
        if waveform_points is not None and waveform_points < 16:
            raise ConfigError(f"waveform_points must be >= 16 or None, got {waveform_points!r}")
        self.waveform_points = waveform_points
        self.rec = rec
        self.scanner_id = str(scanner_id)
        self.scan_id = int(scan_id)
        self.root = root
        self.waveform_spacing = float(waveform_spacing)
        scanner = rr.escape_entity_path_part(self.scanner_id)
        scan = f"scan_{self.scan_id}"
        self._scanner, self._scan = scanner, scan
        self.world = _join(root, "world")
        self.array = _join(root, "world", scanner, "array")
        self.scan_world = _join(root, "world", scanner, "scans", scan)
        self.energy = _join(root, "plots", "energy", scanner, scan)
        self.ratio = _join(root, "plots", "ratio", scanner, scan, "R")
        self.critical = _join(root, "plots", "ratio", scanner, scan, "critical")
        self.waveforms = _join(root, "plots", "waveforms", scanner, scan)
        self.log_path = _join(root, "log", scanner, scan)

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
        self._strip_key: tuple[int, int, float, float] | None = None
        self._strip_x = np.empty(0, dtype=np.float32)
        self._bin = 1
        self._baselines = np.empty((0, 1), dtype=np.float32)

        rec.log(self.world, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        rec.log(
            self.energy, rr.SeriesLines(names=["E^γ", "E0(d_m)"], colors=[(60, 140, 255), (160, 160, 160)]), static=True
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
            rec.set_time(ANGLE_TIMELINE, sequence=_centidegrees(gamma))
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
        names = [_capsule_name(i) for i in range(k)]
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
            rec.log(self.waveforms, rr.LineStrips2D(self._waveform_strips(w, float(sample_rate), float(t0))))

        rec.log(self.energy, rr.Scalars([energy, expected_energy]))
        rec.log(self.ratio, rr.Scalars(ratio))

    def _waveform_strips(self, w: np.ndarray, sample_rate: float, t0: float) -> np.ndarray:
        """(k, m, 2) float32 strips: x = time after the ping in ms, y = stacked, negated volts."""
        k, n = w.shape
        key = (k, n, sample_rate, t0)
        if self._strip_key != key:  # the window is the same for a whole scan: compute the axes once
            self._strip_key = key
            t_ms = (t0 + np.arange(n) / sample_rate) * 1e3
            self._bin = 1 if self.waveform_points is None else max(1, -(-2 * n // self.waveform_points))
            if self._bin > 1:
                # Each bin becomes two vertices, its min then its max, at the bin's first
                # and last sample times: the envelope keeps every peak of the echo.  The
                # last n mod bin samples (< bin, tens of µs after the window) are dropped.
                n_bins = n // self._bin
                t_bins = t_ms[: n_bins * self._bin].reshape(n_bins, self._bin)
                t_ms = np.stack([t_bins[:, 0], t_bins[:, -1]], axis=1).reshape(-1)
            self._strip_x = t_ms.astype(np.float32)
            self._baselines = np.arange(k, dtype=np.float32)[:, None] * np.float32(self.waveform_spacing)
        if self._bin > 1:
            w = _min_max_envelope(w, self._bin)
        # A fresh array every time: Rerun keeps a zero-copy view of what it is given until
        # the batch is flushed, so reusing a buffer would rewrite earlier steps' waveforms.
        strips = np.empty((k, w.shape[1], 2), dtype=np.float32)
        strips[:, :, 0] = self._strip_x
        # 2D views point y down: negate so positive volts go up; capsule i sits at y = i·spacing.
        np.subtract(self._baselines, w, out=strips[:, :, 1])
        return strips

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
        for fit in fits:
            self._log_plane(fit)
            self._drawn.add((fit.method, fit.label))
        fitted = {(p.method, p.label) for p in fits}
        for f in planes:
            if isinstance(f, FitFailure):
                # A FitFailure does not name its method: take down every patch of that
                # label this estimate did not redraw, so no stale plane stays on screen.
                for method, label in sorted(self._drawn):
                    if label == f.label and (method, label) not in fitted:
                        rec.log(self._plane_path(method, label), rr.Clear(recursive=True))
                        rec.log(self._errors_path(method, label), rr.Clear(recursive=False))
                        self._drawn.discard((method, label))
                self._warn_once(f"plane/{f.label}", f"plane fit failed: {f}", final)

        if isinstance(edge, EdgeLine):
            self._reported.pop("edge", None)
            self._log_edge(edge, fits)
        elif isinstance(edge, FitFailure):
            rec.log(f"{self.scan_world}/edge", rr.Clear(recursive=False))
            self._warn_once("edge", f"edge: {edge}", final)

        if critical_step is not None and critical_gamma is not None and math.isfinite(critical_gamma):
            self._log_critical(int(critical_step), float(critical_gamma), final)

        if final:
            lines = [f"final estimate of scan {self.scan_id} after step {step}"]
            for p in planes:
                if isinstance(p, PlaneFit):
                    n = p.normal
                    lines.append(
                        f"  {p.method} {p.label}: n = ({n[0]:+.4f}, {n[1]:+.4f}, {n[2]:+.4f}) "
                        f"± {math.degrees(p.normal_stderr):.2f}°, h = {p.offset:.4f} "
                        f"± {p.offset_stderr * 1e3:.1f} mm, σ = {p.sigma * 1e3:.1f} mm, "
                        f"{p.n_inliers}/{p.n_points} inliers, {p.quality or 'unassessed'}"
                        + (f" ({'; '.join(p.quality_reasons)})" if p.quality_reasons else "")
                    )
                else:
                    lines.append(f"  {p.label}: failed, {p.reason.value}")
            if isinstance(edge, EdgeLine):
                lines.append(
                    f"  edge angle {math.degrees(edge.angle):.2f}°, point ± {edge.point_stderr * 1e3:.1f} mm, "
                    f"direction ± {math.degrees(edge.direction_stderr):.2f}°"
                )
            untrusted = any(isinstance(p, PlaneFit) and p.quality in ("degraded", "unreliable") for p in planes)
            rec.log(
                self.log_path,
                rr.TextLog("\n".join(lines), level=rr.TextLogLevel.WARN if untrusted else rr.TextLogLevel.INFO),
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

    def _plane_path(self, method: str, label: str) -> str:
        return f"{self.scan_world}/planes/{rr.escape_entity_path_part(method)}/{rr.escape_entity_path_part(label)}"

    def _log_plane(self, p: PlaneFit) -> None:
        rec = self.rec
        rgb = method_color(p.method)
        path = self._plane_path(p.method, p.label)
        rec.log(
            path,
            rr.Mesh3D(
                vertex_positions=p.patch,
                triangle_indices=[[0, 1, 2], [0, 2, 3]],
                vertex_normals=np.tile(p.normal, (4, 1)),
                albedo_factor=(*rgb, _PLANE_ALPHA),
                face_rendering="DoubleSided",
            ),
        )
        centre = p.patch.mean(axis=0)
        rec.log(
            f"{path}/normal",
            rr.Arrows3D(
                origins=[centre],
                vectors=[p.normal * _NORMAL_LENGTH],
                colors=rgb,
                radii=0.005,
                labels=f"{p.method} {p.label} ({p.quality or 'unassessed'})",
            ),
        )
        # The verdict as the patch's outline: green good, amber degraded, red unreliable.
        outline = np.vstack([p.patch, p.patch[:1]])
        rec.log(
            f"{path}/quality",
            rr.LineStrips3D([outline], colors=quality_color(p.quality), radii=0.004, labels=p.quality or "unassessed"),
        )
        # The uncertainty: the offset band (patch outline at ±2σ_h) and the normal cone (half-angle 2σ_n).
        band = [outline + k * 2.0 * p.offset_stderr * p.normal for k in (-1.0, 1.0)]
        rec.log(f"{path}/uncertainty/offset_band", rr.LineStrips3D(band, colors=rgb, radii=0.0015))
        rec.log(
            f"{path}/uncertainty/normal_cone",
            rr.Arrows3D(
                origins=np.tile(centre, (8, 1)),
                vectors=_cone(p.normal, 2.0 * p.normal_stderr) * _NORMAL_LENGTH,
                colors=rgb,
                radii=0.0015,
            ),
        )
        rec.log(self._errors_path(p.method, p.label), rr.BarChart(p.sorted_residuals, color=rgb))

    def _errors_path(self, method: str, label: str) -> str:
        return _join(
            self.root,
            "plots",
            "errors",
            rr.escape_entity_path_part(label),
            self._scanner,
            self._scan,
            rr.escape_entity_path_part(method),
        )

    def _warn_once(self, key: str, text: str, final: bool) -> None:
        """A warning, unless the same one was already given (estimates repeat every few steps)."""
        if self._reported.get(key) == text and not final:
            return
        self._reported[key] = text
        self.rec.log(self.log_path, rr.TextLog(text, level=rr.TextLogLevel.WARN))

    def _log_edge(self, edge: EdgeLine, fits: Sequence[PlaneFit], half_length: float = 0.5) -> None:
        # Draw ±half_length around the point nearest the origin, but no further than the
        # observed patches reach along the edge (the edge beyond them is extrapolation).
        lo, hi = -half_length, half_length
        if fits:
            t = np.concatenate([(f.patch - edge.point) @ edge.direction for f in fits])
            lo_p, hi_p = max(lo, float(t.min())), min(hi, float(t.max()))
            if hi_p - lo_p > 1e-3:
                lo, hi = lo_p, hi_p
        seg = edge.point + np.outer([lo, hi], edge.direction)
        label = f"edge {math.degrees(edge.angle):.1f}°"
        if math.isfinite(edge.point_stderr):
            label += f" ± {edge.point_stderr * 1e3:.0f} mm"
        self.rec.log(f"{self.scan_world}/edge", rr.LineStrips3D([seg], colors=_EDGE_RGB, radii=0.004, labels=label))

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
            corners = np.array(corners, dtype=np.float64).reshape(4, 3)  # a copy, see scan_started
            n = np.asarray(normal, dtype=np.float64).reshape(3)
            path = _join(self.root, "world", self._scanner, "truth", rr.escape_entity_path_part(label))
            self.rec.log(
                path,
                rr.Mesh3D(
                    vertex_positions=corners,
                    triangle_indices=[[0, 1, 2], [0, 2, 3]],
                    vertex_normals=np.tile(n, (4, 1)),
                    albedo_factor=_TRUTH_RGBA,
                    face_rendering="DoubleSided",
                ),
                static=True,
            )
            self.rec.log(
                f"{path}/normal",
                rr.Arrows3D(
                    origins=[corners.mean(axis=0)],
                    vectors=[n * _NORMAL_LENGTH],
                    colors=_TRUTH_RGBA[:3],
                    radii=0.004,
                    labels=f"truth {label}: h = {float(offset):.3f} m",
                ),
                static=True,
            )

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


# --- a simulated world as truth, and where each scan was ----------------------------------------
_WORLD_RGB = (150, 150, 150)
_BOX_RGB = (190, 160, 110)
_PATH_RGB = (120, 200, 255)
_POSE_RGB = (255, 200, 0)


def log_world_truth(rec: rr.RecordingStream, world: dict, root: str = "/") -> None:
    """A simulated world (a recording's ``truth_world`` metadata) under ``<root>/map/truth``: wall outlines,
    boxes, the robot's true path and poses.  Static: the world does not move."""
    base = _join(root, "map", "truth")
    floor = float(world.get("floor") or 0.0)
    strips = []
    for w in world.get("walls", []):
        (x0, y0), (x1, y1) = w["from"], w["to"]
        z0 = floor + float(w.get("bottom", 0.0))
        z1 = z0 + float(w["height"])
        strips.append([[x0, y0, z0], [x1, y1, z0], [x1, y1, z1], [x0, y0, z1], [x0, y0, z0]])
    if strips:
        rec.log(f"{base}/walls", rr.LineStrips3D(np.array(strips, dtype=np.float64), colors=_WORLD_RGB), static=True)
    boxes = world.get("boxes", [])
    if boxes:
        rec.log(
            f"{base}/boxes",
            rr.Boxes3D(
                centers=[[b["center"][0], b["center"][1], floor + b["size"][2] / 2] for b in boxes],
                half_sizes=[[s / 2 for s in b["size"]] for b in boxes],
                rotation_axis_angles=[rr.RotationAxisAngle(axis=[0, 0, 1], radians=float(b["yaw"])) for b in boxes],
                colors=_BOX_RGB,
                labels=[b.get("name", "") for b in boxes],
            ),
            static=True,
        )
    poses = world.get("poses", [])
    if poses:
        path = np.array([[p["x"], p["y"], floor + 0.01] for p in poses], dtype=np.float64)
        rec.log(f"{base}/path", rr.LineStrips3D([path], colors=_PATH_RGB), static=True)
        heads = np.array([[0.2 * math.cos(p["heading"]), 0.2 * math.sin(p["heading"]), 0.0] for p in poses])
        rec.log(
            f"{base}/poses",
            rr.Arrows3D(origins=path, vectors=heads, colors=_PATH_RGB, labels=[str(i + 1) for i in range(len(poses))]),
            static=True,
        )


def log_scan_pose(
    rec: rr.RecordingStream, scanner_id: str, scan_id: int, position, heading: float, frame_id: str, root: str = "/"
) -> None:
    """Where a scan was (its ``ScanStart`` pose) under ``<root>/map/poses/<scanner>/<scan>``: an arrow along the
    γ = 0 beam, labelled with the pose's frame."""
    p = np.array(position, dtype=np.float64).reshape(1, 3)
    rec.log(
        _join(root, "map", "poses", rr.escape_entity_path_part(scanner_id), str(int(scan_id))),
        rr.Arrows3D(
            origins=p,
            vectors=[[0.25 * math.cos(heading), 0.25 * math.sin(heading), 0.0]],
            colors=_POSE_RGB,
            labels=f"scan {scan_id} ({frame_id})",
        ),
        static=True,
    )
