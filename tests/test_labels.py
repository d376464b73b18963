"""Device labels (site, line, axis): set by an operator, the fleet read and rolled out to by them. Real stores
(SQLite, PostgreSQL), the real REST app, the command in its own process."""

import subprocess
import sys
import time

import pytest
from fastapi.testclient import TestClient
from operator_cli import operator_cli
from pg_locks import wait_for_a_lock_wait
from wire_samples import window

from service.api import create_app
from service.auth import TokenAuth
from service.labels import check_labels, parse_selectors
from service.rollout import RolloutError, Rollouts, RolloutSpec
from service.store import Store

RESET = {"change": {"kind": "reset_to_factory"}, "base_per_minute": 10, "soak_windows": 5}
SITES = {"drive-001": "plant-3", "drive-002": "plant-3", "drive-003": "plant-7", "drive-004": None}


def four_drives(store) -> None:
    """Two drives at plant-3 (one on line 1, offline with an offline alarm), one at plant-7, one unlabelled."""
    for name, site in SITES.items():
        store.insert_window(window(name, 1))
        if site is not None:
            store.set_labels(name, {"site": site, **({"line": "1"} if name == "drive-002" else {})})
    store.save_monitor(
        "drive-002",
        {},
        0,
        [{"kind": "raise", "cause": "offline", "at": 60.0, "parameters": {"since": 60.0}, "evidence": "x"}],
    )


def test_labels_select_devices_alarms_and_silent_drives(store):
    four_drives(store)
    assert store.device("drive-002")["labels"] == {"line": "1", "site": "plant-3"}
    assert store.device("drive-004")["labels"] == {}
    assert store.device_ids(labels={"site": "plant-3"}) == ["drive-001", "drive-002"]
    assert store.device_ids(labels={"site": "plant-3", "line": "1"}) == ["drive-002"]
    assert store.device_ids(labels={"site": "plant-9"}) == []
    assert [d["id"] for d in store.devices(labels={"site": "plant-7"})] == ["drive-003"]
    assert [d["id"] for d in store.devices(after="drive-001", limit=1, labels={"site": "plant-3"})] == ["drive-002"]
    assert store.open_alarm_counts(labels={"site": "plant-3"}) == {"offline": 1}
    assert store.open_alarm_counts(labels={"site": "plant-7"}) == {}
    store.set_online("drive-003", True)
    later = time.time() + 86400.0
    assert store.silent_devices(1800.0, now=later, labels={"site": "plant-7"}) == ["drive-003"]
    assert store.silent_devices(1800.0, now=later, labels={"site": "plant-3"}) == []
    # replaced whole: a label left out is gone
    assert store.set_labels("drive-002", {"site": "plant-7"}) == {"site": "plant-7"}
    assert store.device_ids(labels={"line": "1"}) == []
    with pytest.raises(KeyError):
        store.set_labels("drive-999", {"site": "plant-3"})
    assert store.labels_of(["drive-003", "drive-004"]) == {"drive-003": {"site": "plant-7"}, "drive-004": {}}


@pytest.mark.parametrize(
    "value, ok",
    [
        ("7", True),  # one character
        ("hall B, bay 4", False),
        ("hall B bay 4", True),  # spaces inside
        ("Zürich-Süd", True),
        ("🏭" * 64, True),  # 64 characters, not bytes
        ("x" * 64 + "\n", False),  # "$" matched before a trailing newline: a second line in `devices list`
        ("plant-3\r", False),
    ],
)
def test_the_label_rules_at_their_edges(value, ok):
    if ok:
        assert check_labels({"site": value}) == {"site": value}
        assert parse_selectors([f"site={value}"]) == {"site": value}
    else:
        for bad in (lambda: check_labels({"site": value}), lambda: parse_selectors([f"site={value}"])):
            with pytest.raises(ValueError):
                bad()
    with pytest.raises(ValueError):
        check_labels({"site\n": "x"})


