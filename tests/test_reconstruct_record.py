"""The reconstruction of record: what the service publishes is what ``reconstruct_scan`` returns, and
a compared method is judged against the method of record."""

from __future__ import annotations

import numpy as np
import pytest

from lelsonar import codec
from lelsonar.errors import ConfigError
from lelsonar.reconstruct.estimate import wire
from lelsonar.reconstruct.estimate.pipeline import reconstruct
from lelsonar.reconstruct.estimate.record import (
    ProvisionalState,
    RecordOptions,
    ScanInput,
    reconstruct_scan,
)
from lelsonar.reconstruct.estimate.results import PlaneFit
from lelsonar.reconstruct.stream.config import ReconstructConfig
from lelsonar.reconstruct.stream.scan_input import scan_input
from lelsonar.reconstruct.stream.service import ReconstructionService
from lelsonar.signal.energy import echo_amplitude, waveform_energy
from lelsonar.sim import default_energy_model, preset, simulate_scan

from .conftest import simulated_messages, type_name


def _without_clock(msg: codec.Reconstruction) -> codec.Reconstruction:
    m = codec.Reconstruction()
    m.CopyFrom(msg)
    for f in ("stamp_ns", "timings"):
        m.ClearField(f)
    return m


@pytest.fixture(scope="module")
def simulated():
    scan = simulate_scan(preset("paper-test1"), seed=3)
    energy = waveform_energy(scan.waveforms, scan.sample_rate)
    amplitude = echo_amplitude(scan.waveforms, scan.sample_rate, scan.t0, scan.tof)
    return scan, energy, amplitude


def test_the_services_final_is_the_reconstruction_of_record():
    messages = simulated_messages("paper-test1", seed=4)
    config = ReconstructConfig(provisional=False, compare_methods=("ls", "lel"))
    seen = {}

    class Spy:
        def scan_started(self, scan):
            pass

        def step(self, *a):
            pass

        def event(self, *a):
            pass

        def estimate(self, scan, message, results, partial):
            if results is not None:  # the final, before the service forgets the scan
                seen["input"] = scan_input(scan)

    service = ReconstructionService(config, observer=Spy())
    for m in messages:
        service.handle(type_name(m), m.SerializeToString())
    (final,) = service.finals.values()
    est = reconstruct_scan(seen["input"], config.record_options())
    again = wire.estimate_message(
        est, final.scanner_id, final.scan_id, status="final", missing_steps=(), accounting=final.accounting
    )
    assert _without_clock(final) == _without_clock(again)
    # The planes of record come first, then each compared method's, by name.
    assert [p.method for p in final.planes] == ["corner", "corner", "ls", "ls", "lel", "lel"]


def test_a_simulated_scan_is_the_methods_own_reconstruction(simulated):
    """With nothing to repair and nothing compared, the estimate of record is the method's own fit."""
    scan, energy, amplitude = simulated
    model = default_energy_model()
    given = ScanInput.of_scan(
        scan.gamma_measured, scan.distance, energy, scan.geometry, model, echo_amplitude=amplitude
    )
    for method in ("corner", "lel-refit-ls"):
        est = reconstruct_scan(given, RecordOptions(method=method))
        own = reconstruct(
            scan.gamma_measured, scan.distance, energy, scan.geometry, model, method, echo_amplitude=amplitude
        )
        assert est.critical_step == own.critical_step
        for mine, theirs in zip(est.planes, own.planes, strict=True):
            assert isinstance(mine, PlaneFit) and isinstance(theirs, PlaneFit)
            np.testing.assert_array_equal(mine.normal, theirs.normal)
            assert (mine.offset, mine.quality, mine.quality_reasons) == (
                theirs.offset,
                theirs.quality,
                theirs.quality_reasons,
            )


def test_a_compared_plane_is_judged_against_the_plane_of_record(simulated):
    """LS on the corner's double-bounce echoes doubts its own walls; the joint model fits them well.  As a
    compared method the joint model's good planes have no good plane of record to vouch for them (degraded,
    and said why); as the method of record they are good, and a compared method that agrees stays good."""
    scan, energy, amplitude = simulated
    model = default_energy_model()
    given = ScanInput.of_scan(
        scan.gamma_measured, scan.distance, energy, scan.geometry, model, echo_amplitude=amplitude
    )
    est = reconstruct_scan(given, RecordOptions(method="ls", compare_methods=("corner",)))
    assert all(p.quality != "good" for p in est.planes_of("ls"))
    assert [p.quality for p in est.results["corner"].planes] == ["good", "good"]  # its own verdict
    for plane in est.planes_of("corner"):
        assert plane.quality == "degraded" and plane.quality_reasons[-1].startswith("unchecked: the method of record")
    # The message a planner gets carries the judged planes, not the methods' own verdicts.
    published = est.as_published()
    assert [p.quality for p in published["corner"].planes] == ["degraded", "degraded"]
    agree = reconstruct_scan(given, RecordOptions(method="corner", compare_methods=("adaptive",)))
    assert [p.quality for p in agree.planes] == ["good"] * 4
    with pytest.raises(ConfigError):
        agree.planes_of("lel")


def test_the_provisional_variant_needs_its_state_and_the_final_its_energies(simulated):
    scan, energy, _ = simulated
    model = default_energy_model()
    bare = ScanInput(scan.geometry, model, np.arange(scan.n_steps), scan.gamma_measured, scan.distance)
    with pytest.raises(ConfigError):
        reconstruct_scan(bare, RecordOptions(provisional=True))
    with pytest.raises(ConfigError):
        reconstruct_scan(bare, RecordOptions())
    # Before the corner is confirmed (a few steps only) there is no provisional estimate.
    few = ScanInput(scan.geometry, model, np.arange(5), scan.gamma_measured[:5], scan.distance[:5], ratio=np.ones(5))
    assert reconstruct_scan(few, RecordOptions(provisional=True), ProvisionalState()) is None
