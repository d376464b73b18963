"""Encoders age: with a horizon on each band's sum, refits follow the drive instead of its history."""

import numpy as np

from edge_agent.sources import SimulatedDrive, drive_model, evaluation_set, factory_calibration
from encoder_core.correction import BandedCorrection
from encoder_core.physics import angle_error_deg, rms
from encoder_core.stats import WindowStats, window_stats
from fleet_wire import messages as wire
from service.refit import refit_device
from service.store import Store

DEVICE = "drive-age"
HOURS = 48
HORIZON_H = 12.0  # drive time each band remembers: one temperature cycle


def test_band_horizon_follows_an_aging_drive(tmp_path):
    seed = 6
    model = drive_model(seed).with_(aging_offset_counts_per_khour=(400.0, -300.0))  # +19 / -14 counts in 48 h
    factory = factory_calibration(model, seed)  # written at the factory, when the drive was new
    scale = float(round(1 / factory.bands[0].w1))
    stores = {
        "all history": Store.open(tmp_path / "all.sqlite"),
        "horizon": Store.open(tmp_path / "horizon.sqlite", band_horizon_s=HORIZON_H * 3600),
    }
    source = SimulatedDrive(seed, hours=HOURS, model=model)
    messages = []
    while (block := source.read(60.0)) is not None:
        stats = window_stats(block, scale)
        messages.append(
            wire.window_message(
                DEVICE,
                len(messages) + 1,
                stats,
                window_start=float(block.t[0]),
                window_end=float(block.t[-1]),
                temp_rate_c_per_s=0.0,
                coefficients_version=0,
                angle_quality_deg=0.0,
            )
        )
    truth = evaluation_set(model.with_(noise_counts=0.0), seed, hours=HOURS)  # the drive as it is now
    errors = {}
    for name, store in stores.items():
        with store.transaction():
            for msg in messages:
                assert store.insert_window(msg)
        bands = {b: s for b, (s, _, _) in store.band_stats(DEVICE).items()}
        fleet = BandedCorrection.from_dict({"bands": refit_device(bands, factory, factory).bands})
        errors[name] = rms(angle_error_deg(fleet.angle(truth.d, truth.q, truth.temp_c), truth.theta_ref))
    print("rms angle error at end of life (deg):", errors)
    assert errors["horizon"] < 0.7 * errors["all history"], errors

    # the horizon store keeps every window, and each band's sum is exactly the windows that ended within
    # HORIZON_H of the band's newest (memory in drive time, not a window count)
    store = stores["horizon"]
    assert store.device(DEVICE)["windows"] == len(messages)
    for band, (total, windows, samples) in store.band_stats(DEVICE).items():
        in_band = [m for m in messages if m["band"] == band]
        mine = [m for m in in_band if m["window_end"] >= in_band[-1]["window_end"] - HORIZON_H * 3600]
        expected = WindowStats.from_dict(mine[0]["stats"])
        for m in mine[1:]:
            expected = expected.merge(WindowStats.from_dict(m["stats"]))
        assert windows == len(mine) and samples == sum(m["samples"] for m in mine)
        assert np.allclose(total.moments, expected.moments, rtol=1e-9, atol=1e-6)
        assert np.allclose(total.bins, expected.bins, rtol=1e-9, atol=1e-6)
    for s in stores.values():
        s.close()
