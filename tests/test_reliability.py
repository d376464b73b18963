"""Faults a plant has, on a real router and a real database file: hostile messages among good ones, an
agent whose clock jumps or restarts at 0, an agent started before any router, acks the service missed,
liveliness tokens from nobody, a peer that floods."""

from __future__ import annotations

import json
import time

import pytest
import zenoh

import tests.wire_samples as ws
from edge_agent.agent import EdgeAgent, factory_message
from edge_agent.outbox import Outbox
from edge_agent.sources import SimulatedDrive, drive_model, factory_calibration
from fleet_wire import keys
from fleet_wire import messages as wire
from fleet_wire.session import agent_session_config, loopback_endpoint, session_config
from service.runtime import PUMP_CAPACITY, FleetService, PumpedSubscriber, open_session
from service.store import Store

DEVICE, SEED = "drive-t", 4


def wait_for(predicate, timeout=30.0):
    deadline = time.monotonic() + timeout
    while not predicate() and time.monotonic() < deadline:
        time.sleep(0.05)
    return predicate()


class Fleet:
    """A router with the service in it, on a real database file; started and stopped at will."""

    def __init__(self, tmp_path, **service_options):
        self.endpoint = loopback_endpoint()
        self.db = tmp_path / "fleet.sqlite"
        self.options = service_options
        self.router = self.store = self.service = None

    def start(self) -> Fleet:
        self.store = Store.open(self.db)
        self.router = open_session(listen=[self.endpoint])
        self.service = FleetService(self.store, self.router, refit_interval_s=0, **self.options).start()
        return self

    def stop(self) -> None:
        if self.service is not None:
            self.service.stop()
            self.router.close()
            self.store.close()
        self.router = self.store = self.service = None

    def seqs(self, device=DEVICE) -> list[int]:
        return [w["seq"] for w in self.store.windows(device, limit=100_000)]


@pytest.fixture
def fleet(tmp_path):
    f = Fleet(tmp_path)
    yield f
    f.stop()


def agent_for(session, outbox_path, *, hours=1.0, clock=time.monotonic) -> EdgeAgent:
    factory = factory_calibration(drive_model(SEED), SEED)
    return EdgeAgent(
        DEVICE, SimulatedDrive(SEED, hours=hours), session, Outbox(outbox_path), factory, clock=clock, resend_after_s=1
    )


# --- one message is judged alone ------------------------------------------------------------------


def deep_json(depth: int) -> bytes:
    return b'{"device":"drive-001","x":' + b"[" * depth + b"]" * depth + b"}"


