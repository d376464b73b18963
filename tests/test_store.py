"""The history: migrations, dedupe, band sums, dead letters, threads. Real SQLite files and a real PostgreSQL
server (tests/conftest.py), no mocks: every test that takes `store` runs on both."""

import json
import sqlite3
import threading
import time

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from wire_samples import ack, coefficients, window

from fleet_wire import keys
from fleet_wire import messages as wire
from service import db
from service.store import Store, StoreError


def test_migrations_apply_once_and_are_recorded(tmp_path):
    from service.store import migration_files

    files = [f.name for _, f in migration_files()]
    expected = [(version, f.name) for version, f in migration_files()]
    path = tmp_path / "fleet.db"
    with Store.open(path) as s:
        assert s.migrations() == expected and expected[0] == (1, "001_initial.sql")
        s.insert_window(window())
    with Store.open(path) as s:  # reopening applies nothing twice and keeps the data
        assert s.migrations() == expected
        assert s.max_seq("drive-001") == 1
    conn = sqlite3.connect(path)
    assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    assert conn.execute("SELECT count(*) FROM schema_migrations").fetchone()[0] == len(files)


def test_new_migration_is_applied_in_order(tmp_path):
    from service.store import MIGRATIONS_DIR

    mig = tmp_path / "migrations"
    mig.mkdir()
    (mig / "001_initial.sql").write_text((MIGRATIONS_DIR / "001_initial.sql").read_text())
    with Store.open(tmp_path / "a.db", migrations_dir=mig):
        pass
    (mig / "002_notes.sql").write_text(
        "-- a later change; kept small\nCREATE TABLE notes (\n  id INTEGER\n);\nINSERT INTO notes VALUES (7);\n"
    )
    with Store.open(tmp_path / "a.db", migrations_dir=mig) as s:
        assert [v for v, _ in s.migrations()] == [1, 2]
    with Store.open(tmp_path / "a.db", migrations_dir=mig) as s:
        assert s._rows("SELECT count(*) AS n FROM notes")[0]["n"] == 1


def test_failed_migration_leaves_nothing_behind(tmp_path):
    from service.store import MIGRATIONS_DIR

    mig = tmp_path / "migrations"
    mig.mkdir()
    (mig / "001_initial.sql").write_text((MIGRATIONS_DIR / "001_initial.sql").read_text())
    (mig / "002_broken.sql").write_text("CREATE TABLE half (id INTEGER);\nINSERT INTO nowhere VALUES (1);\n")
    with pytest.raises(sqlite3.OperationalError, match="nowhere"):
        Store.open(tmp_path / "a.db", migrations_dir=mig)
    conn = sqlite3.connect(tmp_path / "a.db")
    assert [r[0] for r in conn.execute("SELECT version FROM schema_migrations")] == [1]
    assert conn.execute("SELECT count(*) FROM sqlite_master WHERE name = 'half'").fetchone()[0] == 0
    (mig / "002_broken.sql").write_text("CREATE TABLE half (\n  id INTEGER\n")
    with pytest.raises(ValueError, match="incomplete statement"):
        Store.open(tmp_path / "a.db", migrations_dir=mig)


def test_duplicate_window_is_dropped_and_changes_nothing(store):
    msg = window(seq=1)
    assert store.insert_window(msg, received_at=10.0) is True
    before = (store.devices(), store.band_stats("drive-001")[2][1:], store.windows("drive-001", stats=True))
    assert store.insert_window(json.loads(json.dumps(msg)), received_at=20.0) is False
    after = (store.devices(), store.band_stats("drive-001")[2][1:], store.windows("drive-001", stats=True))
    assert before == after
    assert store.windows("drive-001", stats=True) == [msg]


def test_reused_seq_with_other_content_is_a_conflict_not_a_duplicate(store):
    store.insert_window(window(seq=1))
    payload = wire.encode("window", window(seq=1, temp_c=30.0))
    assert store.ingest(keys.key("drive-001", keys.STATS), payload) == "seq_conflict"
    assert store.rejection_counts() == {"seq_conflict": 1}
    assert store.dead_letters()[0]["payload"] == payload
    assert len(store.windows("drive-001")) == 1


@pytest.mark.parametrize(
    ("where", "path"),
    [(("stats", "moments", 3), r"\$\.stats\.moments\[3\]"), (("stats", "bins", 5, 1), r"\$\.stats\.bins\[5\]\[1\]")],
)
def test_a_window_stored_directly_is_checked_as_the_wire_checks_it(store, where, path):
    """insert_window (the replays', the imports' and the tests' way in) refuses what the wire refuses: a NaN in the
    statistics' arrays passes their types, and stored it failed every later export of the device."""
    store.insert_window(window(seq=1))
    bad = window(seq=2)
    *parents, last = where
    target = bad
    for p in parents:
        target = target[p]
    target[last] = float("nan")
    with pytest.raises(wire.WireError, match=path) as err:
        store.insert_window(bad)
    assert err.value.reason == "non_finite"
    inconsistent = window(seq=3)
    inconsistent["samples"] += 1
    with pytest.raises(wire.WireError, match=r"\$\.samples"):
        store.insert_window(inconsistent)
    assert [w["seq"] for w in store.windows("drive-001")] == [1]
    assert store.band_stats("drive-001")[2][1] == 1


