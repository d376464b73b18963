"""Diagnose a recording: fit seed 000's baseline, find what it misses, name the cause, measure the gain.

Pure numpy: no file I/O, no printing. `diagnose(samples)` returns a `Diagnosis` whose `report` is the
"Diagnose JSON" contract of docs/architecture.md and whose `plots` holds the arrays the HTML report draws;
`measure(samples, spec, train)` fits a model on some rows and measures it on the others.

Modules, in the order the data flows:

    causes.py    the vocabulary: one `Cause` per name (parameters, testability, statement), form-free
    data.py      the recording made ready: normalised channels, temperature views, sample masks
    terms.py     each cause's sample form (`Term`): how it extends the model, how its parameters read
    fit.py       fitting one model (`Spec`, a set of terms): stage A in d/q, stage B on the residual
    crossval.py  held-out evaluation (by run or by time block)
    search.py    greedy forward selection of the terms
    report.py    the JSON and the plot arrays
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..samples import InputError, Samples
from .causes import CAUSES, Cause, Observables, Param, split_by_testability
from .crossval import CrossValidation
from .data import MIN_SAMPLES, RecordingData
from .fit import fit_model, flag_suspects
from .report import Diagnosis, build
from .search import Search, forward_selection
from .terms import TERMS, Spec, Term

__all__ = [
    "CAUSES",
    "TERMS",
    "Cause",
    "Diagnosis",
    "Observables",
    "Param",
    "Spec",
    "Term",
    "diagnose",
    "measure",
]


def diagnose(samples: Samples, *, on_step: Callable[[str], None] | None = None) -> Diagnosis:
    """Fit the baseline, name what it misses, and measure every gain on held-out data."""
    data = RecordingData(samples)
    testable, not_testable = split_by_testability(data.observables())
    flag_suspects(data)
    cv = CrossValidation(data)
    selection = forward_selection(Search(data, cv, on_step or (lambda _name: None)), testable)
    return build(data, cv, selection, not_testable)


def measure(samples: Samples, spec: Spec, train) -> dict:
    """Fit the baseline and the model `spec` on the rows `train` (mask) and measure both on the rest:
    {"baseline": {rms_error_deg, max_error_deg}, "extended": {...}, "train": n, "test": n}."""
    data = RecordingData(samples)
    train = np.asarray(train, bool)
    test = ~train
    if train.sum() < MIN_SAMPLES or not test.any():
        raise InputError("measure needs at least 64 training rows and at least one held-out row")
    out = {"train": int(train.sum()), "test": int(test.sum())}
    for name, sp in (("baseline", Spec()), ("extended", spec)):
        fit = fit_model(data, sp, train)
        e = np.degrees(fit.err[test & ~fit.reject])
        out[name] = {"rms_error_deg": float(np.sqrt(np.mean(e**2))), "max_error_deg": float(np.max(np.abs(e)))}
    return out
