"""`encoder-fleet bench-fleet-accuracy`: is the fleet ever worse than the factory, on drives it did not write?

Fleets of drives from the independent field simulator (encoder_fleet/fieldsim.py), each calibrated at
the end of the line by `encoder-fleet calibrate` on its own +20 °C bench sweep, then run for days in
the field. The fleet loop runs in this process through the same code as the real parts: the agent's
usable-sample mask and window statistics (edge_agent.agent.EdgeAgent), the window's band as the wire
message computes it, band sums with the store's drive-time horizon, the drift monitor restarting every
band's memory after an offset step and moving the running set by it (as service.runtime does), the
watch of the running set against the factory's every quarter of a drive-hour
(service.trial.watch_against_factory), `service.refit.refit_device` on a refit cadence with what the
service passes it, the agent's plausibility check before applying a set, and the set applied from the
next window on, and the guard's trials as service.runtime judges them.
The windows and band sums go through the service's own store (a SQLite file per drive). Only the transport
(Zenoh) is left out, so that a fleet of drives × days × rates runs in minutes.

Scoring uses the simulator's truth, which the loop never sees: the true angle error of what each drive
ran (the factory set, then every applied set from the window after its refit), on noise-free signals
at the samples' true angles and die temperatures, as an RMS per drive-hour. Beside it, the
reference-free floors (`floor_sets`): the best any refit without a reference could have done.
"""

from __future__ import annotations

import math
import multiprocessing
import re
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from edge_agent.agent import check_plausible, factory_message, temp_rate
from encoder_core.correction import BandedCorrection, Correction, zero_shift
from encoder_core.methods import OursLsRef
from encoder_core.monitor import DeviceMonitor, window_features
from encoder_core.physics import BAND_WIDTH_C, band_of
from encoder_core.samples import InputError, Samples
from encoder_core.stats import WindowStats, normalisation_scale, window_stats
from encoder_core.thermal import DieTemperature, first_order_lag, lag_to_send
from encoder_fleet import fieldsim
from encoder_fleet.calibrate import calibrate
from fleet_wire import keys
from fleet_wire import messages as wire
from service.refit import STEP_CAUSES, STEP_OPEN_S, refit_device, step_moved_bands
from service.runtime import BAND_HORIZON_H, REFIT_EVERY_S, TRIAL_MAX_S, WATCH_EVERY_S
from service.store import Store
from service.trial import WATCH_S, TrialEvidence, changed_bands, judge, watch_against_factory

EVENTS = (None, "offset_step", "gain_step", "axis_step")
BAND_HORIZON_S = BAND_HORIZON_H * 3600.0  # drive time a band's sum remembers, as the service's store
SCORE_PER_HOUR = 300  # samples scored per drive-hour
# service.runtime judges a set on trial at every refit pass (as soon as windows are stored); the loop every 5 drive-min
# (or every window, when windows are longer). Until 2026-11-27 it judged only on its hourly refit grid and then
# skipped that hour's refit: up to two hours later than the service after every new set (s1-5hz-04)
JUDGE_EVERY_S = 300.0
# an hour is worse than the factory's when its RMS error is higher by over 1 % and over a millidegree
WORSE_MARGIN = 0.01
WORSE_MIN_DEG = 0.001
MAX_WORSE_SHARE = 0.01  # the bar: a drive worse than its factory set in more of its hours than this fails it


@dataclass
class DriveSpec:
    name: str
    seed: int
    index: int
    motion: str
    event: str | None
    rate_hz: float
    window_s: float
    days: float


