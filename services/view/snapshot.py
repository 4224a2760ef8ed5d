"""``lelsonar review FILE --screenshot OUT.png``: the review's final step as a still image (matplotlib).

The observer receives what the Rerun observer receives (the same service callbacks, in the same
run), keeps the last scan's points, energies and final planes, and draws them: the scan's raw points
with the final planes of every method and the true planes, and beside them E^γ against E0(d_m) and
R with the critical step.  Only the final planes are drawn, as the review shows them at its last step.
The README's ``docs/review.png`` is made with it, so anyone can remake it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lelsonar import codec
from lelsonar.draw.palette import method_color
from lelsonar.errors import ConfigError
from lelsonar.reconstruct.estimate import wire
from lelsonar.reconstruct.estimate.results import PlaneFit, ScanReconstruction
from lelsonar.reconstruct.stream.assembly import ScanAssembly, StepView
from lelsonar.view.rerun_observer import preset_truth

#: The image formats a screenshot can take, by suffix.
IMAGE_SUFFIXES = (".png", ".pdf", ".svg")


def check_image_path(path: Path) -> Path:
    """``path`` if matplotlib can write it.

    Raises
    ------
    ConfigError
        Another suffix, or matplotlib (the ``plot`` extra) missing.
    """
    if Path(path).suffix.lower() not in IMAGE_SUFFIXES:
        raise ConfigError(f"--screenshot writes {', '.join(IMAGE_SUFFIXES)} files, got {path}")
    try:
        import matplotlib  # noqa: F401 - an optional extra: checked before the replay, not after
    except ImportError:
        raise ConfigError("--screenshot needs matplotlib, an optional extra: pip install 'lelsonar[plot]'") from None
    return Path(path)


@dataclass
class _Scan:
    title: str
    points: dict[int, np.ndarray] = field(default_factory=dict)
    energy: dict[int, tuple[float, float, float]] = field(default_factory=dict)  # step → (E, E0, R)
    planes: list[PlaneFit] = field(default_factory=list)
    critical_step: int | None = None
    status: str = "no final estimate"


class SnapshotObserver:
    """Implements :class:`lelsonar.reconstruct.stream.service.Observer`; :meth:`save` draws the last scan.

    Parameters
    ----------
    main_method : str
        The estimator of record (its planes drawn opaque, the compared ones see-through).
    truth_preset : str, optional
        A simulator preset whose true planes are drawn in grey.
    """

    def __init__(self, main_method: str, truth_preset: str | None = None) -> None:
        self.main_method = main_method
        self.truth = preset_truth(truth_preset) if truth_preset else None
        self._scans: dict[tuple[str, int], _Scan] = {}
        self._last: _Scan | None = None

    def _scan(self, scan: ScanAssembly) -> _Scan:
        s = self._scans.get(scan.key)
        if s is None:
            s = self._scans[scan.key] = _Scan(f"{scan.start.scanner_id} scan {scan.start.scan_id}")
        self._last = s
        return s

    def scan_started(self, scan: ScanAssembly) -> None:
        self._scan(scan)

    def step(self, scan: ScanAssembly, view: StepView, energy: float, expected: float, ratio: float) -> None:
        s = self._scan(scan)
        pts = np.asarray(scan.raw_points(view.step), dtype=float).reshape(-1, 3)
        s.points[view.step] = pts[np.isfinite(pts).all(axis=1)]
        s.energy[view.step] = (float(energy), float(expected), float(ratio))

    def estimate(
        self,
        scan: ScanAssembly,
        message: codec.Reconstruction,
        results: dict[str, ScanReconstruction] | None,
        partial,
    ) -> None:
        if results is None:  # provisional: the screenshot shows the final state only
            return
        s = self._scan(scan)
        s.planes = [p for r in results.values() for p in r.planes if isinstance(p, PlaneFit)]
        s.critical_step = int(message.critical_step) if message.HasField("critical_step") else None
        s.status = wire.status_name(message)

    def event(self, level: str, text: str, time_ns: int | None = None) -> None:
        pass

    def save(self, path: Path | str) -> Path:
        """Draw the last scan reviewed into ``path`` (PNG, PDF or SVG by suffix).

        Raises
        ------
        ConfigError
            No scan was reviewed.
        """
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        s = self._last
        if s is None:
            raise ConfigError("no scan to draw: the recording held no scan the review could reconstruct")
        path = Path(path)
        fig = Figure(figsize=(12.0, 6.0), layout="constrained")
        FigureCanvasAgg(fig)
        grid = fig.add_gridspec(2, 2, width_ratios=[3, 2])
        ax3 = fig.add_subplot(grid[:, 0], projection="3d")
        self._draw_world(ax3, s)
        steps = np.array(sorted(s.energy))
        e, e0, r = (np.array([s.energy[k][i] for k in steps]) for i in range(3))
        ax_e = fig.add_subplot(grid[0, 1])
        ax_e.plot(steps, e, color="#1f77b4", label=r"$E^\gamma$")
        ax_e.plot(steps, e0, color="#7f7f7f", label=r"$E_0(d_m)$")
        ax_e.set_ylabel(r"energy, V$^2\cdot$s")
        ax_e.legend(loc="upper left", fontsize="small")
        ax_r = fig.add_subplot(grid[1, 1], sharex=ax_e)
        ax_r.plot(steps, r, color="#ff8c00", label="R")
        if s.critical_step is not None and s.critical_step in s.energy:
            ax_r.plot([s.critical_step], [s.energy[s.critical_step][2]], "D", color="#eb2828", label="critical step")
        ax_r.set_xlabel("step")
        ax_r.set_ylabel(r"$R = E^\gamma / E_0(d_m)$, no unit")
        ax_r.legend(loc="upper left", fontsize="small")
        fig.suptitle(f"{s.title}: {s.status}; {self.main_method}'s planes opaque, the compared ones see-through")
        path.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path, dpi=100)
        return path

    def _draw_world(self, ax, s: _Scan) -> None:
        from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # type: ignore[import-untyped]

        order = sorted(s.points)
        if order:
            pts = np.concatenate([s.points[k] for k in order])
            step = np.concatenate([np.full(len(s.points[k]), k) for k in order])
            ax.scatter(pts[:, 0], pts[:, 1], pts[:, 2], c=step, cmap="turbo", s=4, depthshade=False)
        for label, _normal, offset, corners in self.truth or ():
            patch = Poly3DCollection([np.asarray(corners, float)], alpha=0.15, facecolor="#a0a0a0", edgecolor="#808080")
            ax.add_collection3d(patch)
            c = np.asarray(corners, float)[0]
            ax.text(c[0], c[1], c[2], f"truth {label}: h = {offset:.3f} m", color="#606060", fontsize="small")
        for p in s.planes:
            main = p.method == self.main_method
            rgb = np.array(method_color(p.method)) / 255.0
            patch = Poly3DCollection(
                [p.patch], alpha=0.45 if main else 0.15, facecolor=rgb, edgecolor=rgb, linewidths=1.5 if main else 0.5
            )
            ax.add_collection3d(patch)
            if main:
                centre = p.patch.mean(axis=0) + 0.25 * p.normal
                ax.text(*centre, f"{p.label}: {p.method}, {p.quality or 'unassessed'}", fontsize="small")
        ax.set_xlabel("x, m")
        ax.set_ylabel("y, m")
        ax.set_zlabel("z, m")
        ax.view_init(elev=25, azim=-60)
        # Equal scales on the three axes, so angles between planes look as they are.
        extents = [p.patch for p in s.planes] + [s.points[k] for k in order]
        if extents:
            allpts = np.concatenate(extents)
            lo, hi = allpts.min(axis=0), allpts.max(axis=0)
            mid, half = (lo + hi) / 2, float((hi - lo).max()) / 2 + 0.05
            ax.set_xlim(mid[0] - half, mid[0] + half)
            ax.set_ylim(mid[1] - half, mid[1] + half)
            ax.set_zlim(mid[2] - half, mid[2] + half)
        ax.set_box_aspect((1, 1, 1))
