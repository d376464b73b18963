"""Hidden events for the drift monitor: field drives with one planted change each, and river-style scoring.

A seeded generator draws, per drive, a production encoder (the simulator's `typical_drive`), its own
temperature cycle, the fleet's normal aging (offsets and amplitude drifting slowly) and noise, and plants
at most one event at a random onset and size:

| cause             | planted as                                                              |
|-------------------|-------------------------------------------------------------------------|
| offset_step       | both offsets jump by 1.0–2.0 % of the amplitude, random direction       |
| accelerated_aging | offsets drift at 0.8–1.5 % of the amplitude per day, random direction   |
| magnet_weakening  | the field amplitude falls by 3–5 % per day                              |
| harmonic_growth   | a harmonic of order 4–7 grows linearly to 0.25–0.35° over 3–8 h         |
| outliers          | 1.5–2.5 % of the samples get an impulse of 300–500 counts on one hall   |
| adc_clipping      | one channel pinned at a rail that clips 0.8–1.2 % of its samples        |

`EventDrive` is a SampleSource (the agent's own interface), so the same drive runs offline through the
agent's statistics path (`encoder_core.stats.block_statistics`) or, written as a recording, through a
real agent process. `score` counts what river's drift evaluation counts: detection delay, false alarms
per device-day, missed detections, and whether the alarm named the planted cause.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from edge_agent.sources import SampleSource, factory_calibration
from encoder_core.samples import Samples
from encoder_core.simulator import EncoderModel, cycle_profile, simulate, typical_drive

CAUSES = ("offset_step", "accelerated_aging", "magnet_weakening", "harmonic_growth", "outliers", "adc_clipping")
DAY_S = 86400.0
SLOW = ("accelerated_aging", "magnet_weakening", "harmonic_growth")


@dataclass
class Event:
    cause: str
    onset_s: float
    size: float  # the cause's size: fraction, fraction per day, degrees
    direction: float = 0.0  # rad: which way offsets move
    order: int = 0  # harmonic order n
    growth_h: float = 0.0  # harmonic: hours to reach its size
    impulse_counts: float = 0.0
    channel: str = "d"  # clipping: which channel, which rail
    rail: str = "high"

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class DriveSpec:
    seed: int
    days: float
    event: Event | None
    t_min: float = -40.0
    t_max: float = 85.0
    cycle_hours: float = 12.0
    offset_rate: tuple[float, float] = (0.0, 0.0)  # normal aging, fraction of amplitude per day (d, q)
    amp_loss: float = 0.0  # normal aging, fractional amplitude loss per day
    model: EncoderModel = field(default=None)

    @property
    def name(self) -> str:
        return f"drive-{self.seed:04d}"


def draw_drive(
    seed: int, days: float, cause: str | None, *, onset_range_s: tuple[float, float] | None = None
) -> DriveSpec:
    """One drive of the hidden-event set: its encoder, cycle, normal aging, and the event (None: clean)."""
    rng = np.random.default_rng([seed, 9])
    model = typical_drive(np.random.default_rng([seed, 0]))
    spec = DriveSpec(
        seed=seed,
        days=days,
        event=None,
        t_min=float(rng.uniform(-40.0, -10.0)),
        t_max=float(rng.uniform(50.0, 85.0)),
        cycle_hours=float(rng.uniform(8.0, 16.0)),
        offset_rate=tuple(float(v) for v in rng.uniform(-0.0008, 0.0008, 2)),
        amp_loss=float(rng.uniform(0.0, 0.002)),
        model=model,
    )
    if cause is None:
        return spec
    lo, hi = onset_range_s or (1.0 * DAY_S, days * DAY_S - 0.75 * DAY_S)
    onset = float(rng.uniform(lo, max(lo, hi)))
    direction = float(rng.uniform(-np.pi, np.pi))
    if cause == "offset_step":
        event = Event(cause, onset, float(rng.uniform(0.010, 0.020)), direction)
    elif cause == "accelerated_aging":
        event = Event(cause, onset, float(rng.uniform(0.008, 0.015)), direction)
    elif cause == "magnet_weakening":
        event = Event(cause, onset, float(rng.uniform(0.03, 0.05)))
    elif cause == "harmonic_growth":
        event = Event(
            cause,
            onset,
            float(rng.uniform(0.25, 0.35)),
            direction,
            order=int(rng.integers(4, 8)),
            growth_h=float(rng.uniform(3.0, 8.0)),
        )
    elif cause == "outliers":
        event = Event(cause, onset, float(rng.uniform(0.015, 0.025)), impulse_counts=float(rng.uniform(300, 500)))
    elif cause == "adc_clipping":
        event = Event(
            cause,
            onset,
            float(rng.uniform(0.008, 0.012)),
            channel=str(rng.choice(["d", "q"])),
            rail=str(rng.choice(["high", "low"])),
        )
    else:
        raise ValueError(f"unknown cause {cause!r}")
    spec.event = event
    return spec


def fleet_specs(n_drives: int, days: float, *, seed: int = 0, clean_share: float = 0.25) -> list[DriveSpec]:
    """A seeded set: about clean_share of the drives clean, the others one event each, causes in turn."""
    rng = np.random.default_rng([seed, 77])
    n_clean = int(round(n_drives * clean_share))
    causes: list[str | None] = [None] * n_clean + [CAUSES[i % len(CAUSES)] for i in range(n_drives - n_clean)]
    order = rng.permutation(len(causes))
    return [draw_drive(seed * 100000 + i, days, causes[j]) for i, j in enumerate(order)]


class EventDrive(SampleSource):
    """A DriveSpec as a stream of samples (what an agent reads), events applied block by block."""

    def __init__(self, spec: DriveSpec, *, sample_hz: float = 2.0):
        self.spec = spec
        self.base = spec.model
        self.rng = np.random.default_rng([spec.seed, 1])
        self.sample_s = 1.0 / sample_hz
        self.end_s = spec.days * DAY_S
        self.now = 0.0
        self.amp = 2.0 * self.base.hall_amplitude  # d and q swing twice the hall amplitude

    def model_at(self, t: float) -> EncoderModel:
        s, ev, base = self.spec, self.spec.event, self.base
        days = t / DAY_S
        off = [base.offset_counts[i] + s.offset_rate[i] * self.amp * days for i in (0, 1)]
        amp_scale = 1.0 - s.amp_loss * days
        harmonics = list(base.harmonics)
        changes: dict = {}
        if ev is not None and t >= ev.onset_s:
            since_d = (t - ev.onset_s) / DAY_S
            unit = (np.cos(ev.direction), np.sin(ev.direction))
            if ev.cause == "offset_step":
                off = [off[i] + ev.size * self.amp * unit[i] for i in (0, 1)]
            elif ev.cause == "accelerated_aging":
                off = [off[i] + ev.size * self.amp * since_d * unit[i] for i in (0, 1)]
            elif ev.cause == "magnet_weakening":
                amp_scale -= ev.size * since_d
            elif ev.cause == "harmonic_growth":
                k = np.radians(ev.size) * min(1.0, since_d * 24.0 / ev.growth_h)
                harmonics.append((ev.order, float(k), ev.direction))
            elif ev.cause == "outliers":
                changes.update(impulse_fraction=ev.size, impulse_counts=ev.impulse_counts)
        return base.with_(
            offset_counts=tuple(off),
            hall_amplitude=base.hall_amplitude * amp_scale,
            harmonics=tuple(harmonics),
            **changes,
        )

    def read(self, duration_s: float) -> Samples | None:
        if self.now >= self.end_s:
            return None
        s = self.spec
        hours = min(duration_s, self.end_s - self.now) / 3600.0
        profile = cycle_profile(
            hours,
            sample_s=self.sample_s,
            t_min=s.t_min,
            t_max=s.t_max,
            cycle_hours=s.cycle_hours,
            t0=self.now,
            rng=self.rng,
        )
        model = self.model_at(self.now + duration_s / 2)
        samples, _ = simulate(model, profile.t, profile.theta, profile.temp_c, self.rng)
        ev = s.event
        if ev is not None and ev.cause == "adc_clipping" and self.now + duration_s / 2 >= ev.onset_s and len(samples):
            chan = samples.d if ev.channel == "d" else samples.q
            if ev.rail == "high":
                rail = np.quantile(chan, 1.0 - ev.size, method="higher")
                chan = np.minimum(chan, rail)
            else:
                rail = np.quantile(chan, ev.size, method="lower")
                chan = np.maximum(chan, rail)
            if ev.channel == "d":
                samples.d = chan
            else:
                samples.q = chan
        self.now += duration_s
        return Samples(t=samples.t, d=samples.d, q=samples.q, temp_c=samples.temp_c)  # a recording: no halls

    def factory(self):
        return factory_calibration(self.base, self.spec.seed)


# --- scoring --------------------------------------------------------------------------------------


def score(specs: list[DriveSpec], alarms: dict[str, list[dict]]) -> dict:
    """alarms: device -> [{"cause", "raised_at"}]. River's drift evaluation: each planted event is detected
    by the first alarm of its cause after its onset (delay = raised_at - onset); every other alarm is false
    (before the onset, on a clean drive, or of another cause after the onset: that one also lowers the
    cause precision)."""
    detections, missed, false_alarms, wrong_cause = [], [], [], 0
    named = 0
    device_days = 0.0
    for spec in specs:
        device_days += spec.days
        ev = spec.event
        found = None
        for a in sorted(alarms.get(spec.name, []), key=lambda a: a["raised_at"]):
            if a["cause"] == "offline":
                continue
            if ev is not None and a["raised_at"] >= ev.onset_s:
                named += 1
                if a["cause"] == ev.cause and found is None:
                    found = a
                    continue
                if a["cause"] != ev.cause:
                    wrong_cause += 1
                    false_alarms.append((spec.name, a))
                continue
            false_alarms.append((spec.name, a))
        if ev is not None:
            if found is None:
                missed.append({"device": spec.name, **ev.to_dict()})
            else:
                detections.append({"device": spec.name, "cause": ev.cause, "delay_s": found["raised_at"] - ev.onset_s})
    planted = sum(1 for s in specs if s.event is not None)
    per_cause = {}
    for cause in CAUSES:
        delays = [d["delay_s"] for d in detections if d["cause"] == cause]
        n = sum(1 for s in specs if s.event is not None and s.event.cause == cause)
        per_cause[cause] = {
            "planted": n,
            "detected": len(delays),
            "median_delay_h": float(np.median(delays)) / 3600.0 if delays else None,
            "max_delay_h": float(np.max(delays)) / 3600.0 if delays else None,
        }
    return {
        "drives": len(specs),
        "clean_drives": sum(1 for s in specs if s.event is None),
        "device_days": device_days,
        "planted": planted,
        "detected": len(detections),
        "recall": len(detections) / planted if planted else None,
        "cause_precision": (named - wrong_cause) / named if named else None,
        "false_alarms": len(false_alarms),
        "false_alarms_per_device_day": len(false_alarms) / device_days if device_days else None,
        "per_cause": per_cause,
        "missed": missed,
        "false": [{"device": d, "cause": a["cause"], "raised_at_h": a["raised_at"] / 3600.0} for d, a in false_alarms],
    }


def record_drive(spec: DriveSpec, *, sample_hz: float = 2.0, block_s: float = 3600.0) -> Samples:
    """The whole drive as one recording (t, d, q, temp_c), for a replaying agent."""
    source = EventDrive(spec, sample_hz=sample_hz)
    parts = []
    while (block := source.read(block_s)) is not None:
        parts.append(block)
    return Samples(
        t=np.concatenate([p.t for p in parts]),
        d=np.concatenate([p.d for p in parts]),
        q=np.concatenate([p.q for p in parts]),
        temp_c=np.concatenate([p.temp_c for p in parts]),
    )


def write_drive(spec: DriveSpec, folder, *, sample_hz: float = 2.0) -> tuple[str, str]:
    """REC.csv and FACTORY.json of a drive: what `encoder-fleet agent --source replay:REC.csv --factory F` reads."""
    import json
    from pathlib import Path

    from edge_agent.agent import factory_message
    from encoder_fleet.recording import write_recording

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rec, factory = folder / f"{spec.name}.csv", folder / f"{spec.name}-factory.json"
    write_recording(record_drive(spec, sample_hz=sample_hz), rec)
    factory.write_text(json.dumps(factory_message(spec.name, EventDrive(spec).factory())))
    return str(rec), str(factory)
