"""Drift since the bench, from window statistics, without taking the field's harmonics for drift.

The factory measured the drive against a reference at the bench: its correction holds the zero and
the angle harmonics, and the bench locus (d, q against the reference angle) is the shape of the
drive's own field. In the field, temperature and age change each channel's gain and offset and its
axis (seed 000 eq. 4-5): an affine map of the channels, which leaves the field's harmonics where
they are. So the field locus at temperature T is the bench locus moved by an affine map, and the
correction at T is the factory's applied after the map that takes the field back to the bench:

    angle_T(p) = factory.angle(Δ_T(p)),   Δ_T(p) = c_bench + S·(p - c_field),  S lower triangular

A direct ellipse fit of a locus with field harmonics is biased (a 3rd harmonic's radius ripple
reads as amplitude imbalance: seed 001's trap), but the fit is affine-equivariant, so the same fit
of the bench locus, weighted as the field visited its angles, is biased in the same way: Δ_T from
the two fits cancels the bias. The bench locus is re-weighted bin by bin to the field's angle
histogram, so a drive that dwells or reverses is compared like with like.

Each term of Δ (two offsets, the gain ratio, the axis) is kept only when it stands clear of its own
uncertainty; otherwise it keeps the factory's value (no drift). The zero is never taken from the
field: the lower-triangular S fixes the d axis, as the factory's correction form does.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from .correction import Correction, angles_of
from .physics import circular_mean
from .samples import InputError
from .stacked import solve_stack
from .stats import N_BINS, WindowStats, plausible_mask

LOCUS_ORDER = 12  # Fourier orders of the bench locus: field harmonics to 7 in either sense, with room
SYNTHETIC_POINTS = 64 * 32  # bench-locus points per re-weighted fit (32 per angle bin)
TERM_SIGMAS = 3.0  # a drift term is kept when it is this many standard errors from zero
TERMS = ("offset_d", "offset_q", "imbalance", "axis")


@dataclass
class BenchLocus:
    """d(θ) and q(θ) at the bench as Fourier series in the reference angle: [c0, a1, b1, ..., aK, bK]."""

    temp_c: float
    d: np.ndarray
    q: np.ndarray
    samples: int
    residual_rms: float = 0.0  # radial scatter of the bench samples about the series, raw units

    @property
    def order(self) -> int:
        return (len(self.d) - 1) // 2

    def points(self, theta) -> tuple[np.ndarray, np.ndarray]:
        design = fourier_design(np.asarray(theta, float), self.order)
        return design @ self.d, design @ self.q

    @property
    def radius(self) -> float:
        """Mean radius of the locus about its centre, raw units."""
        return float(np.hypot(self.d[1], self.d[2]) + np.hypot(self.q[1], self.q[2])) / 2

    @property
    def precision(self) -> float:
        """Standard error of the fitted curve at a point (raw units): the bench's noise over its samples."""
        return self.residual_rms * float(np.sqrt(len(self.d) / max(self.samples, 1)))

    def to_dict(self) -> dict:
        return {
            "temp_c": self.temp_c,
            "d": self.d.tolist(),
            "q": self.q.tolist(),
            "samples": self.samples,
            "residual_rms": self.residual_rms,
        }

    @classmethod
    def from_dict(cls, data: dict) -> BenchLocus:
        d, q = np.asarray(data["d"], float), np.asarray(data["q"], float)
        if d.shape != q.shape or d.ndim != 1 or d.size % 2 != 1 or d.size < 3 or not np.all(np.isfinite([*d, *q])):
            raise InputError("bench locus: d and q must be finite Fourier series of the same odd length >= 3")
        return cls(
            temp_c=float(data["temp_c"]),
            d=d,
            q=q,
            samples=int(data.get("samples", 0)),
            residual_rms=float(data.get("residual_rms", 0.0)),
        )

    @classmethod
    def fit(cls, theta_ref, d, q, temp_c: float, order: int = LOCUS_ORDER, center=None) -> BenchLocus:
        """Least squares of d and q on the reference angle (samples far off the circle about `center`, by default
        the median of d and q, left out)."""
        theta_ref, d, q = (np.asarray(a, float) for a in (theta_ref, d, q))
        keep = plausible_mask(d, q, center=(np.median(d), np.median(q)) if center is None else center)
        if keep.sum() < 4 * order + 2:
            raise InputError(f"bench locus: {int(keep.sum())} usable samples, need at least {4 * order + 2}")
        design = fourier_design(theta_ref[keep], order)
        coef, *_ = np.linalg.lstsq(design, np.column_stack([d[keep], q[keep]]), rcond=None)
        resid = np.column_stack([d[keep], q[keep]]) - design @ coef
        rms = float(np.sqrt(np.mean(np.sum(resid**2, axis=1)) / 2))  # per axis ≈ radial, for isotropic noise
        return cls(temp_c=float(temp_c), d=coef[:, 0], q=coef[:, 1], samples=int(keep.sum()), residual_rms=rms)


