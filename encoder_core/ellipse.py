"""Reference-free fit from window statistics: a direct ellipse fit, then harmonics from sample density.

The ellipse (Fitzgibbon's direct least-squares conic fit, in Halir & Flusser's numerically
stable split) gives offsets, gains and phase: the 5 numbers the locus of (d, q) can show.

The locus cannot show harmonics: a 3rd harmonic and an amplitude imbalance make the same shape
to first order (seed 001 eq. 8 and 18 both give a cos 2θ radius ripple) but opposite angle
errors. What does show them, without a reference, is where along the circle the samples fall.
A drive that turns, sampled asynchronously, visits every true angle equally often, so the
cumulative share of samples below a corrected angle φ is the true angle: θ(φ) = 2π·F(φ) + c.
The difference φ - θ(φ), fitted with a few Fourier orders, is the remaining angle error.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .correction import Correction, from_inverse_matrix
from .samples import InputError
from .stats import N_BINS, WindowStats, bin_edges

_DESIGN = ((2, 0), (1, 1), (0, 2), (1, 0), (0, 1), (0, 0))  # conic a·x² + b·xy + c·y² + d·x + e·y + f
MIN_SAMPLES = 32
MIN_DENSITY_SAMPLES = 1000
NOISE_ORDERS = (10, 20)  # density orders used only to measure its noise
# amplitude of a pure-noise order is Rayleigh: P(amp > k·rms) = exp(-k²), 0.2 % per order at k = 2.5
SIGNIFICANCE = 2.5


@dataclass
class EllipseFit:
    center: np.ndarray  # in normalised units
    qform: np.ndarray  # (p - c)^T Q (p - c) = 1 on the ellipse
    conic: np.ndarray  # a..f scaled so that the conic value is r² - 1 of the corrected point
    residual_rms: float  # rms of (r - 1) over the samples, from the 4th-order sums


def scatter_matrix(stats: WindowStats) -> np.ndarray:
    s = np.empty((6, 6))
    for a, (ia, ja) in enumerate(_DESIGN):
        for b, (ib, jb) in enumerate(_DESIGN):
            s[a, b] = stats.moment(ia + ib, ja + jb)
    return s


def fit_ellipse(stats: WindowStats) -> EllipseFit:
    """Direct ellipse fit from the moment sums alone."""
    if stats.n < MIN_SAMPLES:
        raise InputError(f"too few samples for an ellipse fit: {stats.n}, need at least {MIN_SAMPLES}")
    occupied = int(np.count_nonzero(stats.bins[:, 0]))
    if occupied < N_BINS // 2:
        raise InputError(
            f"too little angle coverage for an ellipse fit: samples in {occupied} of {N_BINS} "
            f"angle bins, need at least {N_BINS // 2}"
        )
    s = scatter_matrix(stats)
    s1, s2, s3 = s[:3, :3], s[:3, 3:], s[3:, 3:]
    try:
        t = -np.linalg.solve(s3, s2.T)
    except np.linalg.LinAlgError as exc:
        raise InputError("degenerate statistics: the samples do not span a plane") from exc
    m = s1 + s2 @ t
    c1_inv = np.array([[0.0, 0.0, 0.5], [0.0, -1.0, 0.0], [0.5, 0.0, 0.0]])
    eigval, eigvec = np.linalg.eig(c1_inv @ m)
    eigvec = np.real(eigvec)
    cond = 4 * eigvec[0] * eigvec[2] - eigvec[1] ** 2
    good = np.flatnonzero(cond > 0)
    if good.size == 0:
        raise InputError("the samples do not lie on an ellipse")
    a1 = eigvec[:, good[np.argmin(np.abs(np.real(eigval[good])))]]
    conic = np.concatenate([a1, t @ a1])
    a, b, c, d, e, f = conic
    center = np.linalg.solve(np.array([[2 * a, b], [b, 2 * c]]), np.array([-d, -e]))
    f_center = f + 0.5 * (d * center[0] + e * center[1])
    qform = np.array([[a, b / 2], [b / 2, c]]) / -f_center
    if np.linalg.eigvalsh(qform).min() <= 0:
        raise InputError("the samples do not lie on an ellipse")
    conic = conic / -f_center  # its value at a point is now (that point's corrected radius)² - 1
    mean_sq = float(conic @ s @ conic) / stats.n
    residual = 0.5 * np.sqrt(max(mean_sq, 0.0))
    return EllipseFit(center=center, qform=qform, conic=conic, residual_rms=residual)


def ellipse_correction(stats: WindowStats, fit: EllipseFit) -> Correction:
    """The fit as raw-unit weights, with q as the zero reference.

    The locus fixes the map to a circle only up to a rotation. Seed 001 (eq. 10) puts the phase
    error on the cos channel d, so the sin channel q is taken as true: u = U·(p - c) with U upper
    triangular (u2 depends on q alone); Correction expresses that as weights plus a zero offset.
    """
    upper = np.linalg.cholesky(fit.qform).T
    g = upper / stats.scale
    offset = np.array([stats.center_d, stats.center_q]) + stats.scale * fit.center
    return from_inverse_matrix(g, offset)


def density_reference(stats: WindowStats, fit: EllipseFit) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Raw (d, q) on the fitted locus at each angle-bin edge, and the true angle there up to a constant:
    2π times the share of samples below the edge (a turning drive visits every angle equally often).
    None when the binning's origin lies outside the locus (then bins are not angles)."""
    counts = stats.bins[:, 0]
    total = counts.sum()
    edges = bin_edges()[:-1]
    v = np.column_stack([np.cos(edges), np.sin(edges)])
    qc = fit.qform @ fit.center
    vqv = np.einsum("ij,jk,ik->i", v, fit.qform, v)
    vqc = v @ qc
    cqc = fit.center @ qc
    disc = vqc**2 - vqv * (cqc - 1.0)
    if total <= 0 or cqc >= 1.0 or np.any(disc <= 0):
        return None
    points = v * ((vqc + np.sqrt(disc)) / vqv)[:, None]
    d = stats.center_d + stats.scale * points[:, 0]
    q = stats.center_q + stats.scale * points[:, 1]
    true_angle = 2 * np.pi * np.concatenate(([0.0], np.cumsum(counts)[:-1])) / total
    return d, q, true_angle


