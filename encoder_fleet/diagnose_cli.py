"""`encoder-fleet diagnose` and `encoder-fleet bench-diagnose` (registered by encoder_fleet.cli)."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from encoder_fleet.argtypes import positive_int
from encoder_fleet.outputs import write_file

PROGRESS_MIN_ROWS = 20000  # a progress bar only on long recordings


def register(sub) -> None:
    p = sub.add_parser("diagnose", help="name what the seed-000 baseline misses in a recording, with held-out gains")
    p.add_argument("recording", help="recording CSV (t, d, q or the four halls; optional temp_c, theta_ref_deg, run)")
    p.add_argument("--json", metavar="FILE", help="write the findings (Diagnose JSON of docs/architecture.md) here")
    p.add_argument("--report", metavar="FILE", help="write an HTML report with plots here")
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    p.set_defaults(func=cmd_diagnose)

    p = sub.add_parser("bench-diagnose", help="time diagnose on simulated recordings of growing length")
    p.add_argument(
        "--rows", type=positive_int, nargs="+", default=[10000, 30000, 100000], help="recording lengths to time"
    )
    p.add_argument("--seed", type=int, default=0, help="random seed of the simulated recordings")
    p.set_defaults(func=cmd_bench_diagnose)


def _progress(rows: int, enabled: bool):
    """A callback for diagnose's steps: a tqdm counter on stderr, or nothing."""
    if not enabled or rows < PROGRESS_MIN_ROWS:
        return None, None
    from tqdm import tqdm

    bar = tqdm(desc="diagnose", unit="fit", file=sys.stderr, leave=False)

    def step(name: str) -> None:
        bar.set_postfix_str(name, refresh=False)
        bar.update(1)

    return step, bar


def cmd_diagnose(args) -> int:
    from encoder_core.diagnose import diagnose
    from encoder_fleet.recording import read_recording

    samples = read_recording(args.recording)
    step, bar = _progress(len(samples), not args.no_progress)
    try:
        result = diagnose(samples, on_step=step)
    finally:
        if bar is not None:
            bar.close()
    report = result.report
    if args.json:
        write_file(args.json, json.dumps(_finite(report), indent=2, allow_nan=False) + "\n")
    if args.report:
        from encoder_fleet.report import write_report

        write_report(result, args.report, title=Path(args.recording).name)
    _print_summary(report)
    return 0


def _finite(obj):
    """JSON has no NaN or infinity: a number that is not finite is written as null."""
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


def _print_summary(report: dict) -> None:
    b, e = report["baseline"], report["extended"]
    print(
        f"{report['samples']} samples, error metric: {report['error_metric']} (held out by "
        f"{report.get('held_out', {}).get('by', '?')})"
    )
    print(f"baseline: rms {b['rms_error_deg']:.4f}°  max {b['max_error_deg']:.4f}°")
    for f in report["findings"]:
        params = ", ".join(f"{k}={v}" for k, v in f["parameters"].items())
        print(f"  {f['cause']:<24} {params}: rms {f['rms_error_deg_before']:.4f}° -> {f['rms_error_deg_after']:.4f}°")
    if not report["findings"]:
        print("  no findings: the baseline explains the recording down to its noise")
    print(f"extended: rms {e['rms_error_deg']:.4f}°  max {e['max_error_deg']:.4f}°")
    rep = report.get("repeatability")
    if rep:
        shifts = ", ".join(f"run {run} {shift:+.3f}°" for run, shift in rep["runs"].items())
        within = rep["within_run_rms_error_deg"]
        print(f"  run-to-run repeatability: {shifts} (rms {rep['rms_deg']:.3f}°; within runs {within:.3f}°)")
    for item in report["not_testable"]:
        print(f"  not testable: {item['cause']}: {item['why']}")


def bench_recording(rows: int, seed: int = 0):
    """A bench-style recording with a reference, temperature and two hidden effects, cut to `rows`."""
    from encoder_core.simulator import EncoderModel, bench_profile, record

    rng = np.random.default_rng(seed)
    model = EncoderModel(
        hall_amplitude=700.0,
        amplitude_imbalance=0.02,
        gain_tc_per_c=(-0.002, -0.0008),
        offset_counts=(10.0, -15.0),
        offset_tc_counts_per_c=(0.8, -0.5),
        noise_counts=1.0,
        thermal_lag_tau_s=200.0,
        harmonics=((5, 0.01, 0.3),),
    )
    plateaus = [20.0, -40.0, 60.0, 20.0]
    profile = bench_profile(tuple(plateaus), rng=rng)
    while profile.t.size < rows:  # more plateaus until long enough
        plateaus += [-20.0, 40.0]
        profile = bench_profile(tuple(plateaus), rng=rng)
    samples = record(model, profile, rng)
    return samples.subset(np.arange(rows))


def field_recording(rows: int, seed: int = 0):
    """A field-style recording (no reference; random angles, load-driven temperature) of `rows` rows."""
    from encoder_core.simulator import EncoderModel, field_profile, record

    rng = np.random.default_rng(seed)
    model = EncoderModel(
        hall_amplitude=700.0,
        amplitude_imbalance=0.02,
        gain_tc_per_c=(-0.002, -0.0008),
        offset_counts=(10.0, -15.0),
        offset_tc_counts_per_c=(0.8, -0.5),
        noise_counts=1.0,
        thermal_lag_tau_s=300.0,
        harmonics=((5, 0.01, 0.3),),
    )
    profile = field_profile(rows * 10.0 / 86400.0 + 0.001, sample_s=10.0, rng=rng)
    samples = record(model, profile, rng, reference=False)
    return samples.subset(np.arange(rows))


def cmd_bench_diagnose(args) -> int:
    """Time diagnose on bench-style (reference) and field-style (reference-free) recordings."""
    from encoder_core.diagnose import diagnose

    print(
        f"{'style':<6} {'rows':>8} {'seconds':>8} {'rows/s':>9}  findings (planted: harmonic_distortion, thermal_lag)"
    )
    for style, make in (("bench", bench_recording), ("field", field_recording)):
        for rows in args.rows:
            samples = make(rows, args.seed)
            start = time.perf_counter()
            result = diagnose(samples)
            secs = time.perf_counter() - start
            causes = ", ".join(result.report["extended"]["causes"]) or "-"
            print(f"{style:<6} {rows:>8} {secs:>8.2f} {rows / secs:>9.0f}  {causes}", flush=True)
    return 0