def fourier_design(theta: np.ndarray, order: int) -> np.ndarray:
    cols = [np.ones_like(theta)]
    for k in range(1, order + 1):
        cols += [np.cos(k * theta), np.sin(k * theta)]
    return np.column_stack(cols)


@dataclass
class Drift:
    """Field point p -> where the bench saw it: bench_center + shape·(p - field_center), raw units."""

    field_center: np.ndarray
    bench_center: np.ndarray
    shape: np.ndarray  # lower triangular, positive diagonal

    def apply(self, d, q) -> tuple[np.ndarray, np.ndarray]:
        p = np.vstack([np.asarray(d, float) - self.field_center[0], np.asarray(q, float) - self.field_center[1]])
        out = self.shape @ p
        return out[0] + self.bench_center[0], out[1] + self.bench_center[1]

    def inverse(self, d, q) -> tuple[np.ndarray, np.ndarray]:
        p = np.vstack([np.asarray(d, float) - self.bench_center[0], np.asarray(q, float) - self.bench_center[1]])
        out = np.linalg.solve(self.shape, p)
        return out[0] + self.field_center[0], out[1] + self.field_center[1]

    def terms(self, radius: float) -> dict[str, float]:
        """The drift as angle-sized numbers (rad): offsets over the radius, the gain ratio's log and the
        axis shear (each the size of the angle error it makes, to first order, times 1 or 2)."""
        s = self.shape
        off = (self.field_center - self.bench_center) / radius
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):  # a run-away fit reads as inf/nan
            return self._terms(s, off)

    @staticmethod
    def _terms(s: np.ndarray, off: np.ndarray) -> dict[str, float]:
        values = _term_values(off[0], off[1], s[0, 0], s[1, 0], s[1, 1])
        return {**dict(zip(TERMS, values.tolist())), "common": float(np.log(s[0, 0] * s[1, 1]) / 2)}

    @classmethod
    def from_terms(cls, terms: dict[str, float], bench_center, radius: float) -> Drift:
        common, g = terms.get("common", 0.0), terms["imbalance"]
        s11, s22 = np.exp(common - g), np.exp(common + g)
        shape = np.array([[s11, 0.0], [2 * terms["axis"] * s22, s22]])
        bench_center = np.asarray(bench_center, float)
        field_center = bench_center + radius * np.array([terms["offset_d"], terms["offset_q"]])
        return cls(field_center=field_center, bench_center=bench_center, shape=shape)


def _term_values(offset_d, offset_q, s00, s10, s11) -> np.ndarray:
    """TERMS of a drift (numbers, or arrays of many drifts: (..., 4)) from its offsets over the radius and its
    shape's entries: the gain ratio's log and the axis shear."""
    return np.stack([offset_d, offset_q, np.log(s11 / s00) / 2, s10 / s11 / 2], axis=-1)


@dataclass
class BinPoints:
    """What the angle bins of a band's statistics say about the locus: each bin's mean point (raw units),
    moved outward by the bin's spread along the circle (points spread over an arc average inside it), its
    count, and the pooled radial scatter of single samples."""

    points: np.ndarray  # (k, 2)
    counts: np.ndarray  # (k,)
    sigma: float  # radial scatter of one sample, raw units
    index: np.ndarray  # (k,) the angle bin of each point


def bin_points(fields: list[WindowStats], centers: np.ndarray, min_count: int = 2) -> list[BinPoints]:
    """The BinPoints of several statistics, each about its own centre (raw units), in one array pass."""
    if not fields:
        return []
    bins = np.array([f.bins for f in fields])  # (fields, bins, sums)
    scale = np.array([f.scale for f in fields])[:, None]
    counts = bins[..., 0]
    ok = counts >= min_count
    with np.errstate(invalid="ignore", divide="ignore"):  # bins left out (ok False) may divide by zero: unused
        mean = bins[..., 1:3] / counts[..., None]
        second = bins[..., 3:6] / counts[..., None]
        cxx = second[..., 0] - mean[..., 0] ** 2
        cxy = second[..., 1] - mean[..., 0] * mean[..., 1]
        cyy = second[..., 2] - mean[..., 1] ** 2
        raw = np.array([[f.center_d, f.center_q] for f in fields])[:, None, :] + scale[..., None] * mean
        rel = raw - np.asarray(centers, float).reshape(-1, 1, 2)
        radius = np.hypot(rel[..., 0], rel[..., 1])
        nx, ny = rel[..., 0] / radius, rel[..., 1] / radius
        var_t = (ny * ny * cxx - 2 * nx * ny * cxy + nx * nx * cyy) * scale**2
        var_r = (nx * nx * cxx + 2 * nx * ny * cxy + ny * ny * cyy) * scale**2
        points = raw + (np.maximum(var_t, 0.0) / (2 * radius))[..., None] * np.stack([nx, ny], axis=-1)
    out = []
    for k in range(len(fields)):
        n = counts[k, ok[k]]
        # no bin with min_count samples (a soak of a few samples): no points, which the fits refuse as too few bins
        sigma = float(np.sqrt(max(np.average(np.maximum(var_r[k, ok[k]], 0.0), weights=n), 1e-12))) if n.size else 1e-6
        out.append(BinPoints(points=points[k, ok[k]], counts=n, sigma=sigma, index=np.flatnonzero(ok[k])))
    return out


