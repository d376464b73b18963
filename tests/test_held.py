"""A drive that holds a few positions (a servo) and never shows the ellipse enough of the circle: an offset step
is still named, from the positions it holds (encoder_core/held.py, the monitor's `_held_step`). Drives from the
independent simulator (encoder_fleet/fieldsim.py); the drive, its positions and the step's time, size and axis
are drawn from the seed, and the monitor sees only window statistics."""

from __future__ import annotations

import math

import numpy as np

from edge_agent.agent import factory_message
from encoder_core.correction import BandedCorrection
from encoder_core.held import held_drift_model, held_points
from encoder_core.monitor import DeviceMonitor, Settings, window_features
from encoder_core.physics import band_of
from encoder_core.samples import Samples
from encoder_core.stats import WindowStats, normalisation_scale, window_stats
from encoder_fleet import fieldsim
from encoder_fleet.calibrate import calibrate
from encoder_fleet.fleet_accuracy import drive_of, fleet_loop, fleet_specs, score, windows_of, worse_than
from service.refit import bench_anchors, difference_deg, refit_device, step_moved_bands
from service.trial import MIN_SOAK_SAMPLES, TrialEvidence, judge
from tests.monitor_runs import monitored, moved_for_offset_steps, offset_step_alarms, step_alarms

SEEDS = range(4)


def dwelling_drive(seed: int, event: str | None):
    rng = np.random.default_rng([404, seed])
    phys = fieldsim.draw_drive(rng, event=event, days=1.0)
    factory = calibrate(fieldsim.bench_sweep(phys, rng))
    return phys, factory, fieldsim.field_run(phys, days=1.0, rate_hz=20.0, regime="dwell", rng=rng)


def half_day_dwelling(rng):
    """(physics, factory set, run) of a drive holding positions for half a day at 20 Hz."""
    phys = fieldsim.draw_drive(rng, days=0.5)
    factory = calibrate(fieldsim.bench_sweep(phys, rng))
    return phys, factory, fieldsim.field_run(phys, days=0.5, rate_hz=20.0, regime="dwell", rng=rng)


def remeasured(phys, run, rng):
    """The same shaft, temperature and clock measured again by phys (after events were planted in it)."""
    d, q = phys.measure(run.theta, run.die_c, run.samples.t, rng)
    samples = Samples(t=run.samples.t, d=d, q=q, temp_c=run.samples.temp_c)
    return fieldsim.FieldRun(samples, run.theta, run.die_c, phys, run.regime, run.rate_hz)


def stepped_by(phys, run, rng, event: fieldsim.Event):
    """remeasured with one event planted in phys for this measurement only."""
    phys.events.append(event)
    try:
        return remeasured(phys, run, rng)
    finally:
        phys.events.remove(event)


def amplitude_of(phys, channel: int) -> float:
    """A channel's amplitude (counts, 0 d, 1 q) over one turn at 20 °C."""
    circle = np.linspace(0, 2 * np.pi, 360, endpoint=False)
    return float(np.ptp(phys.channels(circle, np.full(360, 20.0), np.zeros(360))[channel]) / 2)


def measured_shaft(phys, t, theta, temp, rng) -> Samples:
    """What phys reads of a shaft at theta (rad) at times t, the die lagging the reported temperature temp."""
    d, q = phys.measure(theta % (2 * np.pi), fieldsim.lagged_fast(temp, t, phys.die_lag_s), t, rng)
    return Samples(t=t, d=d, q=q, temp_c=temp)


def with_offset_step(phys, run, rng, t_step: float, low: float, high: float):
    """The same drive and shaft with an offset step at t_step of low-high of amplitude (sign and axis drawn from
    rng): (the stepped run, the step in counts, its axis: 0 d, 1 q)."""
    size = rng.uniform(low, high) * amplitude_of(phys, 0) * rng.choice([-1.0, 1.0])
    axis = rng.integers(2)
    phys.events.append(fieldsim.Event(t_step, "offset_step", d_offset=size * (axis == 0), q_offset=size * (axis == 1)))
    return remeasured(phys, run, rng), size, axis


def sized_hit(hits: list[dict], factory, size: float, axis: int) -> bool:
    """Whether an alarm named the step with_offset_step planted; the first one's size must be within a quarter."""
    if not hits:
        return False
    measured = np.array([hits[0]["delta_d"], hits[0]["delta_q"]]) * normalisation_scale(factory)
    truth = np.array([size * (axis == 0), size * (axis == 1)])
    assert np.hypot(*(measured - truth)) < 0.25 * abs(size), (measured, truth)
    return True


def test_offset_steps_are_named_where_the_drive_holds_positions_and_clean_drives_stay_quiet():
    named = 0
    for seed in SEEDS:
        phys, factory, run = dwelling_drive(seed, "offset_step")
        step = phys.events[0].t_s
        raised = [t for t, _ in offset_step_alarms(run, factory)[0]]
        assert not [t for t in raised if t < step], (seed, step, raised)  # nothing before the step
        named += any(step <= t <= step + 3600 for t in raised)
        _, clean_factory, clean = dwelling_drive(seed, None)
        assert offset_step_alarms(clean, clean_factory)[0] == [], seed
    # a position must be held across the step to see it jump: most steps are named within the hour (7 of 8 on
    # another set of seeds)
    assert named >= 3, named


def test_windows_written_at_a_die_lag_name_the_held_steps_as_at_the_reported_temperature():
    """An agent running a set that carries a die lag writes its windows at its die estimate, which moves faster than
    the reported temperature while the die catches up after a bump; the held test's bars (held_match_c) were set on
    reported temperatures, and a first-order lag gives them back: T = die + τ·d(die)/dt (s10-20hz-14: at the die's
    temperature a gain step that fell inside a window went unnamed; test_a_step_kind_that_fails_its_checks_...
    guards that). The same drives (offset step and all else drawn from the seed), written with and without a lag
    (60-600 s, drawn from the seed; not the drive's own): the held test names the same steps, when it names them.
    (Every comparison read back at the reported temperature named false steps through the temperature map on two
    seeds of four, hours before the step.)"""
    steps = 0
    for seed in SEEDS:
        phys, factory, run = dwelling_drive(seed, "offset_step")
        lag = float(np.random.default_rng([406, seed]).uniform(60.0, 600.0))
        named = []
        for lag_used_s in (0.0, lag):
            monitor = DeviceMonitor("under-test")
            named.append(
                [
                    end_s
                    for end_s, event in monitored(run, factory, 60.0, monitor, lag_used_s=lag_used_s)
                    if event.kind == "raise" and event.cause == "offset_step"
                ]
            )
        assert named[1] == named[0], (seed, lag, named)
        steps += bool(named[0])
    assert steps >= 3, steps  # (test_offset_steps_are_named_...: most steps are named within the hour)


def test_held_points_are_where_the_drive_sat():
    """Each window's held points are positions the drive sat at (most of the window's samples within a tenth of a
    degree of one of them), and a window of a drive that turns holds none."""
    phys, factory, run = dwelling_drive(0, None)
    scale = normalisation_scale(factory)
    found = 0
    windows = windows_of(run.samples.t, 60.0)[:180]  # three hours
    for start, end in windows:
        block = run.samples.subset(slice(start, end))
        held = held_points(window_stats(block, scale))
        found += bool(held)
        raw = np.degrees(np.arctan2(block.q, block.d))
        for point, _ in held:
            near = np.abs((raw - np.degrees(np.arctan2(point[1], point[0])) + 180) % 360 - 180) < 0.1
            assert near.sum() >= 20
    assert found > 0.8 * len(windows)
    turning = fieldsim.field_run(phys, days=0.05, rate_hz=20.0, regime="random", rng=np.random.default_rng(1))
    assert held_points(window_stats(turning.samples, scale)) == []