def test_a_seq_floor_steps_over_gone_windows(store):
    """Below the floor an agent names (`gone_below`: the lowest seq it holds, its full outbox having dropped the
    ones before), the windows the service lacks are gone and the contiguous watermark steps over them, also past
    the highest seq stored (the agent holds nothing below the floor, and one that numbers anew goes on from the
    mark, so no window is ever numbered where a loss on the way would count as gone)."""
    for seq in (1, 2, 3, 7, 8):
        store.insert_window(window(seq=seq))
    assert store.contiguous_seq("drive-001") == 3
    assert not store.mark_gone_below("drive-unseen", 7)  # no such device: nothing to raise
    assert store.mark_gone_below("drive-001", 7) and not store.mark_gone_below("drive-001", 5)  # only raised
    assert store.contiguous_seq("drive-001") == 8 and store.contiguous_seq("drive-001", start=3) == 8
    assert store.mark_gone_below("drive-001", 12)
    assert store.contiguous_seq("drive-001") == 11  # 9-11 gone, nothing stored past 8
    store.insert_window(window(seq=13))
    assert store.contiguous_seq("drive-001") == 11  # 12 is held by the agent: waited for
    store.insert_window(window(seq=12))
    assert store.contiguous_seq("drive-001") == 13


def test_band_stats_equal_the_sum_of_windows(store):
    msgs = [window(seq=s, temp_c=t) for s, t in enumerate([21.0, 24.0, 35.0, 27.5, 22.0], start=1)]
    for m in reversed(msgs):  # arrival order does not matter
        store.insert_window(m)
    bands = store.band_stats("drive-001")
    assert sorted(bands) == [2, 3]
    merged, n_windows, n_samples = bands[2]
    in_band = [m for m in msgs if m["band"] == 2]
    assert n_windows == 4 and n_samples == sum(m["samples"] for m in in_band) == merged.n
    np.testing.assert_allclose(merged.moments, np.sum([m["stats"]["moments"] for m in in_band], axis=0), rtol=1e-12)
    np.testing.assert_allclose(merged.bins, np.sum([m["stats"]["bins"] for m in in_band], axis=0), rtol=1e-12)
    assert merged.temp_n == sum(m["stats"]["temp_n"] for m in in_band)
    assert merged.temp_min == min(m["temp_min_c"] for m in in_band)
    assert merged.temp_max == max(m["temp_max_c"] for m in in_band)


def test_band_sums_keep_when_in_the_band_each_angle_was_seen(tmp_path):
    """Σ window temperature × bin count per band (the refit's per-bin temperatures) survives a restart."""
    msgs = [window(seq=s, temp_c=t) for s, t in enumerate([21.0, 24.0, 27.5, 22.0], start=1)]
    expected = sum(m["stats"]["temp_sum"] / m["stats"]["temp_n"] * np.array(m["stats"]["bins"])[:, 0] for m in msgs)
    with Store.open(tmp_path / "fleet.db") as s:
        for m in msgs:
            s.insert_window(m)
        np.testing.assert_allclose(s.band_stats("drive-001")[2][0].bin_temps(), expected, rtol=1e-12)
    with Store.open(tmp_path / "fleet.db") as s:  # read back from band_stats.bin_temp, not re-derived
        merged = s.band_stats("drive-001")[2][0]
        assert merged.bin_temp is not None
        np.testing.assert_allclose(merged.bin_temps(), expected, rtol=1e-12)


def test_window_with_other_normalisation_is_dead_lettered_atomically(store):
    store.insert_window(window(seq=1))
    other = window(seq=2)
    other["stats"]["scale"] = 1000.0
    assert store.ingest(keys.key("drive-001", keys.STATS), wire.encode("window", other)) == "normalisation_mismatch"
    assert store.max_seq("drive-001") == 1  # the window insert was rolled back with the merge
    assert store.band_stats("drive-001")[2][1] == 1


def test_ingest_keeps_every_bad_input(store):
    good = wire.encode_json("window", window(seq=1))  # JSON windows of older agents are still accepted
    outcomes = [
        store.ingest(keys.key("drive-001", keys.STATS), good),
        store.ingest(keys.key("drive-001", keys.STATS), good),
        store.ingest(keys.key("drive-002", keys.STATS), good),
        store.ingest(keys.key("drive-001", keys.STATS), b"\x00garbage"),
        store.ingest(keys.key("drive-001", keys.STATS), good.replace(b'"seq":1', b'"seq":-4')),
        store.ingest(keys.key("drive-001", keys.ACK), wire.encode("ack", ack())),
        store.ingest("encoders/drive-001/coefficients", wire.encode("coefficients", coefficients())),
        store.ingest(keys.key("drive-001", keys.STATS), b" " * (wire.MAX_PAYLOAD + 1)),
        store.ingest("sensors/x", b"{}"),
    ]
    assert outcomes == [
        "stored",
        "duplicate",
        "device_mismatch",
        "not_json",
        "schema",
        "stored",
        "unexpected_kind",
        "too_large",
        "bad_key",
    ]
    assert store.rejection_counts() == {
        "bad_key": 1,
        "device_mismatch": 1,
        "not_json": 1,
        "schema": 1,
        "too_large": 1,
        "unexpected_kind": 1,
    }
    letters = store.dead_letters(limit=100)
    assert [d["reason"] for d in letters][:2] == ["bad_key", "too_large"]  # newest first
    garbage = next(d for d in letters if d["reason"] == "not_json")
    assert garbage["payload"] == b"\x00garbage" and garbage["key_expr"] == keys.key("drive-001", keys.STATS)
    assert "$.seq" in next(d for d in letters if d["reason"] == "schema")["detail"]


