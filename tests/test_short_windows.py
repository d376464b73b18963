"""Offset steps on drives whose windows are too short to fit (`DeviceMonitor._short_block`), on drives from the
independent simulator (encoder_fleet/fieldsim.py): the step's time, size, channel and sign are drawn from the seed,
and the monitor sees only window statistics.

At 5 Hz a 10 s window holds 50 samples, under the ellipse's MIN_FIT_SAMPLES: no window alone gives offsets, a gain
ratio or a skew, and until 2026-11-27 a drive sending such windows had no offset test at all (s1-5hz-11-reverse,
bench-fleet-accuracy --rates 5 --window-s 10: a 0.29 % offset step unnamed for the 15 hours left, five of them worse
than its factory set). Consecutive short windows are now summed until they hold short_block_samples, and the whole
circle's tests judge the block as one window."""

from __future__ import annotations

import numpy as np
import pytest

from encoder_core.monitor import MIN_FIT_SAMPLES, window_features
from encoder_core.physics import band_of
from encoder_core.stats import normalisation_scale, window_stats
from encoder_fleet import fieldsim
from encoder_fleet.calibrate import calibrate
from encoder_fleet.fleet_accuracy import windows_of
from tests.monitor_runs import step_alarms

DAYS = 0.5
RATE_HZ = 5.0
WINDOW_S = 10.0
NAMED_WITHIN_S = 3600.0  # within the hour the refit cadence allows


def short_window_drive(seed: int, motion: str, stepped: bool):
    """Half a day at 5 Hz; the offset step drawn whether or not it is planted, so that the clean drive is the same
    drive, sample for sample."""
    rng = np.random.default_rng([505, seed])
    phys = fieldsim.draw_drive(rng, days=DAYS)
    factory = calibrate(fieldsim.bench_sweep(phys, rng))
    step = fieldsim.draw_event(rng, "offset_step", days=DAYS)
    if stepped:
        phys.events.append(step)
    run = fieldsim.field_run(phys, days=DAYS, rate_hz=RATE_HZ, regime=motion, rng=rng)
    return factory, run, step


def test_no_short_window_can_be_fitted_alone():
    """The premise: every window is under MIN_FIT_SAMPLES, so no window of its own has offsets to judge."""
    factory, run, _ = short_window_drive(0, "reverse", stepped=False)
    scale = normalisation_scale(factory)
    for start, end in windows_of(run.samples.t, WINDOW_S)[:200]:
        stats = window_stats(run.samples.subset(slice(start, end)), scale)
        assert stats.n < MIN_FIT_SAMPLES
        features = window_features(stats, t=float(run.samples.t[end - 1]), temp_c=20.0, band=band_of(20.0))
        assert features.y is None and features.stats is not None


@pytest.mark.parametrize(("motion", "must_name"), [("reverse", 2), ("even", 3), ("random", 3)])
def test_an_offset_step_in_short_windows_is_named_and_sized_and_the_clean_drive_stays_quiet(motion, must_name):
    """Of three drives of each kind, every step named within the hour and sized within 35 %, nothing raised before it
    or twice, and nothing at all on the same drive without the step. A reversing drive over an arc under the arcs'
    arc_min_bins (135°) shows neither a block that covers the circle nor a pair of arcs to compare: seed 2's 112°
    arc is such a drive, its step unnamed."""
    named = 0
    for seed in range(3):
        factory, run, step = short_window_drive(seed, motion, stepped=True)
        truth = np.array([step.d_offset, step.q_offset]) / normalisation_scale(factory)  # of the amplitude
        raised, _ = step_alarms(run, factory, WINDOW_S, "offset_step")
        after = [(t, p) for t, p in raised if step.t_s <= t <= step.t_s + NAMED_WITHIN_S]
        assert len(raised) == len(after) <= 1, (motion, seed, raised, step)  # nothing before the step, nor twice
        if after:
            got = np.array([after[0][1]["delta_d"], after[0][1]["delta_q"]])
            assert np.linalg.norm(got - truth) < 0.35 * np.linalg.norm(truth), (motion, seed, got, truth)
            named += 1
        clean_factory, clean_run, _ = short_window_drive(seed, motion, stepped=False)
        quiet, _ = step_alarms(clean_run, clean_factory, WINDOW_S, "offset_step")
        assert quiet == [], (motion, seed, quiet)
    assert named >= must_name, (motion, named)
