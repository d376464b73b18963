"""Never worse than the factory (issue 8), on drives from the independent simulator (encoder_fleet/fieldsim.py,
written from the physics, not from encoder_core/simulator.py): the end-of-line calibration from a bench
recording, and a small seeded fleet whose true angle error is scored against the factory set's."""

from __future__ import annotations

import json
import re
import subprocess
import sys

import numpy as np
import pytest

from encoder_core.correction import BandedCorrection, Correction
from encoder_core.differential import MODEL_REACH_C
from encoder_core.physics import band_of
from encoder_core.stats import normalisation_scale, window_stats
from encoder_fleet import fieldsim
from encoder_fleet.calibrate import calibrate
from encoder_fleet.fleet_accuracy import (
    DriveResult,
    drive_of,
    fleet_specs,
    floor_sets,
    run_bench,
    run_drive,
    score,
    summarise,
    truth_fit,
    windows_of,
    worse_than,
)
from encoder_fleet.recording import write_recording
from service.refit import band_index, centre, refit_device


def run_cli(*args: str) -> subprocess.CompletedProcess:
    """`encoder-fleet ARGS` as a user runs it: its own process, its output captured."""
    return subprocess.run([sys.executable, "-m", "encoder_fleet.cli", *args], capture_output=True, text=True)


def test_calibrate_writes_the_factory_set_an_agent_reads(tmp_path):
    rng = np.random.default_rng(11)
    phys = fieldsim.draw_drive(rng)
    bench = fieldsim.bench_sweep(phys, rng)
    write_recording(bench, tmp_path / "bench.csv")
    out = tmp_path / "factory.json"
    done = run_cli("calibrate", str(tmp_path / "bench.csv"), "--out", str(out))
    assert done.returncode == 0, done.stderr
    msg = json.loads(out.read_text())
    assert msg["version"] == 0 and msg["basis"] == "factory" and all("bench_locus" in b for b in msg["bands"])
    factory = BandedCorrection.from_dict({"bands": msg["bands"]})
    assert factory.bands[0].harmonics  # the field harmonics the reference reveals are kept

    # on the bench itself, against the reference: the factory set leaves almost nothing
    def rms_deg(theta):
        return float(np.degrees(np.sqrt(np.mean(np.angle(np.exp(1j * (theta - bench.theta_ref))) ** 2))))

    raw = rms_deg(np.arctan2(bench.q, bench.d))
    assert rms_deg(factory.angle(bench.d, bench.q, bench.temp_c)) < 0.2 * raw  # what is left is the noise
    assert calibrate(bench).bands[0].harmonics.keys() == factory.bands[0].harmonics.keys()


def test_calibrate_fits_each_plateau_of_a_bench_that_records_its_ramps(tmp_path):
    """A bench holds its plateaus and records the ramps between them (`simulate --scenario bench` does): the ramps
    pass through every temperature between the plateaus, so splitting at temperature gaps alone made the whole bench
    one band at its mean temperature (+12.8 °C for -40, +20, +60: a user's second reader found it). Each plateau is
    now a band at its own temperature, the ramps in none; on each plateau its band leaves what the noise leaves."""
    from encoder_fleet.recording import read_recording

    rec, out = tmp_path / "bench.csv", tmp_path / "factory.json"
    for argv in (["simulate", "--scenario", "bench", "--out", str(rec), "--seed", "3", "--plateaus", "-40", "25", "70"],
                 ["calibrate", str(rec), "--out", str(out)]):  # fmt: skip
        done = run_cli(*argv)
        assert done.returncode == 0, done.stderr
    factory = BandedCorrection.from_dict({"bands": json.loads(out.read_text())["bands"]})
    assert [round(b.temp_c) for b in factory.bands] == [-40, 25, 70]
    bench = read_recording(rec)
    for band in factory.bands:
        on = np.abs(bench.temp_c - band.temp_c) < 0.5
        err = np.angle(np.exp(1j * (band.angle(bench.d[on], bench.q[on]) - bench.theta_ref[on])))
        assert float(np.degrees(np.sqrt(np.mean(err**2)))) < 0.05, band.temp_c


def bench_error_deg(path, bench) -> tuple[float, float]:
    """RMS and max error (degrees) of the factory set at path on the bench's signals against its reference."""
    factory = BandedCorrection.from_dict({"bands": json.loads(path.read_text())["bands"]})
    err = np.degrees(np.angle(np.exp(1j * (factory.angle(bench.d, bench.q, bench.temp_c) - bench.theta_ref))))
    return float(np.sqrt(np.mean(err**2))), float(np.max(np.abs(err)))