def test_a_message_python_cannot_read_is_dead_lettered_alone_and_its_batch_stored(store):
    """A JSON integer of 5000 digits made Python's parser raise a plain ValueError: the whole batch rolled back,
    its good windows with it, and nothing was dead-lettered. Now each such message is refused alone, with why."""
    good = [(keys.key("drive-001", keys.STATS), wire.encode("window", window(seq=seq))) for seq in range(1, 4)]
    huge = b"9" * 5000
    bad = [
        (
            keys.key("drive-001", keys.STATS),
            wire.encode_json("window", window(seq=9)).replace(b'"seq":9', b'"seq":' + huge),
        ),
        (keys.key("drive-001", keys.ACK), wire.encode("ack", ack()).replace(b'"version":1', b'"version":' + huge)),
        (
            keys.key("drive-001", keys.STATS),
            wire.encode("window", window(seq=8)).replace(b"\xa9drive-001", b"\xa9\xffrive-001"),
        ),
    ]
    outcomes = store.ingest_many([good[0], bad[0], good[1], bad[1], bad[2], good[2]])
    assert outcomes == ["stored", "not_json", "stored", "not_json", "not_json", "stored"]
    assert store.max_seq("drive-001") == 3 and store.band_stats("drive-001")[2][1] == 3
    letters = sorted(store.dead_letters(limit=10), key=lambda d: d["payload"])
    assert [d["payload"] for d in letters] == sorted(payload for _, payload in bad)
    assert ["5000 digits" in d["detail"] for d in letters] == [True, True, False]  # window and ack; not MessagePack
    assert "not MessagePack" in letters[2]["detail"]


def test_coefficients_fits_acks_and_devices(store):
    assert store.next_version("drive-001") == 1 and store.current_coefficients("drive-001") is None
    store.insert_window(window(seq=1, version=0), received_at=5.0)
    store.record_fit("drive-001", 2, {"w": [1, 0, 1, 0]}, {"samples": 10}, created_at=50.0)
    fit_id = store.record_fit(
        "drive-001", 2, {"w": [1.1, 0, 1, 0]}, {"samples": 20, "residual_rms_rad": 0.01}, created_at=60.0
    )
    store.record_fit("drive-001", 3, {"w": [1, 0, 1, 0]}, {"samples": 5}, created_at=60.0)
    assert [(f["band"], f["samples"]) for f in store.latest_fits("drive-001")] == [(2, 20), (3, 5)]
    assert store.latest_fits("drive-001")[0]["id"] == fit_id

    c1, c2 = coefficients(version=1, created_at=100.0), coefficients(version=2, created_at=200.0, bands=(2, 3))
    store.insert_coefficient_set(c1)
    store.insert_coefficient_set(c2)
    with pytest.raises(StoreError, match="already exists"):
        store.insert_coefficient_set(c1)
    assert store.next_version("drive-001") == 3
    assert store.current_coefficients("drive-001") == c2
    assert store.current_coefficients("drive-001", published_only=True) is None
    store.mark_published("drive-001", 1, at=101.0)
    assert store.current_coefficients("drive-001", published_only=True) == c1
    with pytest.raises(KeyError):
        store.mark_published("drive-001", 9)
    assert [(h["version"], h["published_at"]) for h in store.coefficient_history("drive-001")] == [
        (2, None),
        (1, 101.0),
    ]

    a1, a2 = ack(version=1, at=150.0), ack(version=2, at=250.0, status="rejected")
    store.insert_ack(a1, received_at=151.0)
    store.insert_ack(a2, received_at=251.0)
    assert store.acks("drive-001") == [a1, a2]
    assert store.device("drive-001")["current_version"] == 1
    store.insert_ack(ack(version=2, at=260.0), received_at=261.0)  # retried and applied
    assert store.device("drive-001")["current_version"] == 2
    store.insert_ack(ack(version=1, at=120.0), received_at=262.0)  # late and older: changes no version
    assert store.acks("drive-001")[0] == ack(version=1, at=120.0) and len(store.acks("drive-001")) == 4
    store.set_online("drive-001", True, at=300.0)
    dev = store.device("drive-001")
    assert dev["online"] is True and dev["current_version"] == 2 and dev["windows"] == 1
    assert dev["first_seen"] == 5.0 and dev["last_seen"] == 300.0
    assert store.device("nope") is None and [d["id"] for d in store.devices()] == ["drive-001"]
    with pytest.raises(ValueError, match="does not match"):
        store.set_online("encoders/*", True)


def test_windows_time_range_and_catch_up_order(store):
    for seq in (3, 1, 2, 5, 4):
        store.insert_window(window(seq=seq, version={1: 0, 2: 0, 3: 1, 4: 1, 5: 2}[seq]))
        if seq == 2:
            assert store.device("drive-001")["current_version"] == 1  # from seq 3, not the late seqs 1 and 2
    assert [w["seq"] for w in store.windows("drive-001", 60.0, 180.0)] == [2, 3, 4]
    assert "stats" not in store.windows("drive-001")[0]
    assert [w["seq"] for w in store.iter_windows("drive-001", page=2)] == [1, 2, 3, 4, 5]
    assert store.max_seq("drive-001") == 5
    assert store.device("drive-001")["current_version"] == 2  # from seq 5, not the late seq 4
    summary = store.window_summary("drive-001", recent=2)
    assert summary["windows"] == 5 and [w["seq"] for w in summary["recent"]] == [5, 4]


