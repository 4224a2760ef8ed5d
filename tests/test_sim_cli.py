"""`lelsonar simulate`, `lelsonar calibrate`, the figure and the benchmark tool."""

from __future__ import annotations

import argparse
import io

import numpy as np
import pytest

from lelsonar.acquire.sim import cli, preset, simulate_scan
from lelsonar.acquire.sim.plot import plane_section, scan_figure
from lelsonar.errors import ConfigError
from lelsonar.tools import bench_sim


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="lelsonar")
    sub = parser.add_subparsers(dest="command", required=True)
    cli.register(sub)
    return parser


def test_simulate_prints_a_summary_and_writes_the_figure(tmp_path, capsys):
    out = tmp_path / "out" / "sim.png"
    args = _parser().parse_args(["simulate", "--preset", "paper-test1", "--seed", "0", "--plot", str(out)])
    assert args.run(args) == 0
    text = capsys.readouterr().out
    assert "critical angle 34.03° (step 67)" in text
    assert "corner" in text and "plane a" in text
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
    assert "phi0 =" in text and "phi2 =" in text and text.count("\n  ") >= 6


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
    assert "machine:" in text and "median s" in text and "within" in text
