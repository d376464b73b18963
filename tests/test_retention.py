"""Retention (`service --keep-days`): the oldest windows and dead letters are deleted, and nothing the refit, the
drift monitor, a trial or the watermark still needs goes with them."""

from __future__ import annotations

import json
import sqlite3
import subprocess
import sys
import threading
import time

import msgspec
import numpy as np
import pytest
import zenoh
from pg_locks import wait_for_a_lock_wait

import tests.wire_samples as ws
from fleet_wire import keys
from fleet_wire import messages as wire
from fleet_wire.session import loopback_endpoint, session_config
from service.runtime import FleetService, open_session
from service.store import Store

DEVICE = "drive-001"
HORIZON_S = 150.0  # 60 s windows: a band's sum holds its newest two or three


def wait_for(predicate, timeout=30.0):
    deadline = time.monotonic() + timeout
    while not predicate() and time.monotonic() < deadline:
        time.sleep(0.05)
    return predicate()


def seqs(store: Store, device: str = DEVICE) -> list[int]:
    return [w["seq"] for w in store.windows(device, limit=100_000)]


def sums(store: Store) -> dict:
    return {b: (w, s, total.moments.copy()) for b, (total, w, s) in store.band_stats(DEVICE).items()}


@pytest.mark.parametrize("backend", ["sqlite", "postgres"])
def test_pruning_keeps_every_band_sum_the_watermark_and_what_a_trial_or_the_bound_holds(backend, tmp_path, request):
    target = tmp_path / "fleet.db" if backend == "sqlite" else request.getfixturevalue("postgres_url")
    # two bands, so that one of them (band 3, last seen at seq 20) holds old windows in its sum
    msgs = [ws.window(seq=s, temp_c=33.0 if s <= 20 else 23.0, version=3 if 11 <= s <= 14 else 0) for s in range(1, 41)]
    with Store.open(target, band_horizon_s=HORIZON_S) as store:
        store.ingest_many([(keys.key(DEVICE, keys.STATS), wire.encode("window", m)) for m in msgs])
        before = sums(store)
        in_band_3 = {s for s in range(1, 21) if s >= store._device_bands(DEVICE)[3][3]}
        assert in_band_3 and store.contiguous_seq(DEVICE) == 40
        n = store.prune_windows(DEVICE, ended_before=np.inf, below_seq=36, keep_version=3, limit=7)
        assert n == 7 and seqs(store)[:1] == [8]  # the oldest first, a batch at a time
        while store.prune_windows(DEVICE, ended_before=np.inf, below_seq=36, keep_version=3):
            pass
        kept = set(seqs(store))
        assert kept == in_band_3 | set(range(11, 15)) | set(range(36, 41)) | {
            s for s in range(21, 36) if s >= store._device_bands(DEVICE)[2][3]
        }
        assert store.contiguous_seq(DEVICE) == 40  # the floor stepped over what was deleted
        assert store.prune_windows(DEVICE, ended_before=np.inf, below_seq=36, keep_version=3) == 0
        assert store.device(DEVICE)["windows"] == len(kept)  # the count kept with the device's row follows
    with Store.open(target, band_horizon_s=HORIZON_S) as store:  # read again: no sum is rebuilt short of a window
        after = sums(store)
        assert after.keys() == before.keys()
        for band, (windows, samples, moments) in before.items():
            assert after[band][:2] == (windows, samples)
            np.testing.assert_allclose(after[band][2], moments, rtol=1e-12)
        assert set(seqs(store)) == kept and store.contiguous_seq(DEVICE) == 40
        # a window that ended after `ended_before` stays, whatever else holds
        assert store.prune_windows(DEVICE, ended_before=0.0, below_seq=41, keep_version=None) == 0