def test_hostile_messages_are_refused_alone_and_counted(fleet):
    fleet.start()
    client = zenoh.open(session_config("client", connect=[fleet.endpoint]))
    huge_version = json.dumps({**ws.ack(version=1), "version": 2**70}).encode()
    # MessagePack cannot carry 2**70; JSON windows (older agents) can
    huge_rejected = json.dumps(
        {**json.loads(wire.encode_json("window", ws.window(seq=41))), "rejected": 2**70}
    ).encode()
    deep_msgpack = b"\x82\xa6device\xa9drive-001\xa5stats" + b"\x91" * 5000 + b"\xc0"
    hostile = [
        ("ack", huge_version),
        ("stats", huge_rejected),
        ("ack", deep_json(1500)),
        ("stats", deep_json(1500)),
        ("stats", deep_msgpack),
    ]
    try:
        for seq in range(1, 41):
            client.put(keys.key("drive-001", keys.STATS), wire.encode("window", ws.window(seq=seq)))
            if seq % 8 == 0:
                client.put(keys.key("drive-001", keys.ACK), wire.encode("ack", ws.ack(version=seq // 8, at=60.0 * seq)))
                suffix, payload = hostile[seq // 8 - 1]
                client.put(keys.key("drive-001", suffix), payload)
        expected = {"schema": 2, "too_deep": 3}
        assert wait_for(lambda: fleet.store.rejection_counts() == expected), fleet.store.rejection_counts()
        assert wait_for(lambda: fleet.seqs("drive-001") == list(range(1, 41)))
        assert [a["version"] for a in fleet.store.acks("drive-001")] == [1, 2, 3, 4, 5]
        assert {k: fleet.service.counters.ingested.get(k) for k in expected} == expected
    finally:
        client.close()


# --- the agent's clocks ---------------------------------------------------------------------------


def test_agent_started_before_any_router_buffers_and_resends_after_its_clock_jumps_back(fleet, tmp_path):
    """No router when the agent starts: it opens, buffers 20 windows, then its monotonic clock jumps back a
    day (as after a reboot that kept the process's notion of sends). The service appears: every window
    arrives exactly once, and the factory set is announced."""
    now, jumped_at = [1e6], [None]

    def clock() -> float:  # stepped by hand until the jump, then running in real time, as after a reboot (a clock
        # frozen there would never let a send lost while the service was still subscribing come due again)
        return now[0] if jumped_at[0] is None else now[0] + time.monotonic() - jumped_at[0]

    agent = agent_for(zenoh.open(agent_session_config([fleet.endpoint])), tmp_path / "outbox.sqlite", clock=clock)
    agent.start()
    for _ in range(20):
        assert agent.step()
        now[0] += 60.0
    assert len(agent.outbox) == 20 and agent.counters.offline_syncs == 20
    now[0] -= 86400.0  # the clock jumps back: every send time is now "in the future"
    jumped_at[0] = time.monotonic()
    fleet.start()
    try:
        counters = agent.run()
        assert agent.drain() and len(agent.outbox) == 0
        assert counters.windows == 60
        assert wait_for(lambda: fleet.seqs() == list(range(1, 61))), fleet.seqs()
        assert fleet.store.current_coefficients(DEVICE) is not None  # the factory set, announced late
        assert fleet.store.rejection_counts() == {}
    finally:
        agent.close()
        agent.session.close()


def test_a_restarted_drive_clock_is_continued_and_a_backwards_window_is_refused(fleet, tmp_path):
    fleet.start()
    session = zenoh.open(agent_session_config([fleet.endpoint]))
    try:
        first = agent_for(session, tmp_path / "outbox.sqlite", hours=0.5)
        first.start()
        first.run()
        first.close()
        first.outbox.close()
        again = agent_for(session, tmp_path / "outbox.sqlite", hours=0.5)  # the drive's clock starts at 0 again
        again.start()
        again.run()
        again.close()
        assert wait_for(lambda: fleet.seqs() == list(range(1, 61)))
        windows = fleet.store.windows(DEVICE, limit=1000)
        ends = [w["window_end"] for w in windows]
        assert all(b["window_start"] > a["window_end"] for a, b in zip(windows, windows[1:])), "time stored twice"
        assert ends[-1] > 3600.0 - 60
        # a window from a drive that did reset its clock is refused as such, and nothing else is touched
        stale = ws.window(DEVICE, seq=61, start=120.0)
        assert fleet.store.ingest(keys.key(DEVICE, keys.STATS), wire.encode("window", stale)) == "clock_backwards"
        assert fleet.seqs() == list(range(1, 61))
        assert "went back" in fleet.store.dead_letters(1)[0]["detail"]
    finally:
        session.close()


# --- acks, at least once --------------------------------------------------------------------------


def test_an_ack_the_service_missed_is_resent_until_stored(fleet, tmp_path):
    fleet.start()
    session = zenoh.open(agent_session_config([fleet.endpoint]))
    agent = agent_for(session, tmp_path / "outbox.sqlite")
    try:
        agent.start()
        assert wait_for(lambda: fleet.store.current_coefficients(DEVICE) is not None)
        fleet.service.stop()  # the service goes; its router stays: what is put now reaches nobody
        v1 = {**factory_message(DEVICE, agent.factory), "version": 1, "basis": "fit", "created_at": 60.0}
        fleet.store.insert_coefficient_set(v1)
        fleet.store.mark_published(DEVICE, 1)
        fleet.router.put(keys.key(DEVICE, keys.COEFFICIENTS), wire.encode("coefficients", v1))
        assert wait_for(lambda: agent.inbox.qsize() == 1)
        assert agent.step()  # applies version 1 and acknowledges it into the void
        assert agent.version == 1 and agent.outbox.pending_acks() == [1]
        assert fleet.store.acks(DEVICE) == []
        fleet.service = FleetService(fleet.store, fleet.router, refit_interval_s=0).start()
        time.sleep(1.1)  # the ack's resend is due
        assert agent.step()
        assert wait_for(lambda: [a["version"] for a in fleet.store.acks(DEVICE)] == [1])
        assert agent.sync() and agent.outbox.pending_acks() == []  # the watermark confirmed it
        for _ in range(3):  # and it is not sent again
            time.sleep(1.1)
            agent.step()
        assert len(fleet.store.acks(DEVICE)) == 1
        assert fleet.store.device(DEVICE)["current_version"] == 1
    finally:
        agent.close()
        session.close()


# --- devices come from messages, not tokens -------------------------------------------------------


def test_liveliness_tokens_alone_make_no_devices(fleet):
    fleet.start()
    client = zenoh.open(session_config("client", connect=[fleet.endpoint]))
    tokens = [client.liveliness().declare_token(keys.key(f"ghost-{i}", keys.ALIVE)) for i in range(50)]
    tokens.append(client.liveliness().declare_token(keys.key("drive-001", keys.ALIVE)))
    try:
        time.sleep(1.0)
        assert fleet.store.devices() == []
        client.put(keys.key("drive-001", keys.STATS), wire.encode("window", ws.window(seq=1)))
        assert wait_for(lambda: [d["id"] for d in fleet.store.devices()] == ["drive-001"])
        assert wait_for(lambda: fleet.store.device("drive-001")["online"] is True)
    finally:
        for token in tokens:
            token.undeclare()
        client.close()


def test_a_drive_that_left_while_the_service_was_down_is_offline_once_it_is_back(tmp_path):
    """Two drives online; the service (and its router) down; one drive's agent stops meanwhile. Nobody heard its
    token go, and the tokens replayed at the next start name only the drive still there: the drive that left stayed
    online and ok for good (a second reader). Now, ONLINE_RECHECK_S after the start, a device stored online with no
    token is offline, with its alarm; the drive whose agent reconnected stays online, with none."""
    fleet = Fleet(tmp_path, online_recheck_s=2.0)
    fleet.start()
    client = zenoh.open(agent_session_config([fleet.endpoint]))  # an agent's session: it reconnects by itself
    tokens = {d: client.liveliness().declare_token(keys.key(d, keys.ALIVE)) for d in ("drive-001", "drive-002")}
    try:
        for d in tokens:
            client.put(keys.key(d, keys.STATS), wire.encode("window", ws.window(d, seq=1)))
        assert wait_for(lambda: all(fleet.store.device(d) and fleet.store.device(d)["online"] for d in tokens))
        fleet.stop()
        tokens.pop("drive-001").undeclare()  # its agent stops while nobody listens
        fleet.start()
        assert wait_for(lambda: fleet.store.device("drive-001")["online"] is False, timeout=20)
        (alarm,) = fleet.store.alarms("drive-001", open_=True)
        assert alarm["cause"] == "offline"
        time.sleep(1.0)  # the recheck is done; the drive still there was not taken for gone
        assert fleet.store.device("drive-002")["online"] is True and fleet.store.alarms("drive-002", open_=True) == []
    finally:
        for token in tokens.values():
            token.undeclare()
        client.close()
        fleet.stop()


def test_a_device_marked_online_late_survives_a_database_error_and_the_writer_goes_on(fleet, monkeypatch):
    """A token seen before the device's first window marks it online once that window is stored. A database error
    there killed the writer thread: nothing was stored after it. Now it is logged and retried with the next window."""
    import sqlite3

    fleet.start()
    client = zenoh.open(session_config("client", connect=[fleet.endpoint]))
    token = client.liveliness().declare_token(keys.key("drive-001", keys.ALIVE))
    real, calls = fleet.store.set_online, []

    def full_once(device, online, at=None):  # the disk is full for this one write
        calls.append((device, online))
        if len(calls) == 1:
            raise sqlite3.OperationalError("database or disk is full")
        real(device, online, at)

    monkeypatch.setattr(fleet.store, "set_online", full_once)
    try:
        assert wait_for(lambda: "drive-001" in fleet.service._alive_unknown)
        client.put(keys.key("drive-001", keys.STATS), wire.encode("window", ws.window(seq=1)))
        assert wait_for(lambda: len(calls) == 1) and fleet.store.device("drive-001")["online"] is False
        for seq in (2, 3):
            client.put(keys.key("drive-001", keys.STATS), wire.encode("window", ws.window(seq=seq)))
        assert wait_for(lambda: fleet.seqs("drive-001") == [1, 2, 3])
        assert fleet.service._writer.is_alive() and calls == [("drive-001", True)] * 2  # retried once, then done
        assert fleet.store.device("drive-001")["online"] is True
    finally:
        token.undeclare()
        client.close()


# --- bounded ---------------------------------------------------------------------------------------


def test_a_flooding_key_is_rate_limited_and_the_others_are_served(tmp_path):
    fleet = Fleet(tmp_path, rate_per_key=20.0, burst_per_key=50.0).start()
    client = zenoh.open(session_config("client", connect=[fleet.endpoint]))
    try:
        payload = wire.encode("window", ws.window("drive-009", seq=1))
        started = time.monotonic()
        for _ in range(2000):  # the same window, as fast as the client can
            client.put(keys.key("drive-009", keys.STATS), payload, congestion_control=zenoh.CongestionControl.BLOCK)
        elapsed = time.monotonic() - started
        for seq in range(1, 11):
            client.put(keys.key("drive-001", keys.STATS), wire.encode("window", ws.window(seq=seq)))
        assert wait_for(lambda: fleet.seqs("drive-001") == list(range(1, 11)))
        counted = fleet.service.counters.ingested
        assert wait_for(lambda: counted.get("rate_limited", 0) + counted.get("duplicate", 0) + 1 == 2000), counted
        taken = counted.get("duplicate", 0) + 1  # what passed the limit: the burst and the rate since
        assert taken <= 50 + 20.0 * (elapsed + 1.0), (taken, elapsed)
        assert fleet.seqs("drive-009") == [1]
    finally:
        client.close()
        fleet.stop()


# --- the soak ---------------------------------------------------------------------------------------


def test_bench_soak_loses_and_doubles_nothing(tmp_path):
    """A short soak through the CLI: service, router and agents killed at random, bad messages, a full disk."""
    import subprocess
    import sys

    out = tmp_path / "soak.json"
    cmd = [sys.executable, "-m", "encoder_fleet.cli", "bench-soak", "--minutes", "0.6", "--agents", "2"]
    done = subprocess.run(
        cmd + ["--seed", "3", "--out", str(tmp_path / "soak"), "--json", str(out)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    result = json.loads(out.read_text())
    assert set(result) == {"sent", "stored", "lost", "doubled", "memory_mb"}
    assert result["sent"] > 300 and result["stored"] == result["sent"], result
    assert result["lost"] == 0 and result["doubled"] == 0
    assert len(result["memory_mb"]) > 10 and all(m > 0 for m in result["memory_mb"])
    assert "killed" in done.stdout  # faults did happen


def test_the_ingest_queue_is_bounded_when_the_writer_falls_behind(tmp_path):
    fleet = Fleet(tmp_path, max_queued=5, queue_wait_s=0.05).start()
    client = zenoh.open(session_config("client", connect=[fleet.endpoint]))
    try:
        with fleet.store._lock:  # the writer is stuck (a slow disk): nothing leaves the queue
            for seq in range(1, 51):
                client.put(
                    keys.key("drive-001", keys.STATS),
                    wire.encode("window", ws.window(seq=seq)),
                    congestion_control=zenoh.CongestionControl.BLOCK,
                )
            counted = fleet.service.counters.ingested
            assert wait_for(lambda: counted.get("overloaded", 0) >= 40, timeout=60), counted
            assert fleet.service._inbox.qsize() <= 5
        assert wait_for(lambda: len(fleet.seqs("drive-001")) + counted.get("overloaded", 0) == 50), counted
    finally:
        client.close()
        fleet.stop()


def test_a_fleet_starting_at_once_announces_its_factory_sets_and_each_is_stored_once(tmp_path):
    """Factory sets queued in a row are stored in one transaction (FleetService._on_factories): while the store is
    busy (its lock held, as by a long batch) 40 drives announce theirs, one of them malformed and one of them a
    drive the service already holds a set for. Every good one is stored as version 0 and published, the malformed one
    alone is dead-lettered with its reason, and the held set is not replaced."""
    fleet = Fleet(tmp_path).start()
    client = zenoh.open(session_config("client", connect=[fleet.endpoint]))
    names = [f"drive-{i:03d}" for i in range(40)]
    runs, store_run = [], fleet.service._on_factories

    def counted(samples):  # the real handler, its run's length noted
        runs.append(len(samples))
        store_run(samples)

    fleet.service._on_factories = counted
    held = {**ws.coefficients(names[5], 0), "basis": "factory"}
    try:
        with fleet.store.transaction():
            fleet.store.insert_coefficient_set(held)
            fleet.store.mark_published(names[5], 0)
        with fleet.store._lock:  # the control thread waits for the store: the announcements queue behind it
            for name in names:
                payload = wire.encode("coefficients", {**ws.coefficients(name, 0, bands=(1, 2)), "basis": "factory"})
                if name == names[17]:
                    payload = payload[: len(payload) // 2]  # cut short: not a message at all
                client.put(keys.key(name, keys.FACTORY), payload, congestion_control=zenoh.CongestionControl.BLOCK)
            time.sleep(0.5)
        good = [n for n in names if n != names[17]]
        assert wait_for(lambda: all(fleet.store.current_coefficients(n) is not None for n in good))
        assert fleet.store.current_coefficients(names[17]) is None
        for name in good:
            current = fleet.store.current_coefficients(name, published_only=True)
            assert current is not None and current["version"] == 0 and current["basis"] == "factory", name
            assert [b["band"] for b in current["bands"]] == ([2] if name == names[5] else [1, 2]), name
        refused = [d for d in fleet.store.dead_letters() if names[17] in d["key_expr"]]
        assert len(refused) == 1 and refused[0]["reason"] == "not_json", refused
        assert sum(runs) == len(names) and max(runs) > 1, runs  # they queued behind the busy store: runs formed
    finally:
        client.close()
        fleet.stop()


def test_a_run_of_factory_sets_the_full_disk_refuses_is_stored_whole_once_space_is_back(tmp_path):
    """The disk is full while a fleet announces its factory sets: a run the disk refuses is stored not at all (no
    set without its publication; none of the run committed apart from it, as a savepoint after SQLite ended the
    transaction would have been), the control thread goes on (it still answers the watermark query), and the
    announcements the agents make again once there is space are stored, each once."""
    fleet = Fleet(tmp_path).start()
    client = zenoh.open(session_config("client", connect=[fleet.endpoint]))
    names = [f"drive-{i:03d}" for i in range(30)]
    store = fleet.store
    runs, store_run = [], fleet.service._on_factories

    def noted(samples):  # the real handler, the drives of each run noted
        runs.append([keys.split(s.key_expr)[0] for s in samples])
        store_run(samples)

    fleet.service._on_factories = noted

    def announce():
        for name in names:
            payload = wire.encode("coefficients", {**ws.coefficients(name, 0), "basis": "factory"})
            client.put(keys.key(name, keys.FACTORY), payload, congestion_control=zenoh.CongestionControl.BLOCK)

    try:
        with store._lock:  # the disk is full: not one page more
            store._conn.execute("VACUUM")  # no free page in the file either (a migration's rebuilt table leaves some)
            pages = store._conn.execute("PRAGMA page_count").fetchone()[0]
            store._conn.execute(f"PRAGMA max_page_count = {pages}")
            announce()  # queued behind the lock: taken as runs once it is let go
        assert wait_for(lambda: fleet.service._control.empty())
        replies = [r.ok for r in client.get(keys.key(names[0], keys.RECEIVED), timeout=10) if r.ok]
        assert replies and wire.parse_watermark(replies[0].payload.to_bytes(), names[0]) == 0  # still answering
        held = {n for n in names if store.current_coefficients(n) is not None}  # what the free pages took
        assert len(held) < len(names) and sum(map(len, runs)) == len(names), (held, runs)
        assert held == {n for n in names if store.current_coefficients(n, published_only=True) is not None}
        assert all(set(run) <= held or not set(run) & held for run in runs), (held, runs)  # each run whole or not
        with store._lock:  # space is back
            store._conn.execute("PRAGMA max_page_count = 1073741823")
        announce()  # as each agent does at its next sync, having no set from the service
        assert wait_for(lambda: all(store.current_coefficients(n, published_only=True) is not None for n in names))
        rows = store._rows("SELECT device, version FROM coefficient_sets ORDER BY device")
        assert [(r["device"], r["version"]) for r in rows] == [(n, 0) for n in names]
    finally:
        client.close()
        fleet.stop()


@pytest.mark.parametrize("refused", ["restart", "move"])
def test_a_step_whose_action_the_database_refused_is_taken_up_by_the_next_refit_pass(tmp_path, refused):
    """The monitor stores an offset step, and the database refuses (an outside writer holds its lock past the busy
    timeout) either the band memory's restart that acts on it, or the refit pass's set moved for it. The alarm is
    still put; the next refit pass takes the step up again and sends the drive its set moved for the step. Before,
    a refused restart left the device waiting for a move no pass made, refitting nothing until the process
    restarted, and a refused move was dropped."""
    import contextlib
    import sqlite3

    from fleet_wire import alarms as alarm_wire

    @contextlib.contextmanager
    def locked(when: bool):
        other = sqlite3.connect(path, isolation_level=None) if when else None
        if other is not None:
            other.execute("BEGIN IMMEDIATE")
        try:
            yield
        finally:
            if other is not None:
                other.execute("ROLLBACK")
                other.close()

    path = tmp_path / "fleet.sqlite"
    store = Store.open(path)
    session = open_session(listen=[loopback_endpoint()])
    heard = []
    listener = session.declare_subscriber(keys.every(keys.ALARMS), lambda sample: heard.append(sample))
    service = FleetService(store, session, refit_interval_s=0, monitor_interval_s=0)  # passes called by the test
    try:
        # a factory set with its bench locus, as the agents announce it (a drive without one is not refit)
        factory = factory_message(DEVICE, factory_calibration(drive_model(3), 3))
        with store.transaction():
            store.insert_coefficient_set(factory)
            store.mark_published(DEVICE, 0)
            for seq in range(1, 41):
                store.insert_window(ws.window(DEVICE, seq))
        step = {"kind": "raise", "cause": "offset_step", "at": 1500.0, "parameters": {"delta_d": 0.01, "delta_q": 0.0}}
        (alarm,) = store.save_monitor(DEVICE, {}, 0, [{**step, "evidence": "a step, drawn by the test"}])
        store._conn.execute("PRAGMA busy_timeout = 50")  # the service waits 30 s; the test need not
        with locked(refused == "restart"):
            if refused == "restart":
                with pytest.raises(sqlite3.OperationalError, match="locked"):
                    service._publish_alarm(*alarm_wire.encode(alarm))  # as the monitor publishes what it stored
            else:
                service._publish_alarm(*alarm_wire.encode(alarm))
        assert wait_for(lambda: heard, timeout=10)  # the alarm went out all the same
        with locked(refused == "move"):
            if refused == "move":
                assert service.refit_all() == []  # the move refused: logged, kept for the next pass
        published = service.refit_all()
        assert len(published) == 1, published
        (newest, *_) = store.coefficient_history(DEVICE)
        assert newest["version"] == published[0] and newest["state"] == "trial", newest
        assert newest["state_reason"].startswith("offset step: v0 moved for it"), newest  # the step's move
        assert service._restarted_for[DEVICE] == alarm["raised_at"]
        assert service.fit(DEVICE) is not None  # refits go on after the step
    finally:
        listener.undeclare()
        session.close()
        store.close()


def test_the_control_thread_stops_when_the_stop_comes_behind_a_run_of_factory_sets(tmp_path):
    """The stop (None) queued right behind factory sets, as when the service stops while a fleet announces: the run
    is handled and the thread ends (it once took the stop as "nothing taken" and waited for a next job forever)."""
    store = Store.open(tmp_path / "fleet.sqlite")
    session = open_session(listen=[loopback_endpoint()])
    service = FleetService(store, session, refit_interval_s=0)  # not started: only its control thread runs
    try:
        for _ in range(5):
            service._control.put((service._on_factory, "not a sample"))  # refused, logged, the run goes on
        service._control.put(None)
        service._control_thread.start()
        service._control_thread.join(timeout=10)
        assert not service._control_thread.is_alive()
        assert service._control.empty()
    finally:
        session.close()
        store.close()


def test_analysis_waits_while_a_backlog_is_stored_but_is_never_starved(tmp_path):
    from service.runtime import STORE_FIRST_BACKLOG, STORE_FIRST_MAX_WAIT_S

    store = Store.open(tmp_path / "fleet.sqlite")
    session = open_session(listen=[loopback_endpoint()])
    service = FleetService(store, session, refit_interval_s=0)  # not started: no writer empties the inbox
    try:

        def stored(first, last):
            items = [
                (keys.key("drive-a", keys.STATS), wire.encode("window", ws.window("drive-a", s)))
                for s in range(first, last + 1)
            ]
            assert store.ingest_many(items) == ["stored"] * len(items)
            service._monitor_changed.add("drive-a")

        stored(1, 3)
        for _ in range(STORE_FIRST_BACKLOG + 1):  # a flood waiting for the writer
            service._inbox.put_nowait(("k", b"", 0.0))
        service.monitor_pass()
        waited = service.counters.analysis_waited_s
        assert STORE_FIRST_MAX_WAIT_S <= waited < 2 * STORE_FIRST_MAX_WAIT_S  # it waited, up to its bound
        assert service.monitor.last_seq["drive-a"] == 3  # and then analysed anyway

        while not service._inbox.empty():  # the writer caught up
            service._inbox.get_nowait()
        stored(4, 5)
        service.monitor_pass()
        assert service.counters.analysis_waited_s == waited  # no backlog, no wait
        assert service.monitor.last_seq["drive-a"] == 5
    finally:
        session.close()
        store.close()


def test_the_window_pump_hands_on_windows_and_acks_in_the_order_sent_past_its_channel_and_a_failing_one():
    """Windows and acks wait in one Zenoh channel for the pump's thread (PumpedSubscriber on every agent-to-service
    key): twice the channel's capacity put while the handler is slow all come through, windows and acks in the
    order sent (the store sets a device's current version from an ack and the windows before it in that order; with
    acks on a callback of their own, an ack put after 200 windows was handed on before the last two of them); a full
    channel makes Zenoh wait, it drops nothing; a sample whose handling fails is logged and the pump goes on;
    undeclaring waits until the channel is handed on. The service's own windows and acks come through one such pump
    (FleetService._declare_partition)."""
    session = open_session(listen=[loopback_endpoint()])
    handed, count = [], 2 * PUMP_CAPACITY
    sent = [(keys.ACK if value % 50 == 49 else keys.STATS, value) for value in range(count)]

    def handler(sample: zenoh.Sample) -> None:
        value = int(sample.payload.to_bytes())
        if value == 7:
            raise ValueError("a window the handler refuses")
        if value < 50:
            time.sleep(0.002)  # slow at first: the channel fills
        handed.append((keys.split(sample.key_expr)[1], value))

    pump = PumpedSubscriber(session, keys.every_to_service(), handler)
    try:
        for suffix, value in sent:
            session.put(keys.key("drive-001", suffix), str(value))
    finally:
        pump.undeclare()
        session.close()
    assert handed == [(suffix, value) for suffix, value in sent if value != 7]
