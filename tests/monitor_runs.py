"""The drift monitor run over a simulated drive's windows, for the monitor tests."""

from __future__ import annotations

from dataclasses import replace

from edge_agent.agent import temp_rate
from encoder_core.monitor import DeviceMonitor, Settings, window_features
from encoder_core.physics import band_of
from encoder_core.stats import normalisation_scale, window_stats
from encoder_core.thermal import DieTemperature
from encoder_fleet.fleet_accuracy import windows_of


def offset_step_alarms(
    run, factory, window_s: float = 60.0, settings: Settings | None = None
) -> tuple[list[tuple[float, dict]], int]:
    """(drive time, parameters) of every offset_step raised (each cleared at once, so that every one is counted),
    and how many windows the ellipse could judge."""
    return step_alarms(run, factory, window_s, "offset_step", settings)


def step_alarms(
    run, factory, window_s: float, cause: str, settings: Settings | None = None, *, moved_for: bool = False
) -> tuple[list[tuple[float, dict]], int]:
    """offset_step_alarms for any cause. moved_for: only those the service moves the running set for, not the ones
    the held test named undecided (DeviceMonitor.step_measured)."""
    monitor, raised = DeviceMonitor("under-test", settings=settings or Settings()), []
    for end_s, event in monitored(run, factory, window_s, monitor):
        if event.kind == "raise" and event.cause == cause:
            if not moved_for or monitor.step_measured(event.at):
                raised.append((end_s, event.parameters))
            monitor.clear(cause, end_s, "counted")
    return raised, monitor.judged


def moved_for_offset_steps(run, factory, window_s: float = 60.0) -> list[tuple[float, dict]]:
    """The offset steps raised that the service moves the running set for (step_alarms' moved_for)."""
    return step_alarms(run, factory, window_s, "offset_step", moved_for=True)[0]


def monitored(
    run, factory, window_s: float, monitor: DeviceMonitor, until_s: float = float("inf"), lag_used_s: float = 0.0
):
    """(window end, event) of every event the monitor gives over the drive's windows (those ending by until_s).
    lag_used_s: the windows as an agent running a set with that die lag writes them (at its die estimate)."""
    scale, die = normalisation_scale(factory), DieTemperature()
    for start, end in windows_of(run.samples.t, window_s):
        block = run.samples.subset(slice(start, end))
        if lag_used_s:
            block = replace(block, temp_c=die(block.t, block.temp_c, lag_used_s))
        stats = window_stats(block, scale)
        if not stats.temp_n:
            continue
        end_s = float(run.samples.t[end - 1])
        if end_s > until_s:
            return
        features = window_features(  # as the agent reports it: with how fast the temperature moved
            stats,
            t=end_s,
            temp_c=stats.temp_mean,
            band=band_of(stats.temp_mean),
            temp_rate=temp_rate(block),
            lag_used_s=lag_used_s,
        )
        for event in monitor.update(features):
            yield end_s, event
