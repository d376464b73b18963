"""The angle error a coefficient set leaves, measured without a reference, and the guard's decision.

Two estimates, each with its own confidence, neither of them the radius ripple (which a wrong set can
make rounder, seed 001's trap):

- From the corrected angle's histogram (the agent's, 64 bins, additive): a drive that turns evenly
  visits every true angle equally often, so the corrected angle φ = θ + ε(θ) has density
  (1 - ε'(φ))/2π, and its order-m Fourier coefficient is -m/2·(B_m + i·A_m) for ε = Σ A_m cos mθ + B_m sin mθ.
  That sees order-2 angle error the radius cannot. Counting noise is measured on high orders, where an
  encoder has no error; when those orders hold more than counting noise the drive did not visit angles
  evenly (it dwells, or reverses over an arc) and there is no estimate.
- From the band's raw statistics and the bench locus (service side): the drift the data show against
  the drift the set assumes (encoder_core/differential.py). It sees the offsets, gain ratio and axis a
  set gets wrong, at any sample rate and for any motion that shows enough of the circle, but not the
  zero or harmonics (which a refit never changes).

The zero (order 0) is seen by neither: without a reference nothing sees it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .correction import Correction
from .differential import TERMS, BenchLocus, Drift, fit_drift
from .held import dwelt
from .samples import InputError
from .stats import WindowStats

N_HIST = 64
ORDERS = tuple(range(1, 9))  # angle-error orders an estimate reports
NOISE_ORDERS = tuple(range(12, 25))  # orders with no encoder error: they measure counting noise
MIN_HIST_SAMPLES = 2000
EVEN_CHI2_P = 1e-3  # visitation is uneven when the noise orders' power is this unlikely under counting noise


@dataclass
class AngleErrorEstimate:
    """RMS angle error (zero aside) a set leaves, in degrees, with its uncertainty; None when not measurable."""

    angle_error_deg: float | None
    ci_deg: float  # one standard error of angle_error_deg (inf when not measurable)
    samples: int
    method: str  # "histogram" or "locus"
    reason: str = ""
    harmonics: dict[int, tuple[float, float]] = field(default_factory=dict)  # m -> (A_m, B_m), rad

    @property
    def measured(self) -> bool:
        return self.angle_error_deg is not None and np.isfinite(self.ci_deg)

    def to_dict(self) -> dict:
        return {
            "angle_error_deg": self.angle_error_deg,
            "ci_deg": self.ci_deg if np.isfinite(self.ci_deg) else None,
            "samples": self.samples,
            "method": self.method,
            "reason": self.reason,
        }


# --- the corrected angle's histogram ---------------------------------------------------------------


def angle_histogram(theta_rad) -> np.ndarray:
    """Counts of corrected angles in 64 equal bins of [0, 2π): additive, so windows merge by addition."""
    theta = np.asarray(theta_rad, float) % (2 * np.pi)
    idx = np.minimum((theta * (N_HIST / (2 * np.pi))).astype(int), N_HIST - 1)
    return np.bincount(idx, minlength=N_HIST).astype(float)


def _coefficients(counts: np.ndarray, orders) -> np.ndarray:
    """Fourier coefficients (1/N)·Σ n_k e^{-imφ_k} at the bin centres, corrected for the bins' width."""
    n = counts.sum()
    centres = (np.arange(N_HIST) + 0.5) * (2 * np.pi / N_HIST)
    m = np.asarray(orders, float)
    width = np.pi * m / N_HIST
    return (counts @ np.exp(-1j * np.outer(centres, m))) / n / (np.sin(width) / width)