def test_threads_share_one_store(store):
    errors = []

    def agent(device):
        try:
            for seq in range(1, 9):
                payload = wire.encode("window", window(device, seq))
                assert store.ingest(wire.key_for("window", device), payload) == "stored"
                store.ingest(wire.key_for("window", device), payload)  # redelivery
                store.devices()
                store.band_stats(device)
        except Exception as exc:  # surfaced below: an assert in a thread would be lost
            errors.append(exc)

    threads = [threading.Thread(target=agent, args=(f"drive-{i:03d}",)) for i in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == []
    assert [(d["id"], d["windows"]) for d in store.devices()] == [(f"drive-{i:03d}", 8) for i in range(6)]
    assert all(store.band_stats(f"drive-{i:03d}")[2][1] == 8 for i in range(6))


def test_huge_refused_payloads_keep_a_bounded_head_with_size_and_hash(store, tmp_path):
    import hashlib

    from service.store import DEAD_LETTER_KEEP

    huge = b"{" + b"x" * (10 * 1024 * 1024)
    for _ in range(5):
        assert store.ingest(keys.key("drive-001", keys.STATS), huge) == "too_large"
    letters = store.dead_letters(10)
    assert len(letters) == 5
    for letter in letters:
        assert len(letter["payload"]) == DEAD_LETTER_KEEP and letter["payload"] == huge[:DEAD_LETTER_KEEP]
        assert letter["payload_bytes"] == len(huge)
        assert letter["payload_sha256"] == hashlib.sha256(huge).hexdigest()
    if store.path.startswith("postgresql://"):
        size = store._rows("SELECT pg_total_relation_size('dead_letters') AS n")[0]["n"]
    else:
        store.close()
        size = (tmp_path / "fleet.db").stat().st_size
    assert size < 2 * 1024 * 1024  # not 50 MB


def test_a_corrupt_database_is_refused_at_start(tmp_path):
    from service.store import StoreError

    path = tmp_path / "c.db"
    with Store.open(path) as s:
        for seq in range(1, 200):
            s.insert_window(window(seq=seq))
        s._rows("PRAGMA wal_checkpoint(TRUNCATE)")
    data = bytearray(path.read_bytes())
    page = 4096
    data[5 * page : 5 * page + 64] = b"\xff" * 64  # a b-tree page header in the middle of the file
    path.write_bytes(bytes(data))
    with pytest.raises(StoreError, match="corrupt") as err:
        Store.open(path, check_integrity=True)
    assert err.value.reason == "unavailable" and str(path) in str(err.value)


def _checkpointed(store: Store, after: int) -> None:
    """Wait (at most 15 s) until the store's checkpointer has copied the whole WAL once more than `after` times."""
    deadline = time.monotonic() + 15.0
    while store._checkpointer.checkpoints <= after:
        assert time.monotonic() < deadline, "no checkpoint in 15 s"
        time.sleep(0.05)


def test_the_wal_is_copied_into_the_file_off_the_writers_commits(tmp_path):
    """The writer's COMMIT only appends to the WAL (SQLite's own checkpoint inside it was over half of a COMMIT's
    time on a slow disk); the store's checkpointer thread copies the WAL into the file, so the file alone holds
    what was committed and the WAL stays one round of writes long however much is stored."""
    path = tmp_path / "fleet.db"
    rounds = [[window(seq=seq) for seq in range(1 + 40 * r, 41 + 40 * r)] for r in range(5)]
    with Store.open(path) as store:
        assert store._conn.execute("PRAGMA wal_autocheckpoint").fetchone()[0] == 0
        wal_sizes = []
        for msgs in rounds:
            done = store._checkpointer.checkpoints
            store.ingest_many([(keys.key("drive-001", keys.STATS), wire.encode("window", m)) for m in msgs])
            _checkpointed(store, done)
            wal_sizes.append((tmp_path / "fleet.db-wal").stat().st_size)
        alone = tmp_path / "copy.db"
        alone.write_bytes(path.read_bytes())  # the file without its WAL
        assert sqlite3.connect(alone).execute("SELECT count(*) FROM windows").fetchone()[0] == 200
    assert max(wal_sizes) < 2 * wal_sizes[0]  # restarted after each copy, not grown by every round
    assert sqlite3.connect(path).execute("SELECT count(*) FROM windows").fetchone()[0] == 200


def test_a_checkpoint_the_disk_refuses_is_counted_and_loses_nothing(tmp_path):
    """The disk is full for the database file (RLIMIT_FSIZE at its size): the checkpointer cannot copy the WAL in,
    counts each refused pass and keeps trying; the WAL keeps every commit, and once space is back the copy goes
    through and the file alone holds every window."""
    import resource
    import signal

    path = tmp_path / "fleet.db"
    items = [(keys.key("drive-001", keys.STATS), wire.encode("window", window(seq=seq))) for seq in range(1, 81)]
    with Store.open(path) as store:
        store.ingest_many(items[:5])
        _checkpointed(store, store._checkpointer.checkpoints)
        old_limit = resource.getrlimit(resource.RLIMIT_FSIZE)
        old_handler = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails, not the process
        try:
            store.ingest_many(items[5:])  # into the WAL: the file does not grow until a checkpoint
            resource.setrlimit(resource.RLIMIT_FSIZE, (path.stat().st_size, old_limit[1]))
            deadline = time.monotonic() + 15.0
            while store.checkpoint_failures == 0:
                assert time.monotonic() < deadline, "no refused checkpoint counted in 15 s"
                time.sleep(0.05)
        finally:
            resource.setrlimit(resource.RLIMIT_FSIZE, old_limit)
            signal.signal(signal.SIGXFSZ, old_handler)
        assert store.max_seq("drive-001") == 80  # every commit is still read, from the WAL
        _checkpointed(store, store._checkpointer.checkpoints)
        alone = tmp_path / "copy.db"
        alone.write_bytes(path.read_bytes())
        assert sqlite3.connect(alone).execute("SELECT count(*) FROM windows").fetchone()[0] == 80


def test_a_commit_failed_by_a_full_disk_leaves_the_batch_out_of_the_band_sums(tmp_path):
    """In WAL mode a full disk fails the COMMIT, after the batch was summed in memory. The agents resend the
    batch: each window must be summed once (the sums kept the failed batch: 75 windows summed for 39 stored)."""
    import resource
    import signal

    msgs = [window(seq=seq) for seq in range(1, 40)]
    items = [(keys.key("drive-001", keys.STATS), wire.encode("window", m)) for m in msgs]
    samples = sum(m["samples"] for m in msgs)
    with Store.open(tmp_path / "fleet.db") as store:
        assert store.ingest_many(items[:3]) == ["stored"] * 3
        # the files may grow by one page: the batch's statements fit in the page cache, its WAL append does not
        limit = max(p.stat().st_size for p in tmp_path.glob("fleet.db*")) + 4096
        old_limit = resource.getrlimit(resource.RLIMIT_FSIZE)
        old_handler = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails, not the process
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, old_limit[1]))
        try:
            with pytest.raises(sqlite3.OperationalError):
                store.ingest_many(items[3:])
        finally:
            resource.setrlimit(resource.RLIMIT_FSIZE, old_limit)
            signal.signal(signal.SIGXFSZ, old_handler)
        assert store.max_seq("drive-001") == 3  # nothing of the batch was stored
        assert store.ingest_many(items[3:]) == ["stored"] * 36  # the resend
        assert store.band_stats("drive-001")[2][1:] == (39, samples)
    with Store.open(tmp_path / "fleet.db") as store:  # the sum written is right too
        assert store.band_stats("drive-001")[2][1:] == (39, samples)


