"""Greedy forward selection: name a cause only when adding its term cuts the held-out RMS enough.

A cause whose term finds it evident in the data (dropped reads) is named first, without a gain test.
Then each round every testable cause proposes its extensions of the current model (its `Term.propose`);
those that cut the held-out RMS by at least `MIN_GAIN` and that the term admits are candidates. The
best wins, but among candidates within `PARSIMONY` of it the one with the fewest parameters: the terms
overlap (zero offset + phase spans what phase + a 3rd harmonic spans). After a term joins, the terms
already in the model may re-tune their argument (thermal lag's τ).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

from .crossval import CrossValidation, Eval
from .data import RecordingData
from .terms import TERMS, Spec

MIN_GAIN = 0.10  # a term must cut the held-out RMS by 10 % to be named
PARSIMONY = 0.03


@dataclass
class Step:
    """One named cause: the term added, the model after it, and the held-out result before and after."""

    name: str
    arg: object
    spec: Spec
    before: Eval
    after: Eval


@dataclass
class Selection:
    baseline: Eval
    spec: Spec
    result: Eval
    steps: list[Step]


@dataclass
class Search:
    """What a term's `propose` may use: the data, a counted evaluation, and memory between rounds."""

    data: RecordingData
    cv: CrossValidation
    on_step: Callable[[str], None]
    memory: dict = field(default_factory=dict)

    def evaluate(self, spec: Spec, label: str) -> Eval:
        self.on_step(label)
        return self.cv(spec)


def forward_selection(search: Search, testable: list[str]) -> Selection:
    baseline = search.evaluate(Spec(), "baseline")
    sel = Selection(baseline, Spec(), baseline, [])
    for name in testable:  # what the data shows by itself is named first, without a gain test
        if TERMS[name].evident(search.data):
            for ext in TERMS[name].extensions(search.data, sel.spec)[:1]:
                _add(sel, name, ext, search.evaluate(ext, name))
    proposers = sorted(testable, key=lambda name: TERMS[name].scans)
    while (chosen := _choose(search.data, _options(search, proposers, sel.spec), sel.result)) is not None:
        _add(sel, *chosen)
        _retune(search, sel, chosen[0])
    return sel


def _options(search: Search, proposers: list[str], spec: Spec) -> list[tuple[str, Spec, Eval]]:
    return [(name, ext, ev) for name in proposers for ext, ev in TERMS[name].propose(search, spec)]


def _add(sel: Selection, name: str, ext: Spec, ev: Eval) -> None:
    sel.steps.append(Step(name, ext.added_over(sel.spec)[1], ext, sel.result, ev))
    sel.spec, sel.result = ext, ev


def _retune(search: Search, sel: Selection, joined: str) -> None:
    """The terms already in the model re-tune their argument now that `joined` is in (thermal lag's τ)."""
    for name in dict.fromkeys(sel.spec.causes()):
        refined = TERMS[name].refine(search, sel.spec, sel.result) if name != joined else None
        if refined:
            sel.spec, sel.result = refined
            sel.steps[-1] = replace(sel.steps[-1], spec=sel.spec, after=sel.result)


def _choose(data: RecordingData, options: list, current: Eval):
    """The option to name, or None: enough gain, admitted by its term, then best with parsimony."""
    accepted = [
        (ev.rms, name, ext, ev)
        for name, ext, ev in options
        if ev.rms < (1 - MIN_GAIN) * current.rms and TERMS[name].admissible(data, ev)
    ]
    if not accepted:
        return None
    best = min(a[0] for a in accepted)
    near = [a for a in accepted if a[0] <= best * (1 + PARSIMONY)]
    _, name, ext, ev = min(near, key=lambda a: (TERMS[a[1]].n_params, a[0]))
    return name, ext, ev
