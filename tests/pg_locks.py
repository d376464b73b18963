"""Two cluster members' transactions meeting on PostgreSQL: the wait, in a test, until the second one waits on a lock
the first holds (the moment the first then commits)."""

from __future__ import annotations

import time


def wait_for_a_lock_wait(postgres_url: str, what: str, timeout_s: float = 10.0) -> None:
    """Return once a session of the database waits on a lock; AssertionError naming `what` if none does in time."""
    import psycopg

    waiting = "SELECT count(*) FROM pg_stat_activity WHERE wait_event_type = 'Lock' AND datname = current_database()"
    with psycopg.connect(postgres_url, autocommit=True) as watch:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if watch.execute(waiting).fetchone()[0]:
                return
            time.sleep(0.01)
    raise AssertionError(f"{what} never waited on a lock")