def test_a_transaction_the_database_ended_takes_no_more_writes_and_commits_nothing(tmp_path):
    """SQLite ends a transaction itself on some errors inside it (a full disk, an I/O error; here its ROLLBACK
    stands in for one). A savepoint opened after that would begin a transaction of its own and commit apart from
    the rest: the store refuses it, and the outer commit says plainly that nothing of the transaction is stored."""
    with Store.open(tmp_path / "fleet.db") as store:
        with pytest.raises(StoreError, match="ended the transaction") as ended:
            with store.transaction():
                store.insert_coefficient_set(coefficients("drive-001", 1))
                store._conn.execute("ROLLBACK")  # what SQLite does on SQLITE_FULL inside a statement
                assert not store.transaction_open
                with pytest.raises(StoreError, match="ended the transaction"):
                    with store.transaction():  # the next write of the run
                        store.insert_coefficient_set(coefficients("drive-002", 1))
        assert ended.value.reason == "unavailable"
        assert store.newest_set("drive-001") is None and store.newest_set("drive-002") is None
        with store.transaction():  # the next transaction is a new one, and commits
            store.insert_coefficient_set(coefficients("drive-002", 1))
        assert store.newest_set("drive-002")["version"] == 1


def test_restarting_band_memory_keeps_only_windows_after_the_step(store):
    from encoder_core.stats import WindowStats

    msgs = [window(seq=seq, temp_c=23.0 if seq % 2 else 33.0) for seq in range(1, 11)]
    for msg in msgs:
        store.insert_window(msg)
    step_at = msgs[5]["window_end"]  # windows 1-6 end at or before it
    assert sorted(store.restart_band_memory("drive-001", after=step_at)) == [2, 3]
    for band, (total, windows, samples) in store.band_stats("drive-001").items():
        after = [m for m in msgs if m["band"] == band and m["window_end"] > step_at]
        expected = WindowStats.from_dict(after[0]["stats"])
        for m in after[1:]:
            expected = expected.merge(WindowStats.from_dict(m["stats"]))
        assert windows == len(after) and samples == sum(m["samples"] for m in after)
        assert np.allclose(total.moments, expected.moments)
    assert store.max_seq("drive-001") == 10  # every window is still stored
    store.insert_window(window(seq=11, temp_c=23.0))  # and new ones add to the restarted sums
    assert (
        store.band_stats("drive-001")[2][1]
        == len([m for m in msgs if m["band"] == 2 and m["window_end"] > step_at]) + 1
    )
    assert store.restart_band_memory("drive-001", after=1e12) == [2, 3] and store.band_stats("drive-001") == {}


@pytest.mark.parametrize("backend", ["sqlite", "postgres"])
def test_a_band_sum_with_a_horizon_forgets_each_window_once_when_an_ack_shares_the_batch(backend, tmp_path, request):
    """An ack writes the windows staged before it; a later window of the same band that pushes them past the
    horizon must take each out of the sum once (it was taken out twice: sums went negative, bands unfittable)."""
    from encoder_core.stats import WindowStats

    target = tmp_path / "fleet.db" if backend == "sqlite" else request.getfixturevalue("postgres_url")
    horizon_s = 150.0  # 60 s windows: a band keeps its newest two or three
    msgs = [window(seq=seq, temp_c=23.0) for seq in range(1, 9)]
    items = [(keys.key("drive-001", keys.STATS), wire.encode("window", m)) for m in msgs]
    items.insert(3, (keys.key("drive-001", keys.ACK), wire.encode("ack", ack(at=170.0))))
    with Store.open(target, band_horizon_s=horizon_s) as store:
        assert store.ingest_many(items) == ["stored"] * len(items)
        total, windows, samples = store.band_stats("drive-001")[2]
    mine = [m for m in msgs if m["window_end"] >= msgs[-1]["window_end"] - horizon_s]
    expected = WindowStats.from_dict(mine[0]["stats"])
    for m in mine[1:]:
        expected = expected.merge(WindowStats.from_dict(m["stats"]))
    assert windows == len(mine) and samples == sum(m["samples"] for m in mine) == total.n
    np.testing.assert_allclose(total.moments, expected.moments, rtol=1e-9)