def test_two_members_pruning_one_drive_at_once_on_postgresql_keep_its_window_count(postgres_url):
    """Two service processes pruning one drive at the same moment (a member whose session dropped, its partitions
    taken meanwhile by another): both read the same oldest windows, the second's deletes, waiting on the first's,
    deleted none once it committed, and it took them off the drive's window count again (and counted them pruned):
    the count stayed short for good. The drive's row is locked first, so the second reads what the first left."""
    msgs = [ws.window(seq=s) for s in range(1, 41)]
    with Store.open(postgres_url, band_horizon_s=HORIZON_S) as first, Store.open(postgres_url) as second:
        first.ingest_many([(keys.key(DEVICE, keys.STATS), wire.encode("window", m)) for m in msgs])
        bound = {"ended_before": np.inf, "below_seq": 36, "keep_version": None, "limit": 10}
        assert first.prune_windows(DEVICE, **bound) == 10  # and its band sums written, as the second reads them
        outcome = {}

        def prune_meanwhile():
            outcome["pruned"] = first.prune_windows(DEVICE, **bound)

        with second.transaction():  # the other member's pruning, not committed yet
            assert second.prune_windows(DEVICE, **bound) == 10
            racer = threading.Thread(target=prune_meanwhile)
            racer.start()
            wait_for_a_lock_wait(postgres_url, "the second pruning")
        racer.join(10)
        assert outcome == {"pruned": 10}
        assert (len(seqs(first)), first.device(DEVICE)["windows"]) == (10, 10)  # 31 to 40


def test_a_band_without_a_stored_sum_keeps_its_windows(tmp_path):
    with Store.open(tmp_path / "fleet.db", band_horizon_s=HORIZON_S) as store:
        for s in range(1, 9):
            store.insert_window(ws.window(seq=s))
        store.restart_band_memory(DEVICE, after=1e9)  # a step forgot every window: the band has no sum
        assert store.band_stats(DEVICE) == {}
        assert store.prune_windows(DEVICE, ended_before=np.inf, below_seq=9, keep_version=None) == 0
        assert seqs(store) == list(range(1, 9))


def test_old_dead_letters_go_and_the_newer_stay(tmp_path):
    with Store.open(tmp_path / "fleet.db") as store:
        ids = [store.dead_letter("k", "bad_json", "x", b"{", received_at=t) for t in (1.0, 2.0, 3.0, 50.0, 4.0)]
        assert store.prune_dead_letters(3.5, limit=2) == 2
        assert store.prune_dead_letters(3.5, limit=2) == 1  # id order: the look stops at the first one kept
        assert store.prune_dead_letters(3.5) == 0
        assert sorted(d["id"] for d in store.dead_letters()) == ids[3:]


class Fleet:
    def __init__(self, tmp_path, **options):
        self.store = Store.open(tmp_path / "fleet.sqlite", band_horizon_s=HORIZON_S)
        self.endpoint = loopback_endpoint()
        self.router = open_session(listen=[self.endpoint])
        self.service = FleetService(self.store, self.router, refit_interval_s=0, **options).start()
        self.client = zenoh.open(session_config("client", connect=[self.endpoint]))

    def put(self, msgs) -> None:
        for m in msgs:
            self.client.put(keys.key(m["device"], keys.STATS), wire.encode("window", m))

    def close(self) -> None:
        self.client.close()
        self.service.stop()
        self.router.close()
        self.store.close()


@pytest.mark.parametrize("monitor", [True, False])
def test_the_service_prunes_behind_the_watermark_and_the_monitor_and_keeps_each_devices_newest(tmp_path, monitor):
    keep_days = 5 * 60 / 86_400  # five 60 s windows of drive time
    fleet = Fleet(tmp_path, keep_days=keep_days, monitor_interval_s=0.5 if monitor else 0)
    try:
        sent = [s for s in range(1, 61) if s != 45]  # 45 is still on its way: nothing from it on may go
        fleet.put([ws.window(seq=s) for s in sent] + [ws.window("drive-002", seq=1)])
        assert wait_for(lambda: len(seqs(fleet.store)) == len(sent) and seqs(fleet.store, "drive-002") == [1])
        assert fleet.service.watermark(DEVICE) == 44
        if monitor:  # it monitors up to the watermark; its last window is read again at a restart
            assert wait_for(lambda: fleet.store.monitor_states(DEVICE).get(DEVICE, (None, 0))[1] == 44)
        # drive time alone would take 1..54 (ended more than five windows before the newest, 60)
        first_kept = 44 if monitor else 46
        first = fleet.service.prune()["windows"]
        assert first == len([s for s in sent if s < first_kept])
        assert seqs(fleet.store) == [s for s in sent if s >= first_kept]
        assert seqs(fleet.store, "drive-002") == [1]  # a device's newest stays however old
        assert fleet.service.watermark(DEVICE) == 44
        fleet.put([ws.window(seq=45)])  # the gap filled: the watermark moves on, and the next pass prunes to 54
        assert wait_for(lambda: fleet.service.watermark(DEVICE) == 60)
        if monitor:
            assert wait_for(lambda: fleet.store.monitor_states(DEVICE)[DEVICE][1] == 60)
        assert fleet.service.prune() == {"windows": 54 - first, "dead_letters": 0}
        band_first = fleet.store._device_bands(DEVICE)[2][3]
        assert seqs(fleet.store) == list(range(min(55, band_first), 61)) and band_first <= 60
        assert fleet.service.counters.snapshot()["pruned_windows"] == 54
    finally:
        fleet.close()


