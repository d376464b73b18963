"""Refit one device from its merged band statistics, and decide whether the result is worth rolling out.

No I/O here: the service hands in the statistics and the sets, and gets back a decision.

A candidate band replaces what the device runs at that temperature only when the two differ by
clearly more than the candidate's own uncertainty (harmonic noise from the sample density, ellipse
scatter): then the running set is measurably wrong and the candidate is the better estimate.
Zero offsets of reference-free fits are anchored to the factory calibration, the only fit that ever saw a reference.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from encoder_core.correction import BandedCorrection, Correction, zero_shift
from encoder_core.ellipse import HarmonicEstimate, density_harmonics, ellipse_correction, ellipse_quality, fit_ellipse
from encoder_core.physics import REFERENCE_TEMP_C, circular_mean, wrap_rad
from encoder_core.samples import InputError
from encoder_core.stats import WindowStats
from fleet_wire import messages as wire

MIN_BAND_SAMPLES = 20000
CONFIDENCE = 3.0  # adopt when the running set is off by 3x the candidate's own uncertainty …
MIN_GAIN_DEG = 0.01  # … and by at least this much


@dataclass
class BandDecision:
    band: int
    temp_c: float
    samples: int
    running_error_deg: float
    candidate_error_deg: float
    adopted: bool
    quality: dict
    candidate: dict  # the fit itself, as a band entry, whether adopted or not


@dataclass
class RefitResult:
    bands: list[dict]  # the coefficient set's band entries (docs/wire.md)
    decisions: list[BandDecision] = field(default_factory=list)

    @property
    def changed(self) -> bool:
        return any(d.adopted for d in self.decisions)


def difference_deg(running: Correction, candidate: Correction) -> float:
    """RMS angle difference between two corrections around the candidate's circle, zero aside:
    the error of the running set if the candidate is right."""
    d, q = candidate.locus()
    diff = wrap_rad(running.angle(d, q) - candidate.angle(d, q))
    diff = wrap_rad(diff - circular_mean(diff))
    return float(np.degrees(np.sqrt(np.mean(diff**2))))


def uncertainty_deg(estimate: HarmonicEstimate, kept: dict, stats: WindowStats, residual_rms: float) -> float:
    """How far the candidate itself may be off: the noise of the harmonic orders it applies, and the
    ellipse's (residual radius scatter over the square root of the sample count)."""
    var = sum((estimate.noise / m) ** 2 for m in kept) + residual_rms**2 / max(stats.n, 1)
    return float(np.degrees(np.sqrt(var)))


def refit_device(
    band_stats: dict[int, WindowStats],
    running: BandedCorrection,
    factory: BandedCorrection | None = None,
    *,
    min_samples: int = MIN_BAND_SAMPLES,
) -> RefitResult:
    candidates: dict[int, tuple[Correction, dict, WindowStats]] = {}
    estimates = []
    for band, stats in sorted(band_stats.items()):
        if stats.n < min_samples:
            continue
        try:
            fit = fit_ellipse(stats)
        except InputError:
            continue  # not enough of the circle seen in this band yet
        corr = ellipse_correction(stats, fit)
        corr.temp_c = stats.temp_mean
        estimates.append(density_harmonics(stats, fit))
        candidates[band] = (corr, ellipse_quality(stats, fit), stats)
    if not candidates:
        return RefitResult(bands=[])
    # harmonics come from the magnet and the sensor geometry, not from temperature: one estimate from
    # all bands together is as many times less noisy as there are bands
    pooled = HarmonicEstimate.pooled(estimates)
    harmonics = pooled.significant()
    for corr, _, _ in candidates.values():
        corr.harmonics = dict(harmonics)
    if factory is not None:
        # one rotation for the whole device, taken where the factory is right: near +20 °C
        anchor_band = min(candidates, key=lambda b: abs(candidates[b][0].temp_c - REFERENCE_TEMP_C))
        anchor_corr = candidates[anchor_band][0]
        shift = zero_shift(factory.at(anchor_corr.temp_c), anchor_corr)
        for corr, _, _ in candidates.values():
            corr.zero_offset_rad = float(wrap_rad(corr.zero_offset_rad + shift))
    result = RefitResult(bands=[])
    for band, (corr, quality, stats) in candidates.items():
        now = running.at(corr.temp_c)
        err_now = difference_deg(now, corr)
        err_new = uncertainty_deg(pooled, harmonics, stats, quality["residual_rms_rad"])
        adopt = err_now > max(MIN_GAIN_DEG, CONFIDENCE * err_new)
        chosen = corr if adopt else now
        candidate = band_entry(band, corr, {**quality, "estimated_error_deg": err_new})
        quality = {**quality, "estimated_error_deg": err_new if adopt else err_now}
        result.bands.append(band_entry(band, chosen, quality))
        result.decisions.append(
            BandDecision(
                band=band,
                temp_c=corr.temp_c,
                samples=stats.n,
                running_error_deg=err_now,
                candidate_error_deg=err_new,
                adopted=adopt,
                quality=quality,
                candidate=candidate,
            )
        )
    return result


def band_entry(band: int, corr: Correction, quality: dict) -> dict:
    keys = ("samples", "residual_rms_rad", "radius_ripple_rad", "estimated_error_deg")
    return wire.band_entry(band, corr.to_dict(), {k: quality[k] for k in keys if k in quality})
