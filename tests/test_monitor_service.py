"""The monitor in the service (service/monitor.py): stored windows in, alarms stored, listed and exported;
a restart neither forgets a drift in progress nor raises an alarm twice; bursts and bad input survive."""

import time
from collections import Counter

import pytest
from fastapi.testclient import TestClient
from mcap.reader import make_reader

from encoder_core.stats import MONOMIALS
from encoder_fleet.bench_monitor import drive_windows
from encoder_fleet.drift_events import draw_drive
from fleet_wire import alarms as alarm_wire
from fleet_wire import messages as wire
from service.api import create_app
from service.mcap_export import export_mcap
from service.monitor import Monitor
from service.store import Store

ONSET = 30 * 3600.0


def messages(spec, start_seq=1, t_shift=0.0, windows=None):
    out = []
    for i, (stats, counts, t_end) in enumerate(windows or drive_windows(spec, window_s=300.0, sample_hz=2.0)):
        out.append(
            wire.window_message(
                spec.name,
                start_seq + i,
                stats,
                window_start=t_shift + t_end - 300.0 + 0.5,
                window_end=t_shift + t_end,
                temp_rate_c_per_s=0.0,
                coefficients_version=0,
                angle_quality_deg=0.1,
                rejected_by_reason=counts,
            )
        )
    return out


@pytest.fixture(scope="module")
def aging():
    spec = draw_drive(21, 2.5, "accelerated_aging", onset_range_s=(ONSET, ONSET))
    return spec, messages(spec)


def insert(store, msgs):
    with store.transaction():
        for m in msgs:
            store.insert_window(m)


def test_restart_mid_drift_neither_forgets_nor_repeats(tmp_path, aging):
    spec, msgs = aging
    with Store.open(tmp_path / "whole.sqlite") as store:
        insert(store, msgs)
        whole = Monitor(store).process(spec.name)
    assert [a["cause"] for a in whole] == ["accelerated_aging"]
    raised_at = whole[0]["raised_at"]
    cut = next(i for i, m in enumerate(msgs) if m["window_end"] >= raised_at) - 3  # the CUSUM is climbing here
    published = []
    with Store.open(tmp_path / "cut.sqlite") as store:
        insert(store, msgs[:cut])
        assert Monitor(store).process(spec.name) == []
    with Store.open(tmp_path / "cut.sqlite") as store:  # the service restarted
        insert(store, msgs[cut:])
        monitor = Monitor(store, publish=lambda key, payload: published.append((key, payload)))
        got = monitor.process(spec.name)
        assert [(a["cause"], a["raised_at"]) for a in got] == [("accelerated_aging", raised_at)]
        assert Monitor(store).process(spec.name) == []  # and again: nothing new, nothing twice
        assert len(store.alarms(spec.name)) == 1
        assert monitor.state(spec.name) == "alarm"
    (key, payload) = published[0]
    assert key == f"encoders/{spec.name}/alarms"
    msg = alarm_wire.decode(payload)
    assert msg["event"] == "raised" and msg["cause"] == "accelerated_aging" and msg["cleared_at"] is None


def test_a_state_fed_but_not_yet_written_is_fed_again_after_a_crash(tmp_path, aging):
    """The state is written with every alarm and otherwise every SAVE_EVERY_WINDOWS windows: a service killed
    between two writes goes on from the last one and feeds the windows since again, to the same state and the same
    alarms as a run that never stopped (windows fed one, two or three at a time, as a service's passes do)."""
    spec, msgs = aging
    with Store.open(tmp_path / "whole.sqlite") as store:
        insert(store, msgs)
        whole = Monitor(store)
        alarms = whole.process(spec.name)
    with Store.open(tmp_path / "steps.sqlite") as store:
        monitor, got, k, crashes = Monitor(store), [], 0, 0
        while k < len(msgs):
            step = 1 + k % 3
            insert(store, msgs[k : k + step])
            k += step
            got += monitor.process(spec.name)
            written = store.monitor_states().get(spec.name, (None, 0))[1]
            if written < monitor.last_seq[spec.name] and k % 50 < 3:  # killed with windows fed and not written
                crashes += 1
                monitor = Monitor(store)
                assert monitor.last_seq.get(spec.name, 0) == written
        monitor.flush()
        assert crashes >= 5
        assert [(a["cause"], a["raised_at"]) for a in got] == [(a["cause"], a["raised_at"]) for a in alarms]
        assert len(store.alarms(spec.name)) == len(alarms) == 1
        assert monitor.devices[spec.name].to_dict() == whole.devices[spec.name].to_dict()
        assert store.monitor_states()[spec.name][1] == len(msgs)


