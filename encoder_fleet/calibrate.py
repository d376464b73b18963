"""`encoder-fleet calibrate BENCH.csv --out FACTORY.json`: the end-of-line calibration.

A bench recording with a reference angle (columns t, d, q, temp_c, theta_ref_deg) is fitted per
temperature plateau by `OursLsRef`: the full channel map, the zero and the angle harmonics, all
measured against the reference. Each band also carries its bench locus (d and q as Fourier series
of the reference angle, `encoder_core.differential.BenchLocus`): the shape of the drive's own field,
which the fleet's reference-free refits need to tell drift from field harmonics. The output is the
coefficient set (version 0, basis factory) that `encoder-fleet agent --factory FACTORY.json` reads.
Each band is checked against its own reference: a handful of glitch rows is left out and reported, a reference
that disagrees with d, q beyond them (or beyond the bench's noise floor) is refused, since every drive's set is
judged against this one for life.
"""

from __future__ import annotations

import json

import numpy as np

from encoder_core.correction import BandedCorrection, Correction
from encoder_core.differential import BenchLocus
from encoder_core.methods import OursLsRef
from encoder_core.physics import REFERENCE_TEMP_C, wrap_rad
from encoder_core.samples import InputError, Samples, check_angle_coverage
from encoder_fleet.argtypes import positive_float
from encoder_fleet.outputs import write_file

PLATEAU_GAP_C = 2.0  # a bench's temperature plateaus are separated by more than this
# a bench holds each plateau while the shaft steps through its reference table, and ramps between them: the samples
# of a plateau crowd into a few bins of PLATEAU_BIN_C, a ramp's spread thinly over all the bins it passes through
PLATEAU_BIN_C = 0.5
PLATEAU_SHARE = 0.05  # bins under this share of the fullest one are a ramp's (or a plateau's thin tails) ...
PLATEAU_CONTRAST = 4.0  # ... and a bin this many times as full as they typically are is a plateau's
PLATEAU_MIN_SAMPLES = 64  # and holds at least this many (what a band's fit needs)
# a row the fit misses by this many robust sigmas (1.4826 x the median miss) is a glitch, not noise (Gaussian: 2e-9)
GLITCH_SIGMAS = 6.0
GLITCH_FLOOR_DEG = 0.01  # nor is a miss under this (a noise-free simulated bench's MAD is rounding)
GLITCH_SHARE = 0.02  # more of a band than this off the fit is a wrong reference, not a handful (impulses: 0.5 %)
RADIUS_TOLERANCE = 0.12  # a corrected point this far off the unit circle is a dropped read (plausible_mask's)
GLITCH_PASSES = 5  # refits until the rows left out stop changing
# a band that misses its own reference by more than this many times the bench's noise floor carries an error of its
# own into the fleet, which measures every set against it (bench-methods' goal for ours-ls-ref is 1.5: a 12-bit
# converter's rounding alone, the simulator's noise-free bench, is 1.35)
RESIDUAL_RATIO = 2.0
REVERSED_AGREEMENT = 0.5  # d, q's angle follows minus the reference this closely (1: exactly): counted the other way
RADIANS_SLACK = 1.01  # a reference column spanning π to 2π·this "degrees" is one turn in radians


def plateaus(temp_c: np.ndarray) -> np.ndarray:
    """Plateau index of each sample, -1 for a ramp's samples between plateaus (left out of every band): the samples
    in or next to a crowded temperature bin, sorted, split where their temperatures jump by more than PLATEAU_GAP_C.
    A bench that records its ramps (the simulator's does) passes through every temperature between its plateaus, so
    splitting at gaps alone made it one plateau: the whole bench fitted as one band at its mean temperature."""
    bins = np.floor((temp_c - temp_c.min()) / PLATEAU_BIN_C).astype(int)
    counts = np.bincount(bins)
    # a plateau is crowded against the ramps, not against the fullest plateau: a short plateau beside a long one
    # (400 samples at -40 °C, 10,000 at +20 °C) is a plateau still
    thin = counts[(counts > 0) & (counts < PLATEAU_SHARE * counts.max())]
    floor = max(PLATEAU_MIN_SAMPLES, PLATEAU_CONTRAST * float(np.median(thin))) if thin.size else PLATEAU_MIN_SAMPLES
    crowded = np.concatenate(([False], counts >= min(floor, counts.max()), [False]))
    held = crowded[bins] | crowded[bins + 1] | crowded[bins + 2]  # the bin before, its own, the bin after
    out = np.full(temp_c.size, -1)
    idx = np.flatnonzero(held)
    order = idx[np.argsort(temp_c[idx])]
    out[order] = np.concatenate(([0], np.cumsum(np.diff(temp_c[order]) > PLATEAU_GAP_C)))
    return out


