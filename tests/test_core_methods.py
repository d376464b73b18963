"""Each method recovers planted parameters; bad input gets a clear error."""

import numpy as np
import pytest

from encoder_core.correction import BandedCorrection, Correction
from encoder_core.ellipse import density_harmonics, fit_ellipse
from encoder_core.methods import OursEllipse, OursLsRef, OursLsTable, ReferenceTable, Seed000, Seed001, stats_for
from encoder_core.physics import angle_error_deg, error_summary, rms
from encoder_core.samples import InputError, Samples
from encoder_core.simulator import EncoderModel, bench_profile, record, simulate
from encoder_core.stats import WindowStats


def sweep(model, temp, rng, positions=3600):
    return record(model, bench_profile((temp,), positions=positions, soak_s=0.0), rng)


def held_out(samples):
    even = np.arange(len(samples)) % 2 == 0
    return samples.subset(even), samples.subset(~even)


@pytest.fixture
def rng():
    return np.random.default_rng(7)


def test_seed000_recovers_gain_ratio(rng):
    model = EncoderModel(gain_tc_per_c=(-0.002, -0.001), noise_counts=0.5)
    table = ReferenceTable.from_samples(sweep(model, 20.0, rng))
    train, test = held_out(sweep(model, -40.0, rng))
    method = Seed000().fit(train, table)
    band = method.correction_.bands[0]
    assert band.w1 == pytest.approx(1 / 1.12, rel=0.01)  # k1(-40) = 1 + 0.002·60
    assert band.w3 == pytest.approx(1 / 1.06, rel=0.01)
    assert method.descents_[0].history[-1] < 0.01 * method.descents_[0].history[0]
    assert error_summary(method.correct(test), test.theta_ref)["rms_error_deg"] < 0.1


def test_ls_table_matches_seed000_target(rng):
    model = EncoderModel(gain_tc_per_c=(-0.002, -0.001), offset_tc_counts_per_c=(0.4, -0.3), noise_counts=1.0)
    table = ReferenceTable.from_samples(sweep(model, 20.0, rng))
    train, test = held_out(sweep(model, 60.0, rng))
    gd = Seed000().fit(train, table).correct(test)
    ls = OursLsTable().fit(train, table).correct(test)
    assert rms(angle_error_deg(ls, gd)) < 0.02  # same answer, one step


def test_seed001_recovers_phase(rng):
    beta = np.radians(2.5)
    model = EncoderModel(phase_error_rad=beta, amplitude_imbalance=0.04, noise_counts=1.0)
    train, test = held_out(sweep(model, 20.0, rng))
    method = Seed001().fit(train)
    assert method.betas_[0] == pytest.approx(beta, abs=np.radians(0.05))
    assert error_summary(method.correct(test), test.theta_ref)["max_error_deg"] < 0.5


def test_ls_ref_recovers_zero_offset_phase_and_harmonic(rng):
    model = EncoderModel(
        zero_offset_rad=np.radians(7.0),
        phase_error_rad=np.radians(-2.0),
        amplitude_imbalance=0.03,
        offset_counts=(25.0, -15.0),
        harmonics=((3, 0.01, 0.4),),
        noise_counts=1.0,
    )
    train, test = held_out(sweep(model, 20.0, rng))
    method = OursLsRef().fit(train)
    err = error_summary(method.correct(test), test.theta_ref)
    assert err["rms_error_deg"] < 0.08 and err["max_error_deg"] < 0.3
    # the weights take d as the axis, and d carries the phase error: the rotation left is zero + β
    assert method.correction_.bands[0].zero_offset_rad == pytest.approx(-np.radians(7.0 - 2.0), abs=np.radians(0.1))


def test_ellipse_recovers_offsets_and_density_finds_hidden_harmonic():
    rng = np.random.default_rng(11)
    k = rng.uniform(0.006, 0.012)
    phase = rng.uniform(-np.pi, np.pi)
    model = EncoderModel(
        offset_counts=(30.0, -20.0), amplitude_imbalance=0.04, harmonics=((3, k, phase),), noise_counts=1.5
    )
    n = 300_000
    theta = rng.uniform(0, 2 * np.pi, n)
    s, _ = simulate(model, np.arange(n) * 0.01, theta, np.full(n, 20.0), rng)
    stats = stats_for(s)
    fit = fit_ellipse(stats)
    center = np.array([stats.center_d, stats.center_q]) + stats.scale * fit.center
    assert center == pytest.approx([30.0, -20.0], abs=1.0)
    found = density_harmonics(stats, fit).significant()
    assert set(found) == {2}  # the 3rd harmonic shows as a 2θ angle error; nothing else is significant
    corr = OursEllipse().fit(s).correction_
    err = angle_error_deg(corr.angle(s.d, s.q, s.temp_c), theta)
    assert rms(err - np.mean(err)) < 0.12  # noise floor is about 0.09°; the zero is not observable


def test_window_stats_merge_in_any_order_equals_one_pass(rng):
    model = EncoderModel(noise_counts=2.0, phase_error_rad=0.02)
    n = 9000
    s, _ = simulate(model, np.arange(n) * 0.1, rng.uniform(0, 2 * np.pi, n), rng.uniform(-40, 80, n), rng)
    whole = WindowStats(scale=1400.0).add(s.d, s.q, s.temp_c)
    parts = [WindowStats(scale=1400.0).add(s.d[i::3], s.q[i::3], s.temp_c[i::3]) for i in range(3)]
    merged = parts[2].merge(parts[0]).merge(parts[1])
    assert np.allclose(merged.moments, whole.moments, rtol=1e-12)
    assert np.array_equal(merged.bins[:, 0], whole.bins[:, 0])
    assert merged.temp_min == whole.temp_min and merged.temp_n == n
    assert WindowStats.from_dict(merged.to_dict()).to_dict() == merged.to_dict()
    with pytest.raises(InputError, match="normalisation"):
        merged.merge(WindowStats(scale=1000.0))


