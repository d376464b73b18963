"""Realistic wire messages for the service tests: simulated drive samples through WindowStats."""

from __future__ import annotations

import numpy as np

from encoder_core.correction import Correction
from encoder_core.simulator import EncoderModel, simulate
from encoder_core.stats import WindowStats
from fleet_wire import messages as wire

MODEL = EncoderModel(gain_tc_per_c=(-0.001, -0.0015), offset_tc_counts_per_c=(0.3, -0.2), noise_counts=2.0)


def window_stats(seed: int, temp_c: float, n: int = 400) -> WindowStats:
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.01
    temp = temp_c + 0.2 * np.sin(t)
    samples, _ = simulate(MODEL, t, rng.uniform(0, 2 * np.pi, n), temp, rng)
    return WindowStats(scale=1400.0).add(samples.d, samples.q, samples.temp_c)


def window(
    device: str = "drive-001",
    seq: int = 1,
    *,
    temp_c: float = 23.0,
    start: float | None = None,
    version: int = 0,
    quality: float = 0.08,
) -> dict:
    start = 60.0 * (seq - 1) if start is None else start
    return wire.window_message(
        device,
        seq,
        window_stats(seq, temp_c),
        window_start=start,
        window_end=start + 60.0,
        temp_rate_c_per_s=0.001,
        coefficients_version=version,
        angle_quality_deg=quality,
    )


def coefficients(device: str = "drive-001", version: int = 1, created_at: float = 100.0, bands=(2,)) -> dict:
    entries = [
        wire.band_entry(
            b,
            Correction(
                w1=1.01, w2=-3.0, w3=0.99, w4=2.0, w5=0.001, harmonics={3: (1e-4, -2e-4)}, temp_c=10.0 * b + 3.0
            ).to_dict(),
            {"samples": 120000, "residual_rms_rad": 0.002, "radius_ripple_rad": 0.0004},
        )
        for b in bands
    ]
    return wire.coefficients_message(device, version, created_at, "fit", entries)


def ack(device: str = "drive-001", version: int = 1, at: float = 160.0, status: str = "applied") -> dict:
    if status == "applied":
        return wire.ack_message(device, version, "applied", at, angle_quality_deg=0.05)
    return wire.ack_message(device, version, "rejected", at, reason="coefficients out of range")
