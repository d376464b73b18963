"""Retiring a drive (replaced, scrapped): out of the fleet's counts, alarms, refits and rollouts, its history kept, and
what it still sends kept as dead letters until it is reinstated. Real stores (SQLite, PostgreSQL), the real REST app,
the real service on a Zenoh session, the command in its own process."""

import json
import subprocess
import sys
import threading

import pytest
from fastapi.testclient import TestClient
from operator_cli import operator_cli
from prometheus_client.parser import text_string_to_metric_families
from test_guard import DEVICE, v2_on_trial_after_v1_ran
from wire_samples import window

from fleet_wire import keys
from fleet_wire import messages as wire
from service.api import create_app
from service.auth import TokenAuth
from service.rollout import RolloutError, Rollouts, RolloutSpec
from service.store import RETIRED_LETTER_EVERY_S, Store, StoreError

RESET = {"change": {"kind": "reset_to_factory"}, "base_per_minute": 10, "soak_windows": 5}


def offline_alarm(store, device: str, at: float) -> int:
    (alarm,) = store.save_monitor(
        device, {}, 0, [{"kind": "raise", "cause": "offline", "at": at, "parameters": {"since": at}, "evidence": "x"}]
    )
    return alarm["id"]


def three_drives(store) -> None:
    """drive-001 online, drive-002 and drive-003 offline with an offline alarm each."""
    for seq, name in enumerate(("drive-001", "drive-002", "drive-003"), start=1):
        store.insert_window(window(name, 1), received_at=1000.0 + seq)
    store.set_online("drive-001", True, at=1010.0)
    offline_alarm(store, "drive-002", 60.0)
    offline_alarm(store, "drive-003", 60.0)


def test_a_retired_drive_leaves_the_fleets_counts_and_keeps_its_history(store):
    three_drives(store)
    assert store.device_counts() == {"online": 1, "offline": 2, "retired": 0}
    got = store.retire_device("drive-003", by="token 1 (ops)", note="replaced by drive-004", at=2000.0)
    assert got["retired"] == {"at": 2000.0, "by": "token 1 (ops)", "note": "replaced by drive-004"}
    assert store.device_counts() == {"online": 1, "offline": 1, "retired": 1}
    assert store.open_alarm_counts() == {"offline": 1}  # drive-003's alarm stays, out of the fleet's count
    assert [a["device"] for a in store.alarms(open_=True)] == ["drive-003", "drive-002"]  # its history
    assert [a["device"] for a in store.alarms(open_=True, in_fleet=True)] == ["drive-002"]
    assert [a["device"] for a in store.alarms(open_=True, in_fleet=False)] == ["drive-003"]
    assert store.device_ids(in_fleet=True) == ["drive-001", "drive-002"]
    assert store.retired_device_ids() == {"drive-003"}
    assert store.device("drive-003")["windows"] == 1  # nothing of it deleted

    with pytest.raises(StoreError, match="retired by token 1 \\(ops\\): replaced") as refused:
        store.retire_device("drive-003", by="token 2", note="again")
    assert refused.value.reason == "already_retired"
    with pytest.raises(KeyError):
        store.retire_device("drive-999", by="token 1", note="no such drive")
    with pytest.raises(StoreError) as refused:
        store.reinstate_device("drive-002", by="token 1", note="it never left")
    assert refused.value.reason == "not_retired"

    back = store.reinstate_device("drive-003", by="token 2 (night)", note="mounted again", at=3000.0)
    assert back["retired"] is None and store.device_counts() == {"online": 1, "offline": 2, "retired": 0}
    store.retire_device("drive-003", by="token 1 (ops)", note="scrapped", at=4000.0)
    history = store.retirements("drive-003")
    assert [(r["note"], r["reinstate_note"]) for r in history] == [
        ("replaced by drive-004", "mounted again"),
        ("scrapped", None),
    ]
    assert history[0]["reinstated_at"] == 3000.0 and history[0]["reinstated_by"] == "token 2 (night)"


def test_a_silent_retired_drive_is_not_named_silent(store):
    store.insert_window(window("drive-001", 1), received_at=1000.0)
    store.set_online("drive-001", True, at=1000.0)
    assert store.silent_devices(1800.0, now=10_000.0) == ["drive-001"]
    store.retire_device("drive-001", by="token 1", note="on the scrap pile, its agent still running")
    assert store.silent_devices(1800.0, now=10_000.0) == []