def test_a_band_restarted_to_nothing_starts_again_from_its_new_windows(tmp_path):
    """After a step forgets every window of a band, its new sum must not take the forgotten ones out again when
    they fall past the horizon (it did: the sum went negative, and the knocked drive was never refitted)."""
    from encoder_core.stats import WindowStats

    horizon_s = 150.0
    msgs = [window(seq=seq, temp_c=23.0) for seq in range(1, 13)]
    with Store.open(tmp_path / "fleet.db", band_horizon_s=horizon_s) as store:
        for m in msgs[:6]:
            store.insert_window(m)
        assert store.restart_band_memory("drive-001", after=msgs[5]["window_end"]) == [2]
        assert store.band_stats("drive-001") == {}
        for m in msgs[6:]:
            store.insert_window(m)
        total, windows, samples = store.band_stats("drive-001")[2]
    mine = [m for m in msgs[6:] if m["window_end"] >= msgs[-1]["window_end"] - horizon_s]
    expected = WindowStats.from_dict(mine[0]["stats"])
    for m in mine[1:]:
        expected = expected.merge(WindowStats.from_dict(m["stats"]))
    assert windows == len(mine) and samples == sum(m["samples"] for m in mine) == total.n
    np.testing.assert_allclose(total.moments, expected.moments, rtol=1e-9)


@pytest.mark.parametrize("horizon_s", [None, 150.0])
def test_a_catch_up_window_from_before_a_step_is_stored_but_not_summed(tmp_path, horizon_s):
    """The drive was offline: windows 3 and 4 wait in its outbox while 1, 2, 5, 6 arrive live, and a step at 6's
    end forgets the band. The late 3 and 4 ended before the step: they started a new sum of pre-step windows
    (one that a horizon never took out again: its first seq was above theirs)."""
    from encoder_core.stats import WindowStats

    msgs = {seq: window(seq=seq, temp_c=23.0) for seq in range(1, 13)}
    with Store.open(tmp_path / "fleet.db", band_horizon_s=horizon_s) as store:
        for seq in (1, 2, 5, 6):
            store.insert_window(msgs[seq])
        assert store.restart_band_memory("drive-001", after=msgs[6]["window_end"]) == [2]
        items = [(keys.key("drive-001", keys.STATS), wire.encode("window", msgs[seq])) for seq in (3, 4)]
        assert store.ingest_many(items) == ["stored", "stored"]
        assert store.band_stats("drive-001") == {} and store.window_summary("drive-001")["windows"] == 6
        for seq in range(7, 13):
            store.insert_window(msgs[seq])
        total, windows, samples = store.band_stats("drive-001")[2]
    newest = msgs[12]["window_end"]
    mine = [msgs[seq] for seq in range(7, 13) if horizon_s is None or msgs[seq]["window_end"] >= newest - horizon_s]
    expected = WindowStats.from_dict(mine[0]["stats"])
    for m in mine[1:]:
        expected = expected.merge(WindowStats.from_dict(m["stats"]))
    assert windows == len(mine) and samples == sum(m["samples"] for m in mine) == total.n
    np.testing.assert_allclose(total.moments, expected.moments, rtol=1e-9)


STEP = st.one_of(
    st.tuples(st.just("windows"), st.lists(st.sampled_from([23.0, 27.0, 33.0]), min_size=1, max_size=6), st.booleans()),
    st.tuples(st.just("restart"), st.integers(0, 3), st.just(False)),
)


