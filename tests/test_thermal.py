"""The die's lag behind the temperature a drive reports (encoder_core/thermal.py): the agent's die estimate, and
the lag the service measures from window statistics of drives this project did not write
(encoder_fleet/fieldsim.py), each lag hidden in a seed: the code under test sees windows, never the truth."""

from __future__ import annotations

import io
import json
from dataclasses import replace

import numpy as np
import pytest
from mcap.reader import make_reader

from edge_agent.agent import temp_rate
from encoder_core.monitor import DeviceMonitor, window_features
from encoder_core.stats import normalisation_scale, window_stats
from encoder_core.thermal import DieTemperature, LagEstimate, first_order_lag, lag_to_send
from encoder_fleet import fieldsim
from encoder_fleet.calibrate import calibrate, factory_set
from fleet_wire import messages as wire
from service.mcap_export import iter_mcap

DEVICE = "drive-lag"


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_the_die_estimate_carried_across_windows_is_the_lag_of_the_whole_stream(seed):
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.05, 3.0, 4000))  # an irregular clock
    temp = 20 + np.cumsum(rng.normal(0, 0.2, t.size))
    tau = float(rng.uniform(30, 900))
    cuts = np.sort(rng.choice(np.arange(1, t.size), 12, replace=False))
    die = DieTemperature()
    pieces = [die(t[a:b], temp[a:b], tau) for a, b in zip([0, *cuts], [*cuts, t.size])]
    whole = first_order_lag(t, temp, tau)
    assert np.allclose(np.concatenate(pieces), whole, atol=1e-9)
    step_by_step = [temp[0]]  # the recursion itself, sample by sample, against the closed form
    for i in range(1, t.size):
        a = np.exp(-(t[i] - t[i - 1]) / tau)
        step_by_step.append(a * step_by_step[-1] + (1 - a) * temp[i - 1])
    assert np.allclose(whole, step_by_step, atol=1e-9)
    # a reading that is not a number passes through as it is and does not move the estimate
    held = die.last
    out = die(np.array([t[-1] + 1, t[-1] + 2]), np.array([np.nan, np.inf]), tau)
    assert np.isnan(out[0]) and np.isinf(out[1]) and die.last == held


def drive_with_hidden_lag(seed: int, days: float = 0.75, rate_hz: float = 5.0):
    rng = np.random.default_rng(seed)
    phys = replace(fieldsim.draw_drive(rng), die_lag_s=float(rng.uniform(60, 900)))
    factory = calibrate(fieldsim.bench_sweep(phys, rng))
    run = fieldsim.field_run(phys, days=days, rate_hz=rate_hz, regime=str(rng.choice(["even", "random"])), rng=rng)
    return phys, factory, run


def windows(run, factory, window_s: float, lag_used_s: float = 0.0):
    """(block, statistics) as an agent running a set with lag_used_s writes them."""
    scale, die = normalisation_scale(factory), DieTemperature()
    t = run.samples.t
    for start in np.arange(t[0], t[-1], window_s):
        block = run.samples.subset((t >= start) & (t < start + window_s))
        if len(block) < 2:
            continue
        block = replace(block, temp_c=die(block.t, block.temp_c, lag_used_s))
        yield block, window_stats(block, scale)


def estimate_from(run, factory, lag_used_s: float = 0.0) -> LagEstimate:
    """The service's estimate from the windows an agent running lag_used_s writes (120 s), fed as the drift
    monitor feeds it (DeviceMonitor._lag): every window draws the die's path, the fitted ones measure."""
    estimate = LagEstimate()
    for block, stats in windows(run, factory, 120.0, lag_used_s):
        f = window_features(stats, t=float(block.t[-1]), temp_c=stats.temp_mean, band=0)
        estimate.add(
            start=float(block.t[0]),
            end=float(block.t[-1]),
            temp_c=stats.temp_mean,
            rate_c_per_s=temp_rate(block),
            lag_used_s=lag_used_s,
            log_amp=None if f.y is None else float(f.y[2]),
            sd=None if f.y is None else float(f.sigma[2]),
        )
    return estimate


