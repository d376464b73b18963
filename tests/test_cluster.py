"""Several service processes share one fleet (issue 13, service/cluster.py): real agent processes, a real
router, a real PostgreSQL server; a second service process joins mid-run and is killed with SIGKILL later."""

import json
import signal
import subprocess
import sys
import threading
import time
import urllib.request

import numpy as np
import pytest

from fleet_wire import keys
from fleet_wire.session import free_port, loopback_endpoint
from service.cluster import owner, shares
from service.runtime import FleetService, open_session
from service.store import Store


def test_partitions_are_shared_out_and_a_newcomer_only_takes():
    rng = np.random.default_rng(13)
    members = [f"svc-{i}" for i in rng.choice(1000, size=4, replace=False)]
    for n in range(1, 5):
        shared = [shares(m, members[:n]) for m in members[:n]]
        assert set().union(*shared) == set(range(keys.PARTITIONS))  # every partition served ...
        assert sum(map(len, shared)) == keys.PARTITIONS  # ... by exactly one process
        assert min(map(len, shared)) >= keys.PARTITIONS / n / 2.5  # none starved
        if n > 1:  # the newcomer takes from the others; nothing moves between the others
            before = {p: owner(p, members[: n - 1]) for p in range(keys.PARTITIONS)}
            after = {p: owner(p, members[:n]) for p in range(keys.PARTITIONS)}
            assert all(after[p] in (before[p], members[n - 1]) for p in range(keys.PARTITIONS))


def devices_split(members, per_member):
    """Device names whose partitions fall to each member (the test knows the hash; the service just serves)."""
    picked = {m: [] for m in members}
    i = 0
    while any(len(v) < per_member for v in picked.values()):
        name = f"drive-{i:03d}"
        who = owner(keys.partition(name), members)
        if len(picked[who]) < per_member:
            picked[who].append(name)
        i += 1
    return picked