def histogram_error(counts, *, orders=ORDERS, min_samples: int = MIN_HIST_SAMPLES) -> AngleErrorEstimate:
    """The angle error left by the set that corrected these angles, if the drive visited angles evenly."""
    from scipy.stats import chi2

    counts = np.asarray(counts, float)
    n = int(round(counts.sum()))
    if n < min_samples:
        return AngleErrorEstimate(None, float("inf"), n, "histogram", f"{n} samples, need {min_samples}")
    noise = _coefficients(counts, NOISE_ORDERS)
    power = np.abs(noise) ** 2
    # counting noise: each complex coefficient has E|c|² = 1/N for independent uniform angles (less for a
    # drive that turns evenly, which is fine); much more means the angles were not visited evenly
    stat = 2 * n * power.sum()
    if chi2.sf(stat, 2 * len(NOISE_ORDERS)) < EVEN_CHI2_P:
        return AngleErrorEstimate(
            None, float("inf"), n, "histogram", "angles not visited evenly (dwell or reversal): density says nothing"
        )
    noise_power = float(power.mean())
    c = _coefficients(counts, orders)
    m = np.asarray(orders, float)
    a = -2 * c.imag / m
    b = -2 * c.real / m
    signal = 2 * (np.abs(c) ** 2 - noise_power) / m**2  # per order: (A² + B²)/2 less the noise's share
    var = float(max(signal.sum(), 0.0))
    # one standard error of the RMS: the noise's contribution to the sum, as an amplitude
    noise_rms = float(np.sqrt(np.sum(2 * noise_power / m**2)))
    err = float(np.degrees(np.sqrt(var)))
    ci = float(np.degrees(noise_rms))
    harmonics = {int(k): (float(x), float(y)) for k, x, y in zip(orders, a, b)}
    return AngleErrorEstimate(err, ci, n, "histogram", "", harmonics)


# --- the drift the data show against the drift a set assumes --------------------------------------


def implied_drift(correction: Correction, factory: Correction, locus: BenchLocus) -> Drift:
    """The drift since the bench that a set corrects for, if it is the factory's after a drift (a refit's
    set is, by construction; any set's affine part can be read so)."""
    lf = np.array([[factory.w1, 0.0], [factory.w5 * factory.w1, factory.w3]])
    tf = np.array([factory.w2, factory.w4 + factory.w5 * factory.w2])
    ls = np.array([[correction.w1, 0.0], [correction.w5 * correction.w1, correction.w3]])
    ts = np.array([correction.w2, correction.w4 + correction.w5 * correction.w2])
    shape = np.linalg.solve(lf, ls)
    offset = np.linalg.solve(lf, ts - tf)
    bench_center = np.array([locus.d[0], locus.q[0]])
    field_center = np.linalg.solve(shape, bench_center - offset)
    return Drift(field_center=field_center, bench_center=bench_center, shape=shape)


def term_gap(correction: Correction, factory: Correction, locus: BenchLocus, data: Drift) -> dict[str, float]:
    """Each drift term the data show less the set's (rad: angle-error amplitudes)."""
    radius = locus.radius
    mine = implied_drift(correction, factory, locus).terms(radius)
    seen = data.terms(radius)
    return {t: seen[t] - mine[t] for t in TERMS}


def rms_of_terms(gap: dict[str, float]) -> float:
    """RMS angle error (rad) of drift-term errors: offsets make order 1, gain ratio and axis order 2."""
    return float(np.sqrt(sum(gap[t] ** 2 for t in TERMS) / 2))


def locus_error(
    stats: WindowStats, correction: Correction, factory: Correction, locus: BenchLocus, **fit_options
) -> AngleErrorEstimate:
    """The observable part of the angle error a set leaves at the statistics' temperature."""
    try:
        fit = fit_drift(stats, locus, **fit_options)
    except InputError as exc:
        return AngleErrorEstimate(None, float("inf"), stats.n, "locus", str(exc))
    gap = term_gap(correction, factory, locus, fit.drift)
    err = rms_of_terms(gap)
    ci = float(np.sqrt(sum(fit.errors[t] ** 2 for t in TERMS) / 2))
    return AngleErrorEstimate(float(np.degrees(err)), float(np.degrees(ci)), stats.n, "locus")


@dataclass
class Comparison:
    """Two sets measured on the same data: the set on trial and the one it replaced."""

    trial: AngleErrorEstimate
    before: AngleErrorEstimate
    difference_deg: float | None  # trial - before
    difference_se_deg: float

    def worse(self, sigmas: float, tolerance_deg: float) -> bool:
        """The trial set is worse than the one before by more than `sigmas` standard errors and the tolerance."""
        return self.difference_deg is not None and self.difference_deg > sigmas * self.difference_se_deg + tolerance_deg


