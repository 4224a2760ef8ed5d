"""The range repair's waveform passes over a scan's kept windows, against the rule they implement written out
step by step: every received step's windows taken, then the kept readings' among them.

Varied inputs: boards whose comparator fires on the noise now and then or before nearly every echo, one whose
crossing walks with the echoes' amplitude, each with whole steps lost on the way (the received steps then skip).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from lelsonar import codec
from lelsonar.reconstruct.stream.assembly import ScanAssembly
from lelsonar.reconstruct.stream.candidates import RANGE_CHECK_MIN
from lelsonar.signal.echo_timing import FLOOR_TIME, echo_onsets
from lelsonar.signal.energy import ECHO_PEAK_WINDOW, echoes_over_noise, ranges_backed

from . import foreign_scenes as fs

NOISY = fs.ForeignRig(seed=3, steps=150, noise=0.007)
SCENES = {
    "noise now and then": NOISY,
    "noise before every echo": replace(NOISY, noise=0.0125),
    "walking comparator": fs.ForeignRig(seed=1),
}


def _assembled(rig: fs.ForeignRig, lost: int) -> ScanAssembly:
    """The scan of ``rig``, every ``lost``-th sample dropped (0: none)."""
    msgs = fs.messages(fs.simulate(rig), fs.Conventions())
    assembly = ScanAssembly(codec.decode(msgs[0].SerializeToString(), type(msgs[0])))
    for k, m in enumerate(msgs[1:-1]):
        if lost and k % lost == lost - 1:
            continue
        assembly.add(codec.decode(m.SerializeToString(), type(m)))
    return assembly


def _reference_echo(a: ScanAssembly) -> tuple[np.ndarray, float]:
    """Which kept readings show an echo over the noise, and σ: the received steps' windows, then the kept ones."""
    steps = np.flatnonzero(a.received)
    at = a._timing_at[steps]
    kept = np.isfinite(at) & np.isfinite(a.distance[steps])
    listened = 2.0 * a.distance[steps][kept] / a.sound_speed
    echo, _, sigma = echoes_over_noise(a._timing_windows[steps][kept], a._timing_rate, at[kept], listened, FLOOR_TIME)
    return echo, sigma


def _reference_timing(a: ScanAssembly) -> np.ndarray:
    """Every received step's echo timing (onset, peak, edge), from its windows taken the same way."""
    steps = np.flatnonzero(a.received)
    at = a._timing_at[steps]
    kept = np.isfinite(at)
    timing = np.full((*at.shape, 3), np.nan)
    timing[kept] = np.stack(echo_onsets(a._timing_windows[steps][kept], a._timing_rate, at[kept]), axis=-1)
    return timing


@pytest.mark.parametrize("lost", [0, 7])
@pytest.mark.parametrize("name", sorted(SCENES))
def test_the_windows_passes_give_the_step_by_step_rules_answers(name, lost):
    a = _assembled(SCENES[name], lost)
    steps = np.flatnonzero(a.received)
    assert lost == 0 or len(steps) < len(a.received)  # the received steps skip
    noise, sigma = a.noise_triggers()
    echo, sigma_ref = _reference_echo(a)
    assert np.count_nonzero(np.isfinite(a._timing_at[steps])) >= RANGE_CHECK_MIN  # the test ran
    assert sigma == sigma_ref or (np.isnan(sigma) and np.isnan(sigma_ref))
    kept = np.isfinite(a._timing_at[steps]) & np.isfinite(a.distance[steps])
    shown = np.isfinite(a.distance[steps])
    shown[kept] = echo
    reach = 0.5 * a.sound_speed * (ECHO_PEAK_WINDOW[1] - ECHO_PEAK_WINDOW[0])
    assert np.array_equal(noise, kept & ~shown & ~ranges_backed(a.distance[steps], shown, reach))
    a._time_echoes(steps)
    assert np.array_equal(a._echo_timing[steps], _reference_timing(a), equal_nan=True)
    if noise.any():
        # The recovered echoes: their windows gathered once, against each step's taken then the rows.
        rows = noise & np.isfinite(a._candidate_at[steps])
        picked, capsules = np.nonzero(rows)
        assert np.array_equal(a._candidate_windows[steps[picked], capsules], a._candidate_windows[steps][rows])