def fit_against_reference(samples: Samples) -> tuple[Correction, np.ndarray]:
    """OursLsRef on the rows that agree with the reference, and which rows those are. A reference glitch (a read
    error: theta_ref far off) or a dropped read (d, q collapsed) pulls a least-squares fit everywhere around the
    circle: 6 of 3,600 rows made a set that misses the good reference by 0.34° rms, 1.12° max (0.08°, 0.30°
    without them). So the fit is repeated without the rows it misses by far more than the others (GLITCH_SIGMAS)
    or that lie off its circle. The circle's centre is the fit's: the median of d and q that OursLsRef's own
    plausibility mask centres on is off the centre on a bench that steps finer over one half of the circle than
    the other, and the mask then left the other half out."""
    method = OursLsRef(outlier_tolerance=None)  # rows are left out here, around the fit's centre
    keep = np.ones(len(samples), bool)
    for _ in range(GLITCH_PASSES):
        corr, _ = method.fit_band(samples.subset(keep), None)
        miss = np.abs(wrap_rad(corr.angle(samples.d, samples.q) - samples.theta_ref))
        sigma = 1.4826 * float(np.median(miss[keep]))
        radius = BandedCorrection([corr]).radius(samples.d, samples.q)
        agree = (miss <= max(GLITCH_SIGMAS * sigma, np.radians(GLITCH_FLOOR_DEG))) & (
            np.abs(radius - 1) <= RADIUS_TOLERANCE
        )
        if np.array_equal(agree, keep):
            break
        if (~agree).sum() > GLITCH_SHARE * agree.size:
            raise InputError(
                f"{int((~agree).sum())} of {agree.size} rows disagree with the reference angle (more than"
                f" {GLITCH_SHARE:.0%}: not a handful of glitches; first at t = {samples.t[~agree][0]:g})"
            )
        check_angle_coverage(samples.theta_ref[agree], min_sectors=12, what="reference angle (rows that agree)")
        keep = agree
    else:  # still changing: the fit of the rows returned
        corr, _ = method.fit_band(samples.subset(keep), None)
    return corr, keep


def miss_deg(corr: Correction, samples: Samples) -> np.ndarray:
    """Each row's miss of its bench reference by the band's angle (degrees, wrapped)."""
    return np.degrees(wrap_rad(corr.angle(samples.d, samples.q) - samples.theta_ref))


def runs_said(shifts: dict[int, float]) -> str:
    return ", ".join(f"run {r} {v:+.3f}°" for r, v in shifts.items())


def run_shifts(corr: Correction, samples: Samples) -> dict[int, float]:
    """Each run's mean miss of the reference (degrees), when the band holds several runs: a shaft re-mounted between
    runs, or a reference slipped on its coupling, shifts the reference by a constant no fit can predict, and the
    set's zero splits the difference. Reported as the bench's run-to-run repeatability; {} for a band of one run."""
    if samples.run is None or np.unique(samples.run).size < 2:
        return {}
    miss = miss_deg(corr, samples)
    return {int(r): float(np.mean(miss[samples.run == r])) for r in np.unique(samples.run)}


