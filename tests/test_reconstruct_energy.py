"""The energy indicator (eq. 10–14) and its fast median."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from lelsonar.errors import ConfigError
from lelsonar.signal.energy import EnergyModel, energy_ratio, fit_energy_model, median_range, waveform_energy

ranges = arrays(
    np.float64,
    st.tuples(st.integers(1, 30), st.integers(1, 6)),
    elements=st.one_of(st.just(np.nan), st.floats(0.05, 5.0)),
)


@settings(max_examples=200, deadline=None)
@given(ranges)
def test_median_range_is_exactly_nanmedian(d):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN rows
        expected = np.nanmedian(d, axis=-1)
    np.testing.assert_array_equal(median_range(d), expected)


def test_energy_is_the_integral_of_the_squared_signal():
    fs = 200_000.0
    t = np.arange(2000) / fs
    w = 0.5 * np.sin(2 * np.pi * 40_000 * t)
    assert waveform_energy(w, fs) == pytest.approx(0.25 / 2 * 2000 / fs, rel=1e-3)


def test_calibration_recovers_the_model_and_ratio_is_one_face_on():
    truth = EnergyModel(0.1, 0.2, 0.05)
    d = np.linspace(0.9, 1.8, 6)
    fitted = fit_energy_model(d, truth.expected_energy(d))
    np.testing.assert_allclose([fitted.phi0, fitted.phi1, fitted.phi2], [0.1, 0.2, 0.05], rtol=1e-9)
    distance = np.repeat(d[:, None], 4, axis=1)
    np.testing.assert_allclose(energy_ratio(truth.expected_energy(d), distance, truth), 1.0)
    assert energy_ratio(np.array([1.0]), np.full((1, 4), np.nan), truth)[0] == 0.0


def test_bad_calibration_input_is_refused():
    with pytest.raises(ConfigError, match="three or more"):
        fit_energy_model([1.0, 1.0, 1.2], [1.0, 1.0, 0.8])
    with pytest.raises(ConfigError, match="non-positive energy"):
        EnergyModel(0.0, -1.0, 1.0)


@settings(max_examples=200, deadline=None)
@given(st.one_of(st.just(np.nan), st.floats(0.05, 5.0)))
def test_expected_energy_of_one_range_is_the_whole_arrays_value_clipped_alike(d):
    # The live service asks for one step's E0(d_m) at a time (a float fast path): the same number as
    # the vectorised form, inside and outside the calibrated interval, NaN included.
    model = EnergyModel(0.1, 0.2, 0.05, d_min=0.9, d_max=1.8)
    one = model.expected_energy(d)
    assert isinstance(one, float)
    np.testing.assert_array_equal(one, model.expected_energy(np.array([d]))[0])
