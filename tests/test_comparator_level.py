"""A board that times the onset is never re-timed as if its comparator walked, even where every echo is two.

The walk test (:func:`lelsonar.signal.echo_timing.range_walk`) reads constant-fraction times against the
writer's.  Under a scanner near the floor each wall echo comes with the double bounce of the wall's foot a
few mm later, and their carriers' phase moves the constant-fraction time with the summed peak: the ranges of
an onset-timed board seem to walk.  Where the writer's times lie on the echoes tells the boards apart
(:mod:`lelsonar.reconstruct.stream.comparator_level`), so a replay of such a sweep gives what the sweep
reconstructed in process gives (the benches score the latter; a user gets the former).
"""

from __future__ import annotations

import json
import math
import threading

import numpy as np
import pytest

from lelsonar.acquire.scan_loop import ScanIdentity, ScanOutput, run_scan
from lelsonar.acquire.world_scans import prepare_world
from lelsonar.cli.main import main
from lelsonar.log.recording import McapRecorder
from lelsonar.reconstruct.stream.comparator_level import envelope_at, fires_up_the_edge
from lelsonar.signal.echo_timing import TIMING_WINDOW, echo_onsets
from lelsonar.sim import default_energy_model
from lelsonar.sim.acoustics import comparator_delay, echo_envelope
from lelsonar.tools.map_worlds import sweep
from lelsonar.tools.stress_world_score import estimate_of, world_run
from lelsonar.tools.stress_worlds import draw_stress_world, stress_world_data, world_toml

RATE = 200_000.0
RISE = 0.15e-3  # the simulator's envelope rise, s


def _windows(peaks, rng, *, threshold=None, second=0.0, delay=0.0, noise=0.002, jitter=0.002):
    """Windows of 40 kHz bursts under the simulator's envelope cut around the time a board reports: the onset
    (``threshold`` None) or its comparator's crossing of ``threshold``.  ``second``: a later echo ``delay`` s
    after the first, ``second`` times as strong, as a wall's foot gives under a scanner near the floor.  ``jitter``:
    the board's timing noise, m of range."""
    width = int(round((TIMING_WINDOW[1] - TIMING_WINDOW[0]) * RATE))
    arrival = 5e-3 + rng.uniform(0, 1 / RATE, peaks.size)
    crossing = 0.0 if threshold is None else comparator_delay(peaks, threshold, RISE)
    tof = arrival + rng.normal(0, jitter / (343.0 / 2), peaks.size) + crossing
    first = np.round((tof + TIMING_WINDOW[0]) * RATE) / RATE
    t = first[:, None] + np.arange(width) / RATE
    w = rng.normal(0, noise, (peaks.size, width))
    for start, amp in ((arrival, peaks), (arrival + delay, second * peaks)):
        u = t - start[:, None]
        w += amp[:, None] * echo_envelope(u, RISE) * np.sin(2 * np.pi * 40_000.0 * np.maximum(u, 0))
    return w, tof - first


@pytest.mark.parametrize("threshold", [0.03, 0.05, 0.12])
def test_a_comparator_fires_up_the_edge_and_an_onset_board_at_its_foot(threshold):
    rng = np.random.default_rng(5)
    # Echoes the comparator fires on: over its threshold, up to 20 times it.
    peaks = threshold * np.exp(rng.uniform(math.log(1.2), math.log(20.0), 200))
    windows, at = _windows(peaks, rng, threshold=threshold)
    level, sigma = envelope_at(windows, RATE, at)
    # The envelope at the writer's times is the comparator's threshold (less the board's 2 mm timing noise on
    # an edge rising at most 2·peak/τ, and the carrier period it is smoothed over).
    _, peak, _ = echo_onsets(windows, RATE, at)
    assert abs(np.median(level) / threshold - 1) < 0.25
    assert fires_up_the_edge(level, sigma, peak)
    for second, delay in ((0.0, 0.0), (1.37, 33e-6)):  # one echo; an echo and its foot's 5.7 mm later
        windows, at = _windows(peaks, rng, second=second, delay=delay)
        level, sigma = envelope_at(windows, RATE, at)
        _, peak, _ = echo_onsets(windows, RATE, at)
        assert not fires_up_the_edge(level, sigma, peak)


def test_the_envelope_at_a_time_is_the_burst_envelope_there():
    rng = np.random.default_rng(6)
    peaks = np.full(50, 0.4)
    windows, at = _windows(peaks, rng, threshold=0.1, noise=0.0, jitter=0.0)
    level, sigma = envelope_at(windows, RATE, at)
    # Noise-free, the smoothed envelope at the crossing of 0.1 V is 0.1 V to the curvature over one carrier period.
    assert np.allclose(level, 0.1, rtol=0.05) and np.all(sigma < 1e-3)


def test_a_replay_of_a_fan_sweep_over_the_floor_equals_the_sweep_in_process(tmp_path, capsys):
    """Stress world `wide` 66, fan mount, scanner 0.28 m over the floor, its fourth pose: every wall echo comes
    with the foot's double bounce 5.6 mm later; the onset-timed ranges are the truth's to 2 mm."""
    cls, seed, index = "wide", 66, 3
    world_file = tmp_path / "world.toml"
    world_file.write_text(world_toml(stress_world_data(cls, seed, "fan")))
    acquired = prepare_world(world_file, seed)
    path = tmp_path / "scan.mcap"
    with McapRecorder(path) as recorder:
        end = run_scan(
            acquired.scanner(index),
            acquired.schedule,
            ScanIdentity("sim", 1),
            default_energy_model(),
            ScanOutput(recorder),
            threading.Event(),
        )
    assert end.samples_sent == end.steps_planned == len(acquired.schedule)
    capsys.readouterr()
    assert main(["reconstruct", "--source", str(path), "--json"]) == 0
    final = [d for d in map(json.loads, capsys.readouterr().out.strip().splitlines()) if "surfaces" in d][-1]
    replay = sorted(
        (str(s["plane"]["quality"]).lower().removeprefix("plane_quality_"), s["plane"]["offset"])
        for s in final["surfaces"]
    )
    mine = sorted(
        (s.quality, s.offset)
        for s in estimate_of(sweep(world_run(draw_stress_world(cls, seed, "fan"), seed), index)).surfaces.surfaces
    )
    assert len(replay) == len(mine), (replay, mine)
    for (q_replay, d_replay), (q_mine, d_mine) in zip(replay, mine, strict=True):
        assert q_replay == q_mine and abs(d_replay - d_mine) <= 1e-3, (replay, mine)
    assert "re-timed" not in json.dumps(final)
