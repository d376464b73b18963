"""The REST API: the real app over a real SQLite file, through TestClient."""

import io
import json

import pytest
from fastapi.testclient import TestClient
from mcap.reader import make_reader
from pg_locks import wait_for_a_lock_wait
from wire_samples import ack, coefficients, window

from fleet_wire import keys
from fleet_wire import messages as wire
from service.api import create_app
from service.mcap_export import window_record
from service.store import Store

DEVICE = "drive-001"


@pytest.fixture
def client(store):
    with TestClient(create_app(store)) as c:
        yield c


@pytest.fixture
def history(store):
    """Three windows at factory coefficients, a fit, set v1 published and applied, two windows on v1."""
    for seq in range(1, 6):
        store.insert_window(
            window(
                seq=seq,
                version=0 if seq <= 3 else 1,
                quality=0.3 if seq <= 3 else 0.1,
                temp_c=23.0 if seq != 2 else 33.0,
            ),
            received_at=1000.0 + seq,
        )
    store.record_fit(DEVICE, 2, {"w": [1, 0, 1, 0]}, {"samples": 800, "residual_rms_rad": 0.004}, created_at=190.0)
    store.record_fit(DEVICE, 2, {"w": [1, 0, 1, 0]}, {"samples": 1200, "residual_rms_rad": 0.002}, created_at=195.0)
    store.insert_coefficient_set(coefficients(version=1, created_at=200.0))
    store.mark_published(DEVICE, 1, at=1004.0)
    store.insert_ack(ack(version=1, at=210.0), received_at=1004.5)
    store.insert_coefficient_set(coefficients(version=2, created_at=280.0, bands=(2, 3)))
    store.set_online(DEVICE, True, at=1006.0)
    store.insert_window(window("drive-002", 1))
    store.dead_letter(keys.key("drive-001", keys.STATS), "not_json", "window message: not JSON", b"\xffjunk")


def test_devices(client, history):
    got = client.get("/devices").json()
    assert [d["id"] for d in got] == [DEVICE, "drive-002"]
    d = got[0]
    assert d == {
        "id": DEVICE,
        "first_seen": 1001.0,
        "last_seen": 1006.0,
        "online": True,
        "current_version": 1,
        "windows": 5,
        "state": "unknown",  # no window monitored yet
        "retired": None,
        "labels": {},
    }
    assert client.get(f"/devices/{DEVICE}").json() == {**d, "retirements": []}


def test_health(client, history, store):
    h = client.get(f"/devices/{DEVICE}/health").json()
    assert h["online"] is True and h["last_seen"] == 1006.0
    assert h["coefficients"] == {"in_use": 1, "latest_published": 1, "latest": 2}
    assert h["angle_error"]["latest_deg"] == 0.1
    assert h["angle_error"]["mean_recent_deg"] == pytest.approx((3 * 0.3 + 2 * 0.1) / 5)
    assert h["bands"] == [
        {
            "band": 2,
            "fit_id": 2,
            "created_at": 195.0,
            "samples": 1200,
            "quality": {"samples": 1200, "residual_rms_rad": 0.002},
        }
    ]
    wins = store.windows(DEVICE)
    assert h["samples"] == sum(w["samples"] for w in wins) and h["windows"] == 5
    assert h["rejected_share"] == sum(w["rejected"] for w in wins) / (h["samples"] + h["rejected"])


def test_health_of_a_device_known_only_by_liveliness(client, store):
    store.set_online("drive-009", True, at=5.0)
    h = client.get("/devices/drive-009/health").json()
    assert h["coefficients"] == {"in_use": None, "latest_published": None, "latest": None}
    assert h["angle_error"]["latest_deg"] is None and h["rejected_share"] is None and h["bands"] == []


def test_coefficients_newest_first_with_acks(client, history, store):
    got = client.get(f"/devices/{DEVICE}/coefficients").json()
    assert [s["version"] for s in got["sets"]] == [2, 1]
    v2, v1 = got["sets"]
    assert v1["published_at"] == 1004.0 and v2["published_at"] is None
    assert v1["acks"] == [ack(version=1, at=210.0)] and v2["acks"] == []
    assert v2["message"] == store.current_coefficients(DEVICE)


def test_windows_range_and_stats(client, history, store):
    got = client.get(f"/devices/{DEVICE}/windows", params={"from": 60, "to": 180}).json()
    assert [w["seq"] for w in got["windows"]] == [2, 3, 4] and got["count"] == 3 and not got["truncated"]
    assert all("stats" not in w for w in got["windows"])
    full = client.get(f"/devices/{DEVICE}/windows", params={"stats": "true"}).json()["windows"]
    assert full == store.windows(DEVICE, stats=True)
    for w in full:
        wire.check("window", w)
    page = client.get(f"/devices/{DEVICE}/windows", params={"limit": 2}).json()
    assert [w["seq"] for w in page["windows"]] == [1, 2] and page["truncated"] and page["next"] == 2