def test_a_state_the_database_refuses_to_write_is_fed_again_and_its_alarm_raised_once(tmp_path, aging):
    """The database refuses the monitor's write (an outside writer holds its lock past the busy timeout) in the pass
    whose windows raise the drift's alarm, and in some passes before it. The monitor in memory had fed those windows
    and opened the alarm; kept, it would feed the next ones twice and never raise the alarm again (it is open in
    memory). It goes on from the state written instead: the alarm is raised, stored and published once, at the same
    time as in a run that never failed, and the state ends as that run's. A token lost to a refused write leaves
    no alarm open in memory that the database does not hold."""
    import sqlite3

    spec, msgs = aging
    with Store.open(tmp_path / "whole.sqlite") as store:
        insert(store, msgs)
        whole = Monitor(store)
        alarms = whole.process(spec.name)
    raised_at = alarms[0]["raised_at"]
    raising = next(i for i, m in enumerate(msgs) if m["window_end"] >= raised_at)
    path = tmp_path / "refused.sqlite"
    published = []
    with Store.open(path) as store:
        store._conn.execute("PRAGMA busy_timeout = 50")  # the service waits 30 s; the test need not
        monitor, got, refused, k = Monitor(store, publish=lambda key, p: published.append(p)), [], 0, 0
        while k < len(msgs):
            step = 1 + k % 3
            insert(store, msgs[k : k + step])
            k += step
            alarm_pass = k > raising >= k - step
            if alarm_pass or k % 40 < 3:  # the alarm's pass, and now and then another (refused where it writes)
                other = sqlite3.connect(path, isolation_level=None)
                other.execute("BEGIN IMMEDIATE")
                try:
                    got += monitor.process(spec.name)
                    assert not alarm_pass  # a pass that raises an alarm writes it
                except sqlite3.OperationalError as exc:
                    assert "locked" in str(exc)
                    refused += 1
                finally:
                    other.execute("ROLLBACK")
                    other.close()
                continue  # a refused pass's windows are fed again by the next one, with the next ones
            got += monitor.process(spec.name)
        got += monitor.process(spec.name)
        monitor.flush()
        assert refused >= 5
        assert [(a["cause"], a["raised_at"]) for a in got] == [(alarms[0]["cause"], raised_at)]
        assert len(store.alarms(spec.name)) == 1 and len(published) == 1
        assert monitor.devices[spec.name].to_dict() == whole.devices[spec.name].to_dict()
        assert store.monitor_states(spec.name)[spec.name][1] == len(msgs)

        other = sqlite3.connect(path, isolation_level=None)
        other.execute("BEGIN IMMEDIATE")
        try:
            with pytest.raises(sqlite3.OperationalError, match="locked"):
                monitor.set_online(spec.name, False)  # the offline alarm this token change raises is not written
        finally:
            other.execute("ROLLBACK")
            other.close()
        assert "offline" not in monitor.devices.get(spec.name, whole.devices[spec.name]).open
        assert [a["cause"] for a in monitor.set_online(spec.name, False)] == ["offline"]  # the next one raises it
        assert [a["cause"] for a in store.alarms(spec.name, cause="offline")] == ["offline"]