@pytest.mark.parametrize(("seed", "written_with"), [(81, 0.0), (82, 0.0), (83, 0.5)])
def test_the_lag_is_measured_from_window_statistics_within_a_tenth(seed, written_with):
    """written_with: the windows come from an agent already reading its die at that fraction of the true lag
    (a first estimate sent earlier); the estimate is of the whole lag all the same."""
    phys, factory, run = drive_with_hidden_lag(seed)
    used = written_with * phys.die_lag_s
    tau, se = estimate_from(run, factory, used).tau()
    assert abs(tau - phys.die_lag_s) < max(0.1 * phys.die_lag_s, 20.0), (tau, se, phys.die_lag_s)
    assert se < 0.1 * phys.die_lag_s
    assert lag_to_send((tau, se), used) is not None  # far enough from what the agent runs to be sent


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_a_dwelling_drives_lag_is_measured_from_the_positions_it_holds(seed):
    """A servo holding positions shows no ellipse, so no amplitude: each held position's radius moves with the
    channels' common gain at the die's temperature instead, one curve per position (DeviceMonitor.held_lag), all on
    the one die path. Hidden in the seed: the lag (60-600 s), the drift, the positions; the monitor sees windows.
    Without it a dwelling drive's held points scatter across the circle in proportion to its lag (README)."""
    rng = np.random.default_rng([86, seed])
    phys = replace(fieldsim.draw_drive(rng), die_lag_s=float(rng.uniform(60, 600)))
    factory = calibrate(fieldsim.bench_sweep(phys, rng))
    run = fieldsim.field_run(phys, days=1.0, rate_hz=5.0, regime="dwell", rng=rng)
    monitor = DeviceMonitor("servo")
    for block, stats in windows(run, factory, 60.0):
        start, end = float(block.t[0]), float(block.t[-1])
        monitor.update(
            window_features(stats, t=end, temp_c=stats.temp_mean, band=0, start=start, temp_rate=temp_rate(block))
        )
    assert monitor.lag.tau() is None  # no window fitted an ellipse
    tau, se = monitor.thermal_lag()
    assert abs(tau - phys.die_lag_s) < max(0.1 * phys.die_lag_s, 20.0), (tau, se, phys.die_lag_s)
    assert (lag_to_send((tau, se), 0.0) is not None) == (phys.die_lag_s > 120.0)  # a minute's lag is not sent
    kept = DeviceMonitor.from_dict(json.loads(json.dumps(monitor.to_dict())))  # the service saves the monitor
    assert kept.thermal_lag() == (tau, se)


def test_a_drive_whose_die_does_not_lag_gets_no_lag():
    rng = np.random.default_rng(84)
    phys = replace(fieldsim.draw_drive(rng), die_lag_s=0.0)
    factory = calibrate(fieldsim.bench_sweep(phys, rng))
    run = fieldsim.field_run(phys, days=0.75, rate_hz=5.0, regime="even", rng=rng)
    estimate = estimate_from(run, factory)
    assert estimate.tau() is not None and estimate.tau()[0] < 20.0
    assert lag_to_send(estimate.tau(), 0.0) is None


def stored_drive_with_hidden_lag(store, service):
    """Windows of a drive with a hidden lag, stored as its agent sends them, and the monitor run over them."""
    phys, factory, run = drive_with_hidden_lag(85)
    store.insert_coefficient_set(factory_set(DEVICE, factory))
    store.mark_published(DEVICE, 0)
    for seq, (block, stats) in enumerate(windows(run, factory, 120.0), start=1):
        store.insert_window(
            wire.window_message(
                DEVICE, seq, stats, window_start=float(block.t[0]), window_end=float(block.t[-1]),
                temp_rate_c_per_s=temp_rate(block), coefficients_version=0, angle_quality_deg=0.1,
            )
        )  # fmt: skip
    service.monitor.process(DEVICE)
    service._changed.add(DEVICE)
    return phys