def test_a_retention_pass_ends_at_its_time_budget_or_a_stop_and_the_next_goes_on_where_it_ended(tmp_path):
    # the first pass over a long history took the refit thread for hours (no refit, trial or rollout step meanwhile)
    # and held service.stop() as long
    fleet = Fleet(tmp_path, keep_days=5 * 60 / 86_400, monitor_interval_s=0)
    try:

        def send(device: str, seq_from: int, seq_to: int) -> None:  # one window's statistics, at every seq
            one = wire.window_from_dict(ws.window(device))
            fleet.store.ingest_many(
                [
                    (keys.key(device, keys.STATS), wire.encode_window(msgspec.structs.replace(one, **at(s))))
                    for s in range(seq_from, seq_to + 1)
                ]
            )

        def at(seq: int) -> dict:
            return {"seq": seq, "window_start": 60.0 * (seq - 1), "window_end": 60.0 * seq}

        send(DEVICE, 1, 2500)
        send("drive-002", 1, 1200)
        passes = []
        for _ in range(6):
            passes.append((fleet.service.prune(budget_s=0.0)["windows"], len(seqs(fleet.store, "drive-002"))))
        # a batch a pass (store.PRUNE_BATCH), the first device's to its end (seq 2494: five windows of drive time and
        # the band's sum stay) before the second's: a pass out of time after a device's last batch does no other
        assert passes == [(1000, 1200), (1000, 1200), (494, 1200), (0, 1200), (1000, 200), (194, 6)]
        assert seqs(fleet.store) == list(range(2495, 2501))
        assert fleet.service.prune() == {"windows": 0, "dead_letters": 0}
        send(DEVICE, 2501, 4000)  # another backlog, then the service stops: a pass takes one batch, no more
        fleet.service.stop()
        assert fleet.service.prune()["windows"] == 1000
    finally:
        fleet.close()  # the service's stop a second time: a no-op


def test_the_service_refuses_retention_without_a_band_horizon(tmp_path):
    db = tmp_path / "fleet.sqlite"
    cmd = [sys.executable, "-m", "encoder_fleet.cli", "service", "--insecure", "--db", str(db), "--http-port", "0"]
    out = subprocess.run([*cmd, "--keep-days", "30", "--band-horizon-h", "0"], capture_output=True, text=True)
    assert out.returncode == 2 and "--keep-days needs a band horizon" in out.stderr, out.stderr
    assert "Traceback" not in out.stderr and not db.exists()  # refused before anything was made
    out = subprocess.run([*cmd, "--keep-days", "-1"], capture_output=True, text=True)
    assert out.returncode == 2 and "must be greater than 0" in out.stderr


# --- backup: a consistent copy while the service writes ---------------------------------------------


def backup_cli(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "encoder_fleet.cli", "backup", *args], capture_output=True, text=True)


