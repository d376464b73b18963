"""Short recordings, as a jig gives them: dropped reads and run-to-run repeatability.

A dropped read is a sample whose field magnitude collapses to a few percent of nominal (a failed
conversion, a loose connector). It must be named `outliers`, kept out of every fit, and must not decide
the extended model's max error; nothing else may be named. Each dropped-read case draws, from its
seed, an encoder with random baseline effects only, records a short jig-style bench (16 positions x
3 runs x 10 samples, with or without the reference column) or a few hundred field rows at random
angles, and collapses one to three samples to a random depth. The truth stays here.
"""

from __future__ import annotations

import numpy as np
import pytest
from test_diagnose import baseline_model

from encoder_core.diagnose import diagnose
from encoder_core.samples import Samples
from encoder_core.simulator import EncoderModel, simulate

JIG_DEG = (-150, -135, -120, -90, -60, -45, -30, 0, 30, 45, 60, 90, 120, 135, 150, 180)  # the real jig's


def jig_style(rng, reference: bool, runs: int = 3, positions=None) -> Samples:
    """16 positions (random unless given), 10 samples each, in 3 runs; constant temperature, no temp_c."""
    positions = np.sort(rng.uniform(0, 2 * np.pi, 16)) if positions is None else np.radians(positions)
    theta = np.tile(np.repeat(positions, 10), runs)
    run = np.repeat(np.arange(1, runs + 1), 160)
    return _record(rng, theta, run, reference)


def field_style(rng) -> Samples:
    """A few hundred rows at random angles, no reference, no runs."""
    n = int(rng.integers(200, 500))
    return _record(rng, rng.uniform(0, 2 * np.pi, n), None, reference=False)


def _record(rng, theta, run, reference: bool) -> Samples:
    model = EncoderModel(**baseline_model(rng, "bench"))
    n = theta.size
    s, _ = simulate(model, np.arange(n) * 0.1, theta, np.full(n, 25.0), rng)
    return Samples(t=s.t, d=s.d, q=s.q, theta_ref=s.theta_ref if reference else None, run=run)


def drop_reads(rng, samples: Samples) -> np.ndarray:
    """Collapse 1-3 samples, each channel to 0-20 % of what it read (the real one: 0.4 % and 17 %)."""
    rows = rng.choice(len(samples), size=int(rng.integers(1, 4)), replace=False)
    samples.d[rows] *= rng.uniform(0.0, 0.2, rows.size)
    samples.q[rows] *= rng.uniform(0.0, 0.2, rows.size)
    return rows


CASES = [(seed, style) for seed in range(300, 306) for style in ("jig-reference", "jig-no-reference", "field")]


@pytest.mark.parametrize("seed,style", CASES, ids=[f"{style}-{seed}" for seed, style in CASES])
def test_dropped_reads_are_named_outliers_and_decide_nothing(seed, style):
    rng = np.random.default_rng(seed)
    if style == "field":
        samples = field_style(rng)
    else:
        samples = jig_style(rng, reference=style == "jig-reference")
    clean = diagnose(samples).report
    rows = drop_reads(rng, samples)
    report = diagnose(samples).report
    assert [f["cause"] for f in clean["findings"]] == []
    assert [f["cause"] for f in report["findings"]] == ["outliers"], report["findings"]
    finding = report["findings"][0]
    assert finding["parameters"]["fraction"] == pytest.approx(rows.size / len(samples), abs=0.5 / len(samples))
    assert "dropped read" in finding["evidence"]
    # with the collapsed samples rejected the extended model's errors are the clean recording's: a
    # dropped read no longer decides the max (it did: 110° on a real sensor)
    assert report["extended"]["max_error_deg"] == pytest.approx(clean["extended"]["max_error_deg"], rel=0.1)
    assert report["extended"]["rms_error_deg"] == pytest.approx(clean["extended"]["rms_error_deg"], rel=0.1)