def test_devices_are_paged_by_id_in_a_list_with_a_link_to_the_next_page(client, store):
    """A fleet of hundreds, pages of 50: the body stays the list it was (the fleet page and older clients read it),
    a cut page names the next in a Link header (RFC 8288), and the pages together are every device once (GET
    /devices sent the whole fleet in one response, with no way to ask for less)."""
    ids = [f"drive-{i:03d}" for i in range(230)]
    for n, device in enumerate(ids):
        store.set_online(device, n % 2 == 0, at=float(n))
    whole = client.get("/devices")
    assert [d["id"] for d in whole.json()] == ids and "link" not in whole.headers  # no limit: every one, as before
    got, url, pages = [], "/devices?limit=50", 0
    while url is not None:
        r = client.get(url)
        assert r.status_code == 200 and isinstance(r.json(), list), r.text
        pages += 1
        got += [d["id"] for d in r.json()]
        if pages == 1:  # seen between two pages: on the page its id falls in (a page read, or one to come)
            store.set_online("drive-000a", True, at=999.0)
            store.set_online("drive-150a", True, at=999.0)
        url = r.links.get("next", {}).get("url")
        assert (url is None) == (pages == 5), (pages, r.headers.get("link"))
        if url is not None:
            assert len(r.json()) == 50 and f"after={r.json()[-1]['id']}" in url and "limit=50" in url
    assert got == ids[:151] + ["drive-150a"] + ids[151:]
    exact = client.get("/devices", params={"limit": 232})
    assert len(exact.json()) == 232 and "link" not in exact.headers  # not cut: no next page
    assert client.get("/devices", params={"after": ids[-1]}).json() == []
    for bad in ({"limit": 0}, {"limit": 10001}, {"limit": "all"}, {"after": "x" * 65}):
        r = client.get("/devices", params=bad)
        assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["query", next(iter(bad))], r.text


def test_windows_are_paged_by_start_then_seq_from_the_last_seq(client, store):
    """Windows past a page: `next` is the last window's seq and `after=<next>` the next page, windows sharing a
    window_start included, the range kept (a truncated page said only that more matched, with no way to get them)."""
    for seq in [*range(2, 25, 2), *range(1, 24, 2)]:  # an odd seq, come late, shares the next one's start
        assert store.insert_window(window(seq=seq, start=60.0 * (seq + seq % 2)))
    found = store.windows(DEVICE, 240.0, 1200.0)
    expected = [w["seq"] for w in found]
    assert len(expected) > 10 and len({w["window_start"] for w in found}) < len(found)
    got, after = [], None
    while True:
        params = {"from": 240, "to": 1200, "limit": 3, **({"after": after} if after is not None else {})}
        page = client.get(f"/devices/{DEVICE}/windows", params=params).json()
        got += [w["seq"] for w in page["windows"]]
        assert page["count"] == len(page["windows"]) and page["truncated"] == (page["next"] is not None)
        if not page["truncated"]:
            break
        assert page["next"] == page["windows"][-1]["seq"]
        after = page["next"]
    assert got == expected
    for bad in ({"after": 0}, {"after": "last"}, {"after": 999}):
        r = client.get(f"/devices/{DEVICE}/windows", params=bad)
        assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["query", "after"], r.text
    assert "no window of seq 999" in r.json()["detail"][0]["msg"]


def _offline(store, device, at):
    (alarm,) = store.save_monitor(
        device,
        {},
        0,
        [{"kind": "raise", "cause": "offline", "at": at, "parameters": {"since": at}, "evidence": "gone"}],
    )
    return alarm["id"]


def test_alarms_are_paged_newest_first_and_say_when_cut(client, store):
    """More alarms than a page: each page says it was cut and where the next begins, and the pages together are
    every alarm once (the list stopped at `limit` and said nothing: a fleet past it could not see the older ones)."""
    ids = [_offline(store, f"drive-{i:03d}", float(i)) for i in range(7)]
    got, before, pages = [], None, 0
    while True:
        params = {"limit": 3, **({"before": before} if before is not None else {})}
        page = client.get("/alarms", params=params).json()
        pages += 1
        got += [a["id"] for a in page["alarms"]]
        if pages == 1:
            _offline(store, "drive-new", 99.0)  # raised between two pages: moves no page after the first
        assert page["truncated"] == (page["next"] is not None)
        if not page["truncated"]:
            break
        assert page["next"] == page["alarms"][-1]["id"]
        before = page["next"]
    assert got == sorted(ids, reverse=True) and pages == 3
    whole = client.get("/alarms", params={"limit": 8}).json()
    assert len(whole["alarms"]) == 8 and not whole["truncated"] and whole["next"] is None
    mine = client.get("/alarms", params={"device": "drive-003", "limit": 1}).json()
    assert [a["id"] for a in mine["alarms"]] == [ids[3]] and not mine["truncated"]
    for bad in ({"before": 0}, {"before": "newest"}, {"before": 2**63}):
        r = client.get("/alarms", params=bad)
        assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["query", "before"], r.text


