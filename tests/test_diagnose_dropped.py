"""Dropped reads: a sample whose field magnitude collapses to a few percent of nominal (a failed
conversion, a loose connector) in a short recording. It must be named `outliers`, kept out of every
fit, and must not decide the extended model's max error; nothing else may be named.

Each case draws, from its seed, an encoder with random baseline effects only, records a short jig-style
bench (16 positions x 3 runs x 10 samples, with or without the reference column) or a few hundred
field rows at random angles, and collapses one to three samples to a random depth. The truth stays here.
"""

from __future__ import annotations

import numpy as np
import pytest
from test_diagnose import baseline_model

from encoder_core.diagnose import diagnose
from encoder_core.samples import Samples
from encoder_core.simulator import EncoderModel, simulate


def jig_style(rng, reference: bool) -> Samples:
    """16 positions, 3 runs, 10 samples per position, constant temperature, no temp_c column."""
    positions = np.sort(rng.uniform(0, 2 * np.pi, 16))
    theta = np.tile(np.repeat(positions, 10), 3)
    run = np.repeat([1, 2, 3], 160)
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
