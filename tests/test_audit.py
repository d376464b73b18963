"""`encoder-fleet audit`: every published coefficient set of the fleet in one CSV, read back as an auditor would."""

from __future__ import annotations

import csv
import hashlib
import json
import subprocess
import sys

import pytest

import tests.wire_samples as ws
from encoder_fleet import audit
from service.store import Store

T0 = 1_780_000_000.0  # 2026-05-28T20:26:40Z on the service's clock


def history(store: Store) -> None:
    """Two drives: factory sets, fits applied and rejected, a fit never acknowledged, a rollback, a rollout's set."""
    for device in ("drive-a", "drive-b"):
        factory = ws.coefficients(device, version=0, created_at=0.0)
        factory["basis"] = "factory"
        store.insert_coefficient_set(factory)
        store.mark_published(device, 0, at=T0)  # the same instant: the order falls to device, then version
    for device, version, at, ack in [
        ("drive-a", 1, T0 + 60, "applied"),
        ("drive-b", 1, T0 + 60, "rejected"),
        ("drive-a", 2, T0 + 3600, None),
        ("drive-b", 2, T0 + 86_400, "applied"),
    ]:
        store.insert_coefficient_set(
            ws.coefficients(device, version=version, created_at=100.0 * version), state="trial"
        )
        store.mark_published(device, version, at=at)
        if ack:
            store.insert_ack(ws.ack(device, version, at=100.0 * version + 5, status=ack), received_at=at + 2)
    back = ws.coefficients("drive-a", version=3, created_at=400.0)
    back["basis"], back["restores_version"] = "rollback", 1
    store.insert_coefficient_set(back)
    store.mark_published("drive-a", 3, at=T0 + 7200)
    store.set_state("drive-a", 2, "rolled_back", at=400.0, reason="worse than v1 on its soak")
    with store._tx() as c:
        c.execute(
            "INSERT INTO rollouts (id, name, spec_json, state, counted_from, created_at, updated_at) "
            "VALUES (7, 'march', '{}', 'completed', ?, ?, ?)",
            (T0, T0, T0),
        )
        c.execute(
            "INSERT INTO rollout_devices (rollout, device, wave, state, version) "
            "VALUES (7, 'drive-b', 0, 'succeeded', 2)"
        )
    store.insert_coefficient_set(ws.coefficients("drive-a", version=4, created_at=500.0), state="trial")  # unpublished


@pytest.mark.parametrize("backend", ["sqlite", "postgres"])
def test_the_audit_lists_every_published_set_in_order_with_what_the_drive_did(backend, tmp_path, request, monkeypatch):
    target = tmp_path / "fleet.sqlite" if backend == "sqlite" else request.getfixturevalue("postgres_url")
    monkeypatch.setattr(audit, "PAGE", 2)  # pages break inside the tie of the two factory sets
    with Store.open(target) as store:
        history(store)
        rows = list(audit.audit_rows(store, float("-inf"), float("inf")))
        body = {(r["device"], r["version"]): r["body_json"] for r in store._rows("SELECT * FROM coefficient_sets")}
        march = list(audit.audit_rows(store, T0 + 30, T0 + 86_400, ["drive-b"]))
    assert [(r["device"], r["version"]) for r in rows] == [
        ("drive-a", 0), ("drive-b", 0), ("drive-a", 1), ("drive-b", 1), ("drive-a", 2), ("drive-a", 3), ("drive-b", 2)
    ]  # fmt: skip
    got = {(r["device"], r["version"]): r for r in rows}
    assert [got[k]["outcome"] for k in sorted(got)] == [
        "the drive's own", "applied", "no ack", "no ack", "the drive's own", "rejected", "applied"
    ]  # fmt: skip
    assert got[("drive-b", 1)]["rejected_reason"] == "coefficients out of range"
    assert got[("drive-a", 1)]["applied_utc"] == "2026-05-28T20:27:42.000Z"
    assert got[("drive-a", 2)]["state"] == "rolled_back" and got[("drive-a", 3)]["restores_version"] == 1
    assert got[("drive-b", 2)]["rollout"] == 7 and got[("drive-a", 1)]["rollout"] == ""
    for key, row in got.items():  # the hash is of the message as stored: an auditor can check any set against it
        assert row["message_sha256"] == hashlib.sha256(body[key].encode()).hexdigest()
    assert ("drive-a", 4) not in got  # never published: it reached no drive
    assert [(r["device"], r["version"]) for r in march] == [("drive-b", 1)]  # [from, to): the 86,400 s one is out