def test_a_long_page_reads_its_own_devices_labels_and_keeps_each_devices_own(store, monkeypatch):
    """A page of more than 500 devices (the devices command asks for 1000) read every label of the fleet, for every
    page: 50,000 drives of four labels took 14 s to list, 0.3 s in pages of 500. Counted as the label rows read."""
    names = [f"drive-{i:04d}" for i in range(1600)]
    with store.transaction():
        for i, name in enumerate(names):
            store.insert_window(window(name, 1))
            if i % 2:
                store.set_labels(name, {"site": f"plant-{i % 5}"})
    found = store.devices()
    assert len(found) == 1600
    assert all(d["labels"] == ({"site": f"plant-{i % 5}"} if i % 2 else {}) for i, d in enumerate(found))
    read, rows = [], store._rows

    def counted(sql, args=()):
        out = rows(sql, args)
        read.extend(out if sql.startswith("SELECT * FROM device_labels") else [])
        return out

    monkeypatch.setattr(store, "_rows", counted)
    page = store.devices(after=names[299], limit=1000)
    assert [d["id"] for d in page] == names[300:1300] and page == found[300:1300]
    assert len(read) == 500  # the page's labelled half, not the fleet's 800


def test_two_members_labelling_one_drive_at_once_on_postgresql_leave_the_later_labels_whole(postgres_url):
    """Two PUT /devices/{id}/labels at once on two cluster members: the second waits for the first and replaces its
    labels whole. Before, both deletes found nothing to wait for and the second insert failed on the primary key: a
    500, and the operator's labels were not set."""
    import threading

    with Store.open(postgres_url) as first, Store.open(postgres_url) as second:
        first.insert_window(window("drive-001", 1))
        outcome = {}

        def label_meanwhile():
            try:
                outcome["labels"] = second.set_labels("drive-001", {"site": "plant-7"})
            except Exception as exc:  # what REST answered with a 500
                outcome["failed"] = exc

        with first._tx():  # the first member's labels, not committed yet
            first.set_labels("drive-001", {"site": "plant-3", "line": "1"})
            racer = threading.Thread(target=label_meanwhile)
            racer.start()
            wait_for_a_lock_wait(postgres_url, "the second member's labels")
        racer.join(10)
        assert outcome == {"labels": {"site": "plant-7"}}, outcome
        assert first.device("drive-001")["labels"] == {"site": "plant-7"}


