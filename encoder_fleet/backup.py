"""`encoder-fleet backup`: a consistent copy of the service's SQLite database, taken while the service runs.

SQLite's `VACUUM INTO` reads one snapshot (in WAL mode the service's writer goes on meanwhile) and writes it compacted
(retention's freed pages left out). The copy is checked (`PRAGMA integrity_check`, the migrations, the rows) before
it takes the name asked for, so a name that exists is a backup that passed. PostgreSQL has its own: pg_dump."""

from __future__ import annotations

import os
import sqlite3
import sys
import threading
import time
from pathlib import Path

from encoder_core.samples import InputError

# tables a user reads the backup's contents by; the audit trail first
TABLES = ("coefficient_sets", "acks", "fits", "alarms", "rollouts", "devices", "windows", "dead_letters")


def backup(db: str, out: Path, *, progress=sys.stderr) -> dict:
    """Copy the database `db` to `out` (which must not exist); returns what the copy holds."""
    from service.db import is_postgres, redacted, sqlite_path
    from service.store import migration_files

    if is_postgres(db):
        raise InputError(f"--db {redacted(db)} is PostgreSQL: back it up with pg_dump (or the server's own backups)")
    source = Path(sqlite_path(db))
    if not source.is_file() or source.stat().st_size == 0:
        raise InputError(f"--db {db}: no such database (or an empty file)")
    # absolute: SQLite takes a name that begins "file:" for a URI (VACUUM INTO, and the check's connect), another file
    partial = out.absolute().with_name(out.name + ".partial")
    # the database's -wal, -shm or -journal is absent while the service is stopped: a backup named so was taken for
    # the database's WAL at its next start and deleted, and a .partial of that name was removed below
    own = {source.resolve().with_name(source.resolve().name + suffix) for suffix in ("", "-wal", "-shm", "-journal")}
    if out.resolve() in own or partial.resolve() in own:
        raise InputError(f"{out}: the name of one of the database's own files (or its .partial is); name another")
    if out.exists() or out.is_symlink():
        raise InputError(f"{out} exists: a backup never replaces a file; name a new one")
    if not out.parent.is_dir():
        raise InputError(f"{out}: its folder {out.parent} does not exist")
    if partial.exists() or partial.is_symlink():  # removed, it was a running backup's: both then failed
        raise InputError(f"{partial} exists: another backup to {out} is running, or one was killed: remove it")
    # as_uri: a ?, # or % in the path is quoted, or the URI would open another file (created, and found empty)
    conn = sqlite3.connect(f"{source.resolve().as_uri()}?mode=ro", uri=True, timeout=30.0)
    _interruptible(conn)
    began = time.monotonic()
    made = False  # the .partial is this backup's, to remove on failure (one made meanwhile is another's)
    try:
        try:
            applied = [r[0] for r in conn.execute("SELECT version FROM schema_migrations ORDER BY version")]
        except sqlite3.DatabaseError as exc:
            raise InputError(f"--db {db}: not the service's database ({exc})") from None
        done = threading.Event()
        watcher = threading.Thread(target=_show_progress, args=(partial, source, done, progress), daemon=True)
        watcher.start()
        try:
            # made 0600 before its first byte (VACUUM INTO takes an empty file): the fleet's whole history, tokens'
            # hashes with it, was readable by all while written, and to a reader who opened it then for good
            os.close(os.open(partial, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
            made = True
            try:
                conn.execute("VACUUM INTO ?", (str(partial),))
            finally:
                done.set()
                watcher.join()
            held = _checked(partial)
        except sqlite3.Error as exc:  # a full disk, an I/O error: said in a line, as the CLI says an OSError
            if str(exc) == "interrupted":  # Ctrl-C (_interruptible)
                raise KeyboardInterrupt from None
            raise InputError(f"{out}: the copy failed ({exc}): no backup written") from None
        os.replace(partial, out)
    except BaseException:
        if made:
            partial.unlink(missing_ok=True)
        raise
    finally:
        conn.close()
    known = {n for n, _ in migration_files()}
    return {
        "backup": str(out),
        "seconds": round(time.monotonic() - began, 2),
        "source_bytes": source.stat().st_size + _size(source.with_name(source.name + "-wal")),
        "backup_bytes": out.stat().st_size,
        "migration": max(applied, default=0),
        "migrations_unknown_here": sorted(set(applied) - known),
        "rows": held,
    }


def _interruptible(conn: sqlite3.Connection) -> None:
    """Ctrl-C stops the connection's statement at once: Python runs its signal handler only between its own steps,
    so without them a VACUUM INTO ran to its end first (a large fleet's database: minutes). The handler's
    KeyboardInterrupt, raised in this callback, makes SQLite abort the statement with "interrupted"."""
    conn.set_progress_handler(lambda: 0, 10_000)


def _checked(path: Path) -> dict[str, int]:
    """Rows per table of the copy, once SQLite has read every page of it and found it whole."""
    conn = sqlite3.connect(path)
    _interruptible(conn)
    try:
        problems = [r[0] for r in conn.execute("PRAGMA integrity_check")]
        if problems != ["ok"]:
            raise InputError(f"the copy failed SQLite's integrity check: {'; '.join(problems[:5])}")
        present = {r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        return {t: conn.execute(f"SELECT count(*) FROM {t}").fetchone()[0] for t in TABLES if t in present}
    finally:
        conn.close()


def _size(path: Path) -> int:
    try:
        return path.stat().st_size
    except FileNotFoundError:
        return 0


def _show_progress(partial: Path, source: Path, done: threading.Event, stream) -> None:
    """The copy's size against the source's, every 2 s, while SQLite writes it (it says nothing itself)."""
    total = max(1, _size(source))
    while not done.wait(2.0):
        print(f"backup: {_size(partial) / 2**20:,.0f} MB written of ~{total / 2**20:,.0f} MB", file=stream, flush=True)


def cmd_backup(args) -> int:
    from encoder_fleet.outputs import write_file
    from encoder_fleet.rest_client import text_out

    result = backup(args.db, Path(args.out))
    out = text_out(args)  # stderr when --json is stdout: the JSON there alone
    mb = 2**20
    print(
        f"wrote {result['backup']} in {result['seconds']:.1f} s: {result['backup_bytes'] / mb:,.1f} MB "
        f"(the database and its WAL {result['source_bytes'] / mb:,.1f} MB), migration {result['migration']}, "
        "integrity check ok",
        file=out,
    )
    print("| table | rows |\n|---|---|", file=out)
    for table, n in result["rows"].items():
        print(f"| {table} | {n:,} |", file=out)
    if result["migrations_unknown_here"]:
        print(f"note: written by a newer encoder-fleet (migrations {result['migrations_unknown_here']})", file=out)
    if args.json:
        import json

        write_file(args.json, json.dumps(result, indent=2) + "\n")
    return 0


def register(sub) -> None:
    p = sub.add_parser(
        "backup",
        help="a consistent, checked copy of the service's SQLite database, taken while the service runs",
    )
    p.add_argument("out", help="the backup file to write (must not exist)")
    p.add_argument("--db", default="out/fleet.sqlite", help="the service's database (default out/fleet.sqlite)")
    p.add_argument("--json", metavar="FILE", help="also write what the backup holds as JSON (/dev/stdout for a script)")
    p.set_defaults(func=cmd_backup)
