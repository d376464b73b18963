"""Diagnose a recording: fit seed 000's baseline, find what it misses, name the cause, measure the gain.

Pure numpy: no file I/O, no printing. `diagnose(samples)` returns a `Diagnosis` whose `report` is the
"Diagnose JSON" contract of docs/architecture.md and whose `plots` holds the arrays the HTML report draws.

The model has two stages.

Stage A (d/q domain) maps each channel to the unit circle with a gain and an offset that depend on a
basis of the operating point:  x = (d - B·o_d)/(B·g_d),  y = (q - B·o_q)/(B·g_q),  B = [1, T]
(seed 000: linear in temperature; [1] without temperature). With a reference angle it is a linear
least-squares fit of d against cos θ_ref and q against sin θ_ref; without one it is the same model
fitted reference-free (radius = 1) by alternating least squares against the model's own angle.
Three causes change stage A: thermal_lag (T replaced by T lagged first-order with τ),
nonlinear_temperature (T² joins B) and aging (operating time joins B).

Stage B (residual domain) models what stage A leaves in the error metric as a linear sum of features
of the corrected angle φ = atan2(y, x) and the temperature:

    metric "reference": e = φ - θ_ref              metric "radius": ρ = |(x, y)| - 1
    zero_offset             1                           (not testable)
    phase_nonorthogonality  sin²φ   (e = β·sin²φ)       sin 2φ   (ρ = -β/2·sin 2φ)
    phase_drift             ΔT·sin²φ                    ΔT·sin 2φ
    harmonic order n        cos, sin (n-1)φ             cos, sin (n-1)φ, n >= 4

(order 2 shows as an offset and order 3 as a phase or gain imbalance on the locus, so without a
reference only orders >= 4 are identifiable). Two causes act on samples: adc_clipping (a channel
stuck at a rail is rebuilt from the other channel and radius 1) and outliers (samples far off the
circle are rejected).

A cause is named only when adding it to the model cuts the held-out RMS error by at least
`MIN_GAIN` (greedy forward selection; among terms within `PARSIMONY` of the best, the one with the
fewest parameters is taken, because the terms overlap: zero offset + phase spans what phase + a 3rd
harmonic spans). The outlier rule needs no reference: a sample whose radius, less the median of its
angle bin and its running median in time, lies beyond 8 robust sigmas and twice the 95th percentile
is rejected (and left out of the error). Held-out means leave-one-run-out when the recording has a
`run` column with several runs, else contiguous time blocks. Samples that are stuck at a rail or
isolated far off the circle never enter a fit (robust fitting), whether or not they become findings.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.ndimage import median_filter

from .physics import REFERENCE_TEMP_C, wrap_rad
from .samples import InputError, Samples, check_angle_coverage, check_fit_input
from .simulator import first_order_lag

MIN_SAMPLES = 64
MIN_GAIN = 0.10  # a term must cut the held-out RMS by 10 % to be named
T_SCALE = 50.0  # °C: temperature is used as (T - 20)/50 for conditioning
MIN_TEMP_SPAN_C = 5.0
OUTLIER_SIGMAS = 8.0
OUTLIER_FLOOR = 0.01  # radius deviation (fraction of the radius) below which nothing is an outlier
MAX_OUTLIER_FRACTION = 0.05
RADIUS_ITERATIONS = 8
PARSIMONY = 0.03
MAX_FOLDS = 5
N_PARAMS = {
    "adc_clipping": 0,
    "zero_offset": 1,
    "phase_nonorthogonality": 1,
    "phase_drift": 1,
    "thermal_lag": 1,
    "outliers": 1,
    "harmonic_distortion": 2,
    "nonlinear_temperature": 4,
    "aging": 4,
}
REF_ORDERS = tuple(range(2, 9))
RADIUS_ORDERS = tuple(range(4, 9))

CAUSES = (
    "zero_offset",
    "phase_nonorthogonality",
    "phase_drift",
    "harmonic_distortion",
    "thermal_lag",
    "nonlinear_temperature",
    "aging",
    "outliers",
    "adc_clipping",
)


@dataclass(frozen=True)
class Spec:
    """Which extension terms a model carries on top of the baseline."""

    tau_s: float = 0.0
    nonlinear: bool = False
    aging: bool = False
    zero: bool = False
    phase: bool = False
    drift: bool = False
    orders: tuple[int, ...] = ()
    outliers: bool = False
    clipping: bool = False

    def stage_a_key(self) -> tuple:
        return (round(self.tau_s, 6), self.nonlinear, self.aging, self.clipping)

    def causes(self) -> list[str]:
        out = []
        if self.zero:
            out.append("zero_offset")
        if self.phase:
            out.append("phase_nonorthogonality")
        if self.drift:
            out.append("phase_drift")
        out += ["harmonic_distortion"] * len(self.orders)
        if self.tau_s > 0:
            out.append("thermal_lag")
        if self.nonlinear:
            out.append("nonlinear_temperature")
        if self.aging:
            out.append("aging")
        if self.outliers:
            out.append("outliers")
        if self.clipping:
            out.append("adc_clipping")
        return out


@dataclass
class Diagnosis:
    report: dict  # the Diagnose JSON contract
    plots: dict = field(default_factory=dict)  # arrays for the HTML report
    spec: Spec = field(default_factory=Spec)  # the extended model's terms (for `measure`)


@dataclass
class _Eval:
    err_deg: np.ndarray  # held-out error per sample (NaN where rejected)
    rms: float
    max: float
    rejected: int = 0


# --- preparing the data -------------------------------------------------------------------------


class _Data:
    """Normalised arrays, folds and per-sample flags: everything the fits share."""

    def __init__(self, samples: Samples):
        n = len(samples)
        if n < MIN_SAMPLES:
            raise InputError(f"too few samples to diagnose: {n}, need at least {MIN_SAMPLES}")
        check_fit_input(
            samples.d, samples.q, min_samples=MIN_SAMPLES, theta_ref=samples.theta_ref, temp_c=samples.temp_c
        )
        self.samples = samples
        self.n = n
        self.t = np.asarray(samples.t, float)
        self.center = np.array([np.median(samples.d), np.median(samples.q)])
        amp = np.sqrt(np.mean((samples.d - self.center[0]) ** 2 + (samples.q - self.center[1]) ** 2))
        if not amp > 0:
            raise InputError("d and q do not vary: nothing to fit")
        self.scale = float(amp)
        self.d = (samples.d - self.center[0]) / self.scale
        self.q = (samples.q - self.center[1]) / self.scale
        self.ref = None if samples.theta_ref is None else np.asarray(samples.theta_ref, float)
        if self.ref is not None:
            check_angle_coverage(self.ref, what="reference angle (theta_ref_deg)")
        else:
            check_angle_coverage(np.arctan2(self.q, self.d), what="d/q angle")
        self.temp = None if samples.temp_c is None else np.asarray(samples.temp_c, float)
        self.temp_span = 0.0 if self.temp is None else float(np.ptp(self.temp))
        self.span_s = float(self.t[-1] - self.t[0]) if n > 1 else 0.0
        self.age = (self.t - self.t[0]) / self.span_s if self.span_s > 0 else np.zeros(n)
        self.rate = self._temp_rate()
        self.folds, self.fold_kind = self._folds(samples)
        self.fold_ids = np.unique(self.folds)
        self._lagged: dict[float, np.ndarray] = {}
        self.clip_d, self.clip_q, self.clip_info = self._clipping(samples)
        self.clipped = self.clip_d | self.clip_q
        self.suspect = np.zeros(n, bool)  # set after the baseline: isolated samples far off the circle

    @property
    def metric(self) -> str:
        return "reference" if self.ref is not None else "radius"

    def temp_n(self, tau_s: float) -> np.ndarray | None:
        """(T - 20)/50 with T lagged first-order by tau (the die temperature model)."""
        if self.temp is None or self.temp_span == 0:
            return None  # no temperature, or one that never changes: gains and offsets are constants
        key = round(float(tau_s), 6)
        if key not in self._lagged:
            tt = first_order_lag(self.t, self.temp, key) if key > 0 else self.temp
            self._lagged[key] = (tt - REFERENCE_TEMP_C) / T_SCALE
            if len(self._lagged) > 64:
                self._lagged.pop(next(iter(self._lagged)))
        return self._lagged[key]

    def _temp_rate(self) -> np.ndarray | None:
        """dT/dt in °C/min from a centred difference over ±60 s (robust to a noisy sensor)."""
        if self.temp is None:
            return None
        w = 60.0
        ahead = np.interp(self.t + w, self.t, self.temp)
        behind = np.interp(self.t - w, self.t, self.temp)
        span = np.minimum(self.t + w, self.t[-1]) - np.maximum(self.t - w, self.t[0])
        return np.where(span > 0, (ahead - behind) / np.where(span > 0, span, 1.0) * 60.0, 0.0)

    def _folds(self, samples: Samples) -> tuple[np.ndarray, str]:
        if samples.run is not None:
            runs = np.unique(samples.run)
            if 3 <= runs.size <= 50:
                counts = np.array([np.count_nonzero(samples.run == r) for r in runs])
                folds = np.searchsorted(runs, samples.run) % MAX_FOLDS  # many runs: several per fold
                if counts.min() >= 8 and self._folds_span_temperature(folds):
                    return folds, "run"
        blocks = np.minimum((np.arange(self.n) * 8) // self.n, 7)
        return blocks % 4, "time block"

    def _folds_span_temperature(self, folds: np.ndarray) -> bool:
        """Leaving a fold out must not leave a fit that only saw part of the temperature range."""
        if self.temp is None or self.temp_span < MIN_TEMP_SPAN_C:
            return True
        return all(np.ptp(self.temp[folds != f]) >= 0.5 * self.temp_span for f in np.unique(folds))

    def _clipping(self, samples: Samples):
        """Channels stuck at one extreme value while the other channel keeps moving."""
        n = self.n
        clip = {"d": np.zeros(n, bool), "q": np.zeros(n, bool)}
        info = []
        raw = {"d": np.asarray(samples.d, float), "q": np.asarray(samples.q, float)}
        norm = {"d": self.d, "q": self.q}
        for name, other in (("d", "q"), ("q", "d")):
            for value in (raw[name].max(), raw[name].min()):
                at = raw[name] == value
                count = int(at.sum())
                if count < max(5, 0.0005 * n):
                    continue
                moving = norm[other][at]
                if np.unique(np.round(moving, 6)).size >= 5 and np.ptp(moving) > 0.1:
                    clip[name] |= at
                    info.append({"channel": name, "value": float(value), "samples": count})
        if samples.halls is not None:
            for key, arr in samples.halls.items():
                arr = np.asarray(arr, float)
                at = (arr <= 0) | (arr >= 4095)
                if at.sum() >= max(5, 0.0005 * n):
                    chan = "q" if key.startswith("a_") else "d"
                    clip[chan] |= at
                    info.append({"channel": key, "value": "rail", "samples": int(at.sum())})
        return clip["d"], clip["q"], info


# --- stage A ------------------------------------------------------------------------------------


def _basis(data: _Data, spec: Spec) -> np.ndarray:
    cols = [np.ones(data.n)]
    tn = data.temp_n(spec.tau_s)
    if tn is not None:
        cols.append(tn)
        if spec.nonlinear:
            cols.append(tn * tn)
    if spec.aging:
        cols.append(data.age)
    return np.column_stack(cols)


def _solve(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    xtx = x.T @ x
    xty = x.T @ y
    try:
        return np.linalg.solve(xtx + 1e-12 * np.trace(xtx) / xtx.shape[0] * np.eye(xtx.shape[0]), xty)
    except np.linalg.LinAlgError:
        return np.linalg.lstsq(x, y, rcond=None)[0]


@dataclass
class _StageA:
    coef_d: np.ndarray  # [gains over basis, offsets over basis]
    coef_q: np.ndarray
    x: np.ndarray  # corrected channels for every sample (from a fit on the training rows)
    y: np.ndarray
    memo: dict = field(default_factory=dict)  # target, angle and features computed from x, y

    def get(self, key, make):
        if key not in self.memo:
            self.memo[key] = make()
        return self.memo[key]


def _stage_a(data: _Data, spec: Spec, train: np.ndarray, basis: np.ndarray, phi0: np.ndarray | None) -> _StageA:
    k = basis.shape[1]
    btr = basis[train]
    dtr, qtr = data.d[train], data.q[train]

    def fit(c, s):
        cd = _solve(np.hstack([btr * c[:, None], btr]), dtr)
        cq = _solve(np.hstack([btr * s[:, None], btr]), qtr)
        return cd, cq

    def apply(cd, cq, rows=slice(None)):
        b = basis[rows]
        gd, od = b @ cd[:k], b @ cd[k:]
        gq, oq = b @ cq[:k], b @ cq[k:]
        return (data.d[rows] - od) / gd, (data.q[rows] - oq) / gq

    if data.ref is not None:
        cd, cq = fit(np.cos(data.ref[train]), np.sin(data.ref[train]))
    else:
        phi = phi0[train] if phi0 is not None else np.arctan2(qtr, dtr)
        iterations = RADIUS_ITERATIONS if phi0 is None else 3
        for _ in range(iterations):
            cd, cq = fit(np.cos(phi), np.sin(phi))
            xt, yt = apply(cd, cq, train)
            phi = np.arctan2(yt, xt)
    x, y = apply(cd, cq)
    if spec.clipping:
        x, y = _repair_clipping(data, x, y)
    return _StageA(cd, cq, x, y)


def _repair_clipping(data: _Data, x, y):
    """A channel stuck at a rail is rebuilt from the other one: the point lies on the unit circle."""
    x, y = x.copy(), y.copy()
    m = data.clip_d & ~data.clip_q
    x[m] = np.sign(x[m]) * np.sqrt(np.clip(1 - y[m] ** 2, 0, None))
    m = data.clip_q & ~data.clip_d
    y[m] = np.sign(y[m]) * np.sqrt(np.clip(1 - x[m] ** 2, 0, None))
    return x, y


# --- stage B ------------------------------------------------------------------------------------


def _features(data: _Data, spec: Spec, sa: _StageA) -> list[tuple[str, np.ndarray]]:
    ref = data.metric == "reference"
    phi = _target(data, sa)[1]
    feats = []
    if spec.zero and ref:
        feats.append(("zero", sa.get("one", lambda: np.ones_like(phi))))
    shape = sa.get("shape", lambda: np.sin(phi) ** 2 if ref else np.sin(2 * phi))
    if spec.phase:
        feats.append(("phase", shape))
    if spec.drift and data.temp is not None:
        feats.append(("drift", sa.get(("drift", spec.tau_s), lambda: data.temp_n(spec.tau_s) * shape)))
    for n in spec.orders:
        m = n - 1
        feats.append((f"h{n}c", sa.get(f"h{n}c", lambda m=m: np.cos(m * phi))))
        feats.append((f"h{n}s", sa.get(f"h{n}s", lambda m=m: np.sin(m * phi))))
    return feats


def _target(data: _Data, sa: _StageA) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The error metric before stage B (rad), the corrected angle, and the radius deviation."""

    def make():
        phi = np.arctan2(sa.y, sa.x)
        radius = np.hypot(sa.x, sa.y) - 1.0
        e = wrap_rad(phi - data.ref) if data.ref is not None else radius
        return e, phi, radius

    return sa.get("target", make)


