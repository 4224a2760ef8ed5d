"""Every surface of a sweep in the reconstruction of record: a final carries them, made from the very input
its L planes were fitted on; a provisional says nothing of them; the writer's findings judge them too."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from lelsonar.reconstruct.estimate import wire
from lelsonar.reconstruct.estimate.quality import DEGRADED
from lelsonar.reconstruct.estimate.record import RecordOptions, ScanInput, reconstruct_scan, with_findings
from lelsonar.reconstruct.estimate.surfaces import extract_surfaces
from lelsonar.reconstruct.stream.config import ReconstructConfig
from lelsonar.reconstruct.stream.service import ReconstructionService
from lelsonar.signal.energy import echo_amplitude, waveform_energy
from lelsonar.sim import default_energy_model, preset, simulate_scan
from lelsonar.view import present

from .conftest import simulated_messages, type_name


@pytest.fixture(scope="module")
def given() -> ScanInput:
    scan = simulate_scan(preset("paper-test1"), seed=3)
    energy = waveform_energy(scan.waveforms, scan.sample_rate)
    amplitude = echo_amplitude(scan.waveforms, scan.sample_rate, scan.t0, scan.tof)
    return ScanInput.of_scan(
        scan.gamma_measured, scan.distance, energy, scan.geometry, default_energy_model(), echo_amplitude=amplitude
    )


def test_a_final_carries_the_surfaces_of_its_own_ranges_and_amplitudes(given):
    est = reconstruct_scan(given, RecordOptions())
    own = extract_surfaces(given.gamma, given.distance, given.geometry, amplitude=given.echo_amplitude)
    assert est.surfaces is not None and len(est.surfaces.surfaces) == len(own.surfaces) == 2
    for mine, theirs in zip(est.surfaces.surfaces, own.surfaces, strict=True):
        np.testing.assert_array_equal(mine.normal, theirs.normal)
        assert (mine.offset, mine.quality, mine.reasons) == (theirs.offset, theirs.quality, theirs.reasons)
    msg = wire.estimate_message(est, "s", 1, status="final")
    assert [s.label for s in msg.surfaces] == [s.label for s in own.surfaces]
    assert len(msg.corners) == len(own.corners) and msg.surface_echo_count == own.n_echoes


def test_the_writers_findings_lower_every_surface_as_every_plane(given):
    text = "the writer's ranges are one-way times"
    est = reconstruct_scan(replace(given, writer_problems=((DEGRADED, text),)), RecordOptions())
    assert est.surfaces is not None and est.surfaces.surfaces
    for s in est.surfaces.surfaces:
        assert s.quality != "good" and s.reasons[-1] == text
    # What the stream adds (a sweep stopped early, conflicting copies) goes the same way.
    clean = reconstruct_scan(given, RecordOptions())
    stopped = with_findings(clean, ((DEGRADED, "stopped early"),))
    assert stopped.surfaces is not None
    assert all(s.reasons[-1] == "stopped early" and s.quality != "good" for s in stopped.surfaces.surfaces)
    assert all(p.quality_reasons[-1] == "stopped early" for p in stopped.planes)


def test_a_provisional_estimate_says_nothing_of_surfaces():
    messages = simulated_messages("paper-test1", seed=4)
    service = ReconstructionService(ReconstructConfig(provisional=True, provisional_period=0.0))
    out = []
    for m in messages:
        out += service.handle(type_name(m), m.SerializeToString())
    provisional = [m for m in out if wire.status_name(m) == "provisional"]
    (final,) = [m for m in out if wire.is_terminal(m)]
    assert provisional and not any(m.surfaces or m.corners or m.edges or m.surface_echo_count for m in provisional)
    assert final.surfaces and final.surface_echo_count


def test_reading_a_json_estimate_back_leaves_the_callers_dict_as_it_was(given):
    """A live estimate compared with its replay after being read back must still be the one printed."""
    msg = wire.estimate_message(reconstruct_scan(given, RecordOptions()), "s", 1, status="final")
    line = present.to_json(msg)
    d = json.loads(line)
    assert present.from_json(d) == present.from_json(line)
    assert d == json.loads(line)