def test_calibrate_leaves_out_a_handful_of_reference_glitches_and_dropped_reads(tmp_path, capsys):
    """A reference read error (theta_ref far off on a row) or a dropped read (d, q collapsed to a few % of the
    signal) on a handful of rows pulled the least-squares fit everywhere around the circle: 6 glitches in 3,600
    rows made the set's error against the good reference 0.34° rms, 1.12° max (0.08°, 0.30° without them), and
    its bench locus was fitted through them too; written without a word. Those rows are now left out of the band
    and its locus, and the output says how many and where (t)."""
    from dataclasses import replace

    from encoder_fleet.cli import main

    rng = np.random.default_rng(11)
    bench = fieldsim.bench_sweep(fieldsim.draw_drive(rng), rng)
    write_recording(bench, tmp_path / "clean.csv")
    theta, d, q = bench.theta_ref.copy(), bench.d.copy(), bench.q.copy()
    glitch, dropped = [300, 1000, 1700, 2400, 2900, 3500], [500, 1500, 2500]
    theta[glitch] = (theta[glitch] + np.radians([90, -120, 170, 45, -60, 135])) % (2 * np.pi)
    d[dropped], q[dropped] = 0.03 * d[dropped], 0.03 * q[dropped]
    write_recording(replace(bench, theta_ref=theta, d=d, q=q), tmp_path / "bad.csv")
    for name in ("clean", "bad"):
        assert main(["calibrate", str(tmp_path / f"{name}.csv"), "--out", str(tmp_path / f"{name}.json")]) == 0
    clean_rms, clean_max = bench_error_deg(tmp_path / "clean.json", bench)
    bad_rms, bad_max = bench_error_deg(tmp_path / "bad.json", bench)
    assert bad_rms < clean_rms + 0.002 and bad_max < clean_max + 0.01, (clean_rms, clean_max, bad_rms, bad_max)
    loci = [json.loads((tmp_path / f"{name}.json").read_text())["bands"][0]["bench_locus"] for name in ("clean", "bad")]
    for key in ("d", "q"):  # the field's shape the fleet's refits measure against (off by 4.6 counts, before)
        assert np.max(np.abs(np.subtract(loci[0][key], loci[1][key]))) < 0.1, key
    out = capsys.readouterr().out
    assert "9 of 3600 rows left out" in out and f"t = {bench.t[300]:g}, {bench.t[500]:g}" in out, out


def test_calibrate_refuses_a_reference_that_disagrees_on_more_than_a_handful_of_rows(tmp_path):
    """Rows the fit misses are left out while they are a handful; a reference off on 5 % of them is a bench that
    is wrong, not glitches (it was fitted through and written): one line, exit 2, no set."""
    from dataclasses import replace

    rng = np.random.default_rng(11)
    bench = fieldsim.bench_sweep(fieldsim.draw_drive(rng), rng)
    theta = bench.theta_ref.copy()
    theta[::20] = (theta[::20] + np.radians(30)) % (2 * np.pi)
    write_recording(replace(bench, theta_ref=theta), tmp_path / "bench.csv")
    done = run_cli("calibrate", str(tmp_path / "bench.csv"), "--out", str(tmp_path / "f.json"))
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
    assert len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert "band at 20.0 °C: 180 of 3600 rows disagree with the reference angle" in done.stderr, done.stderr
    assert not (tmp_path / "f.json").exists()


def test_calibrate_fits_a_bench_that_steps_finer_over_half_the_circle(tmp_path):
    """A bench that steps 0.1° over one half of the circle and 1° over the other: OursLsRef's plausibility mask
    centred on the median of d and q, which such a bench pulls towards its finer half, and then left the coarser
    half out as off the circle; the harmonics fitted on half a circle came out at 10⁹ degrees, and the set was
    written. The rows are now judged around the fit's own centre."""
    rng = np.random.default_rng(0)
    bench = fieldsim.bench_sweep(fieldsim.draw_drive(rng), rng)
    uneven = bench.subset((bench.theta_ref < np.pi) | (np.arange(len(bench)) % 10 == 0))
    write_recording(uneven, tmp_path / "bench.csv")
    done = run_cli("calibrate", str(tmp_path / "bench.csv"), "--out", str(tmp_path / "f.json"))
    assert done.returncode == 0, done.stderr
    assert "left out" not in done.stdout, done.stdout
    rms, worst = bench_error_deg(tmp_path / "f.json", uneven)
    assert rms < 0.1 and worst < 0.4, (rms, worst)  # the noise's (the even bench: 0.087°, 0.34°)