def test_an_operator_acknowledges_an_alarm_once_with_a_note_and_the_unacknowledged_count_falls(store):
    """POST /alarms/{id}/ack (admin): who (the token), when, the note, kept with the alarm; the alarm stays open;
    GET /alarms?acked=false lists the others; /metrics counts open alarms nobody acknowledged, which the alert
    rules watch, so acknowledging one resolves its alert. A read token, an unknown alarm, a second
    acknowledgement and an empty note are refused, and none of them changes the alarm."""
    from prometheus_client.parser import text_string_to_metric_families

    from fleet_wire.session import loopback_endpoint
    from service.auth import TokenAuth
    from service.runtime import FleetService, open_session

    first, second = _offline(store, "drive-001", 10.0), _offline(store, "drive-002", 20.0)
    auth = TokenAuth(store)
    admin_id, admin = auth.create("admin", "ops desk")
    _, reader = auth.create("read", "wallboard")
    session = open_session(listen=[loopback_endpoint()])
    service = FleetService(store, session, refit_interval_s=0, monitor_interval_s=0).start()

    def unacked() -> float:
        text = api.get("/metrics", headers=as_admin).text
        found = [s for f in text_string_to_metric_families(text) for s in f.samples]
        return [
            s.value for s in found if s.name == "encoder_fleet_unacknowledged_alarms" and s.labels["cause"] == "offline"
        ][0]

    try:
        with TestClient(create_app(store, service, auth)) as api:
            as_admin, as_reader = {"Authorization": f"Bearer {admin}"}, {"Authorization": f"Bearer {reader}"}
            assert unacked() == 2
            note = {"note": "site network down, the plant knows"}
            refused = api.post(f"/alarms/{first}/ack", json=note, headers=as_reader)
            assert refused.status_code == 403
            for body in ({"note": ""}, {}, {"note": "x", "by": "someone else"}):
                assert api.post(f"/alarms/{first}/ack", json=body, headers=as_admin).status_code == 422, body
            assert api.post("/alarms/999/ack", json=note, headers=as_admin).status_code == 404
            acked = api.post(f"/alarms/{first}/ack", json=note, headers=as_admin)
            assert acked.status_code == 200, acked.text
            got = acked.json()
            assert got["acked_by"] == f"token {admin_id} (ops desk)" and got["ack_note"] == note["note"]
            assert got["cleared_at"] is None and got["acked_at"] > 0  # still open: acknowledged is not cleared
            again = api.post(f"/alarms/{first}/ack", json={"note": "me too"}, headers=as_admin)
            assert again.status_code == 409 and "ops desk" in again.json()["detail"]
            listed = api.get("/alarms", params={"acked": "false"}, headers=as_reader).json()["alarms"]
            assert [a["id"] for a in listed] == [second]
            listed = api.get("/alarms", params={"acked": "true"}, headers=as_reader).json()["alarms"]
            assert [(a["id"], a["ack_note"]) for a in listed] == [(first, note["note"])]
            assert unacked() == 1
    finally:
        service.stop()
        session.close()


@pytest.mark.parametrize(
    "params",
    [{"from": "yesterday"}, {"to": "nan"}, {"from": "inf"}, {"from": 10, "to": 5}, {"limit": 0}, {"stats": "maybe"}],
)
def test_bad_query_values_are_422(client, history, params):
    r = client.get(f"/devices/{DEVICE}/windows", params=params)
    assert r.status_code == 422, r.text


@pytest.mark.parametrize(
    "path",
    [
        "/devices/drive-404",
        "/devices/drive-404/health",
        "/devices/drive-404/coefficients",
        "/devices/drive-404/windows",
        "/devices/drive-404/export.mcap",
    ],
)
def test_unknown_device_is_404_naming_it(client, history, path):
    r = client.get(path)
    assert r.status_code == 404 and "drive-404" in r.json()["detail"]


