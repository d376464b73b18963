"""One correction form for every method, so an agent needs one function to apply any fit.

    u1 = w1·d + w2                       (seed 000, eq. 10)
    u2 = w3·q + w4 + w5·u1               (seed 000, eq. 11, plus a phase term w5)
    θ0 = atan2(u2, u1)
    θ  = θ0 + zero_offset + Σ_m (a_m·cos mθ0 + b_m·sin mθ0)

Seed 000's weights are the special case w5 = 0, no zero offset, no harmonics.
A set of corrections, one per temperature band, is interpolated linearly in temperature.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .physics import circular_mean, wrap_rad
from .samples import InputError


@dataclass
class Correction:
    w1: float = 1.0
    w2: float = 0.0
    w3: float = 1.0
    w4: float = 0.0
    w5: float = 0.0
    zero_offset_rad: float = 0.0
    harmonics: dict[int, tuple[float, float]] = field(default_factory=dict)  # m -> (a_m, b_m), rad
    temp_c: float | None = None  # temperature this correction was fitted at (band mean)
    # a factory band only: the bench locus it was measured on (encoder_core.differential.BenchLocus.to_dict()),
    # which reference-free refits use to tell drift since the bench from the field's own harmonics
    bench_locus: dict | None = None

    def angle(self, d, q) -> np.ndarray:
        d = np.asarray(d, dtype=float)
        q = np.asarray(q, dtype=float)
        u1 = self.w1 * d + self.w2
        u2 = self.w3 * q + self.w4 + self.w5 * u1
        theta0 = np.arctan2(u2, u1)
        return wrap_rad(theta0 + self.zero_offset_rad + harmonic_sum(theta0, self.harmonics))

    def to_dict(self) -> dict:
        out = {
            "w": [self.w1, self.w2, self.w3, self.w4],
            "w5": self.w5,
            "zero_offset_rad": self.zero_offset_rad,
            "harmonics": [[m, a, b] for m, (a, b) in sorted(self.harmonics.items())],
            "temp_c": self.temp_c,
        }
        if self.bench_locus is not None:
            out["bench_locus"] = self.bench_locus
        return out

    @classmethod
    def from_dict(cls, data: dict) -> Correction:
        w = data["w"]
        return cls(
            w1=float(w[0]),  # floats, as the harmonics: JSON may carry a coefficient as an integer of any size
            w2=float(w[1]),
            w3=float(w[2]),
            w4=float(w[3]),
            w5=float(data.get("w5", 0.0)),
            zero_offset_rad=float(data.get("zero_offset_rad", 0.0)),
            harmonics={int(m): (float(a), float(b)) for m, a, b in data.get("harmonics", [])},
            temp_c=data.get("temp_c"),
            bench_locus=data.get("bench_locus"),
        )

    def locus(self, n: int = 360) -> tuple[np.ndarray, np.ndarray]:
        """Raw (d, q) points that this correction maps onto the unit circle, evenly in θ0."""
        psi = np.arange(n) * (2 * np.pi / n)
        u1, u2 = np.cos(psi), np.sin(psi)
        d = (u1 - self.w2) / self.w1
        q = (u2 - self.w4 - self.w5 * u1) / self.w3
        return d, q

    def offsets_moved(self, delta_d: float, delta_q: float) -> Correction:
        """The same correction for channels whose offsets moved by (delta_d, delta_q) raw units: it reads the
        moved channels as this one read them before (a knocked magnet, a shifted sensor)."""
        out = Correction(**{**self.__dict__, "harmonics": dict(self.harmonics)})
        out.w2 = self.w2 - self.w1 * delta_d  # u1 = w1·(d - Δd) + w2
        out.w4 = self.w4 - self.w3 * delta_q  # u2 = w3·(q - Δq) + w4 + w5·u1
        return out

    def imbalance_moved(self, delta_imbalance: float) -> Correction:
        """The same correction for channels whose amplitude ratio log(d/q) moved by delta_imbalance: q is read
        scaled back about its offset (the angle sees only the ratio: moving d instead would read the same)."""
        out = Correction(**{**self.__dict__, "harmonics": dict(self.harmonics)})
        k = float(np.exp(delta_imbalance))  # q's amplitude grew by 1/k against d's
        out.w3, out.w4 = self.w3 * k, self.w4 * k  # u2 = k·w3·(q - centre_q) + w5·u1
        return out

    def axes_moved(self, delta_skew: float) -> Correction:
        """The same correction for a q axis turned towards d by asin(delta_skew) (the ellipse's skew moved by
        delta_skew): q now reads cosΔ·q - sinΔ·(its amplitude over d's)·d about the centre, and the correction
        takes the d part back out through w5 (its amplitudes per unit are w1 and w3's inverses, to first order)."""
        out = Correction(**{**self.__dict__, "harmonics": dict(self.harmonics)})
        turn = float(np.arcsin(delta_skew))
        out.w3, out.w4 = self.w3 / np.cos(turn), self.w4 / np.cos(turn)
        out.w5 = self.w5 + float(np.tan(turn))
        return out

    def params(self, orders: list[int]) -> np.ndarray:
        row = [self.w1, self.w2, self.w3, self.w4, self.w5, self.zero_offset_rad]
        for m in orders:
            a, b = self.harmonics.get(m, (0.0, 0.0))
            row += [a, b]
        return np.array(row)

    @classmethod
    def from_params(cls, p, orders: list[int], temp_c: float | None = None) -> Correction:
        """The correction whose params(orders) are p."""
        return cls(
            w1=p[0],
            w2=p[1],
            w3=p[2],
            w4=p[3],
            w5=p[4],
            zero_offset_rad=p[5],
            harmonics={m: (p[6 + 2 * i], p[7 + 2 * i]) for i, m in enumerate(orders)},
            temp_c=temp_c,
        )


def angles_of(corrections: list[Correction], d: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Correction.angle of several corrections in one array pass: row k of (K, n) d and q through correction k
    (a refit checks a candidate for every band around its circle)."""
    orders = sorted({m for c in corrections for m in c.harmonics})
    table = np.array([c.params(orders) for c in corrections]).reshape(len(corrections), -1)
    return _angle_of_columns(lambda k: table[:, k, None], orders, np.asarray(d, float), np.asarray(q, float))


def _angle_of_columns(column, orders: list[int], d: np.ndarray, q: np.ndarray) -> np.ndarray:
    """The correction form's angle with its parameters given as columns that broadcast against d and q: column(k)
    is parameter k of params(orders), per sample (BandedCorrection) or per row (angles_of)."""
    u1, u2 = _affine(column, d, q)
    theta0 = np.arctan2(u2, u1)
    harmonics = {m: (column(6 + 2 * i), column(7 + 2 * i)) for i, m in enumerate(orders)}
    return wrap_rad(theta0 + column(5) + harmonic_sum(theta0, harmonics))


def _affine(column, d: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """u1, u2 of the correction form with its parameters as columns: column(k) is w1..w5 for k = 0..4."""
    u1 = column(0) * d + column(1)
    return u1, column(2) * q + column(3) + column(4) * u1


def zero_shift(reference: Correction, other: Correction) -> float:
    """The rotation that makes `other` agree with `reference` on average around other's circle.

    A reference-free fit cannot see the zero; a factory calibration (made against a reference) can.
    Gain, offset and harmonic differences average out around the circle; a rotation does not."""
    d, q = other.locus()
    diff = reference.angle(d, q) - other.angle(d, q)
    return circular_mean(diff)


def harmonic_sum(theta0, harmonics: dict) -> np.ndarray:
    """Σ a_m cos(mθ) + b_m sin(mθ), a_m and b_m numbers or one per θ (a banded set's). The real part of the
    polynomial Σ (a_m - i·b_m)·z^m in z = e^{iθ}, by Horner's rule: one complex exponential instead of a cosine
    and a sine per order, and two operations per order (the refit evaluates sets on every band, the agent every
    sample)."""
    theta0 = np.asarray(theta0, dtype=float)
    if not all(isinstance(m, (int, np.integer)) and m >= 1 for m in harmonics):  # not harmonic orders: term by term
        total = np.zeros_like(theta0)
        for m, (a, b) in harmonics.items():
            total = total + a * np.cos(m * theta0) + b * np.sin(m * theta0)
        return total
    if not harmonics:
        return np.zeros_like(theta0)
    z = np.exp(1j * theta0)
    acc = 0.0
    for m in range(max(harmonics), 0, -1):
        if m in harmonics:
            a, b = harmonics[m]
            acc = acc + (a - 1j * b)
        acc = acc * z
    return np.real(acc) + np.zeros_like(theta0)  # the shape of θ even where the coefficients are numbers


def from_inverse_matrix(g: np.ndarray, offset: np.ndarray) -> Correction:
    """Correction for [cosθ, sinθ] = G·(p - offset), any G with det > 0.

    G = R(θz)·L with L lower-triangular (the QL-type split): L gives w1..w5, R the zero offset.
    """
    g = np.asarray(g, dtype=float)
    if not np.all(np.isfinite(g)) or np.linalg.det(g) <= 0:
        raise InputError("fitted channel map is singular or mirrored (are d and q swapped?)")
    lower = lower_factor(g.T @ g)
    rot = g @ np.linalg.inv(lower)
    theta_z = float(np.arctan2(rot[1, 0], rot[0, 0]))
    m11, m21, m22 = lower[0, 0], lower[1, 0], lower[1, 1]
    return Correction(w1=m11, w2=-m11 * offset[0], w3=m22, w4=-m22 * offset[1], w5=m21 / m11, zero_offset_rad=theta_z)


def lower_factor(qform: np.ndarray) -> np.ndarray:
    """Lower-triangular L with positive diagonal and L^T·L = qform (a 2x2 positive-definite form)."""
    q11, q12, q22 = qform[0, 0], qform[0, 1], qform[1, 1]
    if q22 <= 0:
        raise InputError("fitted quadratic form is not positive definite")
    m22 = np.sqrt(q22)
    m21 = q12 / m22
    rest = q11 - m21 * m21
    if rest <= 0:
        raise InputError("fitted quadratic form is not positive definite")
    return np.array([[np.sqrt(rest), 0.0], [m21, m22]])


@dataclass
class BandedCorrection:
    """Corrections at several temperatures, interpolated linearly between them (held flat outside)."""

    bands: list[Correction]
    # the die's lag behind the reported temperature (encoder_core/thermal.py): the agent reads the bands at its
    # die estimate, the reported temperature lagged by this; 0: at the reported temperature
    thermal_lag_s: float = 0.0

    def __post_init__(self):
        if not self.bands:
            raise InputError("no temperature band has a fit")
        if len(self.bands) > 1 and any(b.temp_c is None for b in self.bands):
            raise InputError("every band of a banded correction needs its temperature")
        self.bands = sorted(self.bands, key=lambda b: b.temp_c if b.temp_c is not None else 0.0)

    def offsets_moved(self, delta_d: float, delta_q: float) -> BandedCorrection:
        """The same set for channels whose offsets moved by (delta_d, delta_q) raw units at every temperature:
        what an offset step does (a knocked magnet, a shifted sensor), the rest of each band as it was."""
        return BandedCorrection([b.offsets_moved(delta_d, delta_q) for b in self.bands], self.thermal_lag_s)

    def at(self, temp_c: float) -> Correction:
        """The correction interpolated to one temperature."""
        return self.at_each([float(temp_c)])[0]

    def at_each(self, temps) -> list[Correction]:
        """The correction interpolated to each of several temperatures (one table for all: a refit's bands)."""
        temps = np.asarray(temps, float).reshape(-1)
        orders, column = self._columns(temps)
        params = np.column_stack([np.broadcast_to(column(k), temps.shape) for k in range(6 + 2 * len(orders))])
        return [Correction.from_params([float(v) for v in row], orders, float(t)) for row, t in zip(params, temps)]

    def angle(self, d, q, temp_c=None) -> np.ndarray:
        orders, column = self._columns(self._temps_for(d, temp_c))
        return _angle_of_columns(column, orders, np.asarray(d, float).ravel(), np.asarray(q, float).ravel())

    def radius(self, d, q, temp_c=None) -> np.ndarray:
        """|u| of the corrected point: 1 everywhere when the gains, offsets and phase are right."""
        _, column = self._columns(self._temps_for(d, temp_c))
        return np.hypot(*_affine(column, np.asarray(d, float).ravel(), np.asarray(q, float).ravel()))

    def _temps_for(self, d, temp_c) -> np.ndarray:
        n = np.asarray(d).size
        if temp_c is None:
            if len(self.bands) > 1:
                raise InputError("temperature is needed to pick among several temperature bands")
            return np.zeros(n)
        return np.broadcast_to(np.asarray(temp_c, dtype=float), (n,))

    def _columns(self, temps: np.ndarray):
        """(orders, column): column(k) is parameter k of params(orders) at each temperature, linear between bands and
        flat outside them (np.interp's rule). The bands either side of each temperature are found once, not once per
        parameter, and no samples × parameters table is built (a day of 20 Hz samples made one of ~500 MB)."""
        orders = sorted({m for b in self.bands for m in b.harmonics})
        table = np.array([b.params(orders) for b in self.bands])
        if len(self.bands) == 1:
            return orders, lambda k: table[0, k]
        centers = np.array([b.temp_c for b in self.bands], dtype=float)
        lo = np.clip(np.searchsorted(centers, temps, side="right") - 1, 0, centers.size - 2)
        span = centers[lo + 1] - centers[lo]
        with np.errstate(invalid="ignore", divide="ignore"):
            weight = np.clip((temps - centers[lo]) / np.where(span > 0, span, np.inf), 0.0, 1.0)
        return orders, lambda k: table[lo, k] * (1.0 - weight) + table[lo + 1, k] * weight

    def to_dict(self) -> dict:
        out: dict = {"bands": [b.to_dict() for b in self.bands]}
        if self.thermal_lag_s:
            out["thermal_lag_s"] = self.thermal_lag_s
        return out

    @classmethod
    def from_dict(cls, data: dict) -> BandedCorrection:
        return cls([Correction.from_dict(b) for b in data["bands"]], float(data.get("thermal_lag_s", 0.0)))
