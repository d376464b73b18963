"""The agent's side of a rollout over a real Zenoh session: what it applies, what it refuses, and what
it remembers across a restart."""

import json
import time

import numpy as np
import pytest
import zenoh

from edge_agent.agent import EdgeAgent, factory_message
from edge_agent.outbox import Outbox
from edge_agent.sources import SimulatedDrive, drive_model, factory_calibration
from encoder_core.samples import InputError
from fleet_wire import keys
from fleet_wire import messages as wire
from fleet_wire.session import loopback_endpoint, session_config
from service.runtime import FleetService, open_session
from service.store import Store
from tests.wire_samples import window as ws_window

DEVICE = "drive-t"
SEED = 4


@pytest.fixture
def setup(tmp_path):
    endpoint = loopback_endpoint()
    store = Store.open(tmp_path / "fleet.sqlite")
    router = open_session(listen=[endpoint])
    service = FleetService(store, router, refit_interval_s=0).start()  # no refits: the test sends the sets
    client = zenoh.open(session_config("client", connect=[endpoint]))
    factory = factory_calibration(drive_model(SEED), SEED)
    outbox_path = tmp_path / "outbox.sqlite"

    def make_agent(session):
        return EdgeAgent(DEVICE, SimulatedDrive(SEED, hours=1), session, Outbox(outbox_path), factory)

    yield store, router, client, factory, make_agent, service
    client.close()
    service.stop()
    router.close()
    store.close()


def coefficient_set(factory, version, scale_w1=1.0):
    msg = factory_message(DEVICE, factory)
    for band in msg["bands"]:
        band["w"][0] *= scale_w1
    return {**msg, "version": version, "basis": "fit", "created_at": 60.0}


def wait_for(predicate, timeout=10.0):
    deadline = time.monotonic() + timeout
    while not predicate() and time.monotonic() < deadline:
        time.sleep(0.05)
    return predicate()


def test_agent_applies_good_sets_and_refuses_bad_ones(setup):
    store, router, client, factory, make_agent, _ = setup
    agent = make_agent(client)
    agent.start()
    assert wait_for(lambda: store.current_coefficients(DEVICE) is not None)  # the factory announcement
    key = f"encoders/{DEVICE}/coefficients"
    router.put(key, wire.encode("coefficients", coefficient_set(factory, 5, scale_w1=1.01)))
    router.put(key, json.dumps(coefficient_set(factory, 6, scale_w1=100.0)).encode())  # implausible gain
    router.put(key, wire.encode("coefficients", coefficient_set(factory, 3)))  # older than what it holds
    router.put(key, b'{"schema": "encoder-fleet/coefficients/1", "version": NaN}')
    router.put(
        "encoders/other/coefficients", wire.encode("coefficients", {**coefficient_set(factory, 9), "device": "other"})
    )
    assert wait_for(lambda: agent.inbox.qsize() >= 4)  # its own four; the other device's never comes
    for _ in range(3):
        agent.step()
    assert agent.version == 5
    assert wait_for(lambda: len(store.acks(DEVICE)) == 2)
    acks = {a["version"]: a for a in store.acks(DEVICE)}
    assert acks[5]["status"] == "applied" and acks[5]["angle_quality_deg"] >= 0
    assert acks[6]["status"] == "rejected" and "w1" in acks[6]["reason"]
    agent.close()


def test_a_set_the_agent_refuses_is_rolled_back_and_the_set_it_runs_sent_again(setup):
    """A set the agent will not run (here an implausible gain, as a refit gone wrong could make): it refuses it and
    says why; the service's next refit pass ends that set rolled back, with the agent's words, and publishes the
    set the drive runs again, which the agent applies. Before, a refused trial was confirmed after an hour on no
    evidence, and the watch judged a set the drive never ran."""
    store, router, client, factory, make_agent, service = setup
    agent = make_agent(client)
    agent.start()
    assert wait_for(lambda: store.current_coefficients(DEVICE) is not None)  # v0, the factory's
    bands = coefficient_set(factory, 1, scale_w1=100.0)["bands"]
    assert service._issue_set(DEVICE, "fit", bands, state="trial", reason="a refit gone wrong") == 1
    assert wait_for(lambda: agent.inbox.qsize() >= 1)
    agent.step()
    assert agent.version == 0  # refused: the drive runs its factory set on
    assert wait_for(lambda: {(a["version"], a["status"]) for a in store.acks(DEVICE)} == {(1, "rejected")})
    assert service.refit_all() == [2]
    history = {h["version"]: h for h in store.coefficient_history(DEVICE)}
    assert history[1]["state"] == "rolled_back" and "the agent refused v1: " in history[1]["state_reason"]
    assert "w1" in history[1]["state_reason"]  # the agent's own reason, kept
    assert history[2]["basis"] == "rollback" and history[2]["restores_version"] == 0
    assert history[2]["state"] == "confirmed" and history[2]["message"]["bands"] == history[0]["message"]["bands"]
    assert wait_for(lambda: agent.inbox.qsize() >= 1)
    agent.step()
    agent.step()  # the ack goes with the quality of the block after the set was applied
    assert agent.version == 2
    acked = {(1, "rejected"), (2, "applied")}
    assert wait_for(lambda: {(a["version"], a["status"]) for a in store.acks(DEVICE)} == acked)
    assert service.refit_all() == []  # answered once: v2 is what runs
    agent.close()


def test_restarted_agent_resumes_with_its_set(setup):
    store, router, client, factory, make_agent, _ = setup
    agent = make_agent(client)
    agent.start()
    router.put(f"encoders/{DEVICE}/coefficients", wire.encode("coefficients", coefficient_set(factory, 7, 1.02)))
    assert wait_for(lambda: agent.inbox.qsize() >= 1)
    agent.step()
    assert agent.version == 7
    seq = agent.seq
    agent.close()
    again = make_agent(client)  # a new process would do the same: open its outbox and go on
    assert again.version == 7 and again.seq == seq
    assert again.correction.bands[0].w1 == pytest.approx(factory.bands[0].w1 * 1.02)