def test_export_mcap(client, history, store):
    r = client.get(f"/devices/{DEVICE}/export.mcap", params={"from": 0, "to": 150})
    assert r.status_code == 200
    assert r.headers["content-disposition"] == f'attachment; filename="{DEVICE}.mcap"'
    reader = make_reader(io.BytesIO(r.content))
    got = [(c.topic, json.loads(m.data)) for _, c, m in reader.iter_messages()]
    expected = [window_record(m) for m in store.iter_windows(DEVICE, 0, 150, with_received_at=True)]
    assert [b for t, b in got if t.endswith("/stats")] == expected
    assert all(t.startswith(f"/encoders/{DEVICE}/") for t, _ in got)
    assert client.get(f"/devices/{DEVICE}/export.mcap", params={"from": "x"}).status_code == 422


def test_rejections(client, history, store):
    store.ingest(keys.key("drive-001", keys.STATS), b"{}")
    got = client.get("/ingest/rejections").json()
    assert got["counts"] == {"not_json": 1, "schema": 1} and got["total"] == 2
    assert [d["reason"] for d in got["latest"]] == ["schema", "not_json"]
    junk = got["latest"][1]
    assert junk["payload_bytes"] == 5 and junk["payload_preview"] == "\ufffdjunk"
    assert client.get("/ingest/rejections", params={"limit": 1}).json()["latest"][0]["reason"] == "schema"


def test_rejections_page_through_every_dead_letter(client, store):
    """GET /ingest/rejections stopped at `limit` (1,000 at most) with no way past it: a flood of bad messages hid
    every older letter. It pages as /alarms does: `truncated`, and `before` = `next` for the next page."""
    for k in range(7):
        store.ingest(keys.key(f"drive-{k:03d}", keys.STATS), b"junk %d" % k)
    seen, before = [], None
    for _ in range(7):
        params = {"limit": 3} | ({"before": before} if before is not None else {})
        page = client.get("/ingest/rejections", params=params).json()
        seen += [d["key_expr"] for d in page["latest"]]
        if not page["truncated"]:
            assert page["next"] is None
            break
        before = page["next"]
        store.ingest(keys.key("drive-late", keys.STATS), b"junk late")  # kept meanwhile: moves no later page
    assert seen == [keys.key(f"drive-{k:03d}", keys.STATS) for k in reversed(range(7))], seen
    counts_only = client.get("/ingest/rejections", params={"limit": 0}).json()
    assert counts_only["latest"] == [] and counts_only["truncated"] and counts_only["next"] is None
    assert client.get("/ingest/rejections", params={"before": 0}).status_code == 422


def test_openapi_documents_every_router(client):
    import warnings

    with warnings.catch_warnings():  # a duplicate operation id is a warning on stderr, outside the JSON log
        warnings.simplefilter("error")
        spec = client.get("/openapi.json").json()
    assert spec["info"]["title"] == "encoder-fleet service"
    assert {
        "/devices",
        "/devices/{device_id}/health",
        "/devices/{device_id}/coefficients",
        "/devices/{device_id}/windows",
        "/devices/{device_id}/export.mcap",
        "/ingest/rejections",
    } <= set(spec["paths"])
    assert all(op.get("summary") for path in spec["paths"].values() for op in path.values())


def test_healthz_readyz_and_metrics_over_a_real_service(tmp_path):
    from prometheus_client.parser import text_string_to_metric_families

    from fleet_wire.session import loopback_endpoint
    from service.runtime import FleetService, open_session

    store = Store.open(tmp_path / "svc.db")
    session = open_session(listen=[loopback_endpoint()])
    service = FleetService(store, session, refit_interval_s=0)
    client = TestClient(create_app(store, service))
    assert client.get("/readyz").status_code == 503  # created, not started: the ingest writer is not running
    service.start()
    try:
        assert client.get("/healthz").json() == {
            "status": "ok",
            "checks": {"process": "ok", "database": "ok", "router": "ok", "storage": "ok"},
        }
        assert client.get("/readyz").status_code == 200
        for path in ("/healthz", "/readyz"):  # a probe that asks with HEAD (was 405)
            head = client.head(path)
            assert head.status_code == 200 and head.content == b"", (path, head.status_code)
        store.ingest(keys.key("drive-001", keys.STATS), wire.encode("window", window()))
        service.counters.count("stored")
        service.counters.count("not_json")
        text = client.get("/metrics").text
    finally:
        service.stop()
        session.close()
    gone = client.get("/healthz")
    assert gone.status_code == 503 and gone.json()["checks"]["router"] == "closed"
    store.close()

    families = {f.name: f for f in text_string_to_metric_families(text)}
    assert all(name.startswith("encoder_fleet_") for name in families)
    for family in families.values():
        for sample in family.samples:
            assert "device" not in sample.labels  # no per-device series
            if family.type == "counter" and not sample.name.endswith("_created"):
                assert sample.name.endswith("_total"), sample.name
    samples = {(s.name, tuple(sorted(s.labels.items()))): s.value for f in families.values() for s in f.samples}
    assert samples[("encoder_fleet_devices", (("state", "offline"),))] == 1
    assert samples[("encoder_fleet_messages_ingested_total", (("outcome", "stored"),))] == 1
    assert samples[("encoder_fleet_ingest_rejections_total", (("reason", "not_json"),))] == 1
    assert samples[("encoder_fleet_storage_failures_total", ())] == 0
    assert samples[("encoder_fleet_wal_checkpoint_failures_total", ())] == 0
    assert families["encoder_fleet_ingest_latency_seconds"].type == "histogram"
    assert families["encoder_fleet_refit_latency_seconds"].type == "histogram"
    assert "encoder_fleet_open_alarms" in families