@pytest.mark.parametrize("saved", ['{"device": "drive", "v": 99}', '{"device": "drive", "ban'])
def test_a_state_unreadable_at_start_is_started_over_holding_the_alarms_it_left_open(tmp_path, aging, saved):
    """A saved state this version cannot read (written by an incompatible one, or cut short) is started over, and
    the alarms the lost state had open in the store are held open by the new monitor: not knowing of them, it never
    cleared them (the offline alarm stayed open with its token back) and said the device was ok beside its open
    drift alarm. A state that is not JSON at all stopped the start of every device's monitor; the others' go on."""
    import sqlite3

    spec, msgs = aging
    path = tmp_path / "fleet.sqlite"
    with Store.open(path) as store:
        insert(store, msgs)
        insert(store, [{**m, "device": "other"} for m in msgs[:20]])
        monitor = Monitor(store)
        assert [a["cause"] for a in monitor.process(spec.name)] == ["accelerated_aging"]
        (offline,) = monitor.set_online(spec.name, False)
        assert monitor.process("other") == []
        other = monitor.devices["other"].to_dict()
    with sqlite3.connect(path) as db:
        db.execute("UPDATE monitor_state SET state_json = ? WHERE device = ?", (saved, spec.name))
    with Store.open(path) as store:
        monitor = Monitor(store)
        assert monitor.last_seq[spec.name] == len(msgs)  # the windows already judged are not judged again
        assert monitor.state(spec.name) == "offline"
        assert monitor.set_online(spec.name, False) == []  # already open
        (back,) = monitor.set_online(spec.name, True)
        assert back["id"] == offline["id"] and back["cleared_at"] == msgs[-1]["window_end"] >= back["raised_at"]
        assert monitor.state(spec.name) == "alarm"
        assert [a["cause"] for a in store.alarms(spec.name, open_=True)] == ["accelerated_aging"]
        assert TestClient(create_app(store)).get(f"/devices/{spec.name}/health").json()["state"] == "alarm"
        assert monitor.devices["other"].to_dict() == other and monitor.last_seq["other"] == 20


def test_offline_before_any_window_is_fed_is_dated_at_the_last_one_stored(tmp_path, aging):
    """A drive whose first window is not stored yet (the monitor waits for it, having fed none) goes offline: its
    alarm is dated at the end of its last window stored, not at drive time 0 "its last window ended at 0.00 h";
    a drive with no window stored at all says so. Its clear is never dated before its raise."""
    spec, msgs = aging
    with Store.open(tmp_path / "fleet.sqlite") as store:
        insert(store, msgs[1:40])
        monitor = Monitor(store)
        assert monitor.process(spec.name) == []  # seq 1 missing: nothing fed
        (offline,) = monitor.set_online(spec.name, False)
        assert offline["raised_at"] == offline["parameters"]["since"] == msgs[39]["window_end"]
        assert f"ended at {msgs[39]['window_end'] / 3600:.2f} h" in offline["evidence"]
        (back,) = monitor.set_online(spec.name, True)
        assert back["cleared_at"] == back["raised_at"]
        insert(store, msgs[:1])
        assert monitor.process(spec.name) == [] and monitor.last_seq[spec.name] == 40
        (ghost,) = monitor.set_online("drive-unseen", False)
        assert ghost["raised_at"] == 0.0 and "no window of it is stored" in ghost["evidence"]


def test_an_offline_alarms_clear_says_how_long_the_token_was_gone(tmp_path, aging):
    """On the drive's clock an outage ends where it began (no window of it is stored meanwhile; those the agent held
    come after its token), so raised_at and cleared_at read as no outage at all: the clear says how long the token
    was gone on the service's clock."""
    spec, msgs = aging
    with Store.open(tmp_path / "fleet.sqlite") as store:
        insert(store, msgs)
        monitor = Monitor(store)
        monitor.process(spec.name)
        (offline,) = monitor.set_online(spec.name, False)
        with store._tx() as c:  # it went three hours ago
            c.execute("UPDATE alarms SET created_at = created_at - 10800 WHERE id = ?", (offline["id"],))
        (back,) = monitor.set_online(spec.name, True)
        assert back["cleared_at"] == back["raised_at"] == msgs[-1]["window_end"]
        (audited,) = store.alarms(spec.name, "offline", audit=True)
        assert "token is back after 3.0 h (service clock)" in audited["clear_evidence"], audited