def test_agent_reads_the_die_temperature_with_the_lag_its_set_carries(setup):
    """A set with thermal_lag_s: the agent corrects with, and writes its windows' temperatures at, the reported
    temperature lagged by it, carried on from the window before (encoder_core/thermal.py)."""
    from encoder_core.stats import rejected_by_reason
    from encoder_core.thermal import DieTemperature

    store, router, client, factory, make_agent, _ = setup
    agent = make_agent(client)
    agent.start()
    agent.step()  # a window at the factory set: the temperature as reported
    lagged = {**coefficient_set(factory, 5), "thermal_lag_s": 300.0}
    router.put(f"encoders/{DEVICE}/coefficients", wire.encode("coefficients", lagged))
    assert wait_for(lambda: agent.apply_inbox() or agent.version == 5)  # (the service's own echo may come first)
    for _ in range(3):
        agent.step()
    assert agent.version == 5 and agent.correction.thermal_lag_s == 300.0
    assert wait_for(lambda: len(store.windows(DEVICE)) == 4)
    stored = store.windows(DEVICE)
    assert [w["coefficients_version"] for w in stored] == [0, 5, 5, 5], stored
    reference, die = SimulatedDrive(SEED, hours=1), DieTemperature()  # the same drive, read again
    for k, window in enumerate(stored):
        block = reference.read(60.0)
        usable, _ = rejected_by_reason(block)
        reported = block.temp_c[usable].mean()
        expected = die(block.t, block.temp_c, 0.0 if k == 0 else 300.0)[usable].mean()
        assert window["temp_mean_c"] == pytest.approx(expected, abs=1e-9), (k, window, reported)
        if k > 0:
            assert abs(expected - reported) > 0.05  # the lag is seen: the drive's temperature moves
    agent.close()


def test_a_window_with_no_usable_sample_is_skipped_without_a_seq_and_the_agent_goes_on(setup, caplog, tmp_path):
    """A minute in which the hall channels read nothing (unplugged: NaN) has no usable sample, so no temperature
    and no band, and the wire refuses it. The agent raised and stopped there, with a seq used and never sent. Now
    it logs the window, sends none for it, and the windows after it go with the next seqs (the service's watermark
    needs seqs without gaps)."""
    import numpy as np

    from edge_agent.sources import ReplaySource
    from encoder_core.samples import Samples
    from encoder_core.simulator import simulate

    store, _, client, factory, _, _ = setup
    rng = np.random.default_rng(SEED)
    t = np.arange(0.0, 240.0, 0.05)
    s, _ = simulate(drive_model(SEED), t, rng.uniform(0, 2 * np.pi, t.size), np.full(t.size, 25.0), rng)
    unplugged = (t >= 60.0) & (t < 120.0)  # the second of four minutes
    d, q = np.where(unplugged, np.nan, s.d), np.where(unplugged, np.nan, s.q)
    source = ReplaySource(Samples(t=t, d=d, q=q, temp_c=s.temp_c))
    agent = EdgeAgent(DEVICE, source, client, Outbox(tmp_path / "replay-outbox.sqlite"), factory)
    agent.start()
    counters = agent.run()
    assert source.pos == t.size and counters.windows == 3 and counters.unsent_windows == 1 and agent.seq == 3
    assert wait_for(lambda: len(store.windows(DEVICE)) == 3)
    stored = store.windows(DEVICE)
    assert [w["seq"] for w in stored] == [1, 2, 3]
    assert [round(w["window_start"]) for w in stored] == [0, 120, 180]  # the unplugged minute is not there
    assert "window 60.0-120.0 s (drive clock) not sent, 1200 of 1200 samples rejected" in caplog.text
    assert len(agent.outbox) == 0  # the watermark passed every window: no gap held it back
    agent.close()


def two_minutes_at_25_c(setup, outbox_path, spoil, **agent_options):
    """Two minutes of the drive at +25 °C replayed through a real agent, its temperature readings spoiled in place by
    `spoil(temp, rng)`: both windows sent and stored. The agent, the times, the samples and the temperatures."""
    import numpy as np

    from edge_agent.sources import ReplaySource
    from encoder_core.samples import Samples
    from encoder_core.simulator import simulate

    store, _, client, factory, _, _ = setup
    rng = np.random.default_rng(SEED)
    t = np.arange(0.0, 120.0, 0.05)
    s, _ = simulate(drive_model(SEED), t, rng.uniform(0, 2 * np.pi, t.size), np.full(t.size, 25.0), rng)
    temp = s.temp_c.copy()
    spoil(temp, rng)
    agent = EdgeAgent(DEVICE, ReplaySource(Samples(t=t, d=s.d, q=s.q, temp_c=temp)), client, Outbox(outbox_path),
                      factory, **agent_options)  # fmt: skip
    agent.start()
    counters = agent.run()
    assert counters.windows == 2 and counters.unsent_windows == 0
    assert wait_for(lambda: len(store.windows(DEVICE)) == 2)
    return agent, t, s, temp