def test_a_full_disk_shows_in_healthz_and_metrics_and_the_service_recovers_by_itself(tmp_path):
    """The database refuses writes (SQLite's page limit: the disk is full for it): /healthz fails with the
    reason, a counter rises, nothing crashes; when space returns the next batch is stored and all is well."""
    import time

    import zenoh
    from prometheus_client.parser import text_string_to_metric_families

    from fleet_wire.session import loopback_endpoint, session_config
    from service.runtime import FleetService, open_session

    store = Store.open(tmp_path / "svc.db")
    endpoint = loopback_endpoint()
    session = open_session(listen=[endpoint])
    service = FleetService(store, session, refit_interval_s=0).start()
    agent = zenoh.open(session_config("client", connect=[endpoint]))
    client = TestClient(create_app(store, service))

    def send(seq):
        agent.put(keys.key("drive-001", keys.STATS), wire.encode("window", window(seq=seq, start=60.0 * seq)))

    def wait_for(predicate, what):
        deadline = time.monotonic() + 60
        while not predicate():
            assert time.monotonic() < deadline, what
            time.sleep(0.05)

    def failures():
        text = client.get("/metrics").text
        found = {s.name: s.value for f in text_string_to_metric_families(text) for s in f.samples}
        return found["encoder_fleet_storage_failures_total"]

    try:
        send(1)
        wait_for(lambda: store.max_seq("drive-001") == 1, "the first window stored")
        with store._lock:  # the disk is full: not one page more
            pages = store._conn.execute("PRAGMA page_count").fetchone()[0]
            store._conn.execute(f"PRAGMA max_page_count = {pages}")
        seq = 1
        while failures() == 0:
            seq += 1
            send(seq)
            wait_for(lambda n=seq: failures() > 0 or store.max_seq("drive-001") == n, "stored or refused")
        health = client.get("/healthz")
        assert health.status_code == 503 and "full" in health.json()["checks"]["storage"], health.json()
        with store._lock:  # space is back
            store._conn.execute("PRAGMA max_page_count = 1073741823")
        send(seq + 1)
        wait_for(lambda: store.max_seq("drive-001") == seq + 1, "stored again once space is back")
        assert client.get("/healthz").status_code == 200 and failures() >= 1
    finally:
        agent.close()
        service.stop()
        session.close()
        store.close()


def test_docs_and_redoc_load_every_asset_from_the_service_itself(client):
    import re

    for page in ("/docs", "/redoc"):
        html = client.get(page).text
        assets = re.findall(r'(?:src|href)="([^"]+)"', html)
        assert assets, page
        for url in assets:
            assert url.startswith("/"), f"{page} loads {url} from elsewhere"
            assert client.get(url).status_code == 200, url


def test_openapi_documents_every_status_the_device_routes_answer(client, history):
    spec = client.get("/openapi.json").json()
    for path, item in spec["paths"].items():
        if "{device_id}" in path:
            for method, operation in item.items():
                assert "404" in operation["responses"], (method, path)
    missing = client.get("/devices/nope/health")
    assert missing.status_code == 404 and set(missing.json()) == {"detail"}
    reversed_range = client.get(f"/devices/{DEVICE}/windows", params={"from": 5, "to": 1})
    assert reversed_range.status_code == 422
    (error,) = reversed_range.json()["detail"]  # the documented HTTPValidationError shape
    assert error["loc"] == ["query", "from"] and "after" in error["msg"]