def test_the_service_sends_the_lag_it_measures_and_every_later_set_keeps_it(fleet):
    """Windows of a drive with a hidden lag, stored as the agent sends them (the real store, its monitor and the
    refit pass): the next set carries the lag (confirmed, the bands as they ran), and the sets after it keep it."""
    store, service = fleet
    phys = stored_drive_with_hidden_lag(store, service)
    assert service.refit_all()
    sent = store.coefficient_set(DEVICE, 1)
    history = {h["version"]: h for h in store.coefficient_history(DEVICE)}
    assert abs(sent["thermal_lag_s"] - phys.die_lag_s) < 0.1 * phys.die_lag_s, (sent["thermal_lag_s"], phys.die_lag_s)
    assert history[1]["state"] == "confirmed" and "die lag" in history[1]["state_reason"]
    assert [b["w"] for b in sent["bands"]] == [b["w"] for b in store.coefficient_set(DEVICE, 0)["bands"]]
    assert store.band_stats(DEVICE)  # band memory is kept (the older windows fade out with the horizon)
    # every set after it carries the drive's lag
    service.publish_step_move(DEVICE, "offset_step", {"delta_d": 0.001, "delta_q": 0.0})
    assert store.coefficient_set(DEVICE, 2)["thermal_lag_s"] == sent["thermal_lag_s"]
    # and the audit export says which lag each set was read at, read back with the mcap reader
    exported = {
        json.loads(m.data)["version"]: json.loads(m.data).get("thermal_lag_s")
        for _, c, m in make_reader(io.BytesIO(b"".join(iter_mcap(store, DEVICE)))).iter_messages()
        if c.topic.endswith("/coefficients")
    }
    assert exported == {0: None, 1: sent["thermal_lag_s"], 2: sent["thermal_lag_s"]}


def test_an_agent_older_than_the_lag_refuses_it_once_and_is_sent_none_again(fleet):
    """The lag is a field newer agents know (docs/wire.md): an older one refuses the set, with its schema's words.
    The service rolls the set back to the one the drive runs, with no lag, and does not send it a lag again."""
    store, service = fleet
    stored_drive_with_hidden_lag(store, service)
    assert service.refit_all() == [1] and store.coefficient_set(DEVICE, 1)["thermal_lag_s"] > 0
    refusal = "coefficients message: $: Additional properties are not allowed ('thermal_lag_s' was unexpected)"
    store.insert_ack(wire.ack_message(DEVICE, 1, "rejected", service._drive_now(DEVICE), reason=refusal))
    service._changed.add(DEVICE)
    assert service.refit_all() == [2]
    history = {h["version"]: h for h in store.coefficient_history(DEVICE)}
    assert history[1]["state"] == "rolled_back" and "thermal_lag_s" in history[1]["state_reason"]
    assert history[2]["restores_version"] == 0 and "thermal_lag_s" not in history[2]["message"]  # it can run it
    assert service.monitor.thermal_lag(DEVICE) is not None  # the windows still measure the lag ...
    assert service.publish_lag(DEVICE) is None  # ... but this drive's agent is not sent it again


def test_an_agent_that_refused_the_lag_is_offered_it_again_once_it_came_back_a_day_later(fleet):
    """An agent older than the lag refused it and got none since; upgraded, it restarts (its liveliness token goes
    and comes back). A day after the refusal the lag is offered again; a token that merely flaps soon after the
    refusal does not make the service ask again."""
    import time

    store, service = fleet
    stored_drive_with_hidden_lag(store, service)
    assert service.refit_all() == [1]
    refusal = "coefficients message: $: Additional properties are not allowed ('thermal_lag_s' was unexpected)"
    ack = wire.ack_message(DEVICE, 1, "rejected", service._drive_now(DEVICE), reason=refusal)
    store.insert_ack(ack, received_at=time.time() - 2 * 86_400)  # refused two days ago
    service._changed.add(DEVICE)
    assert service.refit_all() == [2]  # rolled back, no lag
    assert service.publish_lag(DEVICE) is None  # still the agent that refused: no lag
    store.set_online(DEVICE, True)
    store.set_online(DEVICE, False)
    store.set_online(DEVICE, True)  # restarted (upgraded)
    version = service.publish_lag(DEVICE)
    assert version == 3 and store.coefficient_set(DEVICE, 3)["thermal_lag_s"] > 0

    again = wire.ack_message(DEVICE, 3, "rejected", service._drive_now(DEVICE), reason=refusal)
    store.insert_ack(again)  # still old after all: refused just now
    store.set_online(DEVICE, False)
    store.set_online(DEVICE, True)  # the token flaps
    assert service.publish_lag(DEVICE) is None
