"""The shapes the Rerun view draws, computed from a scan's numbers: pure functions, no logging."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lelsonar.errors import ConfigError
from lelsonar.reconstruct.estimate.results import EdgeLine, PlaneFit

__all__ = [
    "SubsetView",
    "WaveformStrips",
    "cone",
    "centidegrees",
    "min_max_envelope",
    "capsule_name",
    "final_estimate_text",
]


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


def cone(normal: np.ndarray, half_angle: float, n: int = 8) -> np.ndarray:
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


def centidegrees(gamma: float) -> int:
    return int(round(math.degrees(gamma) * 100.0))


def min_max_envelope(w: np.ndarray, bin_: int) -> np.ndarray:
    """(k, n) → (k, 2·(n // bin_)): each bin's min then max.

    Element-wise passes over the bin's columns: numpy's ``min(axis=-1)`` over a
    short last axis costs far more, and this runs at every step.
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


def capsule_name(i: int) -> str:
    # The paper names the capsules A, B, C, D (Fig. 1).
    return chr(ord("A") + i) if i < 26 else str(i)


class WaveformStrips:
    """The four waveforms of a step as stacked 2D strips, their time axis made once per window.

    Parameters
    ----------
    spacing : float
        Vertical distance between the capsules' baselines, V.
    points : int or None
        Longer waveforms become their min/max envelope with about this many vertices (None: every sample).
    """

    def __init__(self, spacing: float, points: int | None) -> None:
        self.waveform_spacing = float(spacing)
        self.waveform_points = points
        self._strip_key: tuple[int, int, float, float] | None = None
        self._strip_x = np.empty(0, dtype=np.float32)
        self._bin = 1
        self._baselines = np.empty((0, 1), dtype=np.float32)

    def __call__(self, w: np.ndarray, sample_rate: float, t0: float) -> np.ndarray:
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
            w = min_max_envelope(w, self._bin)
        # A fresh array every time: Rerun keeps a zero-copy view of what it is given until
        # the batch is flushed, so reusing a buffer would rewrite earlier steps' waveforms.
        strips = np.empty((k, w.shape[1], 2), dtype=np.float32)
        strips[:, :, 0] = self._strip_x
        # 2D views point y down: negate so positive volts go up; capsule i sits at y = i·spacing.
        np.subtract(self._baselines, w, out=strips[:, :, 1])
        return strips


def final_estimate_text(scan_id: int, step: int, planes, edge) -> str:
    """The event line of a final estimate: each plane with its uncertainty and verdict, and the edge."""
    lines = [f"final estimate of scan {scan_id} after step {step}"]
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
    return "\n".join(lines)