def _local_deviation(radius: np.ndarray, phi: np.ndarray, bins: int = 64) -> np.ndarray:
    """What of the radius neither angle nor time explains: minus its median in the sample's angle bin
    (64 bins), then minus its running median over 11 samples in time. Harmonics, phase and slow drifts
    (temperature, lag, aging) cancel; an isolated corrupted sample stands out."""
    idx = np.minimum(((phi % (2 * np.pi)) * (bins / (2 * np.pi))).astype(int), bins - 1)
    order = np.lexsort((radius, idx))
    starts = np.searchsorted(idx[order], np.arange(bins + 1))
    med = np.zeros(bins)
    for b in range(bins):
        lo, hi = starts[b], starts[b + 1]
        if hi > lo:
            med[b] = radius[order[(lo + hi - 1) // 2]]
    r = radius - med[idx]
    return r - median_filter(r, size=11, mode="nearest")


def _outlier_threshold(dev: np.ndarray) -> float:
    """Beyond 8 robust sigmas, beyond twice the 95th percentile (so that a systematic effect spread
    over more than 5 % of the samples never counts), and beyond 1 % of the radius."""
    p95 = float(np.percentile(np.abs(dev), 95)) if dev.size else 0.0
    return max(OUTLIER_SIGMAS * _robust_sigma(dev), 2.0 * p95, OUTLIER_FLOOR)


def _robust_sigma(v: np.ndarray) -> float:
    v = v[np.isfinite(v)]
    if v.size == 0:
        return 0.0
    return float(1.4826 * np.median(np.abs(v - np.median(v))))


@dataclass
class _Fit:
    stage_a: _StageA
    names: list[str]
    coef: np.ndarray
    err: np.ndarray  # residual (rad) after stage B for every sample
    reject: np.ndarray  # samples the outlier rule rejects
    threshold: float


def _fit_model(data: _Data, spec: Spec, train: np.ndarray, phi0=None, stage_a: _StageA | None = None) -> _Fit:
    train = train & ~data.suspect & ~data.clipped
    if stage_a is None:
        stage_a = _stage_a(data, spec, train, _basis(data, spec), phi0)
    e, phi, radius = _target(data, stage_a)
    feats = _features(data, spec, stage_a)
    names = [f[0] for f in feats]
    if feats:
        f = np.column_stack([v for _, v in feats])
        coef = _solve(f[train], e[train])
        e = e - f @ coef
    else:
        coef = np.zeros(0)
    if spec.clipping and data.ref is None:
        # a rebuilt sample lies on the model's circle by construction: no radius error left to correct
        e = np.where(data.clip_d ^ data.clip_q, 0.0, e)
    reject = np.zeros(data.n, bool)
    threshold = np.inf
    if spec.outliers:
        # the rule needs no reference: any stream can apply it to its own radius (test rows: in __call__)
        dev = stage_a.get("local_dev", lambda: _local_deviation(radius, phi))
        threshold = _outlier_threshold(dev[~data.clipped])
        reject = (np.abs(dev) > threshold) & ~data.clipped  # clipped samples are adc_clipping's
    return _Fit(stage_a, names, coef, e, reject, threshold)


# --- held-out evaluation -------------------------------------------------------------------------


class _Evaluator:
    def __init__(self, data: _Data, phi0_by_fold: dict | None = None):
        self.data = data
        self.phi0 = phi0_by_fold or {}
        self._cache: dict = {}
        self.calls = 0

    def stage_a_for(self, spec: Spec, fold) -> _StageA:
        key = (spec.stage_a_key(), int(fold))
        if key not in self._cache:
            train = (self.data.folds != fold) & ~self.data.suspect & ~self.data.clipped
            self._cache[key] = _stage_a(self.data, spec, train, _basis(self.data, spec), self.phi0.get(int(fold)))
            while len(self._cache) > 3 * len(self.data.fold_ids):
                self._cache.pop(next(iter(self._cache)))
        return self._cache[key]

    def __call__(self, spec: Spec) -> _Eval:
        self.calls += 1
        data = self.data
        err = np.full(data.n, np.nan)
        rejected = 0
        for fold in data.fold_ids:
            test = data.folds == fold
            fit = _fit_model(data, spec, ~test, stage_a=self.stage_a_for(spec, fold))
            e = fit.err[test]
            r = fit.reject[test]
            if spec.outliers:
                dev = fit.stage_a.memo["local_dev"][test]
                r = (np.abs(dev) > _outlier_threshold(dev[~data.clipped[test]])) & ~data.clipped[test]
            rejected += int(r.sum())
            e = np.where(r, np.nan, e)
            err[test] = e
        err_deg = np.degrees(err)
        ok = np.isfinite(err_deg)
        rms = float(np.sqrt(np.mean(err_deg[ok] ** 2))) if ok.any() else float("nan")
        mx = float(np.max(np.abs(err_deg[ok]))) if ok.any() else float("nan")
        return _Eval(err_deg, rms, mx, rejected)


# --- the diagnosis ----------------------------------------------------------------------------------


def _testable(data: _Data) -> tuple[list[str], list[dict]]:
    not_testable = []
    if data.ref is None:
        not_testable.append(
            {
                "cause": "zero_offset",
                "why": "no theta_ref_deg column: a constant angle offset "
                "moves every sample along the circle and leaves no trace in d and q",
            }
        )
    if data.temp is None:
        for cause in ("phase_drift", "thermal_lag", "nonlinear_temperature"):
            not_testable.append({"cause": cause, "why": "no temp_c column: nothing thermal can be seen"})
    elif data.temp_span < MIN_TEMP_SPAN_C:
        for cause in ("phase_drift", "thermal_lag", "nonlinear_temperature"):
            not_testable.append(
                {"cause": cause, "why": f"temp_c spans only {data.temp_span:.1f} °C (need {MIN_TEMP_SPAN_C:.0f} °C)"}
            )
    if data.span_s <= 0:
        not_testable.append({"cause": "aging", "why": "the recording has no duration"})
    blocked = {item["cause"] for item in not_testable}
    testable = [c for c in CAUSES if c not in blocked]
    return testable, not_testable


def _candidates(data: _Data, spec: Spec, testable: list[str]) -> list[tuple[str, Spec]]:
    out = []
    ref = data.metric == "reference"
    if "zero_offset" in testable and not spec.zero:
        out.append(("zero_offset", replace(spec, zero=True)))
    if not spec.phase:
        out.append(("phase_nonorthogonality", replace(spec, phase=True)))
    if "phase_drift" in testable and not spec.drift:
        out.append(("phase_drift", replace(spec, drift=True)))
    for n in REF_ORDERS if ref else RADIUS_ORDERS:
        if n not in spec.orders and n * 2 < _distinct_angles(data):
            out.append(("harmonic_distortion", replace(spec, orders=tuple(sorted(spec.orders + (n,))))))
    if "nonlinear_temperature" in testable and not spec.nonlinear:
        out.append(("nonlinear_temperature", replace(spec, nonlinear=True)))
    if "aging" in testable and not spec.aging:
        out.append(("aging", replace(spec, aging=True)))
    if not spec.outliers:
        out.append(("outliers", replace(spec, outliers=True)))
    if data.clipped.any() and not spec.clipping:
        out.append(("adc_clipping", replace(spec, clipping=True)))
    return out


def _distinct_angles(data: _Data) -> int:
    if not hasattr(data, "_n_angles"):
        src = data.ref if data.ref is not None else np.arctan2(data.q, data.d)
        data._n_angles = int(np.unique(np.round(np.degrees(src % (2 * np.pi)), 1)).size)
    return data._n_angles


def _best_tau(data: _Data, spec: Spec, evaluate: _Evaluator, around: float | None, step) -> tuple[float, _Eval]:
    """Scan τ on a log grid (then refine) for the best held-out fit with T lagged by τ."""
    dt = np.median(np.diff(data.t))
    lo = max(dt, 1.0)
    hi = max(data.span_s / 4, lo * 2)
    if around:
        grid = around * np.geomspace(0.5, 2.0, 5)
    else:
        grid = np.geomspace(lo, hi, 14)
    results = {}
    for tau in grid:
        step()
        results[float(tau)] = evaluate(replace(spec, tau_s=float(tau)))
    for _ in range(2):  # refine around the best: parabola in log τ through three neighbours
        taus = sorted(results)
        best = min(taus, key=lambda k: results[k].rms)
        i = taus.index(best)
        if 0 < i < len(taus) - 1:
            x = np.log(taus[i - 1 : i + 2])
            yv = np.array([results[k].rms for k in taus[i - 1 : i + 2]])
            a, b, _ = np.polyfit(x, yv, 2)
            if a > 0:
                tau = float(np.exp(np.clip(-b / (2 * a), x[0], x[2])))
                if all(abs(np.log(tau / k)) > 1e-3 for k in taus):
                    step()
                    results[tau] = evaluate(replace(spec, tau_s=tau))
    best = min(results, key=lambda k: results[k].rms)
    return best, results[best]


def diagnose(samples: Samples, *, on_step: Callable[[str], None] | None = None) -> Diagnosis:
    """Fit the baseline, name what it misses, and measure every gain on held-out data."""
    step_cb = on_step or (lambda _name: None)
    data = _Data(samples)
    testable, not_testable = _testable(data)

    base_spec = Spec()
    # robust baseline: fit on everything not clipped, flag isolated samples far off the circle, refit
    full = np.ones(data.n, bool)
    base_fit = _fit_model(data, base_spec, full)
    _, base_phi, base_radius = _target(data, base_fit.stage_a)
    dev = _local_deviation(base_radius, base_phi)
    thr = _outlier_threshold(dev[~data.clipped])
    far = np.abs(dev) > thr
    isolated = far & ~np.roll(far, 1) & ~np.roll(far, -1)
    data.suspect = isolated & ~data.clipped
    phi0 = {}
    if data.ref is None:
        for fold in data.fold_ids:
            train = (data.folds != fold) & ~data.suspect & ~data.clipped
            a = _stage_a(data, base_spec, train, _basis(data, base_spec), None)
            phi0[int(fold)] = np.arctan2(a.y, a.x)
    evaluate = _Evaluator(data, phi0)

    step_cb("baseline")
    baseline = evaluate(base_spec)
    current, cur_eval = base_spec, baseline
    findings_order: list = []
    tau_hint = None
    while True:
        options = []
        for name, cand in _candidates(data, current, testable):
            step_cb(name)
            options.append((name, cand, evaluate(cand)))
        if "thermal_lag" in testable and current.tau_s == 0:
            tau, ev = _best_tau(data, current, evaluate, tau_hint, lambda: step_cb("thermal_lag"))
            tau_hint = tau
            options.append(("thermal_lag", replace(current, tau_s=tau), ev))
        accepted = []
        for name, cand, ev in options:
            if not (ev.rms < (1 - MIN_GAIN) * cur_eval.rms):
                continue
            if name == "outliers":
                frac = ev.rejected / data.n
                if frac > MAX_OUTLIER_FRACTION or ev.rejected < 3:
                    continue
            accepted.append((ev.rms, name, cand, ev))
        if not accepted:
            break
        # the best, but among terms within 3 % of it the one with the fewest parameters: the terms
        # overlap (zero offset + phase spans what phase + a 3rd harmonic spans), parsimony decides
        best = min(a[0] for a in accepted)
        near = [a for a in accepted if a[0] <= best * (1 + PARSIMONY)]
        _, name, cand, ev = min(near, key=lambda a: (N_PARAMS[a[1]], a[0]))
        findings_order.append((name, cand, cur_eval, ev, sorted(set(cand.orders) - set(current.orders))))
        current, cur_eval = cand, ev
        if current.tau_s > 0 and name != "thermal_lag":
            # the other terms changed: let τ settle again
            tau, ev2 = _best_tau(data, current, evaluate, current.tau_s, lambda: step_cb("thermal_lag"))
            if ev2.rms < cur_eval.rms:
                current, cur_eval = replace(current, tau_s=tau), ev2
                findings_order[-1] = (name, current, findings_order[-1][2], ev2, findings_order[-1][4])

    final = _fit_model(data, current, full)
    findings = []
    for name, _cand, before, after, new_orders in findings_order:
        params, evidence = _describe(name, new_orders, current, final, data, baseline, before, after)
        findings.append(
            {
                "cause": name,
                "parameters": params,
                "evidence": evidence,
                "rms_error_deg_before": round(before.rms, 6),
                "rms_error_deg_after": round(after.rms, 6),
            }
        )
    base_model = (
        "per-axis gain and offset, each linear in temperature (seed 000)"
        if data.temp is not None
        else "per-axis gain and offset, constant (no temperature recorded)"
    )
    base_model += (
        ", fitted against the reference angle" if data.ref is not None else ", fitted reference-free (radius = 1)"
    )
    report = {
        "samples": data.n,
        "has_reference": data.ref is not None,
        "error_metric": data.metric,
        "baseline": {
            "model": base_model,
            "rms_error_deg": round(baseline.rms, 6),
            "max_error_deg": round(baseline.max, 6),
        },
        "findings": findings,
        "extended": {
            "causes": [f["cause"] for f in findings],
            "rms_error_deg": round(cur_eval.rms, 6),
            "max_error_deg": round(cur_eval.max, 6),
        },
        "not_testable": not_testable,
        "held_out": {"by": data.fold_kind, "folds": int(data.fold_ids.size)},
    }
    if data.metric == "radius" and not any(f["cause"] == "harmonic_distortion" for f in not_testable):
        not_testable.append(
            {
                "cause": "harmonic_distortion",
                "why": "orders 2 and 3 only: without a reference "
                "order 2 looks like an offset and order 3 like gain or phase imbalance "
                "(orders 4-8 were tested)",
            }
        )
    phi = np.degrees(np.arctan2(final.stage_a.y, final.stage_a.x)) if data.ref is None else np.degrees(data.ref)
    plots = {
        "t": data.t,
        "angle_deg": phi % 360,
        "temp_c": data.temp,
        "rate_c_per_min": data.rate,
        "baseline_error_deg": baseline.err_deg,
        "extended_error_deg": cur_eval.err_deg,
        "metric": data.metric,
        "thermal_view_deg": baseline.err_deg,
        "thermal_view": "baseline",
    }
    no_thermal = replace(current, tau_s=0.0, nonlinear=False, aging=False)
    if data.temp is not None and no_thermal != current and no_thermal != base_spec:
        # what temperature does to the residual once every other named term is modelled
        plots["thermal_view_deg"] = evaluate(no_thermal).err_deg
        plots["thermal_view"] = "extended minus thermal terms"
    return Diagnosis(report=report, plots=plots, spec=current)


def measure(samples: Samples, spec: Spec, train) -> dict:
    """Fit the baseline and the model `spec` on the rows `train` (mask) and measure both on the rest:
    {"baseline": {rms_error_deg, max_error_deg}, "extended": {...}, "train": n, "test": n}."""
    data = _Data(samples)
    train = np.asarray(train, bool)
    test = ~train
    if train.sum() < MIN_SAMPLES or not test.any():
        raise InputError("measure needs at least 64 training rows and at least one held-out row")
    out = {"train": int(train.sum()), "test": int(test.sum())}
    for name, sp in (("baseline", Spec()), ("extended", spec)):
        fit = _fit_model(data, sp, train)
        e = np.degrees(fit.err[test & ~fit.reject])
        out[name] = {"rms_error_deg": float(np.sqrt(np.mean(e**2))), "max_error_deg": float(np.max(np.abs(e)))}
    return out


# --- parameters and evidence -------------------------------------------------------------------------


def _coef(fit: _Fit, name: str) -> float:
    return float(fit.coef[fit.names.index(name)]) if name in fit.names else 0.0


def _axis_terms(final: _Fit, data: _Data, spec: Spec, which: int) -> tuple[np.ndarray, np.ndarray]:
    """Coefficient `which` of the basis per axis (d, q): gains relative to the constant gain, offsets
    in the recording's own unit (counts, mT, ...)."""
    k = _basis(data, spec).shape[1]
    gains, offsets = [], []
    for c in (final.stage_a.coef_d, final.stage_a.coef_q):
        gains.append(c[which] / c[0])
        offsets.append(c[k + which] * data.scale)
    return np.array(gains), np.array(offsets)


def _rate_split(data: _Data, before: np.ndarray, after: np.ndarray) -> str:
    """Held-out RMS while heating, cooling and steady (|dT/dt| <= 0.2 °C/min), before -> after."""
    if data.rate is None:
        return ""
    parts = []
    for label, mask in (
        ("heating", data.rate > 0.2),
        ("cooling", data.rate < -0.2),
        ("steady", np.abs(data.rate) <= 0.2),
    ):
        b = before[mask & np.isfinite(before)]
        a = after[mask & np.isfinite(after)]
        if b.size and a.size:
            parts.append(f"{label} {np.sqrt(np.mean(b**2)):.3f}° -> {np.sqrt(np.mean(a**2)):.3f}°")
    return ", ".join(parts)


def _describe(
    name, new_orders: list, current: Spec, final: _Fit, data: _Data, baseline: _Eval, before: _Eval, after: _Eval
):
    ref = data.metric == "reference"
    what = "angle error" if ref else "radius ripple"
    gain = f"modelling it cuts the held-out RMS {what} from {before.rms:.3f}° to {after.rms:.3f}°"
    if name == "zero_offset":
        z = np.degrees(_coef(final, "zero"))
        half = ""
        if final.stage_a.coef_d[0] < 0 and final.stage_a.coef_q[0] < 0:
            # both baseline gains negative: the axis-aligned fit turned the angle by half a turn
            z = float((z + 180.0 + 180.0) % 360.0 - 180.0)
            half = " (the baseline's gains came out negative on both axes: half a turn of it is in the gains)"
        return (
            {"offset_deg": round(float(z), 4)},
            f"the angle error has a constant part of {z:.3f}° at every angle{half}; {gain}.",
        )
    if name == "phase_nonorthogonality":
        w = _coef(final, "phase")
        beta = np.degrees(w if ref else -2 * w)
        shape = (
            "β·sin²θ" if ref else "-β/2·sin 2θ (a tilted ellipse; a 3rd harmonic looks the same without a reference)"
        )
        return (
            {"phase_error_deg": round(float(beta), 4)},
            f"the residual follows {shape} with β = {beta:.3f}°, a cross term between the channels; {gain}.",
        )
    if name == "phase_drift":
        w = _coef(final, "drift")
        rate = np.degrees(w if ref else -2 * w) / T_SCALE
        return (
            {"phase_drift_deg_per_c": round(float(rate), 6)},
            f"the channels' phase difference changes with temperature by {rate:.4f}°/°C; {gain}.",
        )
    if name == "harmonic_distortion":
        n = new_orders[0]
        amp = float(np.hypot(_coef(final, f"h{n}c"), _coef(final, f"h{n}s")))
        return (
            {"order": int(n), "amplitude": round(amp, 6)},
            f"the residual has a {n - 1}-cycle-per-turn component of {np.degrees(amp):.3f}° "
            f"(harmonic order {n}, seed 001 eq. 18); {gain}.",
        )
    if name == "thermal_lag":
        return (
            {"tau_s": round(float(current.tau_s), 2)},
            f"the residual depends on the rate of temperature change, and lagging temp_c fixes it where the "
            f"temperature moves (held-out RMS {_rate_split(data, before.err_deg, after.err_deg)});"
            f" the die follows temp_c with a first-order lag of τ = {current.tau_s:.0f} s; {gain}.",
        )
    if name == "nonlinear_temperature":
        g, o = _axis_terms(final, data, current, 2)
        g2 = g / T_SCALE**2
        o2 = o / T_SCALE**2
        return (
            {
                "gain_tc2_per_c2": [round(float(v), 9) for v in g2],
                "offset_tc2_per_c2": [round(float(v), 9) for v in o2],
            },
            f"gains and offsets curve with temperature (d, q gain {g2[0]:.2e}, {g2[1]:.2e} per °C²); {gain}.",
        )
    if name == "aging":
        idx = 2 + (1 if current.nonlinear else 0) if data.temp is not None else 1
        g, o = _axis_terms(final, data, current, idx)
        khours = data.span_s / 3.6e6
        gk = -g / khours
        ok_ = o / khours
        return (
            {
                "gain_loss_per_khour": [round(float(v), 6) for v in gk],
                "offset_per_khour": [round(float(v), 4) for v in ok_],
            },
            f"gains and offsets trend with operating time at equal temperature (gain loss {gk[0]:.3f}, "
            f"{gk[1]:.3f} per 1000 h over {data.span_s / 3600:.1f} h); {gain}.",
        )
    if name == "outliers":
        frac = after.rejected / data.n
        return (
            {"fraction": round(frac, 6)},
            f"{after.rejected} samples ({100 * frac:.2f} %) jump off the circle, each alone, beyond "
            f"{OUTLIER_SIGMAS:.0f}× the robust spread of the radius about its running median; "
            f"rejecting them {gain[len('modelling it ') :]}.",
        )
    if name == "adc_clipping":
        frac = float(data.clipped.mean())
        where = "; ".join(f"{c['channel']} stuck at {c['value']} in {c['samples']} samples" for c in data.clip_info)
        return (
            {"fraction": round(frac, 6), "channels": sorted({c["channel"] for c in data.clip_info})},
            f"{where} while the other channel keeps moving; rebuilding the clipped channel "
            f"{gain[len('modelling it ') :]}.",
        )
    return {}, gain