def start_agent(name, endpoint, outbox, hours):
    return subprocess.Popen(
        [sys.executable, "-m", "encoder_fleet.cli", "agent", "--device", name, "--connect", endpoint]
        + ["--sim-hours", str(hours), "--real-time-factor", "300", "--outbox", str(outbox), "--insecure"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


def assert_each_window_once(store, names, windows):
    """Every seq 1..windows of every drive stored once, and counted once in its band's sum (a sum kept from before a
    hand-over or a lost session would count some twice or miss some)."""
    for name in names:
        seqs = [w["seq"] for w in store.windows(name, limit=10_000)]
        assert sorted(seqs) == list(range(1, windows + 1)), name  # none lost, none twice
        in_bands = sum(count for _, count, _ in store.band_stats(name).values())
        assert in_bands == windows, name


def get_json(url):
    with urllib.request.urlopen(url, timeout=5) as reply:
        return json.loads(reply.read())


def wait_for(condition, timeout_s, what):
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.2)


def test_a_process_joins_mid_run_takes_its_partitions_and_dies_without_a_window_lost_or_doubled(tmp_path, postgres_url):
    endpoint = loopback_endpoint()
    store = Store.open(postgres_url)  # band sums keep every window: their counts must equal the windows stored
    session = open_session(listen=[endpoint])
    a = FleetService(store, session, refit_interval_s=0.5, member="svc-a").start()
    hours = 5  # 300 windows a drive, one every 0.2 s
    fleet = devices_split(["svc-a", "svc-b"], per_member=3)
    names = sorted(fleet["svc-a"] + fleet["svc-b"])
    agents = [start_agent(n, endpoint, tmp_path / f"{n}.sqlite", hours) for n in names]
    b, stopped = None, False
    try:
        wait_for(lambda: a.partitions.held == frozenset(range(keys.PARTITIONS)), 10, "svc-a to serve everything")
        wait_for(lambda: len(store.device_ids()) == len(names), 30, "every drive to be heard")
        time.sleep(3)

        http = free_port()
        b = subprocess.Popen(
            [sys.executable, "-m", "encoder_fleet.cli", "service", "--member", "svc-b", "--connect", endpoint]
            + ["--db", postgres_url, "--insecure", "--http-port", str(http), "--refit-interval", "0.5"],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        mine = shares("svc-a", ["svc-a", "svc-b"])
        wait_for(lambda: a.partitions.held == frozenset(mine), 30, "svc-a to hand svc-b its partitions")
        wait_for(lambda: _served(http) == sorted(map(keys.partition_chunk, set(range(64)) - mine)), 30, "svc-b")
        stored_by_a = dict(a.cluster()["stored_by_partition"])
        time.sleep(4)  # both serve; each receives only its own partitions' windows
        on_b = get_json(f"http://127.0.0.1:{http}/cluster")
        assert on_b["member"] == "svc-b" and on_b["members"] == ["svc-a", "svc-b"]
        b_parts = {keys.partition_chunk(keys.partition(n)) for n in fleet["svc-b"]}
        assert set(on_b["stored_by_partition"]) == b_parts  # svc-b stored windows of its drives only ...
        now_a = a.cluster()["stored_by_partition"]
        assert all(now_a[p] == stored_by_a[p] for p in b_parts)  # ... and svc-a none of them meanwhile
        assert any(now_a[p] > stored_by_a.get(p, 0) for p in now_a if p not in b_parts)  # but of its own

        b.send_signal(signal.SIGKILL)  # mid-run: its partitions come back to svc-a
        b.wait(timeout=10)
        wait_for(lambda: a.partitions.held == frozenset(range(keys.PARTITIONS)), 30, "svc-a to take everything back")
        outputs = [agent.communicate(timeout=180)[0] for agent in agents]
        assert all(agent.returncode == 0 for agent in agents), outputs
        a.stop()  # what is queued is stored, then we count
        stopped = True
        assert_each_window_once(store, names, hours * 60)
    finally:
        if b is not None and b.poll() is None:
            b.kill()
        for agent in agents:
            if agent.poll() is None:
                agent.kill()
        if not stopped:
            a.stop()
        session.close()
        store.close()


def _served(http):
    try:
        return get_json(f"http://127.0.0.1:{http}/cluster")["served"]
    except OSError:
        return None


def test_meshed_routers_carry_each_drive_to_the_process_serving_it(tmp_path, pki, postgres_url):
    """compose's scale profile in one process: two routers from `pki router-config` (TLS, client certificates,
    the registry's ACL, one connected to the other; the Python package's router stands in for zenohd), two
    service members each a client of its own router, and drives on either router."""
    import wire_samples as ws
    import zenoh
    from conftest import DEVICES

    from encoder_fleet.pki import issue, router_config
    from fleet_wire import messages as wire
    from fleet_wire.security import ROLE_DEVICE, ROLE_ROUTER, Identity
    from fleet_wire.session import session_config
    from service.guard import service_security

    for name in ("router-1", "router-2"):
        issue(pki, name, ROLE_ROUTER, force=True)
    one, two = (loopback_endpoint().replace("tcp/", "tls/") for _ in range(2))
    routers = [
        zenoh.open(
            zenoh.Config.from_json5(json.dumps(router_config(pki, "router-1", listen=[one], peers=["router-2"])))
        ),
        zenoh.open(
            zenoh.Config.from_json5(
                json.dumps(router_config(pki, "router-2", listen=[two], connect=[one], peers=["router-1"]))
            )
        ),
    ]
    members = ["svc-1", "svc-2"]
    stores = [Store.open(postgres_url) for _ in members]
    sessions = [open_session(connect=[endpoint], pki=pki) for endpoint in (one, two)]
    services = [
        FleetService(store, session, refit_interval_s=0, member=m, **service_security(store, pki)).start()
        for store, session, m in zip(stores, sessions, members)
    ]
    drives = {}
    try:
        wait_for(lambda: all(s.cluster()["members"] == members for s in services), 20, "the members to see each other")
        # each its own share: a sum of 64 is met too while the first member still holds every partition
        wait_for(
            lambda: all(s.partitions.held == shares(s.partitions.member, members) for s in services),
            20,
            "the partitions shared",
        )
        by_member = {m: [d for d in DEVICES if owner(keys.partition(d), members) == m][:2] for m in members}
        names = by_member["svc-1"] + by_member["svc-2"]  # two of each; svc-1's on router-1, then router-2, ...
        for i, name in enumerate(names):  # half the drives on each router, whoever serves them
            identity = Identity.load(pki, name, ROLE_DEVICE)
            drives[name] = zenoh.open(session_config("client", connect=[(one, two)[i % 2]], identity=identity))
        deadline = time.monotonic() + 30
        while missing := [n for n in names if (stores[0].device(n) or {}).get("windows") != 3]:
            assert time.monotonic() < deadline, f"timed out waiting for the windows of {missing}"
            # as an agent does, what is not stored yet goes again: a put made before the mesh has a route for the
            # drive's key is dropped (a loaded CI machine: the routers took longer than a fixed pause), and the
            # store keeps a window sent twice once (counted as a duplicate, not as stored: the check below)
            for name in missing:
                for seq in (1, 2, 3):
                    drives[name].put(keys.key(name, keys.STATS), wire.encode("window", ws.window(name, seq)))
            time.sleep(1.0)
        for name, session in drives.items():  # the watermark comes back across the mesh from the serving process
            replies = [r.ok.payload.to_bytes() for r in session.get(keys.key(name, keys.RECEIVED), timeout=3) if r.ok]
            assert [wire.parse_watermark(p, name) for p in replies] == [3], name
        for service, member in zip(services, members):
            stored = service.cluster()["stored_by_partition"]
            expected = {keys.partition_chunk(keys.partition(n)): 0 for n in by_member[member]}
            for n in by_member[member]:
                expected[keys.partition_chunk(keys.partition(n))] += 3
            assert stored == expected  # its drives' windows, whichever router they came through, and nobody else's
    finally:
        for session in drives.values():
            session.close()
        for service in services:
            service.stop()
        for session in sessions + routers[::-1]:
            session.close()
        for store in stores:
            store.close()


def _drop_sessions(url):
    """What a PostgreSQL restart or failover does to the service: every session but ours ended by the server."""
    import psycopg

    with psycopg.connect(url, autocommit=True) as admin:
        return admin.execute(
            "SELECT count(pg_terminate_backend(pid)) FROM pg_stat_activity "
            "WHERE datname = current_database() AND pid <> pg_backend_pid()"
        ).fetchone()[0]


def _partition_locks(url):
    import psycopg

    from service.store import PARTITION_LOCKS

    with psycopg.connect(url, autocommit=True) as admin:
        return admin.execute(
            "SELECT count(*) FROM pg_locks WHERE locktype = 'advisory' AND classid = %s AND granted",
            (PARTITION_LOCKS,),
        ).fetchone()[0]


def test_sessions_dropped_by_the_database_mid_run_lose_and_double_nothing(tmp_path, postgres_url):
    endpoint = loopback_endpoint()
    store = Store.open(postgres_url)
    session = open_session(listen=[endpoint])
    a = FleetService(store, session, refit_interval_s=0.5, member="svc-a").start()
    hours, names = 3, ["drive-000", "drive-001", "drive-002"]
    agents = [start_agent(n, endpoint, tmp_path / f"{n}.sqlite", hours) for n in names]
    stopped = False
    try:
        wait_for(lambda: _partition_locks(postgres_url) == keys.PARTITIONS, 20, "svc-a to lock every partition")
        wait_for(lambda: len(store.device_ids()) == len(names), 30, "every drive to be heard")
        dropped = 0
        for _ in range(2):  # twice, mid-run
            time.sleep(3)
            dropped += _drop_sessions(postgres_url)
        assert dropped >= 2  # the writer's session and the read pool's at least
        wait_for(lambda: a.counters.database_reconnects >= 1, 30, "the service to open its session again")
        wait_for(
            lambda: (
                a.partitions.held == frozenset(range(keys.PARTITIONS))
                and _partition_locks(postgres_url) == keys.PARTITIONS
            ),
            30,
            "the partitions taken and locked again",
        )
        outputs = [agent.communicate(timeout=180)[0] for agent in agents]
        assert all(agent.returncode == 0 for agent in agents), outputs
        # every loop outlived the drops (a read refused between two statements once killed the refit thread)
        assert all(t.is_alive() for t in (a._writer, a._thread, a._monitor_thread, a._control_thread))
        a.stop()
        stopped = True
        assert_each_window_once(store, names, hours * 60)
    finally:
        for agent in agents:
            if agent.poll() is None:
                agent.kill()
        if not stopped:
            a.stop()
        session.close()
        store.close()


def test_members_starting_together_migrate_a_new_database_once(postgres_url):
    """Several members start at once on an empty database (compose's scale profile, bench-scale): PostgreSQL's
    CREATE TABLE IF NOT EXISTS is not safe against itself, so migrating is serialised by an advisory lock."""
    opened, failed = [], []

    def open_store():
        try:
            opened.append(Store.open(postgres_url))
        except Exception as exc:  # what the member would have died of
            failed.append(exc)

    threads = [threading.Thread(target=open_store) for _ in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    try:
        assert failed == [] and len(opened) == 6
        versions = [v for v, _ in opened[0].migrations()]
        assert versions == sorted(set(versions))  # each migration applied once
    finally:
        for store in opened:
            store.close()


def test_members_with_embedded_routers_mesh_them_with_mesh(postgres_url):
    """`service --mesh`: each member embeds a router and the second connects it to the first's; a drive on either
    router reaches the member that serves it, and its watermark comes back."""
    import wire_samples as ws
    import zenoh

    from fleet_wire import messages as wire
    from fleet_wire.session import session_config

    one, two = loopback_endpoint(), loopback_endpoint()
    members = ["svc-1", "svc-2"]
    stores = [Store.open(postgres_url) for _ in members]
    sessions = [open_session(listen=[one]), open_session(listen=[two], mesh=[one])]
    services = [
        FleetService(store, session, refit_interval_s=0, member=m).start()
        for store, session, m in zip(stores, sessions, members)
    ]
    drives = []
    try:
        wait_for(lambda: all(s.cluster()["members"] == members for s in services), 20, "the members to see each other")
        # each its own share: a sum of 64 is met too while the first member still holds every partition
        wait_for(
            lambda: all(s.partitions.held == shares(s.partitions.member, members) for s in services),
            20,
            "the partitions shared",
        )
        names = devices_split(members, per_member=2)
        crossed = [
            (names["svc-1"][0], two),
            (names["svc-2"][0], one),
            (names["svc-1"][1], one),
            (names["svc-2"][1], two),
        ]
        for name, endpoint in crossed:
            drives.append((name, zenoh.open(session_config("client", connect=[endpoint]))))

        def stored(name):
            return (stores[0].device(name) or {}).get("windows") == 1

        # like an agent, put again until stored: a put before the routers have exchanged their subscribers is
        # dropped (on a loaded machine 0.5 s was not always enough)
        deadline = time.monotonic() + 30
        while not all(stored(n) for n, _ in drives) and time.monotonic() < deadline:
            for name, session in drives:
                if not stored(name):
                    session.put(keys.key(name, keys.STATS), wire.encode("window", ws.window(name, 1)))
            time.sleep(1.0)
        assert all(stored(n) for n, _ in drives), "every window"
        for name, session in drives:
            replies = [r.ok.payload.to_bytes() for r in session.get(keys.key(name, keys.RECEIVED), timeout=3) if r.ok]
            assert [wire.parse_watermark(p, name) for p in replies] == [1], name
        for service, member in zip(services, members):
            assert sum(service.cluster()["stored_by_partition"].values()) == 2, member  # its own two drives
    finally:
        for _, session in drives:
            session.close()
        for service in services:
            service.stop()
        for session in sessions[::-1]:
            session.close()
        for store in stores:
            store.close()


class HeldMidDevice:
    """Wraps one of a service's methods: its first call for `device` stops in the middle of the pass (`inside` set)
    until `go` is set, as a slow fit or a long page of windows would; `after`: once the real call has returned.
    Every other call goes straight through."""

    def __init__(self, obj, name, device, *, after=False):
        self.inside, self.go, self.device, self.after = threading.Event(), threading.Event(), device, after
        self._real, self._held = getattr(obj, name), False
        setattr(obj, name, self)

    def __call__(self, device, *args, **kwargs):
        if device != self.device or self._held:
            return self._real(device, *args, **kwargs)
        self._held = True
        result = self._real(device, *args, **kwargs) if self.after else None
        self.inside.set()
        assert self.go.wait(60), "the test never let the pass go on"
        return result if self.after else self._real(device, *args, **kwargs)


def handed_over_mid_device(postgres_url, setup, hold, work, more=None):
    """svc-a serves every partition and is stopped in the middle of one of svc-b's devices (`hold(a, device)`, a
    HeldMidDevice, inside `work(a)` on a thread of its own) when svc-b joins. If svc-b takes the device's partition
    while svc-a is still there (the code before), svc-b's `work(b)` runs then; otherwise once svc-a let go of it.
    `more(b, device)`, then `work(b)` again, after svc-b's first work. Returns (device, what work(a) returned, what
    each work(b) returned, in order). `setup(store, device)` stores what the device has before svc-a starts."""
    members = ["svc-a", "svc-b"]
    device = devices_split(members, per_member=1)["svc-b"][0]
    part = keys.partition(device)
    endpoint = loopback_endpoint()
    stores = [Store.open(postgres_url) for _ in members]
    setup(stores[0], device)
    sessions = [open_session(listen=[endpoint]), open_session(connect=[endpoint])]
    a = FleetService(stores[0], sessions[0], refit_interval_s=0, monitor_interval_s=0, member="svc-a").start()
    b, held, by_a, by_b = None, None, [], []
    worker = threading.Thread(target=lambda: by_a.append(work(a)), name="svc-a's pass")

    def b_works():
        by_b.append(work(b))
        if more is not None and len(by_b) == 1:
            more(b, device)
            by_b.append(work(b))

    try:
        wait_for(lambda: a.partitions.held == frozenset(range(keys.PARTITIONS)), 20, "svc-a to serve everything")
        held = hold(a, device)
        worker.start()
        assert held.inside.wait(30), "svc-a's pass never reached the device"
        b = FleetService(stores[1], sessions[1], refit_interval_s=0, monitor_interval_s=0, member="svc-b").start()
        wait_for(lambda: a.cluster()["members"] == members, 20, "svc-a to see svc-b")
        deadline = time.monotonic() + 5  # svc-a hands over at once; svc-b tries its claim again every 0.5 s
        while time.monotonic() < deadline and part not in b.partitions.held:
            time.sleep(0.1)
        if part in b.partitions.held:  # while svc-a's pass is in the middle of the device
            b_works()
        held.go.set()
        worker.join(60)
        assert not worker.is_alive() and len(by_a) == 1, "svc-a's pass did not end"
        wait_for(lambda: part in b.partitions.held, 30, "svc-b to take the device's partition")
        if not by_b:
            b_works()
        return device, by_a[0], by_b
    finally:
        if held is not None:
            held.go.set()
        if worker.is_alive():
            worker.join(60)
        for service in (b, a):
            if service is not None:
                service.stop()
        for session in sessions[::-1]:
            session.close()
        for store in stores:
            store.close()


def test_a_refit_in_the_middle_of_a_device_ends_before_its_partition_is_handed_over(postgres_url):
    """The refit pass checked once that this process serves the device, then worked on it (read, decided, issued a
    set): a hand-over in between let the new owner answer the same refused set as well, and the device got two
    rollbacks for one refusal (or one version twice, a conflict). Now a partition is let go of only once the work in
    hand on its devices is done, and the new owner finds the refusal answered."""
    import wire_samples as ws

    from fleet_wire import messages as wire

    def refused_set(store, device):
        factory = wire.coefficients_message(device, 0, 0.0, "factory", ws.coefficients(device)["bands"])
        store.insert_coefficient_set(factory)
        store.mark_published(device, 0)
        store.insert_coefficient_set(ws.coefficients(device, 1, 100.0), state="trial")
        store.mark_published(device, 1)
        store.insert_ack(ws.ack(device, 1, at=160.0, status="rejected"))

    device, by_a, by_b = handed_over_mid_device(
        postgres_url,
        refused_set,
        hold=lambda a, device: HeldMidDevice(a, "_issue_set", device),  # decided: v1 is rolled back, v0 restored
        work=lambda service: service.refit_all(),
    )
    with Store.open(postgres_url) as store:
        history = {h["version"]: h for h in store.coefficient_history(device)}
        rolled_back = [e for e in store.set_events(device) if e["version"] == 1 and e["state"] == "rolled_back"]
    assert sorted(history) == [0, 1, 2]  # one answer to one refusal
    assert history[2]["basis"] == "rollback" and history[2]["restores_version"] == 0
    assert by_a == [2] and by_b == [[]]  # svc-a's, and svc-b found nothing to answer
    assert len(rolled_back) == 1


def test_a_monitor_pass_in_the_middle_of_a_device_ends_before_its_partition_is_handed_over(postgres_url):
    """The monitor pass checked once that this process serves the device, then fed it a page of windows: a
    hand-over in between let the new owner feed the same windows and the next ones, and the old owner then wrote
    its state over the new owner's (from there a restart feeds windows a second time, an alarm among them raised
    again). Now a partition is let go of only once the page in hand is fed and written."""
    import wire_samples as ws

    first, then = 20, 20

    def store_windows(store, device, seqs):
        with store.transaction():
            for seq in seqs:
                store.insert_window(ws.window(device, seq))

    def monitor_pass(service):  # every device it serves has windows to feed, as after a batch stored
        with service._lock:
            service._monitor_changed.update(service.store.device_ids())
        return service.monitor_pass()

    device, _, by_b = handed_over_mid_device(
        postgres_url,
        lambda store, device: store_windows(store, device, range(1, first + 1)),
        hold=lambda a, device: HeldMidDevice(a.store, "monitor_windows", device, after=True),  # a page read
        work=monitor_pass,
        more=lambda b, device: store_windows(b.store, device, range(first + 1, first + then + 1)),
    )
    with Store.open(postgres_url) as store:
        _, last_seq = store.monitor_states(device)[device]
    assert last_seq == first + then  # the newest state stands


def test_a_member_name_ending_in_a_newline_is_no_member_name(tmp_path):
    """The rule's "$" matched before a trailing newline (re.match): "svc-1\\n" was a member name, a second line in
    the members' keys and logs; the command line's check was a full match already, the service's was not."""
    session = open_session(listen=[loopback_endpoint()])
    try:
        with Store.open(tmp_path / "fleet.sqlite") as store:
            with pytest.raises(ValueError, match="member name"):
                FleetService(store, session, member="svc-1\n")
    finally:
        session.close()