def spike_reads(rng, samples: Samples) -> np.ndarray:
    """1-3 samples read 3 to 10^300 times their field on one channel (a spike on the line, a corrupted word)."""
    rows = rng.choice(len(samples), size=int(rng.integers(1, 4)), replace=False)
    channel = samples.d if rng.random() < 0.5 else samples.q
    channel[rows] = (
        np.sign(channel[rows] + 0.5)
        * np.hypot(samples.d[rows], samples.q[rows])
        * 10.0 ** rng.uniform(0.5, 300, rows.size)
    )
    return rows


SPIKE_CASES = [(seed, style) for seed in range(320, 324) for style in ("jig-reference", "jig-no-reference", "field")]


@pytest.mark.parametrize("seed,style", SPIKE_CASES, ids=[f"{style}-{seed}" for seed, style in SPIKE_CASES])
def test_reads_of_an_impossible_field_are_named_outliers_and_decide_nothing(seed, style):
    """The mirror of a dropped read: a sample whose field reads far over the typical one (up to 1e300 times:
    once, such a value crashed diagnose, and one of 1e6 set the normalisation and left 'no findings' with a max
    error of 38 degrees). Named outliers, said to be over the typical field, and the errors are the clean ones."""
    rng = np.random.default_rng(seed)
    samples = field_style(rng) if style == "field" else jig_style(rng, reference=style == "jig-reference")
    clean = diagnose(samples).report
    rows = spike_reads(rng, samples)
    report = diagnose(samples).report
    assert [f["cause"] for f in report["findings"]] == ["outliers"], report["findings"]
    finding = report["findings"][0]
    assert finding["parameters"]["fraction"] == pytest.approx(rows.size / len(samples), abs=0.5 / len(samples))
    assert "of the typical field (over 200 %" in finding["evidence"], finding["evidence"]
    assert report["extended"]["max_error_deg"] == pytest.approx(clean["extended"]["max_error_deg"], rel=0.1)
    assert report["extended"]["rms_error_deg"] == pytest.approx(clean["extended"]["rms_error_deg"], rel=0.1)


@pytest.mark.parametrize("seed", range(310, 316))
def test_runs_shifted_by_a_constant_are_reported_as_repeatability(seed):
    """Each run re-mounted with its own zero (plus a common one): the common zero is named, the rest is
    reported per run as repeatability, held out: the run's shift less the mean of the others. The real
    jig's angles: at a few uneven angles a zero offset also leaks into the axis offsets (README, limits)."""
    rng = np.random.default_rng(seed)
    runs = int(rng.integers(3, 6))
    samples = jig_style(rng, reference=True, runs=runs, positions=JIG_DEG)
    common = rng.uniform(1.0, 3.0) * rng.choice([-1.0, 1.0])
    shift = rng.uniform(-0.5, 0.5, runs)
    samples.theta_ref = samples.theta_ref - np.radians(common + shift[samples.run.astype(int) - 1])
    report = diagnose(samples).report
    assert [f["cause"] for f in report["findings"]] == ["zero_offset"], report["findings"]
    rep = report["repeatability"]
    others = (shift.sum() - shift) / (runs - 1)
    assert list(rep["runs"]) == [str(r) for r in range(1, runs + 1)]
    assert np.array(list(rep["runs"].values())) == pytest.approx(shift - others, abs=0.03)
    assert rep["rms_deg"] == pytest.approx(np.sqrt(np.mean((shift - others) ** 2)), abs=0.03)
    # within the runs only the noise is left: the shifts were the residual
    clean = diagnose(jig_style(np.random.default_rng(seed), reference=True, runs=runs, positions=JIG_DEG)).report
    assert rep["within_run_rms_error_deg"] < 1.5 * clean["extended"]["rms_error_deg"]
    assert "re-mounted" in rep["note"]


def test_no_repeatability_without_runs_or_reference():
    rng = np.random.default_rng(320)
    assert "repeatability" not in diagnose(jig_style(rng, reference=False)).report
    samples = jig_style(rng, reference=True)
    samples.run = None
    assert "repeatability" not in diagnose(samples).report