def compare_sets(
    stats: WindowStats,
    trial: Correction,
    before: Correction,
    factory: Correction,
    locus: BenchLocus,
    **fit_options,
) -> Comparison:
    """Both sets against one drift fit of the same (soak) statistics: the fit's own error is shared, so the
    difference is known far better than either error alone. Not where the drive held positions (`dwelt`): the
    bins its moves cross pass for a circle, and a fit of them is anything (a watch on s11-20hz-10 read 0.59° for a
    factory set leaving 0.05°, and rolled a better set back)."""
    if dwelt(stats):
        none = AngleErrorEstimate(None, float("inf"), stats.n, "locus", "the drive held positions: no circle to fit")
        return Comparison(none, none, None, float("inf"))
    try:
        fit = fit_drift(stats, locus, **fit_options)
    except InputError as exc:
        none = AngleErrorEstimate(None, float("inf"), stats.n, "locus", str(exc))
        return Comparison(none, none, None, float("inf"))
    gap_t = term_gap(trial, factory, locus, fit.drift)
    gap_b = term_gap(before, factory, locus, fit.drift)
    se = np.array([fit.errors[t] for t in TERMS])
    ci = float(np.sqrt(np.sum(se**2) / 2))
    err_t, err_b = rms_of_terms(gap_t), rms_of_terms(gap_b)
    # err = sqrt(Σ gap²/2) with gap = seen - set: the fit's error enters both through `seen`, so the
    # difference's error is the gradient of err_t - err_b against the seen terms times their errors
    grad = np.array([gap_t[t] / (2 * max(err_t, ci)) - gap_b[t] / (2 * max(err_b, ci)) for t in TERMS])
    # a term the fit cannot pin (infinite error) leaves the difference unknown, not NaN
    diff_se = float(np.sqrt(np.sum((grad * se) ** 2))) if np.all(np.isfinite(se)) else float("inf")
    return Comparison(
        AngleErrorEstimate(float(np.degrees(err_t)), float(np.degrees(ci)), stats.n, "locus"),
        AngleErrorEstimate(float(np.degrees(err_b)), float(np.degrees(ci)), stats.n, "locus"),
        float(np.degrees(err_t - err_b)),
        float(np.degrees(diff_se)),
    )


# --- the guard -----------------------------------------------------------------------------------


@dataclass
class GuardDecision:
    action: str  # "confirm", "rollback" or "wait"
    reason: str


def guard_decision(
    comparisons: list[Comparison],
    *,
    soak_samples: int,
    min_soak_samples: int = 20000,
    max_soak_samples: int = 200000,
    sigmas: float = 2.0,
    tolerance_deg: float = 0.002,
) -> GuardDecision:
    """Whether a set on trial stays, per device, from its comparisons with the set before in the bands it changed.

    Rollback as soon as any band shows the trial worse than the set before by more than `sigmas` standard
    errors of the difference and the tolerance; confirm once the soak has min_soak_samples and no band is
    worse; a set whose outcome cannot be measured (the drive showed too little of the circle) is confirmed
    at max_soak_samples on the refit's own uncertainty, and says so."""
    worse = [c for c in comparisons if c.worse(sigmas, tolerance_deg)]
    if worse:
        c = max(worse, key=lambda c: c.difference_deg)
        return GuardDecision(
            "rollback",
            f"worse than the set before by {c.difference_deg:.4f}° (± {c.difference_se_deg:.4f}°): "
            f"{c.trial.angle_error_deg:.4f}° against {c.before.angle_error_deg:.4f}°",
        )
    # a comparison whose difference has no finite error (a term the soak cannot pin) measured nothing
    measured = [c for c in comparisons if c.difference_deg is not None and np.isfinite(c.difference_se_deg)]
    if soak_samples < min_soak_samples:
        return GuardDecision("wait", f"soak {soak_samples} of {min_soak_samples} samples")
    if measured:
        gain = max(-c.difference_deg for c in measured)
        return GuardDecision("confirm", f"not worse in {len(measured)} band(s) measured; best gain {gain:.4f}°")
    if soak_samples >= max_soak_samples:
        return GuardDecision("confirm", "outcome not measurable (too little of the circle seen); kept on the refit's")
    return GuardDecision("wait", "outcome not measurable yet")
