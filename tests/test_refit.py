"""The service's refit, fed the agent's window statistics of a simulated drive (no transport here)."""

import pytest

from edge_agent.sources import SimulatedDrive, drive_model, evaluation_set, factory_calibration
from encoder_core.correction import BandedCorrection, Correction
from encoder_core.physics import band_of, error_summary
from encoder_core.stats import window_stats
from service.refit import LEGACY_MIN_SAMPLES, MIN_BAND_SAMPLES, refit_device


def band_stats_of(seed, hours, scale):
    bands = {}
    source = SimulatedDrive(seed, hours=hours)
    while (block := source.read(60.0)) is not None:
        stats = window_stats(block, scale)
        band = band_of(stats.temp_mean)
        bands[band] = bands[band].merge(stats) if band in bands else stats
    return bands


@pytest.mark.parametrize("seed", [3, 11])
def test_refit_beats_factory_fivefold_across_the_cycle(seed):
    model = drive_model(seed)
    factory = factory_calibration(model, seed)
    bands = band_stats_of(seed, 24, float(round(1 / factory.bands[0].w1)))
    result = refit_device(bands, factory, factory)
    assert result.changed
    fleet = BandedCorrection.from_dict({"bands": result.bands})
    truth = evaluation_set(model.with_(noise_counts=0.0), seed)  # scores the coefficients, not sensor noise
    before = error_summary(factory.angle(truth.d, truth.q, truth.temp_c), truth.theta_ref)["rms_error_deg"]
    after = error_summary(fleet.angle(truth.d, truth.q, truth.temp_c), truth.theta_ref)["rms_error_deg"]
    assert after * 5 < before, (before, after)


def test_refit_leaves_a_right_set_alone():
    seed = 5
    model = drive_model(seed)
    factory = factory_calibration(model, seed)
    bands = band_stats_of(seed, 24, float(round(1 / factory.bands[0].w1)))
    first = refit_device(bands, factory, factory)
    rolled_out = BandedCorrection.from_dict({"bands": first.bands})
    again = refit_device(bands, rolled_out, factory)
    assert not again.changed  # same statistics, same answer: no churn of versions
    adopted_first = {d.band for d in first.decisions if d.adopted}
    assert adopted_first
    assert all(d.running_error_deg < 1e-6 for d in again.decisions if d.band in adopted_first)


@pytest.mark.parametrize("bench_locus, hours", [(True, 0.02), (False, 0.1)])
def test_too_few_samples_gives_no_fit(bench_locus, hours):
    # with the bench locus a band needs MIN_BAND_SAMPLES (one minute at 20 Hz is fewer); without it, the density
    # harmonics need LEGACY_MIN_SAMPLES (six minutes are fewer)
    seed = 2
    factory = factory_calibration(drive_model(seed), seed)
    if not bench_locus:
        factory = BandedCorrection([Correction.from_dict({**c.to_dict(), "bench_locus": None}) for c in factory.bands])
    bands = band_stats_of(seed, hours, float(round(1 / factory.bands[0].w1)))
    assert 0 < sum(s.n for s in bands.values()) < (MIN_BAND_SAMPLES if bench_locus else LEGACY_MIN_SAMPLES)
    result = refit_device(bands, factory, factory)
    assert not result.changed and not result.decisions


@pytest.mark.parametrize("bench_locus", [True, False])
def test_bands_the_refit_says_nothing_about_stay_as_the_device_runs_them(bench_locus):
    # a set of only the fitted band would hold that band's correction at every temperature
    seed = 3
    factory = factory_calibration(drive_model(seed), seed)
    if not bench_locus:
        factory = BandedCorrection([Correction.from_dict({**c.to_dict(), "bench_locus": None}) for c in factory.bands])
    running = BandedCorrection(
        [Correction.from_dict({**factory.bands[0].to_dict(), "temp_c": t, "bench_locus": None}) for t in (-25, 25, 55)]
    )
    bands = band_stats_of(seed, 24, float(round(1 / factory.bands[0].w1)))
    fitted = max(bands, key=lambda b: bands[b].n)
    result = refit_device({fitted: bands[fitted]}, running, factory)
    assert {d.band for d in result.decisions} == {fitted}
    by_band = {b["band"]: b for b in result.bands}
    for corr in running.bands:
        band = int(band_of(corr.temp_c))
        if band != fitted:
            assert by_band[band]["w"] == corr.to_dict()["w"] and by_band[band]["temp_c"] == corr.temp_c