class PolarLocus:
    """The bench locus in its own fundamental's frame, as radius against polar angle: the curve a field
    point must lie on once the drift is taken back out."""

    def __init__(self, locus: BenchLocus):
        self.center = np.array([locus.d[0], locus.q[0]])
        fundamental = np.array([[locus.d[1], locus.d[2]], [locus.q[1], locus.q[2]]])
        self.to_unit = np.linalg.inv(fundamental)
        theta = np.arange(SYNTHETIC_POINTS) * (2 * np.pi / SYNTHETIC_POINTS)
        u = self.unit(*locus.points(theta))
        psi = np.arctan2(u[1], u[0])
        order = np.argsort(psi)
        self.psi, self.rho = psi[order], np.hypot(u[0], u[1])[order]
        # the curve closed once here (one point past each end), so each interpolation needs no sort: np.interp's
        # `period` re-sorts its 2,048 points on every call, and the drift fit calls it ~2,000 times per device
        self._psi_closed = np.concatenate([[self.psi[-1] - 2 * np.pi], self.psi, [self.psi[0] + 2 * np.pi]])
        self._rho_closed = np.concatenate([[self.rho[-1]], self.rho, [self.rho[0]]])
        self._slope = np.diff(self._rho_closed) / np.diff(self._psi_closed)  # drho/dpsi of each segment

    def unit(self, d, q) -> np.ndarray:
        return self.to_unit @ np.vstack([np.asarray(d, float) - self.center[0], np.asarray(q, float) - self.center[1]])


def polar_locus(locus: BenchLocus) -> PolarLocus:
    """The locus's polar curve, built once per bench locus (a refit pass fits every band against it twice)."""
    return _polar_of(locus.d.tobytes(), locus.q.tobytes())


@lru_cache(maxsize=4096)
def _polar_of(d: bytes, q: bytes) -> PolarLocus:
    return PolarLocus(BenchLocus(0.0, np.frombuffer(d), np.frombuffer(q), 0))


def _drift_of(x: np.ndarray, bench_center: np.ndarray) -> Drift:
    with np.errstate(over="ignore"):  # a fit that ran away gives inf here, and its terms say so
        shape = np.array([[np.exp(x[2]), 0.0], [x[3], np.exp(x[4])]])
    return Drift(field_center=x[:2].copy(), bench_center=bench_center, shape=shape)


@dataclass
class DriftFit:
    drift: Drift
    errors: dict[str, float]  # standard error of each term (rad), misfit included
    chi2_dof: float
    bins: int


def fit_drift(
    field: WindowStats,
    locus: BenchLocus,
    *,
    bin_dtemps: np.ndarray | None = None,
    min_bins: int = 16,
    iterations: int = 8,
    jackknife: bool = True,
) -> DriftFit:
    """Δ by weighted least squares: the field's bin points, taken back through Δ, on the bench locus.

    Five parameters (field centre, lower-triangular shape), and with the bins' temperatures a sixth, the
    locus's common scale per kelvin inside the band (see fit_drifts); weights are the bins' counts over the
    sample scatter. A term's standard error is the larger of two: the scatter's (scaled up by the misfit
    when the model fits worse than the scatter says) and a jackknife over the circle's quarters, which
    sees what the scatter cannot: bins seen at different times disagreeing."""
    (fit,) = fit_drifts(
        [field], locus, bin_dtemps=[bin_dtemps], min_bins=min_bins, iterations=iterations, jackknife=jackknife
    )
    if isinstance(fit, InputError):
        raise fit
    return fit


def fit_drifts(
    fields: list[WindowStats],
    locus: BenchLocus,
    *,
    bin_dtemps: list[np.ndarray | None] | None = None,
    min_bins: int = 16,
    iterations: int = 8,
    jackknife: bool = True,
) -> list[DriftFit | InputError]:
    """`fit_drift` of several statistics (a refit's bands) against one bench locus, as one batch: the
    Gauss-Newton steps and the jackknife's refits of all of them run as a few array operations, so a
    dozen bands cost little more than one. Each entry is its fit, or the InputError that fit would raise.

    bin_dtemps (optional, per field): each angle bin's mean temperature minus the band's (N_BINS values). With
    it the fit has a sixth parameter, the locus's common scale per kelvin inside the band (`GAIN_SLOPE_PRIOR`):
    a drive that reverses over arcs or dwells while the band warms sees some angles only warm and others only
    cool, and the gains' common temperature coefficient (~0.1 %/K, ten times every other drift of a band)
    then reads as an offset or an imbalance. The scale leaves the angle alone, so it is fitted and set aside;
    where it cannot be told from the terms the errors say so."""
    return fit_drifts_each(
        fields,
        [locus] * len(fields),
        bin_dtemps=bin_dtemps,
        min_bins=min_bins,
        iterations=iterations,
        jackknife=jackknife,
    )


