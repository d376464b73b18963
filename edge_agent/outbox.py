"""The agent's durable outbox: every window is written here before it is sent, and removed only when
the service says it has stored it. Bounded: past the limit the oldest windows are dropped and counted."""

from __future__ import annotations

import sqlite3
import threading
from pathlib import Path


class Outbox:
    def __init__(self, path: str | Path, *, max_windows: int = 20000):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.max_windows = max_windows
        self.lock = threading.Lock()
        self.db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
        self.db.execute("PRAGMA journal_mode=WAL")
        self.db.execute(
            "CREATE TABLE IF NOT EXISTS outbox (seq INTEGER PRIMARY KEY, payload BLOB NOT NULL, sent_at REAL)"
        )
        self.db.execute("CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value)")
        self.dropped = int(self._meta("dropped", 0))

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
            row = self.db.execute("SELECT max(seq) FROM outbox").fetchone()
            return max(int(self._meta("last_seq", 0)), row[0] or 0)

    def add(self, seq: int, payload: bytes) -> None:
        with self.lock:
            self.db.execute("BEGIN")
            self.db.execute("INSERT OR REPLACE INTO outbox(seq, payload, sent_at) VALUES(?, ?, NULL)", (seq, payload))
            self._set_meta("last_seq", max(seq, int(self._meta("last_seq", 0))))
            over = self.db.execute("SELECT count(*) FROM outbox").fetchone()[0] - self.max_windows
            if over > 0:
                self.db.execute(
                    "DELETE FROM outbox WHERE seq IN (SELECT seq FROM outbox ORDER BY seq LIMIT ?)", (over,)
                )
                self.dropped += over
                self._set_meta("dropped", self.dropped)
            self.db.execute("COMMIT")

    def confirm_through(self, seq: int) -> int:
        """The service has every window up to seq: forget them. Returns how many were removed."""
        with self.lock:
            return self.db.execute("DELETE FROM outbox WHERE seq <= ?", (seq,)).rowcount

    def pending(self, *, sent_before: float | None = None, limit: int = 500) -> list[tuple[int, bytes]]:
        """Windows not yet confirmed, oldest first; with sent_before, only those never sent or sent earlier."""
        with self.lock:
            if sent_before is None:
                rows = self.db.execute("SELECT seq, payload FROM outbox ORDER BY seq LIMIT ?", (limit,))
            else:
                rows = self.db.execute(
                    "SELECT seq, payload FROM outbox WHERE sent_at IS NULL OR sent_at < ? ORDER BY seq LIMIT ?",
                    (sent_before, limit),
                )
            return [(int(s), bytes(p)) for s, p in rows.fetchall()]

    def mark_sent(self, seqs: list[int], at: float) -> None:
        with self.lock:
            self.db.executemany("UPDATE outbox SET sent_at = ? WHERE seq = ?", [(at, s) for s in seqs])

    def __len__(self) -> int:
        with self.lock:
            return self.db.execute("SELECT count(*) FROM outbox").fetchone()[0]

    def close(self) -> None:
        with self.lock:
            self.db.close()