def reference_miss(corr: Correction, samples: Samples) -> tuple[float, float, float]:
    """How far the band's angle is from its bench reference, rms and max (degrees), and the bench's noise floor:
    the misses' scatter from one row to the next (robust, over √2), which the systematic error a set carries (a
    smooth function of the angle, or a reference that slipped once) leaves out, as it leaves out d, q's noise. A
    row that repeats the one before (d, q and the reference as they were: a logger faster than the bench, a jig
    holding its angle) is no new reading: counted, its step of 0 made the floor 0.000° and every band refused."""
    miss = miss_deg(corr, samples)
    new = (np.diff(samples.d) != 0) | (np.diff(samples.q) != 0) | (np.diff(samples.theta_ref) != 0)
    step = np.diff(miss)[new]
    if step.size == 0:  # not one new reading: no scatter to tell
        return float(np.sqrt(np.mean(miss**2))), float(np.max(np.abs(miss))), 0.0
    floor = 1.4826 * float(np.median(np.abs(step - np.median(step)))) / np.sqrt(2)
    return float(np.sqrt(np.mean(miss**2))), float(np.max(np.abs(miss))), floor


def calibrate_band(samples: Samples, max_miss_ratio: float = RESIDUAL_RATIO) -> tuple[Correction, np.ndarray]:
    """One plateau: the correction fitted against the reference with the bench locus attached, and the rows it
    is fitted on (the others are glitches). max_miss_ratio: the most the band may miss its reference, in noise
    floors (a line's own acceptance bound; RESIDUAL_RATIO by default)."""
    check_angle_coverage(samples.theta_ref, min_sectors=12, what="reference angle")
    # d, q turning from d towards q while the reference turns back fit only as a mirror image, which
    # from_inverse_matrix refuses as "are d and q swapped?": a reference counted the other way is the same thing
    phi = np.arctan2(samples.q - np.mean(samples.q), samples.d - np.mean(samples.d))
    back = abs(np.mean(np.exp(1j * (phi + samples.theta_ref))))
    if back > REVERSED_AGREEMENT and back > abs(np.mean(np.exp(1j * (phi - samples.theta_ref)))):
        raise InputError(
            "the reference angle turns the other way than d, q (from d towards q): theta_ref_deg counted the"
            " other way round (as minus the angle), or d and q swapped"
        )
    corr, keep = fit_against_reference(samples)
    rms, worst, floor = reference_miss(corr, samples.subset(keep))
    if rms > max_miss_ratio * max(floor, GLITCH_FLOOR_DEG):
        shifts = run_shifts(corr, samples.subset(keep))
        why = (
            f"its runs sit apart by {runs_said(shifts)} (re-mounted between them, or the reference slipped)"
            if shifts
            else "the reference and d, q disagree along the bench (a reference that slipped, lagged or is not this"
            " shaft's angle)"
        )
        raise InputError(
            f"the set would miss its own bench reference by {rms:.3f}° rms, {worst:.3f}° max, over"
            f" {max_miss_ratio:g}× the bench's noise floor {floor:.3f}°: {why}; a line that accepts it:"
            " --max-miss-ratio"
        )
    corr.temp_c = band_temp(samples)
    centre = (-corr.w2 / corr.w1, -corr.w4 / corr.w3)  # the fit's, as the rows were chosen around
    good = samples.subset(keep)
    corr.bench_locus = BenchLocus.fit(good.theta_ref, good.d, good.q, corr.temp_c, center=centre).to_dict()
    return corr, keep


def band_temp(samples: Samples) -> float:
    return float(np.mean(samples.temp_c)) if samples.temp_c is not None else REFERENCE_TEMP_C


def calibrate_named_band(samples: Samples, max_miss_ratio: float = RESIDUAL_RATIO) -> tuple[Correction, np.ndarray]:
    """calibrate_band, its errors naming the band: a bench's plateaus fail each on their own."""
    try:
        return calibrate_band(samples, max_miss_ratio)
    except InputError as exc:
        raise InputError(f"band at {band_temp(samples):.1f} °C: {exc}") from None


