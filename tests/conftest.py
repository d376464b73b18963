"""Fixtures shared by the test modules: the fleet's PKI, made once per test session."""

from __future__ import annotations

import pytest

# every device a secured test starts; the registry (and so the router's ACL) is these certificates
DEVICES = ["drive-a", "drive-b", "drive-c", "drive-t"] + [f"drive-{i}" for i in range(10)]


def make_pki(path, devices):
    from encoder_fleet.pki import init_ca, issue
    from fleet_wire.security import ROLE_SERVICE, SERVICE_NAME

    init_ca(path)
    issue(path, SERVICE_NAME, ROLE_SERVICE)
    for device in devices:
        issue(path, device)
    return path


@pytest.fixture(scope="session")
def pki(tmp_path_factory):
    """A CA, the service (certificate and signing key) and a certificate for each of DEVICES."""
    return make_pki(tmp_path_factory.mktemp("pki"), DEVICES)


@pytest.fixture(scope="session")
def foreign_pki(tmp_path_factory):
    """Another CA with the same names: what an attacker can make for themselves."""
    return make_pki(tmp_path_factory.mktemp("foreign-pki"), ["drive-a", "drive-b"])


# --- a throwaway PostgreSQL (issue 13): the machine's own server binaries, initdb into a temp dir ----------


def _postgres_bindir():
    import glob
    import shutil
    from pathlib import Path

    found = shutil.which("initdb")
    if found:
        return Path(found).parent
    versions = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"))
    return Path(versions[-1]).parent if versions else None


@pytest.fixture(scope="session")
def postgres_server():
    """A PostgreSQL server on a free loopback port for the session (fsync off: tests, not durability); as
    root it runs as the `postgres` system user, as PostgreSQL requires. Yields the admin URL."""
    import os
    import shutil
    import subprocess
    import tempfile

    from fleet_wire.session import free_port

    bindir = _postgres_bindir()
    if bindir is None:
        pytest.skip("no PostgreSQL server binaries (initdb, pg_ctl) on this machine")
    pytest.importorskip("psycopg", reason="psycopg is installed by make (postgres extra)")
    folder = tempfile.mkdtemp(prefix="encoder-fleet-pg-")
    as_user = []
    if os.geteuid() == 0:
        import pwd

        try:
            pwd.getpwnam("postgres")
        except KeyError:
            pytest.skip("running as root with no `postgres` user to run the PostgreSQL server as")
        shutil.chown(folder, "postgres", "postgres")
        as_user = ["runuser", "-u", "postgres", "--"]
    data, port = os.path.join(folder, "data"), free_port()

    def run(*cmd):
        subprocess.run([*as_user, *cmd], check=True, capture_output=True, timeout=120)

    run(str(bindir / "initdb"), "-D", data, "-U", "fleet", "--auth=trust", "-E", "UTF8", "--no-instructions")
    options = f"-p {port} -k {folder} -c listen_addresses=127.0.0.1 -c fsync=off -c max_connections=200"
    run(str(bindir / "pg_ctl"), "-D", data, "-o", options, "-l", os.path.join(folder, "log"), "-w", "start")
    try:
        yield f"postgresql://fleet@127.0.0.1:{port}/postgres"
    finally:
        run(str(bindir / "pg_ctl"), "-D", data, "-m", "immediate", "stop")
        shutil.rmtree(folder, ignore_errors=True)


@pytest.fixture
def postgres_url(postgres_server):
    """A new, empty database on the session's server: postgresql://fleet@127.0.0.1:PORT/NAME."""
    import uuid

    import psycopg

    name = f"fleet_{uuid.uuid4().hex[:12]}"
    with psycopg.connect(postgres_server, autocommit=True) as admin:
        admin.execute(f"CREATE DATABASE {name}")
    return postgres_server.rsplit("/", 1)[0] + "/" + name
