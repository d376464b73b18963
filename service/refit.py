"""Refit one device from its merged band statistics, and decide whether the result is worth rolling out.

No I/O here: the service hands in the statistics and the sets, and gets back a decision.

With a factory set that carries its bench locus (`encoder-fleet calibrate`), a band's candidate is the
factory's correction after the drift since the bench (encoder_core/differential.py): offsets, gain
ratio and axis come from the field where the band's statistics support them, one by one; the zero and
the harmonics stay the factory's, measured against its reference. Without a bench locus (older factory
sets) nothing is fitted: the drive keeps the set it runs (NO_BENCH_LOCUS says why).

A candidate band replaces what the device runs at that temperature only when the two differ by
clearly more than the candidate's own uncertainty: then the running set is measurably wrong and the
candidate is the better estimate. Bands the refit has nothing new for keep what the device runs.
"""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np

from encoder_core.correction import BandedCorrection, Correction, angles_of
from encoder_core.differential import (
    MODEL_REACH_C,
    TERMS,
    BenchLocus,
    Drift,
    DriftFit,
    DriftModel,
    anchor_zeros,
    compose,
    fit_drifts_each,
    gate,
)
from encoder_core.held import HeldDrift, dwelt, held_drift_model, held_runs
from encoder_core.physics import BAND_WIDTH_C, REFERENCE_TEMP_C, band_of, circular_mean, wrap_rad
from encoder_core.samples import InputError
from encoder_core.stats import WindowStats
from fleet_wire import messages as wire

MIN_BAND_SAMPLES = 500  # below this a band's statistics are not fitted; above it, the fit's own errors decide
# (2000 when a candidate's error counted only its adopted terms: a 0.5 Hz drive spends under 4,000 s in a 10 °C
# band and was never fitted on the way through; bench-fleet-accuracy 0.5 Hz: median 2.85x -> 3.3x, worse hours
# 17 -> 13, and 2.2x -> 2.3x, 20 -> 18 on two other seeds)
CONFIDENCE = 3.0  # adopt when the running set is off by 3x the candidate's own uncertainty …
MIN_GAIN_DEG = 0.01  # … and by at least this much
UNBOUNDED_ERROR_DEG = 180.0  # a candidate whose drift the data cannot bound (the wire's largest error)
# why a drive whose factory set carries no bench locus gets no fitted set: without the curve its bench measured, the
# window statistics cannot tell the drift from the field's own harmonics (seed 001's trap), and the older ellipse-
# plus-density refit made such drives worse on the independent simulator (fieldsim seeds 1-8, four motions, a day at
# 5 Hz: worse than the factory set on 20 of 32, better on 2, reversing drives 0.04-0.13 deg -> 4.7-10.1 deg; moving
# only each band's centre as that refit measured it: worse on 22)
NO_BENCH_LOCUS = (
    "its factory set carries no bench locus, against which the refit measures drift: it keeps the set it runs "
    "(calibrate it again with `encoder-fleet calibrate` from its bench recording)"
)
STEP_CAUSES = ("offset_step", "gain_step", "axis_step")  # the alarms whose measured step moves the running set at once
STEP_OPEN_S = 86400.0  # drive time after an offset step in which bands with no data since may be moved


@dataclass
class BandDecision:
    band: int
    temp_c: float
    samples: int
    running_error_deg: float
    candidate_error_deg: float
    adopted: bool
    quality: dict
    candidate: dict  # the fit itself, as a band entry, whether adopted or not


@dataclass
class RefitResult:
    bands: list[dict]  # the coefficient set's band entries (docs/wire.md)
    decisions: list[BandDecision] = field(default_factory=list)
    # running bands moved by an offset change (offset_move), or carried over a step (carried_over_step)
    moved_bands: list[int] = field(default_factory=list)

    @property
    def changed(self) -> bool:
        return any(d.adopted for d in self.decisions) or bool(self.moved_bands)


def difference_deg(running: Correction, candidate: Correction) -> float:
    """RMS angle difference between two corrections around the candidate's circle, zero aside:
    the error of the running set if the candidate is right."""
    return float(differences_deg([running], [candidate])[0])


def differences_deg(runnings: list[Correction], candidates: list[Correction]) -> np.ndarray:
    """difference_deg of pairs (a refit's bands), in one array pass."""
    if not candidates:
        return np.zeros(0)
    loci = [c.locus() for c in candidates]
    d, q = np.array([d for d, _ in loci]), np.array([q for _, q in loci])
    diff = wrap_rad(angles_of(runnings, d, q) - angles_of(candidates, d, q))
    diff = wrap_rad(diff - circular_mean(diff, axis=1)[:, None])
    return np.degrees(np.sqrt(np.mean(diff**2, axis=1)))


