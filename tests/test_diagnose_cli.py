"""`encoder-fleet diagnose` as a user runs it: JSON contract, HTML report, bad input, bench-diagnose."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from encoder_core.simulator import EncoderModel, bench_profile, field_profile, record
from encoder_fleet.recording import write_recording

CONTRACT_KEYS = {"samples", "has_reference", "error_metric", "baseline", "findings", "extended", "not_testable"}


def run_cli(*args):
    return subprocess.run([sys.executable, "-m", "encoder_fleet.cli", *args], capture_output=True, text=True)


@pytest.fixture(scope="module")
def bench_csv(tmp_path_factory):
    rng = np.random.default_rng(7)
    model = EncoderModel(
        hall_amplitude=700.0,
        gain_tc_per_c=(-0.002, -0.0008),
        offset_counts=(10.0, -5.0),
        offset_tc_counts_per_c=(0.5, -0.5),
        noise_counts=1.0,
        harmonics=((4, 0.01, 0.5),),
    )
    path = tmp_path_factory.mktemp("rec") / "bench.csv"
    write_recording(record(model, bench_profile(rng=rng), rng), path)
    return path


def test_diagnose_writes_contract_json_and_html(bench_csv, tmp_path):
    out, html = tmp_path / "out.json", tmp_path / "out.html"
    res = run_cli("diagnose", str(bench_csv), "--json", str(out), "--report", str(html))
    assert res.returncode == 0, res.stderr
    report = json.loads(out.read_text())
    assert CONTRACT_KEYS <= set(report)
    assert report["has_reference"] is True and report["error_metric"] == "reference"
    assert set(report["baseline"]) >= {"model", "rms_error_deg", "max_error_deg"}
    assert set(report["extended"]) >= {"causes", "rms_error_deg", "max_error_deg"}
    assert [f["cause"] for f in report["findings"]] == ["harmonic_distortion"]
    finding = report["findings"][0]
    assert set(finding) == {"cause", "parameters", "evidence", "rms_error_deg_before", "rms_error_deg_after"}
    assert finding["parameters"]["order"] == 4
    for item in report["not_testable"]:
        assert set(item) == {"cause", "why"}
    text = html.read_text()
    assert text.count("data:image/png;base64,") == 3  # angle, temperature (heating/cooling), baseline vs extended
    assert "harmonic_distortion" in text and "heating" in text
    assert "harmonic_distortion" in res.stdout
    assert "diagnose:" in res.stderr and "fit" in res.stderr  # tqdm progress on stderr (26,880 rows)


def test_diagnose_halls_without_reference(tmp_path):
    rng = np.random.default_rng(8)
    model = EncoderModel(hall_amplitude=700.0, noise_counts=1.0, phase_error_rad=0.015)
    path = tmp_path / "field.csv"
    write_recording(
        record(model, field_profile(0.5, sample_s=5.0, rng=rng), rng, reference=False, halls=True), path, halls=True
    )
    out = tmp_path / "f.json"
    res = run_cli("diagnose", str(path), "--json", str(out))
    assert res.returncode == 0, res.stderr
    report = json.loads(out.read_text())
    assert report["error_metric"] == "radius" and report["has_reference"] is False
    assert [f["cause"] for f in report["findings"]] == ["phase_nonorthogonality"]
    assert "zero_offset" in {n["cause"] for n in report["not_testable"]}


def _good_rows(n=400):
    th = np.linspace(0, 4 * np.pi, n)
    return [(i * 0.1, 1000 * np.cos(a), 1000 * np.sin(a), 25.0) for i, a in enumerate(th)]


def _write(path, header, rows):
    path.write_text(header + "\n" + "\n".join(",".join(str(v) for v in r) for r in rows) + "\n")
    return path


@pytest.mark.parametrize(
    "case,message",
    [
        ("missing_column", "missing columns: need 'd' and 'q'"),
        ("text_in_number", "line 12, column 'q': not a number: 'abc'"),
        ("t_not_increasing", "line 6, column 't': does not increase"),  # data row 5 repeats row 4's t
        ("too_few", "too few samples to diagnose: 20"),
        ("coverage", "coverage for a fit: samples fall in 3 of 12 30° sectors"),
    ],
)
def test_bad_input_exits_2_with_one_line_message(tmp_path, case, message):
    rows = _good_rows()
    path = tmp_path / f"{case}.csv"
    if case == "missing_column":
        _write(path, "t,d,temp_c", [(r[0], r[1], r[3]) for r in rows])
    elif case == "text_in_number":
        rows[10] = (rows[10][0], rows[10][1], "abc", rows[10][3])
        _write(path, "t,d,q,temp_c", rows)
    elif case == "t_not_increasing":
        rows[4] = (rows[3][0], *rows[4][1:])
        _write(path, "t,d,q,temp_c", rows)
    elif case == "too_few":
        _write(path, "t,d,q,temp_c", rows[:20])
    elif case == "coverage":
        th = np.linspace(0, np.radians(70), 400)
        _write(path, "t,d,q", [(i * 0.1, 1000 * np.cos(a), 1000 * np.sin(a)) for i, a in enumerate(th)])
    res = run_cli("diagnose", str(path), "--json", str(tmp_path / "x.json"))
    assert res.returncode == 2, (res.stdout, res.stderr)
    assert "Traceback" not in res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], res.stderr
    assert not (tmp_path / "x.json").exists()


def test_missing_file_exits_2(tmp_path):
    res = run_cli("diagnose", str(tmp_path / "nope.csv"))
    assert res.returncode == 2 and "cannot open" in res.stderr and "Traceback" not in res.stderr


def test_bench_diagnose_prints_a_table():
    res = run_cli("bench-diagnose", "--rows", "3000")
    assert res.returncode == 0, res.stderr
    lines = res.stdout.strip().splitlines()
    assert "rows" in lines[0] and "seconds" in lines[0] and "rows/s" in lines[0]
    assert len(lines) == 3 and lines[1].split()[:2] == ["bench", "3000"] and lines[2].split()[:2] == ["field", "3000"]