def test_what_a_retired_drive_sends_is_kept_as_dead_letters_and_stored_once_it_is_reinstated(store):
    store.insert_window(window("drive-001", 1))
    store.insert_window(window("drive-002", 1))
    store.retire_device("drive-001", by="token 1", note="replaced")
    late = [(keys.key(name, keys.STATS), wire.encode("window", window(name, 2))) for name in ("drive-001", "drive-002")]
    assert store.ingest_many(late, received_at=5000.0) == ["device_retired", "stored"]  # the other drive is stored
    (letter,) = store.dead_letters()
    assert letter["reason"] == "device_retired" and "POST /devices/drive-001/reinstate" in letter["detail"]
    # its agent, still running, resends its outbox every few seconds: one dead letter an hour, the rest counted
    resent = [late[0]] + [(late[0][0], wire.encode("window", window("drive-001", seq))) for seq in (3, 4)]
    assert store.ingest_many(resent, received_at=5002.0) == ["device_retired"] * 3
    assert len(store.dead_letters()) == 1
    assert store.ingest_many(late[:1], received_at=5000.0 + RETIRED_LETTER_EVERY_S) == ["device_retired"]
    assert len(store.dead_letters()) == 2
    assert store.max_seq("drive-001") == 1
    store.reinstate_device("drive-001", by="token 1", note="it was not replaced after all")
    assert store.ingest_many(late[:1]) == ["stored"]  # the agent sends it again: its watermark never moved
    assert store.max_seq("drive-001") == 2


def test_a_watermark_question_while_a_retirement_commits_leaves_this_writer_no_stale_list(tmp_path):
    """The watermark question reads the retired drives outside the writer's lock (the read pool). Asked while the
    retirement committed, it read the drive in the fleet still and kept that for RETIRED_READ_EVERY_S: this process
    stored the retired drive's windows and told its agent to send them for 5 s (and refused a reinstated one's). The
    list is marked stale once the change is committed, before the writer's next batch. Asked here at the COMMIT."""
    with Store.open(tmp_path / "fleet.db") as store:
        store.insert_window(window("drive-001", 1))
        assert not store.is_retired("drive-001")  # a question before: the list read
        heard = []

        def ask_at_commit(sql: str) -> None:
            if sql == "COMMIT":  # the question in another thread, as Zenoh's query handler asks it
                asker = threading.Thread(target=lambda: heard.append(store.is_retired("drive-001")))
                asker.start()
                asker.join()

        store._conn.set_trace_callback(ask_at_commit)
        store.retire_device("drive-001", by="token 1", note="replaced")
        store._conn.set_trace_callback(None)
        assert heard == [False]  # read before the commit
        assert store.is_retired("drive-001")
        later = (keys.key("drive-001", keys.STATS), wire.encode("window", window("drive-001", 2)))
        assert store.ingest(*later) == "device_retired"
        store._conn.set_trace_callback(ask_at_commit)
        store.reinstate_device("drive-001", by="token 1", note="not replaced after all")
        store._conn.set_trace_callback(None)
        assert heard == [False, True] and not store.is_retired("drive-001")
        assert store.ingest(*later) == "stored"


def test_another_cluster_members_retirement_reaches_this_writer(postgres_url, monkeypatch):
    """Two service processes on one PostgreSQL: the one that did not retire the drive stops storing it within
    RETIRED_READ_EVERY_S (zero here)."""
    import service.store as store_module

    monkeypatch.setattr(store_module, "RETIRED_READ_EVERY_S", 0.0)
    with Store.open(postgres_url) as writer, Store.open(postgres_url) as other:
        writer.insert_window(window("drive-001", 1))
        other.retire_device("drive-001", by="token 1", note="replaced")
        msg = (keys.key("drive-001", keys.STATS), wire.encode("window", window("drive-001", 2)))
        assert writer.ingest_many([msg]) == ["device_retired"]