def test_a_body_json_cannot_carry_back_or_too_large_is_a_clear_4xx_not_a_500(tmp_path):
    """NaN, 1e999 or a lone surrogate in a body: 422 saying where and what (FastAPI's own handler sent the input
    back, which JSON cannot carry: a 500). A body over MAX_BODY: 413 before it is read whole, token or not."""
    from service.api import MAX_BODY
    from service.auth import TokenAuth

    with Store.open(tmp_path / "svc.db") as store:
        auth = TokenAuth(store)
        _, admin = auth.create("admin", "test")
        client = TestClient(create_app(store, None, auth))
        sent = {"Authorization": f"Bearer {admin}", "Content-Type": "application/json"}
        for body, where in [
            ("1e999", ["body"]),
            ('{"scope": "read", "name": NaN}', ["body", "name"]),
            ('{"scope": "read", "name": "\\ud800"}', ["body", "name"]),
        ]:
            answer = client.post("/tokens", content=body, headers=sent)
            assert answer.status_code == 422, (body, answer.text)
            assert [d["loc"] for d in answer.json()["detail"]] == [where], answer.json()
        huge = b'{"scope": "read", "name": "' + b"x" * (MAX_BODY + 1) + b'"}'
        for headers in (sent, {"Content-Type": "application/json"}):
            answer = client.post("/tokens", content=huge, headers=headers)
            assert answer.status_code == 413 and "at most" in answer.json()["detail"], answer.text
        assert [t["name"] for t in auth.tokens()] == ["test"]  # nothing was made of any of them


def test_the_alarms_command_lists_and_acknowledges_as_an_operator_on_shift_would(tmp_path):
    from operator_cli import operator_cli

    with Store.open(tmp_path / "fleet.sqlite") as store:
        ids = [_offline(store, f"drive-{i:03d}", 3600.0 * i) for i in range(3)]
        with operator_cli(store, tmp_path, "alarms") as alarms:
            refused = alarms("ack", str(ids[1]), "--note", "on it", token="read")
            assert refused.returncode == 2 and "403" in refused.stderr and not refused.stdout
            done = alarms("ack", str(ids[1]), "--note", "switch replaced")
            assert done.returncode == 0 and "acknowledged by token 1 (night shift): switch replaced" in done.stdout
            listed = alarms("list", "--open", "--unacked", token="read")
            assert listed.returncode == 0, listed.stderr
            assert [line.split()[1] for line in listed.stdout.splitlines()] == ["drive-002", "drive-000"]
            cut = alarms("list", "--limit", "1", token="read")
            assert cut.returncode == 0 and "more match" in cut.stdout
            twice = alarms("ack", str(ids[1]), "--note", "again")
            assert twice.returncode == 2 and "409" in twice.stderr and "night shift" in twice.stderr


def test_the_status_command_shows_the_fleet_at_a_glance_and_fails_while_a_part_of_the_service_does(tmp_path):
    import subprocess
    import sys

    from fleet_wire.session import free_port, loopback_endpoint
    from service.auth import TokenAuth
    from service.runtime import FleetService, HttpServer, open_session

    with Store.open(tmp_path / "fleet.sqlite") as store:
        ids = [_offline(store, f"drive-{i:03d}", 3600.0 * i) for i in range(3)]
        store.ack_alarm(ids[0], by="token 9 (day shift)", note="planned outage")
        auth = TokenAuth(store)
        reader = tmp_path / "read-token"
        reader.write_text(auth.create("read")[1])
        session = open_session(listen=[loopback_endpoint()])
        service = FleetService(store, session, refit_interval_s=0, monitor_interval_s=0).start()
        port = free_port()
        http = HttpServer(store, port, service=service, auth=auth).start()
        cmd = [sys.executable, "-m", "encoder_fleet.cli", "status", "--url", f"http://127.0.0.1:{port}"]
        cmd += ["--token-file", str(reader)]
        try:
            done = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
            assert done.returncode == 0, done.stderr
            lines = done.stdout.splitlines()
            assert lines[0] == "service: ok" and lines[2] == "open alarms: 3 (offline 3)", done.stdout
            listed = [line.split()[1] for line in lines[4:]]
            assert lines[3] == "not acknowledged:" and listed == ["drive-002", "drive-001"]  # not drive-000's
            service.counters.storage_error = "the database refused the last batch: database or disk is full"
            failing = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
            assert failing.returncode == 1 and failing.stdout.startswith("service: failing\n")
            assert "database or disk is full" in failing.stdout and not failing.stderr
        finally:
            http.stop()
            service.stop()
            session.close()


def test_alarms_list_refuses_a_cause_the_monitor_never_raises(tmp_path):
    """`alarms list --cause offline-` (a typo) said "no alarms" with an offline alarm open: the service filters by
    whatever it is given. The command refuses a cause that is none of the monitor's, in one line naming them."""
    import subprocess
    import sys

    from fleet_wire.session import free_port
    from service.runtime import HttpServer

    with Store.open(tmp_path / "fleet.sqlite") as store:
        _offline(store, "drive-001", 3600.0)
        port = free_port()
        http = HttpServer(store, port).start()  # REST open
        cmd = [sys.executable, "-m", "encoder_fleet.cli", "alarms", "list", "--url", f"http://127.0.0.1:{port}"]
        try:
            typo = subprocess.run([*cmd, "--cause", "offline-"], capture_output=True, text=True, timeout=60)
            assert typo.returncode == 2 and not typo.stdout, typo.stdout
            assert len(typo.stderr.strip().splitlines()) == 1 and "offset_step" in typo.stderr, typo.stderr
            found = subprocess.run([*cmd, "--cause", "offline"], capture_output=True, text=True, timeout=60)
            assert found.returncode == 0 and "drive-001" in found.stdout, found.stderr
        finally:
            http.stop()


