"""Diagnose's sample form of each cause: how it extends the model fitted on samples.

The model has two stages (see `fit.py`). Stage A maps each channel to the unit circle with a gain and an
offset over a basis of the operating point, B = [1, T] (seed 000); stage B models what stage A leaves in
the error metric as a linear sum of features of the corrected angle φ and the temperature. A `Term`
acts in one of three places:

    kind "gain"    stage A       thermal_lag (T lagged by τ), nonlinear_temperature (T²), aging (time)
    kind "angle"   stage B       zero_offset (1), phase_nonorthogonality (sin²φ; sin 2φ on the radius),
                                 phase_drift (ΔT times that), harmonic_distortion n (cos, sin (n-1)φ)
    kind "sample"  the samples   adc_clipping (rebuild a clipped channel), outliers (reject samples)

and knows which extensions of a model to propose, which of its results may be named, and how its
parameters are read from the final fit. Its identity (name, parameters, testability, sentence) is the
`Cause` of the same name in `causes.py`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .causes import CAUSES, DIAGNOSE_CAUSES, Cause
from .data import DROPPED_READ_RATIO, OUTLIER_SIGMAS, T_SCALE, local_deviation, outlier_threshold

MAX_OUTLIER_FRACTION = 0.05
MIN_OUTLIERS = 3  # fewer isolated jumps than this are noise's tail, not a cause
REF_ORDERS = tuple(range(2, 9))
RADIUS_ORDERS = tuple(range(4, 9))  # without a reference order 2 looks like an offset, 3 like imbalance
ORDER = {name: i for i, name in enumerate(DIAGNOSE_CAUSES)}


@dataclass(frozen=True)
class Spec:
    """Which extension terms a model carries on top of the baseline: (cause, argument) pairs in the
    registry's order. The argument is a harmonic's order or thermal lag's τ (s), None for the rest."""

    terms: tuple[tuple[str, object], ...] = ()

    def has(self, name: str) -> bool:
        return any(n == name for n, _ in self.terms)

    def args(self, name: str) -> tuple:
        return tuple(a for n, a in self.terms if n == name)

    def plus(self, name: str, arg=None) -> Spec:
        terms = self.terms + ((name, arg),)
        return Spec(tuple(sorted(terms, key=lambda t: (ORDER[t[0]], t[1] or 0))))

    def minus(self, *names: str) -> Spec:
        return Spec(tuple(t for t in self.terms if t[0] not in names))

    def with_arg(self, name: str, arg) -> Spec:
        """The same model with `name`'s (single) argument replaced, or `name` added."""
        return self.minus(name).plus(name, arg)

    def added_over(self, other: Spec) -> tuple[str, object]:
        """The one term this model has and `other` lacks."""
        return next(t for t in self.terms if t not in other.terms)

    @property
    def tau_s(self) -> float:
        lag = self.args("thermal_lag")
        return float(lag[0]) if lag else 0.0

    def stage_a_key(self) -> tuple:
        return tuple((n, round(a, 6) if isinstance(a, float) else a) for n, a in self.terms if TERMS[n].stage_a)

    def causes(self) -> list[str]:
        return [n for n, _ in self.terms]