def test_an_operator_labels_drives_and_reads_a_site_over_rest(store):
    four_drives(store)
    auth = TokenAuth(store)
    _, admin = auth.create("admin", "ops desk")
    _, reader = auth.create("read", "wallboard")
    as_admin, as_reader = {"Authorization": f"Bearer {admin}"}, {"Authorization": f"Bearer {reader}"}
    with TestClient(create_app(store, auth=auth)) as api:
        body = {"labels": {"site": "plant-7", "axis": "z"}}
        assert api.put("/devices/drive-004/labels", json=body, headers=as_reader).status_code == 403
        for bad in (
            {"labels": {"Site": "plant-7"}},  # a name is lower case
            {"labels": {"site": "a=b"}},  # a value has no "=" (a selector is NAME=VALUE)
            {"labels": {"site": " plant"}},
            {"labels": {"site": "line\nbreak"}},
            {"labels": {"site": "plant-7\n"}},  # a trailing newline too ("$" matched before it)
            {"labels": {"site\n": "plant-7"}},
            {"labels": {"site": ""}},
            {"labels": {"site": "x" * 65}},
            {"labels": {f"l{i}": "x" for i in range(17)}},
            {"labels": {"site": 3}},
            {"labels": ["site"]},
            {"site": "plant-7"},
        ):
            refused = api.put("/devices/drive-004/labels", json=bad, headers=as_admin)
            assert refused.status_code == 422, (bad, refused.text)
        assert store.device("drive-004")["labels"] == {}  # no refusal changed anything
        assert api.put("/devices/drive-999/labels", json=body, headers=as_admin).status_code == 404
        done = api.put("/devices/drive-004/labels", json=body, headers=as_admin)
        assert done.status_code == 200 and done.json()["labels"] == {"axis": "z", "site": "plant-7"}

        listed = api.get("/devices", params={"label": "site=plant-7"}, headers=as_reader).json()
        assert [(d["id"], d["labels"]["site"]) for d in listed] == [("drive-003", "plant-7"), ("drive-004", "plant-7")]
        both = api.get("/devices", params=[("label", "site=plant-3"), ("label", "line=1")], headers=as_reader)
        assert [d["id"] for d in both.json()] == ["drive-002"]
        paged = api.get("/devices", params={"label": "site=plant-7", "limit": 1}, headers=as_reader)
        assert [d["id"] for d in paged.json()] == ["drive-003"] and "label=site%3Dplant-7" in paged.headers["link"]
        for params in (
            {"label": "site"},
            {"label": "Site=x"},
            {"label": "site=plant-7\n"},
            [("label", "site=a"), ("label", "site=b")],
            [("label", f"l{i}=x") for i in range(17)],  # more than a device carries
            [("label", f"l{i}=x") for i in range(1001)],  # a 500 on SQLite: an expression of more than 1000 terms
        ):
            refused = api.get("/devices", params=params, headers=as_reader)
            assert refused.status_code == 422 and refused.json()["detail"][0]["loc"] == ["query", "label"], params
        site = api.get("/fleet/health", params={"label": "site=plant-3"}, headers=as_reader).json()
        assert sum(site["devices"].values()) == 2 and site["open_alarms"] == {"offline": 1}
        other = api.get("/fleet/health", params={"label": "site=plant-7"}, headers=as_reader).json()
        assert sum(other["devices"].values()) == 2 and other["open_alarms"] == {}
        fleet = api.get("/fleet/health", headers=as_reader).json()
        assert sum(fleet["devices"].values()) == 4
        by_site = api.get("/fleet/health/by/site", headers=as_reader).json()["groups"]
        assert [g["value"] for g in by_site] == ["plant-3", "plant-7"]  # drive-004 labelled above
        # a dry run changes nothing: a read token's (creating it is an admin's)
        spec = {"name": "plant 7", "labels": {"site": "plant-7"}, **RESET}
        assert api.post("/rollouts/plan", json=spec, headers=as_reader).json()["devices_total"] == 2
        assert api.post("/rollouts", json=spec, headers=as_reader).status_code == 403


def test_a_rollout_takes_the_drives_that_carry_its_labels(store):
    four_drives(store)
    store.retire_device("drive-001", by="token 1", note="replaced")
    rollouts = Rollouts(store)
    with pytest.raises(RolloutError, match="carries site=plant-9"):
        rollouts.create(RolloutSpec(name="nowhere", labels={"site": "plant-9"}, **RESET))
    for bad in ({"labels": {}}, {"labels": {"site": "plant-3"}, "devices": ["drive-002"]}, {"labels": {"S": "x"}}):
        with pytest.raises(ValueError):
            RolloutSpec(name="bad", **bad, **RESET)
    rollout = rollouts.create(RolloutSpec(name="plant 3 only", labels={"site": "plant-3"}, **RESET))
    assert [d["device"] for d in rollouts.get(rollout)["devices"]] == ["drive-002"]  # drive-001 is retired
    (stored,) = store._rows("SELECT spec_json FROM rollouts WHERE id = ?", (rollout,))
    assert RolloutSpec.model_validate_json(stored["spec_json"]).labels == {"site": "plant-3"}  # as it steps it


def test_a_rollout_without_labels_is_stored_as_a_service_before_labels_reads_it(store):
    """A spec without labels stored "labels": null, which a service before labels (its RolloutSpec forbids other
    fields) refused: stepping every rollout made since failed there, not only those by label."""
    from pydantic import ConfigDict, create_model

    four_drives(store)
    fields = {name: (f.annotation, f) for name, f in RolloutSpec.model_fields.items() if name != "labels"}
    before_labels = create_model("RolloutSpec", __config__=ConfigDict(extra="forbid"), **fields)
    rollout = Rollouts(store).create(RolloutSpec(name="whole fleet", **RESET))
    (stored,) = store._rows("SELECT spec_json FROM rollouts WHERE id = ?", (rollout,))
    assert before_labels.model_validate_json(stored["spec_json"]).name == "whole fleet"