def test_the_rest_commands_json_on_stdout_is_the_json_alone(tmp_path):
    """`status --json /dev/stdout | jq` (and alarms', rollout's): the JSON on stdout is the JSON alone, the lines
    the command prints go to stderr, as `audit --out /dev/stdout` does; they were printed on stdout before the JSON
    (status, alarms) or after it (rollout list), and a script's JSON reader failed at the first line."""
    import subprocess
    import sys

    from fleet_wire.session import free_port
    from service.runtime import HttpServer

    with Store.open(tmp_path / "fleet.sqlite") as store:
        _offline(store, "drive-001", 3600.0)
        port = free_port()
        http = HttpServer(store, port).start()  # REST open
        try:
            for command, text in (
                (["status"], "open alarms: 1 (offline 1)"),
                (["alarms", "list"], "drive-001"),
                (["rollout", "list"], "no rollouts"),
            ):
                cmd = [sys.executable, "-m", "encoder_fleet.cli", *command, "--url", f"http://127.0.0.1:{port}"]
                done = subprocess.run([*cmd, "--json", "/dev/stdout"], capture_output=True, text=True, timeout=60)
                assert done.returncode == 0, (command, done.stderr)
                answer = json.loads(done.stdout)  # nothing but the JSON
                assert isinstance(answer, (dict, list)) and text in done.stderr, (command, done.stdout, done.stderr)
                kept = tmp_path / "answer.json"  # to a file, the lines stay on stdout
                done = subprocess.run([*cmd, "--json", str(kept)], capture_output=True, text=True, timeout=60)
                assert done.returncode == 0 and text in done.stdout and not done.stderr, (command, done.stderr)
                assert json.loads(kept.read_text()) == answer
        finally:
            http.stop()


def test_two_acknowledgements_at_once_on_postgresql_leave_the_first_and_refuse_the_second(postgres_url):
    """Two service processes (a cluster's members) acknowledge one alarm at the same moment: both read it not yet
    acknowledged, and the second's UPDATE, waiting on the first's row lock, overwrote it once that committed; both
    answered 200 and the first operator's note was gone. The second is refused (409), the first stands."""
    import threading
    import time

    from service.store import StoreError

    with Store.open(postgres_url) as first, Store.open(postgres_url) as second:
        alarm = _offline(first, "drive-001", 10.0)
        outcome = {}

        def ack_meanwhile():
            try:
                outcome["ack"] = second.ack_alarm(alarm, by="token 2 (day shift)", note="me too")
            except StoreError as exc:
                outcome["refused"] = exc

        with first._tx() as c:  # the first member's acknowledgement, not committed yet
            c.execute(
                "UPDATE alarms SET acked_at = ?, acked_by = ?, ack_note = ? WHERE id = ?",
                (time.time(), "token 1 (night shift)", "switch replaced", alarm),
            )
            racer = threading.Thread(target=ack_meanwhile)
            racer.start()
            wait_for_a_lock_wait(postgres_url, "the second acknowledgement")
        racer.join(10)
        (stored,) = first.alarms(ids=[alarm])
    assert stored["acked_by"] == "token 1 (night shift)" and stored["ack_note"] == "switch replaced"
    assert "ack" not in outcome and outcome["refused"].reason == "already_acked", outcome
    assert "night shift" in str(outcome["refused"])


def test_a_refused_acknowledgement_keeps_the_band_sums_in_memory(client, store, caplog):
    """An acknowledgement refused inside its transaction (no such alarm: 404; acknowledged already: 409) rolled it
    back as a failed write, which drops every drive's band sums kept in memory, so the next window of each drive
    rebuilt its bands from all their windows: an operator's mistyped id did that to the whole fleet. Nothing was
    written: the sums are kept."""
    import logging

    for seq in range(1, 4):
        store.insert_window(window(seq=seq))
    alarm = _offline(store, "drive-002", 10.0)
    note = {"note": "seen"}
    assert client.post(f"/alarms/{alarm}/ack", json=note).status_code == 200
    assert client.post(f"/alarms/{alarm}/ack", json=note).status_code == 409
    assert client.post(f"/alarms/{alarm + 1}/ack", json=note).status_code == 404
    caplog.set_level(logging.INFO, logger="service.store")
    store.insert_window(window(seq=4))
    assert "rebuilt" not in caplog.text
    assert store.band_stats(DEVICE) and sum(n for _, n, _ in store.band_stats(DEVICE).values()) == 4