def refit_device(
    band_stats: dict[int, WindowStats],
    running: BandedCorrection,
    factory: BandedCorrection | None = None,
    *,
    min_samples: int = MIN_BAND_SAMPLES,
    bin_temps: dict[int, np.ndarray] | None = None,
    after_step: bool = False,
    stepped_since_bench: bool = False,
    no_axis_step: bool = False,
    axis_turn: float = 0.0,
    held_watched: bool = False,
    before_step: BandedCorrection | None = None,
) -> RefitResult:
    """The device's next set (or the reasons for none) from its band statistics.

    held_watched: the drift monitor compares the positions the drive holds visit by visit, so a step of them is
    named (DeviceMonitor.watches_held_positions). Only then does a drive that holds positions get its drift from
    them (held_model): a step nobody named, inside band sums that mix the times before and after it, fits as a
    confident, wrong drift curve (0.5 Hz dwelling drives, whose 300 s windows the monitor never compares: 146
    hours worse than the factory set over 36 drive-runs).

    after_step: the monitor saw the channel offsets step (an open offset_step alarm): bands with no data since
    keep the running set moved by the offset change the fitted bands agree on (offset_move).

    stepped_since_bench: the monitor has named a step (offsets, gain or axes) since the factory's bench: the bench
    is then no point of the drift curve (no drift at its temperature would undo the step there).

    no_axis_step: no step named since the bench turned the sensor's axes (the steps were offset or gain steps). The
    positions a drive holds then still measure its drift, and the step with it, as an offset step or as one channel's
    gain, whichever the points fit (held_model; the held test names a step offset_step when it cannot tell them
    apart: DeviceMonitor.step_measured). An axis step's rotation half turns every held position alike, which no held
    point tells from the factory's zero.

    before_step: the set the drive ran before its newest step, when the monitor could not measure that step and the
    drive went back to its factory set (service.runtime.back_to_factory). Past the bands the data since the step
    speak for, the drive runs it moved by the offset change every fitted band agrees on, where they agree on one
    clear of their errors (offset_move, carried_over_step); otherwise the refit goes on as without it.

    axis_turn: the axis steps the monitor has named since the bench, summed (their delta_skew): each candidate's zero
    is then the factory's moved by them. A turn of one sensor axis is half a shear, which the windows see, and half a
    rotation of both axes, which none does; the step's move corrected both, and a candidate anchored to the factory's
    own zero undid the rotation (s7-20hz-07: a set moved for a 0.43 % turn ran 0.02°, the refits adopted after it
    0.12°).

    bin_temps (optional, per band, additive over its windows: WindowStats.bin_temps): Σ window mean
    temperature × window count per angle bin. With them each band's fit sets aside the locus's common scale
    changing with temperature across its bins (see encoder_core.differential.fit_drifts)."""
    anchors = bench_anchors(factory)
    if not anchors:
        return RefitResult(bands=[])  # NO_BENCH_LOCUS
    return refit_from_bench(
        band_stats,
        running,
        anchors,
        min_samples=min_samples,
        bin_temps=bin_temps,
        after_step=after_step,
        stepped_since_bench=stepped_since_bench,
        no_axis_step=no_axis_step,
        axis_turn=axis_turn,
        held_watched=held_watched,
        before_step=before_step,
    )


def bench_anchors(factory: BandedCorrection | None) -> list[tuple[Correction, BenchLocus]]:
    """The factory's bands that carry the bench locus they were measured on."""
    if factory is None:
        return []
    return [(b, BenchLocus.from_dict(b.bench_locus)) for b in factory.bands if b.bench_locus is not None]