def test_a_0_5_hz_drive_is_not_judged_on_its_held_positions():
    """300 s windows: the die's lag moves a held position by up to 0.2 % of amplitude between visits minutes apart,
    as much as a small step (at 600 s and 1 °C, clean 0.5 Hz drives raised an alarm every few hours): positions are
    only compared within held_match_s, which a 0.5 Hz window never is."""
    rng = np.random.default_rng([404, 1])
    phys = fieldsim.draw_drive(rng, event="offset_step", days=1.0)
    factory = calibrate(fieldsim.bench_sweep(phys, rng))
    run = fieldsim.field_run(phys, days=1.0, rate_hz=0.5, regime="dwell", rng=rng)
    scale = normalisation_scale(factory)
    monitor = DeviceMonitor("slow")
    raised, with_held, windows = [], 0, 0
    for start, end in windows_of(run.samples.t, 300.0):
        stats = window_stats(run.samples.subset(slice(start, end)), scale)
        if stats.temp_n:
            end_s = float(run.samples.t[end - 1])
            features = window_features(stats, t=end_s, temp_c=stats.temp_mean, band=band_of(stats.temp_mean))
            windows, with_held = windows + 1, with_held + bool(features.held)
            raised += [e for e in monitor.update(features) if e.kind == "raise"]
    assert with_held > 0.8 * windows  # the positions are found
    assert raised == [] and monitor.held_last  # remembered, never compared
    assert not monitor.watches_held_positions()  # so the refit takes no drift from them (service.refit.held_model)


def test_a_shaft_creeping_along_is_not_a_step():
    """A shaft that creeps (a fraction of a degree a minute, drawn from the seed) looks held in every window and its
    position moves between windows by as much as a step; but along the circle, and it keeps moving: a step moves
    once."""
    rng = np.random.default_rng([404, 99])
    phys = fieldsim.draw_drive(rng, event=None, days=0.25)
    factory = calibrate(fieldsim.bench_sweep(phys, rng))
    t = fieldsim.sample_times(0.25, 20.0, rng)
    temp = fieldsim.reported_temperature(t, rng)
    theta = rng.uniform(0, 2 * np.pi) + np.radians(rng.uniform(0.25, 0.6) / 60.0) * t
    samples = measured_shaft(phys, t, theta, temp, rng)
    scale = normalisation_scale(factory)
    monitor, moved, raised, last = DeviceMonitor("creeping"), 0, [], None
    for start, end in windows_of(t, 60.0):
        stats = window_stats(samples.subset(slice(start, end)), scale)
        features = window_features(stats, t=float(t[end - 1]), temp_c=stats.temp_mean, band=band_of(stats.temp_mean))
        raised += [e.cause for e in monitor.update(features) if e.kind == "raise"]
        if len(features.held) == 1 and last is not None:  # its move since the last window, as a step's size
            moved += float(np.hypot(features.held[0][0] - last[0], features.held[0][1] - last[1])) >= (
                monitor.settings.held_step_min
            )
        last = features.held[0] if len(features.held) == 1 else None
    assert moved > 30  # its moves between windows are as large as a step's
    assert "offset_step" not in raised


def test_a_servo_switching_between_two_positions_under_a_degree_apart_is_not_a_step():
    """A servo that holds two positions a fraction of a degree apart (0.3-0.8°, drawn from the seed), switching
    every 10-60 min: each switch moves the held position by 0.5-1.4 % of the amplitude, as a step would, but along
    the circle. Taken for one position (within a degree), each switch read as an offset step, and the set moved at
    each (s4-5hz-10-dwell: 62 sets in three days, 9× worse than its factory set). The monitor sees window statistics
    at 5 Hz and 60 s; no step is planted."""
    for seed in range(3):
        rng = np.random.default_rng([408, seed])
        phys = fieldsim.draw_drive(rng, event=None, days=0.5)
        factory = calibrate(fieldsim.bench_sweep(phys, rng))
        t = fieldsim.sample_times(0.5, 5.0, rng)
        temp = fieldsim.reported_temperature(t, rng)
        here, apart = rng.uniform(0, 2 * np.pi), np.radians(rng.uniform(0.3, 0.8))
        switches = np.cumsum(rng.uniform(600.0, 3600.0, size=int(t[-1] / 600.0) + 2))
        theta = here + apart * (np.searchsorted(switches, t) % 2)
        samples = measured_shaft(phys, t, theta, temp, rng)
        scale = normalisation_scale(factory)
        monitor, raised = DeviceMonitor("two-positions"), []
        for start, end in windows_of(t, 60.0):
            stats = window_stats(samples.subset(slice(start, end)), scale)
            at = float(t[end - 1])
            features = window_features(stats, t=at, temp_c=stats.temp_mean, band=band_of(stats.temp_mean))
            raised += [e.cause for e in monitor.update(features) if e.kind == "raise"]
        assert "offset_step" not in raised, (seed, raised)


