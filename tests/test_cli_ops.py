"""Operating the commands: --version, --log-level with one JSON event per line."""

from __future__ import annotations

import contextlib
import json
import math
import subprocess
import sys
import time
from pathlib import Path

import pytest

from encoder_core.samples import InputError
from fleet_wire.session import free_port


def test_version_is_the_installed_package_version():
    from importlib.metadata import version

    done = subprocess.run([sys.executable, "-m", "encoder_fleet.cli", "--version"], capture_output=True, text=True)
    assert done.returncode == 0 and done.stdout.strip() == f"encoder-fleet {version('encoder-fleet')}"


def test_service_logs_one_json_event_per_line_at_the_level_asked(tmp_path):
    command = [sys.executable, "-m", "encoder_fleet.cli", "service", "--db", str(tmp_path / "f.sqlite")]
    command += [
        "--insecure",
        "--listen",
        f"tcp/127.0.0.1:{free_port()}",
        "--http-port",
        str(free_port()),
        "--log-level",
        "info",
    ]
    service = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert service.stdout.readline().startswith("service:")
    finally:
        service.terminate()
        _, err = service.communicate(timeout=30)
    assert service.returncode == 0, err
    events = [json.loads(line) for line in err.splitlines() if line.strip()]  # every line is one JSON event
    assert {"ts", "level", "logger", "event"} <= set(events[0])
    started = [e for e in events if e["event"] == "service started"]
    assert started and started[0]["level"] == "info" and started[0]["database"].endswith("f.sqlite")
    assert any(e["logger"].startswith("uvicorn") for e in events)  # the web server logs the same way

    quiet = subprocess.Popen(command[:-1] + ["warning"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        quiet.stdout.readline()
    finally:
        quiet.terminate()
        _, err = quiet.communicate(timeout=30)
    assert "service started" not in err


def test_log_events_go_to_a_file_while_a_command_shows_progress_and_back_to_stderr_after(tmp_path, capsys):
    """The demo keeps the service's events in DIR/service.log: its stderr is the progress bar and the summary."""
    import logging

    from encoder_fleet.logs import configure, to_file

    configure("warning")  # the root logger is restored after the test (conftest.root_logger_restored)
    log = logging.getLogger("service.monitor")
    with to_file(tmp_path / "service.log"):
        log.warning("alarm raised", extra={"device": "drive-000", "cause": "offset_step"})
        log.info("below the level asked")
    log.warning("after the block")
    (event,) = [json.loads(line) for line in (tmp_path / "service.log").read_text().splitlines()]
    assert (event["event"], event["device"], event["cause"]) == ("alarm raised", "drive-000", "offset_step")
    err = capsys.readouterr().err
    assert "alarm raised" not in err and json.loads(err.splitlines()[-1])["event"] == "after the block"


def _options(parser):
    import argparse

    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                for option, help_text in _options(sub):
                    yield f"{name} {option}", help_text
        elif action.option_strings or action.dest not in ("help",):
            yield "/".join(action.option_strings) or action.dest, action.help


def test_every_option_of_every_command_has_help_text():
    from encoder_fleet.cli import build_parser

    missing = [name for name, help_text in _options(build_parser()) if not help_text and "command" not in name]
    assert not missing, missing


def run_main(capsys, *argv) -> tuple[int, str]:

    from encoder_fleet.cli import main

    try:
        code = main(list(argv))
    except SystemExit as exc:  # argparse refuses before main runs
        code = exc.code
    err = capsys.readouterr().err
    return code, err


def test_bad_arguments_are_one_line_and_exit_2(capsys, tmp_path):
    from service.store import Store

    Store.open(tmp_path / "f.sqlite").close()
    empty = tmp_path / "empty.sqlite"
    empty.touch()
    cases = [
        (("simulate", "--out", str(tmp_path / "x.csv"), "--days", "-1"), "--days"),
        (("simulate", "--out", str(tmp_path / "x.csv"), "--sample-s", "nan"), "--sample-s"),
        (("demo", "--devices", "0"), "--devices"),
        (("agent", "--device", "a/b", "--connect", "tcp/127.0.0.1:1"), "--device"),
        (("agent", "--device", "..", "--connect", "tcp/127.0.0.1:1"), "--device"),
        (("service", "--http-port", "70000"), "--http-port"),
        (("bench-fleet", "--devices", "10", "-5"), "--devices"),
        (("export", "--db", str(tmp_path / "f.sqlite"), "--device", "d", "--out", "o.mcap", "--from", "5", "--to", "1"),
         "--from"),
        (("no-such-command",), "invalid choice"),
        (("simulate", "--out", str(tmp_path / "x.csv"), "--set", "thermal_lag_tau_s=NaN"), "finite numbers only"),
        (("simulate", "--out", str(tmp_path / "x.csv"), "--set", 'thermal_lag_tau_s="x"'), "takes a number"),
        (("simulate", "--out", str(tmp_path / "x.csv"), "--set", "harmonics=3"), "takes a list"),
        (("service", "--insecure", "--db", "mysql://h/fleet", "--http-port", "0"), "not a file path"),
        (("rollout", "list", "--url", "notaurl"), "REST address"),
        (("rollout", "create", "--url", "http://127.0.0.1:1", "--name", "n", "--change", "refit",
          "--base-per-minute", "1", "--abort", "regressed:ten:5"), "PERCENT is a number"),
        # a label's name twice: the last value won unsaid (the rollout went to plant-7 alone), before any request
        (("rollout", "create", "--url", "http://127.0.0.1:1", "--name", "n", "--change", "refit",
          "--base-per-minute", "1", "--soak-windows", "5", "--label", "site=plant-3", "--label", "site=plant-7"),
         "--label: site given twice"),
        (("devices", "label", "drive-1", "site=plant-3", "site=plant-7", "--url", "http://127.0.0.1:1"),
         "site given twice"),
        (("export", "--db", str(empty), "--device", "d", "--out", str(tmp_path / "e.mcap")), "an empty file"),
        (("service", "--insecure", "--db", str(tmp_path / "s" / "f.sqlite"), "--listen", "tcp/bad",
          "--http-port", "0"), "tcp/bad: invalid socket address"),
    ]  # fmt: skip
    for argv, word in cases:
        code, err = run_main(capsys, *argv)
        lines = err.strip().splitlines()
        assert code == 2 and len(lines) == 1 and word in lines[0] and "Traceback" not in err, (argv, err)
        assert ".rs:" not in err, err  # no Rust source file in a person's error
    assert not (tmp_path / "x.csv").exists() and not (tmp_path / "o.mcap").exists()
    assert not list(tmp_path.glob("mysql*")) and not list(Path().glob("mysql:*"))  # no file made of the URL
    assert empty.stat().st_size == 0 and not (tmp_path / "e.mcap").exists()  # an export made no database of it
    assert not (tmp_path / "s" / "f.sqlite").exists()  # a router that could not listen: no database made
    outbox = str(tmp_path / "a" / "o.sqlite")
    code, err = run_main(capsys, "agent", "--device", "d1", "--insecure", "--connect", "nonsense", "--outbox", outbox)
    last = err.strip().splitlines()[-1]  # after the --insecure warning
    assert code == 2 and "cannot connect to nonsense: Endpoints must be of the form <protocol>/<address>" in last, err
    assert ".rs:" not in err and "Json5Err" not in err and "Traceback" not in err, err
    assert not (tmp_path / "a").exists()  # an agent that could not connect: no outbox made (there was one)


def test_a_value_beginning_with_a_minus_and_a_digit_is_taken_as_written(capsys):
    """`agent --temp-range -40,150`, as its help and the README write it: argparse took a value beginning with a minus
    for an option unless it was a plain number (-40, -.5), and refused the range as "expected one argument"; the
    only way in was --temp-range=-40,150. So was a time such as `export --from -1e3`."""
    from encoder_fleet.cli import build_parser

    agent = ["agent", "--device", "d1", "--insecure", "--connect", "tcp/127.0.0.1:1"]
    parser = build_parser()
    assert parser.parse_args([*agent, "--temp-range", "-40,150"]).temp_range == (-40.0, 150.0)
    assert parser.parse_args([*agent, "--temp-range", "-40,-10"]).temp_range == (-40.0, -10.0)
    export = ["export", "--device", "d1", "--out", "o.mcap"]
    assert parser.parse_args([*export, "--from", "-1e3", "--to", "-5"]).t_from == -1000.0
    code, err = run_main(capsys, *agent, "--temp-range", "-40,-50")  # upside down: the range's own reason
    assert code == 2 and len(err.strip().splitlines()) == 1 and "LO must be below HI" in err, err
    code, err = run_main(capsys, *agent, "--temp-range", "-x")  # an option it is not: still refused as one
    assert code == 2 and "--temp-range" in err, err


def test_bench_fleet_stores_every_window_through_a_real_router_and_times_them_from_the_first_put(tmp_path):
    """`encoder-fleet bench-fleet` on a small fleet, as a user runs it: the publisher process's windows all stored
    (none rejected), every device refitted and rolled out, and windows/s timed from the publisher's first put (the
    one line it prints) to the last window stored: a finite rate, over a time no longer than the whole command's."""
    out = tmp_path / "bench.json"
    command = [sys.executable, "-m", "encoder_fleet.cli", "bench-fleet", "--sizes", "10", "--windows", "5"]
    started = time.monotonic()
    done = subprocess.run([*command, "--security", "off", "--json", str(out)], capture_output=True, text=True)
    took = time.monotonic() - started
    assert done.returncode == 0, done.stderr
    (row,) = json.loads(out.read_text())["rows"]
    assert row["devices"] == 10 and row["windows"] == row["expected"] == 50 and row["rejected"] == 0, row
    assert row["refits"] == 10 and row["rollouts"] == 10, row
    assert 0 < row["ingest_s"] <= row["monitored_s"] < took, row
    assert math.isclose(row["windows_per_s"], 50 / row["ingest_s"]), row
    assert "end to end" in done.stdout and "windows/s" in done.stdout


def test_export_refuses_to_write_over_its_own_database(tmp_path):
    """`export --out` naming the database (or its write-ahead log) is refused before anything is opened for writing:
    once, it truncated the fleet's history to 0 bytes. The history is whole afterwards and a real export works."""
    from fleet_wire import keys
    from fleet_wire import messages as wire
    from service.store import Store
    from tests.wire_samples import window

    db = tmp_path / "fleet.sqlite"
    with Store.open(db) as store:
        store.ingest_many([(keys.key("drive-001", keys.STATS), wire.encode("window", window(seq=s))) for s in (1, 2)])
    size = db.stat().st_size
    for out in (db, tmp_path / "fleet.sqlite-wal", tmp_path / "." / "fleet.sqlite"):
        done = subprocess.run(
            [sys.executable, "-m", "encoder_fleet.cli", "export", "--db", str(db), "--device", "drive-001"]
            + ["--out", str(out)],
            capture_output=True,
            text=True,
        )
        assert done.returncode == 2 and "is the database itself" in done.stderr, done.stderr
    assert db.stat().st_size == size
    with Store.open(db) as store:
        assert store.max_seq("drive-001") == 2
    done = subprocess.run(
        [sys.executable, "-m", "encoder_fleet.cli", "export", "--db", str(db), "--device", "drive-001"]
        + ["--out", str(tmp_path / "drive-001.mcap")],
        capture_output=True,
        text=True,
    )
    assert done.returncode == 0 and (tmp_path / "drive-001.mcap").stat().st_size > 0, done.stderr


def test_an_export_to_stdout_is_the_mcap_file_alone(tmp_path):
    """`export --out /dev/stdout > drive.mcap` (or piped into another tool): "wrote /dev/stdout" was printed after
    the MCAP file's last byte, so the file read as truncated garbage at its end. That line goes to stderr."""
    import io

    from mcap.reader import make_reader

    from fleet_wire import keys
    from fleet_wire import messages as wire
    from service.store import Store
    from tests.wire_samples import window

    db = tmp_path / "fleet.sqlite"
    with Store.open(db) as store:
        store.ingest_many([(keys.key("drive-001", keys.STATS), wire.encode("window", window(seq=s))) for s in (1, 2)])
    done = subprocess.run(
        [sys.executable, "-m", "encoder_fleet.cli", "export", "--db", str(db), "--device", "drive-001"]
        + ["--out", "/dev/stdout"],
        capture_output=True,
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.endswith(b"\x89MCAP0\r\n")  # the magic that ends every MCAP file
    assert sum(1 for _ in make_reader(io.BytesIO(done.stdout)).iter_messages()) >= 2
    assert b"wrote /dev/stdout" in done.stderr


def test_export_changes_no_file_it_reads(tmp_path):
    """An export of a database an older encoder-fleet wrote migrated it in place (the audit's evidence rewritten,
    and any SQLite file named by --db given the service's tables). Now such a database is refused in one line,
    byte for byte as it was, unless --migrate is given; a file that is not the service's database is refused."""
    import hashlib
    import sqlite3

    from service.store import Store, migration_files

    older = tmp_path / "migrations"  # the migrations of the version before the newest
    older.mkdir()
    for _, f in migration_files()[:-1]:
        (older / f.name).write_text(f.read_text())
    db = tmp_path / "old.sqlite"
    with Store.open(db, migrations_dir=older) as store:
        store.set_online("drive-001", True)  # its device row, in columns every version has
    other = tmp_path / "notes.sqlite"
    conn = sqlite3.connect(other)
    conn.execute("CREATE TABLE notes (x)")
    conn.commit()
    conn.close()
    digests = {p: hashlib.sha256(p.read_bytes()).hexdigest() for p in (db, other)}
    export = [sys.executable, "-m", "encoder_fleet.cli", "export", "--device", "drive-001"]
    for path, word in ((db, "written by an older encoder-fleet"), (other, "is not the service's")):
        done = subprocess.run([*export, "--db", str(path), "--out", str(tmp_path / "x.mcap")], capture_output=True,
                              text=True)  # fmt: skip
        assert done.returncode == 2 and word in done.stderr and len(done.stderr.strip().splitlines()) == 1, done.stderr
        assert hashlib.sha256(path.read_bytes()).hexdigest() == digests[path] and not (tmp_path / "x.mcap").exists()
    done = subprocess.run([*export, "--db", str(db), "--out", str(tmp_path / "x.mcap"), "--migrate"],
                          capture_output=True, text=True)  # fmt: skip
    assert done.returncode == 0 and (tmp_path / "x.mcap").stat().st_size > 0, done.stderr


def test_an_agent_refuses_a_factory_file_that_is_not_a_coefficient_set(tmp_path):
    """`agent --factory` checks the file as the wire checks a set (schema, types, finite numbers): null, a list, a
    set with a NaN weight, too few weights or no schema is one line naming the file and what is wrong, exit 2, and
    nothing is created (no outbox)."""
    from tests.wire_samples import coefficients

    rec = tmp_path / "rec.csv"
    assert main_simulate(rec) == 0
    good = {**coefficients("drive-001", 0), "basis": "factory"}
    nan_w = json.dumps(good).replace('"w": [1.01', '"w": [NaN', 1)
    short_w = json.loads(json.dumps(good))
    short_w["bands"][0]["w"] = [1.0, 2.0]
    no_schema = {k: v for k, v in good.items() if k != "schema"}
    for name, text in [
        ("null", "null"),
        ("list", "[1, 2, 3]"),
        ("nan", nan_w),
        ("short", json.dumps(short_w)),
        ("schema", json.dumps(no_schema)),
    ]:
        factory = tmp_path / f"{name}.json"
        factory.write_text(text)
        outbox = tmp_path / f"{name}-outbox.sqlite"
        command = [sys.executable, "-m", "encoder_fleet.cli", "agent", "--device", "drive-001", "--insecure"]
        command += ["--connect", f"tcp/127.0.0.1:{free_port()}", "--source", f"replay:{rec}"]
        command += ["--factory", str(factory), "--outbox", str(outbox)]
        done = subprocess.run(command, capture_output=True, text=True, timeout=60)
        assert done.returncode == 2, (name, done.stderr)
        assert f"--factory {factory}: not a coefficient set" in done.stderr and "Traceback" not in done.stderr, name
        assert not outbox.exists(), name


def _replay_agent(rec, factory, outbox, connect, *options):
    command = [sys.executable, "-m", "encoder_fleet.cli", "agent", "--device", "drive-001", "--insecure"]
    command += ["--connect", connect, "--source", f"replay:{rec}", "--window-s", "60"]
    command += ["--factory", str(factory), "--outbox", str(outbox), "--real-time-factor", "3600", *options]
    return subprocess.run(command, capture_output=True, text=True, timeout=120)


def _recording_and_factory(tmp_path, name, t, temp=True):
    import numpy as np

    from encoder_core.samples import Samples
    from encoder_fleet.recording import write_recording
    from tests.wire_samples import coefficients

    factory = tmp_path / "factory.json"
    factory.write_text(json.dumps({**coefficients("drive-001", 0), "basis": "factory"}))
    rec = tmp_path / f"{name}.csv"
    angle = np.random.default_rng(0).uniform(0, 2 * np.pi, t.size)
    temps = np.full(t.size, 25.0) if temp else None
    write_recording(Samples(t=t, d=1000 * np.cos(angle), q=1000 * np.sin(angle), temp_c=temps), rec)
    return rec, factory


@contextlib.contextmanager
def _service(tmp_path):
    """(store, endpoint): the service on a real router and SQLite file, for a replaying agent to send to."""
    from fleet_wire.session import loopback_endpoint
    from service.runtime import FleetService, open_session
    from service.store import Store

    endpoint = loopback_endpoint()
    store = Store.open(tmp_path / "fleet.sqlite")
    router = open_session(listen=[endpoint])
    service = FleetService(store, router, refit_interval_s=0).start()
    try:
        yield store, endpoint
    finally:
        service.stop()
        router.close()
        store.close()


def _windows_stored(store, n: int, device: str = "drive-001") -> list[dict]:
    """The device's windows once `n` are stored (or after 10 s, whatever is stored then)."""
    deadline = time.monotonic() + 10
    while len(store.windows(device)) < n and time.monotonic() < deadline:
        time.sleep(0.1)
    return store.windows(device)


def test_an_agent_refuses_a_recording_whose_clock_the_wire_cannot_carry(tmp_path):
    """A field recording with t in unix milliseconds: the wire carries a drive clock of 0 to 1e10 s, so every window
    was refused one by one, logged, and the command exited 0 having sent none. Now it says so in one line and exits 2
    before anything is created, as for a recording without temp_c or one whose t goes back (read_recording names
    the line)."""
    import numpy as np

    t = np.arange(0.0, 120.0, 0.05)
    back = t.copy()
    back[1000:] -= 10.0
    cases = {
        "millis": (1.7e12 + t * 1000.0, True, "t reaches 1.7e+12 s on its last row"),
        "no-temp": (t, False, "needs the temp_c column"),
        "back": (back, True, "line 1002, column 't': does not increase"),
    }
    for name, (times, temp, says) in cases.items():
        rec, factory = _recording_and_factory(tmp_path, name, times, temp)
        outbox = tmp_path / f"{name}-outbox.sqlite"
        done = _replay_agent(rec, factory, outbox, f"tcp/127.0.0.1:{free_port()}")
        assert done.returncode == 2, (name, done.stderr)
        errors = [line for line in done.stderr.splitlines() if "error" in line]
        assert len(errors) == 1 and says in errors[0] and "Traceback" not in done.stderr, (name, done.stderr)
        assert not outbox.exists(), name


def test_a_recording_from_before_0_is_replayed_whole_from_0(tmp_path):
    """t from a trigger, negative before it (the project's own fieldsim drives start at -0.01 s, jittered): the wire
    refuses a window before 0, so each was logged and dropped (a minute here, a fleet replay's first 300 s), and the
    command exited 0. Now the replay moves every t by the same amount so that the first is 0, and says so."""
    import numpy as np

    rec, factory = _recording_and_factory(tmp_path, "trigger", np.arange(-60.0, 120.0, 0.05))
    with _service(tmp_path) as (store, endpoint):
        done = _replay_agent(rec, factory, tmp_path / "outbox.sqlite", endpoint)
        assert done.returncode == 0, done.stderr
        assert "t starts at -60 s; replayed with every t moved by 60 s" in done.stderr
        assert "not sent" not in done.stderr and "drive-001: 3 windows" in done.stdout, done.stdout
        stored = _windows_stored(store, 3)
        assert [round(w["window_start"]) for w in stored] == [0, 60, 120] and stored[-1]["window_end"] < 180


def test_a_replayed_temperature_below_absolute_zero_costs_its_sample_not_the_replay(tmp_path):
    """A drive's log whose temp_c holds a logger's no-reading sentinel (-999) on one row: the agent reads such a
    temperature as a broken sensor's (NaN: the sample rejected as non_finite, as +999 or one past --temp-range), but
    the replay refused the whole recording at that line, so a day of good samples was never sent. Now that sample
    alone is rejected; a recording read for calibration or diagnosis still refuses it (read_recording)."""
    import numpy as np

    from encoder_fleet.recording import read_recording

    rec, factory = _recording_and_factory(tmp_path, "sentinel", np.arange(0.0, 120.0, 0.05))
    lines = rec.read_text().splitlines(keepends=True)
    header = lines[0].strip().split(",")
    row = lines[301].rstrip("\n").split(",")
    row[header.index("temp_c")] = "-999"
    lines[301] = ",".join(row) + "\n"
    rec.write_text("".join(lines))
    with pytest.raises(InputError, match="line 302, column 'temp_c': -999 °C is below absolute zero"):
        read_recording(rec)
    with _service(tmp_path) as (store, endpoint):
        done = _replay_agent(rec, factory, tmp_path / "outbox.sqlite", endpoint)
        assert done.returncode == 0 and "drive-001: 2 windows" in done.stdout, done.stderr
        _windows_stored(store, 2)
        first, second = store.monitor_windows("drive-001", 0, 2)
        assert first["rejected_by_reason"]["non_finite"] == 1 and first["stats"].temp_min > 24.9
        assert second["rejected_by_reason"]["non_finite"] == 0


def main_simulate(out) -> int:
    from encoder_fleet.cli import main

    return main(["simulate", "--scenario", "field", "--days", "0.01", "--out", str(out)])


def test_a_token_that_could_not_be_written_out_is_revoked(tmp_path):
    """`token create --out` where the file cannot be written (a directory stands there): one line, exit 2, and the
    token it made is revoked, so that no live token exists that nobody holds. The file written for a good path is
    0600 and holds the token."""
    import os
    import stat

    db = tmp_path / "fleet.sqlite"
    (tmp_path / "taken").mkdir()
    token = [sys.executable, "-m", "encoder_fleet.cli", "token"]
    done = subprocess.run(
        [*token, "create", "--scope", "read", "--db", str(db), "--create-db", "--out", str(tmp_path / "taken")],
        capture_output=True,
        text=True,
    )
    assert done.returncode == 2 and "is a directory" in done.stderr and "Traceback" not in done.stderr, done.stderr
    listed = subprocess.run([*token, "list", "--db", str(db)], capture_output=True, text=True).stdout.split()
    assert listed[1:3] == ["read", "revoked"], listed
    good = tmp_path / "keys" / "read.token"
    done = subprocess.run([*token, "create", "--scope", "read", "--db", str(db), "--out", str(good)], text=True)
    assert done.returncode == 0 and stat.S_IMODE(os.stat(good).st_mode) == 0o600 and len(good.read_text()) > 20


def test_token_create_over_a_file_refuses_or_revokes_the_token_it_held(tmp_path):
    """`token create --out FILE` where FILE holds a token: it was replaced without a word and the token in it stayed
    live with nobody holding it; a symlink there had the token written where it pointed. Now a file there is refused
    (one line, exit 2, no token made) unless --force, which replaces it and revokes the live token it held, and says
    so; a link or a stream there is refused even with --force, and what it points to is left as it was."""
    import os
    import stat

    from service.auth import TokenAuth
    from service.store import Store

    db, out = tmp_path / "fleet.sqlite", tmp_path / "admin.token"
    token = [sys.executable, "-m", "encoder_fleet.cli", "token", "create", "--scope", "admin", "--db", str(db)]
    run = lambda *args: subprocess.run([*token, *args], capture_output=True, text=True)  # noqa: E731
    assert run("--create-db", "--out", str(out)).returncode == 0
    first = out.read_text().strip()
    refused = run("--out", str(out))
    assert refused.returncode == 2 and "already exists" in refused.stderr and "--force" in refused.stderr
    assert len(refused.stderr.strip().splitlines()) == 1 and "Traceback" not in refused.stderr
    assert out.read_text().strip() == first
    replaced = run("--out", str(out), "--force")
    assert replaced.returncode == 0 and "token 1, which it held, is revoked" in replaced.stdout, replaced.stdout
    second = out.read_text().strip()
    assert second != first and stat.S_IMODE(out.stat().st_mode) == 0o600
    elsewhere, link = tmp_path / "elsewhere", tmp_path / "link.token"
    elsewhere.write_text("not a token\n")
    os.chmod(elsewhere, 0o644)
    link.symlink_to(elsewhere)
    os.mkfifo(tmp_path / "fifo")
    for path in (link, tmp_path / "fifo"):
        done = run("--out", str(path), "--force")
        assert done.returncode == 2 and str(path) in done.stderr and "Traceback" not in done.stderr, done.stderr
    assert link.is_symlink() and elsewhere.read_text() == "not a token\n"
    with Store.open(db) as store:
        auth = TokenAuth(store)
        assert auth.scope_of(first) is None and auth.scope_of(second) == "admin"
        assert auth.count() == 1 and len(auth.tokens()) == 2  # nothing made for the refusals


def test_a_token_file_is_written_where_the_filesystem_has_no_hard_links(tmp_path, monkeypatch):
    """A new --out file is made with O_CREAT | O_EXCL: it had been a temporary file hard-linked onto the path, and
    vfat and some network mounts refuse hard links (os.link raises EPERM there, as it is made to here), so every
    `token create --out` to such a disk failed."""
    import errno
    import os
    import stat

    from service.auth import write_token_file

    def no_links(*_):
        raise PermissionError(errno.EPERM, "Operation not permitted")

    monkeypatch.setattr(os, "link", no_links)
    out = tmp_path / "a.token"
    write_token_file(out, "t0ken", replace=False)
    assert out.read_text() == "t0ken\n" and stat.S_IMODE(out.stat().st_mode) == 0o600
    with pytest.raises(FileExistsError):  # one there already, or a link there: left as it is
        write_token_file(out, "other", replace=False)
    (tmp_path / "link.token").symlink_to(tmp_path / "nowhere")
    with pytest.raises(FileExistsError):
        write_token_file(tmp_path / "link.token", "other", replace=False)
    assert out.read_text() == "t0ken\n" and not (tmp_path / "nowhere").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.token", "link.token"]  # no temporary file left


def test_a_database_password_is_never_printed(tmp_path):
    """The password of a postgresql:// --db in any of its forms (user:pw@, :pw@, a password with an @ in it, a
    password= parameter) is starred in every message; the first three forms but one were printed as given."""
    from fleet_wire.session import loopback_endpoint
    from service.db import redacted

    for url in ("postgresql://fleet:s3cret@h/db", "postgresql://:s3cret@h/db", "postgresql://u:p@s3cret@h/db",
                "postgresql://u@h/db?sslmode=require&password=s3cret"):  # fmt: skip
        assert "s3cret" not in redacted(url) and "***" in redacted(url), url
    assert redacted("postgresql://u@h/db") == "postgresql://u@h/db" and redacted("f.sqlite") == "f.sqlite"
    done = subprocess.run(
        [sys.executable, "-m", "encoder_fleet.cli", "service", "--insecure", "--db", "postgresql://:s3cret@127.0.0.1:1/x",
         "--listen", loopback_endpoint(), "--http-port", "0"],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert done.returncode == 2 and "s3cret" not in done.stderr + done.stdout and "***" in done.stderr, done.stderr