def test_a_backup_taken_while_windows_are_written_is_a_consistent_checked_copy_the_service_opens(tmp_path):
    db, out = tmp_path / "fleet.sqlite", tmp_path / "backup.sqlite"
    store = Store.open(db, band_horizon_s=HORIZON_S)
    for s in range(1, 201):
        store.insert_window(ws.window(seq=s))
    stop, written = threading.Event(), [200]

    def write_on() -> None:  # the service's writer, going on while the copy is taken
        while not stop.is_set() and written[0] < 2000:
            written[0] += 1
            store.insert_window(ws.window(seq=written[0]))

    writer = threading.Thread(target=write_on)
    writer.start()
    try:
        done = backup_cli("--db", str(db), str(out), "--json", "/dev/stdout")
    finally:
        stop.set()
        writer.join()
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    assert report["backup"] == str(out) and (out.stat().st_mode & 0o777) == 0o600
    n = report["rows"]["windows"]
    assert 200 <= n <= written[0] and report["rows"]["devices"] == 1
    with Store.open(out, band_horizon_s=HORIZON_S) as copy:  # a restore: the service opens it as its own
        got = copy.windows(DEVICE, limit=100_000, stats=True)
        assert [w["seq"] for w in got] == list(range(1, n + 1))  # one snapshot: a prefix, no window half there
        assert got == store.windows(DEVICE, limit=n, stats=True)
        assert copy.migrations() == store.migrations()
    store.close()


def test_a_backup_refuses_an_existing_file_a_postgres_url_and_a_file_that_is_no_database(tmp_path):
    db = tmp_path / "fleet.sqlite"
    Store.open(db).close()
    taken = tmp_path / "taken.sqlite"
    taken.write_bytes(b"a file the user keeps")
    done = backup_cli("--db", str(db), str(taken))
    assert done.returncode == 2 and "exists: a backup never replaces a file" in done.stderr
    assert taken.read_bytes() == b"a file the user keeps"
    done = backup_cli("--db", "postgresql://u:secret@localhost/fleet", str(tmp_path / "b.sqlite"))
    assert done.returncode == 2 and "pg_dump" in done.stderr and "secret" not in done.stderr
    other = tmp_path / "other.sqlite"
    with sqlite3.connect(other) as conn:
        conn.execute("CREATE TABLE t (x)")
    done = backup_cli("--db", str(other), str(tmp_path / "b.sqlite"))
    assert done.returncode == 2 and "not the service's database" in done.stderr and "Traceback" not in done.stderr
    assert not (tmp_path / "b.sqlite").exists() and not (tmp_path / "b.sqlite.partial").exists()


def test_a_backup_of_a_database_whose_path_holds_a_question_mark_or_a_hash(tmp_path):
    db = tmp_path / "fleet?v=2#site a%20.sqlite"  # each would end or change a file: URI written as is
    with Store.open(db) as store:
        store.insert_window(ws.window(seq=1))
    done = backup_cli("--db", str(db), str(tmp_path / "b.sqlite"), "--json", "/dev/stdout")
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["rows"]["windows"] == 1
    # no stray file opened instead ("fleet", empty: the database was refused as not the service's)
    assert {p.name for p in tmp_path.iterdir()} <= {"b.sqlite", db.name, db.name + "-wal", db.name + "-shm"}