def calibrate_bands(
    samples: Samples, max_miss_ratio: float = RESIDUAL_RATIO
) -> list[tuple[Samples, Correction, np.ndarray]]:
    """Each temperature plateau of a bench recording: its samples, its band and the rows the band is fitted on."""
    if samples.theta_ref is None:
        raise InputError("calibration needs the reference angle column theta_ref_deg")
    if len(samples) < 64:
        raise InputError(f"calibration needs at least 64 bench samples, got {len(samples)}")
    span = float(np.degrees(np.ptp(samples.theta_ref)))  # in the column's unit
    if np.pi <= span <= 2 * np.pi * RADIANS_SLACK:
        raise InputError(
            f"theta_ref_deg spans only {span:.3f}: is it in radians? (the column is the reference angle in degrees,"
            " 0 to 360 or on past it)"
        )
    if samples.temp_c is None:
        return [(samples, *calibrate_named_band(samples, max_miss_ratio))]
    groups = plateaus(samples.temp_c)
    parts = [samples.subset(groups == g) for g in np.unique(groups[groups >= 0])]
    return [(part, *calibrate_named_band(part, max_miss_ratio)) for part in parts]


def calibrate(samples: Samples) -> BandedCorrection:
    """The factory set of a bench recording: one band per temperature plateau."""
    return BandedCorrection([corr for _, corr, _ in calibrate_bands(samples)])


def factory_set(device: str, factory: BandedCorrection) -> dict:
    from edge_agent.agent import factory_message

    return factory_message(device, factory)


def cmd_calibrate(args) -> int:
    from encoder_fleet.recording import read_recording

    samples = read_recording(args.bench)
    fitted = calibrate_bands(samples, args.max_miss_ratio)
    factory = BandedCorrection([corr for _, corr, _ in fitted])
    if samples.temp_c is not None:
        ramps = int((plateaus(samples.temp_c) < 0).sum())
        if ramps:
            print(f"{ramps} of {len(samples)} samples between plateaus (ramps) left out of every band")
    msg = factory_set(args.device, factory)
    write_file(args.out, json.dumps(msg, indent=1))
    for part, band, keep in fitted:
        harmonics = ", ".join(f"{m}: {np.degrees(np.hypot(a, b)):.3f}°" for m, (a, b) in sorted(band.harmonics.items()))
        print(
            f"band at {band.temp_c:.1f} °C: zero {np.degrees(band.zero_offset_rad):.3f}°, harmonics {harmonics}",
        )
        if not keep.all():
            shown = ", ".join(f"{t:g}" for t in part.t[~keep][:5])
            print(
                f"band at {band.temp_c:.1f} °C: {int((~keep).sum())} of {keep.size} rows left out, their reference"
                f" angle or d, q far off the fit (a reference glitch or a dropped read): t = {shown}"
                f"{', …' if (~keep).sum() > 5 else ''}"
            )
        good = part.subset(keep)
        rms, worst, floor = reference_miss(band, good)
        shifts = run_shifts(band, good)
        print(
            f"band at {band.temp_c:.1f} °C: misses its reference by {rms:.3f}° rms, {worst:.3f}° max"
            f" (noise floor {floor:.3f}°)"
        )
        if shifts:
            print(f"band at {band.temp_c:.1f} °C: run-to-run repeatability (each run's mean miss): {runs_said(shifts)}")
    print(f"wrote {args.out}")
    return 0


def register(sub) -> None:
    p = sub.add_parser("calibrate", help="the factory coefficient set from a bench recording with a reference angle")
    p.add_argument("bench", help="bench CSV: t, d, q, temp_c, theta_ref_deg")
    p.add_argument("--out", required=True, help="the coefficient set (JSON) that `agent --factory` reads")
    p.add_argument("--device", default="factory", help="device id written into the set")
    p.add_argument(
        "--max-miss-ratio",
        type=positive_float,
        default=RESIDUAL_RATIO,
        metavar="R",
        help=f"refuse a band missing its own reference by more than R noise floors (default {RESIDUAL_RATIO:g})",
    )
    p.set_defaults(func=cmd_calibrate)
