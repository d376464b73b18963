"""A throwaway PostgreSQL server from the machine's own binaries (initdb into a temp dir, a free loopback port):
for the tests and `encoder-fleet bench-scale` when no server is given. Not for production: trust auth, fsync off."""

from __future__ import annotations

import glob
import os
import shutil
import subprocess
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from fleet_wire.session import free_port


class NoPostgres(RuntimeError):
    """What is missing to start one (said in one line)."""


def postgres_bindir() -> Path | None:
    found = shutil.which("initdb")
    if found:
        return Path(found).parent
    versions = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"))
    return Path(versions[-1]).parent if versions else None


@contextmanager
def throwaway_postgres(*, fsync: bool = False, max_connections: int = 200) -> Iterator[str]:
    """Start a server, yield its admin URL (postgresql://fleet@127.0.0.1:PORT/postgres), stop and delete it. As root
    it runs as the `postgres` system user, as PostgreSQL requires. NoPostgres when it cannot be started here."""
    bindir = postgres_bindir()
    if bindir is None:
        raise NoPostgres("no PostgreSQL server binaries (initdb, pg_ctl) on this machine")
    folder = tempfile.mkdtemp(prefix="encoder-fleet-pg-")
    as_user = []
    if os.geteuid() == 0:
        import pwd

        try:
            pwd.getpwnam("postgres")
        except KeyError:
            shutil.rmtree(folder, ignore_errors=True)
            raise NoPostgres("running as root with no `postgres` user to run the PostgreSQL server as") from None
        shutil.chown(folder, "postgres", "postgres")
        as_user = ["runuser", "-u", "postgres", "--"]
    data, port = os.path.join(folder, "data"), free_port()

    def run(*cmd):
        subprocess.run([*as_user, *cmd], check=True, capture_output=True, timeout=120)

    try:
        run(str(bindir / "initdb"), "-D", data, "-U", "fleet", "--auth=trust", "-E", "UTF8", "--no-instructions")
        options = (
            f"-p {port} -k {folder} -c listen_addresses=127.0.0.1 -c fsync={'on' if fsync else 'off'}"
            f" -c max_connections={max_connections}"
        )
        run(str(bindir / "pg_ctl"), "-D", data, "-o", options, "-l", os.path.join(folder, "log"), "-w", "start")
    except BaseException:
        shutil.rmtree(folder, ignore_errors=True)
        raise
    try:
        yield f"postgresql://fleet@127.0.0.1:{port}/postgres"
    finally:
        run(str(bindir / "pg_ctl"), "-D", data, "-m", "immediate", "stop")
        shutil.rmtree(folder, ignore_errors=True)
