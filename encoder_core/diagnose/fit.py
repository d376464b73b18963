"""Fitting one model (a `Spec`) to the training rows of a recording.

Stage A (d/q domain) maps each channel to the unit circle with a gain and an offset that depend on a
basis of the operating point:  x = (d - B·o_d)/(B·g_d),  y = (q - B·o_q)/(B·g_q),  B = [1, T]
(seed 000: linear in temperature; [1] without temperature; gain terms add columns). With a reference
angle it is a linear least-squares fit of d against cos θ_ref and q against sin θ_ref; without one it
is the same model fitted reference-free (radius = 1) by alternating least squares against the
model's own angle.

Stage B (residual domain) fits the angle terms' features to what stage A leaves in the error metric:
the angle error e = φ - θ_ref against a reference, the radius ripple ρ = |(x, y)| - 1 without one.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..physics import wrap_rad
from .data import RecordingData, local_deviation, outlier_threshold
from .terms import TERMS, Spec

RADIUS_ITERATIONS = 8


def solve(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Least squares through the normal equations, with a whisker of ridge for conditioning."""
    xtx = x.T @ x
    xty = x.T @ y
    try:
        return np.linalg.solve(xtx + 1e-12 * np.trace(xtx) / xtx.shape[0] * np.eye(xtx.shape[0]), xty)
    except np.linalg.LinAlgError:
        return np.linalg.lstsq(x, y, rcond=None)[0]


def basis(data: RecordingData, spec: Spec) -> tuple[np.ndarray, list[str]]:
    """Stage A's basis of the operating point, and its columns' names."""
    cols = [("1", np.ones(data.n))]
    tn = data.temp_n(spec.tau_s)
    if tn is not None:
        cols.append(("T", tn))
    for name, _ in spec.terms:
        cols += TERMS[name].basis_columns(data, tn)
    return np.column_stack([c for _, c in cols]), [n for n, _ in cols]


@dataclass
class StageA:
    coef_d: np.ndarray  # [gains over basis, offsets over basis]
    coef_q: np.ndarray
    x: np.ndarray  # corrected channels for every sample (from a fit on the training rows)
    y: np.ndarray
    basis_names: list[str]
    memo: dict = field(default_factory=dict)  # target, angle and features computed from x, y

    def get(self, key, make):
        if key not in self.memo:
            self.memo[key] = make()
        return self.memo[key]


def fit_stage_a(data: RecordingData, spec: Spec, train: np.ndarray, phi0: np.ndarray | None) -> StageA:
    b, names = basis(data, spec)
    k = b.shape[1]
    btr = b[train]
    dtr, qtr = data.d[train], data.q[train]

    def fit(c, s):
        cd = solve(np.hstack([btr * c[:, None], btr]), dtr)
        cq = solve(np.hstack([btr * s[:, None], btr]), qtr)
        return cd, cq

    def apply(cd, cq, rows=slice(None)):
        br = b[rows]
        gd, od = br @ cd[:k], br @ cd[k:]
        gq, oq = br @ cq[:k], br @ cq[k:]
        return (data.d[rows] - od) / gd, (data.q[rows] - oq) / gq

    if data.ref is not None:
        cd, cq = fit(np.cos(data.ref[train]), np.sin(data.ref[train]))
    else:
        phi = phi0[train] if phi0 is not None else conic_angle(dtr, qtr)
        iterations = RADIUS_ITERATIONS if phi0 is None else 3
        for _ in range(iterations):
            cd, cq = fit(np.cos(phi), np.sin(phi))
            xt, yt = apply(cd, cq, train)
            phi = np.arctan2(yt, xt)
    x, y = apply(cd, cq)
    for name, _ in spec.terms:
        x, y = TERMS[name].repair(data, x, y)
    return StageA(cd, cq, x, y, names)


def conic_angle(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The angle on a direct fit of an axis-aligned ellipse, a·x² + c·y² + d·x + e·y = 1: where the
    reference-free iteration starts. From atan2 of the raw channels it needs dozens of rounds when few
    angles are visited, or unevenly (a short jig recording); from here it needs two or three."""
    (a, c, d, e), *_ = np.linalg.lstsq(np.column_stack([x * x, y * y, x, y]), np.ones_like(x), rcond=None)
    if not (a > 0 and c > 0):
        return np.arctan2(y, x)  # not an ellipse: the raw angle is as good a start as any
    x0, y0 = -d / (2 * a), -e / (2 * c)
    g = 1 + a * x0 * x0 + c * y0 * y0
    return np.arctan2((y - y0) * np.sqrt(c / g), (x - x0) * np.sqrt(a / g))


def target(data: RecordingData, sa: StageA) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The error metric before stage B (rad), the corrected angle, and the radius deviation."""

    def make():
        phi = np.arctan2(sa.y, sa.x)
        radius = np.hypot(sa.x, sa.y) - 1.0
        e = wrap_rad(phi - data.ref) if data.ref is not None else radius
        return e, phi, radius

    return sa.get("target", make)


@dataclass
class Fit:
    stage_a: StageA
    names: list[str]  # stage B's features
    coef: np.ndarray
    err: np.ndarray  # residual (rad) after stage B for every sample
    reject: np.ndarray  # samples the model rejects (outliers)

    def coefficient(self, name: str) -> float:
        return float(self.coef[self.names.index(name)]) if name in self.names else 0.0


def fit_model(
    data: RecordingData,
    spec: Spec,
    train: np.ndarray,
    phi0=None,
    stage_a: StageA | None = None,
    judge: np.ndarray | None = None,
) -> Fit:
    """Fit `spec` on the rows `train` (less the samples no fit may use) and apply it to every row.
    Rejection rules are judged on the rows `judge` (default: all), the held-out rows in cross-validation."""
    train = train & ~data.unfit
    if stage_a is None:
        stage_a = fit_stage_a(data, spec, train, phi0)
    e, phi, radius = target(data, stage_a)
    feats = [f for name, arg in spec.terms for f in TERMS[name].features(data, spec, arg, stage_a, phi)]
    names = [f[0] for f in feats]
    if feats:
        f = np.column_stack([v for _, v in feats])
        coef = solve(f[train], e[train])
        e = e - f @ coef
    else:
        coef = np.zeros(0)
    for name, _ in spec.terms:
        e = TERMS[name].settle_error(data, e)
    judge = np.ones(data.n, bool) if judge is None else judge
    reject = np.zeros(data.n, bool)
    for name, _ in spec.terms:
        r = TERMS[name].rejected(data, stage_a, phi, radius, judge)
        if r is not None:
            reject[judge] |= r
    return Fit(stage_a, names, coef, e, reject)


def flag_suspects(data: RecordingData) -> None:
    """Robust baseline: fit on everything not clipped, mark isolated samples far off the circle as
    suspect, so that no later fit uses them (whether or not they become a finding)."""
    fit = fit_model(data, Spec(), np.ones(data.n, bool))
    _, phi, radius = target(data, fit.stage_a)
    dev = local_deviation(radius, phi, data.dropped)
    far = np.abs(dev) > outlier_threshold(dev[~data.clipped & ~data.dropped])
    isolated = far & ~np.roll(far, 1) & ~np.roll(far, -1)
    data.suspect = isolated & ~data.clipped