def refit_from_bench(
    band_stats: dict[int, WindowStats],
    running: BandedCorrection,
    anchors: list[tuple[Correction, BenchLocus]],
    *,
    min_samples: int = MIN_BAND_SAMPLES,
    bin_temps: dict[int, np.ndarray] | None = None,
    after_step: bool = False,
    stepped_since_bench: bool = False,
    no_axis_step: bool = False,
    axis_turn: float = 0.0,
    held_watched: bool = False,
    before_step: BandedCorrection | None = None,
) -> RefitResult:
    """bin_temps (optional): per band, Σ over its windows of the window's mean temperature times the window's
    count in each angle bin; with it each band's fit sets aside the common scale's change across its bins."""
    fits = band_fits(band_stats, anchors, min_samples, bin_temps)
    model = drift_model(fits, bench_holds=not stepped_since_bench)
    held = None
    if held_watched and (not stepped_since_bench or no_axis_step):
        # after offset or gain steps the band sums hold the drive since the last one (restart_band_memory), and a
        # shift or a stretch of the circle is no turn of it: the held positions' angles still tie to the bench's
        held = held_model(band_stats, anchors, min_samples, offsets_stepped=stepped_since_bench)
    if held is not None:
        # a drive that holds positions: the held points see the drift along the circle, where the bands' few
        # angle bins leave the ellipse fit guessing (or fitting none at all)
        model = held.drift.model
        fits = {band: (None, stats, None, None) for band, stats in held.bands.items()}
    result = RefitResult(bands=[])
    chosen: dict[int, dict] = {}
    moves = []  # per fitted band: where the candidate puts the channels' centre against the running set, ± error
    move_temps = []  # and the temperature it was measured at
    move_corrs = []  # and the candidate it was measured on
    candidates = []  # per band the refit speaks for: (band, statistics, quality, the candidate's error, locus, errors)
    corrs = []  # and its candidate correction
    to_anchor = []  # (place, ruler, drift) of the candidates that take the ruler's zero
    spoken = model_bands(fits, model)
    running_at = {band_index(c): c.temp_c for c in running.bands}  # each running entry's temperature, by band
    for band, temp_c, stats in spoken:
        factory, locus = min(anchors, key=lambda a: abs(a[1].temp_c - temp_c))
        if held is not None and band < spoken[-1][0]:
            # the held curve speaks at every band's lower edge, ten kelvin apart through the bench's (+20 °C), and
            # the top band at its centre: the agent interpolates linearly between entries, and an entry at each
            # band's mean left 15 K between the bench and the band above it, where the curve's square bent away
            # from the line (s1-20hz-06: 0.0135° at +26.7 °C against the factory's 0.0075°)
            temp_c = band * BAND_WIDTH_C
        elif model is not None and band == band_of(locus.temp_c):
            # the band that holds the bench speaks at the bench: there the factory is measured and the curve
            # passes through it, where an entry at the band's mean would leave the agent interpolating to the
            # bench between two fitted temperatures, each with its error (a few millidegrees worse than the factory
            # in the hours a drive spends near +20 °C)
            temp_c = locus.temp_c
        if model is not None:
            terms, errors = model.at(temp_c)
            chi2 = held.drift.chi2_dof if held is not None else fits[band][0].chi2_dof if band in fits else None
        else:
            fit = fits[band][0]
            terms, errors, chi2 = fit.drift.terms(locus.radius), fit.errors, fit.chi2_dof
        if held is not None:
            corr, quality, err_new = held_candidate(held, terms, errors, temp_c, factory, locus)
        else:
            corr, quality, err_new, drift = drift_candidate(terms, errors, temp_c, factory, locus)
            # its zero the ruler's: the factory, moved by the axis turns named since the bench
            to_anchor.append((len(corrs), factory.axes_moved(axis_turn) if axis_turn else factory, drift))
        # a fit that ran away (bins a loose magnet's collapsed windows mix with held positions) has a misfit of inf or
        # NaN, which no JSON carries: the set, and the fits recorded with it, were refused at every pass
        chi2 = chi2 if chi2 is not None and np.isfinite(chi2) else None
        quality = {**quality, "samples": stats.n if stats is not None else 0, "chi2_dof": chi2}
        candidates.append((band, stats, quality, err_new, locus, errors))
        corrs.append(corr)
    # every band's candidate anchored and checked against the running set around its circle, in one array pass each
    if to_anchor:
        places, rulers, drifts = zip(*to_anchor)
        loci = [candidates[k][4] for k in places]
        for k, corr in zip(places, anchor_zeros([corrs[k] for k in places], rulers, loci, drifts)):
            corrs[k] = corr
    nows = running.at_each([corr.temp_c for corr in corrs])
    errs_now = differences_deg(nows, corrs)
    for (band, stats, quality, err_new, locus, errors), corr, now, err_now in zip(candidates, corrs, nows, errs_now):
        err_now = float(err_now)
        if stats is not None:
            moves.append(
                (centre(corr) - centre(now), locus.radius * np.array([errors["offset_d"], errors["offset_q"]]))
            )
            move_temps.append(corr.temp_c)
            move_corrs.append(corr)
        adopt = err_now > max(MIN_GAIN_DEG, CONFIDENCE * err_new)
        if held is not None and not held.drift.covers(corr.temp_c):
            adopt = False  # a position the drive holds was not seen near this temperature: its angle is a guess
        entry = band_entry(band, corr, {**quality, "estimated_error_deg": err_new})
        lower_c = band * BAND_WIDTH_C
        bench_below = not stepped_since_bench and lower_c - 1.0 <= locus.temp_c < lower_c  # (holding it: at it already)
        kept_at_edge = abs(running_at.get(band, lower_c) - lower_c) < 1e-6  # no running entry there, or ours
        if not adopt and held is not None and bench_below and band == spoken[-1][0] and kept_at_edge:
            # the top band kept as the device runs it, with the bench just below its lower edge: it speaks at that
            # edge, where the drift is none, not at its centre (s9-20hz-02's first held set: the drift fitted at +10 °C
            # and the factory at +25 °C, so the agent ran a third of the +10 °C drift at the bench: 0.0124° in an hour
            # at +18..+29 °C, the factory set's 0.0097°), and so do the refits after it. A top band above the bench
            # keeps handing over at its centre: there the drift grows on past the data (s11-20hz-06 lost 5 % of its
            # gain at the lower edge)
            now = running.at(lower_c)
        chosen[band] = entry if adopt else band_entry(band, now, {**quality, "estimated_error_deg": err_now})
        result.decisions.append(
            BandDecision(
                band=band,
                temp_c=corr.temp_c,
                samples=quality["samples"],
                running_error_deg=err_now,
                candidate_error_deg=err_new,
                adopted=adopt,
                quality=chosen[band]["quality"],
                candidate=entry,
            )
        )
    if not result.decisions:
        return result
    # what the refit says nothing about stays as the device runs it, moved by an offset change every fitted band
    # agrees on (a step the monitor saw restarts band memory: the first band fitted after it moves the rest)
    carried = None
    if before_step is not None and move_corrs:
        # the same candidates against the set the drive ran before the step: there its drift was measured, so what
        # they agree it is off by is the step alone
        thens = before_step.at_each(move_temps)
        carried = offset_move(
            [(centre(c) - centre(then), err) for c, then, (_, err) in zip(move_corrs, thens, moves)],
            anchors[0][1].radius,
        )
    moved = offset_move(moves, anchors[0][1].radius) if after_step and carried is None else None
    if carried is not None:
        running, result.moved_bands = carried_over_step(running, before_step, carried, set(chosen))
    elif moved is not None:
        running, result.moved_bands = moved_near(running, moved, move_temps, set(chosen))
    # without a drift curve (one band fitted) nothing measured the drift between that band and its neighbours
    # (with one, the curve through the bench says it, and reaches MODEL_REACH_C past the fitted bands: holding the
    # running set a band away from every adopted band there cost evenly turning drives 5-25 % of their gain)
    # and only where the drive dwelt: a reversing drive's arc spreads its samples over the circle and its lone
    # band's reach cost three reversing drives an hour each after axis steps
    adopted = {d.band for d in result.decisions if d.adopted and dwelt(fits[d.band][1])} if model is None else set()
    result.bands = with_running_bands(chosen, running, adopted)
    return result


