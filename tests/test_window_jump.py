"""The monitor's window-to-window jump test (`encoder_core.monitor.WindowJump`) on drives from the independent
simulator (encoder_fleet/fieldsim.py): each step's time, size, sign and channel are drawn from the seed, and the
monitor sees only window statistics.

An offset step as small as the smallest planted in bench-fleet-accuracy, on drives that show the circle: named
within minutes by the jump test on each channel's offset (the monitor's `offset_jump`), sized, and nothing raised on
the same drives without it. The offset CUSUM alone, whose reference is half its `step_min` (0.25 % of the
amplitude), took 3-75 minutes for these steps (s3-20hz-11-reverse: 0.29 %, named ageing, the pre-step set ran
2.6 hours, two of them worse than the factory's)."""

from __future__ import annotations

import numpy as np

from encoder_core.stats import normalisation_scale
from encoder_fleet import fieldsim
from encoder_fleet.calibrate import calibrate
from tests.monitor_runs import offset_step_alarms

SEEDS = range(4)
WINDOW_S = 60.0


def small_step_drive(seed: int, stepped: bool):
    rng = np.random.default_rng([505, seed])
    phys = fieldsim.draw_drive(rng, days=1.0)
    factory = calibrate(fieldsim.bench_sweep(phys, rng))
    regime = ("even", "random")[seed % 2]
    size = float(rng.uniform(0.0025, 0.003) * phys.amplitude * rng.choice([-1.0, 1.0]))
    if stepped:
        on_d = bool(rng.integers(2))
        phys.events.append(
            fieldsim.Event(
                float(rng.uniform(0.4, 0.7) * fieldsim.DAY_S),
                "offset_step",
                d_offset=size if on_d else 0.0,
                q_offset=0.0 if on_d else size,
            )
        )
    return phys, factory, fieldsim.field_run(phys, days=1.0, rate_hz=20.0, regime=regime, rng=rng)


def test_a_small_offset_step_is_named_within_minutes_and_sized_and_clean_drives_stay_quiet():
    for seed in SEEDS:
        phys, factory, run = small_step_drive(seed, stepped=True)
        step = phys.events[0]
        truth = np.array([step.d_offset, step.q_offset]) / normalisation_scale(factory)
        raised, _ = offset_step_alarms(run, factory, WINDOW_S)
        assert len(raised) == 1, (seed, step, raised)
        (at, params) = raised[0]
        assert step.t_s <= at <= step.t_s + 4 * WINDOW_S, (seed, step.t_s, at)  # within four windows
        measured = np.array([params["delta_d"], params["delta_q"]])
        assert np.hypot(*(measured - truth)) < 0.25 * np.hypot(*truth), (seed, measured, truth)
        _, clean_factory, clean = small_step_drive(seed, stepped=False)
        assert offset_step_alarms(clean, clean_factory, WINDOW_S)[0] == [], seed
