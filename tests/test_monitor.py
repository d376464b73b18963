"""The drift monitor's logic (encoder_core/monitor.py) on seeded drives, offline: causes named, temperature
and the first hours quiet, absurd windows ignored, state that survives a round trip through JSON."""

import json
import math

import numpy as np
import pytest

from encoder_core.monitor import Cusum, DeviceMonitor, FleetRates, Settings, ellipse_fits, window_features
from encoder_core.monitor_causes import CAUSES
from encoder_core.physics import band_of
from encoder_core.samples import Samples
from encoder_core.stats import (
    WindowStats,
    block_statistics,
    normalisation_scale,
    pinned_mask,
    rejected_by_reason,
    window_stats,
)
from encoder_fleet import fieldsim
from encoder_fleet.bench_monitor import drive_windows, features_of, run_offline
from encoder_fleet.calibrate import calibrate
from encoder_fleet.drift_events import DAY_S, draw_drive, score

ARCH = open("docs/architecture.md", encoding="utf-8").read()


def test_vocabulary_is_the_contract():
    for name in ("offset_step", "gain_step", "axis_step", "accelerated_aging", "magnet_weakening", "outliers"):
        assert f"`{name}`" in ARCH
    assert set(CAUSES) == {
        "offset_step",
        "gain_step",
        "axis_step",
        "accelerated_aging",
        "magnet_weakening",
        "harmonic_growth",
        "outliers",
        "adc_clipping",
        "offline",
    }
    assert set(CAUSES["offset_step"].alarm_params) == {"delta_d", "delta_q"}
    assert set(CAUSES["gain_step"].alarm_params) == {"delta_imbalance"}
    assert set(CAUSES["axis_step"].alarm_params) == {"delta_skew"}
    assert set(CAUSES["accelerated_aging"].alarm_params) == {"rate_per_day", "fleet_median_rate_per_day"}
    assert set(CAUSES["magnet_weakening"].alarm_params) == {"loss_per_day"}
    assert set(CAUSES["harmonic_growth"].alarm_params) == {"order", "amplitude_deg"}
    assert set(CAUSES["outliers"].alarm_params) == {"fraction"} == set(CAUSES["adc_clipping"].alarm_params)
    assert set(CAUSES["offline"].alarm_params) == {"since"}
    schema = json.loads(open("schemas/alarm.schema.json", encoding="utf-8").read())
    assert set(schema["properties"]["cause"]["enum"]) == set(CAUSES)  # the published contract names them all


@pytest.fixture(scope="module")
def planted():
    """One drive per cause (onset at 30 h) and two clean ones, 2.5 days each, through the offline harness."""
    causes = [None, None, "offset_step", "accelerated_aging", "magnet_weakening", "harmonic_growth"]
    causes += ["outliers", "adc_clipping"]
    specs = [draw_drive(40 + i, 2.5, c, onset_range_s=(30 * 3600, 30 * 3600)) for i, c in enumerate(causes)]
    alarms, cost = run_offline(specs)
    return specs, alarms, cost


def test_every_planted_cause_is_named_after_its_onset_and_clean_drives_stay_quiet(planted):
    specs, alarms, _ = planted
    result = score(specs, alarms)
    assert result["recall"] == 1.0, result["missed"]
    assert result["false_alarms"] == 0, result["false"]
    assert result["cause_precision"] == 1.0
    for cause, c in result["per_cause"].items():
        goal = 8 if cause in ("accelerated_aging", "magnet_weakening", "harmonic_growth") else 2
        assert c["median_delay_h"] <= goal, (cause, c)


def test_alarm_parameters_match_what_was_planted(planted):
    specs, alarms, _ = planted
    for spec in specs:
        ev = spec.event
        if ev is None:
            continue
        (alarm,) = [a for a in alarms[spec.name] if a["cause"] == ev.cause]
        p = alarm["parameters"]
        assert set(p) == set(CAUSES[ev.cause].alarm_params)
        assert alarm["evidence"].endswith(".") and len(alarm["evidence"]) > 40
        if ev.cause == "offset_step":
            size = math.hypot(p["delta_d"], p["delta_q"])
            assert size == pytest.approx(ev.size, rel=0.25)
        elif ev.cause == "harmonic_growth":
            assert p["order"] == ev.order
        elif ev.cause in ("outliers", "adc_clipping"):
            assert 0.3 * ev.size < p["fraction"] < 1.5 * ev.size
        elif ev.cause == "accelerated_aging":
            assert p["rate_per_day"] > 3 * p["fleet_median_rate_per_day"]