@dataclass
class HeldFit:
    drift: HeldDrift
    bands: dict[int, WindowStats]  # the bands it speaks for: those with held points


def held_model(
    band_stats: dict[int, WindowStats], anchors, min_samples: int, *, offsets_stepped: bool = False
) -> HeldFit | None:
    """The drift curve from the positions the drive holds (encoder_core.held.held_drift_model), when most of its
    samples are in bands where it dwelt and the factory was measured at one bench temperature; None otherwise, or
    when too few positions were held across bands."""
    bands = {band: stats for band, stats in band_stats.items() if stats.n >= min_samples}
    dwelling = sum(stats.n for stats in bands.values() if dwelt(stats))
    if len(anchors) != 1 or not bands or dwelling < 0.5 * sum(stats.n for stats in bands.values()):
        # one bench: the held fit is the drift since it, applied to its factory band (a factory measured at several
        # temperatures has the drift to each in its own band, and the ellipse path keeps to it)
        return None
    locus = anchors[0][1]
    found = held_drift_model(list(bands.values()), locus, offsets_stepped=offsets_stepped)
    if found is None:
        return None
    return HeldFit(found, {b: s for b, s in bands.items() if held_runs(s, split=True)})


def step_moved_bands(bands: list[dict], cause: str, step: dict, scale: float) -> list[dict]:
    """A coefficient set's band entries for channels that stepped as the drift monitor measured it (an alarm's
    parameters): an offset_step's (delta_d, delta_q), fractions of the amplitude in the device's statistics scale
    (raw units per unit), a gain_step's delta_imbalance or an axis_step's delta_skew. Every band reads the stepped
    channels as it read them before the step, band and quality kept."""
    moved = []
    for entry in bands:
        corr = Correction.from_dict({k: v for k, v in entry.items() if k not in ("band", "quality")})
        if cause == "offset_step":
            after = corr.offsets_moved(step["delta_d"] * scale, step["delta_q"] * scale)
        elif cause == "gain_step":
            after = corr.imbalance_moved(step["delta_imbalance"])
        elif cause == "axis_step":
            after = corr.axes_moved(step["delta_skew"])
        else:
            raise ValueError(f"no move for a {cause} alarm")
        moved.append({"band": entry["band"], **after.to_dict(), "quality": dict(entry.get("quality", {}))})
    return moved


