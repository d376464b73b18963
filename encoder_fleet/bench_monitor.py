"""`encoder-fleet bench-monitor`: the drift monitor on hidden events, offline, scored like river's drift
evaluation, and its cost per window.

Drives come from `drift_events` (seeded: one planted event per drive, some clean); each drive's samples go
through the agent's statistics path (`block_statistics`: the same usable mask, rejection counts and sums an
agent ships), then the windows of every drive are fed to one fleet of monitors in drive-time order (the
fleet's rate distribution needs the drives side by side, as the service has them).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from encoder_core.monitor import DeviceMonitor, Features, FleetRates, Settings, ellipse_fits, window_features
from encoder_core.physics import band_of
from encoder_core.stats import block_statistics, normalisation_scale

from .drift_events import SLOW, DriveSpec, EventDrive, fleet_specs, score

REFIT_AFTER_S = 3600.0  # the offline harness clears an offset step as a refit would, an hour after it


def drive_windows(spec: DriveSpec, *, window_s: float, sample_hz: float) -> list[tuple]:
    """(WindowStats, rejected_by_reason, window_end) of every window of a drive, as its agent makes them."""
    source = EventDrive(spec, sample_hz=sample_hz)
    scale = normalisation_scale(source.factory())
    out = []
    while (block := source.read(window_s)) is not None:
        if len(block) == 0:
            continue
        stats, counts = block_statistics(block, scale)
        if stats.temp_n == 0:
            continue
        out.append((stats, counts, float(block.t[-1])))
    return out


def features_of(stats, counts, t_end, fits=None) -> Features:
    temp = stats.temp_mean
    return window_features(stats, t=t_end, temp_c=temp, band=band_of(temp), rejected_by_reason=counts, fits=fits)


def run_offline(
    specs: list[DriveSpec],
    *,
    window_s: float = 300.0,
    sample_hz: float = 2.0,
    settings: Settings | None = None,
    progress: bool = False,
) -> tuple[dict[str, list[dict]], dict]:
    """Alarms per device (raise events) and the cost: µs per window for features + detector update."""
    settings = settings or Settings()
    per_drive = {}
    for spec in tqdm(specs, desc="simulating drives", unit="drive", disable=not progress, file=sys.stderr):
        per_drive[spec.name] = drive_windows(spec, window_s=window_s, sample_hz=sample_hz)
    fleet = FleetRates(settings)
    monitors = {name: DeviceMonitor(name, settings) for name in per_drive}
    timeline = sorted(
        ((w[2], name, i) for name, ws in per_drive.items() for i, w in enumerate(ws)), key=lambda x: (x[0], x[1])
    )
    alarms: dict[str, list[dict]] = {name: [] for name in per_drive}
    feature_s = update_s = 0.0
    fits = {}
    for name, windows in per_drive.items():  # as the service does a page of stored windows: fitted at once
        t0 = time.perf_counter()
        fits[name] = ellipse_fits([w[0] for w in windows])
        feature_s += time.perf_counter() - t0
    for _, name, i in timeline:
        stats, counts, t_end = per_drive[name][i]
        t0 = time.perf_counter()
        f = features_of(stats, counts, t_end, fits[name][i])
        t1 = time.perf_counter()
        events = monitors[name].update(f, fleet)
        t2 = time.perf_counter()
        step = monitors[name].open.get("offset_step")
        if step is not None and t_end - step["raised_at"] >= REFIT_AFTER_S:
            # in the service a refit applied after the step clears it; clearing here too lets a detector
            # that keeps firing show up as a second alarm instead of hiding behind the open one
            monitors[name].clear("offset_step", t_end, "refit")
        feature_s += t1 - t0
        update_s += t2 - t1
        for e in events:
            if e.kind == "raise":
                alarms[name].append(
                    {"cause": e.cause, "raised_at": e.at, "parameters": e.parameters, "evidence": e.evidence}
                )
    n = max(len(timeline), 1)
    cost = {
        "windows": len(timeline),
        "features_us_per_window": 1e6 * feature_s / n,
        "update_us_per_window": 1e6 * update_s / n,
        "total_us_per_window": 1e6 * (feature_s + update_s) / n,
    }
    return alarms, cost


def format_table(result: dict) -> str:
    s = result["score"]
    lines = [
        f"{s['drives']} drives ({s['clean_drives']} clean), {s['device_days']:.0f} device-days, "
        f"windows of {result['window_s']:.0f} s at {result['sample_hz']:g} Hz",
        "",
        "| cause | planted | detected | median delay (h) | max delay (h) | delay goal (h) |",
        "|---|---|---|---|---|---|",
    ]
    for cause, c in s["per_cause"].items():
        goal = 8 if cause in SLOW else 2
        med = "-" if c["median_delay_h"] is None else f"{c['median_delay_h']:.2f}"
        mx = "-" if c["max_delay_h"] is None else f"{c['max_delay_h']:.2f}"
        lines.append(f"| {cause} | {c['planted']} | {c['detected']} | {med} | {mx} | ≤ {goal} |")
    cost = result["cost"]
    lines += [
        "",
        "| recall | cause precision | false alarms / device-day | µs per window (features + detectors) |",
        "|---|---|---|---|",
        f"| {s['recall']:.3f} | {s['cause_precision']:.3f} | {s['false_alarms_per_device_day']:.4f} | "
        f"{cost['total_us_per_window']:.0f} ({cost['features_us_per_window']:.0f} + "
        f"{cost['update_us_per_window']:.0f}) |",
    ]
    if s["missed"]:
        lines.append("missed: " + ", ".join(f"{m['device']} {m['cause']} (size {m['size']:.4g})" for m in s["missed"]))
    if s["false"]:
        lines.append(
            "false: " + ", ".join(f"{f['device']} {f['cause']} at {f['raised_at_h']:.1f} h" for f in s["false"])
        )
    return "\n".join(lines)


def run_bench(*, drives: int, days: float, seed: int, window_s: float, sample_hz: float, json_path: str | None) -> int:
    specs = fleet_specs(drives, days, seed=seed)
    started = time.perf_counter()
    alarms, cost = run_offline(specs, window_s=window_s, sample_hz=sample_hz, progress=True)
    result = {
        "seed": seed,
        "window_s": window_s,
        "sample_hz": sample_hz,
        "score": score(specs, alarms),
        "cost": cost,
        "wall_s": time.perf_counter() - started,
        "drives": [
            {"device": s.name, "event": None if s.event is None else s.event.to_dict(), "alarms": alarms[s.name]}
            for s in specs
        ],
    }
    print(format_table(result))
    if json_path:
        Path(json_path).parent.mkdir(parents=True, exist_ok=True)
        Path(json_path).write_text(json.dumps(result, indent=1, default=_plain))
        print(f"wrote {json_path}")
    return 0


def _plain(value):
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")
