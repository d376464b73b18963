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
    from encoder_core.diagnose.causes import DIAGNOSE_CAUSES

    assert list(DIAGNOSE_CAUSES) == DESIGN_NAMES
    assert list(TERMS) == DESIGN_NAMES
    for name, cause in DIAGNOSE_CAUSES.items():
        assert cause.name == name and cause.summary and cause.params
        assert TERMS[name].cause is cause is CAUSES[name]
    assert CAUSES["harmonic_distortion"].param_names == ("order", "amplitude")
    assert CAUSES["outliers"].param_names == ("fraction",)
    assert CAUSES["thermal_lag"].param_names == ("tau_s",)


def test_the_monitor_names_alarms_from_the_same_registry():
    from encoder_core import monitor_causes

    alarm_names = {"offset_step", "gain_step", "axis_step", "accelerated_aging", "magnet_weakening"}
    alarm_names |= {"harmonic_growth", "outliers", "adc_clipping", "offline"}
    assert set(monitor_causes.CAUSES) == alarm_names  # the Alarms contract of docs/architecture.md
    for name, cause in monitor_causes.CAUSES.items():
        assert CAUSES[name] is cause and set(cause.alarm_params) <= set(cause.param_names)
        values = {p: 2 if p == "order" else 0.01 for p in cause.param_names}
        assert cause.state(**values)  # every alarm cause states itself from its parameters
    assert CAUSES["outliers"] is monitor_causes.CAUSES["outliers"]  # one object, two data forms


EXAMPLE_PARAMETERS = {  # as a monitor would have them, from window statistics
    "zero_offset": {"offset_deg": -1.2},
    "phase_nonorthogonality": {"phase_error_deg": 0.8},
    "phase_drift": {"phase_drift_deg_per_c": 0.02},
    "harmonic_distortion": {"order": 5, "amplitude": 0.01},
    "thermal_lag": {"tau_s": 300.0},
    "nonlinear_temperature": {"gain_tc2_per_c2": [2e-5, 1e-5], "offset_tc2_per_c2": [0.01, -0.01]},
    "aging": {"gain_loss_per_khour": [0.3, 0.2], "offset_per_khour": [1.0, -2.0]},
    "outliers": {"fraction": 0.01},
    "adc_clipping": {"fraction": 0.02, "channels": ["d"]},
}


@pytest.mark.parametrize("name", DESIGN_NAMES)
def test_every_cause_states_itself_from_its_parameters_alone(name):
    """A monitor describing a finding from window statistics has the parameters, not diagnose's fit."""
    cause = CAUSES[name]
    params = EXAMPLE_PARAMETERS[name]
    assert tuple(params) == cause.param_names
    text = cause.state(**params)
    assert text and "{" not in text and "nan" not in text


def test_statement_derives_what_it_can_and_takes_facts():
    text = CAUSES["harmonic_distortion"].state(order=5, amplitude=0.01)
    assert text.startswith("the residual has a 4-cycle-per-turn component of 0.573° (harmonic order 5")
    assert CAUSES["outliers"].state(fraction=0.0042, count=2) == "2 samples (0.42 %) are far off the circle"
    assert "over 48.0 h" in CAUSES["aging"].state(**EXAMPLE_PARAMETERS["aging"], over=" over 48.0 h")


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