def test_a_fast_ageing_drive_is_named_ageing_and_never_an_offset_step():
    """Offsets ageing at the top of the planted range (1.5 %/day) among clean drives. The level the offset-step
    detector compares each window with follows slow drift with a lag of its time constant times the rate (~0.19 % of
    the amplitude here), close to the step's reference (0.25 %); once the ageing is named, the level follows the
    measured ramp. Without that, 3 of these 6 drives raised false offset steps (and 9 of 12 in 3 days)."""
    ageing = []
    for seed in range(60, 66):
        spec = draw_drive(seed, 2.5, "accelerated_aging", onset_range_s=(24 * 3600, 24 * 3600))
        spec.event.size = 0.015
        ageing.append(spec)
    clean = [draw_drive(seed, 2.5, None) for seed in range(100, 108)]  # the fleet norm the ageing stands out from
    alarms, _ = run_offline(ageing + clean)
    for spec in ageing:
        assert [a["cause"] for a in alarms[spec.name]] == ["accelerated_aging"], (spec.name, alarms[spec.name])
    assert all(alarms[spec.name] == [] for spec in clean)


def test_temperature_cycle_and_first_hours_never_alarm():
    """A wide, fast cycle (−40…+85 °C every 8 h): the first hours are learning (state unknown), then ok."""
    spec = draw_drive(7, 1.5, None)
    spec.t_min, spec.t_max, spec.cycle_hours = -40.0, 85.0, 8.0
    mon = DeviceMonitor(spec.name)
    states = []
    for w in drive_windows(spec, window_s=300, sample_hz=2.0):
        assert mon.update(features_of(*w)) == []
        states.append(mon.state())
    assert states[0] == "unknown" and states[-1] == "ok"
    assert len(mon.bands) >= 12  # every band of the cycle has its own baseline