def test_banded_correction_interpolates_and_round_trips():
    cold = Correction(w1=1.1, w2=5.0, w3=1.05, w4=-3.0, w5=0.01, harmonics={2: (0.001, 0.0)}, temp_c=-40.0)
    hot = Correction(w1=0.9, w2=-5.0, w3=0.95, w4=3.0, harmonics={3: (0.0, 0.002)}, temp_c=60.0)
    banded = BandedCorrection([hot, cold])
    mid = Correction(w1=1.0, w2=0.0, w3=1.0, w4=0.0, w5=0.005, harmonics={2: (0.0005, 0.0), 3: (0.0, 0.001)})
    d, q = np.array([100.0, -50.0]), np.array([20.0, 80.0])
    assert np.allclose(banded.angle(d, q, np.array([10.0, 10.0])), mid.angle(d, q))
    assert np.allclose(banded.angle(d, q, np.array([-90.0, -90.0])), cold.angle(d, q))
    again = BandedCorrection.from_dict(banded.to_dict())
    assert np.allclose(again.angle(d, q, np.array([0.0, 33.0])), banded.angle(d, q, np.array([0.0, 33.0])))


@pytest.mark.parametrize("method_cls", [Seed000, Seed001, OursLsTable, OursLsRef, OursEllipse])
def test_bad_input_gets_a_clear_error(method_cls, rng):
    good = sweep(EncoderModel(noise_counts=1.0), 20.0, rng, positions=360)
    table = ReferenceTable.from_samples(good)
    nan = good.subset(np.arange(len(good)))
    nan.d[17] = np.nan
    with pytest.raises(InputError, match="non-finite.*index 17"):
        method_cls().fit(nan, table)
    with pytest.raises(InputError, match="empty|too few"):
        method_cls().fit(good.subset(np.zeros(len(good), bool)), table)
    with pytest.raises(InputError, match="lengths must match|expected"):
        method_cls().fit(Samples(t=good.t, d=good.d, q=good.q[:-1]), table)
    narrow = good.subset(good.theta_ref < np.radians(40))
    with pytest.raises(InputError, match="coverage|distinct"):
        method_cls().fit(narrow, table)


def test_reference_table_needs_distinct_angles(rng):
    few = sweep(EncoderModel(), 20.0, rng, positions=8)
    with pytest.raises(InputError, match="distinct reference angles"):
        ReferenceTable.from_samples(few)


NON_DEFAULT_PARAMS = {
    Seed000: {"step": 0.002, "max_iter": 50, "data_scale": 0.01},
    Seed001: {"median_window": 3, "mean_window": 7, "a_out": 1.0},
    OursLsTable: {},
    OursLsRef: {"harmonic_orders": [2, 3], "outlier_tolerance": None},
    OursEllipse: {"harmonics_from_density": False, "outlier_tolerance": 0.2},
}


@pytest.mark.parametrize("method_cls", list(NON_DEFAULT_PARAMS))
def test_constructor_stores_parameters_verbatim_and_learns_nothing(method_cls):
    params = NON_DEFAULT_PARAMS[method_cls]
    method = method_cls(**params)
    assert vars(method) == params  # nothing derived, nothing learned before fit
    for key, value in params.items():
        assert getattr(method, key) is value
    with pytest.raises(InputError, match="fit before correct"):
        method.correct(Samples(t=np.arange(3.0), d=np.ones(3), q=np.ones(3)))


@pytest.mark.parametrize("method_cls", [Seed000, Seed001, OursLsTable, OursLsRef, OursEllipse])
def test_second_fit_leaves_nothing_stale(method_cls, rng):
    """Fit on three temperature bands, then on one: every learned attribute is the one-band fit's."""
    model = EncoderModel(gain_tc_per_c=(-0.002, -0.001), phase_error_rad=0.01, noise_counts=1.0)
    table = ReferenceTable.from_samples(sweep(model, 20.0, rng, positions=720))
    wide = concat_samples([sweep(model, temp, rng, positions=720) for temp in (-30.0, 20.0, 70.0)])
    narrow = sweep(model, 40.0, rng, positions=720)
    refitted = method_cls().fit(wide, table).fit(narrow, table)
    fresh = method_cls().fit(narrow, table)
    learned = {k for k in vars(fresh) if k.endswith("_")}
    assert "correction_" in learned and set(vars(refitted)) == set(vars(fresh))
    assert len(refitted.correction_.bands) == 1
    assert refitted.correction_.to_dict() == fresh.correction_.to_dict()
    if method_cls.band_record:
        assert len(getattr(refitted, method_cls.band_record)) == 1
    assert np.array_equal(refitted.correct(narrow), fresh.correct(narrow))


def concat_samples(parts):
    return Samples(
        t=np.concatenate([p.t + 1e4 * i for i, p in enumerate(parts)]),
        d=np.concatenate([p.d for p in parts]),
        q=np.concatenate([p.q for p in parts]),
        temp_c=np.concatenate([p.temp_c for p in parts]),
        theta_ref=np.concatenate([p.theta_ref for p in parts]),
    )
