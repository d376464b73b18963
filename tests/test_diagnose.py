"""diagnose names what was hidden in a recording, and nothing else.

Each case draws, from its seed, an encoder with random baseline effects (per-axis gain and offset,
linear in temperature, amplitude imbalance, noise) plus zero, one or two hidden effects of random
size, records it bench-style (reference angle, temperature plateaus and ramps, runs) or field-style
(no reference, random angles, load-driven temperature over days), and gives diagnose only the
Samples. The truth stays here in the test.
"""

from __future__ import annotations

import numpy as np
import pytest

from encoder_core.diagnose import CAUSES, diagnose
from encoder_core.simulator import EncoderModel, bench_profile, field_profile, record


def baseline_model(rng, style):
    """Random baseline effects only: what the seed-000 model is meant to absorb."""
    return dict(
        hall_amplitude=float(rng.uniform(600, 800)),
        amplitude_imbalance=float(rng.uniform(-0.03, 0.03)),
        gain_tc_per_c=(float(rng.uniform(-0.0025, -0.0005)), float(rng.uniform(-0.0025, -0.0005))),
        offset_counts=(float(rng.uniform(-20, 20)), float(rng.uniform(-20, 20))),
        offset_tc_counts_per_c=(float(rng.uniform(-0.8, 0.8)), float(rng.uniform(-0.8, 0.8))),
        noise_counts=1.0,
    )


def plant(effect, rng, model, style, truth):
    """Add one hidden effect of random size to the model; record what a correct diagnosis reports."""
    sign = rng.choice([-1.0, 1.0])
    if effect == "zero_offset":
        z = sign * np.radians(rng.uniform(0.4, 1.5))
        model["zero_offset_rad"] = z
        truth[effect] = {"offset_deg": np.degrees(z)}
    elif effect == "phase_nonorthogonality":
        b = sign * np.radians(rng.uniform(0.4, 1.5))
        model["phase_error_rad"] = b
        truth[effect] = {"phase_error_deg": np.degrees(b)}
    elif effect == "phase_drift":
        r = sign * np.radians(rng.uniform(0.012, 0.03))
        model["phase_drift_rad_per_c"] = r
        truth[effect] = {"phase_drift_deg_per_c": np.degrees(r)}
    elif effect.startswith("harmonic"):
        orders = (2, 3, 4, 5, 6, 7) if style == "bench" else (4, 5, 6, 7)
        n = int(effect.split(":")[1]) if ":" in effect else int(rng.choice(orders))
        k = float(rng.uniform(0.006, 0.015))
        model["harmonics"] = ((n, k, float(rng.uniform(-np.pi, np.pi))),)
        truth["harmonic_distortion"] = {"order": n, "amplitude": k}
    elif effect == "thermal_lag":
        tau = float(rng.uniform(150, 450))
        model["thermal_lag_tau_s"] = tau
        # a lag only shows through temperature coefficients: make them clearly different per axis (the
        # reference sees the difference), or both large (the radius sees the common part)
        if style == "bench":
            model["gain_tc_per_c"] = (float(rng.uniform(-0.003, -0.0025)), float(rng.uniform(-0.001, -0.0005)))
        else:
            model["gain_tc_per_c"] = (float(rng.uniform(-0.0035, -0.0025)), float(rng.uniform(-0.0035, -0.0025)))
        model["offset_tc_counts_per_c"] = (float(sign * rng.uniform(1.0, 2.0)), float(-sign * rng.uniform(1.0, 2.0)))
        truth[effect] = {"tau_s": tau}
    elif effect == "nonlinear_temperature":
        if style == "bench":  # the reference sees the axes' difference
            g2 = (float(sign * rng.uniform(1.5e-5, 3e-5)), float(-sign * rng.uniform(0.5e-5, 1.5e-5)))
        else:  # the radius sees their common part
            g2 = (float(sign * rng.uniform(2e-5, 4e-5)), float(sign * rng.uniform(2e-5, 4e-5)))
        model["gain_tc2_per_c2"] = g2
        model["offset_tc2_counts_per_c2"] = (float(rng.uniform(-0.01, 0.01)), float(rng.uniform(-0.01, 0.01)))
        truth[effect] = {"gain_tc2_per_c2": g2}
    elif effect == "aging":
        if style == "bench":  # two hours: only a large trend shows; the reference sees offsets, not a common gain
            off = (float(sign * rng.uniform(5000, 10000)), float(rng.uniform(-3000, 3000)))
            model["aging_offset_counts_per_khour"] = off
            truth[effect] = {"offset_per_khour": off}
        else:
            g = float(rng.uniform(0.2, 0.5))
            model["aging_gain_per_khour"] = g
            truth[effect] = {"gain_loss_per_khour": g}
    elif effect == "outliers":
        f = float(rng.uniform(0.003, 0.02))
        model["impulse_fraction"] = f
        model["impulse_counts"] = float(rng.uniform(250, 500))
        truth[effect] = {"fraction": f}
    elif effect == "adc_clipping":
        # near full scale at +20 °C: the gain rises at cold and the halls hit the rails
        model["hall_amplitude"] = float(rng.uniform(1950, 2000))
        model["gain_tc_per_c"] = (float(rng.uniform(-0.0025, -0.0015)), float(rng.uniform(-0.0025, -0.0015)))
        model["offset_counts"] = (0.0, 0.0)
        truth[effect] = {}
    else:
        raise AssertionError(effect)