def centre(corr: Correction) -> np.ndarray:
    """The raw (d, q) point a correction takes to the circle's centre."""
    return np.array([-corr.w2 / corr.w1, -corr.w4 / corr.w3])


def moved_near(
    running: BandedCorrection, move: tuple[float, float], temps: list[float], spoken: set[int]
) -> tuple[BandedCorrection, list[int]]:
    """The running set moved by an offset change (offset_move), and the bands the refit said nothing about that it
    moved (the others are the refit's). A move is measured against the running set at the fitted bands'
    temperatures (`temps`), so it is the step plus the drift there that the running set does not correct. Where
    the running set has an entry within MODEL_REACH_C of each of them, that is its fit's error, small beside a step,
    and the move reaches every band. Where it runs an entry from farther away (the factory set again: one entry,
    flat in temperature), the move carries that entry's drift out to the fitted bands, and it reaches only the
    bands within MODEL_REACH_C of them: a move measured at -16..-6 °C took the offsets' cold drift to the +20 °C
    entry, which the drive then ran up to +63 °C (s8-20hz-10-dwell, six hours worse than the factory set;
    s10-20hz-10-dwell, from +35..+45 °C down to -20 °C, two)."""

    def reach(temp_c: float | None, others) -> bool:
        return temp_c is None or min(abs(temp_c - t) for t in others) <= MODEL_REACH_C

    entries = [c.temp_c for c in running.bands if c.temp_c is not None]
    fitted_there = not entries or all(reach(t, entries) for t in temps)
    near = [fitted_there or reach(corr.temp_c, temps) for corr in running.bands]
    moved = [corr.offsets_moved(*move) if n else corr for corr, n in zip(running.bands, near)]
    bands = sorted(band_index(c) for c, n in zip(running.bands, near) if n and band_index(c) not in spoken)
    return BandedCorrection(moved, running.thermal_lag_s), bands


def carried_over_step(
    running: BandedCorrection, before_step: BandedCorrection, move: tuple[float, float], spoken: set[int]
) -> tuple[BandedCorrection, list[int]]:
    """The running set inside the bands the refit speaks for (`spoken`), and past them the set the drive ran
    before a step the monitor could not measure, moved by the offset change the fitted bands agree on against it
    (offset_move); and the bands whose entry that moves by MIN_GAIN_DEG or more. After such a step the drive runs
    its factory set again (flat in temperature, off by the step everywhere) and the data since speak only for the
    temperatures visited since: s8-20hz-10-dwell, its bands refitted from -20 to +24 °C after an offset step at
    -10 °C, ran the +24 °C entry flat up to +63 °C, 0.16-0.26° for five hours against the factory set's
    0.08-0.22°, where the set it ran before the step, moved, would have left ~0.01°."""
    lo, hi = min(spoken), max(spoken)
    kept = [c for c in running.bands if lo <= band_index(c) <= hi]
    carried = [c.offsets_moved(*move) for c in before_step.bands if not lo <= band_index(c) <= hi]
    if not carried:
        return running, []
    runs = {band_index(r): r for r in running.bands}  # one entry a band (with_running_bands)
    changed = [b for c in carried if (b := band_index(c)) not in runs or difference_deg(runs[b], c) >= MIN_GAIN_DEG]
    return BandedCorrection(kept + carried, running.thermal_lag_s), sorted(changed)