def fit_drifts_each(
    fields: list[WindowStats],
    loci: list[BenchLocus],
    *,
    bin_dtemps: list[np.ndarray | None] | None = None,
    min_bins: int = 16,
    iterations: int = 8,
    jackknife: bool = True,
) -> list[DriftFit | InputError]:
    """fit_drifts with a bench locus per field: all of a drive's new bands in one batch whichever bench band each
    is nearest (fit_bands), or the bands of many drives. A field's fit does not depend on what else is in the
    batch: each problem is solved against its own curve, and its sums run over its own points (padding has
    weight zero)."""
    if len(loci) != len(fields):
        raise ValueError(f"one bench locus per field: {len(fields)} fields, {len(loci)} loci")
    curves = [polar_locus(locus) for locus in loci]
    radii = np.array([locus.radius for locus in loci]).reshape(-1)
    bin_dtemps = bin_dtemps or [None] * len(fields)
    out: list[DriftFit | InputError | None] = [None] * len(fields)
    x = np.array([[c.center[0], c.center[1], 0.0, 0.0, 0.0, 0.0] for c in curves]).reshape(-1, 6)
    pts: list = [None] * len(fields)
    dtemps: list = [None] * len(fields)
    weights: list = [None] * len(fields)
    info, resid, jacs = {}, {}, {}
    live = list(range(len(fields)))
    for _ in range(2):  # the bin points' outward shift depends on the centre: settle it once
        batch = []
        for i, p in zip(live, bin_points([fields[i] for i in live], x[live, :2])):
            if p.counts.size < min_bins:
                out[i] = InputError(
                    f"too few angle bins with samples for a drift fit: {p.counts.size}, need {min_bins}"
                )
                continue
            # a bin's weight: its mean's variance plus the bench curve's own; counts capped at the median so
            # that a few positions a servo holds for hours do not outvote the rest of the circle
            capped = np.minimum(p.counts, np.median(p.counts))
            pts[i], weights[i] = p, radii[i] ** 2 / (p.sigma**2 / capped + loci[i].precision ** 2)
            dtemps[i] = None if bin_dtemps[i] is None else np.asarray(bin_dtemps[i], float)[p.index]
            batch.append(i)
        solved = _solve(
            [curves[i] for i in batch],
            [pts[i].points for i in batch],
            [weights[i] for i in batch],
            x[batch],
            iterations,
            [dtemps[i] for i in batch],
        )
        live = []
        for i, result in zip(batch, solved):
            if isinstance(result, InputError):
                out[i] = result
                continue
            x[i], info[i], resid[i], jacs[i] = result
            live.append(i)
    spreads = (
        _jackknife(
            [pts[i].index for i in live],
            [weights[i] for i in live],
            x[live],
            [resid[i] for i in live],
            [jacs[i] for i in live],
            np.array([curves[i].center for i in live]).reshape(-1, 2),
            radii[live],
            min_bins // 2,
        )
        if jackknife
        else [None] * len(live)
    )
    chi2_dofs = [float(np.sum(weights[i] * resid[i] * resid[i]) / max(pts[i].counts.size - 5, 1)) for i in live]
    term_errors = _term_errors(
        x[live], np.array([info[i] for i in live]).reshape(-1, 6, 6), np.maximum(chi2_dofs, 1.0), radii[live]
    )
    for i, spread, errors, chi2_dof in zip(live, spreads, term_errors, chi2_dofs):
        if spread is not None:
            errors = np.maximum(errors, spread)
        out[i] = DriftFit(
            _drift_of(x[i], curves[i].center), dict(zip(TERMS, errors.tolist())), chi2_dof, pts[i].counts.size
        )
    return out


STEPS = np.array([1e-3, 1e-3, 1e-5, 1e-5, 1e-5])  # convergence: a step under 1e-3 of these (centre × radius)
# the sixth parameter, the locus's common log-scale per kelvin inside a band: a Gaussian prior of this width
# (1/K) keeps it defined where the bins' temperatures do not vary (then it stays 0 and the fit is the five-term
# one); gains' temperature coefficients are ~0.1 %/K, so 1 %/K holds anything physical
GAIN_SLOPE_PRIOR = 0.01
GAIN_SLOPE_STEP = 1e-7  # convergence: a slope step below this (1/K) is negligible