def test_a_page_of_windows_is_fitted_as_each_window_alone():
    """The service fits the ellipses of a page of stored windows at once (ellipse_fits, one array pass): every
    window's features are the ones it gets alone, to the bit; a scatter no conic fits (singular, or not finite)
    in the batch is refused by itself and leaves the others as they are."""
    from encoder_core.monitor import _SCATTER, _conic_fits

    spec = draw_drive(5, 0.5, "harmonic_growth", onset_range_s=(6 * 3600, 6 * 3600))
    windows = drive_windows(spec, window_s=300, sample_hz=2.0)
    stats = [w[0] for w in windows]
    fits = ellipse_fits(stats)
    assert sum(fit is not None for fit, _ in fits) > 100
    for window, page_fits in zip(windows, fits):
        alone, in_page = features_of(*window), features_of(*window, page_fits)
        for name in ("y", "sigma", "ratio_skew"):
            a, b = getattr(alone, name), getattr(in_page, name)
            assert (a is None and b is None) or np.array_equal(np.asarray(a), np.asarray(b)), name
    # the stack's fallbacks: numpy refuses a whole stack for one singular or non-finite matrix
    good = stats[len(stats) // 2]
    sm, count = good.moments[_SCATTER], good.moments[0]
    bad = [np.zeros((6, 6)), np.full((6, 6), np.nan)]
    batch = _conic_fits(np.array([sm, *bad, sm]), np.array([count, 1.0, 1.0, count]))
    (alone,) = _conic_fits(sm[None], np.array([count]))
    assert batch[1] is None and batch[2] is None
    for fit in (batch[0], batch[3]):
        assert all(np.array_equal(x, y) for x, y in zip(fit, alone))


def _step_monitor():
    spec = draw_drive(3, 2.0, "offset_step", onset_range_s=(30 * 3600, 30 * 3600))
    return spec, [features_of(*w) for w in drive_windows(spec, window_s=300, sample_hz=2.0)]


def test_absurd_window_never_moves_a_baseline():
    spec, feats = _step_monitor()
    mon = DeviceMonitor(spec.name)
    for f in feats[:200]:
        mon.update(f)
    before = json.dumps(mon.to_dict(), sort_keys=True)
    f = feats[200]
    stats_10x = WindowStats(scale=1400.0)
    rng = np.random.default_rng(0)
    theta = rng.uniform(0, 2 * np.pi, 600)
    amp = 10 * 1400 * math.exp(f.y[2])
    stats_10x.add(amp * np.cos(theta), amp * np.sin(theta), np.full(600, f.temp_c))
    absurd = window_features(stats_10x, t=f.t, temp_c=f.temp_c, band=f.band)
    assert mon.update(absurd) == []
    after = mon.to_dict()
    assert after["absurd"] == 1 and mon.state() == "watch"
    for key in ("absurd", "last_absurd_t", "windows", "last_t"):
        after.pop(key)
    ref = json.loads(before)
    for key in ("absurd", "last_absurd_t", "windows", "last_t"):
        ref.pop(key)
    assert json.loads(json.dumps(after, sort_keys=True)) == ref


def test_state_through_json_mid_drift_gives_the_same_alarms():
    spec, feats = _step_monitor()
    whole = DeviceMonitor(spec.name)
    events_whole = [(e.cause, e.at) for f in feats for e in whole.update(f)]
    assert [c for c, _ in events_whole] == ["offset_step"]
    cut = next(i for i, f in enumerate(feats) if f.t >= events_whole[0][1])  # the window that raised it
    mon = DeviceMonitor(spec.name)
    events = [(e.cause, e.at) for f in feats[:cut] for e in mon.update(f)]
    mon = DeviceMonitor.from_dict(json.loads(json.dumps(mon.to_dict())))  # a service restart
    events += [(e.cause, e.at) for f in feats[cut:] for e in mon.update(f)]
    assert events == events_whole


def test_sparse_windows_and_old_clock_are_harmless():
    spec = draw_drive(5, 10.0, None)
    feats = [features_of(*w) for w in drive_windows(spec, window_s=300, sample_hz=2.0)[:288]]
    mon = DeviceMonitor(spec.name)
    for f in feats:
        mon.update(f)
    for day in range(1, 10):  # then one window a day
        f = feats[day * 17 % len(feats)]
        f.t = day * DAY_S + 3600.0
        assert mon.update(f) == []
    f.t = 10.0
    assert mon.update(f) == []  # a clock that goes back changes nothing


def test_cusum_and_fleet_norm():
    c = Cusum(k=0.5, h=3.0)
    assert not c.update(1.0).drift_detected and c.s == 0.5
    for _ in range(6):
        c.update(1.0)
    assert c.drift_detected and Cusum.from_dict(c.to_dict()) == c
    fleet = FleetRates(Settings(min_fleet=3))
    assert fleet.norm("offset") == (Settings().prior_rate[0], Settings().prior_spread[0])  # small fleet: prior
    for i, r in enumerate([0.001, 0.0012, 0.0008, 0.02]):
        fleet.report(f"d{i}", {"offset": r, "amplitude": 0.0})
    median, spread = fleet.norm("offset", exclude="d3")
    assert median == pytest.approx(0.001) and spread < 0.001


def test_a_small_fleets_norm_leaves_out_the_device_it_is_asked_for():
    """The cached norm of a small fleet was one for every device left out: a device judged after another had it
    with its own rate in (here its fleet's median became its own rate, half the fleet ageing), never without."""
    rates = [0.001, 0.0011, 0.0009, 0.02, 0.021, 0.019]
    fleet = FleetRates()
    for i, r in enumerate(rates):
        fleet.report(f"d{i}", {"offset": r, "amplitude": 0.0})
    for i in range(len(rates)):
        alone = FleetRates()
        for j, r in enumerate(rates):
            alone.report(f"d{j}", {"offset": r, "amplitude": 0.0})
        assert fleet.norm("offset", exclude=f"d{i}") == alone.norm("offset", exclude=f"d{i}"), i
    assert fleet.norm("offset", exclude="d3")[0] == pytest.approx(0.0011)


def test_clipping_is_recognised_from_the_data_at_any_rail():
    rng = np.random.default_rng(1)
    theta = rng.uniform(0, 2 * np.pi, 2000)
    d = np.round(30000 + 9000 * np.cos(theta) + rng.normal(0, 3, theta.size))  # counts of another range
    q = np.round(-5000 + 9000 * np.sin(theta) + rng.normal(0, 3, theta.size))
    rail = np.quantile(d, 0.99)
    clipped = np.minimum(d, rail)
    s = Samples(t=np.arange(theta.size, dtype=float), d=clipped, q=q, temp_c=np.full(theta.size, 20.0))
    keep, counts = rejected_by_reason(s)
    assert counts["clipped"] == int((d >= rail).sum()) and counts["non_finite"] == 0
    assert not pinned_mask(d, q).any()  # the same data unclipped: nothing pinned
    s.d[5] = np.nan
    stats, counts = block_statistics(s, 9000.0)
    assert counts["non_finite"] == 1 and stats.rejected == sum(counts.values())
    assert band_of(stats.temp_mean) == 2


def _reversing_drive_alarms(
    rng, days: float, rate_hz: float, window_s: float, third_harmonic: float | None = None
) -> tuple[list, DeviceMonitor]:
    """(cause, hour) of every alarm the monitor raises on a clean reversing drive of the independent simulator
    (third_harmonic: the field's order-3 harmonic set to this size, at a phase drawn from rng)."""
    from encoder_core.stats import normalisation_scale, window_stats
    from encoder_fleet import fieldsim
    from encoder_fleet.calibrate import calibrate
    from encoder_fleet.fleet_accuracy import windows_of

    phys = fieldsim.draw_drive(rng, event=None, days=days)
    if third_harmonic is not None:
        phys.pos_harmonics[3] = third_harmonic * np.exp(2j * np.pi * rng.random())
    scale = normalisation_scale(calibrate(fieldsim.bench_sweep(phys, rng)))
    run = fieldsim.field_run(phys, days=days, rate_hz=rate_hz, regime="reverse", rng=rng)
    monitor = DeviceMonitor("reversing")
    raised = []
    for start, end in windows_of(run.samples.t, window_s):
        stats = window_stats(run.samples.subset(slice(start, end)), scale)
        end_s, temp = float(run.samples.t[end - 1]), stats.temp_mean
        for e in monitor.update(window_features(stats, t=end_s, temp_c=temp, band=band_of(temp))):
            if e.kind == "raise":
                raised.append((e.cause, round(e.at / 3600, 2)))
    return raised, monitor


@pytest.mark.parametrize("seed", range(6))
def test_a_clean_reversing_drive_raises_no_offset_step(seed):
    """Independent simulator, a clean drive that reverses over arcs for a day at 20 Hz: a window that leaves
    more than a quarter turn unseen is not judged (an ellipse through an arc puts its centre anywhere along the
    arc's axis). Judging them, the monitor raised a false offset_step on 4 of these 6 drives, and the service
    then moved every band of a good set by it."""
    raised, monitor = _reversing_drive_alarms(np.random.default_rng(seed), 1, 20.0, 60.0)
    assert "offset_step" not in [cause for cause, _ in raised], raised
    assert monitor.judged > 300  # the windows that do go round the circle are still judged


def test_a_reversing_drive_with_a_strong_field_harmonic_raises_no_offset_step_before_its_step():
    """The accuracy bench's drive s5-20hz-11-reverse (a 1.1 % third field harmonic; its offset step comes at
    30.8 h): the locus is no ellipse, and a centre fitted weighted by the samples moved with where along the
    circle the drive lingered at its turns: two false offset steps, at 23.1 h and 26.6 h, each moved for. The
    centre is fitted with every angle bin weighted alike, as the shape is."""
    from encoder_core.stats import normalisation_scale, window_stats
    from encoder_fleet import fieldsim
    from encoder_fleet.calibrate import calibrate
    from encoder_fleet.fleet_accuracy import fleet_specs, windows_of

    spec = next(s for s in fleet_specs(5, 12, 3.0, 20.0, 60.0) if s.name == "s5-20hz-11-reverse")
    rng = np.random.default_rng([spec.seed, spec.index, int(spec.rate_hz * 1000)])
    phys = fieldsim.draw_drive(rng, event=spec.event, days=spec.days)
    scale = normalisation_scale(calibrate(fieldsim.bench_sweep(phys, rng)))
    run = fieldsim.field_run(phys, days=spec.days, rate_hz=spec.rate_hz, regime=spec.motion, rng=rng)
    step_h = (phys.events[0].t_s - run.samples.t[0]) / 3600
    before = run.samples.subset(slice(0, int(np.searchsorted(run.samples.t, phys.events[0].t_s))))
    monitor, raised = DeviceMonitor("s5-20hz-11"), []
    for start, end in windows_of(before.t, 60.0):
        stats = window_stats(before.subset(slice(start, end)), scale)
        temp = stats.temp_mean
        for e in monitor.update(window_features(stats, t=float(before.t[end - 1]), temp_c=temp, band=band_of(temp))):
            raised.append((e.cause, round(e.at / 3600, 2)))
    assert step_h > 30 and "offset_step" not in [cause for cause, _ in raised], raised


@pytest.mark.parametrize("seed", range(1, 7))
def test_a_clean_reversing_drive_raises_no_gain_or_axis_step(seed):
    """Independent simulator, a clean drive that reverses for three days at 0.5 Hz in 300 s windows (the
    accuracy bench's drive s{seed}-0.5hz-03-reverse): no gain_step and no axis_step. The field's harmonics bend
    the locus away from an ellipse, and an ellipse fitted with a weight per sample tilted with where along the
    circle the reversals left the samples: the monitor raised false axis or gain steps on 2 of these 6 drives, and
    the service then moved a good set by them. The shape is now fitted with each angle bin weighted alike."""
    raised, monitor = _reversing_drive_alarms(np.random.default_rng([seed, 3, 500]), 3.0, 0.5, 300.0)
    assert not [r for r in raised if r[0] in ("gain_step", "axis_step")], raised
    assert monitor.judged > 100  # the windows that go round the circle are still judged


def _step_alarms(phys, rng, rate_hz: float, window_s: float, regime: str, days: float, cause: str) -> list:
    from encoder_core.stats import normalisation_scale, window_stats
    from encoder_fleet import fieldsim
    from encoder_fleet.calibrate import calibrate
    from encoder_fleet.fleet_accuracy import windows_of

    scale = normalisation_scale(calibrate(fieldsim.bench_sweep(phys, rng)))
    run = fieldsim.field_run(phys, days=days, rate_hz=rate_hz, regime=regime, rng=rng)
    monitor = DeviceMonitor("drive")
    raised = []
    for start, end in windows_of(run.samples.t, window_s):
        stats = window_stats(run.samples.subset(slice(start, end)), scale)
        end_s, temp = float(run.samples.t[end - 1]), stats.temp_mean
        for e in monitor.update(window_features(stats, t=end_s, temp_c=temp, band=band_of(temp))):
            if e.kind == "raise" and e.cause in ("gain_step", "axis_step"):
                assert e.cause == cause, (e.cause, e.at / 3600, e.parameters)
                raised.append(e)
                monitor.clear(e.cause, e.at, "the test takes each step as re-corrected at once")
    return raised


@pytest.mark.parametrize(("seed", "rate_hz", "window_s", "regime"), [
    (41, 20.0, 60.0, "even"), (42, 20.0, 60.0, "random"), (43, 0.5, 300.0, "even"), (44, 0.5, 300.0, "random"),
    (45, 5.0, 120.0, "even"), (46, 2.0, 600.0, "random"), (47, 20.0, 10.0, "even"),
])  # fmt: skip
def test_a_gain_step_is_named_with_its_size_and_the_same_drive_without_it_raises_none(seed, rate_hz, window_s, regime):
    """Independent simulator: the q channel's gain steps by a size, sign and time drawn from the seed, on a drive
    cycling -20…+75 °C for a day and a half. The monitor names one gain_step, within an hour, measuring the
    amplitude ratio's jump within a fifth of the truth (the service moves the running set by it); the same drive
    without the step raises none. Judged against a device-wide level, as the offsets are, the ratio's miss of the
    bands' lines raised false steps at band crossings (15 on one drive in three days)."""
    import math

    from encoder_fleet import fieldsim

    days = 1.5
    phys = fieldsim.draw_drive(np.random.default_rng(seed), event="gain_step", days=days)
    (step,) = phys.events
    truth = -math.log1p(step.q_gain)  # log(d/q) of the amplitudes: q's gain grew by q_gain
    raised = _step_alarms(phys, np.random.default_rng(seed + 100), rate_hz, window_s, regime, days, "gain_step")
    assert len(raised) == 1, [(e.at / 3600, e.parameters) for e in raised]
    assert step.t_s <= raised[0].at <= step.t_s + 3600.0
    assert abs(raised[0].parameters["delta_imbalance"] - truth) < 0.2 * abs(truth), (raised[0].parameters, truth)
    phys.events.clear()
    assert _step_alarms(phys, np.random.default_rng(seed + 100), rate_hz, window_s, regime, days, "gain_step") == []


def test_gain_steps_at_the_bottom_of_the_range_are_named_at_half_a_hertz():
    """Independent simulator, 0.5 Hz, 300 s windows (150 samples each): six q-gain steps of 0.30–0.40 %, the planted
    range's bottom, sign, size and time drawn per seed. With the bar at 0.3 % three were named (a 0.31 % step
    measured 0.296 % fell under it; bench-fleet-accuracy's s4-0.5hz-05, 0.38 %, ran three hours worse than its factory
    set); now at least four, each within an hour and a quarter of its size; none on the same drives without a step."""
    from encoder_fleet import fieldsim

    days, named = 1.5, 0
    for seed in range(72, 78):
        rng = np.random.default_rng(seed)
        phys = fieldsim.draw_drive(rng, event="gain_step", days=days)
        (step,) = phys.events
        step.q_gain = float(np.sign(step.q_gain) * rng.uniform(0.003, 0.004))
        truth = -math.log1p(step.q_gain)
        raised = _step_alarms(phys, np.random.default_rng(seed + 100), 0.5, 300.0, "random", days, "gain_step")
        assert len(raised) <= 1, [(e.at / 3600, e.parameters) for e in raised]
        if raised:
            assert step.t_s <= raised[0].at <= step.t_s + 3600.0
            assert abs(raised[0].parameters["delta_imbalance"] - truth) < 0.25 * abs(truth), raised[0].parameters
            named += 1
        phys.events.clear()
        assert _step_alarms(phys, np.random.default_rng(seed + 100), 0.5, 300.0, "random", days, "gain_step") == []
    assert named >= 4


def test_a_gain_step_whose_ratio_takes_three_windows_to_settle_is_named():
    """bench-fleet-accuracy's s7-0.5hz-04-even, a held-out seed (its drive drawn as the bench draws it): a 0.61 %
    q-gain step at 44.7 h. 150 random angles a window scatter the amplitude ratio by ~0.05 %, and the window after
    the step's first whole one read 0.2 % high, so the ratio still moved after two windows and the jump test let the
    step go (jump_settle_windows was 2); the drive ran its old set for three hours, all worse than its factory
    set. With three windows to settle it is named within the hour and sized within a tenth; with two, not."""
    from encoder_fleet.fleet_accuracy import drive_of, fleet_specs
    from tests.monitor_runs import step_alarms

    spec = fleet_specs(7, 12, 3, 0.5, 300.0)[4]
    phys, factory, run = drive_of(spec)  # as run_drive draws it
    (step,) = phys.events
    truth = -math.log1p(step.q_gain)
    raised = step_alarms(run, factory, spec.window_s, "gain_step")[0]
    assert len(raised) == 1, raised
    at, parameters = raised[0]
    assert step.t_s <= at <= step.t_s + 3600.0
    assert abs(parameters["delta_imbalance"] - truth) < 0.1 * abs(truth), (parameters, truth)
    before = step_alarms(run, factory, spec.window_s, "gain_step", Settings(jump_settle_windows=2))[0]
    assert not [a for a, _ in before if step.t_s <= a <= step.t_s + 3600.0], before


@pytest.mark.parametrize(("seed", "rate_hz", "window_s", "regime"), [
    (61, 20.0, 60.0, "even"), (62, 20.0, 60.0, "random"), (63, 0.5, 300.0, "random"), (64, 5.0, 120.0, "even"),
    (65, 2.0, 600.0, "random"),
])  # fmt: skip
def test_an_axis_step_is_named_with_its_size_and_the_same_drive_without_it_raises_none(seed, rate_hz, window_s, regime):
    """Independent simulator: the q sensor's axis turns by 0.3–0.6° of a radian's thousandths (0.003–0.006 rad: a
    sensor tilted on its board), sign and time drawn from the seed. The monitor names one axis_step within the
    hour, the ellipse's skew jump within a fifth of the turn's sine; the same drive without the turn raises none."""
    from encoder_fleet import fieldsim

    days = 1.5
    rng = np.random.default_rng(seed)
    phys = fieldsim.draw_drive(rng, event=None, days=days)
    turn = float(rng.choice([-1.0, 1.0]) * rng.uniform(0.003, 0.006))
    step = fieldsim.Event(float(rng.uniform(0.3, 0.8) * days * DAY_S), "axis_step", q_axis=turn)
    phys.events.append(step)
    raised = _step_alarms(phys, np.random.default_rng(seed + 100), rate_hz, window_s, regime, days, "axis_step")
    assert len(raised) == 1, [(e.at / 3600, e.parameters) for e in raised]
    assert step.t_s <= raised[0].at <= step.t_s + 3600.0
    assert abs(raised[0].parameters["delta_skew"] - np.sin(turn)) < 0.2 * abs(turn), (raised[0].parameters, turn)
    phys.events.clear()
    assert _step_alarms(phys, np.random.default_rng(seed + 100), rate_hz, window_s, regime, days, "axis_step") == []


@pytest.mark.parametrize("seed", range(3))
def test_odd_windows_never_break_the_monitor(seed):
    """Windows a real drive can send that no simulator draws, in a shuffled stream: all samples at one point, two
    clusters, a line through the centre, one channel dead, an arc, an amplitude off the agent's scale (these the
    agent's plausibility mask and the coverage check turn away before any fit), and, within reach of the fits, a
    circle whose radius jumps from bin to bin or alternates around it, an ellipse at the mask's limit, a circle with
    a sample or two per bin. Every window's features are finite or absent, and the monitor's events carry finite
    parameters. Hypothesis draws the streams (derandomized: the same in every run), the noise comes from the seed."""
    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st

    def shaped(kind: str, n: int, amp: float, off: float, rng) -> tuple[np.ndarray, np.ndarray]:
        theta = {
            "point": np.full(n, rng.uniform(0, 2 * np.pi)),
            "two": rng.choice(rng.uniform(0, 2 * np.pi, 2), n),
            "arc": rng.uniform(0, rng.uniform(0.1, 3.0), n),
            "sparse": (np.arange(n) + rng.uniform(0, 1, n)) * (2 * np.pi / n),
        }.get(kind, rng.uniform(0, 2 * np.pi, n))
        radius = np.full(n, amp)
        if kind == "line":  # through the centre: the ellipse degenerates
            r = rng.choice([-amp, amp], n) + rng.normal(0, 1.0, n)
            return r * math.cos(0.3), r * math.sin(0.3)
        if kind == "flat":  # one channel dead
            return amp * np.cos(theta), np.zeros(n)
        if kind == "lumpy":  # a radius of its own in every angle bin, inside the mask's ±12 %
            radius = amp * rng.uniform(0.9, 1.1, 64)[(theta % (2 * np.pi) / (2 * np.pi) * 64).astype(int) % 64]
        if kind == "square":  # the radius alternating around the circle
            radius = amp * (1 + 0.1 * np.sign(np.cos(rng.integers(2, 9) * theta)))
        if kind == "thin":  # an ellipse at the mask's limit, turned
            tilt = rng.uniform(0, np.pi)
            radius = amp / np.sqrt((np.cos(theta - tilt) / 1.1) ** 2 + (np.sin(theta - tilt) / 0.9) ** 2)
        noise = rng.normal(0, 1.0, (2, n))
        return off + radius * np.cos(theta) + noise[0], radius * np.sin(theta) + noise[1]

    odd_fitted = ("lumpy", "square", "thin", "sparse")
    kinds = st.sampled_from(["point", "two", "arc", "line", "flat", "circle", *odd_fitted])
    sizes = st.floats(1400.0, 1600.0) | st.floats(5.0, 5000.0)  # mostly near the agent's scale (1500), where kept
    windows = st.tuples(kinds, st.integers(40, 3000), sizes, st.floats(-100.0, 100.0))
    reached: list[str] = []

    @settings(max_examples=25, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))
    @given(stream=st.lists(windows, min_size=3, max_size=12))
    def check(stream):
        rng = np.random.default_rng([seed, len(stream)])
        monitor = DeviceMonitor("odd")
        t = 0.0
        for kind, n, amp, off in stream:
            d, q = shaped(kind, n, amp, off, rng)
            t += 60.0
            samples = Samples(t=t + np.arange(n) / n, d=d, q=q, temp_c=np.full(n, 25.0 + rng.normal(0, 5)))
            stats, reasons = block_statistics(samples, 1500.0)
            f = window_features(stats, t=t, temp_c=float(samples.temp_c[0]), band=2, rejected_by_reason=reasons)
            for values in (f.y, f.sigma):
                assert values is None or np.all(np.isfinite(values)), (kind, n, amp, values)
            assert f.ratio_skew is None or all(math.isfinite(v) for v in f.ratio_skew), (kind, f.ratio_skew)
            if f.ratio_skew is not None:
                reached.append(kind)
            for event in monitor.update(f):
                numbers = [v for v in event.parameters.values() if isinstance(v, float)]
                assert all(math.isfinite(v) for v in numbers), (kind, event)

    check()
    assert set(odd_fitted) <= set(reached), set(reached)  # the odd shapes reached the per-bin fit


