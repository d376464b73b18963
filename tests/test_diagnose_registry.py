"""The causes' registry: one object per cause, usable whatever form the evidence takes."""

from __future__ import annotations

import numpy as np
import pytest

from encoder_core.diagnose import CAUSES, TERMS, Observables
from encoder_core.diagnose.causes import split_by_testability
from encoder_core.stats import WindowStats

DESIGN_NAMES = [
    "zero_offset",
    "phase_nonorthogonality",
    "phase_drift",
    "harmonic_distortion",
    "thermal_lag",
    "nonlinear_temperature",
    "aging",
    "outliers",
    "adc_clipping",
]


def test_registry_holds_designs_causes_each_with_its_sample_form():
    assert list(CAUSES) == DESIGN_NAMES
    assert list(TERMS) == DESIGN_NAMES
    for name, cause in CAUSES.items():
        assert cause.name == name and cause.summary and cause.params
        assert TERMS[name].cause is cause
    assert CAUSES["harmonic_distortion"].param_names == ("order", "amplitude")
    assert CAUSES["outliers"].param_names == ("fraction",)
    assert CAUSES["thermal_lag"].param_names == ("tau_s",)


@pytest.mark.parametrize("name", DESIGN_NAMES)
def test_every_cause_states_itself_from_its_parameters_alone(name):
    """A monitor describing a finding from window statistics has the parameters, not diagnose's fit."""
    cause = CAUSES[name]
    values = {p.name: 0.5 for p in cause.params}
    text = cause.state(**values)
    assert text and "{" not in text


def test_statement_with_facts():
    text = CAUSES["harmonic_distortion"].state(order=5, amplitude=0.01, cycles=4, amplitude_deg=0.573)
    assert text.startswith("the residual has a 4-cycle-per-turn component of 0.573° (harmonic order 5")
    assert "2 samples (0.42 %) are far off the circle" == CAUSES["outliers"].state(count=2, percent=0.42)


def test_testability_reads_only_observables_from_either_form():
    bench = Observables(has_reference=True, temp_span_c=80.0, span_s=7200.0)
    testable, untestable = split_by_testability(bench)
    assert testable == DESIGN_NAMES and untestable == []

    stats = WindowStats(scale=1000.0).add(np.array([1000.0, 0.0, -1000.0]), np.array([0.0, 1000.0, 0.0]))
    windows = Observables.from_window_stats(stats, span_s=3600.0)  # windows carry no reference, here no temp
    testable, untestable = split_by_testability(windows)
    why = {item["cause"]: item["why"] for item in untestable}
    assert set(why) == {"zero_offset", "phase_drift", "thermal_lag", "nonlinear_temperature", "harmonic_distortion"}
    assert "no temp_c" in why["thermal_lag"] and "orders 2 and 3" in why["harmonic_distortion"]
    assert "harmonic_distortion" in testable and "aging" in testable  # partly testable stays testable
    warm = WindowStats(scale=1000.0).add(np.ones(3), np.ones(3), np.array([20.0, 22.0, 23.0]))
    assert "spans only 3.0 °C" in CAUSES["thermal_lag"].not_testable(Observables.from_window_stats(warm, 60.0))