class Term:
    """How one cause acts on samples. The defaults describe a term that is present or not and adds
    nothing; each cause overrides what it does."""

    name = ""
    kind = "angle"
    n_params = 1  # parsimony: among near-equal terms the one with fewest parameters is named
    stage_a = False  # changes stage A's fit
    scans = False  # proposes by scanning many models: proposed last, so the others share cached fits
    action = "modelling it"  # the subject of the evidence's gain clause

    @property
    def cause(self) -> Cause:
        return CAUSES[self.name]

    # --- search ---

    def extensions(self, data, spec: Spec) -> list[Spec]:
        """The models, one term richer, that this cause proposes."""
        return [] if spec.has(self.name) else [spec.plus(self.name)]

    def propose(self, search, spec: Spec) -> list[tuple[Spec, object]]:
        """Extensions with their held-out evaluation."""
        return [(ext, search.evaluate(ext, self.name)) for ext in self.extensions(search.data, spec)]

    def admissible(self, data, ev) -> bool:
        """Whether a held-out result may be named at all (beyond cutting the RMS enough)."""
        return True

    def evident(self, data) -> bool:
        """The data shows this cause by itself: it is named before the search, without a gain test."""
        return False

    def refine(self, search, spec: Spec, ev):
        """After another term joined: a better (spec, eval) for this term's argument, or None."""
        return None

    # --- stage A ---

    def basis_columns(self, data, tn: np.ndarray | None) -> list[tuple[str, np.ndarray]]:
        return []

    def repair(self, data, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return x, y

    # --- stage B ---

    def features(self, data, spec: Spec, arg, view, phi: np.ndarray) -> list[tuple[str, np.ndarray]]:
        return []

    def settle_error(self, data, e: np.ndarray) -> np.ndarray:
        return e

    def rejected(self, data, view, phi, radius, rows) -> np.ndarray | None:
        """Samples among `rows` this term rejects (None: it rejects nothing)."""
        return None

    # --- report ---

    def parameters(self, ctx, arg) -> tuple[dict, dict]:
        """The finding's parameters, and the facts its statement needs (unrounded values override)."""
        raise NotImplementedError


def phase_shape(data, view, phi):
    """The angle error of a phase error β per unit β: sin²φ against a reference, sin 2φ on the radius."""
    return view.get("shape", lambda: np.sin(phi) ** 2 if data.ref is not None else np.sin(2 * phi))


class ZeroOffset(Term):
    name = "zero_offset"

    def features(self, data, spec, arg, view, phi):
        if data.ref is None:
            return []
        return [("zero", view.get("one", lambda: np.ones_like(phi)))]

    def parameters(self, ctx, arg):
        z = float(np.degrees(ctx.coef("zero")))
        half = ""
        if ctx.final.stage_a.coef_d[0] < 0 and ctx.final.stage_a.coef_q[0] < 0:
            # both baseline gains negative: the axis-aligned fit turned the angle by half a turn
            z = float((z + 180.0 + 180.0) % 360.0 - 180.0)
            half = " (the baseline's gains came out negative on both axes: half a turn of it is in the gains)"
        return {"offset_deg": round(z, 4)}, {"offset_deg": z, "half_turn": half}


class PhaseNonorthogonality(Term):
    name = "phase_nonorthogonality"

    def features(self, data, spec, arg, view, phi):
        return [("phase", phase_shape(data, view, phi))]

    def parameters(self, ctx, arg):
        w = ctx.coef("phase")
        beta = float(np.degrees(w if ctx.reference else -2 * w))
        shape = (
            "β·sin²θ"
            if ctx.reference
            else "-β/2·sin 2θ (a tilted ellipse; a 3rd harmonic looks the same without a reference)"
        )
        return {"phase_error_deg": round(beta, 4)}, {"phase_error_deg": beta, "shape": shape}


class PhaseDrift(Term):
    name = "phase_drift"

    def features(self, data, spec, arg, view, phi):
        if data.temp is None:
            return []
        tau = spec.tau_s
        return [("drift", view.get(("drift", tau), lambda: data.temp_n(tau) * phase_shape(data, view, phi)))]

    def parameters(self, ctx, arg):
        w = ctx.coef("drift")
        rate = float(np.degrees(w if ctx.reference else -2 * w) / T_SCALE)
        return {"phase_drift_deg_per_c": round(rate, 6)}, {"phase_drift_deg_per_c": rate}


class HarmonicDistortion(Term):
    name = "harmonic_distortion"
    n_params = 2

    def extensions(self, data, spec):
        orders = REF_ORDERS if data.ref is not None else RADIUS_ORDERS
        have = spec.args(self.name)
        return [spec.plus(self.name, n) for n in orders if n not in have and n * 2 < data.distinct_angles]

    def features(self, data, spec, n, view, phi):
        m = n - 1
        return [
            (f"h{n}c", view.get(f"h{n}c", lambda: np.cos(m * phi))),
            (f"h{n}s", view.get(f"h{n}s", lambda: np.sin(m * phi))),
        ]

    def parameters(self, ctx, n):
        amp = float(np.hypot(ctx.coef(f"h{n}c"), ctx.coef(f"h{n}s")))
        params = {"order": int(n), "amplitude": round(amp, 6)}
        return params, {"cycles": n - 1, "amplitude_deg": float(np.degrees(amp))}


TAU_GRID_POINTS = 14


class ThermalLag(Term):
    """The die's temperature is T lagged first-order by τ; τ is scanned on a log grid and refined."""

    name = "thermal_lag"
    kind = "gain"
    stage_a = True
    scans = True

    def propose(self, search, spec):
        if spec.has(self.name):
            return []
        tau, ev = best_tau(search, spec, search.memory.get(self.name))
        search.memory[self.name] = tau  # later rounds scan near it
        return [(spec.with_arg(self.name, tau), ev)]

    def refine(self, search, spec, ev):
        tau, ev2 = best_tau(search, spec, spec.tau_s)  # the other terms changed: let τ settle again
        return (spec.with_arg(self.name, tau), ev2) if ev2.rms < ev.rms else None

    def parameters(self, ctx, arg):
        tau = ctx.spec.tau_s
        split = rate_split(ctx.data, ctx.before.err_deg, ctx.after.err_deg)
        where_fixed = f", and lagging temp_c fixes it where the temperature moves (held-out RMS {split})"
        return {"tau_s": round(tau, 2)}, {"tau_s": tau, "where_fixed": where_fixed}


def best_tau(search, spec: Spec, around: float | None) -> tuple[float, object]:
    """Scan τ on a log grid (narrow around a previous τ) for the best held-out fit, then refine twice
    by a parabola in log τ through the best and its neighbours."""
    data = search.data
    dt = np.median(np.diff(data.t))
    lo = max(dt, 1.0)
    hi = max(data.span_s / 4, lo * 2)
    grid = around * np.geomspace(0.5, 2.0, 5) if around else np.geomspace(lo, hi, TAU_GRID_POINTS)
    results = {}

    def evaluate(tau):
        results[tau] = search.evaluate(spec.with_arg("thermal_lag", tau), "thermal_lag")

    for tau in grid:
        evaluate(float(tau))
    for _ in range(2):
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
                    evaluate(tau)
    best = min(results, key=lambda k: results[k].rms)
    return best, results[best]


def rate_split(data, before: np.ndarray, after: np.ndarray) -> str:
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


class NonlinearTemperature(Term):
    name = "nonlinear_temperature"
    kind = "gain"
    n_params = 4
    stage_a = True

    def basis_columns(self, data, tn):
        return [] if tn is None else [("T²", tn * tn)]

    def parameters(self, ctx, arg):
        g, o = ctx.axis_terms("T²")
        g2, o2 = g / T_SCALE**2, o / T_SCALE**2
        params = {
            "gain_tc2_per_c2": [round(float(v), 9) for v in g2],
            "offset_tc2_per_c2": [round(float(v), 9) for v in o2],
        }
        return params, {"gain_d": float(g2[0]), "gain_q": float(g2[1])}


class Aging(Term):
    name = "aging"
    kind = "gain"
    n_params = 4
    stage_a = True

    def basis_columns(self, data, tn):
        return [("age", data.age)]

    def parameters(self, ctx, arg):
        g, o = ctx.axis_terms("age")
        khours = ctx.data.span_s / 3.6e6
        loss, drift = -g / khours, o / khours
        params = {
            "gain_loss_per_khour": [round(float(v), 6) for v in loss],
            "offset_per_khour": [round(float(v), 4) for v in drift],
        }
        over = f" over {ctx.data.span_s / 3600:.1f} h"
        return params, {"loss_d": float(loss[0]), "loss_q": float(loss[1]), "over": over}


class Outliers(Term):
    """Corrupted samples are rejected: dropped reads (field under half the typical one, found in the
    data) and samples whose radius jumps, alone, far from what angle and time explain. Neither rule
    needs a reference, so any stream can apply them to its own radius."""

    name = "outliers"
    kind = "sample"
    action = "rejecting them"

    def evident(self, data):
        return bool(data.dropped.any())  # a read with no field carries no angle: no test needed

    def admissible(self, data, ev):
        return MIN_OUTLIERS <= ev.rejected <= MAX_OUTLIER_FRACTION * data.n

    def rejected(self, data, view, phi, radius, rows):
        dev = view.get("local_dev", lambda: local_deviation(radius, phi, data.dropped))[rows]
        clipped, dropped = data.clipped[rows], data.dropped[rows]  # clipped samples are adc_clipping's
        jumps = (np.abs(dev) > outlier_threshold(dev[~clipped & ~dropped])) & ~clipped
        return jumps | dropped

    def parameters(self, ctx, arg):
        data = ctx.data
        count = ctx.after.rejected
        frac = count / data.n
        beyond = f"beyond {OUTLIER_SIGMAS:.0f}× the robust spread of the radius about its running median"
        dropped = int(data.dropped.sum())
        if not dropped:
            how = f"jump off the circle, each alone, {beyond}"
        else:
            ratio = 100 * data.read_ratio[data.dropped]
            low, high = ratio[ratio < 100], ratio[ratio >= 100]
            said = []
            if low.size:
                said.append(
                    f"{low.size} dropped read(s), a field magnitude of {low.min():.1f}-{low.max():.1f} % of the "
                    f"typical one (under {100 * DROPPED_READ_RATIO:.0f} %: a failed conversion or a loose connector)"
                )
            if high.size:
                said.append(
                    f"{high.size} read(s) of {high.min():.3g}-{high.max():.3g} % of the typical field (over "
                    f"{100 / DROPPED_READ_RATIO:.0f} %: a spike on the line or a corrupted word)"
                )
            how = "are corrupted: " + " and ".join(said)
            if count > dropped:
                how += f", and {count - dropped} isolated jump(s) off the circle {beyond}"
        return {"fraction": round(frac, 6)}, {"count": count, "percent": 100 * frac, "how": how}


class AdcClipping(Term):
    name = "adc_clipping"
    kind = "sample"
    n_params = 0
    stage_a = True
    action = "rebuilding the clipped channel"

    def extensions(self, data, spec):
        return [] if spec.has(self.name) or not data.clipped.any() else [spec.plus(self.name)]

    def repair(self, data, x, y):
        """A channel stuck at a rail is rebuilt from the other one: the point lies on the unit circle."""
        x, y = x.copy(), y.copy()
        m = data.clip_d & ~data.clip_q
        x[m] = np.sign(x[m]) * np.sqrt(np.clip(1 - y[m] ** 2, 0, None))
        m = data.clip_q & ~data.clip_d
        y[m] = np.sign(y[m]) * np.sqrt(np.clip(1 - x[m] ** 2, 0, None))
        return x, y

    def settle_error(self, data, e):
        if data.ref is not None:
            return e
        # a rebuilt sample lies on the model's circle by construction: no radius error left to correct
        return np.where(data.clip_d ^ data.clip_q, 0.0, e)

    def parameters(self, ctx, arg):
        data = ctx.data
        frac = float(data.clipped.mean())
        where = "; ".join(f"{c['channel']} stuck at {c['value']} in {c['samples']} samples" for c in data.clip_info)
        channels = sorted({c["channel"] for c in data.clip_info})
        return {"fraction": round(frac, 6), "channels": channels}, {"where": where}


TERMS: dict[str, Term] = {
    t.name: t
    for t in (
        ZeroOffset(),
        PhaseNonorthogonality(),
        PhaseDrift(),
        HarmonicDistortion(),
        ThermalLag(),
        NonlinearTemperature(),
        Aging(),
        Outliers(),
        AdcClipping(),
    )
}
assert list(TERMS) == list(DIAGNOSE_CAUSES), "one sample form per diagnose cause, in the registry's order"
