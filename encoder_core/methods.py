"""Compensation methods with one interface: fit on samples, then correct d/q to an angle.

- Seed000: Wang et al. 2014, faithful: four weights by gradient descent on the radius error
  against the +20 °C reference table (eq. 10-20).
- Seed001: Liu & Wang, faithful: median then mean filter, amplitude normalisation (eq. 19),
  DFT phase of each channel, phase-error correction by eq. 14.
- OursLsTable: what seed 000's iteration is after, in one closed-form least-squares step.
- OursLsRef: closed-form least squares against the reference angle: a full 2x2 channel map
  with offsets (gain, offset, phase, zero) and angle harmonics on top.
- OursEllipse: reference-free, from additive window statistics: direct ellipse fit, then
  harmonics from the sample density (see ellipse.py); optional zero anchor from a reference.

Every method fits one correction per temperature band and interpolates between bands. They follow
scikit-learn's estimator convention: constructor parameters stored verbatim, learned state (`correction_`
and a per-band record such as `descents_`) set only by `fit`, which returns the method itself.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .correction import BandedCorrection, Correction, from_inverse_matrix
from .ellipse import fit_from_stats
from .physics import BAND_WIDTH_C, REFERENCE_TEMP_C, angle, band_of, circular_mean, wrap_rad
from .samples import InputError, Samples, check_angle_coverage, check_fit_input
from .stats import WindowStats, plausible_mask


@dataclass
class ReferenceTable:
    """Seed 000's Table I: d and q at +20 °C against angle on a uniform grid (3600 points at 0.1°),
    linearly interpolated (periodically) for any angle."""

    theta: np.ndarray
    d: np.ndarray
    q: np.ndarray

    @classmethod
    def from_samples(cls, samples: Samples, points: int = 3600) -> ReferenceTable:
        if samples.theta_ref is None:
            raise InputError("a reference table needs the reference angle column theta_ref_deg")
        check_fit_input(samples.d, samples.q, theta_ref=samples.theta_ref)
        grid = np.arange(points) * (2 * np.pi / points)
        order = np.argsort(samples.theta_ref % (2 * np.pi))
        th = samples.theta_ref[order] % (2 * np.pi)
        d, q = samples.d[order], samples.q[order]
        if np.unique(np.round(th, 9)).size < 16:
            raise InputError("a reference table needs at least 16 distinct reference angles")
        period = 2 * np.pi
        return cls(theta=grid, d=np.interp(grid, th, d, period=period), q=np.interp(grid, th, q, period=period))

    def lookup(self, theta) -> tuple[np.ndarray, np.ndarray]:
        theta = np.asarray(theta, dtype=float) % (2 * np.pi)
        return (
            np.interp(theta, self.theta, self.d, period=2 * np.pi),
            np.interp(theta, self.theta, self.q, period=2 * np.pi),
        )


class Method:
    """Base: fit per temperature band, correct by interpolating between bands.

    The estimator convention (scikit-learn's): the constructor stores its parameters verbatim and
    nothing else; what is learned ends in an underscore (`correction_`, and a method's per-band
    record named by `band_record`) and is set only by `fit`, all at once at its end, so a second fit
    replaces every learned attribute and leaves nothing of the first."""

    name = "method"
    needs_reference = False
    needs_table = False
    band_record: str | None = None  # learned attribute holding what fit_band reports per band

    def fit(self, samples: Samples, table: ReferenceTable | None = None) -> Method:
        check_fit_input(samples.d, samples.q, theta_ref=samples.theta_ref, temp_c=samples.temp_c)
        if self.needs_reference and samples.theta_ref is None:
            raise InputError(f"{self.name} needs the reference angle column theta_ref_deg")
        if self.needs_table and table is None:
            raise InputError(f"{self.name} needs the +20 °C reference table")
        bands = band_of(samples.temp_c) if samples.temp_c is not None else np.zeros(len(samples), int)
        fits, records = [], []
        for band in np.unique(bands):
            part = samples.subset(bands == band)
            where = (
                f" in the {band * BAND_WIDTH_C:g}..{(band + 1) * BAND_WIDTH_C:g} °C band"
                if samples.temp_c is not None
                else ""
            )
            theta = part.theta_ref if part.theta_ref is not None else angle(part.d, part.q)
            check_angle_coverage(theta, what=f"angle{where}")
            corr, record = self.fit_band(part, table)
            corr.temp_c = float(np.mean(part.temp_c)) if part.temp_c is not None else None
            fits.append(corr)
            records.append(record)
        self.correction_ = self.finish_fit(BandedCorrection(fits), table)
        if self.band_record:
            setattr(self, self.band_record, records)
        return self

    def fit_band(self, samples: Samples, table: ReferenceTable | None) -> tuple[Correction, object]:
        """One band's correction, and what the method records about that band (or None)."""
        raise NotImplementedError

    def finish_fit(self, correction: BandedCorrection, table: ReferenceTable | None) -> BandedCorrection:
        """A last step over all bands (the default: none)."""
        return correction

    def correct(self, samples: Samples) -> np.ndarray:
        if not hasattr(self, "correction_"):
            raise InputError(f"{self.name}: fit before correct")
        return self.correction_.angle(samples.d, samples.q, samples.temp_c)


# --- seed 000 ----------------------------------------------------------------------------------


@dataclass
class GradientDescentResult:
    weights: np.ndarray
    history: list[float] = field(default_factory=list)  # V after each iteration, V[0] at the start
    stop_reason: str = ""


def seed000_descent(
    d, q, d_c, q_c, *, step: float = 0.001, max_iter: int = 1000, v_tol: float = 0.0, w0=(1.0, 0.0, 1.0, 0.0)
) -> GradientDescentResult:
    """Eq. 12-20 as printed: V = ½Σ(d_f² + q_f² - d_c² - q_c²)², steepest descent with step T,
    stop when V stops decreasing (or falls below v_tol, or after max_iter)."""
    w = np.array(w0, dtype=float)
    target = d_c * d_c + q_c * q_c

    def value_and_grad(w):
        d_f = w[0] * d + w[1]
        q_f = w[2] * q + w[3]
        e = d_f * d_f + q_f * q_f - target
        grad = 2 * np.array([np.dot(e, d_f * d), e.dot(d_f), np.dot(e, q_f * q), e.dot(q_f)])  # eq. 13-16
        return 0.5 * e.dot(e), grad

    v, grad = value_and_grad(w)
    result = GradientDescentResult(weights=w, history=[float(v)])
    for _ in range(max_iter):
        w_next = w - step * grad  # eq. 17-20
        v_next, grad_next = value_and_grad(w_next)
        if not np.isfinite(v_next) or v_next >= v:
            result.stop_reason = "V stopped decreasing" if np.isfinite(v_next) else "diverged"
            break
        w, v, grad = w_next, v_next, grad_next
        result.history.append(float(v))
        if v < v_tol:
            result.stop_reason = "V below tolerance"
            break
    else:
        result.stop_reason = f"{max_iter} iterations"
    result.weights = w
    return result


def seed000_auto_scale(d, q, step: float) -> float:
    """The data scale at which step T is stable with margin: T·λmax(JᵀJ) = 1 at w = (1, 0, 1, 0).

    V's curvature grows with the 4th power of the signal amplitude and with the number of points,
    so T = 0.001 only converges on data scaled to well under unit amplitude (see bench-methods)."""
    jac = 2 * np.column_stack([d * d, d, q * q, q])
    lam = np.linalg.eigvalsh(jac.T @ jac).max()
    # entries scale as s^2 (w1, w3 columns) and s (w2, w4): solve T·λ(s) = 1 by bisection in log s
    lo, hi = -12.0, 4.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        s = 10.0**mid
        j = 2 * np.column_stack([s * s * d * d, s * d, s * s * q * q, s * q])
        lam = np.linalg.eigvalsh(j.T @ j).max()
        lo, hi = (mid, hi) if step * lam < 1.0 else (lo, mid)
    return 10.0**lo


class Seed000(Method):
    name = "seed000"
    needs_reference = True
    needs_table = True

    band_record = "descents_"  # one GradientDescentResult per band

    def __init__(self, step: float = 0.001, max_iter: int = 1000, data_scale: float | str = "auto"):
        self.step = step
        self.max_iter = max_iter
        self.data_scale = data_scale

    def fit_band(self, samples, table):
        d_c, q_c = table.lookup(samples.theta_ref)  # Fig. 8: look the +20 °C values up by angle
        s = seed000_auto_scale(d_c, q_c, self.step) if self.data_scale == "auto" else float(self.data_scale)
        res = seed000_descent(samples.d * s, samples.q * s, d_c * s, q_c * s, step=self.step, max_iter=self.max_iter)
        w = res.weights
        return Correction(w1=w[0], w2=w[1] / s, w3=w[2], w4=w[3] / s), res


# --- seed 001 ----------------------------------------------------------------------------------


class Seed001(Method):
    """Needs one or more whole revolutions sampled evenly in angle (the paper's constant-speed run);
    with a reference column the samples are put in angle order first."""

    name = "seed001"

    band_record = "betas_"  # the phase error β (rad) found in each band

    def __init__(self, median_window: int = 5, mean_window: int = 5, a_out: float = 2.0):
        self.median_window = median_window
        self.mean_window = mean_window
        self.a_out = a_out

    def fit_band(self, samples, table):
        order = (
            np.argsort(samples.theta_ref % (2 * np.pi)) if samples.theta_ref is not None else np.arange(len(samples))
        )
        if samples.theta_ref is not None:
            check_angle_coverage(samples.theta_ref, min_sectors=12, what="reference angle")
        from scipy.ndimage import median_filter, uniform_filter1d  # here: an import every process paid ~0.4 s for

        norm = []
        for sig in (samples.d[order], samples.q[order]):
            filtered = uniform_filter1d(
                median_filter(sig, size=self.median_window, mode="wrap"), size=self.mean_window, mode="wrap"
            )  # section 3.1
            spectrum = np.fft.rfft(filtered)
            # §3.2: the amplitude comes from the DFT (|X_1|/(N/2)), so eq. 19's A_in (the swing) is twice
            # that and V_min the fundamental's minimum; min/max of the raw trace would read a 3rd harmonic
            # as an amplitude imbalance and double its error
            amplitude = np.abs(spectrum[1]) / (filtered.size / 2)
            v_min, a_in = spectrum[0].real / filtered.size - amplitude, 2 * amplitude
            norm.append((v_min, a_in, np.angle(spectrum[1])))
        (dmin, da, phase_d), (qmin, qa, phase_q) = norm
        beta = float(wrap_rad(phase_d - phase_q - np.pi / 2))  # d = cos(θ+β), q = sin θ; one revolution: bin 1
        # eq. 19 as weights, eq. 14 as harmonics: θ = φ + ε(φ), ε = -β/2·(1 - cos 2φ)
        w1, w2 = self.a_out / da, -self.a_out * dmin / da - self.a_out / 2
        w3, w4 = self.a_out / qa, -self.a_out * qmin / qa - self.a_out / 2
        corr = Correction(w1=w1, w2=w2, w3=w3, w4=w4, zero_offset_rad=-beta / 2, harmonics={2: (beta / 2, 0.0)})
        return corr, beta


# --- ours ----------------------------------------------------------------------------------------


def affine_ls(x, y):
    """y ≈ a·x + b by least squares."""
    return affine_from_sums(x.size, x.sum(), x.dot(x), x.dot(y), y.sum())


def affine_from_sums(n, sx, sxx, sxy, sy):
    """The same from additive sums: n, Σx, Σx², Σxy, Σy."""
    den = n * sxx - sx * sx
    a = (n * sxy - sx * sy) / den
    return a, (sy - a * sx) / n


class OursLsTable(Method):
    """Seed 000's target and weights, solved in one step: d_c ≈ w1·d + w2, q_c ≈ w3·q + w4."""

    name = "ours-ls-table"
    needs_reference = True
    needs_table = True

    def fit_band(self, samples, table):
        d_c, q_c = table.lookup(samples.theta_ref)
        w1, w2 = affine_ls(samples.d, d_c)
        w3, w4 = affine_ls(samples.q, q_c)
        return Correction(w1=w1, w2=w2, w3=w3, w4=w4), None


def fit_harmonics(theta0, residual, orders) -> tuple[float, dict[int, tuple[float, float]]]:
    """residual ≈ c + Σ a_m cos mθ0 + b_m sin mθ0 by least squares."""
    design = [np.ones_like(theta0)]
    for m in orders:
        design += [np.cos(m * theta0), np.sin(m * theta0)]
    coef, *_ = np.linalg.lstsq(np.column_stack(design), residual, rcond=None)
    return float(coef[0]), {m: (float(coef[1 + 2 * i]), float(coef[2 + 2 * i])) for i, m in enumerate(orders)}


class OursLsRef(Method):
    """[d, q] = M·[cos θ, sin θ] + o by linear least squares against the reference angle, inverted
    exactly (gain, offset, phase and zero in one step), then angle harmonics fitted on the rest."""

    name = "ours-ls-ref"
    needs_reference = True

    def __init__(self, harmonic_orders=tuple(range(1, 9)), outlier_tolerance: float | None = 0.12):
        self.harmonic_orders = harmonic_orders
        self.outlier_tolerance = outlier_tolerance

    def fit_band(self, samples, table):
        keep = np.ones(len(samples), bool)
        if self.outlier_tolerance:
            keep = plausible_mask(
                samples.d,
                samples.q,
                center=(np.median(samples.d), np.median(samples.q)),
                tolerance=self.outlier_tolerance,
            )
        th, d, q = samples.theta_ref[keep], samples.d[keep], samples.q[keep]
        design = np.column_stack([np.cos(th), np.sin(th), np.ones_like(th)])
        coef, *_ = np.linalg.lstsq(design, np.column_stack([d, q]), rcond=None)
        signal_map, offset = coef[:2].T, coef[2]
        corr = from_inverse_matrix(np.linalg.inv(signal_map), offset)
        base = Correction(w1=corr.w1, w2=corr.w2, w3=corr.w3, w4=corr.w4, w5=corr.w5)
        theta0 = base.angle(d, q)
        resid = wrap_rad(th - theta0 - corr.zero_offset_rad)
        const, harmonics = fit_harmonics(theta0, resid, list(self.harmonic_orders))
        corr.zero_offset_rad = float(wrap_rad(corr.zero_offset_rad + const))
        corr.harmonics = harmonics
        return corr, None


def zero_error_rad(correction: Correction, samples: Samples) -> float:
    """How far the correction's zero is from the reference's: the circular mean of their difference."""
    return circular_mean(samples.theta_ref - correction.angle(samples.d, samples.q))


class OursEllipse(Method):
    """Reference-free: the agent's window statistics, merged per band, fitted in closed form.
    With a reference table the zero is anchored once at +20 °C, as a factory calibration does."""

    name = "ours-ellipse"

    band_record = "quality_"  # the ellipse fit's quality figures per band

    def __init__(self, harmonics_from_density: bool = True, outlier_tolerance: float = 0.12):
        self.harmonics_from_density = harmonics_from_density
        self.outlier_tolerance = outlier_tolerance

    def fit_band(self, samples, table):
        stats = stats_for(samples, outlier_tolerance=self.outlier_tolerance)
        return fit_from_stats(stats, harmonics_from_density=self.harmonics_from_density)

    def finish_fit(self, correction, table):
        """With a reference table, shift every band's zero by the +20 °C band's error on the table."""
        if table is None:
            return correction
        ref = Samples(t=np.arange(table.theta.size, dtype=float), d=table.d, q=table.q, theta_ref=table.theta)
        temps = np.array([b.temp_c if b.temp_c is not None else REFERENCE_TEMP_C for b in correction.bands])
        shift = zero_error_rad(correction.bands[int(np.argmin(np.abs(temps - REFERENCE_TEMP_C)))], ref)
        for band in correction.bands:
            band.zero_offset_rad = float(wrap_rad(band.zero_offset_rad + shift))
        return correction


def stats_for(
    samples: Samples, *, scale: float | None = None, center=None, outlier_tolerance: float = 0.12
) -> WindowStats:
    """Window statistics of samples, normalised by their own radius unless told otherwise."""
    c = center if center is not None else (float(np.median(samples.d)), float(np.median(samples.q)))
    keep = plausible_mask(samples.d, samples.q, center=c, tolerance=outlier_tolerance)
    if scale is None:
        scale = float(np.median(np.hypot(samples.d[keep] - c[0], samples.q[keep] - c[1])))
    stats = WindowStats(scale=scale, center_d=c[0], center_q=c[1])
    stats.add(samples.d[keep], samples.q[keep], None if samples.temp_c is None else samples.temp_c[keep])
    stats.rejected = int((~keep).sum())
    return stats


METHODS = {cls.name: cls for cls in (Seed000, Seed001, OursLsTable, OursLsRef, OursEllipse)}