@dataclass
class DriveResult:
    name: str
    motion: str
    event: str | None
    rate_hz: float
    versions_applied: int
    factory_hour_deg: list[float] = field(default_factory=list)
    fleet_hour_deg: list[float] = field(default_factory=list)
    floor_hour_deg: list[float] = field(default_factory=list)
    drift_floor_hour_deg: list[float] = field(default_factory=list)  # floor_sets' second reading
    step_hours: list[int] = field(default_factory=list)  # the hours (from the start) a planted step happened in

    @property
    def factory_deg(self) -> float:
        return float(np.mean(self.factory_hour_deg))

    @property
    def fleet_deg(self) -> float:
        return float(np.mean(self.fleet_hour_deg))

    @property
    def floor_deg(self) -> float:
        return float(np.mean(self.floor_hour_deg))

    @property
    def drift_floor_deg(self) -> float:
        return float(np.mean(self.drift_floor_hour_deg))

    @property
    def floor_gain(self) -> float:
        """The best gain any reference-free refit could reach on this drive (see `floor_sets`)."""
        return self.factory_deg / self.floor_deg if self.floor_deg > 0 else float("inf")

    @property
    def gain(self) -> float:
        return self.factory_deg / self.fleet_deg if self.fleet_deg > 0 else float("inf")

    @property
    def worse_hour_indices(self) -> list[int]:
        """The drive-hours (from the start) whose fleet error is worse than the factory set's."""
        return worse_than(self.fleet_hour_deg, self.factory_hour_deg)

    @property
    def worse_hours(self) -> int:
        return len(self.worse_hour_indices)

    @property
    def floor_worse_hour_indices(self) -> list[int]:
        """The drive-hours in which a floor (`floor_sets`) is itself worse than the factory set. The reference-free
        floor: on the arc the drive visited that hour, the factory's drift errors happened to cancel part of the
        zero's own drift, which no refit without a reference can see (a clean reversing drive, s3-0.5hz-03: five
        such hours). The drift floor: there they cancelled part of the factory set's own residual from the bench,
        which no refit without a reference can see either (s1-20hz-06-dwell, hour 23)."""
        floors = (self.floor_hour_deg, self.drift_floor_hour_deg)
        return sorted({h for hours in floors if hours for h in worse_than(hours, self.factory_hour_deg)})

    @property
    def floor_shared_worse_hours(self) -> int:
        """Worse hours that the floor shares: a perfect reference-free refit would be worse there too."""
        return len(set(self.worse_hour_indices) & set(self.floor_worse_hour_indices))

    @property
    def step_near_hours(self) -> set[int]:
        """A planted step's own hour and the next, for every step."""
        return {h + k for h in self.step_hours for k in (0, 1)}

    @property
    def step_worse_hours(self) -> int:
        """Worse hours in a planted step's own hour or the next: the drive runs its set from before the step
        until the step is seen in its windows and a set moved for it is applied, and where the drift the set
        corrects had cancelled part of the step's error, that set is worse than the factory's meanwhile (the floor
        knows a step the moment it happens, so it does not share these). Those the floor shares are counted there, not
        here."""
        return len((set(self.worse_hour_indices) & self.step_near_hours) - set(self.floor_worse_hour_indices))

    @property
    def worse_share(self) -> float:
        """The fraction of the drive's hours it ran worse than its factory set."""
        return self.worse_hours / max(len(self.fleet_hour_deg), 1)

    @property
    def own_worse_share(self) -> float:
        """worse_share without the hours the floor shares or a step's own (the refit's to avoid)."""
        own = set(self.worse_hour_indices) - set(self.floor_worse_hour_indices) - self.step_near_hours
        return len(own) / max(len(self.fleet_hour_deg), 1)


def worse_than(hour_deg, factory_hour_deg) -> list[int]:
    """The hours in which `hour_deg` is worse than the factory's (WORSE_MARGIN and WORSE_MIN_DEG both)."""
    err, factory = np.array(hour_deg), np.array(factory_hour_deg)
    return np.flatnonzero((err > factory * (1 + WORSE_MARGIN)) & (err > factory + WORSE_MIN_DEG)).tolist()


