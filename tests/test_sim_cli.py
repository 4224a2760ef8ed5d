"""`lelsonar simulate`, `lelsonar calibrate`, the figure and the benchmark tool."""

from __future__ import annotations

import argparse
import io
import math
import re

import numpy as np
import pytest

from lelsonar.cli import simulate as cli
from lelsonar.errors import ConfigError
from lelsonar.sim import preset, simulate_scan
from lelsonar.sim.plot import plane_section, scan_figure
from lelsonar.tools import bench_sim


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="lelsonar")
    sub = parser.add_subparsers(dest="command", required=True)
    cli.register(sub)
    return parser


def _numbers(pattern: str, text: str) -> tuple[float, ...]:
    match = re.search(pattern, text)
    assert match, f"{pattern!r} not in:\n{text}"
    return tuple(float(g) for g in match.groups())


def test_simulate_prints_a_summary_and_writes_the_figure(tmp_path, capsys):
    out = tmp_path / "out" / "sim.png"
    args = _parser().parse_args(["simulate", "--preset", "paper-test1", "--seed", "0", "--plot", str(out)])
    assert args.run(args) == 0
    text = capsys.readouterr().out
    cfg = preset("paper-test1")
    # The scene's truth, from its panels: wall a at y = h_a, wall b at z = h_b.
    panels = {p.label: p for p in cfg.scene.panels}
    h = {label: float(np.dot(p.center, p.normal)) for label, p in panels.items()}
    # The beam meets the corner line (y, z) = (h_a, h_b) at γ = atan(h_b / h_a); the step is the
    # schedule's nearest.  Printed to 0.01°.
    critical = math.degrees(math.atan2(h["b"], h["a"]))
    angle, step = _numbers(r"critical angle ([\d.]+)° \(step (\d+)\)", text)
    assert angle == pytest.approx(critical, abs=0.005)
    schedule = np.degrees(np.linspace(cfg.gamma_start, cfg.gamma_stop, cfg.steps))
    assert step == int(np.argmin(np.abs(schedule - critical)))
    for label, panel in panels.items():
        *normal, offset = _numbers(
            rf"plane {label}: n = \(([-+\d.]+), ([-+\d.]+), ([-+\d.]+)\), n·p = ([\d.]+) m", text
        )
        np.testing.assert_allclose(normal, panel.normal, atol=5e-5)
        assert offset == pytest.approx(h[label], abs=5e-5)
    # Every capsule of every step is one echo, from wall a, wall b or the corner.
    counts = _numbers(r"plane_a (\d+), plane_b (\d+), corner (\d+)", text)
    assert sum(counts) == cfg.steps * cfg.geometry.n_capsules and min(counts) > 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out.stat().st_size > 20_000


def test_figure_has_points_energies_and_ratio():
    fig = scan_figure(simulate_scan(preset("paper-test1"), seed=1))
    axes = fig.get_axes()
    assert len(axes) == 3
    assert axes[0].get_xlabel() == "y (m)" and axes[0].get_ylabel() == "z (m)"
    assert "R" in axes[2].get_ylabel()


def test_plane_section_of_the_default_planes():
    scan = simulate_scan(preset("paper-test1"), seed=0, with_waveforms=False)
    a, b = (plane_section(p) for p in scan.truth.planes)
    assert np.allclose(a[:, 1], 1.57) and np.isclose(a[:, 2].max(), 1.06)
    assert np.allclose(b[:, 2], 1.06) and np.isclose(b[:, 1].max(), 1.57)


def test_calibrate_from_the_simulator(capsys):
    args = _parser().parse_args(["calibrate"])
    assert args.run(args) == 0
    text = capsys.readouterr().out
    phi = [_numbers(rf"phi{i} = ([-\d.]+) ", text)[0] for i in range(3)]
    lo, hi = _numbers(r"valid for d in \[([\d.]+), ([\d.]+)\] m", text)
    rows = np.array(
        [
            [float(v.rstrip("%")) for v in line.split()]
            for line in text.splitlines()
            if re.match(r"\s+\d+\.\d+\s+\d", line)
        ]
    )
    assert len(rows) >= 6
    d, energy, fit, misfit = rows.T
    # The table is the printed model (eq. 12: E0 = 1 / (φ0 d² + φ1 d + φ2)) at the calibration
    # distances, which span the validity range, and the misfit is the measured energy against it.
    assert (d.min(), d.max()) == (lo, hi) and np.all(np.diff(d) > 0)
    np.testing.assert_allclose(fit, 1.0 / (phi[0] * d**2 + phi[1] * d + phi[2]), rtol=5e-4)
    np.testing.assert_allclose(misfit, 100 * (energy / fit - 1), atol=0.011)
    # E0 falls with range, as spreading and absorption make it.
    assert np.all(np.diff(energy) < 0) and np.all(np.diff(fit) < 0)


def test_calibrate_manual_reads_typed_pairs(monkeypatch, capsys):
    d = np.array([0.9, 1.2, 1.5, 1.8])
    e = 1.0 / (2.0 * d**2 + 3.0 * d + 0.5)
    monkeypatch.setattr("sys.stdin", io.StringIO("# d E\n" + "\n".join(f"{x} {y}" for x, y in zip(d, e)) + "\n"))
    args = _parser().parse_args(["calibrate", "--manual"])
    assert args.run(args) == 0
    assert "phi0 = 2 " in capsys.readouterr().out
    monkeypatch.setattr("sys.stdin", io.StringIO("0.9 oops\n"))
    with pytest.raises(ConfigError, match="line 1"):
        args.run(args)


def test_bench_tool_reports_times(capsys):
    parser = argparse.ArgumentParser()
    bench_sim.add_arguments(parser)
    args = parser.parse_args(["--runs", "1", "--preset", "paper-test1", "--budget", "60"])
    assert bench_sim.run(args) == 0
    text = capsys.readouterr().out
    assert "machine:" in text
    with_waves = _numbers(r"\n\s+yes\s+([\d.]+)\s+([\d.]+)\s+([\d.]+)", text)
    without = _numbers(r"\n\s+no\s+([\d.]+)\s+([\d.]+)\s+([\d.]+)", text)
    for median, low, high in (with_waves, without):
        assert 0 < low <= median <= high  # one run: all three are that run
    # The verdict is the median with waveforms against the budget given.
    assert ("within the 60.00 s budget" in text) == (with_waves[0] <= 60.0)