def offset_move(moves: list[tuple[np.ndarray, np.ndarray]], radius: float) -> tuple[float, float] | None:
    """The channels' offset change (raw units) since the running set was fitted, when every fitted band sees
    it: the bands' weighted mean clear of CONFIDENCE times the smallest band error (the model's errors are
    correlated across bands: no credit for their number), each band within CONFIDENCE of the mean, and the
    angle it would leave over MIN_GAIN_DEG. None when the data do not support a move."""
    if not moves:
        return None
    deltas = np.array([m for m, _ in moves])
    errors = np.maximum(np.array([e for _, e in moves]), 1e-12)
    if not np.all(np.isfinite(errors)):
        return None
    mean = np.sum(deltas / errors**2, axis=0) / np.sum(1 / errors**2, axis=0)
    floor = errors.min(axis=0)
    if np.any(np.abs(deltas - mean) > CONFIDENCE * np.hypot(errors, floor)):
        return None  # the bands disagree: not one offset change
    if not np.any(np.abs(mean) > CONFIDENCE * floor) or np.degrees(np.hypot(*mean) / radius) < MIN_GAIN_DEG:
        return None
    return float(mean[0]), float(mean[1])


def band_fits(
    band_stats, anchors, min_samples, bin_temps
) -> dict[int, tuple[DriftFit, WindowStats, Correction, BenchLocus]]:
    """Each band's drift fit (bands whose statistics do not pin it down are left out), with the in-band gain
    slope where the bins' temperatures are known. (Until 2026-11-25 a second pass moved each bin to the
    band's temperature along the slope of the neighbouring bands' first-pass fits; on a drive reversing over
    arcs while it warmed those fits were as wrong as the band's, and the second pass adopted the error with
    confidence: tests/test_refit.py, warming arcs.)"""
    chosen, dtemps = band_fit_inputs(band_stats, anchors, min_samples, bin_temps)
    return fit_bands(chosen, dtemps=dtemps)


def band_fit_inputs(band_stats, anchors, min_samples, bin_temps) -> tuple[dict, dict]:
    """What band_fits fits: band -> (statistics, nearest factory band, its bench locus) of the bands with enough
    samples, and band -> its bins' temperatures less the band's, where known."""
    chosen = {
        band: (stats, *min(anchors, key=lambda a: abs(a[1].temp_c - stats.temp_mean)))
        for band, stats in sorted(band_stats.items())
        if stats.n >= min_samples
    }
    dtemps = {band: bin_dtemps(bin_temps[band], chosen[band][0]) for band in chosen if band in (bin_temps or {})}
    return chosen, dtemps


def prefetch_band_fits(drives: list[tuple[dict[int, WindowStats], list]], min_samples: int = MIN_BAND_SAMPLES) -> int:
    """The band fits of many drives' coming refits, in one batch, into FIT_MEMO; returns how many were fitted.
    drives: (band statistics, bench anchors) each, as refit_device will read them. A drive's dozen bands fitted
    alone cost ~6-8 ms; fitted in a batch with other drives' ~3.5 ms (fit_drifts_each's arrays amortise numpy's
    per-call cost), and a fit does not depend on its batch, so the refit that finds it in the memo is the same."""
    keys, fields, loci, dtemps_of = {}, [], [], []  # keys: insertion-ordered, one fit per content
    for band_stats, anchors in drives:
        if not anchors:
            continue  # a factory set without its bench locus: such a drive is not refit (NO_BENCH_LOCUS)
        bin_temps = {band: stats.bin_temps() for band, stats in band_stats.items()}
        chosen, dtemps = band_fit_inputs(band_stats, anchors, min_samples, bin_temps)
        for band, (stats, _, locus) in chosen.items():
            key = _fit_key(stats, locus, dtemps.get(band))
            if key in keys or FIT_MEMO.get(key) is not None:
                continue
            keys[key] = None
            fields.append(stats)
            loci.append(locus)
            dtemps_of.append(dtemps.get(band))
    for key, fit in zip(keys, fit_drifts_each(fields, loci, bin_dtemps=dtemps_of)):
        FIT_MEMO.put(key, fit)
    return len(keys)


def bin_dtemps(bin_temp_sum: np.ndarray, stats: WindowStats) -> np.ndarray:
    """Each angle bin's mean temperature minus the band's (0 for empty bins)."""
    counts = stats.bins[:, 0]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(counts > 0, np.asarray(bin_temp_sum, float) / counts - stats.temp_mean, 0.0)


