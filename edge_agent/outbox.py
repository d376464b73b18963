"""The agent's durable outbox: every window and every ack is written here before it is sent, and removed
only when the service says it has stored it. Bounded: past the limit the oldest windows are dropped and
counted.

What persists is clock-free: sequence numbers, versions and the drive clock's last window end. When a
message was last sent is kept in memory only, so a restart resends everything unconfirmed and a clock that
jumps (either way) makes messages due, never stuck."""

from __future__ import annotations

import logging
import math
import sqlite3
import threading
from pathlib import Path

from fleet_wire import messages as wire

log = logging.getLogger("edge_agent")
SQLITE_CORRUPT = 11  # sqlite_errorcode of a damaged file (not SQLITE_NOTADB: another kind of file)


class Damaged(sqlite3.DatabaseError):
    """PRAGMA quick_check found the file damaged (its first finding)."""


class Outbox:
    def __init__(self, path: str | Path, *, max_windows: int = 20000):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.max_windows = max_windows
        self.lock = threading.Lock()
        self.salvaged: dict | None = None  # what was kept of a damaged file (None: the file was sound)
        try:
            self._open()
            damage = self.db.execute("PRAGMA quick_check").fetchone()[0]
            if damage != "ok":
                raise Damaged(damage)
        except sqlite3.DatabaseError as exc:
            # a damaged file (a power cut on a disk that lies about its writes, a torn page) refused the agent's start,
            # or every window after it: kept aside, and what can still be read goes into a new one. Another kind of
            # file (SQLITE_NOTADB), a directory, a full disk are refused as before
            if not (isinstance(exc, Damaged) or getattr(exc, "sqlite_errorcode", None) == SQLITE_CORRUPT):
                raise
            self._salvage(exc)
        self.dropped = int(self._meta("dropped", 0))
        self._sent: dict[tuple[str, int], float] = {}  # ("window", seq) | ("ack", version) -> when, this process

    def _open(self) -> None:
        self.db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
        self.db.execute("PRAGMA journal_mode=WAL")
        self.db.execute(
            "CREATE TABLE IF NOT EXISTS outbox (seq INTEGER PRIMARY KEY, payload BLOB NOT NULL, sent_at REAL)"
        )
        self.db.execute("CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value)")
        self.db.execute("CREATE TABLE IF NOT EXISTS acks (version INTEGER PRIMARY KEY, payload BLOB NOT NULL)")

    def _salvage(self, exc: Exception) -> None:
        """Move the damaged file aside (PATH.corrupt, PATH.corrupt.1, ...) and open a new outbox holding what of it
        can still be read: the meta values (the seq and drive clock to go on from, the set the drive runs), every
        window and ack whose payload decodes as what it claims. The windows lost count as dropped, so the agent's
        received question names them gone (as a full outbox's) and the watermark steps over those the service lacks;
        with its last seq unreadable, the agent goes on where the service's reply says, as with an outbox lost."""
        if getattr(self, "db", None) is not None:
            self.db.close()
        aside = self.path.with_name(self.path.name + ".corrupt")
        n = 0
        while aside.exists():
            n += 1
            aside = self.path.with_name(f"{self.path.name}.corrupt.{n}")
        self.path.rename(aside)
        for suffix in ("-wal", "-shm"):  # the WAL holds committed writes not yet in the file: read with it
            side = Path(str(self.path) + suffix)
            if side.exists():
                side.rename(Path(str(aside) + suffix))
        old = sqlite3.connect(aside, isolation_level=None)
        try:
            meta, unread = {}, []
            for key in ("last_seq", "last_window_end", "dropped", "coefficients", "unresumed_after"):
                try:
                    row = old.execute("SELECT value FROM meta WHERE key = ?", (key,)).fetchone()
                except sqlite3.DatabaseError:
                    unread.append(key)
                    continue
                if row is not None:
                    meta[key] = row[0]
            windows, lowest, damaged = _readable_rows(old, "outbox", "seq", _window_ok, probe=True)
            acks, _, _ = _readable_rows(old, "acks", "version", _ack_ok, probe=False)  # versions are sparse
        finally:
            old.close()
        self._open()
        last_seq = max([int(meta.get("last_seq", 0))] + list(windows))
        # every seq from the lowest read to the last issued was held (the outbox's seqs have no gaps)
        lost = 0 if lowest is None else last_seq - lowest + 1 - len(windows)
        if damaged:
            lost = max(lost, 1)  # some below the lowest read, maybe: anything the service lacks there is gone
        ends = [wire.decode_window(p, key_device=None).window_end for p in windows.values()]
        ends += [float(meta["last_window_end"])] if "last_window_end" in meta else []
        meta.update(last_seq=last_seq, dropped=int(meta.get("dropped", 0)) + lost)
        if ends:
            meta["last_window_end"] = max(ends)
        with self.lock:
            self.db.execute("BEGIN")
            self.db.executemany("INSERT INTO outbox(seq, payload, sent_at) VALUES(?, ?, NULL)", sorted(windows.items()))
            self.db.executemany("INSERT INTO acks(version, payload) VALUES(?, ?)", sorted(acks.items()))
            for key, value in meta.items():
                self._set_meta(key, value)
            self.db.execute("COMMIT")
        self.salvaged = {"windows": len(windows), "acks": len(acks), "lost": lost, "kept_as": str(aside)}
        log.warning(
            "outbox %s is damaged (%s), kept as %s: %d window(s) and %d ack(s) read back%s; %s%d window(s) it held "
            "unreadable, dropped (the service is told they are gone)",
            self.path, exc, aside, len(windows), len(acks),
            f", unreadable: {', '.join(unread)} (the set the drive ran: the factory's until the service's)"
            if "coefficients" in unread else f", unreadable: {', '.join(unread)}" if unread else "",
            "at least " if damaged and lowest is None else "", lost,
        )  # fmt: skip

    def _meta(self, key, default):
        row = self.db.execute("SELECT value FROM meta WHERE key = ?", (key,)).fetchone()
        return default if row is None else row[0]

    def _set_meta(self, key, value):
        self.db.execute(
            "INSERT INTO meta(key, value) VALUES(?, ?) ON CONFLICT(key) DO UPDATE SET value = excluded.value",
            (key, value),
        )

    def save_coefficients(self, payload: bytes) -> None:
        """The set the agent runs with, so a restart resumes with it even when the service is away."""
        with self.lock:
            self._set_meta("coefficients", payload)

    def saved_coefficients(self) -> bytes | None:
        with self.lock:
            value = self._meta("coefficients", None)
            return None if value is None else bytes(value)

    def last_seq(self) -> int:
        """Highest sequence number ever issued, so a restarted agent continues the series."""
        with self.lock:
            return self._last_seq()

    def _last_seq(self) -> int:
        row = self.db.execute("SELECT max(seq) FROM outbox").fetchone()
        return max(int(self._meta("last_seq", 0)), row[0] or 0)

    def add(self, seq: int, payload: bytes, *, window_end: float | None = None) -> None:
        with self.lock:
            self.db.execute("BEGIN")
            try:
                self.db.execute(
                    "INSERT OR REPLACE INTO outbox(seq, payload, sent_at) VALUES(?, ?, NULL)", (seq, payload)
                )
                self._set_meta("last_seq", max(seq, int(self._meta("last_seq", 0))))
                if window_end is not None:
                    self._set_meta("last_window_end", window_end)
                over = self.db.execute("SELECT count(*) FROM outbox").fetchone()[0] - self.max_windows
                if over > 0:
                    self.db.execute(
                        "DELETE FROM outbox WHERE seq IN (SELECT seq FROM outbox ORDER BY seq LIMIT ?)", (over,)
                    )
                    self._set_meta("dropped", self.dropped + over)
                self.db.execute("COMMIT")
            except BaseException:
                # a write refused (a full disk, a locked file) left the transaction open: every later BEGIN failed,
                # and the outbox refused every window after it (SQLite may have ended it itself already)
                if self.db.in_transaction:
                    self.db.execute("ROLLBACK")
                raise
            if over > 0:
                self.dropped += over

    def held_from(self) -> int:
        """The lowest seq the outbox holds (the next one to issue when it holds none): every window below it was
        confirmed by the service or dropped while the outbox was full."""
        with self.lock:
            row = self.db.execute("SELECT min(seq) FROM outbox").fetchone()
            return row[0] if row[0] is not None else self._last_seq() + 1

    def unresumed_after(self) -> int:
        """The seq after which windows were numbered with no word from the service yet (kept on disk, so that a
        restart before the service answers still knows which windows may have to move): set at first call."""
        with self.lock:
            value = self._meta("unresumed_after", None)
            if value is None:
                value = self._last_seq()
                self._set_meta("unresumed_after", value)
            return int(value)

    def resumed(self, rewrite=None) -> int:
        """The service has said where it stands: the windows numbered since `unresumed_after` are replaced by what
        `rewrite([(seq, payload), ...]) -> [(seq, payload, window_end), ...]` makes of them (when given), in one
        transaction with forgetting the mark. Returns how many it rewrote."""
        with self.lock:
            after = self._meta("unresumed_after", None)
            rows = (
                []
                if after is None or rewrite is None
                else self.db.execute("SELECT seq, payload FROM outbox WHERE seq > ? ORDER BY seq", (after,)).fetchall()
            )
            new = rewrite([(int(s), bytes(p)) for s, p in rows]) if rows else []  # a failure here changes nothing
            self.db.execute("BEGIN")
            try:
                if new:
                    self.db.execute("DELETE FROM outbox WHERE seq > ?", (after,))
                    self.db.executemany(
                        "INSERT INTO outbox(seq, payload, sent_at) VALUES(?, ?, NULL)", [n[:2] for n in new]
                    )
                    self._set_meta("last_seq", max(n[0] for n in new))
                    self._set_meta("last_window_end", max(n[2] for n in new))
                self.db.execute("DELETE FROM meta WHERE key = 'unresumed_after'")
                self.db.execute("COMMIT")
            except BaseException:
                self.db.execute("ROLLBACK")
                raise
            if new:
                self._sent = {k: t for k, t in self._sent.items() if not (k[0] == "window" and k[1] > int(after))}
            return len(new)

    def last_window_end(self) -> float | None:
        """The drive clock at the end of the newest window ever issued (a restarted drive continues past it)."""
        with self.lock:
            value = self._meta("last_window_end", None)
            return None if value is None else float(value)

    def add_ack(self, version: int, payload: bytes) -> None:
        """An ack, kept until the service's watermark says it has stored an ack for this version or a newer one."""
        with self.lock:
            self.db.execute("INSERT OR REPLACE INTO acks(version, payload) VALUES(?, ?)", (version, payload))

    def confirm_through(self, seq: int, acked_version: int = 0) -> int:
        """The service has every window up to seq and an ack up to acked_version: forget them. Returns how
        many windows were removed."""
        with self.lock:
            self.db.execute("DELETE FROM acks WHERE version <= ?", (acked_version,))
            return self.db.execute("DELETE FROM outbox WHERE seq <= ?", (seq,)).rowcount

    def pending(self, *, limit: int = 500) -> list[tuple[int, bytes]]:
        """Windows not yet confirmed, oldest first."""
        with self.lock:
            rows = self.db.execute("SELECT seq, payload FROM outbox ORDER BY seq LIMIT ?", (limit,))
            return [(int(s), bytes(p)) for s, p in rows.fetchall()]

    def due(self, now: float, resend_after_s: float, *, limit: int = 500) -> list[tuple[str, int, bytes]]:
        """Unconfirmed messages to send now, acks first then windows oldest first: ("ack" | "window", id, payload)
        for each one not sent by this process, or sent more than resend_after_s before `now`, or "after" it
        (the clock went back)."""
        with self.lock:
            out = []
            for kind, table, column in (("ack", "acks", "version"), ("window", "outbox", "seq")):
                ids = [i for (i,) in self.db.execute(f"SELECT {column} FROM {table} ORDER BY {column}")]
                due = [i for i in ids if not (now - resend_after_s <= self._sent.get((kind, i), -math.inf) <= now)]
                due = due[: limit - len(out)]
                for i in range(0, len(due), 500):  # payloads of the due ones only, in chunks SQLite takes
                    chunk = due[i : i + 500]
                    marks = ",".join("?" * len(chunk))
                    rows = self.db.execute(
                        f"SELECT {column}, payload FROM {table} WHERE {column} IN ({marks}) ORDER BY {column}", chunk
                    )
                    out += [(kind, int(ident), bytes(payload)) for ident, payload in rows]
            return out

    def mark_sent(self, items: list[tuple[str, int]], at: float) -> None:
        """("ack" | "window", id) sent at `at` (this process's clock; never written to disk)."""
        with self.lock:
            for item in items:
                self._sent[item] = at
            if len(self._sent) > 4 * self.max_windows:  # forget what was confirmed long ago
                keep = {("window", s) for (s,) in self.db.execute("SELECT seq FROM outbox")}
                keep |= {("ack", v) for (v,) in self.db.execute("SELECT version FROM acks")}
                self._sent = {k: t for k, t in self._sent.items() if k in keep}

    def pending_acks(self) -> list[int]:
        with self.lock:
            return [v for (v,) in self.db.execute("SELECT version FROM acks ORDER BY version")]

    def __len__(self) -> int:
        with self.lock:
            return self.db.execute("SELECT count(*) FROM outbox").fetchone()[0]

    def close(self) -> None:
        with self.lock:
            self.db.close()