def test_alarms_in_rest_and_mcap_and_offline(tmp_path, aging):
    spec, msgs = aging
    with Store.open(tmp_path / "fleet.sqlite") as store:
        insert(store, msgs)
        monitor = Monitor(store)
        monitor.process(spec.name)
        (offline,) = monitor.set_online(spec.name, False)
        assert offline["cause"] == "offline" and offline["parameters"] == {"since": msgs[-1]["window_end"]}
        assert monitor.set_online(spec.name, False) == []  # already open
        api = TestClient(create_app(store))
        body = api.get("/alarms").json()
        assert {a["cause"] for a in body["alarms"]} == {"accelerated_aging", "offline"}
        for a in body["alarms"]:
            assert set(a) == {"id", "device", "cause", "parameters", "evidence", "raised_at", "cleared_at"} | {
                "acked_at",  # an operator's acknowledgement (POST /alarms/{id}/ack): null until then
                "acked_by",
                "ack_note",
            }
            assert a["acked_at"] is a["acked_by"] is a["ack_note"] is None
        assert api.get("/alarms", params={"cause": "offline"}).json()["alarms"][0]["cleared_at"] is None
        assert api.get("/alarms", params={"device": "nobody"}).json() == {
            "alarms": [],
            "truncated": False,
            "next": None,
        }
        health = api.get(f"/devices/{spec.name}/health").json()
        assert health["state"] == "offline" and len(health["alarms"]) == 2
        fleet = api.get("/fleet/health").json()
        assert fleet["devices"]["offline"] == 1 and fleet["open_alarms"] == {"accelerated_aging": 1, "offline": 1}
        (back,) = monitor.set_online(spec.name, True)
        assert back["cause"] == "offline" and back["cleared_at"] is not None
        assert api.get("/alarms", params={"open": "false"}).json()["alarms"][0]["cause"] == "offline"
        assert api.get(f"/devices/{spec.name}/health").json()["state"] == "alarm"
        out = tmp_path / "d.mcap"
        with open(out, "wb") as f:
            export_mcap(store, spec.name, f)
        with open(out, "rb") as f:
            topics = Counter(ch.topic for _, ch, _ in make_reader(f).iter_messages())
        assert topics[f"/encoders/{spec.name}/alarms"] == 2


def test_a_burst_of_10000_windows_and_an_absurd_one(tmp_path):
    spec = draw_drive(22, 1.0, None)
    day = drive_windows(spec, window_s=300.0, sample_hz=2.0)
    msgs = []
    for k in range(35):  # the same day again and again: 10,080 windows, sent at once
        msgs += messages(spec, start_seq=1 + k * len(day), t_shift=k * 86400.0, windows=day)
    with Store.open(tmp_path / "burst.sqlite") as store:
        insert(store, msgs)
        started = time.perf_counter()
        assert Monitor(store).process(spec.name) == []
        elapsed = time.perf_counter() - started
        assert store.monitor_states()[spec.name][1] == len(msgs)
        # a valid window that is absurd for this drive: ten times the radius
        stats = day[100][0]
        big = stats.merge(stats)  # same normalisation; scale the sums as for a radius 10x
        big.moments = stats.moments * [10.0 ** (i + j) for i, j in MONOMIALS]
        big.bins = stats.bins.copy()
        big.bins[:, 1:3] *= 10
        big.bins[:, 3:6] *= 100
        big.moments[0] = stats.moments[0]
        absurd = messages(
            spec, start_seq=len(msgs) + 1, t_shift=35 * 86400.0, windows=[(big, day[100][1], day[100][2])]
        )
        insert(store, absurd)
        monitor = Monitor(store)
        assert monitor.process(spec.name) == []
        assert monitor.devices[spec.name].absurd == 1
    assert elapsed < 60, elapsed


def test_an_alarm_raised_and_cleared_in_one_pass_is_heard_twice(tmp_path):
    """A monitor that falls behind can raise an alarm and clear it in the same pass (the refit already
    followed the step): what is published for it must still say raised, then cleared, with the times of each."""
    step = {"cause": "offset_step", "parameters": {}, "evidence": "the offsets jumped (planted)"}
    with Store.open(tmp_path / "fleet.sqlite") as store:
        written = store.save_monitor(
            "drive-9",
            {},
            5,
            [{**step, "kind": "raise", "at": 100.0}, {**step, "kind": "clear", "at": 400.0, "evidence": "refit"}],
        )
        listed = store.alarms("drive-9")
    published = [alarm_wire.decode(alarm_wire.encode(a)[1]) for a in written]
    assert [(a["event"], a["raised_at"], a["cleared_at"]) for a in published] == [
        ("raised", 100.0, None),
        ("cleared", 100.0, 400.0),
    ]
    assert [(a["raised_at"], a["cleared_at"]) for a in listed] == [(100.0, 400.0)]  # one alarm, stored once