def fit_bands(chosen: dict, *, dtemps: dict | None = None) -> dict:
    """band -> (statistics, factory band, bench locus) fitted in one batch, each against its bench locus;
    bands too little of the circle pins are left out. dtemps: per band, its bins' temperatures less its own
    (the fit then has the in-band gain slope, see fit_drifts). A band whose sums and bench locus are the ones
    fitted before is not fitted again (FIT_MEMO): between two hourly refits a drive visits a band or two."""
    dtemps = dtemps or {}
    keys = {band: _fit_key(stats, locus, dtemps.get(band)) for band, (stats, _, locus) in chosen.items()}
    found = {band: hit for band in chosen if (hit := FIT_MEMO.get(keys[band])) is not None}
    new = [band for band in chosen if band not in found]
    fits = fit_drifts_each(
        [chosen[b][0] for b in new], [chosen[b][2] for b in new], bin_dtemps=[dtemps.get(b) for b in new]
    )
    for band, fit in zip(new, fits):
        found[band] = FIT_MEMO.put(keys[band], fit)
    return {band: (fit, *chosen[band]) for band, fit in sorted(found.items()) if not isinstance(fit, InputError)}


class FitMemo:
    """The last FIT_MEMO_SIZE band fits, by content (a digest of what the fit reads), least recently used out.
    A fit is a pure function of its inputs, so a hit is the fit itself; one process's refits share it."""

    def __init__(self, size: int):
        self.size = size
        self._fits: OrderedDict[bytes, DriftFit | InputError] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key: bytes) -> DriftFit | InputError | None:
        with self._lock:
            fit = self._fits.get(key)
            if fit is not None:
                self._fits.move_to_end(key)
            return fit

    def clear(self) -> None:
        with self._lock:
            self._fits.clear()

    def put(self, key: bytes, fit: DriftFit | InputError) -> DriftFit | InputError:
        with self._lock:
            self._fits[key] = fit
            while len(self._fits) > self.size:
                self._fits.popitem(last=False)
        return fit


FIT_MEMO_SIZE = 50_000  # band fits, ~1.2 KB each (60 MB): a dozen bands each of ~4,000 drives
FIT_MEMO = FitMemo(FIT_MEMO_SIZE)


def _fit_key(stats: WindowStats, locus: BenchLocus, dtemps: np.ndarray | None) -> bytes:
    """A digest of everything fit_drifts reads of one band: its bins and frame, its bins' temperatures, the bench
    locus and the precision of its curve."""
    digest = hashlib.blake2b(digest_size=20)
    digest.update(np.array([stats.scale, stats.center_d, stats.center_q, locus.precision], float).tobytes())
    for part in (stats.bins, locus.d, locus.q):
        digest.update(np.ascontiguousarray(part, float).tobytes())
    digest.update(b"-" if dtemps is None else np.ascontiguousarray(dtemps, float).tobytes())
    return digest.digest()


def band_index(corr: Correction) -> int:
    return int(np.floor((corr.temp_c if corr.temp_c is not None else REFERENCE_TEMP_C) / 10.0))


def drift_model(fits, *, bench_holds: bool = True) -> DriftModel | None:
    """All bands' drift fits as one smooth function of temperature (None with fewer than two bands); through the
    bench while it holds (DriftModel.fit)."""
    if not fits:
        return None
    locus = next(iter(fits.values()))[3]
    return DriftModel.fit(
        [(stats.temp_mean, fit) for fit, stats, _, _ in fits.values()],
        locus.temp_c,
        locus.radius,
        bench_holds=bench_holds,
    )


def model_bands(fits, model: DriftModel | None):
    """(band, temperature, statistics or None) of every band the refit speaks for: the fitted ones at their
    mean temperature, and with a model, the unvisited bands within its reach at their centre."""
    out = {band: (band, stats.temp_mean, stats) for band, (_, stats, _, _) in fits.items()}
    if model is not None:
        lo, hi = min(fits), max(fits)
        for band in range(lo - 1, hi + 2):
            centre = (band + 0.5) * BAND_WIDTH_C
            if band not in out and model.reaches(centre):
                out[band] = (band, centre, None)
    return [out[b] for b in sorted(out)]


