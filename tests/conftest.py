"""Fixtures shared by the test modules: the fleet's PKI, made once per test session."""

from __future__ import annotations

import logging

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


@pytest.fixture(autouse=True)
def root_logger_restored():
    """A test that runs a command in-process (`cli.main` calls `logs.configure`) leaves the root logger as it found
    it: otherwise the worker's later tests print their service warnings as JSON lines into pytest's output."""
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    yield
    root.handlers[:] = handlers
    root.setLevel(level)


@pytest.fixture(scope="session")
def pki(tmp_path_factory):
    """A CA, the service (certificate and signing key) and a certificate for each of DEVICES."""
    return make_pki(tmp_path_factory.mktemp("pki"), DEVICES)


@pytest.fixture(scope="session")
def foreign_pki(tmp_path_factory):
    """Another CA with the same names: what an attacker can make for themselves."""
    return make_pki(tmp_path_factory.mktemp("foreign-pki"), ["drive-a", "drive-b"])


# --- a throwaway PostgreSQL (issue 13): the machine's own server binaries, initdb into a temp dir ----------


@pytest.fixture(scope="session")
def postgres_server():
    """A PostgreSQL server on a free loopback port for the session (encoder_fleet/pgserver.py). Yields the admin URL."""
    from encoder_fleet.pgserver import NoPostgres, throwaway_postgres

    pytest.importorskip("psycopg", reason="psycopg is installed by make (postgres extra)")
    try:
        server = throwaway_postgres()
        url = server.__enter__()
    except NoPostgres as exc:
        pytest.skip(str(exc))
    try:
        yield url
    finally:
        server.__exit__(None, None, None)


@pytest.fixture
def postgres_url(postgres_server):
    """A new, empty database on the session's server: postgresql://fleet@127.0.0.1:PORT/NAME."""
    import uuid

    import psycopg

    name = f"fleet_{uuid.uuid4().hex[:12]}"
    with psycopg.connect(postgres_server, autocommit=True) as admin:
        admin.execute(f"CREATE DATABASE {name}")
    return postgres_server.rsplit("/", 1)[0] + "/" + name


@pytest.fixture(params=["sqlite", "postgres"])
def store(request, tmp_path):
    """A real store: a SQLite file, then a PostgreSQL database. Modules with a store of their own define `store`."""
    from service.store import Store

    target = tmp_path / "fleet.db" if request.param == "sqlite" else request.getfixturevalue("postgres_url")
    with Store.open(target) as s:
        yield s


@pytest.fixture(params=["sqlite", "postgres"])
def fleet(request, tmp_path):
    """(store, service): a real store (SQLite, then PostgreSQL) and the service on a real Zenoh session, with no
    refit timer (the tests call refit_all). Modules with a fleet of their own define `fleet` themselves."""
    from fleet_wire.session import loopback_endpoint
    from service.runtime import FleetService, open_session
    from service.store import Store

    target = tmp_path / "fleet.sqlite" if request.param == "sqlite" else request.getfixturevalue("postgres_url")
    store = Store.open(target)
    session = open_session(listen=[loopback_endpoint()])
    service = FleetService(store, session, refit_interval_s=0).start()
    yield store, service
    service.stop()
    session.close()
    store.close()
