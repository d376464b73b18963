"""Kill the service mid-stream (SIGKILL, its own process) and restart it on the same port and database:
no window it had stored is lost, none is stored twice, and the agents catch up from their outboxes."""

import sqlite3
import subprocess
import sys
import time

import pytest

from fleet_wire.session import loopback_endpoint
from service.store import Store

HOURS = 6
WINDOWS = HOURS * 60


def start_service(db, endpoint, pki, token_folder):
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "encoder_fleet.cli",
            "service",
            "--db",
            str(db),
            "--listen",
            endpoint,
            "--http-port",
            "0",
            "--refit-interval",
            "1",
            "--pki",  # TLS, the ACL of the registry, signed sets (tests/conftest.py)
            str(pki),
            "--admin-token-file",
            str(token_folder / "admin-token"),
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    ready = proc.stdout.readline()
    assert ready.startswith("service:"), ready
    return proc


def start_agent(name, seed, endpoint, outbox, pki):
    # 1800x real time: 360 windows in about 12 s, so the outage falls in the middle of the stream
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "encoder_fleet.cli",
            "agent",
            "--device",
            name,
            "--seed",
            str(seed),
            "--connect",
            endpoint,
            "--sim-hours",
            str(HOURS),
            "--real-time-factor",
            "1800",
            "--outbox",
            str(outbox),
            "--pki",
            str(pki),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


def stored_seqs(db, device):
    """What the database holds, read from outside the service (another connection)."""
    if str(db).startswith("postgresql://"):
        import psycopg

        with psycopg.connect(str(db)) as conn:
            rows = conn.execute("SELECT seq FROM windows WHERE device = %s ORDER BY seq", (device,)).fetchall()
        return [r[0] for r in rows]
    conn = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
    try:
        return [r[0] for r in conn.execute("SELECT seq FROM windows WHERE device = ? ORDER BY seq", (device,))]
    finally:
        conn.close()


@pytest.mark.parametrize("database", ["sqlite", "postgres"])
def test_service_killed_mid_stream_loses_nothing(tmp_path, pki, database, request):
    endpoint = loopback_endpoint().replace("tcp/", "tls/")
    db = tmp_path / "fleet.sqlite" if database == "sqlite" else request.getfixturevalue("postgres_url")
    names = ["drive-a", "drive-b"]
    service = start_service(db, endpoint, pki, tmp_path)
    agents = [start_agent(n, i, endpoint, tmp_path / f"{n}.outbox", pki) for i, n in enumerate(names)]
    try:
        deadline = time.monotonic() + 60
        while min(len(stored_seqs(db, n)) for n in names) < 20 and time.monotonic() < deadline:
            time.sleep(0.1)  # mid-stream: both agents have windows stored, and more to send
        service.kill()  # no chance to flush or say goodbye
        service.wait()
        before = {n: stored_seqs(db, n) for n in names}
        assert all(0 < len(s) < WINDOWS for s in before.values()), {n: len(s) for n, s in before.items()}
        time.sleep(3)  # the agents keep correcting and buffering while the service is gone
        service = start_service(db, endpoint, pki, tmp_path)
        outputs = [a.communicate(timeout=180)[0] for a in agents]
        assert all(a.returncode == 0 for a in agents), outputs
    finally:
        for a in agents:
            if a.poll() is None:
                a.kill()
        service.terminate()
        service.wait(timeout=30)
    store = Store.open(db)
    try:
        for n in names:
            after = stored_seqs(db, n)
            assert after == list(range(1, WINDOWS + 1))  # all of them, once each, nothing lost
            assert set(before[n]) <= set(after)
            assert store.contiguous_seq(n) == WINDOWS
    finally:
        store.close()
    assert any("resent" in out and " 0 resent" not in out for out in outputs), outputs  # the catch-up happened


def test_agent_started_before_the_router_buffers_and_delivers_when_it_appears(tmp_path, pki):
    """The agent CLI with no router and no service: it starts, keeps correcting into its outbox (no
    traceback, no exit), connects through Zenoh's own retry when the service's router appears, and ends
    with every window stored once and its usual summary line."""
    endpoint = loopback_endpoint().replace("tcp/", "tls/")
    db = tmp_path / "fleet.sqlite"
    agent = start_agent("drive-a", 0, endpoint, tmp_path / "drive-a.outbox", pki)
    service = None
    try:
        time.sleep(4)  # a third of its stream, with nobody to hear it
        assert agent.poll() is None, agent.communicate()[0]
        service = start_service(db, endpoint, pki, tmp_path)
        output = agent.communicate(timeout=180)[0]
        assert agent.returncode == 0, output
    finally:
        if agent.poll() is None:
            agent.kill()
        if service is not None:
            service.terminate()
            service.wait(timeout=30)
    assert stored_seqs(db, "drive-a") == list(range(1, WINDOWS + 1))
    summary = [line for line in output.splitlines() if line.startswith("drive-a: ")]
    assert summary and summary[0].startswith(f"drive-a: {WINDOWS} windows"), output
    assert "Traceback" not in output