def test_a_backup_onto_a_full_disk_says_so_in_one_line_and_leaves_no_file(tmp_path):
    import resource
    import signal

    db = tmp_path / "fleet.sqlite"
    with Store.open(db) as store:
        store.ingest_many(
            [(keys.key(DEVICE, keys.STATS), wire.encode("window", ws.window(seq=s))) for s in range(1, 200)]
        )
    size = db.stat().st_size

    def disk_of_half_the_size() -> None:  # a write past it fails as on a full disk (EFBIG), the process lives on
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (size // 2, size // 2))

    out = tmp_path / "b.sqlite"
    cmd = [sys.executable, "-m", "encoder_fleet.cli", "backup", "--db", str(db), str(out)]
    done = subprocess.run(cmd, capture_output=True, text=True, preexec_fn=disk_of_half_the_size)
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
    assert done.stderr.startswith("encoder-fleet backup: error: ") and len(done.stderr.splitlines()) == 1
    assert "no backup written" in done.stderr
    assert not out.exists() and not (tmp_path / "b.sqlite.partial").exists()


@pytest.mark.parametrize("name", ["fleet.sqlite-wal", "fleet.sqlite-shm", "fleet.sqlite-journal", "fleet"])
def test_a_backup_never_takes_the_name_of_one_of_the_databases_own_files(tmp_path, name):
    # with the service stopped its -wal and -shm are gone: a backup written as one was read as the database's WAL,
    # found no WAL, and deleted at the next start; `fleet` would remove fleet.partial, a database of that name
    db = tmp_path / ("fleet.partial" if name == "fleet" else "fleet.sqlite")
    with Store.open(db) as store:
        store.insert_window(ws.window(seq=1))
    assert not db.with_name(db.name + "-wal").exists()
    via_link = tmp_path / "link"
    via_link.symlink_to(tmp_path, target_is_directory=True)  # the same files, named another way
    done = backup_cli("--db", str(db), str(via_link / name))
    assert done.returncode == 2 and "one of the database's own files" in done.stderr, done.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([db.name, "link"])
    with Store.open(db) as store:
        assert seqs(store) == [1]


def test_ctrl_c_stops_a_backup_mid_copy_at_once_and_leaves_no_file(tmp_path):
    import signal

    db, out = tmp_path / "fleet.sqlite", tmp_path / "b.sqlite"
    Store.open(db).close()
    with sqlite3.connect(db) as conn:  # ~0.5 GB to copy, in rows of a window's size: seconds of VACUUM INTO
        conn.execute(
            "WITH RECURSIVE n(i) AS (SELECT 1 UNION ALL SELECT i + 1 FROM n WHERE i < 125000) INSERT INTO dead_letters "
            "(received_at, key_expr, reason, detail, payload) SELECT i, 'k', 'bad_json', '', zeroblob(4000) FROM n"
        )
    cmd = [sys.executable, "-m", "encoder_fleet.cli", "backup", "--db", str(db), str(out)]
    running = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    partial = tmp_path / "b.sqlite.partial"
    assert wait_for(lambda: partial.exists() and partial.stat().st_size > 0, timeout=60)  # the copy has begun
    assert (partial.stat().st_mode & 0o777) == 0o600  # from its first byte: not readable by all while written
    running.send_signal(signal.SIGINT)
    sent = time.monotonic()
    assert running.wait(timeout=60) == 130
    # SQLite ran the copy to its end before Python saw the signal: a large fleet's database for minutes
    assert time.monotonic() - sent < 1.0
    assert "Traceback" not in running.stderr.read()
    assert not out.exists() and not partial.exists()


def test_a_backup_named_like_a_uri_is_written_under_that_name(tmp_path):
    # the source's connection takes URIs: "file:b.sqlite.partial" named b.sqlite.partial to VACUUM INTO, a 0644 copy
    # of the fleet's history left there when the chmod of the name asked for failed
    Store.open(tmp_path / "fleet.sqlite").close()
    cmd = [sys.executable, "-m", "encoder_fleet.cli", "backup", "--db", "fleet.sqlite", "file:b.sqlite"]
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert ((tmp_path / "file:b.sqlite").stat().st_mode & 0o777) == 0o600
    assert not (tmp_path / "b.sqlite.partial").exists()


def test_a_backup_leaves_alone_a_partial_copy_it_did_not_make(tmp_path):
    # another backup to the same name still copying (a slow nightly run overlapped by the next): it was deleted, and
    # its cleanup then deleted the new one's, so both failed
    db, out = tmp_path / "fleet.sqlite", tmp_path / "b.sqlite"
    Store.open(db).close()
    running = tmp_path / "b.sqlite.partial"
    running.write_bytes(b"another backup's copy, half written")
    done = backup_cli("--db", str(db), str(out))
    assert done.returncode == 2 and "b.sqlite.partial exists: another backup" in done.stderr, done.stderr
    assert running.read_bytes() == b"another backup's copy, half written" and not out.exists()


def test_a_windows_page_whose_cursor_retention_deleted_says_so(tmp_path):
    from fastapi.testclient import TestClient

    from service.api import create_app

    with Store.open(tmp_path / "fleet.db", band_horizon_s=HORIZON_S) as store:
        for s in range(1, 21):
            store.insert_window(ws.window(seq=s, temp_c=23.0 if s < 20 else 43.0))
        api = TestClient(create_app(store))
        page = api.get(f"/devices/{DEVICE}/windows", params={"limit": 5}).json()
        assert page["next"] == 5
        assert store.prune_windows(DEVICE, ended_before=np.inf, below_seq=20, keep_version=None) > 5
        r = api.get(f"/devices/{DEVICE}/windows", params={"limit": 5, "after": page["next"]})
        assert r.status_code == 422 and "retention deleted the oldest windows" in r.json()["detail"][0]["msg"]