@pytest.mark.parametrize("seed", range(6))
def test_the_radius_ripple_does_not_depend_on_where_the_shaft_lingers(seed):
    """The harmonics' ripple of one window, on a drive from the independent simulator (its field harmonics drawn from
    the seed), read once at random angles and once reversing over 1.3 turns (a third of the circle seen twice as
    often): the same locus, the same temperature, so the same ripple within the errors. Weighted by each bin's
    samples (the code before), they differed by up to 8 errors, and clean reversing drives raised harmonic_growth
    (13 alarms on 80 clean drive-runs of bench-fleet-accuracy)."""
    rng = np.random.default_rng([515, seed])
    phys = fieldsim.draw_drive(rng, days=0.5)
    scale = normalisation_scale(calibrate(fieldsim.bench_sweep(phys, rng)))
    n = 20 * 600
    t = np.sort(rng.uniform(0.0, 600.0, n))
    temp = np.full(n, 25.0)
    even = rng.uniform(0.0, 2 * np.pi, n)
    turn, period = rng.uniform(0.0, 2 * np.pi), rng.uniform(5.0, 60.0)
    lingering = (turn + 2.6 * np.arcsin(np.sin(2 * np.pi * t / period))) % (2 * np.pi)
    features = []
    for theta in (even, lingering):
        d, q = phys.measure(theta, temp, t, rng)
        stats = window_stats(Samples(t=t, d=d, q=q, temp_c=temp), scale)
        features.append(window_features(stats, t=600.0, temp_c=25.0, band=band_of(25.0)))
    a, b = features
    assert a.gap_bins == 0 and b.gap_bins == 0  # both see the whole circle: the harmonics are judged on both
    z = np.abs(a.y[4:] - b.y[4:]) / np.hypot(a.sigma[4:], b.sigma[4:])
    assert z.max() < 4, z.round(1)