def drift_candidate(
    terms: dict[str, float],
    errors: dict[str, float],
    temp_c: float,
    factory: Correction,
    locus: BenchLocus,
) -> tuple[Correction, dict, float, Drift]:
    """The factory's correction after the supported drift terms, with its quality, uncertainty (deg) and the
    drift applied; its zero is still the factory's own (refit_from_bench anchors every band's to its ruler at
    once: anchor_zeros)."""
    radius = locus.radius
    kept = gate(terms, errors)
    if not np.isfinite(kept.get("common", 0.0)):
        # the common scale, which moves no angle, of a fit that ran away: the factory's (a NaN one made the candidate's
        # every weight NaN, which the fits recorded with the set refuse)
        kept["common"] = 0.0
    drift = Drift.from_terms(kept, np.array([locus.d[0], locus.q[0]]), radius)
    corr = compose(factory, drift)
    corr.temp_c = float(temp_c)
    # the uncertainty of the whole drift the band's data measured, not only of the terms that passed the gate: a
    # term held at the factory's value is as uncertain as its estimate, and a fit that cannot pin one term (an arc,
    # a few held positions) has correlated, understated errors in the rest. Counting only the adopted terms made
    # "nothing measurable" a candidate of zero uncertainty (bench-fleet-accuracy 20 Hz: worse hours 37 -> 17)
    err = float(np.degrees(np.sqrt(sum(errors[t] ** 2 for t in TERMS))))
    err = min(err, UNBOUNDED_ERROR_DEG) if np.isfinite(err) else UNBOUNDED_ERROR_DEG
    quality = {
        "drift_terms": {t: kept[t] for t in TERMS},
        "drift_errors": {t: errors[t] if np.isfinite(errors[t]) else None for t in TERMS},
    }
    return corr, quality, err, drift


def held_candidate(
    held: HeldFit, terms: dict, errors: dict, temp_c: float, factory: Correction, locus: BenchLocus
) -> tuple[Correction, dict, float]:
    """The factory's correction after the drift the held positions measured, its zero turned by their rotation,
    with its uncertainty where the drive sits (deg). No term is gated: a combination of terms that moves no held
    position stays near the factory's by the fit's prior, and one that moves them is measured by them, however
    loosely each term alone is."""
    radius = locus.radius
    drift = Drift.from_terms({t: terms[t] for t in TERMS}, np.array([locus.d[0], locus.q[0]]), radius)
    # not anchored to the factory's zero (drift_candidate's, anchor_zeros): the held positions measured the turn
    # along the circle, the lower-triangular map's share of it included
    corr = compose(factory, drift)
    corr.zero_offset_rad = float(wrap_rad(corr.zero_offset_rad - terms["zero"]))
    corr.temp_c = float(temp_c)
    err = float(np.degrees(held.drift.angle_error(temp_c)))
    quality = {
        "drift_terms": {t: terms[t] for t in TERMS},
        "drift_errors": {t: errors[t] if np.isfinite(errors[t]) else None for t in TERMS},
    }
    return corr, quality, err


def with_running_bands(
    chosen: dict[int, dict], running: BandedCorrection, adopted: set[int] = frozenset()
) -> list[dict]:
    """The set's band entries: the refit's, and the running set's bands it says nothing about, as the device
    runs them (a set of one fitted band would otherwise hold that band's correction at every temperature).

    The agent interpolates between bands, so an adopted band whose neighbour in the set is more than a band away
    gets the running set, as it runs there, one band width toward that neighbour: its drift reaches only as far as
    the data that measured it. (s5-20hz-06, a dwelling drive: one band fitted at +63 °C beside the bench's at
    +20 °C carried its drift by a straight line across +30..+44 °C, where the offsets' drift, a line plus a square,
    has the other sign: six hours worse than the factory set, and the set ran for three days.) Beyond the
    outermost band the set is flat, the nearest fitted band's, as before."""
    out = dict(chosen)
    for corr in running.bands:
        band = band_index(corr)
        if band not in out:
            out[band] = band_entry(band, Correction.from_dict({**corr.to_dict(), "bench_locus": None}), {"samples": 0})
    for band in sorted(adopted):
        for side in (-1, 1):
            beyond = [b for b in out if (b - band) * side > 0]
            if not beyond or min(abs(b - band) for b in beyond) <= 1:
                continue
            temp_c = out[band]["temp_c"] + side * BAND_WIDTH_C
            hold = band_of(temp_c)
            if hold not in out and hold != band:
                held = Correction.from_dict({**running.at(temp_c).to_dict(), "bench_locus": None})
                out[hold] = band_entry(hold, held, {"samples": 0})
    return [out[b] for b in sorted(out)]


def band_entry(band: int, corr: Correction, quality: dict) -> dict:
    keys = ("samples", "residual_rms_rad", "radius_ripple_rad", "estimated_error_deg")
    keys += ("drift_terms", "drift_errors", "chi2_dof")
    return wire.band_entry(band, corr.to_dict(), {k: quality[k] for k in keys if k in quality})
