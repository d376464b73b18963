"""The fleet end to end with real parts: a service (embedded Zenoh router, SQLite file) in this process,
agents in their own processes over loopback, coefficients rolled out and acknowledged."""

import sqlite3
import subprocess
import sys
import time
from collections import Counter

import numpy as np
import pytest
from fastapi.testclient import TestClient
from mcap.reader import make_reader

from encoder_core.stats import WindowStats
from encoder_fleet.demo import applied_set, score
from fleet_wire import messages as wire
from fleet_wire.session import loopback_endpoint
from service.api import create_app
from service.guard import service_security
from service.runtime import FleetService, open_session
from service.store import Store


def start_agent(name, seed, endpoint, outbox, hours, pki):
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
            str(hours),
            "--outbox",
            str(outbox),
            "--pki",  # TLS with its certificate, the router's ACL, signed sets (tests/conftest.py)
            str(pki),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


@pytest.fixture
def fleet(tmp_path, pki):
    endpoint = loopback_endpoint().replace("tcp/", "tls/")
    store = Store.open(tmp_path / "fleet.sqlite")
    session = open_session(listen=[endpoint], pki=pki)
    service = FleetService(store, session, refit_interval_s=0.5, **service_security(store, pki)).start()
    yield endpoint, store, service, session, pki
    service.stop()
    session.close()
    store.close()


def test_agents_roll_out_and_beat_factory(fleet, tmp_path):
    endpoint, store, service, session, pki = fleet
    agents = [start_agent(f"drive-{i}", i, endpoint, tmp_path / f"ob{i}.sqlite", 24, pki) for i in (1, 2)]
    api = TestClient(create_app(store))
    seen_online = set()
    while any(a.poll() is None for a in agents):  # the liveliness tokens, as the REST API shows them
        seen_online |= {d["id"] for d in api.get("/devices").json() if d["online"]}
        time.sleep(0.2)
    outputs = [a.communicate(timeout=300)[0] for a in agents]
    assert all(a.returncode == 0 for a in agents), outputs
    assert seen_online == {"drive-1", "drive-2"}
    deadline = time.monotonic() + 10
    while any(d["online"] for d in api.get("/devices").json()) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(d["online"] for d in api.get("/devices").json())  # tokens gone with the agents
    for i in (1, 2):
        name = f"drive-{i}"
        assert store.device(name)["windows"] == 24 * 60  # every window stored once
        assert store.contiguous_seq(name) == 24 * 60
        applied = applied_set(store, name)
        assert applied is not None and applied["version"] >= 1, store.acks(name)
        assert applied["signature"]  # the sets the agents applied carry the service's signature
        versions = {h["version"] for h in store.coefficient_history(name) if h["basis"] == "fit"}
        with sqlite3.connect(store.path) as conn:  # every fit is kept, tagged with the set it was made for
            fits = conn.execute("SELECT version, adopted FROM fits WHERE device = ?", (name,)).fetchall()
        assert {v for v, _ in fits} == versions and any(a for _, a in fits)
        result = score(i, applied["bands"])
        assert result["rms_error_deg_fleet"] * 5 < result["rms_error_deg_factory"], result
    assert not any(k for k in store.rejection_counts())
    # the audit export, as a user runs it, read back with the mcap reader
    out = tmp_path / "drive-1.mcap"
    res = subprocess.run(
        [
            sys.executable,
            "-m",
            "encoder_fleet.cli",
            "export",
            "--db",
            str(store.path),
            "--device",
            "drive-1",
            "--out",
            str(out),
        ],
        capture_output=True,
        text=True,
    )
    assert res.returncode == 0, res.stderr
    with open(out, "rb") as f:
        topics = Counter(channel.topic for _, channel, _ in make_reader(f).iter_messages())
    assert topics["/encoders/drive-1/stats"] == 24 * 60
    assert topics["/encoders/drive-1/coefficients"] == len(store.coefficient_history("drive-1"))
    assert topics["/encoders/drive-1/ack"] == len(store.acks("drive-1"))


def test_bad_messages_are_counted_and_harmless(fleet, tmp_path):
    endpoint, store, service, session, pki = fleet
    agent = start_agent("drive-7", 7, endpoint, tmp_path / "ob7.sqlite", 2, pki)
    bad = [
        ("encoders/drive-7/stats", b"{not json"),
        ("encoders/drive-7/stats", b'{"schema": "encoder-fleet/window/1", "seq": NaN}'),
        ("encoders/drive-7/stats", b"x" * (300 * 1024)),
        ("encoders/drive-7/ack", b'{"schema": "encoder-fleet/ack/1"}'),
    ]
    for key, payload in bad:
        session.put(key, payload)
    assert agent.wait(timeout=120) == 0
    time.sleep(0.5)
    # drive-7's next window, published under drive-8's key, and drive-7's first window again with new content
    stats = WindowStats(scale=1400.0).add(np.full(50, 1000.0), np.linspace(-900, 900, 50), np.full(50, 25.0))
    forged = wire.window_message(
        "drive-7",
        121,
        stats,
        window_start=1e4,
        window_end=1e4 + 60,
        temp_rate_c_per_s=0.0,
        coefficients_version=0,
        angle_quality_deg=0.1,
    )
    session.put("encoders/drive-8/stats", wire.encode("window", forged))
    replay = wire.window_message(
        "drive-7",
        1,
        stats,
        window_start=0.0,
        window_end=60.0,
        temp_rate_c_per_s=0.0,
        coefficients_version=0,
        angle_quality_deg=0.1,
    )
    session.put("encoders/drive-7/stats", wire.encode("window", replay))
    time.sleep(0.5)
    counts = store.rejection_counts()
    assert sum(counts.values()) >= 6, counts
    assert counts.get("device_mismatch") == 1 and counts.get("seq_conflict") == 1, counts
    assert store.device("drive-8") is None or store.device("drive-8")["windows"] == 0
    assert store.device("drive-7")["windows"] == 120  # nothing else affected
