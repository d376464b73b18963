"""The fleet end to end with real parts: a service (embedded Zenoh router, SQLite file) in this process,
agents in their own processes over loopback, coefficients rolled out and acknowledged."""

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
from fleet_wire import keys
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
def fleet(request, tmp_path, pki):
    """The service on SQLite, or on PostgreSQL where a test asks (parametrize "fleet", indirect)."""
    endpoint = loopback_endpoint().replace("tcp/", "tls/")
    database = getattr(request, "param", "sqlite")
    target = tmp_path / "fleet.sqlite" if database == "sqlite" else request.getfixturevalue("postgres_url")
    store = Store.open(target)
    session = open_session(listen=[endpoint], pki=pki)
    service = FleetService(store, session, refit_interval_s=0.5, **service_security(store, pki)).start()
    yield endpoint, store, service, session, pki
    service.stop()
    session.close()
    store.close()


@pytest.mark.parametrize("fleet", ["sqlite", "postgres"], indirect=True)
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
        # every fit is kept, tagged with the set it was made for
        fits = [
            (r["version"], r["adopted"])
            for r in store._rows("SELECT version, adopted FROM fits WHERE device = ?", (name,))
        ]
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
        (keys.key("drive-7", keys.STATS), b"{not json"),
        (keys.key("drive-7", keys.STATS), b'{"schema": "encoder-fleet/window/1", "seq": NaN}'),
        (keys.key("drive-7", keys.STATS), b"x" * (300 * 1024)),
        (keys.key("drive-7", keys.ACK), b'{"schema": "encoder-fleet/ack/1"}'),
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
    session.put(keys.key("drive-8", keys.STATS), wire.encode("window", forged))
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
    session.put(keys.key("drive-7", keys.STATS), wire.encode("window", replay))
    time.sleep(0.5)
    counts = store.rejection_counts()
    assert sum(counts.values()) >= 6, counts
    assert counts.get("device_mismatch") == 1 and counts.get("seq_conflict") == 1, counts
    assert store.device("drive-8") is None or store.device("drive-8")["windows"] == 0
    assert store.device("drive-7")["windows"] == 120  # nothing else affected


def test_a_staged_rollout_reaches_real_agents_and_soaks_on_their_windows(fleet, tmp_path):
    """The rollout controller on the service's own refit thread, with agents in their own processes over TLS:
    each agent applies the rollout's signed set, labels its windows with it, and the soak counts those."""
    endpoint, store, service, session, pki = fleet
    names = ["drive-1", "drive-2"]
    agents = [
        subprocess.Popen(
            [sys.executable, "-m", "encoder_fleet.cli", "agent", "--device", name, "--seed", str(i),
             "--connect", endpoint, "--sim-hours", "16", "--real-time-factor", "1800",
             "--outbox", str(tmp_path / f"ob{i}.sqlite"), "--pki", str(pki)],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        )
        for i, name in enumerate(names, start=1)
    ]  # fmt: skip
    try:
        deadline = time.monotonic() + 60
        while not all(store.device(n) and store.device(n)["windows"] >= 60 for n in names):
            assert time.monotonic() < deadline, "the agents' first hour never arrived"
            time.sleep(0.2)
        spec = {"name": "back to the bench", "change": {"kind": "reset_to_factory"}, "base_per_minute": 2}
        spec |= {"soak_windows": 20, "timeout_s": 25.0}
        created = TestClient(create_app(store, service)).post("/rollouts", json=spec)
        assert created.status_code == 201, created.text
        deadline = time.monotonic() + 40
        while service.rollouts.get(1)["state"] == "running":
            assert time.monotonic() < deadline, service.rollouts.get(1)
            time.sleep(0.2)
    finally:
        outputs = [a.communicate(timeout=120)[0] for a in agents]
    assert all(a.returncode == 0 for a in agents), outputs
    result = service.rollouts.get(1)
    assert result["state"] in ("completed", "aborted"), result
    for part in result["devices"]:
        device, version = part["device"], part["version"]
        assert part["state"] in ("succeeded", "unchanged", "regressed"), part  # no timeout: the agents answered
        if version is None:
            continue
        acks = {(a["version"], a["status"]) for a in store.acks(device)}
        assert (version, "applied") in acks, (part, acks)  # the agent took the rollout's signed set
        soaked = [w for w in store.windows(device) if w["coefficients_version"] == version]
        assert len(soaked) >= 20, part  # and ran it for the soak, as its windows say
        if part["state"] == "regressed":  # rolled back: the agent applied the set before again
            rollback = [
                h["version"] for h in store.coefficient_history(device)
                if h["basis"] == "rollback" and h["version"] > version
                and h["message"]["restores_version"] == part["before_version"]
            ]  # fmt: skip
            assert rollback and (rollback[-1], "applied") in acks, (part, acks)