def test_a_nan_temperature_reading_costs_its_sample_not_the_window(setup, tmp_path):
    """One temperature sample that reads NaN (a dropped conversion of the sensor) summed into the window's
    temperature made it NaN, and the wire refused the whole window. Now that sample is rejected as non_finite and
    the window goes, its temperature from the others."""
    import numpy as np

    from encoder_core.samples import Samples

    store, _, _, factory, _, _ = setup

    def one_nan(temp, rng):
        temp[rng.integers(0, temp.size // 2)] = np.nan  # in the first of two minutes

    agent, t, s, temp = two_minutes_at_25_c(setup, tmp_path / "nan-temp-outbox.sqlite", one_nan)
    first = store.monitor_windows(DEVICE, 0, 1)[0]
    assert first["rejected_by_reason"]["non_finite"] == 1 and first["stats"].rejected == 1
    assert np.isfinite(first["temp_mean_c"]) and abs(first["temp_mean_c"] - 25.0) < 1.0
    # the angle handed to the drive: with two bands the set interpolates in temperature, and a NaN one made it NaN
    from encoder_core.correction import BandedCorrection, Correction

    warm = Correction.from_dict({**factory.bands[0].to_dict(), "temp_c": 45.0})
    agent.correction = BandedCorrection([factory.bands[0], warm])
    block = Samples(t=t[:1200], d=s.d[:1200], q=s.q[:1200], temp_c=temp[:1200])
    angle = agent.correct(agent.at_die_temperature(block))
    assert np.all(np.isfinite(angle))
    agent.close()


def _replay(seed: int = SEED, seconds: float = 180.0):
    """A replayable stretch of a drive (three minutes by default), its clock from 0."""
    import numpy as np

    from edge_agent.sources import ReplaySource
    from encoder_core.samples import Samples
    from encoder_core.simulator import simulate

    rng = np.random.default_rng(seed)
    t = np.arange(0.0, seconds, 0.05)
    s, _ = simulate(drive_model(SEED), t, rng.uniform(0, 2 * np.pi, t.size), np.full(t.size, 25.0), rng)
    return lambda: ReplaySource(Samples(t=t, d=s.d, q=s.q, temp_c=s.temp_c))


def test_an_agent_that_lost_its_outbox_goes_on_after_the_service_s_last_window(setup, tmp_path, caplog):
    """A drive's agent restarted with a new, empty outbox (its disk replaced): it numbered its windows from 1 and
    restarted the drive clock, and the service refused each as a seq conflict with the windows it had. Now the
    agent asks the service where it stands and goes on after its last window, in seq and in drive time."""
    store, _, client, factory, _, _ = setup
    replay = _replay()
    runs = []
    for name in ("first-outbox", "new-outbox"):  # the same three minutes of drive clock, twice
        agent = EdgeAgent(DEVICE, replay(), client, Outbox(tmp_path / f"{name}.sqlite"), factory)
        agent.start()
        runs.append(agent.run())
        agent.close()
        assert wait_for(lambda n=3 * len(runs): len(store.windows(DEVICE)) == n)
    stored = store.windows(DEVICE)
    assert [w["seq"] for w in stored] == [1, 2, 3, 4, 5, 6]
    ends = [w["window_end"] for w in stored]
    assert all(b["window_start"] > a["window_end"] for a, b in zip(stored, stored[1:])), ends
    assert "the outbox only up to 0" in caplog.text


def test_an_agent_that_lost_its_outbox_fills_the_service_s_gap_first(setup, tmp_path):
    """The service had seqs 1-3 and 5 (4 was still in the outbox that was lost). Going on after 5 would leave 4
    missing for good: the watermark and the drift monitor stop at 3. The agent goes on from the contiguous
    watermark instead (its new window fills 4; the one that lands on 5 is refused as a seq conflict), in drive
    time after the service's newest window."""
    store, _, client, factory, _, _ = setup
    first = _replay(seconds=300.0)
    agent = EdgeAgent(DEVICE, first(), client, Outbox(tmp_path / "lost.sqlite"), factory)
    agent.start()
    sent = []
    agent.put = lambda key, payload: sent.append((key, payload))  # the windows leave the agent, then the outbox goes
    while agent.step():
        pass
    agent.close()
    for key, payload in sent:
        if key == agent.keys["stats"] and wire.decode_window(payload, key_device=DEVICE).seq != 4:
            client.put(key, payload)
    assert wait_for(lambda: [w["seq"] for w in store.windows(DEVICE)] == [1, 2, 3, 5])
    again = EdgeAgent(DEVICE, first(), client, Outbox(tmp_path / "new.sqlite"), factory)
    again.start()
    assert again.seq == 3
    again.run()
    again.close()
    assert wait_for(lambda: sorted(w["seq"] for w in store.windows(DEVICE)) == list(range(1, 9)))
    assert store.contiguous_seq(DEVICE) == 8 and len(again.outbox) == 0
    by_seq = {w["seq"]: w for w in store.windows(DEVICE)}
    assert by_seq[4]["window_start"] > by_seq[5]["window_end"]  # the new seq 4 after the old seq 5, in drive time


def _first_three_windows(store, client, factory, outbox_path) -> None:
    """Three minutes of the drive through an agent and its outbox, stored by the service."""
    first = EdgeAgent(DEVICE, _replay()(), client, Outbox(outbox_path), factory)
    first.start()
    first.run()
    first.close()
    assert wait_for(lambda: len(store.windows(DEVICE)) == 3)


def test_an_agent_that_lost_its_outbox_while_the_service_was_away_moves_what_it_numbered(setup, tmp_path):
    """The outbox lost and the service away at start (a site's power back, the drive's controller up before the
    network): the agent could not ask where to go on, numbered its windows from 1 and restarted the drive clock on
    the same grid of sample times. Every one of them was a seq conflict for good once the service was back. Now
    those windows wait in the outbox (a restart meanwhile included), and the first watermark reply moves them all
    after the service's newest, in seq and drive time."""
    store, router, client, factory, _, service = setup
    _first_three_windows(store, client, factory, tmp_path / "first.sqlite")
    service.stop()  # the service away

    later = _replay(SEED + 1)  # the drive's clock from 0 again, its samples not the same
    outbox = tmp_path / "new.sqlite"
    before_restart = EdgeAgent(DEVICE, later(), client, Outbox(outbox), factory)
    before_restart.start()
    assert before_restart.step() and before_restart.step()
    before_restart.close()  # stopped before the service was back: its two windows wait in the outbox
    agent = EdgeAgent(DEVICE, later(), client, Outbox(outbox), factory)
    agent.start()
    while agent.step():
        pass
    assert agent.seq == 5 and len(agent.outbox) == 5 and len(store.windows(DEVICE)) == 3

    back = FleetService(store, router, refit_interval_s=0).start()
    try:
        assert agent.drain()
    finally:
        agent.close()
        back.stop()
    stored = store.windows(DEVICE)
    assert [w["seq"] for w in stored] == list(range(1, 9))
    assert all(b["window_start"] > a["window_end"] for a, b in zip(stored, stored[1:]))
    assert store.dead_letters() == [] and agent.seq == 8
    assert agent.outbox.last_window_end() == stored[-1]["window_end"]


def test_windows_a_full_outbox_dropped_are_stepped_over_by_the_watermark(setup, tmp_path):
    """The service away for longer than the outbox holds: it dropped its oldest windows (4-6 of 4-9 here). The
    service stored 1-3 and then 7-9, and its contiguous watermark waited at 3 for ever: the agent never forgot 7-9,
    and the drift monitor, reading up to the watermark, went blind for that drive. Now the agent says that what
    the service lacks below 7 is gone, and the watermark steps over it, after a restart of the service too."""
    store, router, client, factory, _, service = setup
    outbox = tmp_path / "small.sqlite"
    _first_three_windows(store, client, factory, outbox)
    service.stop()  # away for six windows; the outbox holds three
    agent = EdgeAgent(DEVICE, _replay(SEED + 1, seconds=360.0)(), client, Outbox(outbox, max_windows=3), factory)
    agent.start()
    while agent.step():
        pass
    assert agent.seq == 9 and agent.outbox.dropped == 3 and agent.outbox.held_from() == 7
    back = FleetService(store, router, refit_interval_s=0).start()
    try:
        assert agent.drain(timeout_s=5.0)  # the outbox empties: the watermark passed 9
        assert [w["seq"] for w in store.windows(DEVICE)] == [1, 2, 3, 7, 8, 9]
        assert back.watermark(DEVICE) == 9
        back.monitor_pass()
        assert back.monitor.last_seq[DEVICE] == 9  # the monitor read past the gap
    finally:
        agent.close()
        back.stop()
    again = FleetService(store, router, refit_interval_s=0).start()  # the floor is kept in the database
    try:
        assert again.watermark(DEVICE) == 9
    finally:
        again.stop()
    assert store.dead_letters() == []


def test_a_window_numbered_after_a_floor_and_lost_on_the_way_is_sent_again(setup, tmp_path):
    """A second reader's case: the floor named (7, the outbox having dropped 4-6), the windows 7-9 never arriving
    (the agent's disk dies), and the drive's agent back with a new, empty outbox. The first version capped the
    watermark at the highest seq stored (3), so the new agent numbered on from 4, below the floor: its window 4,
    dropped once on the way (an overloaded queue), counted as gone, and the agent forgot it unstored. Now the
    watermark is 6 at once, the new agent numbers from 7, and the window lost once is sent again and stored."""
    store, router, client, factory, _, service = setup
    _first_three_windows(store, client, factory, tmp_path / "first.sqlite")
    service.stop()
    small = Outbox(tmp_path / "first.sqlite", max_windows=3)
    dying = EdgeAgent(DEVICE, _replay(SEED + 1, seconds=360.0)(), client, small, factory)
    while dying.step():
        pass
    back = FleetService(store, router, refit_interval_s=0).start()
    try:
        dying.put = lambda key, payload: None  # its windows 7-9 never reach the service
        assert dying.sync() and dying.sync()  # the first settles its seqs, the second names the floor
        dying.close()
        assert store.max_seq(DEVICE) == 3 and back.watermark(DEVICE) == 6
        again = EdgeAgent(DEVICE, _replay(SEED + 2)(), client, Outbox(tmp_path / "new.sqlite"), factory)
        put, lost = again.put, []

        def lose_the_first_window(key, payload):
            if key == again.keys["stats"] and not lost:
                lost.append(wire.decode_window(payload, key_device=DEVICE).seq)
                return
            put(key, payload)

        again.put = lose_the_first_window
        again.start()
        while again.step():
            pass
        assert again.drain(timeout_s=10.0)
        again.close()
    finally:
        back.stop()
    assert lost == [7] and [w["seq"] for w in store.windows(DEVICE)] == [1, 2, 3, 7, 8, 9]


def test_a_device_out_of_the_registry_gets_no_watermark_and_moves_no_floor(tmp_path):
    """The received question skipped the guard that windows, factory sets and tokens pass: behind a stale router
    ACL a revoked id still had its watermark answered and could raise its stored seq floor (a second reader)."""
    from service.guard import IngestGuard

    endpoint = loopback_endpoint()
    store = Store.open(tmp_path / "fleet.sqlite")
    for device in ("drive-ok", "drive-revoked"):
        store.insert_window(ws_window(device, seq=1))
    router = open_session(listen=[endpoint])
    service = FleetService(store, router, refit_interval_s=0, guard=IngestGuard(store, ["drive-ok"])).start()
    client = zenoh.open(session_config("client", connect=[endpoint]))
    try:
        for device, answered in (("drive-ok", True), ("drive-revoked", False)):
            got = list(client.get(keys.key(device, keys.RECEIVED), payload=wire.received_query(device, 50), timeout=2))
            assert bool([r for r in got if r.ok is not None]) == answered, device
        assert store.contiguous_seq("drive-ok") == 49 and store.contiguous_seq("drive-revoked") == 1
    finally:
        client.close()
        service.stop()
        router.close()
        store.close()


def test_a_received_question_is_answered_while_the_database_refuses_writes(setup):
    """The floor and a bad question's dead letter are writes; a database that refuses them (another writer holds
    its lock past the busy timeout, a full disk) must not leave the question unanswered: reads still work, and the
    agent's windows wait for the watermark, not for the write (a second reader found no reply at all)."""
    import sqlite3

    store, _, client, factory, make_agent, _ = setup
    agent = make_agent(client)
    agent.start()
    for _ in range(3):
        agent.step()
    assert wait_for(lambda: store.contiguous_seq(DEVICE) == 3)
    store._conn.execute("PRAGMA busy_timeout = 50")  # the service waits 30 s; the test need not
    other = sqlite3.connect(store.path, isolation_level=None)
    other.execute("BEGIN IMMEDIATE")
    try:
        for payload in (wire.received_query(DEVICE, 9), b"junk"):
            replies = list(client.get(agent.keys["received"], payload=payload, timeout=3))
            assert [wire.parse_watermark_reply(r.ok.payload.to_bytes(), DEVICE)[0] for r in replies] == [3], payload
    finally:
        other.execute("ROLLBACK")
        other.close()
    agent.close()


def test_a_bad_received_question_is_dead_lettered_and_answered_all_the_same(setup):
    """A question on `received` whose payload is not one (a bug, a foreign client) moves no floor: it is kept as a
    dead letter with its reason and counted, and the watermark is answered as for a question without one."""
    store, _, client, factory, make_agent, service = setup
    agent = make_agent(client)
    agent.start()
    while agent.step():
        pass
    assert wait_for(lambda: store.contiguous_seq(DEVICE) == agent.seq)
    replies = list(client.get(agent.keys["received"], payload=b'{"device": "drive-t", "gone_below": -3}', timeout=2))
    assert [wire.parse_watermark_reply(r.ok.payload.to_bytes(), DEVICE)[0] for r in replies] == [agent.seq]
    (letter,) = store.dead_letters()
    assert letter["reason"] == "schema" and "not a received question for drive-t" in letter["detail"]
    assert letter["key_expr"] == agent.keys["received"] and service.counters.ingested["schema"] == 1
    agent.close()


def test_windows_numbered_before_the_service_answers_are_sent_once_it_has(setup, tmp_path):
    """An agent whose questions go unanswered keeps its windows back (their seq and time may still have to move)
    and sends them once the service has said where it stands: nothing is refused, nothing renumbered."""
    store, _, client, factory, _, _ = setup
    outbox = tmp_path / "kept.sqlite"
    _first_three_windows(store, client, factory, outbox)
    agent = EdgeAgent(DEVICE, _replay()(), client, Outbox(outbox), factory)
    asked = agent._get
    agent._get = lambda key, payload=None: None  # the questions lost on the way
    agent.start()
    while agent.step():
        pass
    assert not agent.resumed and len(agent.outbox) == 3
    time.sleep(0.5)
    assert len(store.windows(DEVICE)) == 3  # held back
    agent._get = asked
    try:
        assert agent.drain()
    finally:
        agent.close()
    assert [w["seq"] for w in store.windows(DEVICE)] == [1, 2, 3, 4, 5, 6] and agent.seq == 6
    assert store.dead_letters() == []


def test_held_windows_moved_at_the_next_start_are_followed_by_that_process_s_own(setup, tmp_path):
    """The outbox lost and the service away: a process numbers two windows, holds them and stops; the service is
    back when the next one starts. Its windows follow the two it moved at start, in seq and in drive time (a
    second reader's script stored the same stretch of drive time twice: the clock started at 0 again)."""
    store, router, client, factory, _, service = setup
    _first_three_windows(store, client, factory, tmp_path / "first.sqlite")
    service.stop()
    later, outbox = _replay(SEED + 1), tmp_path / "new.sqlite"
    away = EdgeAgent(DEVICE, later(), client, Outbox(outbox), factory)
    away.start()
    assert away.step() and away.step()
    away.close()
    back = FleetService(store, router, refit_interval_s=0).start()
    try:
        agent = EdgeAgent(DEVICE, later(), client, Outbox(outbox), factory)
        agent.start()
        assert agent.resumed and agent.seq == 5
        agent.run()
        agent.close()
    finally:
        back.stop()
    stored = store.windows(DEVICE)
    assert [w["seq"] for w in stored] == list(range(1, 9)) and store.dead_letters() == []
    assert all(b["window_start"] > a["window_end"] for a, b in zip(stored, stored[1:]))


def test_a_watermark_with_a_bad_resume_point_still_lets_windows_go(setup, tmp_path):
    """A reply whose resume point is unusable (its window end null) is still a watermark: the agent goes on as
    with a service that names none, and does not hold its windows back for ever."""
    store, _, client, factory, _, _ = setup
    agent = EdgeAgent(DEVICE, _replay()(), client, Outbox(tmp_path / "o.sqlite"), factory)
    asked = agent._get

    def spoiled(key, payload=None):
        replies = asked(key, payload)
        if replies and key == agent.keys["received"]:
            body = json.loads(replies[0])
            replies = [json.dumps({**body, "max_seq": 1, "last_window_end": None}).encode()]
        return replies

    agent._get = spoiled
    agent.start()
    agent.run()
    agent.close()
    assert agent.resumed and [w["seq"] for w in store.windows(DEVICE)] == [1, 2, 3] and len(agent.outbox) == 0


def test_a_temperature_dead_from_the_start_still_gives_the_drive_a_finite_angle(setup, tmp_path):
    """A two-band set and a temperature channel that reads NaN from the agent's first sample (unplugged at boot):
    no finite reading to hold, so the angle is corrected at the bench's temperature (it was NaN for every sample)."""
    import numpy as np

    from encoder_core.correction import BandedCorrection, Correction
    from encoder_core.samples import Samples

    _, _, client, factory, _, _ = setup
    agent = EdgeAgent(DEVICE, SimulatedDrive(SEED, hours=1), client, Outbox(tmp_path / "dead.sqlite"), factory)
    warm = Correction.from_dict({**factory.bands[0].to_dict(), "temp_c": 45.0, "w": [1.01, 0.0, 1.0, 0.0]})
    agent.correction = BandedCorrection([factory.bands[0], warm])
    block = agent.source.read(60.0)
    block = Samples(t=block.t, d=block.d, q=block.q, temp_c=np.full(len(block), np.nan))
    angle = agent.correct(agent.at_die_temperature(block))
    assert np.all(np.isfinite(angle)) and angle.size == len(block)
    agent.close()


@pytest.mark.parametrize("term,value", [("w2", 40.0), ("w4", -3.0), ("w5", 500.0), ("zero_offset_rad", 1.5)])
def test_a_set_with_an_absurd_offset_or_axis_term_is_refused(setup, term, value):
    """check_plausible bounded the gains and harmonics only: a set with w2 = 40 (182° of error) or w5 = 500 was
    applied and saved. An offset or axis term more than half the circle's radius from the factory's is refused, and
    the refusal acknowledged."""
    store, _, client, factory, make_agent, _ = setup
    agent = make_agent(client)
    msg = coefficient_set(factory, 3)
    index = {"w2": 1, "w4": 3}.get(term)
    for band in msg["bands"]:
        if index is not None:
            band["w"][index] += value
        else:
            band[term] = value
    agent.on_coefficients(wire.encode("coefficients", msg))
    assert agent.version == 0 and agent.counters.refused and term in agent.counters.refused[0][1]
    good = coefficient_set(factory, 4, scale_w1=1.01)
    agent.on_coefficients(wire.encode("coefficients", good))
    assert agent.version == 4  # a set within the bounds still applies
    agent.close()


def test_an_outbox_that_refuses_windows_does_not_stop_the_agent(setup, tmp_path, caplog):
    """The outbox refuses its writes (here another writer holds its file past the busy timeout, as a full or failing
    disk refuses them): the windows it cannot keep are logged and counted, not sent and given no seq, and the agent
    goes on correcting and, once the outbox takes writes again, keeps and sends. Before, the outbox's error ended the
    agent, and the drive's correction with it; and a refused write left the outbox's transaction open, so that it
    refused every window after (this test's first version found it). A page limit as the full disk was not
    deterministic: the service's confirmations free pages as fast as the windows fill them."""
    import sqlite3

    store, _, client, factory, _, _ = setup
    path = tmp_path / "full.sqlite"
    outbox = Outbox(path)
    outbox.db.execute("PRAGMA busy_timeout = 50")  # the agent waits 5 s; the test need not
    agent = EdgeAgent(DEVICE, SimulatedDrive(SEED, hours=1), client, outbox, factory)
    agent.start()
    for _ in range(3):
        assert agent.step()
    other = sqlite3.connect(path, isolation_level=None)
    other.execute("BEGIN IMMEDIATE")
    try:
        for _ in range(5):
            assert agent.step()
    finally:
        other.execute("ROLLBACK")
        other.close()
    assert agent.counters.unsent_windows == 5 and caplog.text.count("the outbox refused it") == 5
    for _ in range(3):
        assert agent.step()
    assert agent.drain()
    assert [w["seq"] for w in store.windows(DEVICE, limit=1000)] == list(range(1, 7))  # no seq skipped
    agent.close()


def test_a_resume_point_past_any_drive_clock_is_refused():
    """A watermark reply naming a last window end of 1e12 s (windows end by 1e10) was taken, the held windows moved
    past it and refused by the service for ever; it is refused as a bad resume point."""
    reply = json.dumps({"device": DEVICE, "contiguous_seq": 3, "acked_version": 0, "max_seq": 3,
                        "last_window_end": 1e12}).encode()  # fmt: skip
    with pytest.raises(wire.WireError, match="bad resume point"):
        wire.parse_resume_point(reply, DEVICE)
    fine = json.dumps({"device": DEVICE, "contiguous_seq": 3, "max_seq": 3, "last_window_end": 5e4}).encode()
    assert wire.parse_resume_point(fine, DEVICE) == (3, 5e4)


def test_a_set_applied_just_before_the_process_ended_is_acknowledged_after_the_restart(setup):
    """The agent applies v7 and ends before its next block, which would have sent the ack (a power cut; every time
    when the set arrives in the step whose read ends the source). The restart resumes v7 silently; the watermark
    then says the service has no ack for it, and the agent sends 'applied' for v7 (the service clears a step's alarm
    on that ack, which never came)."""
    store, router, client, factory, make_agent, _ = setup
    agent = make_agent(client)
    agent.start()
    assert agent.step()
    router.put(f"encoders/{DEVICE}/coefficients", wire.encode("coefficients", coefficient_set(factory, 7, 1.02)))
    assert wait_for(lambda: agent.apply_inbox() or agent.version == 7)  # applied; its ack waits for a next block
    assert agent.pending_ack == 7
    agent.close()
    assert store.acked_version(DEVICE) == 0
    again = make_agent(client)
    again.start()
    assert again.version == 7
    for _ in range(3):
        assert again.step()
    assert wait_for(lambda: store.acked_version(DEVICE) == 7)
    assert [(a["version"], a["status"]) for a in store.acks(DEVICE)] == [(7, "applied")]
    again.close()


def test_a_drive_clock_stepped_back_while_the_agent_runs_does_not_hold_windows_for_ever(setup, caplog):
    """The drive's clock steps back two minutes while the agent runs (an NTP step, a controller whose clock restarts
    under a running agent). The agent continued its drive clock past the last window only at its first block, so
    the next windows started before the newest one stored ended: the service refused each as clock_backwards, the
    outbox held them and the contiguous watermark (and the drift monitor reading up to it) waited below them until
    the clock passed that window again (a day back: a day of windows, an outbox's two weeks when the clock restarts
    at 0), and they were stored then as resends, the same stretch of drive time twice. Now every block goes on after
    the last window issued, and the step is logged."""
    store, _, client, factory, make_agent, _ = setup
    agent = make_agent(client)
    agent.start()
    for _ in range(5):
        assert agent.step()
    agent.source.now -= 120.0  # the drive's clock, two minutes back
    for _ in range(5):
        assert agent.step()
    assert agent.drain(timeout_s=5.0)
    stored = store.windows(DEVICE)
    assert [w["seq"] for w in stored] == list(range(1, 11)) and store.contiguous_seq(DEVICE) == 10
    assert all(b["window_start"] > a["window_end"] for a, b in zip(stored, stored[1:]))
    assert store.dead_letters() == []
    assert "drive clock went back" in caplog.text
    agent.close()


def test_an_outbox_page_damaged_under_a_running_agent_stops_no_correction(setup, tmp_path):
    """The outbox's meta page is damaged on disk while the agent runs (the salvage runs only at open), so every read
    of it fails. The drive clock's continuation read the outbox's last window end at every block, before the block
    was corrected: each block raised, and the drive got no corrected angle while the outbox failed (before, only the
    first block read it; the window it cannot keep is logged and counted, and the agent corrects on). The end of the
    newest window issued is kept in memory with it now."""
    import sqlite3

    store, _, client, factory, _, _ = setup
    path = tmp_path / "damaged.sqlite"
    agent = EdgeAgent(DEVICE, SimulatedDrive(SEED, hours=1), client, Outbox(path), factory)
    agent.start()
    for _ in range(3):
        assert agent.step()
    agent.outbox.db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    (root,) = agent.outbox.db.execute("SELECT rootpage FROM sqlite_master WHERE name = 'meta'").fetchone()
    with open(path, "r+b") as f:  # the meta table's page, overwritten
        f.seek((root - 1) * 4096)
        f.write(b"\xff" * 4096)
    other = sqlite3.connect(path, isolation_level=None)
    other.execute("CREATE TABLE nudge (a)")  # another writer: the agent's connection reads its pages from disk again
    other.close()
    with pytest.raises(sqlite3.DatabaseError):
        agent.outbox.last_window_end()  # damaged, as SQLite says
    before = agent.die.last
    for _ in range(2):
        assert agent.step()  # corrected, and the window it could not keep counted
    assert agent.counters.unsent_windows == 2 and agent.seq == 3
    assert agent.die.last[0] > before[0]  # the die's estimate followed the blocks: they were corrected
    agent.close()


def test_a_temperature_reading_no_drive_can_have_costs_its_sample_not_the_window(setup, tmp_path):
    """A shorted thermistor reads +400 °C for a sample, a converter's garbage -1000 °C for another: past the wire's
    range (-273.15..300 °C), summed into the window's temperature, the wire refused the whole window (a minute of
    good hall samples), and the angle was corrected at the set's outermost band as if the drive were that hot or
    cold. Now such a reading is no reading, as a NaN one: its sample is rejected as non_finite, the window goes with
    its temperature from the others, and its angle is corrected at the die's last good estimate. A reading inside
    the range but past the set's bands (-200 °C) is held at the outermost band, never extrapolated."""

    from encoder_core.correction import BandedCorrection, Correction
    from encoder_core.samples import Samples

    store, _, _, factory, _, _ = setup

    def two_impossible(temp, _rng):
        temp[300], temp[1500] = 400.0, -1000.0  # one in each minute

    agent, t, s, temp = two_minutes_at_25_c(setup, tmp_path / "hot-outbox.sqlite", two_impossible)
    for window in store.monitor_windows(DEVICE, 0, 2):
        assert window["rejected_by_reason"]["non_finite"] == 1 and window["stats"].rejected == 1
        assert abs(window["temp_mean_c"] - 25.0) < 1.0 and window["stats"].temp_max < 30.0
    # the angle handed to the drive, through a set of a cold and a warm band
    cold = Correction.from_dict({**factory.bands[0].to_dict(), "temp_c": -40.0, "w": [1.2, 0.0, 1.0, 0.0]})
    warm = Correction.from_dict({**factory.bands[0].to_dict(), "temp_c": 85.0, "w": [0.8, 0.0, 1.0, 0.0]})
    agent.correction = BandedCorrection([cold, factory.bands[0], warm])
    block = Samples(t=t[:1200], d=s.d[:1200], q=s.q[:1200], temp_c=temp[:1200])
    angle = agent.correct(agent.at_die_temperature(agent.readable_temperatures(block)))
    held = agent.correction.angle(s.d[300:301], s.q[300:301], [agent.die.last[2]])  # at the last good estimate
    hot = agent.correction.angle(s.d[300:301], s.q[300:301], [85.0])  # what +400 °C read as before
    assert angle[300] == pytest.approx(held[0], abs=1e-12) and abs(angle[300] - hot[0]) > 1e-4
    assert agent.correction.at(-200.0).w1 == pytest.approx(1.2)  # held at the coldest band, no further
    agent.close()


def test_an_open_thermistor_inside_the_wires_range_is_refused_by_the_drives_own_rating(setup, tmp_path):
    """An open NTC thermistor reads -200 °C here: inside the wire's range, so without the drive's rating its sample
    was summed (the window's minimum -200 °C, its mean pulled 0.2 °C colder by one reading). With `--temp-range
    -40,150` (the drive's rating) it is a broken sensor's reading, rejected as a NaN one is, and a range outside the
    wire's, or upside down, is refused at start."""
    from edge_agent.outbox import Outbox as OutboxFile

    store, _, client, factory, _, _ = setup

    def open_circuit(temp, _rng):
        temp[300] = -200.0

    agent, *_ = two_minutes_at_25_c(setup, tmp_path / "rated.sqlite", open_circuit, temp_range_c=(-40.0, 150.0))
    first, second = store.monitor_windows(DEVICE, 0, 2)
    assert first["rejected_by_reason"]["non_finite"] == 1 and first["stats"].temp_min > 20.0
    assert second["rejected_by_reason"]["non_finite"] == 0
    agent.close()
    for bad in ((150.0, -40.0), (-300.0, 100.0), (0.0, 400.0)):
        with pytest.raises(InputError, match="temperature range"):
            EdgeAgent(DEVICE, SimulatedDrive(SEED, hours=1), client, OutboxFile(tmp_path / "x.sqlite"), factory,
                      temp_range_c=bad)  # fmt: skip


def test_an_outbox_damaged_on_disk_is_kept_aside_and_what_it_can_read_is_sent(setup, tmp_path, caplog):
    """The outbox's file damaged on disk (a power cut on a disk that lies about its writes: here one window's page
    overwritten) while the service was away. Opened, it failed its first read of that page: every window the
    agent made after it was refused by the outbox, none was ever sent again, and a file damaged in its first pages
    refused the agent's start (and the drive's correction with it). Now the damaged file is kept aside and a new
    outbox holds what it can read; the window lost is counted as dropped, the service is told it is gone, and the
    watermark passes it: every other window is stored."""
    import sqlite3

    store, router, client, factory, _, service = setup
    path = tmp_path / "damaged.sqlite"
    service.stop()  # away: the windows stay in the outbox
    agent = EdgeAgent(DEVICE, _replay(seconds=360.0)(), client, Outbox(path), factory)
    agent.start()
    while agent.step():
        pass
    assert len(agent.outbox) == 6
    (payload,) = [p for s, p in agent.outbox.pending() if s == 3]
    agent.close()
    agent.outbox.db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    agent.outbox.close()
    data = bytearray(path.read_bytes())
    page = data.find(payload[:200]) // 4096  # the page that holds window 3
    data[page * 4096 : (page + 1) * 4096] = b"\xff" * 4096
    path.write_bytes(bytes(data))
    with pytest.raises(sqlite3.DatabaseError):
        sqlite3.connect(path).execute("SELECT count(*) FROM outbox").fetchone()  # damaged, as SQLite says

    back = FleetService(store, router, refit_interval_s=0).start()
    try:
        outbox = Outbox(path)
        again = EdgeAgent(DEVICE, _replay(SEED + 1, seconds=120.0)(), client, outbox, factory)
        again.start()
        counters = again.run()  # its source to the end, then drained
        again.close()
        assert counters.outbox_errors == 0 and counters.unsent_windows == 0 and again.seq == 8
        assert [w["seq"] for w in store.windows(DEVICE)] == [1, 2, 4, 5, 6, 7, 8] and len(outbox) == 0
        assert back.watermark(DEVICE) == 8 and store.dead_letters() == []
        assert outbox.salvaged["windows"] == 5 and outbox.salvaged["lost"] == 1 and outbox.dropped == 1
        assert (tmp_path / "damaged.sqlite.corrupt").exists()  # kept as it was found
        assert "1 window(s) it held unreadable" in caplog.text
    finally:
        back.stop()


def _field_recording(t: np.ndarray, seed: int = SEED):
    """A drive recorded at times t, its temperature rising 1 °C a minute (a drive that heats, as a logger saw it)."""
    from encoder_core.samples import Samples
    from encoder_core.simulator import simulate

    rng = np.random.default_rng(seed)
    temp = 25.0 + (t - t[0]) / 60.0
    s, _ = simulate(drive_model(SEED), t - t[0], rng.uniform(0, 2 * np.pi, t.size), temp, rng)
    return Samples(t=t, d=s.d, q=s.q, temp_c=temp)


def test_a_recording_with_a_gap_is_replayed_in_blocks_of_its_own_clock(setup, tmp_path):
    """A field recording at unix times, its samples jittered, its logger stopped for an hour: each block of the
    replay took at least one sample, from the next block when its own stretch had none, so the hour after the gap
    came out as twelve windows of one sample each (and a 0.2 Hz recording with 10 s windows as one window per sample
    from the first gap on, for ever behind its clock). Now a stretch with no sample is skipped: every window the
    service stores lies within one block of the recording's clock from its first sample, none is empty, none spans
    the gap, and each has its share of samples and the drive's real heating rate."""
    from edge_agent.sources import ReplaySource

    store, _, client, factory, _, _ = setup
    rng = np.random.default_rng(SEED)
    t0 = 1_700_000_000.0
    before = np.arange(0.0, 600.0, 0.05)
    after = 600.0 + 3600.0 + np.arange(0.5, 600.0, 0.05)
    jitter = rng.uniform(-0.02, 0.02, before.size + after.size)  # irregular spacing
    jitter[0] = 0.0
    t = t0 + np.concatenate([before, after]) + jitter
    agent = EdgeAgent(DEVICE, ReplaySource(_field_recording(t)), client, Outbox(tmp_path / "gap.sqlite"), factory)
    agent.window_s = 300.0
    agent.start()
    counters = agent.run()
    assert counters.windows == 4 and counters.unsent_windows == 0
    assert wait_for(lambda: len(store.windows(DEVICE)) == 4)
    stored = store.monitor_windows(DEVICE, 0, 4)
    blocks = [int((w["window_start"] - t[0]) // 300.0) for w in stored]
    assert blocks == [0, 1, 14, 15]  # the gap is the blocks 2 to 13
    for w, k in zip(stored, blocks):
        assert t[0] + k * 300.0 <= w["window_start"] <= w["window_end"] < t[0] + (k + 1) * 300.0
        assert 5900 <= w["stats"].n <= 6010, w["stats"].n
        assert abs(w["temp_rate_c_per_s"] - 1 / 60.0) < 1e-3  # the heating, not a jump across the gap
    agent.close()

    # a recording far slower than its windows: two samples or none in each 10 s, and an hour missing
    t = t0 + np.concatenate([np.arange(0.0, 600.0, 5.0), 4200.0 + np.arange(0.0, 600.0, 5.0)])
    source = ReplaySource(_field_recording(t))
    blocks = []
    while (block := source.read(10.0)) is not None:
        blocks.append((len(block), int((block.t[0] - t[0]) // 10.0), int((block.t[-1] - t[0]) // 10.0)))
    assert [n for n, _, _ in blocks] == [2] * 120
    assert all(first == last for _, first, last in blocks)  # each block's samples are of one 10 s of the clock
    assert source.now == t[-1]


def test_a_replay_paced_at_a_real_time_factor_takes_its_gaps_time(setup, tmp_path):
    """`--real-time-factor F` paces the drive's clock at F times real time. It counted windows made, so a replayed
    recording's hour with no sample (no window) went by in no time, and the service, which runs on the wall clock,
    saw the drive's time jump. Now the pace follows the drive's clock: ten minutes, two hours missing, ten minutes
    at 3600x take 140 / 60 s, not the 20 / 60 s of the four windows made."""
    from edge_agent.sources import ReplaySource

    _, _, client, factory, _, _ = setup
    t = 1_700_000_000.0 + np.concatenate([np.arange(0.0, 600.0, 0.5), 7800.0 + np.arange(0.0, 600.0, 0.5)])
    agent = EdgeAgent(DEVICE, ReplaySource(_field_recording(t)), client, Outbox(tmp_path / "paced.sqlite"), factory)
    agent.window_s = 300.0
    agent.start()
    started = time.monotonic()
    counters = agent.run(real_time_factor=3600.0)
    took = time.monotonic() - started
    assert counters.windows == 4
    assert took >= (t[-1] - t[0]) / 3600.0 - 0.1, took
    agent.close()


def test_a_retired_drives_agent_holds_its_windows_and_sends_them_once_reinstated(setup, caplog):
    """The watermark reply says the drive is retired: the agent stops sending (each window was refused, and its
    outbox resent every few seconds) and keeps what it makes; reinstated, it sends them all, and none is lost."""
    store, _, client, _, make_agent, service = setup
    agent = make_agent(client)
    agent.start()
    try:
        for _ in range(2):
            assert agent.step()
        assert wait_for(lambda: store.max_seq(DEVICE) == 2)
        store.retire_device(DEVICE, by="token 1", note="replaced")
        with caplog.at_level("WARNING", logger="edge_agent"):
            assert wait_for(lambda: agent.sync() and agent.retired)
            for _ in range(3):
                assert agent.step()
        assert "the service has retired this drive" in caplog.text
        refused = service.counters.ingested.get("device_retired", 0)
        assert refused == 0 and store.dead_letters() == []  # nothing sent after the reply said so
        assert store.max_seq(DEVICE) == 2 and len(agent.outbox) == 3
        store.reinstate_device(DEVICE, by="token 1", note="not replaced after all")
        assert wait_for(lambda: agent.sync() and not agent.retired)
        assert wait_for(lambda: agent.sync() and store.contiguous_seq(DEVICE) == 5)
        assert agent.drain()
    finally:
        agent.close()


def test_a_retired_drives_agent_restarted_sends_nothing_and_keeps_what_it_makes(setup, caplog):
    """Restarted while its drive is retired, the agent learns it from the question it asks at start, before its first
    window: it sent that window (refused, a dead letter) and only the sync after it said the drive was retired."""
    store, _, client, _, make_agent, service = setup
    agent = make_agent(client)
    agent.start()
    assert agent.step()
    assert wait_for(lambda: store.max_seq(DEVICE) == 1)
    store.retire_device(DEVICE, by="token 1", note="on the test bench")
    assert wait_for(lambda: agent.sync() and agent.retired)
    agent.close()
    again = make_agent(client)  # a new process: its outbox, and nothing of what the last one heard
    with caplog.at_level("WARNING", logger="edge_agent"):
        again.start()
    try:
        assert again.retired and "the service has retired this drive" in caplog.text
        for _ in range(2):
            assert again.step()
        assert len(again.outbox) == 2 and store.max_seq(DEVICE) == 1
        store.reinstate_device(DEVICE, by="token 1", note="back on the line")
        assert wait_for(lambda: again.sync() and store.contiguous_seq(DEVICE) == 3)
        assert service.counters.ingested.get("device_retired", 0) == 0 and store.dead_letters() == []
    finally:
        again.close()


def test_a_retired_drives_agent_keeps_the_ack_of_a_set_it_applies_until_reinstated(setup):
    """A set that reaches the drive after it was retired (published just before): the agent runs it and keeps its
    ack with its windows; it sent the ack at once, refused as the drive's, and only the reinstatement's resend
    stored it."""
    store, router, client, factory, make_agent, service = setup
    agent = make_agent(client)
    agent.start()
    try:
        assert agent.step()
        assert wait_for(lambda: store.max_seq(DEVICE) == 1)
        store.retire_device(DEVICE, by="token 1", note="on the test bench")
        assert wait_for(lambda: agent.sync() and agent.retired)
        router.put(f"encoders/{DEVICE}/coefficients", wire.encode("coefficients", coefficient_set(factory, 5, 1.01)))
        assert wait_for(lambda: agent.apply_inbox() or agent.version == 5)  # acknowledged at the next block
        assert agent.step() and agent.outbox.pending_acks() == [5]
        store.reinstate_device(DEVICE, by="token 1", note="back on the line")
        assert wait_for(
            lambda: agent.sync() and [(a["version"], a["status"]) for a in store.acks(DEVICE)] == [(5, "applied")]
        )
        assert service.counters.ingested.get("device_retired", 0) == 0 and store.dead_letters() == []
    finally:
        agent.close()