def test_the_devices_command_labels_and_lists_a_site(tmp_path):
    with Store.open(tmp_path / "fleet.sqlite") as store:
        four_drives(store)
        with operator_cli(store, tmp_path, "devices") as devices:
            done = devices("label", "drive-004", "site=plant-7", "line=2")
            assert done.returncode == 0 and "labels line=2 site=plant-7" in done.stdout, done.stderr
            refused = devices("label", "drive-004", "site=a,b")
            assert refused.returncode == 2 and "422" in refused.stderr and len(refused.stderr.splitlines()) == 1
            assert devices("label", "drive-004", "site").returncode == 2  # not NAME=VALUE: argparse's one line
            listed = devices("list", "--label", "site=plant-7", token="read")
            assert listed.returncode == 0, listed.stderr
            assert [line.split()[0] for line in listed.stdout.splitlines()] == ["drive-003", "drive-004"]
            assert "line=2 site=plant-7" in listed.stdout.splitlines()[1]
            none = devices("list", "--label", "site=plant-9", token="read")
            assert none.returncode == 0 and none.stdout.strip() == "no devices"
            for unsaid in (("label", "drive-004"), ("label", "drive-004", "site=x", "--clear")):
                refused = devices(*unsaid)  # removing every label is said, not typed by mistake
                assert refused.returncode == 2 and "--clear" in refused.stderr, refused.stderr
            cleared = devices("label", "drive-004", "--clear")
            assert cleared.returncode == 0 and "labels" not in cleared.stdout


def test_the_fleets_health_a_site_a_row(store):
    """GET /fleet/health/by/site: each site's drives by state, open alarms and silent drives, the unlabelled last;
    and `status --by site` prints it as a table."""
    from fleet_wire.session import free_port
    from service.runtime import HttpServer

    four_drives(store)
    store.set_online("drive-003", True)
    store.retire_device("drive-001", by="token 1", note="replaced")
    with TestClient(create_app(store)) as api:
        got = api.get("/fleet/health/by/site")
        assert got.status_code == 200, got.text
        groups = {g["value"]: g for g in got.json()["groups"]}
        assert [g["value"] for g in got.json()["groups"]] == ["plant-3", "plant-7", None]
        assert groups["plant-3"]["devices"]["retired"] == 1 and sum(groups["plant-3"]["devices"].values()) == 2
        assert groups["plant-3"]["open_alarms"] == {"offline": 1} and groups["plant-7"]["open_alarms"] == {}
        assert sum(groups[None]["devices"].values()) == 1  # drive-004 carries no site
        by_line = {g["value"]: sum(g["devices"].values()) for g in api.get("/fleet/health/by/line").json()["groups"]}
        assert by_line == {"1": 1, None: 3}
        for bad in ("Site", "a b", "x" * 33):
            assert api.get(f"/fleet/health/by/{bad}").status_code == 422, bad
    if not str(store.path).endswith(".db"):
        return  # the command's table once is enough: SQLite's run
    port = free_port()
    http = HttpServer(store, port).start()
    try:
        cmd = [sys.executable, "-m", "encoder_fleet.cli", "status", "--by", "site", "--url", f"http://127.0.0.1:{port}"]
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
        rows = {line.split()[0]: line.split() for line in done.stdout.splitlines() if line.startswith(("plant", "("))}
        assert set(rows) == {"plant-3", "plant-7", "(no"}, done.stdout + done.stderr
        assert rows["plant-3"][1] == "2" and rows["plant-3"][-2] == "1"  # two drives, one open alarm
        refused = subprocess.run([*cmd[:-4], "--by", "../x", *cmd[-2:]], capture_output=True, text=True, timeout=60)
        assert refused.returncode == 2 and "not a label name" in refused.stderr and not refused.stdout
    finally:
        http.stop()