def draw(seed: int, effects: tuple[str, ...], style: str):
    rng = np.random.default_rng(seed)
    model = baseline_model(rng, style)
    truth: dict = {}
    for effect in effects:
        plant(effect, rng, model, style, truth)
    if style == "bench":
        profile = bench_profile(rng=rng)
        samples = record(EncoderModel(**model), profile, rng)
    else:
        cold = "adc_clipping" in effects
        profile = field_profile(
            2.0, sample_s=10.0, rng=rng, ambient_c=-10.0 if cold else 25.0, load_rise_c=20.0 if cold else 40.0
        )
        samples = record(EncoderModel(**model), profile, rng, reference=False)
    return samples, truth


def check(report, truth, style):
    named = sorted(f["cause"] for f in report["findings"])
    assert named == sorted(truth), f"named {named}, planted {sorted(truth)}: {report['findings']}"
    assert set(named) <= set(CAUSES)
    by = {f["cause"]: f for f in report["findings"]}
    for cause, want in truth.items():
        got = by[cause]["parameters"]
        f = by[cause]
        assert f["rms_error_deg_after"] < f["rms_error_deg_before"]
        assert f["evidence"]
        if cause == "zero_offset":
            assert got["offset_deg"] == pytest.approx(want["offset_deg"], abs=0.05)
        elif cause == "phase_nonorthogonality":
            assert got["phase_error_deg"] == pytest.approx(want["phase_error_deg"], rel=0.15)
        elif cause == "phase_drift":
            assert got["phase_drift_deg_per_c"] == pytest.approx(want["phase_drift_deg_per_c"], rel=0.15)
        elif cause == "harmonic_distortion":
            assert got["order"] == want["order"]
            assert got["amplitude"] == pytest.approx(want["amplitude"], rel=0.15)
        elif cause == "thermal_lag":
            assert got["tau_s"] == pytest.approx(want["tau_s"], rel=0.25)
        elif cause == "nonlinear_temperature":
            for axis in (0, 1):
                assert got["gain_tc2_per_c2"][axis] == pytest.approx(want["gain_tc2_per_c2"][axis], rel=0.25)
        elif cause == "aging":
            if "offset_per_khour" in want:
                axis = int(np.argmax(np.abs(want["offset_per_khour"])))
                assert got["offset_per_khour"][axis] == pytest.approx(want["offset_per_khour"][axis], rel=0.2)
            else:
                for axis in (0, 1):
                    assert got["gain_loss_per_khour"][axis] == pytest.approx(want["gain_loss_per_khour"], rel=0.25)
        elif cause == "outliers":
            assert got["fraction"] == pytest.approx(want["fraction"], rel=0.3)
        elif cause == "adc_clipping":
            assert 0 < got["fraction"] < 0.5
    if truth:
        gain = report["baseline"]["rms_error_deg"] / report["extended"]["rms_error_deg"]
        assert gain >= 2.0, f"gain only {gain:.2f}x: {report}"
    else:
        assert report["extended"]["rms_error_deg"] == report["baseline"]["rms_error_deg"]


