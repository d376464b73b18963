"""The guard's trial of a new coefficient set (issue 8): no I/O here, the service hands in the evidence.

A fitted set is published on trial. While it is on trial the device gets no other new set, so what the
drive does next is the trial set's doing. The evidence is the raw statistics of the windows the drive
ran on the trial set (the soak), per band the set changed; the judge compares the trial set with the set
it replaced on that same data and says confirm, rollback or wait.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from encoder_core.correction import BandedCorrection
from encoder_core.ellipse import ellipse_correction, fit_ellipse
from encoder_core.held import dwelt, held_runs
from encoder_core.outcome import compare_sets, guard_decision
from encoder_core.samples import InputError
from encoder_core.stats import WindowStats

from .refit import bench_anchors, difference_deg

MIN_SOAK_SAMPLES = 20000  # samples run on the trial set, summed over the bands it changed
MAX_SOAK_SAMPLES = 200000  # past this, a set whose outcome cannot be measured is kept (and says so)
SIGMAS = 2.0
TOLERANCE_DEG = 0.002


@dataclass
class TrialEvidence:
    trial: dict  # the set on trial (wire message)
    before: dict  # the confirmed set it replaced (wire message)
    soak: dict[int, WindowStats]  # band -> windows run on the trial set, in the bands it changed
    factory: dict | None = None  # the factory set (wire message); its bench locus, when it has one, is the ruler

    @property
    def soak_samples(self) -> int:
        return sum(s.n for s in self.soak.values())


@dataclass
class Verdict:
    action: str  # confirm | rollback | wait
    reason: str


def changed_bands(trial: dict, before: dict) -> set[int]:
    """Bands whose entry the trial set changed (a band it adds counts as changed)."""
    old = {b["band"]: {k: v for k, v in b.items() if k != "quality"} for b in before["bands"]}
    return {b["band"] for b in trial["bands"] if old.get(b["band"]) != {k: v for k, v in b.items() if k != "quality"}}


def judge(evidence: TrialEvidence) -> Verdict:
    """With a factory set that carries its bench locus (`encoder-fleet calibrate`), both sets are measured
    against the drift the soak shows since the bench (encoder_core/outcome.py: the field's harmonics cancel,
    and the difference is known better than either error); otherwise by a fresh ellipse fit per band."""
    anchors = (
        bench_anchors(BandedCorrection.from_dict({"bands": evidence.factory["bands"]})) if evidence.factory else []
    )
    if anchors:
        return judge_against_bench(evidence, anchors)
    return judge_by_ellipse(evidence)


def judge_against_bench(evidence: TrialEvidence, anchors) -> Verdict:
    soak = evidence.soak.values()
    if evidence.soak_samples >= MIN_SOAK_SAMPLES and all(dwelt(stats) and held_runs(stats) for stats in soak):
        # a drive holding positions shows no circle to measure either set on, however long it soaks; the set's
        # uncertainty where it sits is the refit's own (held_drift_model), and waiting for the longest soak held a
        # step's move back for hours (s2-20hz-10). Only positions held, not an arc swept (a reversing drive's short
        # arcs are dwelt too, and may show a circle later)
        return Verdict("confirm", "the drive holds positions: no circle to measure the set on; kept on the refit's")
    trial = BandedCorrection.from_dict({"bands": evidence.trial["bands"]})
    before = BandedCorrection.from_dict({"bands": evidence.before["bands"]})
    comparisons = []
    for _, stats in sorted(evidence.soak.items()):
        temp = stats.temp_mean
        factory, locus = min(anchors, key=lambda a: abs(a[1].temp_c - temp))
        comparisons.append(compare_sets(stats, trial.at(temp), before.at(temp), factory, locus))
    decision = guard_decision(
        comparisons, soak_samples=evidence.soak_samples, sigmas=SIGMAS, tolerance_deg=TOLERANCE_DEG
    )
    return Verdict(decision.action, decision.reason)


def judge_by_ellipse(evidence: TrialEvidence) -> Verdict:
    """Each band of the soak is fitted afresh (reference-free); the set whose angles stay closer to that
    fit is the better one there. Worse than the set before by more than SIGMAS times the fit's own
    scatter (and TOLERANCE_DEG) in any band: rollback."""
    trial = BandedCorrection.from_dict({"bands": evidence.trial["bands"]})
    before = BandedCorrection.from_dict({"bands": evidence.before["bands"]})
    worst, measured = None, 0
    for band, stats in sorted(evidence.soak.items()):
        try:
            fit = fit_ellipse(stats)
        except InputError:
            continue  # too little of the circle seen in this band
        fresh = ellipse_correction(stats, fit)
        fresh.temp_c = stats.temp_mean
        err_trial = difference_deg(trial.at(fresh.temp_c), fresh)
        err_before = difference_deg(before.at(fresh.temp_c), fresh)
        scatter = float(np.degrees(fit.residual_rms / np.sqrt(max(stats.n, 1))))
        measured += 1
        if err_trial - err_before > SIGMAS * scatter + TOLERANCE_DEG and (worst is None or err_trial > worst[1]):
            worst = (band, err_trial, err_before)
    if worst is not None:
        band, err_trial, err_before = worst
        return Verdict("rollback", f"band {band}: {err_trial:.4f}° from the drive's own fit against {err_before:.4f}°")
    if evidence.soak_samples < MIN_SOAK_SAMPLES:
        return Verdict("wait", f"soak {evidence.soak_samples} of {MIN_SOAK_SAMPLES} samples")
    if measured:
        return Verdict("confirm", f"not worse than v{evidence.before['version']} in {measured} band(s)")
    if evidence.soak_samples >= MAX_SOAK_SAMPLES:
        return Verdict("confirm", "outcome not measurable (too little of the circle seen); kept on the refit's")
    return Verdict("wait", "outcome not measurable yet")


WATCH_S = 3600.0  # drive time of the newest windows the watch compares the running set with the factory's on
MIN_WATCH_SAMPLES = 1000  # per band
WATCH_SIGMAS = 5.0  # the watch asks at every pass, not once per set: a stricter bar against false alarms
WATCH_TOLERANCE_DEG = 0.01


@dataclass
class WatchFinding:
    band: int
    temp_c: float
    reason: str


def watch_against_factory(
    recent: dict[int, WindowStats], running: BandedCorrection, factory: BandedCorrection
) -> list[WatchFinding]:
    """The first rule, checked on the newest windows: bands where the set the drive runs is worse than its
    factory set by more than the comparison's own uncertainty (the guard's rule). A trial judges a set once,
    against the set before; this watch keeps judging what runs against the factory, so a drive that changes
    after its set was confirmed (a gain or axis step the monitor does not name) is not left worse than the
    factory until its band memory has relearned it."""
    anchors = bench_anchors(factory)
    if not anchors:
        return []
    found = []
    for band, stats in sorted(recent.items()):
        if stats.n < MIN_WATCH_SAMPLES:
            continue
        temp = stats.temp_mean
        fband, locus = min(anchors, key=lambda a: abs(a[1].temp_c - temp))
        c = compare_sets(stats, running.at(temp), fband, fband, locus)
        if c.worse(WATCH_SIGMAS, WATCH_TOLERANCE_DEG):
            found.append(
                WatchFinding(
                    band,
                    temp,
                    f"band {band}: the running set leaves {c.trial.angle_error_deg:.4f}° against the factory's "
                    f"{c.before.angle_error_deg:.4f}° (worse by {c.difference_deg:.4f}° ± {c.difference_se_deg:.4f}°)",
                )
            )
    return found