def fleet_specs(
    seed: int, drives: int, days: float, rate_hz: float, window_s: float, events: bool = True
) -> list[DriveSpec]:
    """A mixed fleet: motions in turn; with events, one planted in two drives of three (a third stay clean)."""
    specs = []
    for i in range(drives):
        motion = fieldsim.REGIMES[i % len(fieldsim.REGIMES)]
        event = None if (i % 3 == 0 or not events) else EVENTS[1 + (i // 3) % (len(EVENTS) - 1)]
        name = f"s{seed}-{rate_hz:g}hz-{i:02d}-{motion}"
        specs.append(DriveSpec(name, seed, i, motion, event, rate_hz, window_s, days))
    return specs


def windows_of(t: np.ndarray, window_s: float) -> list[tuple[int, int]]:
    """Index ranges of consecutive windows of the drive's clock (as ReplaySource.read cuts them)."""
    edges = np.arange(t[0], t[-1] + window_s, window_s)[1:]
    cuts = np.searchsorted(t, edges, side="left")
    starts = np.concatenate(([0], cuts))
    ends = np.concatenate((cuts, [t.size]))
    return [(int(a), int(b)) for a, b in zip(starts, ends) if b > a]


class StoreSums:
    """The drive's windows in the service's own store (service/store.py, a SQLite file): its band sums with
    the drive-time horizon, its restart of band memory after a step, and its windows since a time for the
    watch. The bench once kept its own copy of these sums and so never saw two bugs the store had."""

    DEVICE = "drive"

    def __init__(self, path, origin_s: float, horizon_s: float | None = BAND_HORIZON_S):
        self.store = Store.open(path, band_horizon_s=horizon_s)
        self.origin_s = origin_s  # the agent's clock starts at 0; the simulator's first sample may be jittered below
        self.seq = 0
        self.pending: list[tuple[str, bytes]] = []

    def add(self, stats: WindowStats, start_s: float, end_s: float) -> None:
        """A window, sent as the agent sends it; stored with the others in one batch when the sums are read."""
        self.seq += 1
        message = wire.window_message(
            self.DEVICE,
            self.seq,
            stats,
            window_start=start_s - self.origin_s,
            window_end=end_s - self.origin_s,
            temp_rate_c_per_s=0.0,
            coefficients_version=0,
            angle_quality_deg=0.0,
        )
        self.pending.append((keys.key(self.DEVICE, keys.STATS), wire.encode("window", message)))

    def _ingest(self) -> None:
        if self.pending:
            statuses = self.store.ingest_many(self.pending)
            refused = [s for s in statuses if s != "stored"]
            if refused:
                raise RuntimeError(f"the store refused {len(refused)} of the bench's windows: {refused[0]}")
            self.pending = []

    def band_sums(self) -> dict[int, WindowStats]:
        self._ingest()
        return {band: stats for band, (stats, _, _) in self.store.band_stats(self.DEVICE).items()}

    def recent(self, after_s: float) -> dict[int, WindowStats]:
        """Each band's sum of the windows that ended after `after_s`."""
        self._ingest()
        return self.store.stats_since(self.DEVICE, after_s - self.origin_s)

    def restart(self, after_s: float) -> None:
        """Forget the windows that ended at or before `after_s` in every band."""
        self._ingest()
        self.store.restart_band_memory(self.DEVICE, after=after_s - self.origin_s)


def drive_of(spec: DriveSpec) -> tuple[fieldsim.DrivePhysics, BandedCorrection, fieldsim.FieldRun]:
    """The drive a spec names, drawn from its seed: its physics (the truth), its factory set, its run."""
    rng = np.random.default_rng([spec.seed, spec.index, int(spec.rate_hz * 1000)])
    phys = fieldsim.draw_drive(rng, event=spec.event, days=spec.days)
    factory = calibrate(fieldsim.bench_sweep(phys, rng))
    return phys, factory, fieldsim.field_run(phys, days=spec.days, rate_hz=spec.rate_hz, regime=spec.motion, rng=rng)


def run_drive(spec: DriveSpec) -> DriveResult:
    _, factory, run = drive_of(spec)
    return scored(spec, factory, run, fleet_loop(run.samples, factory, window_s=spec.window_s))


@dataclass
class Explanation:
    """One drive of a benchmark fleet, replayed with every decision the loop took (`explain_drive`)."""

    result: DriveResult
    planted: list[tuple[float, str]]  # the simulator's truth: (hour, kind) of each planted event
    decisions: list[tuple[float, str]]  # (hour, what the loop did or saw)
    hour_temp_c: list[float]  # the reported temperature, mean per drive-hour


SPEC_NAME = re.compile(r"^s(\d+)-([0-9.]+)hz-(\d+)-([a-z]+)$")


def spec_named(name: str, *, drives: int, days: float, window_s: float | None, events: bool = True) -> DriveSpec:
    """The drive a benchmark names (s<seed>-<rate>hz-<index>-<motion>, as in its table) in a fleet of `drives`."""
    match = SPEC_NAME.match(name)
    if match is None:
        raise InputError(f"drive name {name!r} is not s<seed>-<rate>hz-<index>-<motion> (e.g. s8-20hz-10-dwell)")
    seed, rate = int(match.group(1)), float(match.group(2))
    window = window_s or default_window(rate)
    specs = fleet_specs(seed, drives, days, rate, window, events)
    found = [spec for spec in specs if spec.name == name]
    if not found:
        raise InputError(
            f"no drive {name!r} in the fleet of seed {seed} at {rate:g} Hz with {drives} drives: "
            f"{', '.join(spec.name for spec in specs)}"
        )
    return found[0]


def explain_drive(spec: DriveSpec) -> Explanation:
    """Run one drive as the benchmark does, keeping every decision of the loop beside its score."""
    physics, factory, run = drive_of(spec)
    t0 = float(run.samples.t[0])
    decisions = []
    timeline = fleet_loop(
        run.samples,
        factory,
        window_s=spec.window_s,
        log=lambda t, text: decisions.append(((t - t0) / 3600.0, text)),
    )
    hours = np.floor((run.samples.t - t0) / 3600.0).astype(int)  # as `score` counts drive-hours
    temps = (np.bincount(hours, weights=run.samples.temp_c) / np.bincount(hours)).tolist()
    planted = [((e.t_s - t0) / 3600.0, e.kind) for e in physics.events]
    return Explanation(scored(spec, factory, run, timeline), planted, decisions, temps)


def format_explanation(ex: Explanation) -> str:
    """The decisions in drive order, then a table of every drive-hour: what the factory set, the fleet and the
    floors left, and which hours count as worse (and whether a floor or a planted step shares them)."""
    r = ex.result
    planted = ", ".join(f"{kind} at {h:.2f} h" for h, kind in ex.planted) or "nothing"
    lines = [
        f"{r.name}: {r.gain:.2f}x the factory set (its floor {r.floor_gain:.1f}x), {r.worse_hours} worse hour(s), "
        f"{r.versions_applied} set(s) applied; planted (the simulator's truth, which the loop never sees): {planted}",
        "",
        "| drive hour | what the fleet did or saw |",
        "|---|---|",
    ]
    lines += [f"| {h:.2f} | {text} |" for h, text in ex.decisions]
    lines += [
        "",
        "| hour | °C | factory ° | fleet ° | reference-free floor ° | drift floor ° | |",
        "|---|---|---|---|---|---|---|",
    ]
    worse, floors, steps = set(r.worse_hour_indices), set(r.floor_worse_hour_indices), r.step_near_hours
    planted_hours = set(r.step_hours)
    for h, temp in enumerate(ex.hour_temp_c):
        mark = ""
        if h in worse:
            mark = "worse" + (" (a floor too)" if h in floors else " (at a step)" if h in steps else "")
        elif h in planted_hours:
            mark = "step"
        lines.append(
            f"| {h} | {temp:+.1f} | {r.factory_hour_deg[h]:.4f} | {r.fleet_hour_deg[h]:.4f} | "
            f"{r.floor_hour_deg[h]:.4f} | {r.drift_floor_hour_deg[h]:.4f} | {mark} |"
        )
    return "\n".join(lines)


def plot_explanation(ex: Explanation, path) -> None:
    """The drive-hours as a picture: the factory set's, the fleet's and the floor's error (log scale), the worse
    hours shaded, a tick at every set applied and every alarm raised; the temperature below."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    r = ex.result
    hours = np.arange(len(r.fleet_hour_deg)) + 0.5
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(11, 6), sharex=True, height_ratios=(3, 1))
    top.semilogy(hours, r.factory_hour_deg, "-", color="0.45", label="factory set")
    top.semilogy(hours, r.fleet_hour_deg, "-", color="tab:blue", label="fleet (what the drive ran)")
    top.semilogy(hours, r.floor_hour_deg, ":", color="tab:green", label="reference-free floor")
    for h in r.worse_hour_indices:
        top.axvspan(h, h + 1, color="tab:red", alpha=0.2, lw=0)
    for h, text in ex.decisions:
        if " applied: " in text:
            top.axvline(h, color="tab:blue", lw=0.6, alpha=0.5)
        elif text.startswith("alarm raise"):
            top.axvline(h, color="tab:red", lw=1.0, ls="--")
    for h, kind in ex.planted:
        top.axvline(h, color="black", lw=1.0, ls=":")
        top.annotate(f" {kind} (planted)", (h, 0.02), xycoords=("data", "axes fraction"), fontsize=8)
    top.set_ylabel("true angle error, ° RMS per hour")
    top.legend(loc="upper right", fontsize=8)
    top.set_title(
        f"{r.name}: {r.gain:.2f}x, {r.worse_hours} worse hour(s) shaded; blue lines: sets applied, red dashed: alarms, "
        "black dotted: planted events",
        fontsize=10,
    )
    bottom.plot(hours, ex.hour_temp_c, color="tab:orange")
    bottom.set_ylabel("°C")
    bottom.set_xlabel("drive hour")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def scored(spec: DriveSpec, factory: BandedCorrection, run: fieldsim.FieldRun, timeline) -> DriveResult:
    """A drive's result from the timeline of what it ran (from drive time, set), on true angle."""
    factory_hours, fleet_hours = score(run, factory, timeline)
    floor_hours, drift_floor_hours = score_floor(run, factory)
    return DriveResult(
        name=spec.name,
        motion=spec.motion,
        event=spec.event,
        rate_hz=spec.rate_hz,
        versions_applied=len(timeline) - 1,
        factory_hour_deg=factory_hours,
        fleet_hour_deg=fleet_hours,
        floor_hour_deg=floor_hours,
        drift_floor_hour_deg=drift_floor_hours,
        step_hours=sorted({int((e.t_s - run.samples.t[0]) // 3600) for e in run.physics.events}),
    )


def fleet_loop(
    samples: Samples,
    factory: BandedCorrection,
    *,
    window_s: float,
    refit_every_s: float = REFIT_EVERY_S,
    horizon_s: float | None = BAND_HORIZON_S,
    monitor: bool = True,
    guard: bool = True,
    watch_factory: bool = True,
    watch_every_s: float = WATCH_EVERY_S,
    log: Callable[[float, str], None] | None = None,
) -> list[tuple[float, BandedCorrection]]:
    """The agent's windows, the service's band sums and refits, the drift monitor restarting band memory
    after a step, the guard holding each new set on trial until the soak judges it (service.runtime), the
    agent applying sets: returns the timeline of what the drive ran, as (from drive time, set). `log(drive time,
    text)`, when given, hears every decision: alarms, refits, verdicts, sets sent and applied (`explain_drive`)."""
    with tempfile.TemporaryDirectory(prefix="fleet-accuracy-") as tmp:
        sums = StoreSums(Path(tmp) / "fleet.sqlite", float(samples.t[0]), horizon_s)
        try:
            return _fleet_loop(
                samples,
                factory,
                sums,
                window_s,
                refit_every_s,
                monitor,
                guard,
                watch_factory,
                watch_every_s,
                log,
            )
        finally:
            sums.store.close()


def _fleet_loop(samples, factory, sums, window_s, refit_every_s, monitor, guard, watch_factory, watch_every_s, listen):
    log = listen or (lambda t, text: None)  # the summaries below are only built for a listener
    scale = normalisation_scale(factory)  # the agent's normalisation
    watch = DeviceMonitor("drive") if monitor else None
    factory_msg = factory_message("drive", factory)
    confirmed, trial = factory_msg, None  # trial: [set message, soak band -> stats, bands it changed]
    running, running_msg = factory, factory_msg
    timeline = [(float(samples.t[0]), factory)]
    next_watch = float(samples.t[0]) + refit_every_s
    next_refit = float(samples.t[0])  # service.runtime refits a device at its first pass, then an hour after each fit
    next_judge = -math.inf
    pending: dict | None = None  # a set message sent, applied by the agent from its next window
    step_at = None
    axis_turn = 0.0  # the axis steps named so far, summed (service.runtime.fit)
    no_axis_step = True  # no step named so far was an axis step (service.runtime.fit)
    deferred = None  # a step's move waiting for a trial's verdict: (cause, parameters, at)
    before_step = None  # the set confirmed before a step the monitor could not measure (service.runtime.fit)
    die = DieTemperature()  # the agent's
    for start, end in windows_of(samples.t, window_s):
        block = samples.subset(slice(start, end))
        if pending is not None:  # the agent applies what arrived before this window
            lag = pending.get("thermal_lag_s", running.thermal_lag_s)  # a set without one keeps the drive's
            running, running_msg = BandedCorrection.from_dict({**pending, "thermal_lag_s": lag}), pending
            timeline.append((float(block.t[0]), running))
            if listen:
                log(float(block.t[0]), f"v{pending['version']} applied: {_set_summary(pending)}")
            if watch is not None and step_at is not None and pending["created_at"] >= step_at:
                # service.monitor: the step is cleared once a set made after it is applied (the next can be named)
                for cause in STEP_CAUSES:
                    watch.clear(cause, float(block.t[0]), "a set made after the step was applied")
            if pending.get("lag_only"):  # service.runtime.publish_lag: confirmed as it is sent
                confirmed = pending
            elif guard and pending["basis"] != "rollback":
                trial = [pending, {}, changed_bands(pending, confirmed), float(block.t[0])]
                next_judge = float(block.t[0])  # service.runtime judges a new trial from its next pass on
            pending = None
        if deferred is not None and pending is None and trial is None:  # service.runtime.refit: after the verdict
            bands = step_moved_bands(running_msg["bands"], deferred[0], deferred[1], scale)
            pending = {"bands": bands, "basis": "fit", "version": len(timeline), "created_at": float(block.t[0])}
            log(float(block.t[0]), f"v{pending['version']} sent: the running set moved for the {deferred[0]}")
            deferred = None
            next_refit = float(block.t[0]) + refit_every_s
        block = replace(block, temp_c=die(block.t, block.temp_c, running.thermal_lag_s))  # EdgeAgent.step
        stats = window_stats(block, scale)  # the agent's own code path
        if stats.temp_n == 0:
            continue
        band, end_s = band_of(stats.temp_mean), float(block.t[-1])
        sums.add(stats, float(block.t[0]), end_s)
        if trial is not None and band in trial[2]:  # the soak: what the drive ran on the trial set
            trial[1][band] = trial[1][band].merge(stats) if band in trial[1] else stats
        if watch is not None:
            features = window_features(
                stats,
                t=end_s,
                temp_c=stats.temp_mean,
                band=band,
                start=float(block.t[0]),
                temp_rate=temp_rate(block),
                lag_used_s=running.thermal_lag_s,
            )
            for event in watch.update(features):
                log(event.at, f"alarm {event.kind}: {event.cause}: {event.evidence}")
                if event.cause in STEP_CAUSES and event.kind == "raise":
                    sums.restart(after_s=event.at)
                    step_at = event.at
                    before_step = None
                    axis_turn += event.parameters["delta_skew"] if event.cause == "axis_step" else 0.0
                    no_axis_step &= event.cause != "axis_step"
                    if not watch.step_measured(event.at):  # service.runtime.back_to_factory: not moved for
                        if -math.inf < bands_from(confirmed) < step_at:
                            before_step = BandedCorrection.from_dict(confirmed)
                        pending = factory_again(factory_msg, len(timeline), end_s)
                        log(end_s, f"v{pending['version']} sent: the factory set again (the step was not measured)")
                        confirmed, trial, deferred = pending, None, None
                        next_refit = end_s + refit_every_s
                    elif trial is not None and trial[0]["created_at"] >= event.at:
                        deferred = None  # the set on trial was fitted after the step (service.runtime.refit)
                    elif pending is not None or trial is not None:  # the move waits for them
                        deferred = (event.cause, event.parameters, event.at)
                    else:  # service.runtime.publish_step_move
                        bands = step_moved_bands(running_msg["bands"], event.cause, event.parameters, scale)
                        pending = {"bands": bands, "basis": "fit", "version": len(timeline), "created_at": end_s}
                        log(end_s, f"v{pending['version']} sent: the running set moved for the {event.cause}")
                        next_refit = end_s + refit_every_s
        if watch_factory and pending is None and end_s >= next_watch:
            next_watch = end_s + watch_every_s
            since = max(end_s - WATCH_S, step_at or 0.0)  # service.runtime.watch: the drive as it is since a step
            if watch_against_factory(sums.recent(since), running, factory):
                # the first rule: the running set is worse than the factory's: the factory's again, and the drive
                # learnt from what it is now
                pending = factory_again(factory_msg, len(timeline), end_s)
                log(end_s, f"v{pending['version']} sent: the factory set again (the running set measured worse)")
                confirmed, trial = pending, None
                sums.restart(after_s=end_s - WATCH_S)
                next_refit = end_s + refit_every_s
                continue
        if trial is not None:  # no new set while one is on trial: service.runtime judges it at every pass
            if end_s >= next_judge:
                next_judge = end_s + JUDGE_EVERY_S
                verdict = judge(TrialEvidence(trial[0], confirmed, trial[1], factory=factory_msg))
                if verdict.action == "wait" and end_s - trial[3] >= TRIAL_MAX_S:
                    verdict.action = "confirm"  # a trial not measured in time stays on the refit's word
                    verdict.reason = "not measured within the trial's limit: kept on the refit's word"
                if verdict.action != "wait":
                    log(end_s, f"v{trial[0]['version']} {verdict.action}: {verdict.reason}")
                if verdict.action == "confirm":
                    confirmed, trial = trial[0], None
                elif verdict.action == "rollback":
                    pending, trial = {**confirmed, "basis": "rollback", "created_at": end_s}, None
                    pending["bands_from"] = bands_from(confirmed)
            continue  # a verdict is the pass's work; the refit is due an hour after the last fit or move
        if end_s < next_refit:
            continue
        next_refit = end_s + refit_every_s  # service.runtime._refitted: the cadence restarts at every fit
        if watch is not None and pending is None and deferred is None:
            lag = lag_to_send(watch.thermal_lag(), running.thermal_lag_s)
            if lag is not None:  # service.runtime.publish_lag: the bands as they run, read at the new die estimate
                pending = {"bands": running_msg["bands"], "basis": "fit", "version": len(timeline), "created_at": end_s}
                pending.update(thermal_lag_s=lag, lag_only=True, bands_from=bands_from(running_msg))
                log(end_s, f"v{pending['version']} sent: the running bands with a die lag of {lag:.0f} s")
                continue
        band_sums = sums.band_sums()
        bin_temps = {b: s.bin_temps() for b, s in band_sums.items()}  # what service.runtime passes
        # service.runtime: only a set whose bands predate the step has bands to move for it
        after_step = step_at is not None and end_s - step_at < STEP_OPEN_S and bands_from(running_msg) < step_at
        result = refit_device(
            band_sums,
            running,
            factory,
            bin_temps=bin_temps,
            after_step=after_step,
            stepped_since_bench=step_at is not None,
            no_axis_step=no_axis_step,
            axis_turn=axis_turn,
            held_watched=watch is not None and watch.watches_held_positions(),  # as service.runtime passes it
            before_step=before_step,
        )
        if listen:
            log(end_s, _refit_summary(result))
        if result.changed:
            candidate = BandedCorrection.from_dict({"bands": result.bands})
            try:
                check_plausible(candidate, factory)
            except InputError as exc:
                log(end_s, f"the agent would refuse that set ({exc}): not sent")
                continue  # the agent refuses it and keeps running what it has
            pending = {"bands": result.bands, "basis": "fit", "version": len(timeline), "created_at": end_s}
            log(end_s, f"v{pending['version']} sent: the refit's set")
    return timeline


def _set_summary(msg: dict) -> str:
    """A set message in a line: its basis and the temperatures of its entries."""
    temps = ", ".join("bench" if b["temp_c"] is None else f"{b['temp_c']:+.1f}" for b in msg["bands"])
    lag = f", die lag {msg['thermal_lag_s']:.0f} s" if msg.get("thermal_lag_s") else ""
    return f"{msg['basis']}, entries at {temps} °C{lag}"


def _refit_summary(result) -> str:
    """A refit's decisions in a line: each band adopted (its stated error, and how far the running set sat from
    it), the bands moved for an offset step, and how many candidates it kept the running set against."""
    adopted = [
        f"{d.temp_c:+.1f} °C (states {d.candidate_error_deg:.4f}°, the running set {d.running_error_deg:.4f}° off)"
        for d in result.decisions
        if d.adopted
    ]
    kept = sum(not d.adopted for d in result.decisions)
    parts = [f"adopted {', '.join(adopted)}"] if adopted else ["adopted nothing"]
    if result.moved_bands:
        parts.append(f"moved bands {result.moved_bands} for the offset step")
    if kept:
        parts.append(f"kept the running set in {kept} band(s)")
    return "refit: " + "; ".join(parts)


def factory_again(factory_msg: dict, version: int, at: float) -> dict:
    """The factory set sent again (service.runtime._factory_again: basis rollback, confirmed as it is sent)."""
    bands_from = -math.inf  # the factory's bands: from the bench
    return {
        "bands": factory_msg["bands"],
        "basis": "rollback",
        "version": version,
        "created_at": at,
        "bands_from": bands_from,
    }


def bands_from(msg: dict) -> float:
    """Drive time the set's bands were made at: a rollback's or a new die lag's are the restored set's, the
    factory's the bench's."""
    if msg.get("basis") == "factory":
        return -math.inf
    return msg.get("bands_from", msg.get("created_at", -math.inf))


def score(run: fieldsim.FieldRun, factory: BandedCorrection, timeline) -> tuple[list[float], list[float]]:
    """RMS true angle error per drive-hour of the factory set and of what the drive ran."""
    t = run.samples.t
    hours = np.floor((t - t[0]) / 3600.0).astype(int)
    picked = []
    for h in range(hours.max() + 1):
        idx = np.flatnonzero(hours == h)
        if idx.size:
            picked.append(idx[np.linspace(0, idx.size - 1, min(SCORE_PER_HOUR, idx.size)).astype(int)])
    idx = np.concatenate(picked)
    err_factory = fieldsim.true_error_deg(factory, run, idx)
    err_fleet = np.empty_like(err_factory)
    starts = np.array([s for s, _ in timeline])
    which = np.searchsorted(starts, t[idx], side="right") - 1
    die = {0.0: run.samples.temp_c}  # the agent's die estimate per lag (from the run's start: the same after a few τ)
    for k, (_, corr) in enumerate(timeline):
        sel = which == k
        if sel.any():
            lag = corr.thermal_lag_s
            if lag not in die:
                die[lag] = first_order_lag(t, run.samples.temp_c, lag)
            err_fleet[sel] = fieldsim.true_error_deg(corr, run, idx[sel], temp_c=die[lag][idx[sel]])
    h = hours[idx]
    per_hour = [
        (float(np.sqrt(np.mean(err_factory[h == k] ** 2))), float(np.sqrt(np.mean(err_fleet[h == k] ** 2))))
        for k in np.unique(h)
    ]
    return [f for f, _ in per_hour], [g for _, g in per_hour]


FLOOR_TEMPS_C = np.arange(-35.0, 95.0, BAND_WIDTH_C)  # the floor set's bands: one per band, across the range


def truth_fit(phys: fieldsim.DrivePhysics, temp_c: float, t_s: float):
    """A band fitted against the truth: noise-free channels at 3600 true angles, the die at temp_c, drive time t_s."""
    theta = np.arange(3600) * (2 * np.pi / 3600)
    d, q = phys.channels(theta, np.full(theta.size, temp_c), np.full(theta.size, t_s))
    corr, _ = OursLsRef().fit_band(
        Samples(t=theta, d=d, q=q, temp_c=np.full(theta.size, temp_c), theta_ref=theta), None
    )
    return corr


def floor_sets(
    phys: fieldsim.DrivePhysics, factory: BandedCorrection, t_s: float, bench: Correction
) -> tuple[BandedCorrection, BandedCorrection]:
    """What a perfect reference-free refit would send at drive time t_s, in two readings.

    The floor: each band fitted against the truth, then its zero turned to the factory's. The windows cannot see
    a rotation of both sensor axes together (it is a shift of the zero), so no refit without a reference beats it.

    The drift floor: the factory set plus the change of the truth-fitted band from the bench (`bench`: +20 °C,
    drive time 0) to each band now, its zero turned the same way. What a refit would send that knew exactly how
    the sensor changed since the bench but, like every refit without a reference, not what the bench left: the
    factory set's own residual along the circle (a few millidegrees), which the floor above removes too. On an
    arc, the drift the factory set does not correct can cancel part of that residual, and then the factory set
    is better there than any set that corrects the drift (s1-20hz-06-dwell, hour 23)."""
    floor, drift_floor = [], []
    for temp in FLOOR_TEMPS_C.tolist():
        here = factory.at(temp)
        now = truth_fit(phys, temp, t_s)
        orders = sorted({*now.harmonics, *bench.harmonics, *here.harmonics})
        moved = Correction.from_params(here.params(orders) + now.params(orders) - bench.params(orders), orders, temp)
        for corr, out in ((now, floor), (moved, drift_floor)):
            corr.zero_offset_rad += zero_shift(here, corr)  # the zero the factory's, as the refit's anchor_zero does
            corr.temp_c = temp
            out.append(corr)
    return BandedCorrection(floor), BandedCorrection(drift_floor)


def score_floor(run: fieldsim.FieldRun, factory: BandedCorrection) -> tuple[list[float], list[float]]:
    """RMS true angle error per drive-hour of the reference-free floor and of the drift floor (`floor_sets`),
    their sets refreshed every 6 hours (aging, planted steps: the floors know them the moment they happen)."""
    t = run.samples.t
    events = [e.t_s for e in run.physics.events if t[0] < e.t_s < t[-1]]
    starts = sorted({*np.arange(t[0], t[-1], 6 * 3600.0).tolist(), *events})
    bench = truth_fit(run.physics, fieldsim.BENCH_TEMP_C, 0.0)
    sets = [(float(start), floor_sets(run.physics, factory, float(start), bench)) for start in starts]
    floor = score(run, factory, [(start, pair[0]) for start, pair in sets])[1]
    drift_floor = score(run, factory, [(start, pair[1]) for start, pair in sets])[1]
    return floor, drift_floor


def summarise(results: list[DriveResult]) -> dict:
    gains = np.array([r.gain for r in results])
    hours = sum(len(r.fleet_hour_deg) for r in results)
    worse = sum(r.worse_hours for r in results)
    worst = min(results, key=lambda r: r.gain)
    return {
        "drives": len(results),
        "drive_hours": hours,
        "factory_deg": float(np.median([r.factory_deg for r in results])),
        "fleet_deg": float(np.median([r.fleet_deg for r in results])),
        "median_gain": float(np.median(gains)),
        "floor_median_gain": float(np.median([r.floor_gain for r in results])),
        "worst_gain": float(gains.min()),
        "worst_drive": worst.name,
        "worse_hours": worse,
        "worse_hours_pct": 100.0 * worse / max(hours, 1),
        "max_drive_worse_hours_pct": max(100.0 * r.worse_share for r in results),
        "worse_hours_floor_shares": sum(r.floor_shared_worse_hours for r in results),
        "worse_hours_at_steps": sum(r.step_worse_hours for r in results),
        # the bar: no drive worse than its factory set in more than 1 % of its hours
        "drives_past_1pct": sum(r.worse_share > MAX_WORSE_SHARE for r in results),
        "drives_past_1pct_own": sum(r.own_worse_share > MAX_WORSE_SHARE for r in results),
        "floor_worse_hours": sum(len(r.floor_worse_hour_indices) for r in results),
    }


def run_bench(
    *,
    drives: int,
    days: float,
    seeds: list[int],
    rates: list[float],
    windows: dict[float, float],
    events: bool = True,
    processes: int = 2,
    through_service: float | None = None,
) -> dict:
    """through_service: the real time factor to replay each fleet at through `encoder-fleet service` and agent
    processes (encoder_fleet/fleet_replay.py) instead of the in-process loop."""
    fleets = [
        fleet_specs(seed, drives, days, rate, windows.get(rate, default_window(rate)), events)
        for rate in rates
        for seed in seeds
    ]
    started = time.monotonic()

    def progress(text: str) -> None:
        print(f"… {text}", file=sys.stderr, flush=True)

    if through_service:
        from encoder_fleet.fleet_replay import replay_fleet

        results = [
            r for fleet in fleets for r in replay_fleet(fleet, real_time_factor=through_service, progress=progress)
        ]
    else:
        # spawned, not forked: the caller may hold a Zenoh session (a test run, the service), and a forked child of a
        # process with Zenoh's threads can hang on a lock one of them held
        specs = [spec for fleet in fleets for spec in fleet]
        results = []
        with multiprocessing.get_context("spawn").Pool(processes) as pool:
            for r in pool.imap(run_drive, specs, chunksize=1):  # in order, each drive as it is done
                results.append(r)
                worse = f", {r.worse_hours} worse hour(s)" if r.worse_hours else ""
                progress(
                    f"{len(results)}/{len(specs)} drives, {time.monotonic() - started:.0f} s: {r.name} "
                    f"{r.gain:.2f}x{worse}"
                )
    report = {"elapsed_s": time.monotonic() - started, "regimes": {}, "drives": []}
    for rate in rates:
        mine = [r for r in results if r.rate_hz == rate]
        window = windows.get(rate, default_window(rate))
        report["regimes"][f"{rate:g} Hz, {window:g} s windows"] = summarise(mine)
        for motion in fieldsim.REGIMES:
            subset = [r for r in mine if r.motion == motion]
            if subset:
                report["regimes"][f"{rate:g} Hz, {window:g} s windows, {motion}"] = summarise(subset)
    for r in results:
        row = {k: v for k, v in asdict(r).items() if not k.endswith("hour_deg")}
        row.update(factory_deg=r.factory_deg, fleet_deg=r.fleet_deg, gain=r.gain, worse_hours=r.worse_hours)
        row.update(floor_deg=r.floor_deg, floor_gain=r.floor_gain, worse_hour_indices=r.worse_hour_indices)
        row.update(drift_floor_deg=r.drift_floor_deg)
        row.update(floor_worse_hour_indices=r.floor_worse_hour_indices, step_worse_hours=r.step_worse_hours)
        report["drives"].append(row)
    return report


def default_window(rate_hz: float) -> float:
    """The issue's settings: 300 s windows at 0.5 Hz, 60 s at the faster rates."""
    return 300.0 if rate_hz < 2 else 60.0


def format_report(report: dict) -> str:
    lines = [
        "| regime | drives | drive-hours | factory ° | fleet ° | median gain | reference-free floor | worst drive gain "
        "| worse hours | of which the floor shares | of which at a step | drives past 1 % (besides those) "
        "| the floors' own worse hours |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, s in report["regimes"].items():
        lines.append(
            f"| {name} | {s['drives']} | {s['drive_hours']} | {s['factory_deg']:.4f} | {s['fleet_deg']:.4f} | "
            f"{s['median_gain']:.1f}× | {s['floor_median_gain']:.1f}× | {s['worst_gain']:.2f}× | "
            f"{s['worse_hours']} ({s['worse_hours_pct']:.1f} %, "
            f"worst drive {s['max_drive_worse_hours_pct']:.1f} %) | {s['worse_hours_floor_shares']} | "
            f"{s['worse_hours_at_steps']} | {s['drives_past_1pct']} ({s['drives_past_1pct_own']}) | "
            f"{s['floor_worse_hours']} |"
        )
    lines.append(f"\n{len(report['drives'])} drives in {report['elapsed_s']:.0f} s")
    return "\n".join(lines)