def test_the_audit_command_writes_the_csv_and_refuses_bad_input_in_one_line(tmp_path):
    db, out = tmp_path / "fleet.sqlite", tmp_path / "audit.csv"
    with Store.open(db) as store:
        history(store)

    def run(*args):
        cmd = [sys.executable, "-m", "encoder_fleet.cli", "audit", "--db", str(db), *args]
        return subprocess.run(cmd, capture_output=True, text=True, timeout=60)

    done = run("--out", str(out), "--from", "2026-05-28T20:27Z", "--to", str(T0 + 86_400))
    assert done.returncode == 0, done.stderr
    with open(out, newline="") as f:
        rows = list(csv.DictReader(f))
    assert [(r["device"], r["version"]) for r in rows] == [
        ("drive-a", "1"),
        ("drive-b", "1"),
        ("drive-a", "2"),
        ("drive-a", "3"),
    ]
    assert "4 coefficient sets published to 2 drives" in done.stdout and "| fit | 3 | 1 | 1 | 1 | 0 |" in done.stdout
    for args, said in [
        (("--out", str(tmp_path / "x.csv"), "--from", "yesterday"), "'yesterday': not a time"),
        (("--out", str(tmp_path / "x.csv"), "--from", "2026-06-01", "--to", "2026-05-01"), "is not before --to"),
        (("--out", str(tmp_path / "x.csv"), "--device", "drive-z"), "device(s) not in"),
        (("--out", str(db)), "is the database itself"),
    ]:
        done = run(*args)
        assert done.returncode == 2 and said in done.stderr and "Traceback" not in done.stderr, (args, done.stderr)
        assert len(done.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "x.csv").exists()
    assert json.loads(json.dumps(rows))  # plain text cells: no object leaked into the CSV


def test_a_reason_a_spreadsheet_would_run_as_a_formula_is_written_as_text(tmp_path):
    """A rejection's reason is the drive's own text (the ack's `reason`, up to 1,000 characters of anything): one
    beginning with = (or +, -, @) was written as it came, and the auditor's spreadsheet ran it as a formula
    (=HYPERLINK(...) a link to anywhere, =cmd|... on some). Such a cell begins with a ' now, which a spreadsheet shows
    as text and a reader strips; a newline inside a reason stays inside its cell."""
    from fleet_wire import messages as wire

    db, out = tmp_path / "fleet.sqlite", tmp_path / "audit.csv"
    formula = '=HYPERLINK("http://example.invalid/x","coefficients out of range")'
    with Store.open(db) as store:
        for version, reason in ((1, formula), (2, "-12 V on the hall supply\nsecond line"), (3, "@SUM(A1)")):
            store.insert_coefficient_set(ws.coefficients("drive-a", version=version, created_at=100.0 * version))
            store.mark_published("drive-a", version, at=T0 + version)
            rejected = wire.ack_message("drive-a", version, "rejected", 100.0 * version + 5, reason=reason)
            store.insert_ack(rejected, received_at=T0 + version + 1)
        store.set_state("drive-a", 1, "rolled_back", at=400.0, reason="+1 window worse")
    cmd = [sys.executable, "-m", "encoder_fleet.cli", "audit", "--db", str(db), "--out", str(out)]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    with open(out, newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["rejected_reason"] for r in rows] == [
        "'" + formula,
        "'-12 V on the hall supply\nsecond line",
        "'@SUM(A1)",
    ]
    assert rows[0]["state_reason"] == "'+1 window worse" and rows[1]["state_reason"] == ""
    assert all(
        not cell.startswith(("=", "+", "-", "@")) for r in rows for k, cell in r.items() if k != "created_at_drive_s"
    )


def test_the_audit_to_stdout_is_the_csv_alone_and_the_summary_goes_to_stderr(tmp_path):
    """`audit --out /dev/stdout > audit.csv` (or piped on): the CSV went to stdout and the summary after it, so the
    file ended in "wrote /dev/stdout: ..." and a markdown table, read as rows of junk. The summary goes to stderr."""
    db = tmp_path / "fleet.sqlite"
    with Store.open(db) as store:
        history(store)
    cmd = [sys.executable, "-m", "encoder_fleet.cli", "audit", "--db", str(db), "--out", "/dev/stdout"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    rows = list(csv.reader(done.stdout.splitlines()))
    assert rows[0] == list(audit.COLUMNS) and len(rows) == 8 and all(len(r) == len(audit.COLUMNS) for r in rows)
    assert "7 coefficient sets published to 2 drives" in done.stderr and "| fit | 4 |" in done.stderr


def test_a_time_that_reads_as_a_date_and_as_unix_seconds_is_refused_not_guessed():
    """--from 20260301 (ISO 8601's basic date, as `date +%Y%m%d` prints it) was read as unix seconds: 1970-08-23,
    so `--to 20260401` audited nothing and said so, 0 sets, as if no set had gone out. An all-digit time that is
    also a date is refused, saying both readings; 2026-03-01 and 20260301.0 say which."""
    with pytest.raises(audit.InputError, match=r"'20260301'.*2026-03-01.*20260301\.0"):
        audit.service_time("20260301")
    assert audit.service_time("2026-03-01") == 1_772_323_200.0
    assert audit.service_time("20260301.0") == 20_260_301.0
    assert audit.service_time("99999999") == 99_999_999.0  # no date: seconds
    assert audit.service_time(str(int(T0))) == T0