@dataclass
class HarmonicEstimate:
    """Unthresholded angle-error harmonics from the density, with the noise of one order scaled by m:
    an order's amplitude scatters as about noise/m."""

    coefficients: dict[int, tuple[float, float]]  # m -> (a_m, b_m) of the correction, rad
    noise: float

    def significant(self) -> dict[int, tuple[float, float]]:
        return {m: ab for m, ab in self.coefficients.items() if np.hypot(*ab) > SIGNIFICANCE * self.noise / m}

    @staticmethod
    def pooled(estimates: list[HarmonicEstimate]) -> HarmonicEstimate:
        """Inverse-variance mean of several estimates of the same harmonics (e.g. a device's bands)."""
        usable = [e for e in estimates if e.noise > 0]
        if not usable:
            return HarmonicEstimate({}, 0.0)
        weights = np.array([1 / e.noise**2 for e in usable])
        orders = sorted({m for e in usable for m in e.coefficients})
        coef = {
            m: tuple(
                float(np.dot(weights, [e.coefficients.get(m, (0.0, 0.0))[i] for e in usable]) / weights.sum())
                for i in (0, 1)
            )
            for m in orders
        }
        return HarmonicEstimate(coef, float(1 / np.sqrt(weights.sum())))


def density_harmonics(stats: WindowStats, fit: EllipseFit, orders=range(1, 7)) -> HarmonicEstimate:
    """Angle-error harmonics left after the ellipse, from where the samples fall (uniform true angle)."""
    ref = density_reference(stats, fit) if stats.bins[:, 0].sum() >= MIN_DENSITY_SAMPLES else None
    if ref is None:
        return HarmonicEstimate({}, 0.0)
    d, q, true_angle = ref
    phi = np.unwrap(ellipse_correction(stats, fit).angle(d, q))
    err = phi - phi[0] - true_angle
    # Fit far more orders than we keep: the high ones carry no signal, only the sampling noise of the
    # density (for random angles each order's amplitude scatters as ~sqrt(2/N)/m; a uniform sweep is
    # much quieter), so they measure the noise, and an order is kept only when it stands clear of it.
    fitted = range(1, NOISE_ORDERS[1] + 1)
    design = [np.ones_like(phi)]
    for m in fitted:
        design += [np.cos(m * phi), np.sin(m * phi)]
    coef, *_ = np.linalg.lstsq(np.column_stack(design), err, rcond=None)
    amp = {m: (coef[2 * m - 1], coef[2 * m]) for m in fitted}
    noise = np.sqrt(np.mean([m * m * (a * a + b * b) for m, (a, b) in amp.items() if m >= NOISE_ORDERS[0]]))
    return HarmonicEstimate({m: (-float(amp[m][0]), -float(amp[m][1])) for m in orders}, float(noise))


def radius_ripple_rms(stats: WindowStats, correction_fit: EllipseFit) -> float:
    """RMS of (corrected radius - 1) over angle bins: a reference-free quality number (≈ radians)."""
    q, c = correction_fit.qform, correction_fit.center
    counts = stats.bins[:, 0]
    ok = counts > 0
    mean = stats.bins[ok, 1:3] / counts[ok, None]
    second = stats.bins[ok, 3:6] / counts[ok, None]
    r2 = q[0, 0] * second[:, 0] + 2 * q[0, 1] * second[:, 1] + q[1, 1] * second[:, 2] - 2 * mean @ (q @ c) + c @ q @ c
    dev = np.sqrt(np.maximum(r2, 0.0)) - 1.0
    return float(np.sqrt(np.average(dev**2, weights=counts[ok])))


def ellipse_quality(stats: WindowStats, fit: EllipseFit) -> dict:
    return {
        "samples": stats.n,
        "residual_rms_rad": fit.residual_rms,
        "radius_ripple_rad": radius_ripple_rms(stats, fit),
    }


def fit_from_stats(stats: WindowStats, *, harmonics_from_density: bool = True) -> tuple[Correction, dict]:
    """Reference-free correction from window statistics, with its quality numbers."""
    fit = fit_ellipse(stats)
    corr = ellipse_correction(stats, fit)
    if harmonics_from_density:
        corr.harmonics = density_harmonics(stats, fit).significant()
    corr.temp_c = stats.temp_mean if stats.temp_n else None
    return corr, ellipse_quality(stats, fit)
