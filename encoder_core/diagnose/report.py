"""The Diagnose JSON (docs/architecture.md contract, plus additions) and the arrays the HTML report draws."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .crossval import CrossValidation, Eval
from .data import RecordingData
from .fit import Fit, fit_model
from .search import Selection, Step
from .terms import TERMS, Spec


@dataclass
class Diagnosis:
    report: dict  # the Diagnose JSON contract
    plots: dict = field(default_factory=dict)  # arrays for the HTML report
    spec: Spec = field(default_factory=Spec)  # the extended model's terms (for `measure`)


@dataclass
class FindingContext:
    """What a term reads its parameters from: the final fit of the extended model, and the held-out
    results just before and after the term joined."""

    data: RecordingData
    spec: Spec
    final: Fit
    before: Eval
    after: Eval

    @property
    def reference(self) -> bool:
        return self.data.ref is not None

    def coef(self, name: str) -> float:
        return self.final.coefficient(name)

    def axis_terms(self, column: str) -> tuple[np.ndarray, np.ndarray]:
        """Stage A's coefficient of basis column `column` per axis (d, q): gains relative to the
        constant gain, offsets in the recording's own unit (counts, mT, ...)."""
        sa = self.final.stage_a
        k, which = len(sa.basis_names), sa.basis_names.index(column)
        gains = np.array([c[which] / c[0] for c in (sa.coef_d, sa.coef_q)])
        offsets = np.array([c[k + which] * self.data.scale for c in (sa.coef_d, sa.coef_q)])
        return gains, offsets


def finding(step: Step, ctx: FindingContext) -> dict:
    term = TERMS[step.name]
    params, facts = term.parameters(ctx, step.arg)
    if set(params) != set(term.cause.param_names):  # the sample form must report the cause's parameters
        raise AssertionError(f"{step.name}: parameters {sorted(params)}, cause has {term.cause.param_names}")
    what = "angle error" if ctx.reference else "radius ripple"
    cut = f"cuts the held-out RMS {what} from {step.before.rms:.3f}° to {step.after.rms:.3f}°"
    return {
        "cause": step.name,
        "parameters": params,
        "evidence": f"{term.cause.state(**{**params, **facts})}; {term.action} {cut}.",
        "rms_error_deg_before": round(step.before.rms, 6),
        "rms_error_deg_after": round(step.after.rms, 6),
    }


def baseline_model(data: RecordingData) -> str:
    text = (
        "per-axis gain and offset, each linear in temperature (seed 000)"
        if data.temp is not None
        else "per-axis gain and offset, constant (no temperature recorded)"
    )
    return text + (
        ", fitted against the reference angle" if data.ref is not None else ", fitted reference-free (radius = 1)"
    )


def errors(ev: Eval) -> dict:
    return {"rms_error_deg": round(ev.rms, 6), "max_error_deg": round(ev.max, 6)}


def build(data: RecordingData, cv: CrossValidation, sel: Selection, not_testable: list[dict]) -> Diagnosis:
    final = fit_model(data, sel.spec, np.ones(data.n, bool))
    findings = [finding(s, FindingContext(data, sel.spec, final, s.before, s.after)) for s in sel.steps]
    report = {
        "samples": data.n,
        "has_reference": data.ref is not None,
        "error_metric": data.metric,
        "baseline": {"model": baseline_model(data), **errors(sel.baseline)},
        "findings": findings,
        "extended": {"causes": [f["cause"] for f in findings], **errors(sel.result)},
        "not_testable": not_testable,
        "held_out": {"by": cv.kind, "folds": int(cv.fold_ids.size)},
    }
    shifts = repeatability(data, sel.result)
    if shifts is not None:
        report["repeatability"] = shifts
    return Diagnosis(report=report, plots=plots(data, cv, sel, final), spec=sel.spec)


def repeatability(data: RecordingData, extended: Eval) -> dict | None:
    """Run-to-run repeatability: each run's mean held-out angle error after the extended model.

    A run that sits shifted by its own constant (the sensor re-mounted between runs) leaves a residual
    that no term fitted on other runs can predict; it is reported per run here, and the RMS the
    extended model would reach without it, rather than left in the residual unexplained. Needs a
    reference (the radius cannot see a shift along the circle) and at least two runs."""
    if data.ref is None or data.run is None or np.unique(data.run).size < 2:
        return None
    shifts, within = run_shifts(data.run, extended.err_deg)
    rms = float(np.sqrt(np.mean(np.square(list(shifts.values())))))
    within_rms = _rms(within)
    return {
        "runs": {_run_label(r): round(v, 6) for r, v in shifts.items()},
        "rms_deg": round(rms, 6),
        "within_run_rms_error_deg": round(within_rms, 6),
        "note": (
            f"each run's mean held-out angle error after the extended model: a constant shift per run "
            f"(RMS {rms:.3f}° over {len(shifts)} runs, e.g. the sensor re-mounted) that no model fitted on "
            f"other runs can predict; within the runs the held-out RMS is {within_rms:.3f}° "
            f"(extended: {extended.rms:.3f}°)"
        ),
    }


def run_shifts(run: np.ndarray, err_deg: np.ndarray) -> tuple[dict, np.ndarray]:
    """Each run's mean error (rejected samples, NaN, left out), and the error less its run's mean."""
    shifts = {}
    within = np.full(err_deg.size, np.nan)
    for r in np.unique(run):
        rows = (run == r) & np.isfinite(err_deg)
        if rows.any():
            shifts[r] = float(np.mean(err_deg[rows]))
            within[rows] = err_deg[rows] - shifts[r]
    return shifts, within


def _rms(v: np.ndarray) -> float:
    v = v[np.isfinite(v)]
    return float(np.sqrt(np.mean(v**2))) if v.size else float("nan")


def _run_label(run) -> str:
    """ "1" for run 1.0 (the CSV reader gives floats), the value as written otherwise."""
    try:
        value = float(run)
    except (TypeError, ValueError):
        return str(run)
    return str(int(value)) if value.is_integer() else str(run)


def plots(data: RecordingData, cv: CrossValidation, sel: Selection, final: Fit) -> dict:
    sa = final.stage_a
    phi = np.degrees(np.arctan2(sa.y, sa.x)) if data.ref is None else np.degrees(data.ref)
    out = {
        "t": data.t,
        "angle_deg": phi % 360,
        "temp_c": data.temp,
        "rate_c_per_min": data.rate,
        "baseline_error_deg": sel.baseline.err_deg,
        "extended_error_deg": sel.result.err_deg,
        "metric": data.metric,
        "thermal_view_deg": sel.baseline.err_deg,
        "thermal_view": "baseline",
    }
    no_thermal = sel.spec.minus(*[n for n in sel.spec.causes() if TERMS[n].kind == "gain"])
    if data.temp is not None and no_thermal != sel.spec and no_thermal != Spec():
        # what temperature does to the residual once every other named term is modelled
        out["thermal_view_deg"] = cv(no_thermal).err_deg
        out["thermal_view"] = "extended minus thermal terms"
    return out