@settings(max_examples=40, deadline=None, suppress_health_check=list(HealthCheck))
@given(
    program=st.lists(STEP, min_size=1, max_size=8),
    horizon_windows=st.integers(1, 5),
    write_every_s=st.sampled_from([0.0, 1e9]),
)
def test_band_sums_equal_their_definition_under_any_interleaving(
    tmp_path_factory, program, horizon_windows, write_every_s
):
    """Batches of windows (an ack inside some), restarts after a step, a drive-time horizon, in any order: each
    band's sum is always exactly the windows of that band that ended after the last restart and within the
    horizon of the band's newest (the two bugs above each broke this; sums went negative). The same holds for a
    second process that opens the file while the first never wrote its sums again (written behind: every batch,
    or never after a band's first; a crash), which must rebuild what is behind from the windows."""
    import service.store
    from encoder_core.stats import WindowStats

    horizon_s, restart_after, sent, acks = 60.0 * horizon_windows + 30.0, -1.0, [], 0
    path = tmp_path_factory.mktemp("sums") / "fleet.db"
    kept, service.store.BANDS_WRITE_EVERY_S = service.store.BANDS_WRITE_EVERY_S, write_every_s
    try:
        store = Store.open(path, band_horizon_s=horizon_s)
        for kind, arg, with_ack in program:
            if kind == "restart":
                if sent:  # forget what ended at or before a window already stored (the step's time)
                    restart_after = max(restart_after, sent[max(0, len(sent) - 1 - arg)]["window_end"])
                    store.restart_band_memory("drive-001", after=restart_after)
                continue
            batch = [window(seq=len(sent) + i + 1, temp_c=t) for i, t in enumerate(arg)]
            items = [(keys.key("drive-001", keys.STATS), wire.encode("window", m)) for m in batch]
            if with_ack:
                acks += 1
                items.insert(len(items) // 2, (keys.key("drive-001", keys.ACK), wire.encode("ack", ack(version=acks))))
            assert store.ingest_many(items) == ["stored"] * len(items)
            sent += batch
        sums = store.band_stats("drive-001")
        with Store.open(path, band_horizon_s=horizon_s) as after_a_crash:  # the first one still open, not flushed
            rebuilt = after_a_crash.band_stats("drive-001")
        store.close()
    finally:
        service.store.BANDS_WRITE_EVERY_S = kept
    expected = {}
    for band in {m["band"] for m in sent}:
        in_band = [m for m in sent if m["band"] == band]
        mine = [m for m in in_band if m["window_end"] > restart_after]
        mine = [m for m in mine if m["window_end"] >= in_band[-1]["window_end"] - horizon_s]
        if mine:
            expected[band] = mine
    for held in (sums, rebuilt):
        assert sorted(held) == sorted(expected)
        for band, mine in expected.items():
            total, windows, samples = held[band]
            reference = WindowStats.from_dict(mine[0]["stats"])
            for m in mine[1:]:
                reference = reference.merge(WindowStats.from_dict(m["stats"]))
            assert windows == len(mine) and samples == sum(m["samples"] for m in mine) == total.n
            np.testing.assert_allclose(total.moments, reference.moments, rtol=1e-9, atol=1e-9)
            np.testing.assert_allclose(total.bins, reference.bins, rtol=1e-9, atol=1e-9)
            np.testing.assert_allclose(total.bin_temps(), reference.bin_temps(), rtol=1e-9, atol=1e-9)


def test_windows_lost_with_a_session_and_sent_again_after_their_band_was_rebuilt_are_summed(tmp_path):
    """A batch lost with a dropped session (or a crash) can hold a band's first windows; the drive goes on, its
    next windows in that band are stored, and the lost ones come again later, resent. A sum rebuilt in between
    (written behind, so behind its windows) started at the first window stored, and the resent ones, below it,
    were kept but never summed: the cluster test's drive counted 177 of its 180 windows."""
    import service.store

    path = tmp_path / "fleet.db"
    kept, service.store.BANDS_WRITE_EVERY_S = service.store.BANDS_WRITE_EVERY_S, 1e9  # sums written behind
    try:
        store = Store.open(path)
        sent = [window(seq=s, temp_c=23.0) for s in (1, 2, 3)] + [window(seq=s, temp_c=33.0) for s in (7, 8, 9)]
        for m in sent:  # seqs 4-6, the band's first three, are lost
            assert store.insert_window(m)
        with Store.open(path) as after_a_crash:  # the first never wrote band 33's sum again
            late = [window(seq=s, temp_c=33.0) for s in (4, 5, 6)]
            for m in late:
                assert after_a_crash.insert_window(m)
            counts = {band: n for band, (_, n, _) in after_a_crash.band_stats("drive-001").items()}
        store.close()
    finally:
        service.store.BANDS_WRITE_EVERY_S = kept
    bands = sorted({m["band"] for m in sent + late})
    assert counts == {bands[0]: 3, bands[1]: 6}


def test_a_batch_with_an_ack_and_a_late_window_keeps_the_newest_windows_version(store):
    """A device's current version is the newest window's or a later applied ack's, in arrival order; a late window
    (a catch-up, its seq under the highest stored) in the same batch or a later one does not roll it back."""

    def item(msg: dict, kind: str = "window") -> tuple[str, bytes]:
        return keys.key(msg["device"], keys.STATS if kind == "window" else keys.ACK), wire.encode(kind, msg)

    batch = [item(window(seq=2, version=0)), item(ack(version=1, at=125.0), "ack"), item(window(seq=3, version=1))]
    assert store.ingest_many([*batch, item(window(seq=1, version=0))]) == ["stored"] * 4
    assert store.device("drive-001")["current_version"] == 1
    assert store.ingest_many([item(window(seq=6, version=3))]) == ["stored"]
    assert store.ingest_many([item(window(seq=5, version=2)), item(window(seq=4, version=2))]) == ["stored"] * 2
    assert store.device("drive-001")["current_version"] == 3


@pytest.mark.parametrize("backend", ["sqlite", "postgres"])
def test_band_sums_the_database_holds_in_step_with_their_windows_are_read_as_stored(backend, tmp_path, request, caplog):
    """Reopened, a band sum that counts all its windows is read as it was written, on either database. On PostgreSQL
    every sum was rebuilt from all its band's windows whenever it was read (each start, each partition taken, each
    rolled-back batch): its rows unpacked into their column names (`(count,) = row` gave 'count'), never a count."""
    target = tmp_path / "fleet.db" if backend == "sqlite" else request.getfixturevalue("postgres_url")
    with Store.open(target) as s:
        s.ingest_many([(keys.key("drive-001", keys.STATS), wire.encode("window", window(seq=i))) for i in (1, 2, 3)])
    with Store.open(target) as s, caplog.at_level("INFO", logger="service.store"):
        assert s.band_stats("drive-001")[2][1] == 3
        assert s._dirty == set() and "rebuilt" not in caplog.text
        row = s._conn.execute("SELECT count(*) AS n, 7 AS m FROM windows").fetchone()
        assert tuple(row) == (3, 7) and dict(row) == {"n": 3, "m": 7} and row["n"] == row[0] == 3


def test_a_nul_character_in_a_message_or_a_query_fails_nothing_else(store):
    """PostgreSQL's text holds no NUL (SQLite's does): an ack whose reason held one (the wire allows it) failed its
    whole batch, so another drive's window beside it was not stored, each time the agent sent the ack again; a
    look-up with one (a REST path or query) raised instead of finding nothing."""
    refused = ack(status="rejected")
    refused["reason"] = "gain\x00out of range"
    items = [
        (keys.key("drive-001", keys.ACK), wire.encode("ack", refused)),
        (keys.key("drive-002", keys.STATS), wire.encode("window", window("drive-002", seq=1))),
    ]
    assert store.ingest_many(items) == ["stored", "stored"]
    assert store.max_seq("drive-002") == 1
    (reason,) = [r["reason"] for r in store.refusals("drive-001")]
    assert reason in ("gain\x00out of range", "gain\ufffdout of range")  # SQLite keeps the NUL, PostgreSQL cannot
    assert store.device("drive\x00002") is None and store.alarms(cause="\x00") == []


def test_a_transaction_a_failed_statement_ended_does_not_commit_as_if_stored(store):
    """A statement that fails inside a transaction, its error caught outside a savepoint: SQLite undoes that statement
    alone and commits the rest; PostgreSQL aborts the transaction, and its COMMIT rolled everything back without an
    error, so the caller went on as if it were stored. Now it is said, as when SQLite ends a transaction itself."""
    postgres = store.path.startswith("postgresql://")
    try:
        with store.transaction():
            store.dead_letter("fleet/drive-001/x", "schema", "kept?", b"{}")
            with pytest.raises(db.database_errors()):
                store._conn.execute("SELECT * FROM nowhere")
    except StoreError as exc:
        assert postgres and exc.reason == "unavailable"
    else:
        assert not postgres
    assert len(store.dead_letters()) == (0 if postgres else 1)
    store.dead_letter("fleet/drive-001/x", "schema", "after", b"{}")  # the connection is usable again
    assert [d["detail"] for d in store.dead_letters()][0] == "after"


def test_silent_devices_are_online_and_unheard_past_three_of_their_windows(store):
    """One query for SQLite and PostgreSQL: online, nothing stored for silent_s, and past three of the newest
    window's length when that is longer (an hour-long window is not silence between windows)."""
    now = time.time()
    store.set_online("drive-quiet", True, at=now - 3600)
    store.set_online("drive-slow", True, at=now - 3600)
    store.insert_window({**window("drive-slow", seq=1), "window_end": 3600.0}, received_at=now - 3000)
    store.set_online("drive-gone", True, at=now - 7200)
    store.set_online("drive-gone", False, at=now - 7100)
    assert store.silent_devices(1800.0, now=now) == ["drive-quiet"]
    assert store.silent_devices(1800.0, now=now + 9000) == ["drive-quiet", "drive-slow"]  # three hours on
    assert store.silent_devices(1800.0, now=now + 9000, limit=1) == ["drive-quiet"]


def test_a_devices_window_count_is_kept_with_its_row_through_batches_duplicates_and_refusals(store):
    """GET /devices counted every device's windows at each read (1.3 billion index entries for 10,000 drives keeping
    90 days): the count is kept with the device's row, added to by each batch, a redelivery or a refusal adding
    nothing."""
    msgs = [window("drive-001", seq) for seq in range(1, 6)] + [window("drive-002", 1)]
    items = [(keys.key(m["device"], keys.STATS), wire.encode("window", m)) for m in msgs]
    assert store.ingest_many(items[:3]) == ["stored"] * 3
    assert store.ingest_many(items[2:]) == ["duplicate", "stored", "stored", "stored"]
    conflict = wire.encode("window", window("drive-001", 5, temp_c=40.0))
    assert store.ingest_many([(items[0][0], conflict)]) == ["seq_conflict"]
    assert {d["id"]: d["windows"] for d in store.devices()} == {"drive-001": 5, "drive-002": 1}
    assert store.device("drive-001")["windows"] == 5


def test_an_older_databases_window_counts_are_counted_once_by_the_migration(tmp_path):
    db_path = tmp_path / "old.sqlite"
    with Store.open(db_path) as store:
        for seq in range(1, 4):
            store.insert_window(window("drive-001", seq))
    conn = sqlite3.connect(db_path)  # as a database from before migration 105 is: no count kept
    conn.execute("ALTER TABLE devices DROP COLUMN windows")
    conn.execute("DELETE FROM schema_migrations WHERE version = 105")
    conn.commit()
    conn.close()
    with Store.open(db_path) as store:
        assert store.device("drive-001")["windows"] == 3
        store.insert_window(window("drive-001", 4))
        assert store.device("drive-001")["windows"] == 4


def test_each_migration_an_older_database_takes_is_said_while_it_runs(tmp_path, caplog):
    """Store.open said nothing while it migrated an older database, and the service prints nothing before its store
    is open (its logs are warnings and worse by default): a migration that counts or rewrites a large table (105
    counts every window: 1-2 s for 2 million here, minutes for a fleet's billion) was a start that seemed to hang.
    Each one an older database takes is said before it runs and once done; a new database's first tables are not."""
    db_path = tmp_path / "old.sqlite"
    with caplog.at_level("WARNING", logger="service.store"), Store.open(db_path) as store:
        store.insert_window(window("drive-001", 1))
    assert "migration" not in caplog.text
    conn = sqlite3.connect(db_path)  # as a database from before migration 105 is
    conn.execute("ALTER TABLE devices DROP COLUMN windows")
    conn.execute("DELETE FROM schema_migrations WHERE version = 105")
    conn.commit()
    conn.close()
    with caplog.at_level("WARNING", logger="service.store"), Store.open(db_path):
        said = [r.getMessage() for r in caplog.records]
    assert len(said) == 2 and all("105_device_window_count.sql" in line for line in said), said
    assert said[0].startswith("applying migration 105") and " applied in " in said[1]


def test_a_large_databases_start_up_check_is_said_while_it_runs(tmp_path, caplog, monkeypatch):
    """The service checks its SQLite file at start-up (quick_check reads every page: ~3 min for 8.5 GB) and printed
    nothing meanwhile, a start that seemed to hang; past QUICK_CHECK_SAID_MB it says so, before and once done."""
    import service.store as store_module

    db_path = tmp_path / "fleet.sqlite"
    with Store.open(db_path) as store:
        store.insert_window(window("drive-001", 1))
    with caplog.at_level("WARNING", logger="service.store"), Store.open(db_path, check_integrity=True):
        pass
    assert "checking the database" not in caplog.text  # a small file: nothing to say
    monkeypatch.setattr(store_module, "QUICK_CHECK_SAID_MB", 0.0)
    with caplog.at_level("WARNING", logger="service.store"), Store.open(db_path, check_integrity=True):
        said = [r.getMessage() for r in caplog.records]
    assert said[0].startswith("checking the database before start") and str(db_path) in said[0], said
    assert said[1].startswith("database checked in "), said