def test_two_retirements_at_once_on_postgresql_leave_one(postgres_url):
    with Store.open(postgres_url) as setup:
        setup.insert_window(window("drive-001", 1))
    outcomes, start = [], threading.Barrier(2)

    def retire(name: str) -> None:
        with Store.open(postgres_url) as s:
            start.wait()
            try:
                s.retire_device("drive-001", by=name, note="replaced")
                outcomes.append("retired")
            except StoreError as exc:
                outcomes.append(exc.reason)

    threads = [threading.Thread(target=retire, args=(f"token {i}",)) for i in (1, 2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(outcomes) == ["already_retired", "retired"]
    with Store.open(postgres_url) as s:
        assert len(s.retirements("drive-001")) == 1


def test_an_operator_retires_and_reinstates_a_drive_over_rest(store):
    from fleet_wire.session import loopback_endpoint
    from service.runtime import FleetService, open_session

    three_drives(store)
    auth = TokenAuth(store)
    admin_id, admin = auth.create("admin", "ops desk")
    _, reader = auth.create("read", "wallboard")
    session = open_session(listen=[loopback_endpoint()])
    service = FleetService(store, session, refit_interval_s=0, monitor_interval_s=0).start()

    def metric(name: str, **labels) -> float:
        text = api.get("/metrics", headers=as_admin).text
        found = [s for f in text_string_to_metric_families(text) for s in f.samples if s.name == name]
        return next(s.value for s in found if all(s.labels.get(k) == v for k, v in labels.items()))

    try:
        with TestClient(create_app(store, service, auth)) as api:
            as_admin, as_reader = {"Authorization": f"Bearer {admin}"}, {"Authorization": f"Bearer {reader}"}
            note = {"note": "replaced by drive-004 (work order 7731)"}
            assert api.post("/devices/drive-003/retire", json=note, headers=as_reader).status_code == 403
            for body in ({"note": ""}, {}, {"note": "a\nb"}, {"note": "x", "by": "someone else"}):
                assert api.post("/devices/drive-003/retire", json=body, headers=as_admin).status_code == 422, body
            assert api.post("/devices/drive-999/retire", json=note, headers=as_admin).status_code == 404
            assert store.retired_device_ids() == set()  # none of the refusals changed anything
            assert metric("encoder_fleet_devices", state="offline") == 2

            done = api.post("/devices/drive-003/retire", json=note, headers=as_admin)
            assert done.status_code == 200, done.text
            got = done.json()
            assert got["state"] == "retired" and got["retired"]["by"] == f"token {admin_id} (ops desk)"
            assert got["retirements"][0]["note"] == note["note"]
            again = api.post("/devices/drive-003/retire", json=note, headers=as_admin)
            assert again.status_code == 409 and "ops desk" in again.json()["detail"]

            listed = {d["id"]: d for d in api.get("/devices", headers=as_reader).json()}
            assert listed["drive-003"]["state"] == "retired" and listed["drive-002"]["retired"] is None
            health = api.get("/fleet/health", headers=as_reader).json()
            assert health["devices"]["retired"] == 1 and health["open_alarms"] == {"offline": 1}
            in_fleet = api.get("/alarms", params={"open": "true", "in_fleet": "true"}, headers=as_reader).json()
            assert [a["device"] for a in in_fleet["alarms"]] == ["drive-002"]
            assert metric("encoder_fleet_devices", state="retired") == 1
            assert metric("encoder_fleet_devices", state="offline") == 1  # the alert's share counts the fleet's
            assert metric("encoder_fleet_unacknowledged_alarms", cause="offline") == 1

            assert api.post("/devices/drive-002/reinstate", json=note, headers=as_admin).status_code == 409
            back = api.post("/devices/drive-003/reinstate", json={"note": "mounted again"}, headers=as_admin)
            assert back.status_code == 200 and back.json()["retired"] is None
            assert back.json()["retirements"][0]["reinstate_note"] == "mounted again"
            assert api.get("/fleet/health", headers=as_reader).json()["open_alarms"] == {"offline": 2}
    finally:
        service.stop()
        session.close()


def test_a_retired_drive_gets_no_set_and_no_rollout(fleet):
    """A refusal the refit pass would answer (test_guard's) waits while the drive is retired and is answered once it
    is back; a rollout to the whole fleet leaves it out, and one naming it is refused."""
    store, service = fleet
    v2_on_trial_after_v1_ran(store, service)
    store.insert_window(window("drive-002", 1))
    store.insert_ack(wire.ack_message(DEVICE, 2, "rejected", 17_002.0, reason="band at 20.0 °C: out of range"))
    store.retire_device(DEVICE, by="token 1", note="replaced")
    service._changed.add(DEVICE)
    assert service.refit_all() == []
    assert store.published_version(DEVICE) == 2

    rollouts = Rollouts(store)
    with pytest.raises(RolloutError, match=f"retired devices: {DEVICE}"):
        rollouts.create(RolloutSpec(name="named", devices=[DEVICE, "drive-002"], **RESET))
    rollout = rollouts.create(RolloutSpec(name="everyone", **RESET))
    assert [d["device"] for d in rollouts.get(rollout)["devices"]] == ["drive-002"]

    store.reinstate_device(DEVICE, by="token 1", note="back")
    service._changed.add(DEVICE)
    assert service.refit_all() == [3]  # the refusal answered: the set it runs again


def test_the_devices_command_retires_shows_and_reinstates_a_drive(tmp_path):
    with Store.open(tmp_path / "fleet.sqlite") as store:
        three_drives(store)
        with operator_cli(store, tmp_path, "devices") as devices:
            refused = devices("retire", "drive-002", "--note", "replaced", token="read")
            assert refused.returncode == 2 and "403" in refused.stderr and not refused.stdout
            done = devices("retire", "drive-002", "--note", "replaced by drive-009")
            assert done.returncode == 0, done.stderr
            assert done.stdout.startswith("drive-002: retired, offline")
            assert "by token 1 (night shift): replaced by drive-009" in done.stdout
            twice = devices("retire", "drive-002", "--note", "again")
            assert twice.returncode == 2 and "409" in twice.stderr and "night shift" in twice.stderr
            unknown = devices("show", "drive-999", token="read")
            assert unknown.returncode == 2 and "404" in unknown.stderr
            back = devices("reinstate", "drive-002", "--note", "found in stock")
            assert back.returncode == 0 and "reinstated" in back.stdout and "found in stock" in back.stdout
            shown = devices("show", "drive-002", token="read")
            assert shown.returncode == 0 and shown.stdout.startswith("drive-002: "), shown.stderr
            assert len(shown.stdout.splitlines()) == 3  # the device, its retirement, its reinstatement


def test_the_mcap_export_logs_each_retirement_and_reinstatement(store, tmp_path):
    import io

    from mcap.reader import make_reader

    from service.mcap_export import export_mcap

    store.insert_window(window("drive-001", 1))
    store.retire_device("drive-001", by="token 1 (ops)", note="replaced by drive-004", at=2000.0)
    store.reinstate_device("drive-001", by="token 2 (night)", note="mounted again", at=3000.0)
    out = io.BytesIO()
    export_mcap(store, "drive-001", out, t_from=0.0, t_to=30.0)  # a drive-clock range: retirements whatever it is
    out.seek(0)
    logs = [
        (m.log_time, json.loads(m.data)["message"])
        for _, c, m in make_reader(out).iter_messages()
        if c.topic.endswith("/log") and "the fleet" in json.loads(m.data)["message"]
    ]
    assert logs == [
        (2000 * 10**9, "retired from the fleet by token 1 (ops): replaced by drive-004"),
        (3000 * 10**9, "reinstated in the fleet by token 2 (night): mounted again"),
    ]


def test_a_retired_drives_ageing_rates_leave_the_fleets_reference(fleet):
    """The drift monitor judges a drive's ageing against the fleet's median rate. The drives replaced for ageing kept
    their (frozen, high) rates in it for good: here four of them moved the median from 4 to 6, and a drive ageing at
    5 read as slower than the fleet."""
    store, service = fleet
    rates = service.monitor.fleet
    names = [f"drive-{i:03d}" for i in range(1, 11)]
    for rate, name in enumerate(names, start=1):
        store.insert_window(window(name, 1))
        rates.report(name, {"offset": [1, 2, 3, 4, 5, 6, 40, 50, 60, 70][rate - 1], "amplitude": 0.0})
    assert rates.norm("offset", exclude="drive-001")[0] == 6.0
    for name in names[6:]:
        store.retire_device(name, by="token 1", note="replaced: aged fast")
    service.monitor_pass()
    assert rates.norm("offset", exclude="drive-001")[0] == 4.0
    store.reinstate_device(names[6], by="token 1", note="back in service")
    service.monitor_pass()
    assert rates.norm("offset", exclude="drive-001")[0] == 4.5


def test_a_rollout_to_a_fleet_all_retired_says_so(store):
    store.insert_window(window("drive-001", 1))
    store.retire_device("drive-001", by="token 1", note="replaced")
    with pytest.raises(RolloutError, match="every device is retired"):
        Rollouts(store).create(RolloutSpec(name="everyone", **RESET))


def test_the_alarms_command_leaves_retired_drives_out_when_asked(tmp_path):
    from fleet_wire.session import free_port
    from service.runtime import HttpServer

    with Store.open(tmp_path / "fleet.sqlite") as store:
        three_drives(store)
        store.retire_device("drive-003", by="token 1", note="replaced")
        port = free_port()
        http = HttpServer(store, port).start()
        try:
            cmd = [sys.executable, "-m", "encoder_fleet.cli", "alarms", "list", "--url", f"http://127.0.0.1:{port}"]
            every = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
            in_fleet = subprocess.run([*cmd, "--in-fleet"], capture_output=True, text=True, timeout=60)
            assert every.returncode == 0 and in_fleet.returncode == 0, every.stderr + in_fleet.stderr
            assert [line.split()[1] for line in every.stdout.splitlines()] == ["drive-003", "drive-002"]
            assert [line.split()[1] for line in in_fleet.stdout.splitlines()] == ["drive-002"]
        finally:
            http.stop()