def _window_ok(seq: int, payload: bytes) -> bool:
    try:
        return wire.decode_window(payload, key_device=None).seq == seq
    except wire.WireError:
        return False


def _ack_ok(version: int, payload: bytes) -> bool:
    try:
        return wire.decode("ack", payload, key_device=None)["version"] == version
    except wire.WireError:
        return False


def _readable_rows(
    db: sqlite3.Connection, table: str, column: str, ok, *, probe: bool
) -> tuple[dict[int, bytes], int | None, bool]:
    """The rows of a damaged table that can be read and whose payload passes `ok`, the lowest id read, and whether
    any read failed: a scan up from the lowest and one down from the highest, each to the first page that fails, and
    between them (`probe`: ids without gaps) one lookup per id (a damaged page fails the lookups into it alone)."""
    rows: dict[int, bytes] = {}
    damaged = False
    for order in ("ASC", "DESC"):
        try:
            for ident, payload in db.execute(f"SELECT {column}, payload FROM {table} ORDER BY {column} {order}"):
                if int(ident) in rows:
                    break
                rows[int(ident)] = bytes(payload)
        except sqlite3.DatabaseError:
            damaged = True
    if probe and damaged and rows and max(rows) - min(rows) < 10**6:
        for ident in range(min(rows) + 1, max(rows)):
            if ident in rows:
                continue
            try:
                row = db.execute(f"SELECT payload FROM {table} WHERE {column} = ?", (ident,)).fetchone()
            except sqlite3.DatabaseError:
                damaged = True
                continue
            if row is not None:
                rows[ident] = bytes(row[0])
    good = {ident: payload for ident, payload in rows.items() if ok(ident, payload)}
    return good, min(rows) if rows else None, damaged or len(good) < len(rows)
