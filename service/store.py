"""The service's history in one SQLite file: every window, fit, coefficient set, ack and bad input.

One writing connection guarded by a lock: Zenoh callbacks, FastAPI's worker threads and the refit
loop all call in, and SQLite serialises writers anyway. Reads from threads outside the transaction
take a connection of a small read pool (service/db.py) and see the last commit without waiting for
the batch being written; WAL mode lets them, and outside readers (sqlite3 CLI, backups), read while
we write. The same holds on PostgreSQL (psycopg_pool). Methods take and return wire-shaped dicts (fleet_wire.messages):
messages handed in must come from wire.decode or a wire builder, which have checked them.

Clocks: devices' first_seen/last_seen, received_at and published_at are the service's clock
(unix s); window times, created_at of fits and sets and an ack's `at` are the drive's clock, as
on the wire (see migrations/001_initial.sql).
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import re
import sqlite3
import threading
import time
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from importlib import resources
from importlib.resources.abc import Traversable
from pathlib import Path

import msgspec
import numpy as np

from encoder_core.samples import InputError
from encoder_core.stats import WindowStats
from fleet_wire import keys
from fleet_wire import messages as wire

from . import db

# numbered SQL files: migrations/ in the repository, shipped as package data (service.migrations)
log = logging.getLogger("service.store")
MIGRATIONS_DIR = resources.files("service.migrations")
MIGRATION_NAME = re.compile(r"^(\d+)_[\w.-]*\.sql$")

_READ = re.compile(r"^\s*(SELECT|WITH)\b", re.I)  # what the read pool may run (a PRAGMA goes to the writer)
PARTITION_LOCKS = 0x454E43  # the advisory lock class of partitions ('ENC'); the partition is the object id
DEAD_LETTER_KEEP = 64 * 1024  # bytes of a refused payload kept for audit (a whole window message fits)
DEAD_LETTER_DETAIL = 1000  # characters of its reason text
# changed band sums are written with the batch that is storing windows once this much time has passed since they
# were last written (a new band's sum at once): upserting every changed sum with every batch rewrote ~4 KB per
# window beside its own row. A sum the database holds behind its windows (a crash between writes) is rebuilt from
# them when it is read (Store._device_bands), so a crash still loses nothing.
BANDS_WRITE_EVERY_S = 2.0

# rows deleted in one transaction by retention (Store.prune_windows, prune_dead_letters): the writer waits for one
# such at most (~10 ms of SQLite), never for a whole fleet's pruning
PRUNE_BATCH = 1000

# how often the writer reads which devices are retired (a retirement by another cluster member is seen within it;
# this process's own at once)
RETIRED_READ_EVERY_S = 5.0
RETIRED_LETTER_EVERY_S = 3600.0  # a retired device's messages kept as dead letters: one per device in this (service s)

TRANSACTION_ENDED = (
    "the database ended the transaction after an error inside it (a full disk, an I/O error, a lost connection): "
    "nothing of it is stored"
)

# wire fields of a window stored as columns of the same name, in wire order
WINDOW_FIELDS = (
    "device",
    "seq",
    "window_start",
    "window_end",
    "samples",
    "rejected",
    "temp_mean_c",
    "temp_min_c",
    "temp_max_c",
    "temp_rate_c_per_s",
    "band",
    "coefficients_version",
    "angle_quality_deg",
)


class NothingWritten(Exception):
    """Raised inside a transaction by a check that refuses it before it wrote anything the band sums hold (a
    rollout already running, a device a rollout holds): rolled back without dropping the sums kept in memory. Any
    other error drops them (they may hold what the rollback took back), and the ingest rebuilds them from their
    windows: a refused POST /rollouts did that to the whole fleet (a second reader)."""


class StoreError(InputError):
    """A well-formed message the history cannot take (e.g. a seq reused with other content), or a database
    that cannot be used at all (reason 'unavailable')."""

    def __init__(self, reason: str, message: str):
        super().__init__(message)
        self.reason = reason

    def __reduce__(self):  # pickled with both arguments: a worker process's error reaches its pool intact
        return type(self), (self.reason, str(self))


def _json(value) -> str:
    return json.dumps(value, separators=(",", ":"), allow_nan=False)


def _pack(stats: WindowStats) -> bytes:
    return wire.pack_stats(wire.packed_stats(stats))


def _pack_bin_temp(stats: WindowStats) -> bytes:
    return np.ascontiguousarray(stats.bin_temps(), "<f8").tobytes()


def _band_sum(row: sqlite3.Row) -> WindowStats:
    """A stored band sum with its per-bin temperatures (migration 055; older sums fall back to the mean)."""
    stats = Store._stats_of(row).window_stats()
    if row["bin_temp"] is not None:
        stats.bin_temp = np.frombuffer(row["bin_temp"], "<f8").copy()
    return stats


@dataclass
class _Batch:
    """What one ingest transaction has staged and not yet written."""

    now: float
    rows: list = field(default_factory=list)  # window rows for executemany
    staged: dict = field(default_factory=dict)  # (device, seq) -> (window_start, window_end, stats blob)
    by_band: dict = field(default_factory=dict)  # (device, band) -> [(seq, samples, WindowStats, window_end)]
    newest: dict = field(default_factory=dict)  # device -> (seq, coefficients_version) of its newest staged window
    new_bands: set = field(default_factory=set)  # (device, band) whose sum starts in this batch: written with it


# a database past this size is said to be checked at start-up: the check reads every page (8.5 GB: ~3 min cold), and
# the service prints nothing before its store is open (its logs are warnings and worse by default)
QUICK_CHECK_SAID_MB = 1024.0


def _quick_check(conn: sqlite3.Connection, path: str) -> list[str]:
    """PRAGMA quick_check's first problems (["ok"]: none), said before and after when the file is large."""
    mb = os.path.getsize(path) / 2**20 if os.path.exists(path) else 0.0
    if mb < QUICK_CHECK_SAID_MB:
        return [r[0] for r in conn.execute("PRAGMA quick_check(3)")]
    log.warning("checking the database before start (%s, %.1f GB): it reads every page", path, mb / 1024)
    began = time.monotonic()
    problems = [r[0] for r in conn.execute("PRAGMA quick_check(3)")]
    log.warning("database checked in %.0f s", time.monotonic() - began)
    return problems


def migration_files(migrations_dir=MIGRATIONS_DIR) -> list[tuple[int, Traversable]]:
    """(version, file) of every numbered SQL file, in order; StoreError when there is none (a broken
    install must stop at start-up, not run on a database without tables)."""
    found = []
    for entry in migrations_dir.iterdir():
        match = MIGRATION_NAME.match(entry.name)
        if match and entry.is_file():
            found.append((int(match.group(1)), entry))
    if not found:
        raise StoreError("unavailable", f"no migration file (NNN_name.sql) found in {migrations_dir}")
    return sorted(found, key=lambda vf: vf[0])


def unapplied_migrations(path, migrations_dir=MIGRATIONS_DIR) -> list[str]:
    """The migration files a SQLite database of the service has not had applied, read without changing the file
    (an export is no reason to rewrite the evidence); StoreError when the file is not the service's database."""
    try:
        conn = sqlite3.connect(f"{Path(path).resolve().as_uri()}?mode=ro", uri=True)
        try:
            applied = {r[0] for r in conn.execute("SELECT version FROM schema_migrations")}
        finally:
            conn.close()
    except sqlite3.Error as exc:
        raise StoreError("unavailable", f"database {path} is not the service's ({exc})") from None
    return [f.name for version, f in migration_files(migrations_dir) if version not in applied]


def _statements(sql: str) -> Iterator[str]:
    """Split a migration into statements (one statement may span lines; a line holds at most one end)."""
    buf = ""
    for line in sql.splitlines(keepends=True):
        buf += line
        if sqlite3.complete_statement(buf):
            yield buf
            buf = ""
    leftover = [line for line in buf.splitlines() if line.strip() and not line.strip().startswith("--")]
    if leftover:
        raise ValueError(f"migration ends in an incomplete statement: {leftover[0].strip()[:80]!r}")


