"""A recording made ready for diagnose: normalised channels, temperature views, and sample masks.

The masks mark samples that no fit may use: channels stuck at a rail (`clipped`), dropped reads whose
field collapsed (`dropped`), and isolated samples far off the circle (`suspect`, set after the robust
baseline). The radius rules that find them need no reference, so any stream can apply them, and they
work on a recording of a few hundred rows as on one of a million.
"""

from __future__ import annotations

import numpy as np

from ..physics import REFERENCE_TEMP_C
from ..samples import InputError, Samples, check_angle_coverage, check_fit_input
from ..thermal import first_order_lag
from .causes import Observables

MIN_SAMPLES = 64
T_SCALE = 50.0  # °C: temperature is used as (T - 20)/50 for conditioning
OUTLIER_SIGMAS = 8.0
OUTLIER_FLOOR = 0.01  # radius deviation (fraction of the radius) below which nothing is an outlier
# A read whose field magnitude is under half the recording's typical one carries no angle: no drift,
# imbalance or harmonic moves a healthy sample that far, a failed conversion or a loose connector does; nor does
# one over twice the typical one (a spike on the line, a corrupted word)
DROPPED_READ_RATIO = 0.5


class RecordingData:
    """Normalised arrays and per-sample flags: everything the fits share."""

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
        # the median radius, not the rms: one corrupted read of a thousand times the field would set the scale
        amp = np.median(np.hypot(samples.d - self.center[0], samples.q - self.center[1]))
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
        self.run = None if samples.run is None else np.asarray(samples.run)
        self._lagged: dict[float, np.ndarray] = {}
        self.read_ratio = field_ratio(self.d, self.q)
        # a read under half the typical field (dropped) or over twice it (a spike on the line) carries no angle
        self.dropped = ~((self.read_ratio >= DROPPED_READ_RATIO) & (self.read_ratio <= 1 / DROPPED_READ_RATIO))
        self.clip_d, self.clip_q, self.clip_info = find_clipping(samples, self.d, self.q, self.dropped)
        self.clipped = self.clip_d | self.clip_q
        self.suspect = np.zeros(n, bool)  # set after the baseline: isolated samples far off the circle
        self._distinct_angles: int | None = None

    @property
    def metric(self) -> str:
        return "reference" if self.ref is not None else "radius"

    @property
    def unfit(self) -> np.ndarray:
        """Samples no fit may use."""
        return self.suspect | self.clipped | self.dropped

    def observables(self) -> Observables:
        return Observables(
            has_reference=self.ref is not None,
            temp_span_c=None if self.temp is None else self.temp_span,
            span_s=self.span_s,
        )

    @property
    def distinct_angles(self) -> int:
        """Distinct angles visited (0.1° resolution): a harmonic needs more than twice its order."""
        if self._distinct_angles is None:
            src = self.ref if self.ref is not None else np.arctan2(self.q, self.d)
            self._distinct_angles = int(np.unique(np.round(np.degrees(src % (2 * np.pi)), 1)).size)
        return self._distinct_angles

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


def find_clipping(samples: Samples, d_norm: np.ndarray, q_norm: np.ndarray, dropped: np.ndarray):
    """Channels stuck at one extreme value while the other channel keeps moving (a dropped read that
    reads a rail on every channel is the outlier rule's, not clipping)."""
    n = len(samples)
    clip = {"d": np.zeros(n, bool), "q": np.zeros(n, bool)}
    info = []
    raw = {"d": np.asarray(samples.d, float), "q": np.asarray(samples.q, float)}
    norm = {"d": d_norm, "q": q_norm}
    for name, other in (("d", "q"), ("q", "d")):
        for value in (raw[name].max(), raw[name].min()):
            at = (raw[name] == value) & ~dropped
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
            at = ((arr <= 0) | (arr >= 4095)) & ~dropped
            if at.sum() >= max(5, 0.0005 * n):
                chan = "q" if key.startswith("a_") else "d"
                clip[chan] |= at
                info.append({"channel": key, "value": "rail", "samples": int(at.sum())})
    return clip["d"], clip["q"], info


# --- radius rules for corrupted samples ------------------------------------------------------------


def field_ratio(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Each sample's distance from the centre of the locus over the typical (median) distance: about 1
    for every healthy sample, near 0 where the field reading collapsed. The centre is an algebraic
    circle fit on the samples not near it (a median centre is off when angles are visited unevenly)."""
    cx, cy = np.median(x), np.median(y)
    for _ in range(2):
        r = np.hypot(x - cx, y - cy)
        keep = (r >= DROPPED_READ_RATIO * np.median(r)) & (r <= np.median(r) / DROPPED_READ_RATIO)
        a = np.column_stack([2 * x[keep], 2 * y[keep], np.ones(int(keep.sum()))])
        (cx, cy, _), *_ = np.linalg.lstsq(a, x[keep] ** 2 + y[keep] ** 2, rcond=None)
    r = np.hypot(x - cx, y - cy)
    return r / np.median(r)


def local_deviation(radius: np.ndarray, phi: np.ndarray, known_bad: np.ndarray | None = None, bins: int = 64):
    """What of the radius neither angle nor time explains: minus its median in the sample's angle bin
    (64 bins), then minus its running median over 11 samples in time. Harmonics, phase and slow drifts
    (temperature, lag, aging) cancel; an isolated corrupted sample stands out. Samples already known to
    be bad (dropped reads) take no part in the medians: in a short recording an angle bin holds two or
    three samples, and a dropped one would make its healthy neighbour look off the circle."""
    good = np.ones(radius.size, bool) if known_bad is None else ~known_bad
    idx = np.minimum(((phi % (2 * np.pi)) * (bins / (2 * np.pi))).astype(int), bins - 1)
    gidx, grad = idx[good], radius[good]
    order = np.lexsort((grad, gidx))
    starts = np.searchsorted(gidx[order], np.arange(bins + 1))
    med = np.zeros(bins)
    for b in range(bins):
        lo, hi = starts[b], starts[b + 1]
        if hi > lo:
            med[b] = grad[order[(lo + hi - 1) // 2]]
    r = radius - med[idx]
    rows = np.arange(r.size)
    filled = r if good.all() else np.interp(rows, rows[good], r[good])  # bad samples: their neighbours' value
    from scipy.ndimage import median_filter  # here: scipy.ndimage costs every process that imports diagnose ~0.4 s

    return r - median_filter(filled, size=11, mode="nearest")


def outlier_threshold(dev: np.ndarray) -> float:
    """Beyond 8 robust sigmas, beyond twice the 95th percentile (so that a systematic effect spread
    over more than 5 % of the samples never counts), and beyond 1 % of the radius."""
    p95 = float(np.percentile(np.abs(dev), 95)) if dev.size else 0.0
    return max(OUTLIER_SIGMAS * robust_sigma(dev), 2.0 * p95, OUTLIER_FLOOR)


def robust_sigma(v: np.ndarray) -> float:
    v = v[np.isfinite(v)]
    if v.size == 0:
        return 0.0
    return float(1.4826 * np.median(np.abs(v - np.median(v))))