def test_every_member_answers_a_devices_state_as_its_monitor_wrote_it(tmp_path, aging):
    """Every service process answers REST for the whole fleet, but its monitor in memory is current for its own
    partitions only: the other members' devices stood there as when it started. Read from it, GET /devices/{id}/health
    said "unknown" beside the open alarms the other member wrote, /fleet/health counted the device unknown,
    and GET /devices (which the fleet page's "Devices by state" reads) sent no state at all: the page showed
    online/offline, never an alarm."""
    from types import SimpleNamespace

    spec, msgs = aging
    with Store.open(tmp_path / "fleet.sqlite") as store:
        insert(store, msgs)
        here = Monitor(store)  # this member, started before the windows came; the device is another member's
        there = Monitor(store)
        assert [a["cause"] for a in there.process(spec.name)] == ["accelerated_aging"]
        service = SimpleNamespace(monitor=here, partitions=SimpleNamespace(serves=lambda device: False))
        api = TestClient(create_app(store, service))
        health = api.get(f"/devices/{spec.name}/health").json()
        assert [a["cause"] for a in health["alarms"]] == ["accelerated_aging"]
        assert health["state"] == "alarm"
        assert api.get("/fleet/health").json()["devices"]["alarm"] == 1
        assert [(d["id"], d["state"]) for d in api.get("/devices").json()] == [(spec.name, "alarm")]
        assert api.get(f"/devices/{spec.name}").json()["state"] == "alarm"
        # the member that monitors it answers from memory, and so does a service alone (no partitions)
        mine = TestClient(create_app(store, SimpleNamespace(monitor=there)))
        assert [d["state"] for d in mine.get("/devices").json()] == ["alarm"]
        (offline,) = there.set_online(spec.name, False)
        assert [d["state"] for d in api.get("/devices").json()] == ["offline"]  # as written with the alarm
        assert TestClient(create_app(store)).get("/fleet/health").json()["devices"]["offline"] == 1


def test_a_step_cleared_by_the_factory_set_again_says_so(tmp_path):
    """The factory set published again after a step (basis rollback, restores v0: back_to_factory for a step the
    monitor could not measure, a guard's rollback, a rollout's reset) clears the step once applied, as any set made
    since does (the monitor can name the next step; bench-fleet-accuracy's loop judges the refit on that rule). Its
    clear said "made after the step", which read as if the drive were corrected for it (a second reader); it now
    says the factory set is back and the step not yet corrected for."""
    from wire_samples import coefficients

    spec = draw_drive(31, 2.5, "offset_step", onset_range_s=(ONSET, ONSET))
    msgs = messages(spec)
    dev = spec.name
    with Store.open(tmp_path / "fleet.sqlite") as store:
        bench = coefficients(dev, version=0, created_at=0.0)["bands"]
        store.insert_coefficient_set(wire.coefficients_message(dev, 0, 0.0, "factory", bench))
        monitor = Monitor(store)
        k = next(i for i, m in enumerate(msgs) if m["window_end"] > ONSET + 3 * 3600)
        insert(store, msgs[:k])
        (step,) = [a for a in monitor.process(dev) if a["cause"] == "offset_step"]
        t = msgs[k]["window_end"]
        store.insert_coefficient_set(wire.coefficients_message(dev, 1, t, "rollback", bench, restores_version=0))
        store.insert_ack(wire.ack_message(dev, 1, "applied", t + 60.0, angle_quality_deg=0.05))
        insert(store, msgs[k : k + 5])
        (cleared,) = monitor.process(dev)
        assert (cleared["id"], cleared["cleared_at"]) == (step["id"], t + 60.0)
        (stored,) = store.alarms(dev, ids=[step["id"]], audit=True)
        assert "the factory set again" in stored["clear_evidence"] and "not corrected for" in stored["clear_evidence"]