class Store:
    def __init__(self, conn: sqlite3.Connection, path: str, band_horizon_s: float | None = None):
        self._conn = conn
        self._lock = threading.RLock()
        self._depth = 0  # open transactions: 0 none, 1 a transaction, more are savepoints inside it
        self._writing: int | None = None  # the thread inside the transaction
        # reads from threads not inside the transaction go to a pool and never wait behind a batch being written
        self._read_pool = None
        self._checkpointer = None  # SQLite: db.SqliteCheckpointer, the WAL copied off the writer's COMMITs
        self.path = path
        # a band's sum covers the windows that ended within this much drive time (s) of the band's newest,
        # so refits follow a drive as it ages; None keeps all history in the sum (every window is stored)
        self.band_horizon_s = band_horizon_s
        # device -> band -> [WindowStats, windows, samples, first_seq]: band_stats, kept in memory once read and
        # written behind (BANDS_WRITE_EVERY_S) with a batch of windows; dropped whenever a transaction rolls back
        self._bands: dict[str, dict[int, list]] = {}
        self._dirty: set[tuple[str, int]] = set()  # (device, band) whose kept sum the database does not hold yet
        self._bands_written_at = time.monotonic()
        self._max_seq: dict[str, int] = {}  # device -> highest seq stored or staged (read with its bands)
        self._max_end: dict[str, float] = {}  # device -> that window's end on the drive clock
        # device -> it had no stored window when its bands were read: a band of it that has no sum has no window
        # either, so a new band's sum starts at seq 1 without asking (a fleet's first windows, after a start)
        self._unwritten: dict[str, bool] = {}
        self._retired: frozenset[str] = frozenset()  # devices retired (device_retirements), as read at _retired_read_at
        self._retired_read_at = -math.inf  # monotonic, when that read began
        self._retired_changed_at = -math.inf  # monotonic, this process's last retirement or reinstatement committed
        self._retired_letter_at: dict[str, float] = {}  # device -> when its last message was kept as a dead letter

    @classmethod
    def open(
        cls,
        path,
        *,
        migrations_dir=MIGRATIONS_DIR,
        band_horizon_s: float | None = None,
        check_integrity: bool = False,
        max_mb: float | None = None,
    ) -> Store:
        """Open (or create) the database and apply the migrations it lacks. A database that cannot be
        opened raises StoreError('unavailable') with one line that says which file and why; with
        check_integrity (the service at start-up) a corrupt file is refused before anything runs on it."""
        migrations = migration_files(migrations_dir)
        if db.is_postgres(path):
            try:
                conn = db.PgConnection(path)
            except ModuleNotFoundError as exc:  # the postgres extra not installed (an image built with [service] alone)
                raise StoreError(
                    "unavailable",
                    f"database {db.redacted(path)}: PostgreSQL needs {exc.name}: pip install 'encoder-fleet[postgres]'",
                ) from None
            except db.database_errors() as exc:
                raise StoreError("unavailable", f"database {db.redacted(path)} cannot be opened: {exc}") from None
            store = cls._migrated(conn, db.redacted(path), band_horizon_s, migrations)
            try:
                store._read_pool = db.PgReadPool(path)
            except db.database_errors() as exc:
                store.close()
                raise StoreError("unavailable", f"database {db.redacted(path)} cannot be opened: {exc}") from None
            return store
        path = db.sqlite_path(path)
        try:
            # isolation_level=None: we issue BEGIN/COMMIT ourselves, so a transaction is exactly what we say
            conn = sqlite3.connect(str(path), isolation_level=None, check_same_thread=False, timeout=30.0)
            conn.row_factory = sqlite3.Row
            conn.execute("PRAGMA journal_mode=WAL")
            conn.execute("PRAGMA wal_autocheckpoint=0")  # db.SqliteCheckpointer's thread does it instead
            conn.execute("PRAGMA foreign_keys=ON")
            if max_mb is not None:  # a quota: past it writes fail as on a full disk (SQLITE_FULL)
                page = conn.execute("PRAGMA page_size").fetchone()[0]
                conn.execute(f"PRAGMA max_page_count = {max(1, int(max_mb * 2**20 / page))}")
            problems = _quick_check(conn, path) if check_integrity else ["ok"]
        except sqlite3.Error as exc:
            raise StoreError("unavailable", f"database {path} cannot be opened: {exc}") from None
        if problems != ["ok"]:
            conn.close()
            raise StoreError(
                "unavailable", f"database {path} is corrupt ({' '.join(' '.join(problems).split())}); restore a backup"
            )
        store = cls._migrated(conn, str(path), band_horizon_s, migrations)
        store._read_pool = db.SqliteReadPool(str(path))
        store._checkpointer = db.SqliteCheckpointer(str(path))
        return store

    @classmethod
    def _migrated(cls, conn, path: str, band_horizon_s: float | None, migrations) -> Store:
        """The store on an open connection (either database), with the migrations it lacks applied."""
        store = cls(conn, path, band_horizon_s)
        try:
            store._migrate(migrations)
        except BaseException:
            conn.close()
            raise
        return store

    def close(self) -> None:
        if self._checkpointer is not None:
            self._checkpointer.close()
        if self._read_pool is not None:
            self._read_pool.close()
        with self._lock:
            try:
                if self._dirty:
                    with self._tx() as c:
                        self._write_bands(c, set(self._dirty))
            except Exception:  # a disk that refuses: the sums are rebuilt from the windows at the next start
                log.exception("writing the band sums at close failed; they are rebuilt from the windows when read")
            self._conn.close()

    @property
    def checkpoint_failures(self) -> int:
        """Passes of the SQLite file's checkpointer the disk refused (0 on PostgreSQL): while they fail, the WAL
        keeps every commit and grows."""
        return 0 if self._checkpointer is None else self._checkpointer.failures

    def __enter__(self) -> Store:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # --- plumbing ---------------------------------------------------------------------------

    @contextmanager
    def _tx(self) -> Iterator[sqlite3.Connection]:
        """One write transaction; BEGIN IMMEDIATE takes the write lock up front, so no upgrade deadlock.
        Inside another, a savepoint: a failing inner step rolls back alone and the batch goes on."""
        with self._lock:
            depth = self._depth
            if depth and not self._conn.in_transaction:
                # SQLite ended the transaction on an error inside it: a savepoint now would begin a transaction of its
                # own and commit apart from the rest, so nothing more joins it (the caller's commit then fails too)
                raise StoreError("unavailable", TRANSACTION_ENDED)
            self._conn.execute(f"SAVEPOINT sp{depth}" if depth else "BEGIN IMMEDIATE")
            self._depth += 1
            self._writing = threading.get_ident()
            try:
                yield self._conn
            except BaseException as exc:
                if not depth and not isinstance(exc, NothingWritten):
                    self._forget_sums()  # they may hold what the rollback took back: read them again
                # SQLite ends the transaction itself on some errors (a full disk, an I/O error): then there is
                # nothing to roll back, and trying would hide the real error behind "no transaction is active"
                if self._conn.in_transaction:
                    self._conn.execute(f"ROLLBACK TO sp{depth}" if depth else "ROLLBACK")
                    if depth:
                        self._conn.execute(f"RELEASE sp{depth}")
                raise
            finally:
                self._depth -= 1
                if not self._depth:
                    self._writing = None
            try:
                # said plainly, not as "cannot commit - no transaction is active"; on PostgreSQL a transaction a failed
                # statement aborted (its error caught, outside a savepoint) is still open, and its COMMIT rolls it back
                # without an error: every write of it lost while the caller goes on as if stored
                if not self._conn.in_transaction or getattr(self._conn, "aborted", False):
                    raise StoreError("unavailable", TRANSACTION_ENDED)
                self._conn.execute(f"RELEASE sp{depth}" if depth else "COMMIT")
            except BaseException:
                # a COMMIT can fail too (in WAL mode a full disk usually fails here): nothing of the batch was
                # stored, so the sums must not hold it either, or the agents' resend is summed twice
                if not depth:
                    self._forget_sums()
                    if self._conn.in_transaction:
                        self._conn.execute("ROLLBACK")
                raise

    def _forget_sums(self) -> None:
        """Drop the band sums and seqs kept in memory: read again from the database when next needed."""
        self._max_seq.clear()
        self._max_end.clear()
        self._unwritten.clear()
        self._bands.clear()
        self._dirty.clear()  # what the database holds is repaired when read again (_device_bands)

    def _rows(self, sql: str, args=()) -> list[sqlite3.Row]:
        if self._read_pool is not None and self._writing != threading.get_ident() and _READ.match(sql):
            return self._read_pool.rows(sql, args)  # committed data, on a connection of its own
        with self._lock:
            return self._conn.execute(sql, args).fetchall()

    def _migrate(self, migrations: list[tuple[int, Traversable]]) -> None:
        with self._lock, db.migrating(self._conn):
            try:
                self._conn.execute(
                    "CREATE TABLE IF NOT EXISTS schema_migrations "
                    "(version INTEGER PRIMARY KEY, name TEXT NOT NULL, applied_at REAL NOT NULL)"
                )
            except db.database_errors() as exc:  # not a database, corrupt, read-only when new, ...
                raise StoreError("unavailable", f"database {self.path} cannot be used: {exc}") from None
            # an older database's migrations are said: one may count or rewrite a large table (105 counts every
            # window, minutes for a fleet's billion), and nothing else is printed before the store is open
            older = self._conn.execute("SELECT 1 FROM schema_migrations LIMIT 1").fetchone() is not None
            for version, path in migrations:
                # check inside the write transaction: another process may be migrating the same file
                with self._tx() as c:
                    if c.execute("SELECT 1 FROM schema_migrations WHERE version = ?", (version,)).fetchone():
                        continue
                    if older:
                        log.warning("applying migration %s to database %s (a large one: minutes)", path.name, self.path)
                    began = time.monotonic()
                    for statement in _statements(path.read_text(encoding="utf-8")):
                        c.execute(statement)
                    c.execute("INSERT INTO schema_migrations VALUES (?, ?, ?)", (version, path.name, time.time()))
                if older:
                    log.warning("migration %s applied in %.1f s", path.name, time.monotonic() - began)

    def migrations(self) -> list[tuple[int, str]]:
        return [
            (r["version"], r["name"])
            for r in self._rows("SELECT version, name FROM schema_migrations ORDER BY version")
        ]

    @staticmethod
    def _touch(c: sqlite3.Connection, device: str, now: float, *, heard: bool = True) -> None:
        """Make sure the device row exists; heard=True when the device itself spoke (moves last_seen)."""
        c.execute(
            "INSERT INTO devices (id, first_seen, last_seen) VALUES (?, ?, ?) ON CONFLICT(id) DO "
            + ("UPDATE SET last_seen = max(devices.last_seen, excluded.last_seen)" if heard else "NOTHING"),
            (device, now, now),
        )

    # --- partitions (service/cluster.py) ---------------------------------------------------------
    #
    # A partition's windows are written by one process at a time: it holds the partition's PostgreSQL advisory
    # lock (on this connection, so the lock goes when the process does). A SQLite file has one process.

    def claim_partition(self, part: int) -> bool:
        if not isinstance(self._conn, db.PgConnection):
            return True
        with self._lock:
            row = self._conn.execute("SELECT pg_try_advisory_lock(?, ?) AS taken", (PARTITION_LOCKS, part)).fetchone()
            return bool(row["taken"])

    def serialise_transaction(self, lock: int, wait_s: float = 2.0) -> bool:
        """Inside a transaction: take a PostgreSQL advisory lock held to the transaction's end, so that a check and
        the write it decides are one step across service processes; False when another process's transaction has
        held it for wait_s (the wait holds this process's writer: a member stuck inside its transaction must not
        stall this one's ingest for good). SQLite's BEGIN IMMEDIATE serialises every writer already."""
        if not isinstance(self._conn, db.PgConnection):
            return True
        deadline = time.monotonic() + wait_s
        while True:
            row = self._conn.execute("SELECT pg_try_advisory_xact_lock(?) AS taken", (lock,)).fetchone()
            if row["taken"]:
                return True
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.02)

    def release_partition(self, part: int) -> None:
        if isinstance(self._conn, db.PgConnection) and not self._conn.lost:  # a lost session took its locks along
            with self._lock:
                self._conn.execute("SELECT pg_advisory_unlock(?, ?)", (PARTITION_LOCKS, part))

    def reconnect_if_lost(self) -> bool:
        """PostgreSQL: open the writer's connection again if the server dropped it; True when it did. What the
        old session held (the partitions' advisory locks) is gone: the caller takes its partitions again."""
        if not isinstance(self._conn, db.PgConnection):
            return False
        with self._lock:
            if self._depth or not self._conn.lost:
                return False
            try:
                self._conn.reconnect()
            except db.database_errors():
                return False  # the server is not back yet: the next call tries again
            self._forget_sums()
            return True

    def forget_partitions(self, parts: set[int]) -> None:
        """Drop the sums and seqs kept in memory for some partitions' devices: read again when next needed."""
        with self._lock:
            for cache in (self._bands, self._max_seq, self._max_end, self._unwritten):
                for device in [d for d in cache if keys.partition(d) in parts]:
                    del cache[device]
            # not written now: the partition may already be another process's; it rebuilds what is behind
            self._dirty = {(d, b) for d, b in self._dirty if keys.partition(d) not in parts}

    # --- ingest -----------------------------------------------------------------------------
    #
    # Windows are checked, deduplicated and added to their band's sum in memory, then written in bulk
    # (executemany) when the batch ends, in the batch's one transaction. The changed band sums (one UPSERT
    # each) go with it when BANDS_WRITE_EVERY_S has passed since they were last written, a new band's at once;
    # a sum the database holds behind its windows is rebuilt from them when read. A bad message is refused
    # before anything of it is written, so it alone is dead-lettered and the batch goes on.

    def ingest(self, key_expr: str, payload: bytes, *, received_at: float | None = None) -> str:
        """A Zenoh sample in, whatever it is: 'stored', 'duplicate', or the reason it went to dead letters."""
        return self.ingest_many([(key_expr, payload)], received_at=received_at)[0]

    @contextmanager
    def transaction(self) -> Iterator[Store]:
        """Several writes as one transaction (one disk sync); any failure undoes them all."""
        with self._tx():
            yield self

    @property
    def transaction_open(self) -> bool:
        """False once the database has ended the transaction under way on an error inside it (see _tx)."""
        return self._conn.in_transaction

    def ingest_many(self, items: list[tuple[str, bytes]], *, received_at: float | None = None) -> list[str]:
        """Several Zenoh samples in one transaction (one disk sync): the statuses of ingest(), in order."""
        now = time.time() if received_at is None else received_at
        with self._tx():
            batch = _Batch(now)
            out = [self._ingest_one(batch, key, payload, now) for key, payload in items]
            self._flush(batch, bands=True)
            return out

    def _ingest_one(self, batch: _Batch, key_expr: str, payload: bytes, now: float) -> str:
        try:
            device, kind = wire.parse_key(key_expr)
            if device in self._retired_devices():
                return self._refuse_retired(device, key_expr, payload, now)
            if kind == "window":
                win = wire.decode_window(payload, key_device=device)
                return "stored" if self._stage_window(batch, win) else "duplicate"
            if kind != "ack":
                raise wire.WireError("unexpected_kind", f"the service does not accept {kind} messages on {key_expr}")
            msg = wire.decode(kind, payload, key_device=device)
            self._flush(batch)  # an ack and the windows before it update current_version in arrival order
            return "duplicate" if self.insert_ack(msg, received_at=now) is None else "stored"
        except (wire.WireError, StoreError) as exc:
            self.dead_letter(key_expr, exc.reason, str(exc), payload, received_at=now)
            return exc.reason

    def _refuse_retired(self, device: str, key_expr: str, payload: bytes, now: float) -> str:
        """A retired device's message, not stored: the first one in RETIRED_LETTER_EVERY_S kept as a dead letter, the
        rest only counted (its agent, still running, resends its whole outbox every few seconds, and keeps it)."""
        last = self._retired_letter_at.get(device)
        if last is None or now - last >= RETIRED_LETTER_EVERY_S or now < last:
            self._retired_letter_at[device] = now
            detail = (
                f"{device} is retired: nothing it sends is stored until it is reinstated (POST "
                f"/devices/{device}/reinstate), and its agent keeps it; one message in {RETIRED_LETTER_EVERY_S:.0f} s "
                "is kept here, the others counted"
            )
            self.dead_letter(key_expr, "device_retired", detail, payload, received_at=now)
        return "device_retired"

    def insert_window(self, msg: dict, *, received_at: float | None = None) -> bool:
        """Store a window and add it to its band's sum in one transaction. False (nothing changed) for a duplicate."""
        win = wire.window_from_dict(msg)
        with self._tx():
            batch = _Batch(time.time() if received_at is None else received_at)
            stored = self._stage_window(batch, win)
            self._flush(batch, bands=True)
        return stored

    def _device_bands(self, device: str) -> dict[int, list]:
        """band -> [WindowStats, windows, samples, first_seq]: the device's band sums, read once, then kept."""
        bands = self._bands.get(device)
        if bands is None:
            bands = self._bands[device] = {}
            for r in self._conn.execute(
                "SELECT band, stats, stats_json, bin_temp, windows, samples, first_seq FROM band_stats "
                "WHERE device = ?",
                (device,),
            ).fetchall():
                bands[r["band"]] = self._current_sum(device, r)
            newest = self._conn.execute(
                "SELECT seq, window_end FROM windows WHERE device = ? ORDER BY seq DESC LIMIT 1", (device,)
            ).fetchone()
            self._max_seq[device] = 0 if newest is None else newest["seq"]
            self._max_end[device] = -math.inf if newest is None else newest["window_end"]
            self._unwritten[device] = newest is None
        return bands

    def _current_sum(self, device: str, r: sqlite3.Row) -> list:
        """A stored band sum as kept in memory, rebuilt from the band's windows when it is behind them (written
        behind, and the process stopped before it was written again). Every window a sum holds has a seq from its
        first_seq on, and every window summed after it was written adds one to that count, so a count that differs
        means windows are missing from it; rebuilt, it holds the band's windows from first_seq on that ended within
        the horizon of the band's newest, as it would have."""
        band, first_seq = r["band"], r["first_seq"]
        (count,) = self._conn.execute(
            "SELECT count(*) FROM windows WHERE device = ? AND band = ? AND seq >= ?", (device, band, first_seq)
        ).fetchone()
        if count == r["windows"] or count == 0:  # none: nothing to rebuild it from (kept as it was written)
            return [_band_sum(r), r["windows"], r["samples"], first_seq]
        rows = self._conn.execute(
            "SELECT seq, band, samples, window_end, stats, stats_json FROM windows WHERE device = ? AND band = ? "
            "AND seq >= ? ORDER BY seq",
            (device, band, first_seq),
        ).fetchall()
        if self.band_horizon_s:
            cutoff = rows[-1]["window_end"] - self.band_horizon_s
            past = [w["seq"] for w in rows if w["window_end"] < cutoff]
            rows = [w for w in rows if w["window_end"] >= cutoff]
            if past:  # as _forget_before leaves it
                first_seq = max(past) + 1
        total = self._sum_by_band(rows)[band]
        log.info(  # after a crash, or a partition another process served and released without writing its sums
            "band sum behind its windows rebuilt",
            extra={"device": device, "band": band, "windows_before": r["windows"], "windows": len(rows)},
        )
        self._dirty.add((device, band))
        # from the sum's first_seq, not the first window stored: a lost batch's windows below it, sent again, are
        # summed when they come (from the first stored, the cluster test's drive counted 177 of 180)
        return [total, len(rows), sum(w["samples"] for w in rows), first_seq]

    @staticmethod
    def _stats_of(r: sqlite3.Row) -> wire.PackedStats:
        if r["stats"] is not None:
            return wire.unpack_stats(r["stats"])
        return msgspec.convert(json.loads(r["stats_json"]), wire.ArrayStats).packed()  # before migration 040

    @staticmethod
    def _window_stats_or_none(r: sqlite3.Row) -> WindowStats | None:
        """A stored window's statistics as the monitor computes with them (no dict in between: that round trip
        was ~7 % of the monitor's time); None for one that cannot be read, so it alone is passed over."""
        try:
            return Store._stats_of(r).window_stats()
        except (InputError, msgspec.DecodeError, KeyError, TypeError, ValueError):
            return None

    @staticmethod
    def _stats_dict(r: sqlite3.Row) -> dict:
        return wire.unpack_stats(r["stats"]).to_dict() if r["stats"] is not None else json.loads(r["stats_json"])

    def _stage_window(self, batch: _Batch, win: wire.Window) -> bool:
        """Check a window against what is stored and staged, add it to its band's sum; written by _flush.
        False for a duplicate; StoreError (nothing changed) for a conflict or a sum it cannot join."""
        device, seq, band = win.device, win.seq, win.band
        blob = wire.pack_stats(win.stats)
        bands = self._device_bands(device)
        old = batch.staged.get((device, seq))
        if old is None and seq <= self._max_seq[device]:  # above every stored seq it cannot be a repeat
            r = self._conn.execute(
                "SELECT window_start, window_end, stats, stats_json FROM windows WHERE device = ? AND seq = ?",
                (device, seq),
            ).fetchone()
            if r is not None:
                old = (r["window_start"], r["window_end"], wire.pack_stats(self._stats_of(r)))
        if old is not None:
            if old == (win.window_start, win.window_end, blob):
                return False  # redelivery: same window again
            raise StoreError(
                "seq_conflict",
                f"window {device}#{seq} is already stored with different content (agent restarted its sequence?)",
            )
        if old is None and seq > self._max_seq[device] and win.window_start < self._max_end[device]:
            # a later window that starts before the newest one ended: the drive's clock went back (a restart
            # that reset it), and storing it would hold one stretch of drive time twice
            raise StoreError(
                "clock_backwards",
                f"window {device}#{seq} starts at {win.window_start:.3f} s, before window "
                f"#{self._max_seq[device]} ended at {self._max_end[device]:.3f} s (the drive clock went back)",
            )
        stats = win.stats.window_stats()
        entry = bands.get(band)
        pending = batch.by_band.setdefault((device, band), [])
        first_seq = entry[3] if entry is not None else self._first_seq_of_new_band(device, band)
        if seq < first_seq:  # past the band's horizon, or forgotten by a restart (a late catch-up): kept, not summed
            entry = None
        elif entry is None:  # a band's sum starts here; its stored windows, if any, were forgotten by a restart
            entry = [stats, 1, win.samples, first_seq]
            batch.new_bands.add((device, band))
        else:
            try:
                total = entry[0].merge(stats)
            except InputError as exc:
                raise StoreError("normalisation_mismatch", f"window {device}#{seq}, band {band}: {exc}") from None
            entry = [total, entry[1] + 1, entry[2] + win.samples, entry[3]]
            if self.band_horizon_s:
                cutoff = win.window_end - self.band_horizon_s
                entry = self._forget_before(device, band, entry, pending, cutoff)
        # nothing can fail from here on: the window is staged and its band's sum replaced
        batch.staged[(device, seq)] = (win.window_start, win.window_end, blob)
        batch.rows.append(
            [getattr(win, f) for f in WINDOW_FIELDS]
            + [
                blob,
                batch.now,
                None if win.rejected_by_reason is msgspec.UNSET else _json(msgspec.to_builtins(win.rejected_by_reason)),
            ]
        )
        pending.append((seq, win.samples, stats, win.window_end))
        if seq > self._max_seq[device]:
            self._max_seq[device], self._max_end[device] = seq, win.window_end
        if seq > batch.newest.get(device, (0, 0))[0]:
            batch.newest[device] = (seq, win.coefficients_version)
        if entry is not None:
            bands[band] = entry
            self._dirty.add((device, band))
        return True

    def _first_seq_of_new_band(self, device: str, band: int) -> int:
        """The first seq a band's new sum may hold: none of those stored before it started (a restart after a step
        forgot them and deleted the sum), nor a catch-up window with a lower seq, which ended before them."""
        if self._unwritten.get(device):
            return 1
        row = self._conn.execute(
            "SELECT max(seq) AS seq FROM windows WHERE device = ? AND band = ?", (device, band)
        ).fetchone()
        return 1 if row is None or row["seq"] is None else row["seq"] + 1

    def restart_band_memory(self, device: str, after: float) -> list[int]:
        """Forget, in every band's sum, the windows that ended at or before `after` (drive clock): after an
        offset step the refit must learn the drive as it is now, not average it with what it was. Every
        window stays stored. Returns the bands whose sums changed."""
        changed = []
        with self._tx() as c:
            self._write_bands(c, {(d, b) for d, b in self._dirty if d == device})  # its first_seqs, as kept
            for row in c.execute("SELECT band, first_seq FROM band_stats WHERE device = ?", (device,)).fetchall():
                band = row["band"]
                kept = c.execute(
                    "SELECT seq, band, samples, stats, stats_json FROM windows WHERE device = ? AND band = ? "
                    "AND seq >= ? AND window_end > ? ORDER BY seq",
                    (device, band, row["first_seq"], after),
                ).fetchall()
                changed.append(band)
                if not kept:
                    c.execute("DELETE FROM band_stats WHERE device = ? AND band = ?", (device, band))
                    continue
                total = self._sum_by_band(kept)[band]
                c.execute(
                    "UPDATE band_stats SET stats_json = '', stats = ?, bin_temp = ?, windows = ?, samples = ?, "
                    "first_seq = ?, updated_at = ? WHERE device = ? AND band = ?",
                    (
                        _pack(total),
                        _pack_bin_temp(total),
                        len(kept),
                        sum(r["samples"] for r in kept),
                        kept[0]["seq"],
                        time.time(),
                        device,
                        band,
                    ),
                )
            self._bands.pop(device, None)  # the kept sums are read again, from what was just written
            self._dirty = {(d, b) for d, b in self._dirty if d != device}
            self._unwritten.pop(device, None)
        return changed

    def _forget_before(self, device, band, entry, pending, cutoff: float):
        """Subtract from the band's sum the windows (stored or staged) that ended before `cutoff` (drive clock):
        memory is drive time, so a band follows the drive however many windows it gets."""
        total, windows, samples, first_seq = entry
        rows = self._conn.execute(
            "SELECT seq, samples, stats, stats_json FROM windows WHERE device = ? AND band = ? AND seq >= ? "
            "AND window_end < ? ORDER BY seq",
            (device, band, first_seq, cutoff),
        ).fetchall()
        old = [(r["seq"], r["samples"], self._stats_of(r).window_stats()) for r in rows]
        stored = {r["seq"] for r in rows}  # an ack in the batch writes the windows staged before it: count each once
        old += [p[:3] for p in pending if p[0] >= first_seq and p[3] < cutoff and p[0] not in stored]
        if not old:
            return entry
        for _, _, stats in old:
            total = total.subtract(stats)
        return [total, windows - len(old), samples - sum(o[1] for o in old), max(o[0] for o in old) + 1]

    def _flush(self, batch: _Batch, *, bands: bool = False) -> None:
        """Write what is staged: devices, windows (executemany), current versions; with bands, the changed sums."""
        c = self._conn
        if batch.rows:
            # the newest window tells which coefficients the agent corrects with; late catch-up windows do not
            # (their seq is under the highest stored, which _max_seq holds: no max(seq) query per device)
            stored = Counter(row[0] for row in batch.rows)  # WINDOW_FIELDS begin with the device
            c.executemany(
                "INSERT INTO devices (id, first_seen, last_seen, current_version, windows) VALUES (?, ?, ?, ?, ?) "
                "ON CONFLICT(id) DO UPDATE SET last_seen = max(devices.last_seen, excluded.last_seen), "
                "current_version = coalesce(excluded.current_version, devices.current_version), "
                "windows = devices.windows + excluded.windows",
                [
                    (device, batch.now, batch.now, version if seq >= self._max_seq[device] else None, stored[device])
                    for device, (seq, version) in batch.newest.items()
                ],
            )
            c.executemany(
                f"INSERT INTO windows ({', '.join(WINDOW_FIELDS)}, stats_json, stats, received_at,"
                f" rejected_by_reason_json) VALUES ({', '.join('?' * len(WINDOW_FIELDS))}, '', ?, ?, ?)",
                batch.rows,
            )
            batch.rows, batch.newest = [], {}
        if bands:
            if time.monotonic() - self._bands_written_at >= BANDS_WRITE_EVERY_S:
                self._write_bands(c, set(self._dirty))
                self._bands_written_at = time.monotonic()
            else:
                self._write_bands(c, batch.new_bands & self._dirty)

    def _write_bands(self, c, which: set[tuple[str, int]]) -> None:
        """Upsert the kept sums of `which` (device, band), inside the caller's transaction."""
        sums = [(d, b, self._bands[d][b]) for d, b in which if b in self._bands.get(d, {})]
        now = time.time()
        if sums:
            c.executemany(
                "INSERT INTO band_stats (device, band, stats_json, stats, bin_temp, windows, samples, updated_at, "
                "first_seq) VALUES (?, ?, '', ?, ?, ?, ?, ?, ?) ON CONFLICT(device, band) DO UPDATE SET "
                "stats_json = '', stats = excluded.stats, bin_temp = excluded.bin_temp, windows = excluded.windows, "
                "samples = excluded.samples, updated_at = excluded.updated_at, first_seq = excluded.first_seq",
                [(device, band, _pack(e[0]), _pack_bin_temp(e[0]), e[1], e[2], now, e[3]) for device, band, e in sums],
            )
        self._dirty -= which

    def dead_letter(
        self, key_expr: str, reason: str, detail: str, payload: bytes, *, received_at: float | None = None
    ) -> int:
        """Keep a refused message for audit: its first DEAD_LETTER_KEEP bytes, its size and SHA-256, so a
        flood of huge payloads cannot fill the disk while each is still identified."""
        payload = bytes(payload)
        with self._tx() as c:
            cur = c.execute(
                "INSERT INTO dead_letters (received_at, key_expr, reason, detail, payload, payload_bytes, "
                "payload_sha256) VALUES (?, ?, ?, ?, ?, ?, ?)",
                (
                    time.time() if received_at is None else received_at,
                    str(key_expr)[:DEAD_LETTER_KEEP],
                    reason,
                    detail[:DEAD_LETTER_DETAIL],
                    payload[:DEAD_LETTER_KEEP],
                    len(payload),
                    hashlib.sha256(payload).hexdigest(),
                ),
            )
            return cur.lastrowid

    def prune_dead_letters(self, received_before: float, limit: int = PRUNE_BATCH) -> int:
        """Delete those of the `limit` oldest dead letters (by id: arrival order) received before `received_before`
        (service clock). Only those are read, so a flood's table is not scanned whole: a page with none to delete
        ends the caller's loop."""
        with self._tx() as c:
            rows = c.execute("SELECT id, received_at FROM dead_letters ORDER BY id LIMIT ?", (limit,)).fetchall()
            old = [(r["id"],) for r in rows if r["received_at"] < received_before]
            c.executemany("DELETE FROM dead_letters WHERE id = ?", old)
        return len(old)

    def rejection_counts(self) -> dict[str, int]:
        return {
            r["reason"]: r["n"]
            for r in self._rows("SELECT reason, count(*) AS n FROM dead_letters GROUP BY reason ORDER BY reason")
        }

    def dead_letters(self, limit: int = 20, *, before: int | None = None) -> list[dict]:
        """Newest first; before: only those of a lower id (the next page's)."""
        where, args = ("", ()) if before is None else (" WHERE id < ?", (before,))
        sql = "SELECT * FROM dead_letters" + where + " ORDER BY id DESC LIMIT ?"
        return [dict(r) for r in self._rows(sql, (*args, limit))]

    def insert_ack(self, msg: dict, *, received_at: float | None = None) -> int | None:
        """Store an ack; None (nothing changed) when the same ack (version, verdict, drive time) is already
        stored: agents resend acks until the watermark confirms them."""
        now = time.time() if received_at is None else received_at
        with self._tx() as c:
            seen = c.execute(
                "SELECT 1 FROM acks WHERE device = ? AND version = ? AND status = ? AND at = ?",
                (msg["device"], msg["version"], msg["status"], msg["at"]),
            ).fetchone()
            if seen is not None:
                return None
            self._touch(c, msg["device"], now)
            cur = c.execute(
                "INSERT INTO acks (device, version, status, reason, angle_quality_deg, at, received_at) "
                "VALUES (?, ?, ?, ?, ?, ?, ?)",
                (
                    msg["device"],
                    msg["version"],
                    msg["status"],
                    msg.get("reason"),
                    msg["angle_quality_deg"],
                    msg["at"],
                    now,
                ),
            )
            if msg["status"] == "applied":  # a late ack from a catch-up does not roll the version back
                c.execute(
                    "UPDATE devices SET current_version = ? WHERE id = ? AND "
                    "? >= (SELECT max(at) FROM acks WHERE device = ? AND status = 'applied')",
                    (msg["version"], msg["device"], msg["at"], msg["device"]),
                )
            return cur.lastrowid

    def set_online(self, device: str, online: bool, at: float | None = None) -> None:
        """From the liveliness token: the one source of `online`."""
        if not keys.DEVICE_RE.fullmatch(device):
            raise ValueError(f"device id {device!r} does not match {keys.DEVICE_RE.pattern}")
        now = time.time() if at is None else at
        with self._tx() as c:
            self._touch(c, device, now)
            if online:  # back after being gone: perhaps another agent (FleetService._lag_refused)
                c.execute("UPDATE devices SET online_since = ? WHERE id = ? AND online = 0", (now, device))
            c.execute("UPDATE devices SET online = ? WHERE id = ?", (int(bool(online)), device))

    # --- refit and rollout ------------------------------------------------------------------

    def band_stats(self, device: str) -> dict[int, tuple[WindowStats, int, int]]:
        """band -> (merged statistics, windows, samples): everything a refit needs (kept in memory)."""
        with self._lock:
            bands = self._device_bands(device)
            return {band: (e[0], e[1], e[2]) for band, e in sorted(bands.items())}

    def record_fit(
        self,
        device: str,
        band: int,
        correction: dict,
        quality: dict,
        *,
        created_at: float,
        version: int | None = None,
        adopted: bool = True,
    ) -> int:
        """correction: Correction.to_dict(); quality: as in a coefficient set's band entry;
        created_at: the drive's clock, like the coefficient set the fit goes into (`version`). Returns its id."""
        with self._tx() as c:
            self.record_fits(device, [(band, correction, quality, adopted)], created_at=created_at, version=version)
            return c.execute("SELECT max(id) AS id FROM fits WHERE device = ?", (device,)).fetchone()["id"]

    def record_fits(
        self, device: str, fits: list[tuple[int, dict, dict, bool]], *, created_at: float, version: int | None = None
    ) -> None:
        """Several fits of one refit, (band, correction, quality, adopted) each, in one statement (a refit of a
        dozen bands made three dozen statements)."""
        with self._tx() as c:
            self._touch(c, device, time.time(), heard=False)
            rows = [
                (device, band, created_at, int(quality.get("samples", 0)), _json(quality), _json(correction), version,
                 int(adopted))
                for band, correction, quality, adopted in fits
            ]  # fmt: skip
            c.executemany(
                "INSERT INTO fits (device, band, created_at, samples, quality_json, correction_json,"
                " version, adopted) VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                rows,
            )

    def latest_fits(self, device: str) -> list[dict]:
        """The newest fit of each band, by band."""
        rows = self._rows(
            "SELECT * FROM fits WHERE id IN (SELECT max(id) FROM fits WHERE device = ? GROUP BY band) ORDER BY band",
            (device,),
        )
        return [
            {
                "id": r["id"],
                "band": r["band"],
                "created_at": r["created_at"],
                "samples": r["samples"],
                "quality": json.loads(r["quality_json"]),
                "correction": json.loads(r["correction_json"]),
            }
            for r in rows
        ]

    def next_version(self, device: str) -> int:
        return self._rows(
            "SELECT coalesce(max(version), 0) + 1 AS v FROM coefficient_sets WHERE device = ?", (device,)
        )[0]["v"]

    def insert_coefficient_set(self, msg: dict, *, state: str = "confirmed", reason: str | None = None) -> None:
        """Keep a set (wire message) in its first guard state: a fitted set starts on trial, the factory's
        and a rollback (which carries a confirmed set again) start confirmed."""
        if state not in self.SET_STATES:
            raise ValueError(f"set state {state!r} is not one of {self.SET_STATES}")
        with self._tx() as c:
            if c.execute(
                "SELECT 1 FROM coefficient_sets WHERE device = ? AND version = ?", (msg["device"], msg["version"])
            ).fetchone():
                raise StoreError("version_exists", f"coefficient set {msg['device']} v{msg['version']} already exists")
            self._touch(c, msg["device"], time.time(), heard=False)
            c.execute(
                "INSERT INTO coefficient_sets (device, version, created_at, basis, body_json, state, state_reason, "
                "restores_version) VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                (
                    msg["device"],
                    msg["version"],
                    msg["created_at"],
                    msg["basis"],
                    _json(msg),
                    state,
                    reason,
                    msg.get("restores_version"),
                ),
            )
            if state == "trial" or reason:
                c.execute(
                    "INSERT INTO set_events (device, version, state, at, decided_at, reason) VALUES (?, ?, ?, ?, ?, ?)",
                    (msg["device"], msg["version"], state, msg["created_at"], time.time(), reason or "new fit"),
                )

    def mark_published(self, device: str, version: int, at: float | None = None) -> None:
        with self._tx() as c:
            cur = c.execute(
                "UPDATE coefficient_sets SET published_at = ? WHERE device = ? AND version = ?",
                (time.time() if at is None else at, device, version),
            )
            if cur.rowcount == 0:
                raise KeyError(f"no coefficient set {device} v{version}")

    def current_coefficients(self, device: str, *, published_only: bool = False) -> dict | None:
        """The latest coefficient set (wire message), or None."""
        rows = self._rows(
            "SELECT body_json FROM coefficient_sets WHERE device = ?"
            + (" AND published_at IS NOT NULL AND state != 'rolled_back'" if published_only else "")
            + " ORDER BY version DESC LIMIT 1",
            (device,),
        )
        return json.loads(rows[0]["body_json"]) if rows else None

    def published_version(self, device: str) -> int | None:
        """The version of the latest published set (what current_coefficients(published_only=True) returns): a
        set rolled back is not it (a rollback publishes a newer one, or the drive refused it and runs the one
        before)."""
        return self._rows(
            "SELECT max(version) AS v FROM coefficient_sets WHERE device = ? AND published_at IS NOT NULL "
            "AND state != 'rolled_back'",
            (device,),
        )[0]["v"]

    def versions_since(self, device: str, at: float) -> list[int]:
        """The device's sets (any state) made at or after drive time `at`, newest first."""
        rows = self._rows(
            "SELECT version FROM coefficient_sets WHERE device = ? AND created_at >= ? ORDER BY version DESC",
            (device, at),
        )
        return [r["version"] for r in rows]

    def newest_set(self, device: str) -> dict | None:
        """The newest set not rolled back, published or not: {version, created_at (drive clock), published_at (None:
        never put)}. What the service means the drive to run."""
        rows = self._rows(
            "SELECT version, created_at, published_at FROM coefficient_sets WHERE device = ? "
            "AND state != 'rolled_back' ORDER BY version DESC LIMIT 1",
            (device,),
        )
        return dict(rows[0]) if rows else None

    def state_of(self, device: str, version: int) -> str | None:
        """A set's guard state (trial, confirmed, rolled_back), or None when there is no such set."""
        rows = self._rows("SELECT state FROM coefficient_sets WHERE device = ? AND version = ?", (device, version))
        return rows[0]["state"] if rows else None

    def running_version(self, device: str) -> int | None:
        """The version the device says it runs: its newest window's, or its newest applied ack's."""
        rows = self._rows("SELECT current_version FROM devices WHERE id = ?", (device,))
        return rows[0]["current_version"] if rows else None

    def coefficient_set(self, device: str, version: int) -> dict | None:
        """One set (wire message) by version; version 0 is the factory's."""
        rows = self._rows("SELECT body_json FROM coefficient_sets WHERE device = ? AND version = ?", (device, version))
        return json.loads(rows[0]["body_json"]) if rows else None

    def coefficient_history(self, device: str) -> list[dict]:
        """Every set, newest first: version, created_at, basis, published_at, its guard state (trial,
        confirmed, rolled_back) with the reason, the version a rollback restores, and the wire message."""
        return [
            {
                "version": r["version"],
                "created_at": r["created_at"],
                "basis": r["basis"],
                "published_at": r["published_at"],
                "state": r["state"],
                "state_reason": r["state_reason"],
                "restores_version": r["restores_version"],
                "message": json.loads(r["body_json"]),
            }
            for r in self._rows("SELECT * FROM coefficient_sets WHERE device = ? ORDER BY version DESC", (device,))
        ]

    # --- the guard's states -----------------------------------------------------------------

    SET_STATES = ("trial", "confirmed", "rolled_back")

    def set_state(self, device: str, version: int, state: str, *, at: float, reason: str) -> None:
        """Move a set to `state` and keep the transition (`at`: the drive clock the decision is made at)."""
        if state not in self.SET_STATES:
            raise ValueError(f"set state {state!r} is not one of {self.SET_STATES}")
        with self._tx() as c:
            cur = c.execute(
                "UPDATE coefficient_sets SET state = ?, state_reason = ? WHERE device = ? AND version = ?",
                (state, reason, device, version),
            )
            if cur.rowcount == 0:
                raise KeyError(f"no coefficient set {device} v{version}")
            c.execute(
                "INSERT INTO set_events (device, version, state, at, decided_at, reason) VALUES (?, ?, ?, ?, ?, ?)",
                (device, version, state, at, time.time(), reason),
            )

    def rollout_records(self, device: str) -> list[dict]:
        """The device's part in every staged rollout (service/rollout.py), oldest first: the rollout's id and name,
        its wave, outcome, the set it ran before and the one the change published, when (service clock) and why."""
        rows = self._rows(
            "SELECT d.rollout, r.name, d.wave, d.state, d.before_version, d.version, d.started_at, d.decided_at, "
            "d.reason, r.created_at FROM rollout_devices d JOIN rollouts r ON r.id = d.rollout "
            "WHERE d.device = ? ORDER BY d.rollout",
            (device,),
        )
        return [dict(r) for r in rows]

    def set_events(self, device: str) -> list[dict]:
        """Every guard transition of the device's sets, oldest first."""
        return [
            dict(r)
            for r in self._rows(
                "SELECT version, state, at, decided_at, reason FROM set_events WHERE device = ? ORDER BY id", (device,)
            )
        ]

    def stats_run_on(self, device: str, version: int, bands: set[int] | None = None) -> dict[int, WindowStats]:
        """band -> the summed statistics of the windows the agent ran on coefficient set `version`."""
        rows = self._rows(
            "SELECT band, stats, stats_json FROM windows WHERE device = ? AND coefficients_version = ?",
            (device, version),
        )
        return self._sum_by_band(r for r in rows if bands is None or r["band"] in bands)

    def stats_since(self, device: str, after: float) -> dict[int, WindowStats]:
        """band -> the summed statistics of the device's windows that ended after `after` (drive clock)."""
        sql = "SELECT band, stats, stats_json FROM windows WHERE device = ? AND window_end > ?"
        return self._sum_by_band(self._rows(sql, (device, after)))

    def _sum_by_band(self, rows) -> dict[int, WindowStats]:
        out: dict[int, WindowStats] = {}
        for r in rows:
            stats = self._stats_of(r).window_stats()
            out[r["band"]] = out[r["band"]].merge(stats) if r["band"] in out else stats
        return out

    def set_on_trial(self, device: str) -> dict | None:
        """The newest published set, when it is on trial: {version, message}."""
        rows = self._rows(
            "SELECT version, body_json, state FROM coefficient_sets WHERE device = ? AND published_at IS NOT NULL "
            "ORDER BY version DESC LIMIT 1",
            (device,),
        )
        if not rows or rows[0]["state"] != "trial":
            return None
        return {"version": rows[0]["version"], "message": json.loads(rows[0]["body_json"])}

    def last_confirmed(self, device: str, before: int | None = None) -> dict | None:
        """The newest confirmed set (wire message) older than `before`: what a rollback restores."""
        rows = self._rows(
            "SELECT body_json FROM coefficient_sets WHERE device = ? AND state = 'confirmed' AND version < ? "
            "ORDER BY version DESC LIMIT 1",
            (device, 2**62 if before is None else before),
        )
        return json.loads(rows[0]["body_json"]) if rows else None

    def confirmed_before(self, device: str, at: float) -> int | None:
        """The version of the newest confirmed set made before drive time `at`: what the drive ran then, a set on
        trial at `at` aside."""
        return self._rows(
            "SELECT max(version) AS v FROM coefficient_sets WHERE device = ? AND state = 'confirmed' "
            "AND created_at < ?",
            (device, at),
        )[0]["v"]

    def refusals(self, device: str, *, since: float | None = None) -> list[dict]:
        """The sets the device's agent refused and never applied (acks with status rejected, none applied: a
        forged or damaged copy refused before the real one was applied does not count): {version, reason}, oldest
        first; `since`: only refusals received after it (service clock)."""
        rows = self._rows(
            "SELECT version, reason FROM acks a WHERE device = ? AND status = 'rejected' "
            + ("" if since is None else "AND received_at > ? ")
            + "AND NOT EXISTS "
            "(SELECT 1 FROM acks b WHERE b.device = a.device AND b.version = a.version AND b.status = 'applied') "
            "ORDER BY id",
            (device,) if since is None else (device, since),
        )
        return [{"version": r["version"], "reason": r["reason"] or ""} for r in rows]

    def acks(self, device: str, *, with_received_at: bool = False) -> list[dict]:
        """Every ack (wire message), in the order the agent sent them; with_received_at adds the service's
        receipt time (unix s) as "received_at"."""
        out = []
        for r in self._rows("SELECT * FROM acks WHERE device = ? ORDER BY at, id", (device,)):
            msg = {
                "schema": wire.SCHEMA_NAME["ack"],
                "device": r["device"],
                "version": r["version"],
                "status": r["status"],
                "angle_quality_deg": r["angle_quality_deg"],
                "at": r["at"],
            }
            if r["reason"] is not None:
                msg["reason"] = r["reason"]
            if with_received_at:
                msg["received_at"] = r["received_at"]
            out.append(msg)
        return out

    # --- reading ----------------------------------------------------------------------------

    @staticmethod
    def _device_row(r: sqlite3.Row) -> dict:
        return {
            "id": r["id"],
            "first_seen": r["first_seen"],
            "last_seen": r["last_seen"],
            "online": bool(r["online"]),
            "current_version": r["current_version"],
            "windows": r["windows"],
            "retired": None
            if r["retired_at"] is None
            else {"at": r["retired_at"], "by": r["retired_by"], "note": r["retired_note"]},
        }

    _DEVICE_SQL = (
        "SELECT d.*, r.retired_at, r.retired_by, "
        "r.note AS retired_note FROM devices d "
        "LEFT JOIN device_retirements r ON r.device = d.id AND r.reinstated_at IS NULL"
    )
    # a device in the fleet: not retired (device_retirements), for the fleet's counts
    _IN_FLEET = "NOT EXISTS (SELECT 1 FROM device_retirements r WHERE r.device = {} AND r.reinstated_at IS NULL)"

    def check(self) -> str:
        """'ok' when the database answers a read, else what went wrong (for /healthz)."""
        try:
            self._rows("SELECT count(*) FROM schema_migrations")
        except db.database_errors() as exc:
            return f"database error: {exc}"
        return "ok"

    def silent_devices(
        self, silent_s: float, *, limit: int | None = None, now: float | None = None, labels: dict | None = None
    ) -> list[str]:
        """Devices online (their agent's liveliness token up) that sent nothing stored for `silent_s` (service clock):
        an agent that runs but whose windows cannot be made or are all refused (a thermistor broken for good, a
        sensor gone, a clock the service refuses), which no alarm sees, the drift monitor having no window.
        labels: only devices that carry all of them."""
        now = time.time() if now is None else now
        labelled, label_args = self._labelled("d.id", labels)
        # a drive whose windows are longer than a third of silent_s is silent only past three of them (its newest's)
        rows = self._rows(
            "SELECT d.id FROM devices d WHERE d.online = 1 AND d.last_seen < ? AND d.last_seen < ? - 3 * coalesce("
            "(SELECT w.window_end - w.window_start FROM windows w WHERE w.device = d.id ORDER BY w.seq DESC LIMIT 1), "
            f"0) AND {self._IN_FLEET.format('d.id')}{labelled} ORDER BY d.id LIMIT ?",
            (now - silent_s, now, *label_args, 2**62 if limit is None else limit),
        )
        return [r["id"] for r in rows]

    @staticmethod
    def _labelled(column: str, labels: dict | None) -> tuple[str, list]:
        """SQL (" AND ...") and its arguments that keep the devices in `column` carrying every one of `labels`."""
        clause = " AND EXISTS (SELECT 1 FROM device_labels l WHERE l.device = {} AND l.name = ? AND l.value = ?)"
        args = [part for item in (labels or {}).items() for part in item]
        return "".join(clause.format(column) for _ in labels or ()), args

    def set_labels(self, device: str, labels: dict[str, str]) -> dict[str, str]:
        """Replace the device's labels (checked by service.labels.check_labels first), and return them, by name;
        KeyError: no such device."""
        labels = dict(sorted(labels.items()))
        with self._tx() as c:
            # the device's row locked to the transaction's end: a PUT at once on another cluster member waits, then
            # replaces these whole (the two deletes found nothing to wait for, and the second insert failed on the key)
            known = c.execute("UPDATE devices SET first_seen = first_seen WHERE id = ?", (device,)).rowcount > 0
            if known:
                c.execute("DELETE FROM device_labels WHERE device = ?", (device,))
                c.executemany(
                    "INSERT INTO device_labels (device, name, value) VALUES (?, ?, ?)",
                    [(device, name, value) for name, value in labels.items()],
                )
        if not known:
            raise KeyError(f"no device {device}")
        return labels  # what the transaction wrote, whole: not read back (PUT /devices/{id}/labels reads the device)

    def labels_of(self, ids: list[str]) -> dict[str, dict[str, str]]:
        """device -> its labels, for every device of `ids` ({} for one without)."""
        out: dict[str, dict[str, str]] = {d: {} for d in ids}
        # 500 ids a read, never the whole fleet's labels: read for every page of 1000, 50,000 drives took 14 s
        for chunk in (ids[i : i + 500] for i in range(0, len(ids), 500)):
            sql = f"SELECT * FROM device_labels WHERE device IN ({', '.join('?' * len(chunk))}) ORDER BY name"
            for r in self._rows(sql, chunk):
                out[r["device"]][r["name"]] = r["value"]
        return out

    def device_counts(self) -> dict[str, int]:
        """Devices by liveliness state, the retired apart: {'online': n, 'offline': m, 'retired': k}."""
        rows = self._rows(
            f"SELECT CASE WHEN {self._IN_FLEET.format('d.id')} THEN d.online ELSE -1 END AS state, count(*) AS n "
            "FROM devices d GROUP BY 1"
        )
        counts = {"online": 0, "offline": 0, "retired": 0}
        for r in rows:
            counts["retired" if r["state"] == -1 else "online" if r["state"] else "offline"] += r["n"]
        return counts

    def devices(self, *, after: str | None = None, limit: int | None = None, labels: dict | None = None) -> list[dict]:
        """Devices by id, each with its labels; after: only those of a higher id (the next page's); limit None: every
        one; labels: only those that carry all of them."""
        where, args = ("d.id > ?", [after]) if after is not None else ("1 = 1", [])
        labelled, label_args = self._labelled("d.id", labels)
        bound = 2**62 if limit is None else limit  # no bound: SQLite reads -1 so, PostgreSQL does not
        rows = self._rows(
            f"{self._DEVICE_SQL} WHERE {where}{labelled} ORDER BY d.id LIMIT ?", (*args, *label_args, bound)
        )
        found = [self._device_row(r) for r in rows]
        labels_of = self.labels_of([d["id"] for d in found])
        return [{**d, "labels": labels_of[d["id"]]} for d in found]

    def online_device_ids(self) -> list[str]:
        """The devices marked online (their liveliness token last seen coming), by id."""
        return [r["id"] for r in self._rows("SELECT id FROM devices WHERE online = 1 ORDER BY id")]

    def device_ids(self, *, in_fleet: bool = False, labels: dict | None = None) -> list[str]:
        """Every device's id; in_fleet: the retired left out; labels: only those that carry all of them."""
        where = f" AND {self._IN_FLEET.format('devices.id')}" if in_fleet else ""
        labelled, args = self._labelled("devices.id", labels)
        return [r["id"] for r in self._rows(f"SELECT id FROM devices WHERE 1 = 1{where}{labelled} ORDER BY id", args)]

    def retired_device_ids(self) -> set[str]:
        return {r["device"] for r in self._rows("SELECT device FROM device_retirements WHERE reinstated_at IS NULL")}

    def is_retired(self, device: str) -> bool:
        """As the writer checks it (read again every RETIRED_READ_EVERY_S): the watermark reply says it."""
        return device in self._retired_devices()

    def _retired_devices(self) -> frozenset[str]:
        """The retired devices as the writer checks them: read again every RETIRED_READ_EVERY_S."""
        if time.monotonic() - self._retired_read_at > RETIRED_READ_EVERY_S:
            began = time.monotonic()
            self._retired = frozenset(self.retired_device_ids())
            # begun before this process's last change was committed (a watermark question, outside the writer's
            # lock): it may not hold it, so it is read again at the next call
            self._retired_read_at = began if began > self._retired_changed_at else -math.inf
        return self._retired

    def retire_device(self, device: str, *, by: str, note: str, at: float | None = None) -> dict:
        """Take a device out of the fleet (replaced, scrapped): who, when, why. Its history stays. KeyError: no such
        device; StoreError `already_retired`: it is (the first retirement stands)."""
        return self._retirement(device, retire=True, by=by, note=note, at=at)

    def reinstate_device(self, device: str, *, by: str, note: str, at: float | None = None) -> dict:
        """Bring a retired device back into the fleet; its retirement stays in the history, closed by who and why.
        KeyError: no such device; StoreError `not_retired`: it is in the fleet."""
        return self._retirement(device, retire=False, by=by, note=note, at=at)

    def _retirement(self, device: str, *, retire: bool, by: str, note: str, at: float | None) -> dict:
        at = time.time() if at is None else at
        holder = None
        # refused after the transaction, not inside it: an error inside drops every band sum kept in memory; the
        # writer's lock held on to the mark below, after the commit, so that no batch of the writer's comes between
        with self._lock:
            with self._tx() as c:
                known = c.execute("SELECT 1 FROM devices WHERE id = ?", (device,)).fetchone() is not None
                if known and retire:
                    # the unique index allows one retirement in force: a second one, even at once from another cluster
                    # member, inserts nothing and is refused below
                    changed = c.execute(
                        "INSERT INTO device_retirements (device, retired_at, retired_by, note) VALUES (?, ?, ?, ?) "
                        "ON CONFLICT DO NOTHING",
                        (device, at, by, note),
                    ).rowcount
                    if not changed:  # who holds it, read here: reinstated after this transaction, it would be no one
                        holder = c.execute(
                            "SELECT retired_by, note FROM device_retirements "
                            "WHERE device = ? AND reinstated_at IS NULL",
                            (device,),
                        ).fetchone()
                elif known:
                    changed = c.execute(
                        "UPDATE device_retirements SET reinstated_at = ?, reinstated_by = ?, reinstate_note = ? "
                        "WHERE device = ? AND reinstated_at IS NULL",
                        (at, by, note, device),
                    ).rowcount
            # this process's writer reads them again at its next batch, a watermark question at its next: one that
            # read them while this committed (the read pool, outside the lock) saw the drive as it was, for 5 s
            if known and changed:
                self._retired_changed_at, self._retired_read_at = time.monotonic(), -math.inf
        if not known:
            raise KeyError(f"no device {device}")
        if not changed and retire:
            said = f" by {holder['retired_by']}: {holder['note']}" if holder is not None else ""
            raise StoreError("already_retired", f"{device} was retired{said}")
        if not changed:
            raise StoreError("not_retired", f"{device} is not retired")
        return self.device(device)

    def retirements(self, device: str) -> list[dict]:
        """The device's retirements, oldest first, each with its reinstatement (None while in force)."""
        return [
            {
                "retired_at": r["retired_at"],
                "retired_by": r["retired_by"],
                "note": r["note"],
                "reinstated_at": r["reinstated_at"],
                "reinstated_by": r["reinstated_by"],
                "reinstate_note": r["reinstate_note"],
            }
            for r in self._rows("SELECT * FROM device_retirements WHERE device = ? ORDER BY id", (device,))
        ]

    def online_since(self, device: str) -> float | None:
        """When the device's liveliness token last came back after being gone (service clock; None: not seen)."""
        rows = self._rows("SELECT online_since FROM devices WHERE id = ?", (device,))
        return rows[0]["online_since"] if rows else None

    def device(self, device: str) -> dict | None:
        rows = self._rows(self._DEVICE_SQL + " WHERE d.id = ?", (device,))
        return {**self._device_row(rows[0]), "labels": self.labels_of([device])[device]} if rows else None

    def contiguous_seq(self, device: str, *, start: int = 0) -> int:
        """Highest seq with every window from 1 up to it stored or gone (below the seq floor the agent named:
        `gone_below`, the lowest seq it holds); `start` is a watermark known to hold. The mark may pass the highest
        seq stored: an agent that numbers anew goes on from it, so nothing is ever numbered beneath the floor (where
        a window lost on the way would count as gone, and the agent forget it unstored)."""
        mark = max(start, self.seq_floor(device) - 1)
        while True:
            rows = self._rows(
                "SELECT seq FROM windows WHERE device = ? AND seq > ? ORDER BY seq LIMIT 512", (device, mark)
            )
            for r in rows:
                if r["seq"] != mark + 1:
                    return mark
                mark += 1
            if len(rows) < 512:
                return mark

    def seq_floor(self, device: str) -> int:
        """The seq below which a window not stored is gone for good (the agent's gone_below, or retention); 0: none."""
        rows = self._rows("SELECT seq_floor FROM devices WHERE id = ?", (device,))
        return rows[0]["seq_floor"] if rows else 0

    def mark_gone_below(self, device: str, seq: int) -> bool:
        """The agent says every window of it below `seq` that is not stored is gone (its outbox dropped them): raise
        the device's seq floor to it. False when that changes nothing (a floor as high already, a device unseen)."""
        with self._tx() as c:
            cur = c.execute(
                "UPDATE devices SET seq_floor = ? WHERE id = ? AND seq_floor < ?", (int(seq), device, int(seq))
            )
            return cur.rowcount > 0

    def prune_windows(
        self, device: str, *, ended_before: float, below_seq: int, keep_version: int | None, limit: int = PRUNE_BATCH
    ) -> int:
        """Delete up to `limit` of the device's windows past retention: ended before `ended_before` (drive clock),
        seq below `below_seq` (the caller's bound: under the contiguous watermark, monitored, not the newest), not
        run on `keep_version` (a set on trial is judged from its windows), and in no band's sum (seq below its
        band's first_seq: the horizon has subtracted it; a sum's own windows are what rebuild it after a crash, and
        a band without a stored sum keeps its windows). The seq floor rises over them, so the watermark steps over
        the gap and a window that is not stored below it counts as gone. Coefficient sets, acks, fits and alarms
        all stay: retention takes the bulk telemetry only. Returns how many were deleted."""
        with self._tx() as c:
            # the device's row locked first: another process pruning it at once (PostgreSQL) waits, then reads what
            # this left (it read the same windows, deleted none, and took them off the count again)
            c.execute("UPDATE devices SET seq_floor = seq_floor WHERE id = ?", (device,))
            # the sums' first_seqs as kept in memory (written behind): a sum counts its windows from first_seq on to
            # tell whether it is behind them, so no window from the stored first_seq on may go
            self._write_bands(c, {(d, b) for d, b in self._dirty if d == device})
            rows = c.execute(
                "SELECT w.seq FROM windows w JOIN band_stats b ON b.device = w.device AND b.band = w.band "
                "WHERE w.device = ? AND w.window_end < ? AND w.seq < ? AND w.seq < b.first_seq "
                "AND w.coefficients_version <> ? ORDER BY w.window_end LIMIT ?",
                (device, ended_before, below_seq, -1 if keep_version is None else keep_version, limit),
            ).fetchall()
            seqs = [r["seq"] for r in rows]
            if not seqs:
                return 0
            c.executemany("DELETE FROM windows WHERE device = ? AND seq = ?", [(device, s) for s in seqs])
            floor = max(seqs) + 1  # every seq below below_seq was stored or gone: none waits under the floor
            c.execute(
                "UPDATE devices SET seq_floor = max(seq_floor, ?), windows = windows - ? WHERE id = ?",
                (floor, len(seqs), device),
            )
        return len(seqs)

    def acked_version(self, device: str) -> int:
        """Highest coefficient version the device has acknowledged, either way (0 when none)."""
        return self._rows("SELECT coalesce(max(version), 0) AS v FROM acks WHERE device = ?", (device,))[0]["v"]

    def last_window(self, device: str) -> tuple[int, float] | None:
        """(seq, window_end) of the device's highest-seq window stored, None when it has none."""
        rows = self._rows("SELECT seq, window_end FROM windows WHERE device = ? ORDER BY seq DESC LIMIT 1", (device,))
        return (rows[0]["seq"], rows[0]["window_end"]) if rows else None

    def window_start_of(self, device: str, seq: int) -> float | None:
        """window_start of the device's window `seq`, None when none is stored."""
        rows = self._rows("SELECT window_start FROM windows WHERE device = ? AND seq = ?", (device, seq))
        return rows[0]["window_start"] if rows else None

    def max_seq(self, device: str) -> int:
        """Highest window seq stored (0 when none): where an agent's catch-up resumes."""
        last = self.last_window(device)
        return last[0] if last else 0

    @staticmethod
    def _window(r: sqlite3.Row, stats: bool) -> dict:
        msg = {"schema": wire.SCHEMA_NAME["window"], **{f: r[f] for f in WINDOW_FIELDS}}
        if stats:
            msg["stats"] = Store._stats_dict(r)
        return msg

    def windows(
        self,
        device: str,
        t_from: float | None = None,
        t_to: float | None = None,
        *,
        stats: bool = False,
        limit: int | None = None,
        after: tuple[float, int] | None = None,
    ) -> list[dict]:
        """Windows with t_from <= window_start <= t_to, by window_start then seq; wire messages (without stats unless
        asked). after: (window_start, seq) of the last window of the page before: only the windows past it."""
        cols = ", ".join(WINDOW_FIELDS) + (", stats_json, stats" if stats else "")
        sql = (
            f"SELECT {cols} FROM windows WHERE device = ? AND window_start >= ? AND window_start <= ? "
            "AND (window_start, seq) > (?, ?) ORDER BY window_start, seq LIMIT ?"
        )
        rows = self._rows(
            sql,
            (
                device,
                -float("inf") if t_from is None else t_from,
                float("inf") if t_to is None else t_to,
                *((-float("inf"), 0) if after is None else after),
                2**62 if limit is None else limit,  # no bound: SQLite reads -1 so, PostgreSQL does not
            ),
        )
        return [self._window(r, stats) for r in rows]

    def iter_windows(
        self,
        device: str,
        t_from: float | None = None,
        t_to: float | None = None,
        *,
        page: int = 200,
        with_received_at: bool = False,
    ) -> Iterator[dict]:
        """Full window messages with t_from <= window_start <= t_to, by window_end, a page at a time
        (the lock is not held between pages, so a long export does not stall ingest); with_received_at
        adds the service's receipt time (unix s) as "received_at"."""
        after = (-float("inf"), 0)
        lo = -float("inf") if t_from is None else t_from
        hi = float("inf") if t_to is None else t_to
        while True:
            rows = self._rows(
                f"SELECT {', '.join(WINDOW_FIELDS)}, stats_json, stats, received_at FROM windows WHERE device = ? "
                "AND window_start >= ? AND window_start <= ? AND (window_end, seq) > (?, ?) "
                "ORDER BY window_end, seq LIMIT ?",
                (device, lo, hi, *after, page),
            )
            for r in rows:
                msg = self._window(r, True)
                if with_received_at:
                    msg["received_at"] = r["received_at"]
                yield msg
            if len(rows) < page:
                return
            after = (rows[-1]["window_end"], rows[-1]["seq"])

    def angle_error_by_band(self, device: str) -> list[dict]:
        """Per temperature band, the agent's angle-error estimate averaged over the windows it ran on the
        factory set (version 0) and on fleet sets: [{band, basis, temp_c, angle_error_deg, windows}]."""
        rows = self._rows(
            "SELECT band, CASE WHEN coefficients_version = 0 THEN 'factory' ELSE 'fleet' END AS basis, "
            "avg(temp_mean_c) AS temp_c, avg(angle_quality_deg) AS angle_error_deg, count(*) AS windows "
            "FROM windows WHERE device = ? GROUP BY band, basis ORDER BY basis, band",
            (device,),
        )
        return [dict(r) for r in rows]

    def window_summary(self, device: str, recent: int = 10) -> dict:
        """Totals over all windows and the newest `recent` windows (by seq), newest first."""
        total = self._rows(
            "SELECT count(*) AS windows, coalesce(sum(samples), 0) AS samples, "
            "coalesce(sum(rejected), 0) AS rejected FROM windows WHERE device = ?",
            (device,),
        )[0]
        latest = self._rows(
            "SELECT seq, window_start, window_end, coefficients_version, angle_quality_deg "
            "FROM windows WHERE device = ? ORDER BY seq DESC LIMIT ?",
            (device, recent),
        )
        return {**dict(total), "recent": [dict(r) for r in latest]}

    # --- drift monitor (service/monitor.py; migration 020) -------------------------------------

    def monitor_windows(self, device: str, after_seq: int, through_seq: int, limit: int = 500) -> list[dict]:
        """Windows after_seq < seq <= through_seq in seq order, with what the monitor reads of them."""
        rows = self._rows(
            "SELECT seq, window_start, window_end, temp_mean_c, temp_rate_c_per_s, coefficients_version, band, "
            "stats_json, stats, rejected_by_reason_json FROM windows "
            "WHERE device = ? AND seq > ? AND seq <= ? ORDER BY seq LIMIT ?",
            (device, after_seq, through_seq, limit),
        )
        return [
            {
                "seq": r["seq"],
                "window_start": r["window_start"],
                "window_end": r["window_end"],
                "temp_mean_c": r["temp_mean_c"],
                "temp_rate_c_per_s": r["temp_rate_c_per_s"],
                "coefficients_version": r["coefficients_version"],
                "band": r["band"],
                "stats": self._window_stats_or_none(r),
                "rejected_by_reason": json.loads(r["rejected_by_reason_json"])
                if r["rejected_by_reason_json"]
                else None,
            }
            for r in rows
        ]

    def monitor_states(self, device: str | None = None) -> dict[str, tuple[dict | None, int]]:
        """device -> (monitor state, last seq seen) for every device the monitor has seen (or for one); the state is
        None where its JSON does not parse (the monitor starts that device over: one device's, it stopped every
        device's monitor at start)."""
        sql, args = "SELECT device, state_json, last_seq FROM monitor_state", ()
        if device is not None:
            sql, args = sql + " WHERE device = ?", (device,)
        out = {}
        for r in self._rows(sql, args):
            try:
                state = json.loads(r["state_json"])
            except ValueError:
                state = None
            out[r["device"]] = (state, r["last_seq"])
        return out

    def monitor_device_states(self, device: str | None = None) -> dict[str, str | None]:
        """device -> the state (ok | watch | ...) its monitor was in when last written (for every device the monitor
        has seen, or for one); None: written before migration 075 (read it from monitor_states)."""
        sql, args = "SELECT device, device_state FROM monitor_state", ()
        if device is not None:
            sql, args = sql + " WHERE device = ?", (device,)
        return {r["device"]: r["device_state"] for r in self._rows(sql, args)}

    def save_monitor(
        self, device: str, state: dict, last_seq: int, events: list[dict], *, device_state: str | None = None
    ) -> list[dict]:
        """The monitor's state (and `device_state`, what it judges the device: DeviceMonitor.state) and the alarms
        it raised or cleared, in one transaction. events: {"kind":
        "raise" | "clear", "cause", "at", "parameters", "evidence"}; returns one alarm (as listed) per event
        written, in order, as it stood after that event: an alarm raised and cleared in the same call is
        returned twice, open and then cleared, so its listeners hear both."""
        written = []  # (alarm id, "raise" | "clear")
        now = time.time()
        with self._tx() as c:
            self._touch(c, device, now, heard=False)
            for e in events:
                if e["kind"] == "raise":
                    if c.execute(
                        "SELECT 1 FROM alarms WHERE device = ? AND cause = ? AND cleared_at IS NULL",
                        (device, e["cause"]),
                    ).fetchone():
                        continue  # already open (e.g. offline raised again after a restart)
                    cur = c.execute(
                        "INSERT INTO alarms (device, cause, parameters_json, evidence, raised_at, created_at)"
                        " VALUES (?, ?, ?, ?, ?, ?)",
                        (device, e["cause"], _json(e["parameters"]), e["evidence"], e["at"], now),
                    )
                    written.append((cur.lastrowid, "raise"))
                else:
                    rows = c.execute(
                        "SELECT id FROM alarms WHERE device = ? AND cause = ? AND cleared_at IS NULL",
                        (device, e["cause"]),
                    ).fetchall()
                    c.execute(
                        "UPDATE alarms SET cleared_at = ?, clear_evidence = ? WHERE device = ? AND cause = ?"
                        " AND cleared_at IS NULL",
                        (max(e["at"], 0.0), e["evidence"], device, e["cause"]),
                    )
                    written += [(r["id"], "clear") for r in rows]
            c.execute(
                "INSERT INTO monitor_state (device, state_json, last_seq, updated_at, device_state)"
                " VALUES (?, ?, ?, ?, ?) ON CONFLICT(device) DO UPDATE SET state_json = excluded.state_json,"
                " last_seq = excluded.last_seq, updated_at = excluded.updated_at, device_state = excluded.device_state",
                (device, _json(state), last_seq, now, device_state),
            )
        if not written:
            return []
        rows = {a["id"]: a for a in self.alarms(ids=[i for i, _ in written])}
        return [rows[i] if kind == "clear" else {**rows[i], "cleared_at": None} for i, kind in written]

    @staticmethod
    def _alarm(r: sqlite3.Row, audit: bool = False) -> dict:
        # for the audit (the MCAP export): when the service raised it (its clock), and what cleared it
        extra = {"created_at": r["created_at"], "clear_evidence": r["clear_evidence"]} if audit else {}
        return {
            **extra,
            "id": r["id"],
            "device": r["device"],
            "cause": r["cause"],
            "parameters": json.loads(r["parameters_json"]),
            "evidence": r["evidence"],
            "raised_at": r["raised_at"],
            "cleared_at": r["cleared_at"],
            "acked_at": r["acked_at"],
            "acked_by": r["acked_by"],
            "ack_note": r["ack_note"],
        }

    def alarms(
        self,
        device: str | None = None,
        cause: str | None = None,
        open_: bool | None = None,
        *,
        ids: list[int] | None = None,
        before: int | None = None,
        limit: int | None = 1000,
        audit: bool = False,
        acked: bool | None = None,
        in_fleet: bool | None = None,
    ) -> list[dict]:
        """Alarms (the GET /alarms contract's objects), newest first; before: only those of a lower id (the next
        page's); limit None: every one. audit: with when the service raised each (`created_at`, its clock) and what
        cleared it (`clear_evidence`). in_fleet: True, only retired devices' left out; False, only theirs."""
        where, args = [], []
        if before is not None:
            where.append("id < ?")
            args.append(before)
        if device is not None:
            where.append("device = ?")
            args.append(device)
        if cause is not None:
            where.append("cause = ?")
            args.append(cause)
        if open_ is not None:
            where.append("cleared_at IS NULL" if open_ else "cleared_at IS NOT NULL")
        if acked is not None:
            where.append("acked_at IS NOT NULL" if acked else "acked_at IS NULL")
        if in_fleet is not None:
            where.append(("" if in_fleet else "NOT ") + self._IN_FLEET.format("alarms.device"))
        if ids is not None:
            where.append(f"id IN ({', '.join('?' * len(ids))})")
            args += list(ids)
        sql = "SELECT * FROM alarms" + (" WHERE " + " AND ".join(where) if where else "") + " ORDER BY id DESC LIMIT ?"
        bound = 2**62 if limit is None else limit  # no bound: SQLite reads -1 so, PostgreSQL does not
        return [self._alarm(r, audit) for r in self._rows(sql, (*args, bound))]

    def ack_alarm(self, alarm_id: int, *, by: str, note: str, at: float | None = None) -> dict:
        """Acknowledge an alarm, open or cleared (an operator may see it only after it cleared): who, when, the note.
        KeyError: no such alarm; StoreError `already_acked`: it was, by someone (the first acknowledgement stands)."""
        # refused after the transaction, not inside it: an error inside drops every band sum kept in memory
        with self._tx() as c:
            row = c.execute("SELECT acked_at, acked_by FROM alarms WHERE id = ?", (alarm_id,)).fetchone()
            if row is not None and row["acked_at"] is None:
                # only if still not acknowledged: on PostgreSQL another process's acknowledgement may commit between
                # the read and this write (which waits for it), and it stands
                acked = c.execute(
                    "UPDATE alarms SET acked_at = ?, acked_by = ?, ack_note = ? WHERE id = ? AND acked_at IS NULL",
                    (time.time() if at is None else at, by, note, alarm_id),
                ).rowcount
                if not acked:
                    row = c.execute("SELECT acked_at, acked_by FROM alarms WHERE id = ?", (alarm_id,)).fetchone()
        if row is None:
            raise KeyError(f"no alarm {alarm_id}")
        if row["acked_at"] is not None:
            raise StoreError("already_acked", f"alarm {alarm_id} was acknowledged by {row['acked_by']}")
        return self.alarms(ids=[alarm_id])[0]

    def label_values(self, name: str) -> dict[str, str]:
        """device -> its value of label `name`, for the devices that carry it."""
        return {
            r["device"]: r["value"]
            for r in self._rows("SELECT device, value FROM device_labels WHERE name = ?", (name,))
        }

    def open_alarm_counts_by(self, name: str) -> dict[str | None, dict[str, int]]:
        """Open alarms per cause of the fleet's devices, by their value of label `name` (None: devices without it)."""
        rows = self._rows(
            "SELECT l.value, a.cause, count(*) AS n FROM alarms a "
            "LEFT JOIN device_labels l ON l.device = a.device AND l.name = ? "
            f"WHERE a.cleared_at IS NULL AND {self._IN_FLEET.format('a.device')} GROUP BY l.value, a.cause",
            (name,),
        )
        out: dict[str | None, dict[str, int]] = {}
        for r in rows:
            out.setdefault(r["value"], {})[r["cause"]] = r["n"]
        return out

    def open_alarm_counts(self, *, unacked: bool = False, labels: dict | None = None) -> dict[str, int]:
        """Open alarms per cause, fleet-wide; unacked: only those nobody acknowledged; labels: only those of devices
        that carry all of them."""
        # a retired drive's alarms stay (its history), and leave the fleet's counts, which the alerting rules watch
        where = (
            "cleared_at IS NULL"
            + (" AND acked_at IS NULL" if unacked else "")
            + " AND "
            + self._IN_FLEET.format("alarms.device")
        )
        labelled, args = self._labelled("alarms.device", labels)
        rows = self._rows(
            f"SELECT cause, count(*) AS n FROM alarms WHERE {where}{labelled} GROUP BY cause ORDER BY cause", args
        )
        return {r["cause"]: r["n"] for r in rows}