class _Curves:
    """The bench curves of a batch's problems side by side (one per problem, shared ones once): their maps to the
    unit frame and one table of line segments, each curve's polar angles shifted by 4π per curve so that one
    search finds every problem's segment. Values come from each curve's own angles, not the shifted ones, so a
    problem's residuals do not depend on which curves share its batch."""

    def __init__(self, curves: list[PolarLocus]):
        unique = list({id(c): c for c in curves}.values())  # in order of first use
        place = {id(c): k for k, c in enumerate(unique)}
        which = np.array([place[id(c)] for c in curves])
        self.to_unit = np.array([c.to_unit for c in curves])
        self.radius = 1.0 / np.sqrt(np.abs(np.linalg.det(self.to_unit)))
        self.shift = 4 * np.pi * which
        self.psi = np.concatenate([c._psi_closed for c in unique])
        self.rho = np.concatenate([c._rho_closed for c in unique])
        self.slope = np.concatenate([np.append(c._slope, 0.0) for c in unique])  # a curve's last point: no segment
        self.search = np.concatenate([c._psi_closed + 4 * np.pi * k for k, c in enumerate(unique)])
        sizes = np.array([len(c._psi_closed) for c in unique])
        starts = np.cumsum(sizes) - sizes
        self.first_segment = starts[which]  # each problem's curve's first and last segment, in the joined table
        self.last_segment = (starts + sizes - 2)[which]

    def rho_and_slope(self, psi: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The curves' radius at (a, n) polar angles in [-π, π] (row k on the curve of problem rows[k]) and its
        slope drho/dpsi there: np.interp's line segments, with the derivative the Jacobian needs."""
        first, last = self.first_segment[rows, None], self.last_segment[rows, None]
        segment = np.clip(np.searchsorted(self.search, psi + self.shift[rows, None], side="right") - 1, first, last)
        # the shift rounds: an angle within an ulp of a node may land one segment off; the curve's own angles say
        segment = np.clip(segment - (psi < self.psi[segment]), first, last)
        segment = np.clip(segment + (psi >= self.psi[segment + 1]), first, last)
        slope = self.slope[segment]
        return self.rho[segment] + slope * (psi - self.psi[segment]), slope


def _solve(
    curves: list[PolarLocus],
    points: list[np.ndarray],
    weights: list[np.ndarray],
    x0: np.ndarray,
    iterations: int,
    dtemps: list[np.ndarray | None] | None = None,
):
    """Gauss-Newton on the radial residuals of several problems at once, each against its own bench curve (each
    stops when its own step is negligible); per problem its six parameters (fit_drifts), their information
    matrix (from the last step's start), and its residuals and their Jacobian at those parameters (the jackknife's
    one step starts there), or an InputError. dtemps: per problem, each point's temperature minus the band's (None:
    all zero)."""
    if not points:
        return []
    stacked = _Curves(curves)
    steps = STEPS * np.column_stack([stacked.radius, stacked.radius, np.ones((len(curves), 3))])  # (problems, 5)
    # the problems side by side, padded to the longest with a real point of weight zero
    sizes = [len(p) for p in points]
    longest = max(sizes)
    field = np.empty((len(points), 2, longest))
    w = np.zeros((len(points), longest))
    dt = np.zeros((len(points), longest))
    for k, (p, wk) in enumerate(zip(points, weights)):
        field[k] = p[np.minimum(np.arange(longest), len(p) - 1)].T
        w[k, : len(p)] = wk
        if dtemps is not None and dtemps[k] is not None:
            dt[k, : len(p)] = dtemps[k]

    def residuals(xs: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(a, 6) parameter sets of problems `rows` -> (a, n) residuals and their (a, n, 6) Jacobian, exact:
        u = to_unit·S·(p - c) is polar.unit(drift.apply(p)), because the drift's bench centre is the locus's
        centre; the residual is |u|, divided by the locus's scale at the point's temperature, less the curve's
        radius at u's polar angle (the curve's line segments give its slope)."""
        c0, c1, b, slope_k = (xs[:, k, None] for k in (0, 1, 3, 5))
        with np.errstate(over="ignore", invalid="ignore"):  # a run-away step: non-finite terms, gated out later
            ea, ec = np.exp(xs[:, 2, None]), np.exp(xs[:, 4, None])
            v0, v1 = field[rows, 0] - c0, field[rows, 1] - c1
            s0, s1 = ea * v0, b * v0 + ec * v1  # S·(p - c)
            to_unit = stacked.to_unit[rows, :, :, None]  # (a, 2, 2, 1): each problem's map to its curve's frame
            u0 = to_unit[:, 0, 0] * s0 + to_unit[:, 0, 1] * s1
            u1 = to_unit[:, 1, 0] * s0 + to_unit[:, 1, 1] * s1
            norm = np.hypot(u0, u1)
            scale = np.exp(-slope_k * dt[rows])
            rad = norm * scale
            rho, drho = stacked.rho_and_slope(np.arctan2(u1, u0), rows)
            # dr/du: the radius's gradient less the curve's slope times the polar angle's gradient
            g0 = scale * u0 / norm + drho * u1 / norm**2
            g1 = scale * u1 / norm - drho * u0 / norm**2
            w0 = g0 * to_unit[:, 0, 0] + g1 * to_unit[:, 1, 0]  # dr/d(S·(p - c)), component by component
            w1 = g0 * to_unit[:, 0, 1] + g1 * to_unit[:, 1, 1]
            jac = np.stack([-(ea * w0 + b * w1), -ec * w1, w0 * s0, w1 * v0, w1 * ec * v1, -dt[rows] * rad], axis=2)
        return rad - rho, jac

    x = np.array(x0, float)
    info = np.zeros((len(points), 6, 6))
    active = np.ones(len(points), bool)
    failed = np.zeros(len(points), bool)
    prior = 1.0 / GAIN_SLOPE_PRIOR**2
    for _ in range(iterations):
        rows = np.flatnonzero(active)
        if rows.size == 0:
            break
        r0, jac = residuals(x[rows], rows)
        # a run-away problem carries non-finite numbers through here (no warning per batch: bench-fleet-accuracy
        # printed dozens); the batch's other problems are not touched by it. A singular one is marked failed below;
        # one whose information is no longer finite ends with NaN parameters, whose terms' errors are infinite
        # (_term_errors), so every term stays the factory's (gate)
        with np.errstate(invalid="ignore", over="ignore"):
            info[rows] = np.swapaxes(jac, 1, 2) @ (jac * w[rows, :, None])
            info[rows, 5, 5] += prior
            rhs = -np.einsum("ank,an->ak", jac, w[rows] * r0)
            rhs[:, 5] -= prior * x[rows, 5]
        step = _solve_each(info[rows], rhs)
        bad = np.isnan(step[:, 0]) & np.all(np.isfinite(info[rows]), axis=(1, 2))
        failed[rows[bad]] = True
        x[rows] += np.where(bad[:, None], 0.0, step)
        done = bad | (np.all(np.abs(step[:, :5]) < steps[rows] * 1e-3, axis=1) & (np.abs(step[:, 5]) < GAIN_SLOPE_STEP))
        active[rows[done]] = False
    final, final_jac = residuals(x, np.arange(len(points)))
    return [
        InputError("drift fit: the bins do not constrain the drift")
        if failed[k]
        else (x[k], info[k], final[k, :n], final_jac[k, :n])
        for k, n in enumerate(sizes)
    ]


def _solve_each(matrices: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """np.linalg.solve of a stack, with NaN rows for the singular matrices instead of one error for all."""
    return solve_stack(matrices, rhs[..., None])[..., 0]


def _jackknife(
    indices: list[np.ndarray],
    weights: list[np.ndarray],
    xs: np.ndarray,
    resids: list[np.ndarray],
    jacs: list[np.ndarray],
    bench_centers: np.ndarray,
    radii: np.ndarray,
    min_bins: int,
) -> np.ndarray:
    """Standard error of each term (TERMS' order), per problem, from the four fits that each leave one quarter of
    the circle out (indices: each point's angle bin). Each is one Gauss-Newton step from the whole circle's fit,
    taken with the residuals and Jacobian that fit already has (the one-step jackknife): from the optimum a second
    step moves a leave-out fit far less than the first (against four steps: spreads within ~1e-3 relative, the same
    adoptions on 100 bench devices), and four refits took a third of a device's refit. Inf
    where a quarter left out leaves too little of the circle, or the step runs away (the circle does not pin the
    terms without it). All problems' quarters in one batch, padded with points of weight zero."""
    if not indices:
        return np.zeros((0, len(TERMS)))
    longest = max(len(i) for i in indices)
    quarter = np.full((len(indices), longest), -1)
    w, r, jac = np.zeros(quarter.shape), np.zeros(quarter.shape), np.zeros((*quarter.shape, 6))
    for k, (index, wk, rk, jk) in enumerate(zip(indices, weights, resids, jacs)):
        n = len(index)
        quarter[k, :n], w[k, :n], r[k, :n], jac[k, :n] = index * 4 // N_BINS, wk, rk, jk
    keeps = (quarter[:, None, :] != np.arange(4)[None, :, None]) & (quarter[:, None, :] >= 0)  # (problems, 4, points)
    enough = np.all(keeps.sum(axis=2) >= max(min_bins, 6), axis=1)
    with np.errstate(invalid="ignore", over="ignore"):
        jw = jac[:, None] * (keeps * w[:, None, :])[..., None]  # (problems, 4, points, 6)
        info = np.swapaxes(jw, 2, 3) @ jac[:, None]
        info[..., 5, 5] += 1.0 / GAIN_SLOPE_PRIOR**2
        grad = np.einsum("bqnk,bn->bqk", jw, r)
        grad[..., 5] += xs[:, None, 5] / GAIN_SLOPE_PRIOR**2
    steps = _solve_each(info.reshape(-1, 6, 6), -grad.reshape(-1, 6))
    values = _terms_of(
        np.repeat(xs, 4, axis=0) + steps, np.repeat(bench_centers, 4, axis=0), np.repeat(radii, 4)[:, None]
    ).reshape(len(indices), 4, len(TERMS))
    with np.errstate(invalid="ignore"):  # a run-away quarter's inf: its problem's spread is inf below
        spread = np.sqrt(3 / 4 * np.sum((values - values.mean(axis=1, keepdims=True)) ** 2, axis=1))
    return np.where((enough & np.all(np.isfinite(values), axis=(1, 2)))[:, None], spread, np.inf)


def _terms_of(xs: np.ndarray, bench_center: np.ndarray, radius: float) -> np.ndarray:
    """Drift.terms of fitted parameter vectors (m, 6) as an (m, 4) array in TERMS' order, through the same exp
    and log, so a fit that ran away reads as inf/nan here too."""
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        offsets = (xs[:, :2] - bench_center) / radius
        return _term_values(offsets[:, 0], offsets[:, 1], np.exp(xs[:, 2]), xs[:, 3], np.exp(xs[:, 4]))


def _term_errors(xs: np.ndarray, infos: np.ndarray, inflates: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """Standard errors of the drift terms (m, 4; TERMS' order) of m fits, by the delta method from each fit's
    parameter covariance (the in-band gain slope, the sixth parameter, marginalised: its uncertainty widens the
    terms it can be mistaken for). inf where the information is singular, ill-conditioned or not finite."""
    out = np.full((len(xs), len(TERMS)), np.inf)
    finite = np.all(np.isfinite(infos), axis=(1, 2))
    if not finite.any():
        return out
    rows = np.flatnonzero(finite)
    rows = rows[np.linalg.cond(infos[rows]) <= 1e14]
    try:
        cov = np.linalg.inv(infos[rows])
    except np.linalg.LinAlgError:  # one singular matrix among them: each on its own, NaN for the singular
        cov = np.array([_inverse(m) for m in infos[rows]]).reshape(-1, 6, 6)
    cov = cov[:, :5, :5] * inflates[rows, None, None]
    # the terms' derivatives by the five parameters: offsets 1/radius, imbalance (x4 - x2)/2, axis x3·e^-x4/2
    x3, e4 = xs[rows, 3], np.exp(-xs[rows, 4])
    jac = np.zeros((len(rows), len(TERMS), 5))
    jac[:, 0, 0] = jac[:, 1, 1] = 1.0 / radii[rows]
    jac[:, 2, 2], jac[:, 2, 4] = -0.5, 0.5
    jac[:, 3, 3], jac[:, 3, 4] = e4 / 2, -x3 * e4 / 2
    var = np.einsum("mik,mkl,mil->mi", jac, cov, jac)
    ok = np.all(np.isfinite(cov), axis=(1, 2))
    out[rows[ok]] = np.sqrt(np.maximum(var[ok], 0.0))
    return out


def _inverse(matrix: np.ndarray) -> np.ndarray:
    try:
        return np.linalg.inv(matrix)
    except np.linalg.LinAlgError:
        return np.full(matrix.shape, np.nan)


def gate(terms: dict[str, float], errors: dict[str, float], sigmas: float = TERM_SIGMAS) -> dict[str, float]:
    """Terms that do not stand `sigmas` standard errors clear of zero keep the factory's value (no drift)."""
    out = dict(terms)
    for name in TERMS:
        if not abs(terms[name]) > sigmas * errors[name]:
            out[name] = 0.0
    return out


def compose(factory: Correction, drift: Drift) -> Correction:
    """factory.angle(drift.apply(p)) in the correction form, exactly: the factory's zero and harmonics kept."""
    lf = np.array([[factory.w1, 0.0], [factory.w5 * factory.w1, factory.w3]])
    tf = np.array([factory.w2, factory.w4 + factory.w5 * factory.w2])
    k = lf @ drift.shape
    s = lf @ (drift.bench_center - drift.shape @ drift.field_center) + tf
    w5 = k[1, 0] / k[0, 0]
    return Correction(
        w1=float(k[0, 0]),
        w2=float(s[0]),
        w3=float(k[1, 1]),
        w4=float(s[1] - w5 * s[0]),
        w5=float(w5),
        zero_offset_rad=factory.zero_offset_rad,
        harmonics=dict(factory.harmonics),
        temp_c=factory.temp_c,
    )


@lru_cache(maxsize=8)
def _whole_degrees(order: int) -> np.ndarray:
    """The Fourier design at every whole degree, built once per order (anchor_zero runs for every band)."""
    return fourier_design(np.arange(360) * (2 * np.pi / 360), order)


def anchor_zero(candidate: Correction, factory: Correction, locus: BenchLocus, drift: Drift) -> Correction:
    """Give the candidate the factory's zero: no rotation between them on average around the field's locus.

    The field cannot see a rotation of both axes together; whatever part of it the drift map carries is a
    convention (S lower triangular keeps the d axis). Anchored, the candidate's mean angle error is the
    factory's at the same temperature, whatever the axes did."""
    return anchor_zeros([candidate], [factory], [locus], [drift])[0]


def anchor_zeros(
    candidates: list[Correction], factories: list[Correction], loci: list[BenchLocus], drifts: list[Drift]
) -> list[Correction]:
    """anchor_zero of several candidates (a refit's bands), their angles in one array pass."""
    if not candidates:
        return []
    # each band's bench locus at every whole degree, taken back through its drift: the field's locus
    designs = [_whole_degrees(locus.order) for locus in loci]
    points = [drift.inverse(m @ locus.d, m @ locus.q) for m, locus, drift in zip(designs, loci, drifts)]
    d, q = np.array([p[0] for p in points]), np.array([p[1] for p in points])
    diff = angles_of(factories, d, q) - angles_of(candidates, d, q)
    shifts = circular_mean(diff, axis=1)
    out = []
    for candidate, shift in zip(candidates, shifts):
        anchored = Correction(**{**candidate.__dict__, "harmonics": dict(candidate.harmonics)})
        anchored.zero_offset_rad = float(np.angle(np.exp(1j * (candidate.zero_offset_rad + shift))))
        out.append(anchored)
    return out


MODEL_DEGREE = 2  # drift terms as polynomials in temperature: the tempcos are linear with a small square
BENCH_PRIOR = 1e-4  # how far (rad) a term may have moved at the bench temperature since the bench (aging)
MODEL_REACH_C = 10.0  # a band this far beyond the fitted ones still gets the model's prediction


@dataclass
class TermModel:
    """One drift term against temperature: value and standard error anywhere, from a weighted fit."""

    coef: np.ndarray  # polynomial in (T - bench), highest power first
    cov: np.ndarray
    bench_c: float

    def at(self, temp_c: float) -> tuple[float, float]:
        x = float(temp_c) - self.bench_c
        basis = x ** np.arange(self.coef.size - 1, -1, -1)
        return float(basis @ self.coef), float(np.sqrt(max(basis @ self.cov @ basis, 0.0)))


@dataclass
class DriftModel:
    """The drift since the bench as a smooth function of temperature, from every band's fit at once.

    The physics (seed 000 eq. 4-5): each channel's gain and offset and each axis move with temperature as a
    line plus a small square, so every drift term does. One fit through all bands, with the bench as a soft
    point (no drift at its temperature, give or take aging), pools their samples: a term too small for one
    band's own error stands clear in the fit, and a band not yet visited (the first day, a new extreme) gets
    its terms from the bands on either side, or the slope, instead of no correction at all. Where the bands
    disagree with the curve more than their errors allow, the errors are scaled up by the misfit."""

    terms: dict[str, TermModel]
    temps: np.ndarray  # the fitted bands' temperatures

    @classmethod
    def fit(
        cls, fits: list[tuple[float, DriftFit]], bench_c: float, radius: float, *, bench_holds: bool = True
    ) -> DriftModel | None:
        """fits: (band temperature, drift fit) of the bands that have one; None with fewer than two. The bench
        point is left out when the bands say it no longer holds (a step since the bench), and when the caller
        knows it does not (bench_holds=False: the drift monitor named a step since; bands of a drive that
        dwells bound the drift too loosely to say so themselves)."""
        if len(fits) < 2:
            return None
        if not bench_holds:
            return cls._fit(fits, bench_c, radius, bench=False)
        with_bench = cls._fit(fits, bench_c, radius, bench=True)
        if with_bench is not None and with_bench._bench_consistent(fits, bench_c, radius):
            return with_bench
        return cls._fit(fits, bench_c, radius, bench=False)

    def _bench_consistent(self, fits, bench_c: float, radius: float) -> bool:
        without = self._fit(fits, bench_c, radius, bench=False)
        if without is None:
            return True
        for m in without.terms.values():
            value, err = m.at(bench_c)
            if abs(value) > 3.0 * np.hypot(err, BENCH_PRIOR):
                return False
        return True

    @classmethod
    def _fit(cls, fits, bench_c: float, radius: float, *, bench: bool) -> DriftModel | None:
        temps = np.array([t for t, _ in fits] + ([bench_c] if bench else [])) - bench_c
        degree = min(MODEL_DEGREE, max(len(temps) - 2, 1))  # a degree of freedom left to see misfit
        design = np.vander(temps, degree + 1)
        models = {}
        fitted = [f.drift.terms(radius) for _, f in fits]
        for name in TERMS:
            values = np.array([terms[name] for terms in fitted] + ([0.0] if bench else []))
            errors = np.array([f.errors[name] for _, f in fits] + ([BENCH_PRIOR] if bench else []))
            ok = np.isfinite(errors) & (errors > 0) & np.isfinite(values)
            rows, values, errors = design[ok], values[ok], errors[ok]
            if rows.shape[0] < rows.shape[1]:
                return None
            w = 1.0 / errors
            coef, *_ = np.linalg.lstsq(rows * w[:, None], values * w, rcond=None)
            try:
                cov = np.linalg.inv((rows * (w * w)[:, None]).T @ rows)
            except np.linalg.LinAlgError:
                return None
            dof = rows.shape[0] - rows.shape[1]
            if dof > 0:  # bands that disagree with the curve more than their errors allow: trust it less
                chi2 = float(np.sum(((rows @ coef - values) * w) ** 2) / dof)
                cov = cov * max(chi2, 1.0)
            models[name] = TermModel(coef=coef, cov=cov, bench_c=bench_c)
        # the bench is a point of the curve when it is in the fit: the model reaches the bands around it too
        return cls(terms=models, temps=np.array([t for t, _ in fits] + ([bench_c] if bench else [])))

    def reaches(self, temp_c: float) -> bool:
        return self.temps.min() - MODEL_REACH_C <= temp_c <= self.temps.max() + MODEL_REACH_C

    def at(self, temp_c: float) -> tuple[dict[str, float], dict[str, float]]:
        """Each term's value and standard error at a temperature."""
        out = {name: m.at(temp_c) for name, m in self.terms.items()}
        return {k: v for k, (v, _) in out.items()}, {k: e for k, (_, e) in out.items()}