def test_a_dry_run_says_which_drives_and_waves_a_rollout_would_take_and_creates_nothing(store, tmp_path):
    from fleet_wire.session import free_port
    from service.runtime import HttpServer

    four_drives(store)
    store.set_online("drive-001", True)
    spec = {"name": "plant 3 reset", "labels": {"site": "plant-3"}, **RESET, "base_per_minute": 1}
    with TestClient(create_app(store)) as api:
        plan = api.post("/rollouts/plan", json={**spec, "increment_factor": 2.0})
        assert plan.status_code == 200, plan.text
        assert plan.json() == {
            "devices_total": 2,
            "devices": ["drive-001", "drive-002"],
            "waves": [1, 1],
            "last_wave_after_min": 1,
            "offline": 1,
            "refused": None,
        }
        everyone = api.post(
            "/rollouts/plan", json={**RESET, "name": "all", "base_per_minute": 1, "increment_factor": 2}
        )
        assert everyone.json()["waves"] == [1, 2, 1] and everyone.json()["devices_total"] == 4
        nowhere = api.post("/rollouts/plan", json={**spec, "labels": {"site": "plant-9"}})
        assert nowhere.status_code == 422 and "plant-9" in nowhere.json()["detail"][0]["msg"]
        assert api.get("/rollouts").json() == []  # nothing created
    if not str(store.path).endswith(".db"):
        return  # the command once is enough: SQLite's run
    port = free_port()
    http = HttpServer(store, port).start()
    try:
        cmd = [sys.executable, "-m", "encoder_fleet.cli", "rollout", "create", "--name", "plant 3", "--dry-run"]
        cmd += [
            "--change",
            "reset_to_factory",
            "--base-per-minute",
            "1",
            "--soak-windows",
            "5",
            "--label",
            "site=plant-3",
        ]
        done = subprocess.run([*cmd, "--url", f"http://127.0.0.1:{port}"], capture_output=True, text=True, timeout=60)
        assert done.returncode == 0, done.stderr
        assert "would roll out to 2 drives (1 offline now) in 2 waves of 1, 1" in done.stdout
        assert "drive-001, drive-002" in done.stdout and "nothing created" in done.stdout
        assert Rollouts(store).list() == [] and "refused" not in done.stdout
        # while another rollout runs, create answers 409: the dry run says so, and exits 1 (it said "would roll out")
        first = Rollouts(store).create(RolloutSpec(**{**spec, "name": "first"}))
        with TestClient(create_app(store)) as api:
            plan = api.post("/rollouts/plan", json=spec).json()
        assert plan["refused"] == f"rollout {first} ('first') is still running or paused"
        assert plan["devices_total"] == 2  # the plan all the same
        done = subprocess.run([*cmd, "--url", f"http://127.0.0.1:{port}"], capture_output=True, text=True, timeout=60)
        assert done.returncode == 1, done.stderr
        assert f"refused now: rollout {first} ('first') is still running or paused" in done.stdout
        assert [r["id"] for r in Rollouts(store).list()] == [first]
    finally:
        http.stop()


def test_the_status_table_keeps_its_columns_for_a_value_of_any_length(tmp_path):
    """A value may be 64 characters: the table's first column was 20 wide, and a longer value moved its row's
    counts out from under their heads."""
    from encoder_fleet.status_cli import group_table

    with Store.open(tmp_path / "fleet.db") as store:
        four_drives(store)
        long = "Plant 3, hall B - the north line by the loading bay"
        store.set_labels("drive-003", {"site": long})
        with TestClient(create_app(store)) as api:
            lines = group_table(api.get("/fleet/health/by/site").json())
    assert [line.split("  ")[0] for line in lines[1:]] == [
        "Plant 3, hall B - the north line by the loading bay",
        "plant-3",
        "(no label)",
    ]
    assert len({len(line) for line in lines}) == 1, "\n".join(lines)  # every count under its head
