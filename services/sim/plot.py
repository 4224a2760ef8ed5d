"""A figure of a simulated scan, like the paper's Figs. 3, 4–5 and 6.

Uses matplotlib's object API with the Agg canvas (no global backend, no window).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lelsonar.errors import ConfigError
from lelsonar.signal.energy import EnergyModel, energy_ratio, median_range
from lelsonar.sim.calibrate import default_energy_model
from lelsonar.sim.scan import EchoSource, SimulatedScan, TruePlane

_SOURCE_STYLE = {
    EchoSource.PLANE_A: ("tab:blue", "mirror, plane a"),
    EchoSource.PLANE_B: ("tab:green", "mirror, plane b"),
    EchoSource.PLANE_OTHER: ("tab:olive", "mirror, other panel"),
    EchoSource.CORNER: ("tab:red", "corner double bounce"),
    EchoSource.DIFFUSE: ("tab:purple", "diffuse"),
}


def plane_section(plane: TruePlane, x: float = 0.0) -> np.ndarray:
    """Where a panel crosses the plane ``x = const``: (2, 3) segment ends, or (0, 3) if it does not."""
    corners = np.asarray(plane.corners)
    points = []
    for a, b in zip(corners, np.roll(corners, -1, axis=0)):
        da, db = a[0] - x, b[0] - x
        if da == db:
            continue
        s = da / (da - db)
        if 0.0 <= s <= 1.0:
            points.append(a + s * (b - a))
    if len(points) < 2:
        return np.empty((0, 3))
    pts = np.array(points)
    # Keep the two points farthest apart (a crossing through a corner repeats one).
    d = np.linalg.norm(pts[:, None] - pts[None], axis=-1)
    i, j = np.unravel_index(np.argmax(d), d.shape)
    return pts[[i, j]]


def scan_figure(scan: SimulatedScan, model: EnergyModel | None = None):
    """Three panels: raw points (eq. 9) with the true planes; ``E^γ`` and ``E0(d_m)``; ``R``.

    Parameters
    ----------
    scan : SimulatedScan
        Must carry waveforms.
    model : EnergyModel, optional
        ``E0(d)``; default :func:`default_energy_model`.

    Returns
    -------
    matplotlib.figure.Figure
    """
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ModuleNotFoundError:
        raise ConfigError("figures need matplotlib, an optional extra: pip install 'lelsonar[plot]'") from None

    model = model or default_energy_model()
    gamma_deg = np.degrees(scan.gamma_measured)
    energy = scan.step_energy()
    ratio = energy_ratio(energy, scan.distance, model)
    d_m = median_range(scan.distance)
    expected = np.where(np.isfinite(d_m), model.expected_energy(np.nan_to_num(d_m, nan=model.d_min)), np.nan)
    critical = np.degrees(scan.truth.critical_angle)
    k = int(np.argmax(ratio))

    fig = Figure(figsize=(15, 4.8), layout="constrained")
    FigureCanvasAgg(fig)
    ax_pts, ax_e, ax_r = fig.subplots(1, 3)

    points = scan.points()
    src = scan.truth.echo_source
    for code, (colour, label) in _SOURCE_STYLE.items():
        sel = (src == code) & np.isfinite(points[..., 0])
        if sel.any():
            ax_pts.scatter(points[sel][:, 1], points[sel][:, 2], s=5, c=colour, label=f"{label} ({sel.sum()})")
    for plane in scan.truth.planes:
        seg = plane_section(plane)
        if len(seg):
            ax_pts.plot(seg[:, 1], seg[:, 2], "k-", lw=1.5)
            ax_pts.annotate(
                f"plane {plane.label}", seg.mean(axis=0)[1:], fontsize=8, xytext=(4, 4), textcoords="offset points"
            )
    ax_pts.plot([0], [0], "k+", ms=10)
    ax_pts.set(
        xlabel="y (m)", ylabel="z (m)", title="raw points along the beams (eq. 9), x = all capsules", aspect="equal"
    )
    ax_pts.legend(fontsize=7, loc="lower left")

    ax_e.plot(gamma_deg, energy, "-", c="tab:blue", label=r"$E^\gamma$ (eq. 11)")
    ax_e.plot(gamma_deg, expected, "--", c="tab:orange", label=r"$E_{0°}(d_m)$ (eq. 12)")
    ax_e.axvline(critical, c="tab:red", lw=0.8, ls=":")
    ax_e.set(xlabel="γ (deg)", ylabel="energy (V²·s)", title="energy level (Figs. 4–5)")
    ax_e.legend(fontsize=8)

    ax_r.plot(gamma_deg, ratio, ".-", c="tab:blue", ms=3)
    ax_r.axvline(critical, c="tab:red", lw=1, ls=":", label=f"true critical angle {critical:.1f}°")
    ax_r.plot(gamma_deg[k], ratio[k], "o", mfc="none", c="k", label=f"argmax R: step {k}, {gamma_deg[k]:.1f}°")
    ax_r.set(xlabel="γ (deg)", ylabel=r"$R = E^\gamma / E_{0°}(d_m)$", title="energy ratio (Fig. 6)")
    ax_r.legend(fontsize=8)
    fig.suptitle(
        f"simulated scan: {scan.n_steps} steps, c = {scan.sound_speed:.1f} m/s, "
        f"critical step {scan.truth.critical_step}"
    )
    return fig


def save_scan_figure(scan: SimulatedScan, path: str | Path, model: EnergyModel | None = None) -> Path:
    """Render :func:`scan_figure` to ``path`` (PNG, PDF, SVG by suffix); creates the folder."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    scan_figure(scan, model).savefig(path, dpi=110)
    return path