def test_a_step_inside_a_window_is_named_from_the_visit_before():
    """A step that falls inside a window while the drive holds one position splits into two jumps, each under the bar
    (held_step_min): the window that straddles it and the one after. The position is then compared with its visit
    two windows back, as close in time as the test allows any pair (held_match_s). The step's size (0.32-0.45 % of
    amplitude, over the bar), axis and the second within the window are drawn from the seed; the monitor sees window
    statistics."""
    named = 0
    for seed in SEEDS:
        rng = np.random.default_rng([405, seed])
        phys = fieldsim.draw_drive(rng, days=0.25)
        factory = calibrate(fieldsim.bench_sweep(phys, rng))
        run = fieldsim.field_run(phys, days=0.25, rate_hz=20.0, regime="dwell", rng=rng)
        windows = windows_of(run.samples.t, 60.0)
        # a window in the middle of five the shaft spends at one position (the truth, which only the test sees)
        still = [
            k
            for k in range(2, len(windows) - 2)
            if np.ptp(np.unwrap(run.theta[windows[k - 2][0] : windows[k + 2][1]])) < np.radians(0.2)
        ]
        a, b = windows[still[len(still) // 2]]
        third = (run.samples.t[b - 1] - run.samples.t[a]) / 3  # the middle third: both parts under the bar
        t_step = float(rng.uniform(run.samples.t[a] + third, run.samples.t[b - 1] - third))
        stepped, size, axis = with_offset_step(phys, run, rng, t_step, 0.0032, 0.0045)
        raised = offset_step_alarms(stepped, factory)[0]
        assert not [t for t, _ in raised if t < t_step], (seed, t_step, raised)
        # named once a position held before it moved alike, or none is left to tell (held_check_s)
        named += sized_hit([p for t, p in raised if t_step <= t <= t_step + 3 * 3600.0], factory, size, axis)
        phys.events.clear()
        assert offset_step_alarms(run, factory)[0] == [], seed  # the same drive without the step: nothing
    assert named >= 3, named


def test_a_step_while_the_servo_moves_is_named_at_the_next_position_it_comes_back_to():
    """A step that comes while the servo moves between positions is never seen at one held position: the next one
    the drive holds was last visited minutes to an hour before, kelvins away. The monitor learns how its held
    positions move with temperature from visits close together (HeldMap) and judges that return against it
    (s9-20hz-02: a 1.04 % step, unnamed, five hours worse than the factory set). The step (0.5-0.9 % of amplitude,
    axis and sign drawn from the seed) comes in the move onto a position the drive last moved onto 10-50 min
    before, after a quarter day of the drive; the monitor sees window statistics. Without the map (held_far_s = 0)
    the same steps go unnamed (one may be named where the drive left that position only minutes before the step);
    the same drives without them raise nothing."""
    named, named_without_map, tried = 0, 0, 0
    for seed in range(6):
        rng = np.random.default_rng([406, seed])
        phys, factory, run = half_day_dwelling(rng)
        t, theta = run.samples.t, np.unwrap(run.theta)
        # the truth, which only the test sees: the moves between holds, and where each one lands
        moving = np.flatnonzero(np.abs(np.diff(theta)) > np.radians(0.5))
        starts = moving[np.diff(moving, prepend=-10) > 1]  # the first sample of each move
        landing = [(i, float(np.mod(theta[min(i + 400, t.size - 1)], 2 * np.pi))) for i in starts]
        chosen = None
        for k, (i, angle) in enumerate(landing):
            if t[i] < 0.25 * fieldsim.DAY_S or t[i] > 0.45 * fieldsim.DAY_S:
                continue
            before = [t[j] for j, a in landing[:k] if abs(np.angle(np.exp(1j * (a - angle)))) < np.radians(1)]
            if before and 600.0 < t[i] - before[-1] < 3000.0:
                chosen = i
                break
        if chosen is None:
            continue
        tried += 1
        t_step = float(t[chosen])
        stepped, size, axis = with_offset_step(phys, run, rng, t_step, 0.005, 0.009)
        raised = offset_step_alarms(stepped, factory)[0]
        assert not [at for at, _ in raised if at < t_step], (seed, t_step, raised)
        assert len(raised) <= 1, (seed, raised)  # one step, one alarm (the set is moved once), to the run's end
        named += sized_hit([p for at, p in raised if t_step <= at <= t_step + 3600.0], factory, size, axis)
        without = offset_step_alarms(stepped, factory, settings=Settings(held_far_s=0.0))[0]
        named_without_map += any(t_step <= at <= t_step + 3600.0 for at, _ in without)
        phys.events.clear()
        assert offset_step_alarms(run, factory)[0] == [], seed  # the same drive without the step: nothing
    assert tried >= 4, tried
    assert named >= tried - 1, (named, tried)
    assert named_without_map <= 1, named_without_map


def holds_before_a_return(seed_key: int, seeds: int, q_at_least: float, q_apart: float):
    """Half-day dwelling drives, each with a hold of 8 minutes or more after a quarter day at a position whose q is
    q_at_least of the amplitude or more, followed by a position q_apart of the amplitude or more away in q (over 1: on
    the other side of the circle's q axis) last held 10-60 min before: (rng, phys, factory, run, the hold's middle,
    its angle) per seed that has one. The truth (the holds between the servo's moves) only the test sees."""
    for seed in range(seeds):
        rng = np.random.default_rng([seed_key, seed])
        phys, factory, run = half_day_dwelling(rng)
        t, theta = run.samples.t, np.unwrap(run.theta)
        moving = np.abs(np.diff(theta)) > np.radians(0.5)
        edges = np.flatnonzero(np.diff(moving.astype(int)))
        holds = [
            (t[a + 1], t[b], float(np.mod(theta[(a + b) // 2], 2 * np.pi))) for a, b in zip(edges[1::2], edges[2::2])
        ]
        for k in range(1, len(holds) - 1):
            (start, end, angle), (_, _, following) = holds[k], holds[k + 1]
            if not (0.25 * fieldsim.DAY_S < start < 0.45 * fieldsim.DAY_S and end - start > 480.0):
                continue
            if abs(np.sin(angle)) < q_at_least or abs(np.sin(following) - np.sin(angle)) < q_apart:
                continue
            before = [b for _, b, a in holds[:k] if abs(np.angle(np.exp(1j * (a - following)))) < np.radians(1)]
            if before and 600.0 < start - before[-1] < 3600.0:
                yield rng, phys, factory, run, (start + end) / 2, angle
                break


def gain_step_named(stepped, factory, t_step: float, gain: float) -> bool:
    """A drive with a step of q's gain planted at t_step: never a gain step alarm before it, and named a gain step at
    its size (within a third) and sign within three hours, or not at all (True: named)."""
    as_gain = step_alarms(stepped, factory, 60.0, "gain_step")[0]
    assert not [at for at, _ in as_gain if at < t_step], as_gain
    # log(d/q) falls by q's growth
    sized = [p["delta_imbalance"] for at, p in as_gain if at <= t_step + 3 * 3600.0]
    assert all(abs(d + math.log1p(gain)) < abs(gain) / 3 for d in sized), (gain, sized)
    return bool(sized)


def test_a_gain_step_is_not_named_an_offset_step_where_a_position_held_before_it_moved_otherwise():
    """A step of one channel's gain moves a held position along that channel in proportion to its value there: at a
    lone position one vector, as an offset step moves it (s3-20hz-22: a 0.41 % gain step named an offset step, the
    offsets moved for it, the drive 15 hours worse than its factory set). The next position the drive holds, held
    before the step too, tells them apart: moved alike, an offset step; otherwise not one. The step (a q gain of
    0.5-1 %, sign drawn from the seed) comes in the middle of a hold of 8 minutes or more at a position whose q is 0.4
    of the amplitude or more; the next position held, with q 0.5 of the amplitude or more away, was last held 10-60
    min before. Where that position moved as q's gain moves it and as no other one-channel step would, the step is
    named a gain step at its size. An offset step that moves the first position alike, at the same second, is named
    at its size; the monitor sees window statistics. Where it moved as q's gain does but not clear of the offset step,
    a step is named that the held test could not decide, which the service does not move the offsets for: not an
    offset step here."""
    tried, refused, named, named_gain = 0, 0, 0, 0
    for rng, phys, factory, run, t_step, angle in holds_before_a_return(407, 8, q_at_least=0.4, q_apart=0.5):
        tried += 1
        gain = rng.uniform(0.005, 0.01) * rng.choice([-1.0, 1.0])
        stepped = stepped_by(phys, run, rng, fieldsim.Event(t_step, "gain_step", q_gain=gain))
        refused += not [at for at, _ in moved_for_offset_steps(stepped, factory) if at >= t_step]
        named_gain += gain_step_named(stepped, factory, t_step, gain)
        size = gain * np.sin(angle) * amplitude_of(phys, 1)  # the gain step's move at the position held across it
        raised = offset_step_alarms(
            stepped_by(phys, run, rng, fieldsim.Event(t_step, "offset_step", q_offset=size)), factory
        )[0]
        named += sized_hit([p for at, p in raised if t_step <= at <= t_step + 3 * 3600.0], factory, size, 1)
    assert tried >= 4, tried
    assert refused >= tried - 1 and named >= tried - 1, (tried, refused, named)
    assert named_gain >= tried // 2, (tried, named_gain)  # where the positions tell it: a gain step, for the service


def test_a_gain_step_is_named_where_the_position_held_before_it_sits_across_the_circle():
    """A gain step of q moves a position on the other side of the circle's q axis the other way: against where an
    offset step would have moved it, by up to twice the step. That check was refused as too far to be the same position
    (held_step_max, meant for two positions sharing an angle bin), so the step stayed undecided and was named an
    offset step once no position held before it was left (s1-5hz-22: a 0.9 % gain step sat 1.7 % off the offset step's
    prediction; the offsets moved for it, the drive 20 hours worse than its factory set). The step (q's gain 0.8-1 %,
    sign drawn from the seed) in a hold at a position whose q is 0.6 of the amplitude or more, the next position held
    across the q axis, 1.4 of the amplitude or more away in q (the check sits 1.1-2 % off the offset step's), last
    held 10-60 min before: named a gain step at its size on 7 of the 8 drives the seeds give, and an offset step on
    none (the code before: 3 and 2; an offset step the service moves for: a step named undecided is not one)."""
    tried, named_gain, as_offset = 0, 0, 0
    for rng, phys, factory, run, t_step, _ in holds_before_a_return(408, 16, 0.6, 1.4):
        tried += 1
        gain = rng.uniform(0.008, 0.01) * rng.choice([-1.0, 1.0])
        stepped = stepped_by(phys, run, rng, fieldsim.Event(t_step, "gain_step", q_gain=gain))
        named_gain += gain_step_named(stepped, factory, t_step, gain)
        as_offset += bool([at for at, _ in moved_for_offset_steps(stepped, factory) if at >= t_step])
    assert tried >= 6, tried
    assert named_gain >= tried - 1 and as_offset == 0, (tried, named_gain, as_offset)


def band_sums(samples, scale: float, monitor: DeviceMonitor, window_s: float = 60.0) -> dict:
    """Each temperature band's window statistics summed, as the service's store keeps them; each window also goes
    to the drift monitor, as in the service."""
    bands: dict = {}
    for start, end in windows_of(samples.t, window_s):
        stats = window_stats(samples.subset(slice(start, end)), scale)
        if stats.temp_n:
            band = band_of(stats.temp_mean)
            bands[band] = bands[band].merge(stats) if band in bands else stats
            monitor.update(window_features(stats, t=float(samples.t[end - 1]), temp_c=stats.temp_mean, band=band))
    return bands


def gain_with_no_hour_worse(run, idx, before, after, stated: dict, seed, reach: int = 0) -> float:
    """`before`'s RMS true angle error over `after`'s on the samples idx of the run; no hour of them may be worse
    with `after` by more than three times the refit's stated error (`stated`: band -> deg) for the hour's band, or
    a band within `reach` of it, and 0.002°."""
    hours = np.floor((run.samples.t[idx] - run.samples.t[idx[0]]) / 3600.0).astype(int)
    before_err, after_err = (fieldsim.true_error_deg(c, run, idx) for c in (before, after))
    for hour in np.unique(hours):
        rows = hours == hour
        band = band_of(float(np.mean(run.samples.temp_c[idx][rows])))
        error = max(stated.get(b, 0.0) for b in range(band - reach, band + reach + 1))
        rms_before, rms_after = (float(np.sqrt(np.mean(e[rows] ** 2))) for e in (before_err, after_err))
        assert rms_after <= rms_before + 3 * error + 0.002, (seed, hour, band, rms_after, rms_before)
    return float(np.sqrt(np.mean(before_err**2)) / np.sqrt(np.mean(after_err**2)))


def test_the_held_positions_measure_the_drift_a_dwelling_drive_shows_no_circle_for():
    """A servo holding a few positions shows too few angle bins for the ellipse fit, but each position is one true
    angle at every temperature: its held points in bands of different temperatures show the drift along the circle
    (held_drift_model). Hidden from the refit: the drive's drift, die lag and positions, drawn from the seed. The
    set it makes from a day's band sums, run on the next day, leaves no hour of the day worse than the factory set
    by more than the refit's own stated uncertainty for that band, and two drives of four at most half the
    factory set's true angle error. A drive whose positions do not qualify (fewer than three held near the
    bench's temperature and in another band, or a half circle without one) keeps its factory set: no worse."""
    gains = []
    for seed in range(4):
        rng = np.random.default_rng([406, seed])
        phys = fieldsim.draw_drive(rng, event=None, days=2.0)
        factory = calibrate(fieldsim.bench_sweep(phys, rng))
        run = fieldsim.field_run(phys, days=2.0, rate_hz=20.0, regime="dwell", rng=rng)
        first_day = run.samples.t < run.samples.t[0] + 86400.0
        monitor = DeviceMonitor("servo")
        bands = band_sums(run.samples.subset(first_day), normalisation_scale(factory), monitor)
        assert monitor.watches_held_positions()  # one-minute windows: a step of the positions would be named
        result = refit_device(bands, factory, factory, held_watched=True)
        fitted = BandedCorrection.from_dict({"bands": result.bands}) if result.changed else factory
        stated = {d.band: d.candidate_error_deg for d in result.decisions if d.adopted}
        gains.append(gain_with_no_hour_worse(run, np.flatnonzero(~first_day), factory, fitted, stated, seed))
    assert min(gains) >= 0.99 and sum(g >= 2.0 for g in gains) >= 2, gains  # seeds 0-3: 1.0, 12.1, 7.0, 1.2


def three_position_servo(t: np.ndarray, rng, widest_gap_deg=(0.0, 200.0)) -> np.ndarray:
    """A servo holding one of three positions around the circle (20° apart at least, the widest gap between them in
    widest_gap_deg) for 2-10 minutes at a time, then another of them, moving between them in a sample."""
    while True:
        positions = rng.uniform(0, 2 * np.pi, 3)
        ordered = np.sort(positions)
        gaps = np.diff(ordered, append=ordered[0] + 2 * np.pi)
        if np.radians(widest_gap_deg[0]) < gaps.max() < np.radians(widest_gap_deg[1]) and gaps.min() > np.radians(20):
            break
    starts = t[0] + np.cumsum(rng.uniform(120.0, 600.0, int((t[-1] - t[0]) / 120.0) + 2))
    which = np.cumsum(rng.integers(1, 3, starts.size + 1)) % 3  # each hold another position than the one before
    return positions[which][np.searchsorted(starts, t)] + rng.normal(0, np.radians(0.02), t.size)


def three_position_drive(rng, widest_gap_deg=(0.0, 200.0)):
    """(factory set, run) of a drive two days at 20 Hz whose servo holds three positions."""
    phys = fieldsim.draw_drive(rng, event=None, days=2.0)
    factory = calibrate(fieldsim.bench_sweep(phys, rng))
    t = fieldsim.sample_times(2.0, 20.0, rng)
    temp = fieldsim.reported_temperature(t, rng, low=-20.0, high=75.0)
    theta = three_position_servo(t, rng, widest_gap_deg) % (2 * np.pi)
    samples = measured_shaft(phys, t, theta, temp, rng)
    return factory, fieldsim.FieldRun(
        samples, theta, fieldsim.lagged_fast(temp, t, phys.die_lag_s), phys, "dwell", 20.0
    )


def test_three_held_positions_measure_the_drift_until_a_step_asks_for_a_fourth():
    """A servo that holds three positions spread around the circle: each is one true angle at every temperature,
    and three pin the drift's terms while the bench holds (with four needed, such a drive, a quarter of the
    independent simulator's dwelling drives, ran its factory set for three days). Hidden from the refit: the drive's
    drift, die lag and positions, drawn from the seed. The set made from a day's band sums, run on the next day,
    leaves no hour worse than the factory set by more than the refit's stated uncertainty, and three drives of four
    at most half the factory set's error (seeds 0-3: 67x, 18x, 12x, 1.1x; with four positions needed, 1.0x each).
    After a step the step's terms at the bench are unknowns too, and three positions do not pin them (s2-5hz-10's
    curve after its offset step stated 0.03-0.05° and was 0.10-0.15° wrong): no curve from the same sums then."""
    gains = []
    for seed in range(4):
        factory, bands, gain = three_positions_next_day(np.random.default_rng([408, seed]), seed)
        locus = bench_anchors(factory)[0][1]
        assert held_drift_model(list(bands.values()), locus, offsets_stepped=True) is None, seed
        gains.append(gain)
    assert min(gains) >= 0.99 and sum(g >= 2.0 for g in gains) >= 3, gains


def test_three_held_positions_within_a_third_of_the_circle_still_measure_the_drift():
    """Three positions bunched within 110-130° of the circle (the widest gap between them 230-250°): the curve they
    give is checked around the whole circle, gap included (HeldDrift.angle_error), so it is adopted only where that
    error is small beside the factory set's. Until the fifty-eighth session a gap over 225° gave no curve at all:
    s6-5hz-14 ran its factory set, moved for its gain step, 15 hours worse than the factory set itself. Hidden as
    above; the set from a day's sums, run on the next day, leaves no hour worse than the factory set by more than
    its stated uncertainty, and two drives of four at most half its error (seeds 0-3: 9.7x, 1.0x, 1.0x, 27x; at 225°,
    1.0x each)."""
    gains = [three_positions_next_day(np.random.default_rng([409, seed]), seed, (230.0, 250.0))[2] for seed in range(4)]
    assert min(gains) >= 0.99 and sum(g >= 2.0 for g in gains) >= 2, gains


def test_three_held_positions_within_a_fifth_of_the_circle_measure_the_drift_where_their_error_allows():
    """Three positions within 75-100° of the circle (the widest gap 260-285°): a curve, checked around the whole
    circle, the gap included, adopted only where that error is small beside the factory set's. Hidden as above;
    the set from a day's sums leaves no hour of the next day worse than the factory set by more than its stated
    uncertainty, and one drive of six at least half its error (seeds 0-5: 6.8x on seed 1, 1.0x the others; with
    the gap limited to 252°, 1.0x each)."""
    gains = [three_positions_next_day(np.random.default_rng([410, seed]), seed, (260.0, 285.0))[2] for seed in range(6)]
    assert min(gains) >= 0.99 and max(gains) >= 2.0, gains


def three_positions_next_day(rng, seed: int, widest_gap_deg=(0.0, 200.0)) -> tuple:
    """(factory set, a day's band sums, the gain over the factory set the next day of the set refit from them) of a
    three-position servo drive (three_position_drive), checked hour by hour (gain_with_no_hour_worse)."""
    factory, run = three_position_drive(rng, widest_gap_deg)
    first_day = run.samples.t < run.samples.t[0] + 86400.0
    monitor = DeviceMonitor("servo")
    bands = band_sums(run.samples.subset(first_day), normalisation_scale(factory), monitor)
    assert monitor.watches_held_positions(), seed  # one-minute windows: a step of the positions would be named
    result = refit_device(bands, factory, factory, held_watched=True)
    fitted = BandedCorrection.from_dict({"bands": result.bands}) if result.changed else factory
    stated = {d.band: d.candidate_error_deg for d in result.decisions if d.adopted}
    return factory, bands, gain_with_no_hour_worse(run, np.flatnonzero(~first_day), factory, fitted, stated, seed)


def test_a_trial_is_confirmed_unmeasured_only_where_the_drive_held_positions():
    """A drive holding positions shows no circle to judge a set on, however long it soaks: its trial is kept on the
    refit's word once the minimum soak has run. A reversing drive's short arc is as few angle bins (`dwelt`) but no
    held position, and may show a circle later: it waits, as does a soak with nothing in it."""
    rng = np.random.default_rng([407, 1])
    phys = fieldsim.draw_drive(rng, event=None, days=1.0)
    factory = calibrate(fieldsim.bench_sweep(phys, rng))
    scale = normalisation_scale(factory)
    bands = [{**b.to_dict(), "band": 2} for b in factory.bands]
    trial = {"bands": [{**bands[0], "zero_offset_rad": bands[0]["zero_offset_rad"] + np.radians(1.0)}], "version": 2}
    before, fac = {"bands": bands, "version": 1}, {"bands": bands, "version": 0}

    def soak(theta):
        t = np.arange(theta.size) * 0.05
        temp = np.full(theta.size, 24.0)
        d, q = phys.measure(theta % (2 * np.pi), temp, t, rng)
        return {2: window_stats(Samples(t=t, d=d, q=q, temp_c=temp), scale)}

    positions = rng.uniform(0, 2 * np.pi, 4)
    held = np.repeat(positions, MIN_SOAK_SAMPLES // 4 + 1) + rng.normal(
        0, np.radians(0.02), 4 * (MIN_SOAK_SAMPLES // 4 + 1)
    )
    arc = rng.uniform(0, 2 * np.pi) + np.radians(36) * np.sin(np.arange(MIN_SOAK_SAMPLES + 1) * 0.05)
    assert judge(TrialEvidence(trial, before, soak(held), factory=fac)).action == "confirm"
    assert judge(TrialEvidence(trial, before, soak(arc), factory=fac)).action == "wait"
    assert judge(TrialEvidence(trial, before, {2: WindowStats(scale=scale)}, factory=fac)).action == "wait"


def test_after_an_offset_step_the_held_positions_still_measure_the_drift_and_the_step():
    """An offset step shifts the circle and turns no position along it: after one, the band sums (restarted at the
    alarm, as the service restarts them) still tie each held position's angle to the bench's, with the step's
    offsets as two more unknowns (held_drift_model(offsets_stepped=True)). Hidden from the refit: the drive's
    drift, die lag, positions and the step (0.4-0.8 % of amplitude, axis, sign and time), drawn from the seed; the
    running set is the factory's moved by the step the drift monitor measured, as the service moves it. The set the
    refit makes from a day of sums after the alarm (every band of the daily cycle visited), run on the rest of the
    run, leaves no hour worse than the moved set by more than the refit's stated uncertainty (which holds the
    fitted step's), and at least two drives of four gain twice over it (before, no drive got a held fit after any
    step: 1.0x). Seeds 8-11: 1.0, 2.6, 1.0, 5.7 (the other two do not qualify, as a drive with fewer positions or a
    half circle without one does not, and keep the moved set)."""
    gains, named = [], 0
    for seed in range(8, 12):
        rng = np.random.default_rng([406, seed])
        phys = fieldsim.draw_drive(rng, event=None, days=2.5)
        factory = calibrate(fieldsim.bench_sweep(phys, rng))
        run = fieldsim.field_run(phys, days=2.5, rate_hz=20.0, regime="dwell", rng=rng)
        t_step = float(rng.uniform(0.25, 0.35) * fieldsim.DAY_S + run.samples.t[0])
        run, _, _ = with_offset_step(phys, run, rng, t_step, 0.004, 0.008)
        scale = normalisation_scale(factory)
        monitor, raised, bands = DeviceMonitor("servo"), None, {}
        for start, end in windows_of(run.samples.t, 60.0):
            stats = window_stats(run.samples.subset(slice(start, end)), scale)
            end_s = float(run.samples.t[end - 1])
            if not stats.temp_n:
                continue
            band = band_of(stats.temp_mean)
            if raised is None:
                events = monitor.update(window_features(stats, t=end_s, temp_c=stats.temp_mean, band=band))
                # the step's alarm (the monitor's false alarms are tested elsewhere; this is about the refit after)
                stepped = [e for e in events if e.kind == "raise" and e.cause == "offset_step" and e.at >= t_step]
                raised = stepped[0] if stepped else None
            elif end_s <= raised.at + fieldsim.DAY_S:  # the band memory restarted at the alarm
                bands[band] = bands[band].merge(stats) if band in bands else stats
        if raised is None:
            continue
        named += 1
        factory_entries = [{"band": band_of(b.temp_c), **b.to_dict()} for b in factory.bands]
        moved = BandedCorrection.from_dict(
            {"bands": step_moved_bands(factory_entries, "offset_step", raised.parameters, scale)}
        )
        result = refit_device(bands, moved, factory, stepped_since_bench=True, no_axis_step=True, held_watched=True)
        fitted = BandedCorrection.from_dict({"bands": result.bands}) if result.changed else moved
        stated = {d.band: d.candidate_error_deg for d in result.decisions if d.adopted}
        for decision in [d for d in result.decisions if d.adopted]:  # the step's offsets are fitted: their error too
            offsets = [decision.quality["drift_errors"][t] or 0.0 for t in ("offset_d", "offset_q")]
            assert decision.candidate_error_deg >= 0.99 * np.degrees(max(offsets)), (seed, decision.band)
        later = np.flatnonzero(run.samples.t > raised.at + fieldsim.DAY_S)
        # the agent interpolates between neighbouring bands' entries: either one's error may show in an hour
        gains.append(gain_with_no_hour_worse(run, later, moved, fitted, stated, seed, reach=1))
    assert named >= 3, named
    assert min(gains) >= 0.99 and sum(g >= 2.0 for g in gains) >= 2, gains


def test_a_held_set_made_below_the_bench_leaves_the_bench_as_the_factory_measured_it():
    """Two drives of bench-fleet-accuracy (s9-20hz-02, s12-20hz-10: servos whose first hours are all below +20 °C).
    The held refit after four hours adopts bands up to +10..+20 °C and keeps the band above, which its positions
    were not held near, as the factory runs it. The agent interpolates between entries: that band's entry sits at
    the bench, where the drift is none, so the set runs the factory's correction there (it ran a third of the
    +10 °C drift at +20 °C, and the next hour, at +18..+29 °C, was worse than the factory set by 0.003°); so does
    the set of the refit after it."""
    for seed, index in [(9, 2), (12, 10)]:
        spec = fleet_specs(seed, 12, 3.0, 20.0, 60.0)[index]
        _, factory, run = drive_of(spec)
        t = run.samples.t - run.samples.t[0]
        bands = band_sums(run.samples.subset(t < 4 * 3600.0), normalisation_scale(factory), DeviceMonitor("servo"))
        result = refit_device(bands, factory, factory, held_watched=True)
        assert result.changed and any(d.adopted and d.band == 1 for d in result.decisions), spec.name
        fitted = BandedCorrection.from_dict({"bands": result.bands})
        bench_c = factory.bands[0].temp_c
        assert difference_deg(fitted.at(bench_c), factory.at(bench_c)) < 1e-4, spec.name
        # and the next refit, running that set, keeps its entry there (a second reader found it moved back)
        again = BandedCorrection.from_dict({"bands": refit_device(bands, fitted, factory, held_watched=True).bands})
        assert difference_deg(again.at(bench_c), factory.at(bench_c)) < 1e-4, spec.name
        hour = np.flatnonzero((t >= 4 * 3600.0) & (t < 5 * 3600.0))[::20]
        before, after = (float(np.sqrt(np.mean(fieldsim.true_error_deg(c, run, hour) ** 2))) for c in (factory, fitted))
        assert not worse_than([after], [before]), (spec.name, before, after)  # the bench's own rule for a worse hour


def test_a_step_at_the_one_position_held_is_named_as_not_measured():
    """A drive holding one position (a servo parked) sees an offset step there, and nothing else it held before the
    step to compare with: an offset step and a step of one channel's gain move that position alike. The step is named
    (an offset step: the band memory restarts), and marked as not measured (DeviceMonitor.step_measured), so the
    service does not move the running set by it (it returns to the factory set, service.runtime.back_to_factory);
    the mark survives the monitor's saved state. The step (0.4-0.8 % of the amplitude on q, sign, the position and
    the drive drawn from the seed) the monitor sees through window statistics only."""
    named = 0
    for seed in range(4):
        rng = np.random.default_rng([409, seed])
        phys = fieldsim.draw_drive(rng, event=None, days=0.25)
        factory = calibrate(fieldsim.bench_sweep(phys, rng))
        scale = normalisation_scale(factory)
        t = np.arange(0.0, 4 * 3600.0, 0.05)
        temp = 25.0 + 0.5 * np.sin(t / 3600.0)
        theta = rng.uniform(0, 2 * np.pi) + rng.normal(0, np.radians(0.02), t.size)
        size = rng.uniform(0.004, 0.008) * amplitude_of(phys, 0) * rng.choice([-1.0, 1.0])
        phys.events.append(fieldsim.Event(3600.0, "offset_step", q_offset=size))
        samples = measured_shaft(phys, t, theta, temp, rng)
        monitor, raised = DeviceMonitor("servo"), []
        for start, end in windows_of(t, 60.0):
            stats = window_stats(samples.subset(slice(start, end)), scale)
            features = window_features(
                stats, t=float(t[end - 1]), temp_c=stats.temp_mean, band=band_of(stats.temp_mean)
            )
            raised += [e for e in monitor.update(features) if e.kind == "raise"]
        if not raised:
            continue
        named += 1
        (step,) = raised
        assert step.cause == "offset_step" and step.at > 3600.0, (seed, step)
        assert "one channel's gain" in step.evidence, step.evidence
        saved = DeviceMonitor.from_dict(monitor.to_dict())
        assert not monitor.step_measured(step.at) and not saved.step_measured(step.at)
        assert monitor.step_measured(step.at + 60.0)  # another step is its own
    assert named >= 2, named


def test_after_a_step_the_held_test_could_not_judge_the_held_positions_tell_a_gain_step_from_an_offset_step():
    """A step named with no position held before it left to compare with (DeviceMonitor.step_measured is False) may
    have been an offset step or a step of one channel's gain: at the positions held across it, both moved them
    alike. The positions the drive holds after it do not: an offset step shifts the circle, a gain step stretches
    it, and their radial moves differ around the circle. held_drift_model(offsets_stepped=True) fits both and takes
    the one the points sit closer to. Hidden from the fit: the drive, its positions, the step's kind, size (gain
    0.5-1 % of q, offsets 0.4-0.8 % of the amplitude), sign, axis and time, drawn from the seed. From a day of band
    sums after the step at 5 Hz (memory restarted there, as the alarm restarts it): the kind fitted is the planted
    one on every drive fitted (seeds 1, 4 and 7, of both kinds: the others hold too few positions near the bench's
    temperature; on each, the other kind's fit failed its checks), and after a gain step the refit's set leaves at
    least five times less true angle error than the factory set (which runs then: the service returns to it for
    such a step) on the half day after: 59x, 17x, 51x."""
    kinds, gains = [], []
    for seed in range(8):
        for planted in ("gain", "offset"):
            rng = np.random.default_rng([408, seed])
            phys = fieldsim.draw_drive(rng, event=None, days=1.75)
            factory = calibrate(fieldsim.bench_sweep(phys, rng))
            run = fieldsim.field_run(phys, days=1.75, rate_hz=5.0, regime="dwell", rng=rng)
            t_step = float(rng.uniform(0.15, 0.25) * fieldsim.DAY_S + run.samples.t[0])
            if planted == "gain":
                gain = rng.uniform(0.005, 0.01) * rng.choice([-1.0, 1.0])
                phys.events.append(fieldsim.Event(t_step, "gain_step", q_gain=gain))  # kept: the truth scored below
                run = remeasured(phys, run, rng)
            else:
                run, _, _ = with_offset_step(phys, run, rng, t_step, 0.004, 0.008)
            scale = normalisation_scale(factory)
            t = run.samples.t
            day = (t > t_step) & (t <= t_step + fieldsim.DAY_S)
            bands = band_sums(run.samples.subset(np.flatnonzero(day)), scale, DeviceMonitor("servo"))
            ((_, locus),) = bench_anchors(factory)
            fit = held_drift_model(list(bands.values()), locus, offsets_stepped=True)
            if fit is None:
                continue  # too few positions held, or held too close together: the refit keeps the factory set
            kinds.append((seed, planted, fit.step, round(fit.across_misfit, 1)))
            if planted == "gain":
                result = refit_device(
                    bands, factory, factory, stepped_since_bench=True, no_axis_step=True, held_watched=True
                )
                fitted = BandedCorrection.from_dict({"bands": result.bands}) if result.changed else factory
                later = np.flatnonzero(t > t_step + fieldsim.DAY_S)[::5]
                before, after = (
                    float(np.sqrt(np.mean(fieldsim.true_error_deg(c, run, later) ** 2))) for c in (factory, fitted)
                )
                gains.append(before / after)
    assert len(kinds) >= 4, kinds
    assert all(planted == kind for _, planted, kind, _ in kinds), kinds
    assert gains and min(gains) >= 5.0, (gains, kinds)


def test_a_step_kind_that_fails_its_checks_leaves_the_step_unmeasured_instead_of_the_other_kind():
    """s10-20hz-14-dwell (a drive of bench-fleet-accuracy's 24-drive fleets; the step of q's gain, its size, sign and
    time drawn from the seed), through the bench's fleet loop: the held test names the step with no position held
    before it left to compare with, so the service returns the drive to its factory set, and the refits after it fit
    the step both as an offset step and as one channel's gain (held_drift_model). In the first hours the points sit
    closer to the gain kind across the circle, but its misfit along the circle is past MAX_ALONG_SCALE; the offset
    kind passes that check, and its set, adopted, was 0.3° wrong where the factory set left 0.1° (hours 48-50 worse).
    The kind the points sit closer to is the one judged: failing, it leaves the step unmeasured and the drive on the
    set it runs. In the eight hours after the step's own, no hour is over 0.01° worse than the factory set (the offset
    kind's set: 0.2°; with the drive's die lag measured from its held positions the refit adopts an hour earlier, its
    top entry at +32 °C, and hours 47-48 at +39 and +47 °C ran 0.004° worse than the factory set: the drift past that
    entry); over the day after it, the sets made once the gain kind passes its checks leave a fifth less error than
    the factory set or more."""
    spec = fleet_specs(10, 24, 3.0, 20.0, 60.0)[14]
    phys, factory, run = drive_of(spec)
    factory_hours, fleet_hours = score(run, factory, fleet_loop(run.samples, factory, window_s=spec.window_s))
    (step,) = phys.events  # the truth, the test's only
    first = int((step.t_s - run.samples.t[0]) // 3600) + 2
    after = slice(first, first + 8)
    excess = np.array(fleet_hours[after]) - np.array(factory_hours[after])
    assert excess.max() < 0.01, (first, fleet_hours[after], factory_hours[after])
    day = slice(first, first + 24)  # and the gain kind's sets, once it passes, beat the factory set over the day
    assert sum(fleet_hours[day]) < 0.8 * sum(factory_hours[day]), (fleet_hours[day], factory_hours[day])


def test_after_a_named_gain_step_the_held_positions_still_measure_the_drift():
    """s12-20hz-14-dwell (a drive of bench-fleet-accuracy's 24-drive fleets; the step of q's gain, its size, sign and
    time drawn from the seed): the held test names a gain step (a position held before it moved as that channel's
    gain moves it). One channel's gain stretches the circle and turns none of it, so the positions held since still
    tie to the bench's angles: from a day of band sums after the alarm, the refit fits the drift and the step
    (held_drift_model) and adopts a set for the bands the drive held its positions in, which leaves less than half
    the true angle error of the set moved by the step alone (the running set) over the half day after. Until the
    fifty-fifth session a gain step turned the held fit off, as an axis step does, and nothing was adopted. (Until
    the sixty-second session this was s7-20hz-14-dwell, whose step the held test named a gain step from where the
    servo was still again, not where the step was seen; judged there, it cannot tell gain from an axis turn.)"""
    spec = fleet_specs(12, 24, 3.0, 20.0, 60.0)[14]
    _, factory, run = drive_of(spec)
    scale, t = normalisation_scale(factory), run.samples.t
    (raised_at, parameters), *_ = step_alarms(run, factory, 60.0, "gain_step")[0]
    assert offset_step_alarms(run, factory)[0] == []  # named a gain step, and no offset step
    entries = step_moved_bands(factory_message("servo", factory)["bands"], "gain_step", parameters, scale)
    moved = BandedCorrection.from_dict({"bands": entries})
    since = np.flatnonzero((t > raised_at) & (t <= raised_at + fieldsim.DAY_S))
    bands = band_sums(run.samples.subset(since), scale, DeviceMonitor("servo"))
    result = refit_device(bands, moved, factory, stepped_since_bench=True, no_axis_step=True, held_watched=True)
    assert result.changed, [(d.band, d.running_error_deg, d.candidate_error_deg) for d in result.decisions]
    fitted = BandedCorrection.from_dict({"bands": result.bands})
    later = np.flatnonzero((t > raised_at + fieldsim.DAY_S) & (t <= raised_at + 1.5 * fieldsim.DAY_S))[::10]
    before, after = (float(np.sqrt(np.mean(fieldsim.true_error_deg(c, run, later) ** 2))) for c in (moved, fitted))
    assert after < 0.5 * before, (before, after)


def test_a_smaller_jump_of_the_held_positions_is_a_step_once_the_temperature_has_moved_steadily():
    """s7-20hz-22-dwell (a drive of bench-fleet-accuracy's 24-drive fleets; the step of q's gain, its size, sign and
    time drawn from the seed): the step moved the position the servo held by 0.27 % of the amplitude, under
    held_step_min, and went unnamed (the drive ran its old set 8 hours worse than its factory set). The temperature
    had moved steadily for half an hour: the smaller bar (held_step_min_calm) names it within two hours (as an offset
    step it cannot decide, once no position held before it is left to compare with), and nothing before it.
    s12-20hz-18-dwell, clean, a minute after a load bump at +72 °C, moved its held position by 0.21 % while the die
    caught up with the bump: no step is named there (the smaller bar without the calm named one)."""
    spec = fleet_specs(7, 24, 3.0, 20.0, 60.0)[22]
    phys, factory, run = drive_of(spec)
    (step,) = phys.events  # the truth, the test's only
    alarms = [at for cause in ("offset_step", "gain_step") for at, _ in step_alarms(run, factory, 60.0, cause)[0]]
    assert alarms and min(alarms) >= step.t_s, (step.t_s, alarms)
    assert min(alarms) <= step.t_s + 2 * 3600.0, (step.t_s, alarms)
    phys, factory, run = drive_of(fleet_specs(12, 24, 3.0, 20.0, 60.0)[18])
    assert phys.events == []
    for cause in ("offset_step", "gain_step"):
        assert step_alarms(run, factory, 60.0, cause)[0] == [], cause


def test_a_position_held_before_the_step_that_moved_as_one_channels_gain_would_names_a_step_the_refit_measures():
    """s6-5hz-22-dwell (a drive of bench-fleet-accuracy's 24-drive fleets; the step of q's gain, its size, sign and
    time drawn from the seed): the positions held across the step jumped, and the one position held before it that
    tells a gain step from an offset step, 7 °C away through the drive's temperature map, sat 7 standard errors off
    the offset step and under one off the q gain step. That is short of the twice-the-tolerance a gain step is named
    at, and the candidate was forgotten: no alarm, and the drive ran its old set 18 hours worse than its factory set.
    Now a step is named within an hour, as one the held test could not decide (the refit measures which it was), and
    nothing before it."""
    spec = fleet_specs(6, 24, 3.0, 5.0, 60.0)[22]
    phys, factory, run = drive_of(spec)
    (step,) = phys.events  # the truth, the test's only
    monitor = DeviceMonitor("under-test")
    raised = [
        (at, event.cause, monitor.step_measured(at))
        for at, event in monitored(run, factory, 60.0, monitor, until_s=step.t_s + 2 * 3600.0)
        if event.kind == "raise" and event.cause in ("offset_step", "gain_step", "axis_step")
    ]
    assert raised, "no step named"
    at, cause, measured = raised[0]
    assert step.t_s <= at <= step.t_s + 3600.0, (step.t_s, raised)
    assert cause == "offset_step" and not measured, raised  # named, not moved for: the refit measures it


def test_far_moves_of_several_positions_are_one_step_when_one_offset_or_gain_step_explains_them():
    """The rule behind held_far_seen_z (monitor._one_step_fits): far moves of positions held around the circle, each
    under the held test's bar, are one step when the same offset vector, or one channel's gain (each position moved
    along that channel by the step times where it sits on it), explains every one within 3 standard deviations and
    the step stands held_step_z clear of its error. Moves the channels' common gain explains as well (every position
    toward the centre: the temperature map's miss), also at positions 12° apart where an offset or one channel's gain
    could fit them too, or moves no one step explains, are none. Positions, step and noise drawn from the seed."""
    from encoder_core.monitor import _one_step_fits

    z = Settings().held_step_z
    for seed in range(6):
        rng = np.random.default_rng([611, seed])
        angles = rng.uniform(-np.pi, np.pi, 3)
        pos = np.column_stack([np.cos(angles), np.sin(angles)])
        sd = rng.uniform(2e-4, 6e-4, 3)
        noise = rng.normal(0.0, 1.0, (3, 2)) * sd[:, None] / 2

        def group(move, pos=pos, noise=noise, sd=sd):
            return [[0.0, 0.0, *p, *m, s] for p, m, s in zip(pos, move + noise, sd)]

        size = rng.uniform(0.004, 0.008) * rng.choice([-1, 1])
        axis = int(rng.integers(2))
        gain = np.zeros((3, 2))
        gain[:, axis] = size * pos[:, axis]
        offset = np.tile(rng.normal(0.0, 1.0, 2) / math.sqrt(2) * abs(size), (3, 1))
        radial = -abs(size) * pos  # every position toward the centre by the same fraction
        assert _one_step_fits(group(offset), z), seed
        if np.sum((pos[:, axis] / sd) ** 2) * size**2 >= (1.5 * z) ** 2:  # a step the positions see
            assert _one_step_fits(group(gain), z), seed
        assert not _one_step_fits(group(radial), z), seed
        assert not _one_step_fits(group(offset * np.array([[1], [-1], [1]])), z), seed
        near = angles[0] + np.radians([0.0, 12.0, 24.0])  # three positions a few tens of degrees apart
        pos = np.column_stack([np.cos(near), np.sin(near)])
        assert not _one_step_fits(group(-abs(size) * pos, pos=pos), z), seed  # toward the centre: no step


def step_named_within_an_hour_and_never_worse(name: str, drives: int, event: str) -> None:
    """A drive of bench-fleet-accuracy's fleets (3 days, 60 s windows) with `event` planted: a step alarm within an
    hour of the step (the simulator's truth, the test's only), and no hour worse than the factory set."""
    from encoder_fleet.fleet_accuracy import explain_drive, spec_named

    spec = spec_named(name, drives=drives, days=3.0, window_s=60.0)
    assert spec.event == event
    phys, _, _ = drive_of(spec)
    (step,) = phys.events
    explained = explain_drive(spec)
    raised = [at for at, text in explained.decisions if text.startswith("alarm raise") and "_step" in text]
    t0 = step.t_s / 3600.0
    assert raised and t0 <= min(raised) <= t0 + 1.0, (t0, raised)
    assert explained.result.worse_hour_indices == [], explained.result.worse_hour_indices


def test_a_gain_step_seen_only_against_the_temperature_map_at_several_positions_is_named():
    """s5-20hz-22-dwell (a drive of bench-fleet-accuracy's 24-drive fleets; the step of q's gain, its size, sign and
    time drawn from the seed, at 40.3 h): the servo moved between positions across the step, so each position came
    back 15-50 minutes and 2-7 °C later, 4.8-6.9 standard errors off where the temperature map put it, under the 8 the
    held test asks of one position. Unnamed, the drive ran its set from before the step nine hours worse than its
    factory set. Four positions, all moved after one moment, as one step of q's gain moves them: named within an
    hour, and no hour worse than the factory set."""
    step_named_within_an_hour_and_never_worse("s5-20hz-22-dwell", drives=24, event="gain_step")


def test_a_step_one_position_shows_clearly_is_named_though_another_in_the_same_window_shows_it_less_well():
    """s5-20hz-02-dwell (a drive of the issue's 12-drive fleets; the offset step, its size, axis and time drawn from
    the seed, at 46.8 h): the first window after the step held two positions, one 13 standard errors off where the
    temperature map put its visit 18 minutes before, the other (held for part of the window, against a visit an hour
    and 10 °C away) moved alike but only 4 standard errors clear. Judged together every position had to be 8 clear:
    unnamed, the drive ran its set from before the step to the end, one hour worse than its factory set. A position
    seen less well that moved alike within 3 of its errors no longer hides the step: named within an hour, and no
    hour worse than the factory set."""
    step_named_within_an_hour_and_never_worse("s5-20hz-02-dwell", drives=12, event="offset_step")


def test_a_step_is_judged_at_the_position_it_was_seen_at_not_where_the_drive_holds_next():
    """s5-5hz-14-dwell (a drive of the 24-drive fleets at 5 Hz; the step of q's gain, its size, sign and time drawn
    from the seed, at 39.2 h): the step was seen at the position held at 101°, where it moved q by about its size, and
    the drive was still again at -161°, where it moved q by a third as much and the other way. Taken as the step's
    move at -161°, a position held before it at 90° (where q's gain and q's offset move it alike) read as moved alike
    unlike a gain step: named an offset step, the set moved for it, eight hours worse than the factory set. Judged at
    the position it was seen at, that position cannot tell the two apart: no offset step is named as decided, and no
    hour is worse than the factory set."""
    from encoder_fleet.fleet_accuracy import explain_drive, spec_named

    spec = spec_named("s5-5hz-14-dwell", drives=24, days=3.0, window_s=60.0)
    assert spec.event == "gain_step"
    explained = explain_drive(spec)
    raised = [text for _, text in explained.decisions if text.startswith("alarm raise") and "_step" in text]
    assert raised and not [text for text in raised if "offset_step" in text and "moved alike" in text], raised
    assert explained.result.worse_hour_indices == [], explained.result.worse_hour_indices


def test_the_held_candidate_keeps_where_the_jump_was_seen_through_the_saved_state():
    """The servo jumps at one position (its angle, the step's size and direction drawn from the seed) and is next still
    at another: the candidate step carries the position the jump was seen at, also when the monitor's state is saved
    as JSON and loaded between the two. A state saved before jumps carried their position (a jump of 6 or 7 fields)
    takes the positions seen still again, as it did then."""
    import json

    from encoder_core.monitor import Features

    rng = np.random.default_rng([612, 0])
    seen_at, still_at = rng.uniform(-np.pi, np.pi), rng.uniform(-np.pi, np.pi)
    step = rng.uniform(0.004, 0.008) * np.array([math.cos(a := rng.uniform(-np.pi, np.pi)), math.sin(a)])

    def held(angle: float, moved=(0.0, 0.0)) -> list:
        return [[math.cos(angle) + moved[0], math.sin(angle) + moved[1], 1e-4]]

    def window(monitor: DeviceMonitor, t: float, positions: list) -> None:
        features = Features(t=t, temp_c=20.0, band=0, samples=1000, seen=1000, rejected={}, held=positions)
        monitor._held_step(features, [])

    for kept_fields in (None, 7, 6):
        monitor = DeviceMonitor("servo")
        for t, positions in ((0.0, held(seen_at)), (60.0, held(seen_at)), (120.0, held(seen_at, step))):
            window(monitor, t, positions)
        assert monitor.held_jump is not None and np.allclose(monitor.held_jump[:2], step)
        if kept_fields is not None:
            monitor.held_jump = monitor.held_jump[:kept_fields]
        monitor = DeviceMonitor.from_dict(json.loads(json.dumps(monitor.to_dict(), allow_nan=False)))
        for t in (180.0, 240.0):
            window(monitor, t, held(still_at))
        assert monitor.held_candidate is not None
        expected = still_at if kept_fields else seen_at
        where = monitor.held_candidate[5:7]
        assert np.allclose(where, held(expected, step if expected == seen_at else (0.0, 0.0))[0][:2]), (
            kept_fields,
            where,
        )
