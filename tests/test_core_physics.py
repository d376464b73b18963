"""The simulator's effects move the angle error the way seed 001's small-parameter formulas say."""

import numpy as np
import pytest

from encoder_core.physics import angle, angle_error_deg, wrap_rad
from encoder_core.simulator import EncoderModel, clean_signals, first_order_lag, simulate

THETA = np.linspace(0, 2 * np.pi, 720, endpoint=False)
ROOM = np.full(THETA.size, 20.0)


def error_rad(model):
    d, q = clean_signals(model, THETA, ROOM, 0.0)
    return wrap_rad(THETA - angle(d, q))  # seed 001's ε = θ - φ


@pytest.mark.parametrize("alpha", [0.01, 0.03, -0.02])
def test_amplitude_imbalance_follows_eq8(alpha):
    eps = error_rad(EncoderModel(amplitude_imbalance=alpha))
    predicted = alpha / 2 * np.sin(2 * THETA)
    assert np.max(np.abs(eps - predicted)) < 0.6 * alpha**2 + 1e-12


@pytest.mark.parametrize("beta_deg", [0.5, 2.0, -1.5])
def test_phase_error_follows_eq14(beta_deg):
    beta = np.radians(beta_deg)
    eps = error_rad(EncoderModel(phase_error_rad=beta))
    predicted = -beta / 2 * (1 - np.cos(2 * THETA))
    assert np.max(np.abs(eps - predicted)) < beta**2
    assert np.max(np.abs(eps)) > 0.9 * abs(beta)  # the effect is really there


@pytest.mark.parametrize("n,k", [(3, 0.01), (5, 0.005), (2, 0.008)])
def test_harmonic_follows_eq18(n, k):
    eps = error_rad(EncoderModel(harmonics=((n, k, 0.0),)))
    predicted = -k * np.sin((n - 1) * THETA)
    assert np.max(np.abs(eps - predicted)) < 2 * k * k
    assert np.max(np.abs(eps)) > 0.9 * k


def test_temperature_gain_drift_follows_seed000_eq4_5():
    model = EncoderModel(gain_tc_per_c=(-0.002, -0.001), offset_tc_counts_per_c=(0.5, -0.2))
    d20, q20 = clean_signals(model, THETA, ROOM, 0.0)
    dc, qc = clean_signals(model, THETA, np.full(THETA.size, -40.0), 0.0)
    k1 = 1 + (-0.002) * (-60)
    assert np.allclose(dc, k1 * d20 + 0.5 * (-60))
    assert np.allclose(qc, (1 + 0.06) * q20 - 0.2 * (-60))


def test_thermal_lag_is_first_order():
    t = np.arange(0, 3000.0, 1.0)
    step = np.where(t > 0, 60.0, 20.0)
    die = first_order_lag(t, step, 300.0, y0=20.0)
    at_tau = die[np.searchsorted(t, 301.0)]
    assert abs((at_tau - 20) / 40 - (1 - np.exp(-1))) < 0.01


def test_zero_offset_and_clipping():
    model = EncoderModel(zero_offset_rad=np.radians(5.0), hall_amplitude=1900.0, gain_tc_per_c=(-0.003, -0.003))
    rng = np.random.default_rng(0)
    s, _ = simulate(model, np.arange(THETA.size, dtype=float), THETA, np.full(THETA.size, -40.0), rng)
    assert s.halls["a_plus"].max() == 4095 and s.halls["a_plus"].min() == 0  # 1900·1.18 > 2047: clipped
    warm, _ = simulate(model.with_(hall_amplitude=900.0), np.arange(THETA.size, dtype=float), THETA, ROOM, rng)
    err = angle_error_deg(angle(warm.d, warm.q), THETA)
    assert abs(np.mean(err) - 5.0) < 0.05
