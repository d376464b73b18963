"""Held-out evaluation: every RMS and max that diagnose reports is on rows the fit did not see.

Leave-one-run-out when the recording has 3-50 runs of at least 8 rows and every training set still
spans the temperature range (many runs: several per fold, at most 5 folds); otherwise 8 contiguous
time blocks in 4 interleaved folds.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from .causes import MIN_TEMP_SPAN_C
from .data import RecordingData
from .fit import StageA, fit_model, fit_stage_a
from .terms import Spec

MAX_FOLDS = 5


@dataclass
class Eval:
    err_deg: np.ndarray  # held-out error per sample (NaN where rejected)
    rms: float
    max: float
    rejected: int = 0


def held_out_folds(data: RecordingData) -> tuple[np.ndarray, str]:
    """A fold index per row, and what the folds are ("run" or "time block")."""
    if data.run is not None:
        runs = np.unique(data.run)
        if 3 <= runs.size <= 50:
            counts = np.array([np.count_nonzero(data.run == r) for r in runs])
            folds = np.searchsorted(runs, data.run) % MAX_FOLDS  # many runs: several per fold
            if counts.min() >= 8 and _folds_span_temperature(data, folds):
                return folds, "run"
    blocks = np.minimum((np.arange(data.n) * 8) // data.n, 7)
    return blocks % 4, "time block"


def _folds_span_temperature(data: RecordingData, folds: np.ndarray) -> bool:
    """Leaving a fold out must not leave a fit that only saw part of the temperature range."""
    if data.temp is None or data.temp_span < MIN_TEMP_SPAN_C:
        return True
    return all(np.ptp(data.temp[folds != f]) >= 0.5 * data.temp_span for f in np.unique(folds))


def summarise(err_deg: np.ndarray, rejected: int = 0) -> Eval:
    ok = np.isfinite(err_deg)
    # no angle is further off than 180°: the radius metric of a corrupted read (10^300 times the field) says more
    err = np.clip(err_deg[ok], -180.0, 180.0)
    rms = float(np.sqrt(np.mean(err**2))) if ok.any() else float("nan")
    mx = float(np.max(np.abs(err))) if ok.any() else float("nan")
    return Eval(err_deg, rms, mx, rejected)


class CrossValidation:
    """Evaluates a model on held-out folds; stage A fits are cached by what changes them."""

    def __init__(self, data: RecordingData):
        self.data = data
        self.folds, self.kind = held_out_folds(data)
        self.fold_ids = np.unique(self.folds)
        self._cache: OrderedDict = OrderedDict()
        self.phi0 = self._starting_angles()
        self.calls = 0

    def train_rows(self, fold) -> np.ndarray:
        return (self.folds != fold) & ~self.data.unfit

    def _starting_angles(self) -> dict:
        """Without a reference, each fold's reference-free fits start from the baseline's angle on that
        fold's training rows (fewer alternating iterations per model)."""
        if self.data.ref is not None:
            return {}
        out = {}
        for fold in self.fold_ids:
            a = fit_stage_a(self.data, Spec(), self.train_rows(fold), None)
            out[int(fold)] = np.arctan2(a.y, a.x)
        return out

    def stage_a_for(self, spec: Spec, fold) -> StageA:
        key = (spec.stage_a_key(), int(fold))
        if key in self._cache:
            self._cache.move_to_end(key)
        else:
            self._cache[key] = fit_stage_a(self.data, spec, self.train_rows(fold), self.phi0.get(int(fold)))
            while len(self._cache) > 3 * len(self.fold_ids):
                self._cache.popitem(last=False)
        return self._cache[key]

    def __call__(self, spec: Spec) -> Eval:
        self.calls += 1
        data = self.data
        err = np.full(data.n, np.nan)
        rejected = 0
        for fold in self.fold_ids:
            test = self.folds == fold
            fit = fit_model(data, spec, ~test, stage_a=self.stage_a_for(spec, fold), judge=test)
            r = fit.reject[test]
            rejected += int(r.sum())
            err[test] = np.where(r, np.nan, fit.err[test])
        return summarise(np.degrees(err), rejected)