@pytest.mark.parametrize(
    "note", ["seen\x00", "seen\nand on it", "\x1b[2J\x1b[Hall clear", "\t", "   ", "x" * 501, "seen\x7f"]
)
def test_a_note_is_one_line_of_text_or_the_acknowledgement_is_refused(client, store, note):
    """A note is printed on one line by `alarms list` and in a cell of the fleet page: a newline broke the line, an
    escape sequence reached the operator's terminal as a command, and a NUL was kept on SQLite but stored as U+FFFD
    on PostgreSQL (another note than the one sent). Each is refused with 422 saying where, and nothing is kept."""
    alarm = _offline(store, "drive-002", 10.0)
    refused = client.post(f"/alarms/{alarm}/ack", json={"note": note})
    assert refused.status_code == 422 and refused.json()["detail"][0]["loc"] == ["body", "note"], refused.text
    assert store.alarms(ids=[alarm])[0]["acked_at"] is None
    kept = client.post(f"/alarms/{alarm}/ack", json={"note": "Schalter getauscht – läuft wieder ✓"})
    assert kept.status_code == 200 and kept.json()["ack_note"] == "Schalter getauscht – läuft wieder ✓"


def test_the_status_command_pointed_at_another_server_says_so_in_one_line():
    """--url naming something that is not the service (another web server answering 503 with its own JSON): one
    line and exit 2; it ended in a KeyError traceback."""
    import http.server
    import subprocess
    import sys
    import threading

    class Other(http.server.BaseHTTPRequestHandler):
        def do_GET(self):
            body = b'{"detail": "maintenance"}'
            self.send_response(503)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args):
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Other)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        url = f"http://127.0.0.1:{server.server_address[1]}"
        done = subprocess.run(
            [sys.executable, "-m", "encoder_fleet.cli", "status", "--url", url],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert done.returncode == 2 and "not the service's checks" in done.stderr and "Traceback" not in done.stderr
    finally:
        server.shutdown()
        server.server_close()


def test_a_drive_online_but_sending_nothing_is_named_silent_in_fleet_health_metrics_and_status(tmp_path):
    """An agent that runs (its token up) but whose windows never come (a thermistor broken for good makes every
    window unsendable; a sensor gone) gave no sign at all: no window, so no drift alarm, and the drive counted as
    online. Online with nothing stored for 30 minutes is silent now: GET /fleet/health names it, /metrics counts
    it (ops/alerts.yml's EncoderFleetDrivesSilent), `status` says so."""
    import subprocess
    import sys
    import time

    from prometheus_client.parser import text_string_to_metric_families

    from fleet_wire.session import free_port, loopback_endpoint
    from service.runtime import FleetService, HttpServer, open_session

    with Store.open(tmp_path / "fleet.sqlite") as store:
        now = time.time()
        store.set_online("drive-quiet", True, at=now - 3600)  # token up an hour ago, nothing since
        store.set_online("drive-talks", True, at=now - 3600)
        store.insert_window(window("drive-talks", seq=1))  # stored now: heard
        store.set_online("drive-slow", True, at=now - 3600)  # hour-long windows: silent only past three of them
        store.insert_window({**window("drive-slow", seq=1), "window_end": 3600.0}, received_at=now - 3000)
        store.set_online("drive-gone", True, at=now - 7200)
        store.set_online("drive-gone", False, at=now - 7100)  # offline: its own state, not silent
        assert store.silent_devices(1800.0) == ["drive-quiet"]
        session = open_session(listen=[loopback_endpoint()])
        service = FleetService(store, session, refit_interval_s=0, monitor_interval_s=0).start()
        port = free_port()
        http = HttpServer(store, port, service=service).start()
        try:
            api = TestClient(create_app(store, service))
            health = api.get("/fleet/health").json()
            assert health["silent"] == 1 and health["silent_devices"] == ["drive-quiet"]
            samples = [s for f in text_string_to_metric_families(api.get("/metrics").text) for s in f.samples]
            assert [s.value for s in samples if s.name == "encoder_fleet_devices_silent"] == [1.0]
            cmd = [sys.executable, "-m", "encoder_fleet.cli", "status", "--url", f"http://127.0.0.1:{port}"]
            done = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
            assert "silent: 1 online but nothing stored for 30 min: drive-quiet" in done.stdout, done.stdout
        finally:
            http.stop()
            service.stop()
            session.close()