def test_calibrate_refuses_a_set_that_misses_its_own_reference_by_more_than_the_noise(tmp_path, capsys):
    """The simulator's bench visits +20 °C twice; a reference that slipped on its coupling by 1° between the visits
    made that band split the difference: 0.5° off its own reference everywhere, 27 times the bench's noise floor
    (0.018° from row to row), written without a word and the fleet's baseline for life. It is refused now (one
    line, exit 2, no set), and a good bench's output says how far each band misses its reference, beside the
    noise floor."""
    from dataclasses import replace

    from encoder_fleet.calibrate import plateaus
    from encoder_fleet.cli import main
    from encoder_fleet.recording import read_recording

    rec, out = tmp_path / "bench.csv", tmp_path / "factory.json"
    done = run_cli("simulate", "--scenario", "bench", "--out", str(rec))
    assert done.returncode == 0, done.stderr
    done = run_cli("calibrate", str(rec), "--out", str(out))
    assert done.returncode == 0, done.stderr
    reported = re.findall(
        r"band at (\S+) °C: misses its reference by (\S+)° rms, (\S+)° max \(noise floor (\S+)°\)", done.stdout
    )
    assert [t for t, *_ in reported] == ["-40.0", "20.0", "60.0"], done.stdout
    assert all(float(rms) < 0.03 and float(rms) < 2 * float(floor) for _, rms, _, floor in reported), done.stdout

    bench = read_recording(rec)
    second = np.flatnonzero(plateaus(bench.temp_c) == 1)
    second = second[bench.t[second] > bench.t[second].mean()]  # the second visit of +20 °C
    theta = bench.theta_ref.copy()
    theta[second] += np.radians(1.0)
    write_recording(replace(bench, theta_ref=theta), rec)
    out.unlink()
    assert main(["calibrate", str(rec), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "band at 20.0 °C: the set would miss its own bench reference" in err
    assert "noise floor" in err and not out.exists(), err
    # the two visits are runs 0 and 3 of the bench: the message says they sit apart, and a line may accept it
    assert re.search(r"its runs sit apart by .*run 3 [+-]0\.\d+°.*--max-miss-ratio", err), err
    assert main(["calibrate", str(rec), "--out", str(out), "--max-miss-ratio", "40"]) == 0
    said = capsys.readouterr().out
    line = re.search(r"band at 20\.0 °C: run-to-run repeatability.*", said).group(0)
    shifts = dict(re.findall(r"run (\d+) ([+-]\d\.\d+)°", line))
    assert abs(float(shifts["0"]) - float(shifts["3"]) - 1.0) < 0.05, said  # the slip, as the runs' repeatability


def test_calibrate_says_which_line_mistake_a_reference_is(tmp_path, capsys):
    """The reference's own mistakes are refused saying what they are, naming the band: theta_ref_deg written in
    radians (0 to 6.28) was "too little reference angle coverage: 1 of 12 sectors"; a reference counted the other
    way round was "fitted channel map is singular or mirrored (are d and q swapped?)"; a bench that covered 90°
    did not say which plateau. A reference whose zero is offset by a constant is the factory zero, not an error,
    and a reference counting on past 360° is the same as one that wraps."""
    from dataclasses import replace

    from encoder_fleet.cli import main

    rng = np.random.default_rng(11)
    bench = fieldsim.bench_sweep(fieldsim.draw_drive(rng), rng)

    def calibrate_cli(name, theta):
        write_recording(replace(bench, theta_ref=theta), tmp_path / f"{name}.csv")
        code = main(["calibrate", str(tmp_path / f"{name}.csv"), "--out", str(tmp_path / f"{name}.json")])
        return code, capsys.readouterr()

    turns = np.floor(np.arange(len(bench)) / 900)  # four turns' worth of counting on past 360°
    for name, theta in (("wraps", bench.theta_ref), ("offset", bench.theta_ref + np.radians(37.0)),
                        ("on-past-360", bench.theta_ref + 2 * np.pi * turns)):  # fmt: skip
        code, seen = calibrate_cli(name, theta)
        assert code == 0, seen.err
    angle = {
        n: BandedCorrection.from_dict({"bands": json.loads((tmp_path / f"{n}.json").read_text())["bands"]}).angle(
            bench.d, bench.q, bench.temp_c
        )
        for n in ("wraps", "offset", "on-past-360")
    }
    for name, shift in (("offset", 37.0), ("on-past-360", 0.0)):  # apart from the 6 digits a recording is written to
        apart = np.degrees(np.angle(np.exp(1j * (angle[name] - angle["wraps"])))) - shift
        assert np.max(np.abs(apart)) < 0.002, (name, np.max(np.abs(apart)))

    for name, theta, says in (
        ("radians", np.radians(bench.theta_ref), "theta_ref_deg spans only 6.281: is it in radians?"),
        ("reversed", -bench.theta_ref, "band at 20.0 °C: the reference angle turns the other way than d, q"),
        ("quarter", bench.theta_ref / 4, "band at 20.0 °C: too little reference angle coverage for a fit"),
    ):
        code, seen = calibrate_cli(name, theta)
        assert code == 2 and len(seen.err.strip().splitlines()) == 1 and says in seen.err, seen.err
        assert not (tmp_path / f"{name}.json").exists()


def test_calibrate_judges_a_bench_that_repeats_its_readings_by_its_own_noise(tmp_path, capsys):
    """A bench logged faster than it reads (each reading held for three rows, as a jig holding its angle writes
    it): the rows that repeat the one before were steps of 0 in the noise floor, which came out 0.000°, and every
    band was refused as missing its reference by more than twice that (the simulator's clean bench, and the real
    jig sensors calibrate wrote sets for before). Its floor is its readings' now: the set is the bench's own."""
    from dataclasses import replace

    from encoder_fleet.cli import main
    from encoder_fleet.recording import read_recording

    rec, held, out = tmp_path / "bench.csv", tmp_path / "held.csv", tmp_path / "factory.json"
    done = run_cli("simulate", "--scenario", "bench", "--out", str(rec))
    assert done.returncode == 0, done.stderr
    bench = read_recording(rec)
    rows = np.repeat(np.arange(len(bench)), 3)
    step = float(np.median(np.diff(bench.t)))
    write_recording(
        replace(bench.subset(rows), t=bench.t[rows] + np.tile([0.0, 1 / 3, 2 / 3], len(bench)) * step), held
    )
    assert main(["calibrate", str(held), "--out", str(out)]) == 0, capsys.readouterr().err
    floors = [float(f) for f in re.findall(r"\(noise floor (\S+)°\)", capsys.readouterr().out)]
    assert len(floors) == 3 and all(0.01 < f < 0.03 for f in floors), floors  # the bench's 0.018°, not 0.000°
    got = BandedCorrection.from_dict(json.loads(out.read_text()))
    assert main(["calibrate", str(rec), "--out", str(tmp_path / "own.json")]) == 0
    own = BandedCorrection.from_dict(json.loads((tmp_path / "own.json").read_text()))
    for a, b in zip(got.bands, own.bands, strict=True):
        assert a.temp_c == pytest.approx(b.temp_c) and a.w1 == pytest.approx(b.w1, rel=1e-6)
        assert a.zero_offset_rad == pytest.approx(b.zero_offset_rad, abs=1e-6)


def test_a_short_plateau_beside_a_long_one_is_a_plateau_still():
    """Plateaus are told from ramps by how crowded their temperatures are against the ramps', not against the
    fullest plateau: 400 samples at -40 °C beside 10,000 at +20 °C were all taken for a ramp (a second reader),
    with or without recorded ramps; a plateau whose temperature wanders by ±1 °C keeps every sample."""
    from encoder_fleet.calibrate import plateaus

    rng = np.random.default_rng(5)
    held = [np.full(400, -40.0), np.full(10_000, 20.0), np.full(3_000, 60.0)]
    for ramps in (True, False):
        parts = [held[0], np.linspace(-40, 20, 1200), held[1], np.linspace(20, 60, 800), held[2]] if ramps else held
        temp = np.concatenate(parts) + rng.normal(0, 0.05, sum(p.size for p in parts))
        groups = plateaus(temp)
        sizes = [int((groups == g).sum()) for g in range(3)]
        assert groups.max() == 2 and all(abs(n - h.size) <= 0.05 * h.size for n, h in zip(sizes, held)), (ramps, sizes)
    assert (plateaus(20 + rng.uniform(-1, 1, 2000)) == 0).all()


def step_follower_worse_hours(drive: dict, specs: list) -> set[int]:
    """The hours in which the factory set moved by the drive's planted offset step, from the step's time (what naming
    the step exactly gives), is itself worse than the factory set: the step had cancelled part of the drift there.
    The drive drawn again as run_drive draws it (drive_of); only the test sees the truth."""
    (spec,) = [s for s in specs if s.name == drive["name"]]
    phys, factory, run = drive_of(spec)
    timeline = [(float(run.samples.t[0]), factory)]
    timeline += [(e.t_s, factory.offsets_moved(e.d_offset, e.q_offset)) for e in phys.events if e.kind == "offset_step"]
    factory_hours, follower_hours = score(run, factory, timeline)
    return set(worse_than(follower_hours, factory_hours))


def test_a_small_fleet_of_independent_drives_is_never_worse_and_gains():
    """Hours worse than the factory set, apart from those in which even the set that follows a planted offset step
    exactly is worse (s5-20hz-02-dwell: its 0.38 % step, named 3 minutes after it since the held positions' map,
    had cancelled part of the cold drift at the positions it holds, and the day ends before a refit there: 5 such
    hours of 96, none before the map named the step; none of this kind on the 3-day benches, README)."""
    report = run_bench(drives=4, days=1.0, seeds=[5], rates=[20.0], windows={}, processes=2)
    fleet = report["regimes"]["20 Hz, 60 s windows"]
    assert fleet["drives"] == 4
    specs = fleet_specs(5, 4, 1.0, 20.0, 60.0)
    worse = sum(
        len(set(d["worse_hour_indices"]) - step_follower_worse_hours(d, specs))
        for d in report["drives"]
        if d["worse_hour_indices"]
    )
    assert worse <= 0.025 * fleet["drive_hours"], (worse, report["drives"])  # the issue asks for 1 %: README
    assert fleet["worse_hours_pct"] <= 6.0, fleet  # and those it shares stay a few (5 of 96 today)
    assert fleet["worst_gain"] >= 0.95 and fleet["median_gain"] >= 1.5, fleet


def test_the_issues_own_measurement_through_the_service_and_agent_processes():
    """`bench-fleet-accuracy --through-service`: a fleet replayed through `encoder-fleet service` and one
    `encoder-fleet agent --source replay:` process per drive at 3600x real time, as the issue measured it; what each
    drive ran is read from the service's database (its applied acks). Every drive that turns gets sets and beats its
    factory set, and none is worse in any hour (12 drive-hours each; a dwelling drive keeps its factory set)."""
    from encoder_fleet.fleet_replay import replay_fleet

    results = replay_fleet(fleet_specs(1, 4, 0.5, 0.5, 300.0), real_time_factor=3600.0)
    assert [r.name for r in results] == [s.name for s in fleet_specs(1, 4, 0.5, 0.5, 300.0)]
    turning = [r for r in results if r.motion != "dwell"]
    assert len(turning) == 3 and all(r.versions_applied >= 1 for r in turning), results
    assert all(len(r.fleet_hour_deg) == 12 and r.worse_hours == 0 for r in results), results
    assert min(r.gain for r in turning) >= 1.5, [(r.name, r.gain) for r in results]


def test_the_loop_judges_a_trial_at_the_services_pace_and_refits_an_hour_after_the_last_fit():
    """s1-5hz-04 (10 s windows, a gain step drawn from the seed at 12.8 h): the step is named while a set is on
    trial, the watch rolls that set back, and the drive runs the factory set moved by the step, on trial in a band it
    never visits again that day. The service (service.runtime) judges a trial at every pass and refits an hour after
    its last fit: the trial is confirmed after TRIAL_MAX_S and the refit follows at once. The loop judged only on
    its hourly refit grid and then skipped that hour's refit, so the moved set, worse than the factory at +55..+60 °C
    where the step had cancelled part of the drift, ran two hours more: two worse hours, none at the service's pace.
    The gain step is drawn from the seed; the loop never sees it."""
    (spec,) = [s for s in fleet_specs(1, 12, 1.0, 5.0, 10.0) if s.index == 4]
    assert spec.event == "gain_step"
    result = run_drive(spec)
    assert result.worse_hour_indices == [], result.worse_hour_indices
    assert result.factory_deg / result.fleet_deg > 3.0


def test_worse_hours_the_reference_free_floors_share_and_those_at_a_step_are_counted_apart():
    """A worse hour in which a floor (the best set without a reference, in either reading) is worse too is no
    refit's to avoid; one in a planted step's hour or the next is counted apart too (the drive runs its set from
    before the step until the step is seen). A drive worse in more than 1 % of its hours fails the issue's bar."""
    r = DriveResult(
        "d", "reverse", "offset_step", 0.5, 1,
        factory_hour_deg=[0.10, 0.10, 0.10, 0.10, 0.10],
        fleet_hour_deg=[0.15, 0.10, 0.15, 0.1005, 0.05],  # worse in hours 0 and 2 (hour 3 is within the margin)
        floor_hour_deg=[0.12, 0.12, 0.05, 0.05, 0.10],  # the floor worse in hours 0 and 1
        drift_floor_hour_deg=[0.05, 0.05, 0.05, 0.05, 0.12],  # the drift floor in hour 4
        step_hours=[1],  # hours 1 and 2 are the step's
    )  # fmt: skip
    assert r.worse_hour_indices == [0, 2] and r.floor_worse_hour_indices == [0, 1, 4]
    assert r.floor_shared_worse_hours == 1 and r.step_worse_hours == 1
    clean = DriveResult("c", "even", None, 0.5, 1, [0.1] * 200, [0.05] * 199 + [0.2], [0.05] * 200)
    assert clean.worse_hours == 1 and clean.step_worse_hours == 0  # 0.5 % of its hours: within the bar
    summary = summarise([r, r, clean])
    assert summary["worse_hours"] == 5 and summary["worse_hours_floor_shares"] == 2
    assert summary["worse_hours_at_steps"] == 2 and summary["drives_past_1pct"] == 2
    assert summary["drives_past_1pct_own"] == 0  # r's hour 0 is the floor's, hour 2 the step's
    assert summary["floor_worse_hours"] == 6


def test_explain_replays_one_drive_with_every_decision_beside_its_hours(tmp_path, capsys):
    """`bench-fleet-accuracy --explain DRIVE`: the drive the table names, run as the benchmark runs it, with every
    set the loop sent and applied, every verdict and alarm, then its error hour by hour, its worse hours and its
    planted step's hour marked. Listening changes nothing: the drive scores as the benchmark scores it.
    s10-0.5hz-07-reverse (the 12-drive fleet, 3 days): its axis step is drawn from the seed; the loop never sees it."""
    from encoder_fleet.cli import main
    from encoder_fleet.fleet_accuracy import explain_drive, format_explanation, plot_explanation, spec_named

    spec = spec_named("s10-0.5hz-07-reverse", drives=12, days=3.0, window_s=None)
    assert (spec.seed, spec.index, spec.rate_hz, spec.window_s, spec.event) == (10, 7, 0.5, 300.0, "axis_step")
    explained = explain_drive(spec)
    result = run_drive(spec)
    assert explained.result.fleet_hour_deg == result.fleet_hour_deg
    assert explained.result.versions_applied == result.versions_applied >= 1
    applied = [text for _, text in explained.decisions if " applied: " in text]
    assert len(applied) == result.versions_applied, explained.decisions
    assert any(text.startswith("refit: adopted +") for _, text in explained.decisions)
    hours = [h for h, _ in explained.decisions]
    assert hours == sorted(hours) and 0.0 <= hours[0] and hours[-1] < 72.0
    text = format_explanation(explained)
    rows = [line.split("|")[1:-1] for line in text.splitlines() if re.match(r"\| \d+ \|", line)]  # the hours' table
    assert [int(row[0]) for row in rows] == list(range(72))
    assert [int(row[0]) for row in rows if row[-1].strip().startswith("worse")] == result.worse_hour_indices
    ((step_hour, kind),) = explained.planted
    assert kind == "axis_step" and result.step_hours == [int(step_hour)]
    assert rows[int(step_hour)][-1].strip() in ("step", "worse (at a step)")
    plot_explanation(explained, tmp_path / "drive.png")
    assert (tmp_path / "drive.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    for argv, says in (
        (["--explain", "s10-0.5hz-7-reverse"], "no drive 's10-0.5hz-7-reverse' in the fleet of seed 10 at 0.5 Hz"),
        (["--explain", "s10-0.5hz-07-even"], "s10-0.5hz-07-reverse"),  # the fleet's names, to pick from
        (["--explain", "drive-7"], "is not s<seed>-<rate>hz-<index>-<motion>"),
        (["--plot", str(tmp_path / "p.png")], "--plot draws the drive --explain names"),
    ):
        assert main(["bench-fleet-accuracy", *argv]) == 2
        assert says in capsys.readouterr().err
    assert not (tmp_path / "p.png").exists()


@pytest.mark.parametrize("seed", [3, 8])
def test_the_drift_floor_corrects_the_drift_and_keeps_what_the_bench_left(seed):
    """The drift floor is the factory set plus the truth's change since the bench: at the bench (+20 °C, time 0) it
    is the factory set; away from it, it leaves the factory set's own bench residual (no window sees it), where the
    factory set leaves that and the drift; the reference-free floor, fitted against the truth, leaves neither. The
    drive is drawn from the seed."""
    rng = np.random.default_rng(seed)
    phys = fieldsim.draw_drive(rng, days=1.0)
    factory = calibrate(fieldsim.bench_sweep(phys, rng))
    bench = truth_fit(phys, fieldsim.BENCH_TEMP_C, 0.0)
    theta = np.linspace(0, 2 * np.pi, 720, endpoint=False)

    def error_deg(correction, temp_c, t_s):  # around the circle, the zero aside (no window sees it)
        d, q = phys.channels(theta, np.full(theta.size, temp_c), np.full(theta.size, t_s))
        err = np.degrees((correction.angle(d, q, np.full(theta.size, temp_c)) - theta + np.pi) % (2 * np.pi) - np.pi)
        return float(np.sqrt(np.mean((err - err.mean()) ** 2)))

    at_bench = floor_sets(phys, factory, 0.0, bench)[1]
    assert error_deg(at_bench, fieldsim.BENCH_TEMP_C, 0.0) == pytest.approx(
        error_deg(factory, fieldsim.BENCH_TEMP_C, 0.0), abs=2e-4
    )
    residual = error_deg(factory, fieldsim.BENCH_TEMP_C, 0.0)
    floor, drift_floor = floor_sets(phys, factory, 12 * 3600.0, bench)
    for temp_c in (-15.0, 55.0):
        left = error_deg(drift_floor, temp_c, 12 * 3600.0)
        assert abs(left - residual) < 0.25 * residual + 5e-4, (temp_c, left, residual)
        assert left < 0.5 * error_deg(factory, temp_c, 12 * 3600.0)
        assert error_deg(floor, temp_c, 12 * 3600.0) < 0.5 * residual


def drive_stepped_at_start(seed: int):
    """(rng, physics, factory set, step) of a drive whose hidden offset step (size and axis from the seed) comes at
    drive time 0, right after its bench calibration."""
    rng = np.random.default_rng(seed)
    phys = fieldsim.draw_drive(rng)
    factory = calibrate(fieldsim.bench_sweep(phys, rng))
    step = fieldsim.draw_event(rng, "offset_step", days=1.0)
    step.t_s = 0.0
    phys.events.append(step)
    return rng, phys, factory, step


@pytest.mark.parametrize("seed", [3, 4])
def test_after_an_offset_step_the_bands_without_data_move_with_the_ones_that_have(seed):
    """A hidden offset step (size and axis drawn from the seed): one band seen after it moves the rest of the
    running set (the factory's, one entry at the bench) by the step, but only when the monitor saw a step
    (after_step). A band within MODEL_REACH_C of the bench measures the step; a warm band measures it plus the
    offsets' drift since the bench, which the flat factory set does not correct, and its move stays near it."""
    rng, phys, factory, step = drive_stepped_at_start(seed)
    truth = np.array([step.d_offset, step.q_offset])  # counts; the code under test never saw it
    bench = factory.bands[0]
    for low_c, reaches in ((11.0, True), (44.0, False)):
        run = fieldsim.field_run(
            phys, days=1 / 24, rate_hz=5.0, regime="random", rng=rng, low_c=low_c, high_c=low_c + 2
        )
        stats = window_stats(run.samples, normalisation_scale(factory))
        bands = {band_of(stats.temp_mean): stats}
        assert band_index(bench) not in bands  # the factory's band (+20 °C) saw nothing since the step
        assert (abs(stats.temp_mean - bench.temp_c) <= MODEL_REACH_C) == reaches

        moved = refit_device(
            bands, factory, factory, bin_temps={b: s.bin_temps() for b, s in bands.items()}, after_step=True
        )
        assert moved.moved_bands == ([band_index(bench)] if reaches else [])
        at_bench = BandedCorrection.from_dict({"bands": moved.bands}).at(bench.temp_c)
        shift = centre(at_bench) - centre(bench)
        if reaches:
            assert np.hypot(*(shift - truth)) < 0.25 * np.hypot(*truth), (shift, truth)
        else:
            assert np.hypot(*shift) < 1e-9, shift  # the bench's entry as the device runs it

        still = refit_device(bands, factory, factory, bin_temps={b: s.bin_temps() for b, s in bands.items()})
        assert still.moved_bands == []


def bench_band_error_deg(phys, corr, temp_c: float = 20.0, t_s: float = 3600.0) -> float:
    """RMS true angle error of a set at one temperature around the whole circle, its mean (the zero) aside."""
    theta = np.linspace(0, 2 * np.pi, 720, endpoint=False)
    d, q = phys.channels(theta, np.full(theta.size, temp_c), np.full(theta.size, t_s))
    err = np.angle(np.exp(1j * (corr.angle(d, q, np.full(theta.size, temp_c)) - theta)))
    err = np.angle(np.exp(1j * (err - np.angle(np.mean(np.exp(1j * err))))))
    return float(np.degrees(np.sqrt(np.mean(err**2))))


def band_sums(run, scale: float, window_s: float = 60.0) -> dict:
    """The run cut into windows as the agent cuts them, summed per band as the store sums them."""
    bands = {}
    for a, b in windows_of(run.samples.t, window_s):
        w = window_stats(run.samples.subset(slice(a, b)), scale)
        band = band_of(w.temp_mean)
        bands[band] = bands[band].merge(w) if band in bands else w
    return bands


def test_after_a_named_step_the_drift_curve_does_not_pass_through_the_bench():
    """A hidden offset step (size and axis drawn from each seed), the running set already moved by it (the monitor
    named it), then six hours of a drive that holds a few positions while it cools from +25 to -20 °C. Its bands
    bound the drift too loosely to say that the bench (no drift at +20 °C) no longer holds, so a drift curve through
    the bench undid the step at +20 °C with confidence (bench-fleet-accuracy s7-20hz-02: 13 worse hours). With the
    step named the bench is no point of the curve, and the bench band stays as good as it runs."""
    worse_through_bench = 0
    for seed in range(8, 20):
        rng, phys, factory, step = drive_stepped_at_start(seed)
        run = fieldsim.field_run(phys, days=0.25, rate_hz=20.0, regime="dwell", rng=rng, low_c=-20.0, high_c=25.0)
        bands = band_sums(run, normalisation_scale(factory))
        running = factory.offsets_moved(step.d_offset, step.q_offset)  # the service's move for the named step
        before = bench_band_error_deg(phys, running)
        after = {}
        for stepped in (True, False):
            r = refit_device(
                bands, running, factory, bin_temps={k: v.bin_temps() for k, v in bands.items()},
                stepped_since_bench=stepped,
            )  # fmt: skip
            sent = BandedCorrection.from_dict({"bands": r.bands}) if r.bands else running  # no bands: nothing new
            after[stepped] = bench_band_error_deg(phys, sent)
        assert after[True] <= before + 0.002, (seed, before, after)
        worse_through_bench += after[False] > before + 0.1
    assert worse_through_bench >= 2  # the trap is in these drives: the curve through the bench falls in it


def zero_error_deg(phys, corr: Correction, temp_c: float, t_s: float) -> float:
    """The set's mean true angle error around the circle at one temperature: its zero, which no window sees."""
    theta = np.linspace(0, 2 * np.pi, 720, endpoint=False)
    d, q = phys.channels(theta, np.full(theta.size, temp_c), np.full(theta.size, t_s))
    err = corr.angle(d, q) - theta
    return float(np.degrees(np.angle(np.mean(np.exp(1j * err)))))


def test_after_a_named_axis_turn_the_refit_keeps_the_rotation_no_window_sees():
    """A hidden turn of the q axis (size and sign drawn from each seed) right after the bench, the running set
    already moved by it (the monitor named it), then hours of a drive turning at random while it warms. A turn of
    one axis is half a shear, which the windows see, and half a rotation of both axes, which none does: every
    candidate anchored to the factory's own zero carries the rotation back in (s7-20hz-07, bench-fleet-accuracy:
    2.8× where the moved set alone ran 8×). Told the turn (axis_turn), each band's candidate keeps the moved set's
    zero, to within a fifth of the rotation."""
    for seed in range(30, 34):
        rng = np.random.default_rng(seed)
        phys = fieldsim.draw_drive(rng)
        factory = calibrate(fieldsim.bench_sweep(phys, rng))
        turn = float(rng.choice([-1.0, 1.0]) * rng.uniform(0.003, 0.006))
        phys.events.append(fieldsim.Event(0.0, "axis_step", q_axis=turn))
        run = fieldsim.field_run(phys, days=0.25, rate_hz=20.0, regime="random", rng=rng, low_c=25.0, high_c=60.0)
        bands = band_sums(run, normalisation_scale(factory))
        running = BandedCorrection([b.axes_moved(np.sin(turn)) for b in factory.bands])  # the service's move
        half_turn_deg = np.degrees(abs(turn)) / 2
        for told, bar in ((True, 0.2), (False, None)):
            r = refit_device(
                bands, running, factory, bin_temps={k: v.bin_temps() for k, v in bands.items()},
                stepped_since_bench=True, axis_turn=np.sin(turn) if told else 0.0,
            )  # fmt: skip
            assert r.decisions, seed
            for decision in r.decisions:
                entry = {k: v for k, v in decision.candidate.items() if k not in ("band", "quality")}
                # against the moved set's own zero there (the zero's drift with temperature no refit sees either)
                zero = abs(
                    zero_error_deg(phys, Correction.from_dict(entry), decision.temp_c, 3600.0)
                    - zero_error_deg(phys, running.at(decision.temp_c), decision.temp_c, 3600.0)
                )
                if told:  # the candidate's zero within a fifth of the rotation's size of the moved set's
                    assert zero < bar * half_turn_deg, (seed, decision.band, zero, half_turn_deg)
                else:  # the trap is there: anchored to the factory, the rotation comes back
                    assert zero > 0.5 * half_turn_deg, (seed, decision.band, zero, half_turn_deg)


def test_past_the_data_since_a_step_nobody_could_measure_the_drive_runs_its_set_from_before_it_moved():
    """s8-20hz-10-dwell (the 12-drive fleet, 3 days; its offset step drawn from the seed at 47.4 h, the loop never
    sees it): the held test names the step with no position held before it left to compare with, so the drive goes
    back to its factory set. The refits since saw -20..+24 °C; the drive ran the +24 °C entry flat up to +63 °C, five
    hours worse than the factory set (0.16-0.26° against 0.08-0.22°). Past the data since the step it now runs the
    set from before the step, moved by the offset change the bands fitted since agree on (service.refit.
    carried_over_step): no hour worse than the factory set."""
    from encoder_fleet.fleet_accuracy import explain_drive, spec_named

    spec = spec_named("s8-20hz-10-dwell", drives=12, days=3.0, window_s=None)
    assert spec.event == "offset_step"
    explained = explain_drive(spec)
    texts = [text for _, text in explained.decisions]
    back = [k for k, text in enumerate(texts) if "the factory set again (the step was not measured)" in text]
    assert back, "the step was measured: not the case this test is about"
    assert any("for the offset step" in text for text in texts[back[0] :]), texts[back[0] :]
    result = explained.result
    assert result.worse_hour_indices == [], result.worse_hour_indices
    assert result.gain >= 3.0, result.gain