BENCH = [
    (0, ()),
    (1, ()),
    (2, ()),
    (3, ()),
    (4, ()),
    (10, ("zero_offset",)),
    (11, ("phase_nonorthogonality",)),
    (12, ("phase_drift",)),
    (13, ("harmonic",)),
    (14, ("harmonic",)),
    (15, ("harmonic:3",)),
    (22, ("harmonic",)),
    (16, ("thermal_lag",)),
    (17, ("thermal_lag",)),
    (23, ("thermal_lag",)),
    (18, ("nonlinear_temperature",)),
    (19, ("aging",)),
    (20, ("outliers",)),
    (21, ("adc_clipping",)),
    (30, ("zero_offset", "harmonic")),
    (31, ("thermal_lag", "harmonic:3")),
    (32, ("phase_drift", "outliers")),
    (33, ("zero_offset", "phase_nonorthogonality")),
    (34, ("adc_clipping", "harmonic")),
]
FIELD = [
    (100, ()),
    (101, ()),
    (102, ()),
    (103, ()),
    (104, ()),
    (110, ("phase_nonorthogonality",)),
    (111, ("phase_drift",)),
    (112, ("harmonic",)),
    (113, ("thermal_lag",)),
    (118, ("thermal_lag",)),
    (119, ("harmonic",)),
    (114, ("nonlinear_temperature",)),
    (115, ("aging",)),
    (116, ("outliers",)),
    (117, ("adc_clipping",)),
    (130, ("thermal_lag", "harmonic")),
    (131, ("aging", "outliers")),
    (132, ("adc_clipping", "harmonic")),
]


@pytest.mark.parametrize("seed,effects", BENCH, ids=[f"bench-{s}-{'+'.join(e) or 'clean'}" for s, e in BENCH])
def test_bench_recording_names_what_was_planted(seed, effects):
    samples, truth = draw(seed, effects, "bench")
    report = diagnose(samples).report
    assert report["has_reference"] and report["error_metric"] == "reference"
    assert report["samples"] == len(samples)
    check(report, truth, "bench")


@pytest.mark.parametrize("seed,effects", FIELD, ids=[f"field-{s}-{'+'.join(e) or 'clean'}" for s, e in FIELD])
def test_field_recording_names_what_was_planted(seed, effects):
    samples, truth = draw(seed, effects, "field")
    report = diagnose(samples).report
    assert not report["has_reference"] and report["error_metric"] == "radius"
    assert {"cause": "zero_offset"}.items() <= report["not_testable"][0].items()
    check(report, truth, "field")


def test_without_temperature_thermal_causes_are_not_testable():
    rng = np.random.default_rng(3)
    model = EncoderModel(
        **{
            **baseline_model(rng, "bench"),
            "gain_tc_per_c": (0.0, 0.0),
            "offset_tc_counts_per_c": (0.0, 0.0),
            "harmonics": ((5, 0.01, 1.0),),
        }
    )
    samples = record(model, bench_profile(rng=rng), rng, temperature=False)
    report = diagnose(samples).report
    untestable = {n["cause"] for n in report["not_testable"]}
    assert {"phase_drift", "thermal_lag", "nonlinear_temperature"} <= untestable
    assert [f["cause"] for f in report["findings"]] == ["harmonic_distortion"]
    assert report["findings"][0]["parameters"]["order"] == 5
    assert "constant" in report["baseline"]["model"]


@pytest.mark.parametrize("zero_deg", [37.0, 175.0])
def test_large_zero_offset_is_named_in_full(zero_deg):
    """The encoder's zero need not be near the machine's: even past a quarter turn, where the
    axis-aligned baseline's gains turn negative, the named offset is the whole offset."""
    rng = np.random.default_rng(int(zero_deg))
    model = EncoderModel(**{**baseline_model(rng, "bench"), "zero_offset_rad": np.radians(zero_deg)})
    report = diagnose(record(model, bench_profile(rng=rng), rng)).report
    assert [f["cause"] for f in report["findings"]] == ["zero_offset"]
    assert report["findings"][0]["parameters"]["offset_deg"] == pytest.approx(zero_deg, abs=0.05)
