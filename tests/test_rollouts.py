"""Staged rollouts (issue 12): waves, soak, abort criteria, pause/resume/abort, restart. Real SQLite, a real
Zenoh session, the real FastAPI app; simulated drives stand in for the physical ones.

The hidden effect: which drives drifted since their factory bench, and by how much, is drawn from a seed.
The rollout never sees it; it sees only the windows each drive runs on the set it was given."""

from __future__ import annotations

import json

import numpy as np
import pytest

from edge_agent.agent import factory_message
from edge_agent.sources import SimulatedDrive, drive_model, factory_calibration
from encoder_core.stats import normalisation_scale, window_stats
from fleet_wire import messages as wire
from fleet_wire.session import loopback_endpoint
from service.rollout import RolloutSpec, wave_sizes
from service.runtime import FleetService, open_session
from service.store import Store

DEVICES = [f"drive-{i:02d}" for i in range(1, 9)]
DEVICE_0 = DEVICES[0]


class Clock:
    def __init__(self):
        self.now = 1_700_000_000.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def clock():
    return Clock()


def start(path, clock):
    store = Store.open(path)
    session = open_session(listen=[loopback_endpoint()])
    service = FleetService(store, session, refit_interval_s=0, monitor_interval_s=0, clock=clock).start()
    return store, session, service


def stop(store, session, service):
    service.stop()
    session.close()
    store.close()


@pytest.fixture(params=["sqlite", "postgres"])
def fleet(request, tmp_path, clock):
    target = tmp_path / "fleet.sqlite" if request.param == "sqlite" else request.getfixturevalue("postgres_url")
    parts = start(target, clock)
    yield parts[0], parts[2]
    stop(*parts)


def true_bands(device: str) -> list[dict]:
    seed = DEVICES.index(device) + 1
    return factory_message(device, factory_calibration(drive_model(seed), seed))["bands"]


def shifted(bands: list[dict], offset_error: float) -> list[dict]:
    """The same set with its zero moved (a drift the set does not follow), or barely changed."""
    out = [dict(b) for b in bands]
    for b in out:
        b["w"] = [b["w"][0], b["w"][1] + offset_error, *b["w"][2:]]
        b["zero_offset_rad"] += 1e-6  # a different set even when the offset error is 0
    return out


def drive(device: str, hours: float, knock: float = 0.0) -> SimulatedDrive:
    """The drive; a knock > 0 moved its magnet (both hall offsets, by that share of the amplitude) before
    the records begin: a drift its factory set does not know."""
    seed = DEVICES.index(device) + 1
    knocked = dict(knock_at_s=0.0, knock_fraction=knock) if knock else {}
    return SimulatedDrive(seed, hours=hours, t_min=15.0, t_max=35.0, cycle_hours=1.0, **knocked)


def run_on(store, device: str, version: int, hours: float = 1.0, knock: float = 0.0) -> None:
    """An agent's windows while its drive runs set `version` (raw hall statistics, labelled with the set)."""
    seed = DEVICES.index(device) + 1
    scale = normalisation_scale(factory_calibration(drive_model(seed), seed))
    source = drive(device, hours, knock)
    seq = store.max_seq(device)
    recent = store.window_summary(device, recent=1)["recent"]
    at = recent[0]["window_end"] + 60.0 if recent else 0.0  # the drive's clock goes on
    while (block := source.read(60.0)) is not None:
        seq += 1
        store.insert_window(
            wire.window_message(
                device, seq, window_stats(block, scale), window_start=float(block.t[0]) + at,
                window_end=float(block.t[-1]) + at, temp_rate_c_per_s=0.0, coefficients_version=version,
                angle_quality_deg=0.1,
            )
        )  # fmt: skip


def install(store, service, device: str, running: list[dict], knock: float = 0.0) -> None:
    """The factory set from the drive's bench (v0, with its bench locus) and a confirmed fleet set (v1); its agent
    holds a liveliness token (online)."""
    seed = DEVICES.index(device) + 1
    store.set_online(device, True)
    store.insert_coefficient_set(factory_message(device, factory_calibration(drive_model(seed), seed)))
    store.mark_published(device, 0)
    run_on(store, device, 0, hours=0.25, knock=knock)
    msg = wire.coefficients_message(device, 1, 5000.0, "fit", running)
    store.insert_coefficient_set(msg)
    service._publish(msg)
    run_on(store, device, 1, hours=0.25, knock=knock)


def four_drives_to_reset(store, service, criteria: list[dict]) -> RolloutSpec:
    """DEVICES[:4] installed on a fleet set 0.03 off, and the spec of a reset of them: waves of two, a soak of 60
    windows in 600 s, `criteria`."""
    for device in DEVICES[:4]:
        install(store, service, device, shifted(true_bands(device), 0.03))
    return RolloutSpec(
        name="reset", change={"kind": "reset_to_factory"}, devices=DEVICES[:4], base_per_minute=2,
        soak_windows=60, timeout_s=600.0, abort_criteria=criteria,
    )  # fmt: skip


def soak_and_step(store, service, clock, rounds: int = 12, knocks: dict[str, float] | None = None) -> dict:
    """Rounds of: every drive holding a rollout set runs it for an hour, then the controller steps."""
    for _ in range(rounds):
        for device in DEVICES:
            if service.rollouts.holds(device):
                run_on(store, device, store.published_version(device), knock=(knocks or {}).get(device, 0.0))
        clock.now += 61.0
        service.rollouts.step()
        if service.rollouts.get(1)["state"] != "running":
            break
    return service.rollouts.get(1)


def drifted_drives(seed: int) -> dict[str, float]:
    """The hidden effect: six of the eight drives drifted since the bench (0.02-0.04: a knock's share of the
    hall amplitude, or a bad fleet set's zero error)."""
    rng = np.random.default_rng([seed, 12])
    chosen = rng.choice(DEVICES, size=6, replace=False)
    return {device: float(rng.uniform(0.02, 0.04)) for device in sorted(chosen)}


POLICY = dict(base_per_minute=3, increment_factor=2.0, soak_windows=60)
REGRESSED_ABORTS = [{"failure_type": "regressed", "threshold_percentage": 30, "min_executed": 3}]


@pytest.mark.parametrize("seed", [0, 1])
def test_a_reset_that_makes_drifted_drives_worse_aborts_after_its_first_wave(fleet, clock, seed):
    """The fleet sets follow each drive's drift; a reset to factory puts the drift back on the drifted ones.
    The first wave (three drives, at least one drifted) trips the abort; the wave is rolled back and the
    other five drives never get the change."""
    store, service = fleet
    drifted = drifted_drives(seed)
    fleet_sets = {}
    for device in DEVICES:  # a drifted drive's fleet set is the one right for it now (its knocked magnet)
        knocked = drive(device, 0.0, drifted[device]).knocked if device in drifted else None
        seed_of = DEVICES.index(device) + 1
        right = factory_message(device, factory_calibration(knocked, seed_of)) if knocked else None
        fleet_sets[device] = right["bands"] if right else shifted(true_bands(device), 0.0)
        install(store, service, device, fleet_sets[device], knock=drifted.get(device, 0.0))
    service.rollouts.create(
        RolloutSpec(name="reset", change={"kind": "reset_to_factory"}, abort_criteria=REGRESSED_ABORTS, **POLICY)
    )
    result = soak_and_step(store, service, clock, knocks=drifted)
    assert result["state"] == "aborted", result
    first_wave = {d["device"]: d for d in result["devices"] if d["wave"] == 0}
    assert len(first_wave) == 3 and result["wave"] == 0
    regressed = {device for device, d in first_wave.items() if d["state"] == "regressed"}
    assert regressed == set(first_wave) & set(drifted)  # the judge found exactly the drifted ones
    assert all(d["state"] in ("regressed", "rolled_back") for d in first_wave.values())
    for device in DEVICES:
        published = store.coefficient_set(device, store.published_version(device))
        assert published["bands"] == fleet_sets[device], device
        if device not in first_wave:  # untouched: still v1, no set after it
            assert store.published_version(device) == 1 and store.next_version(device) == 2
            assert not service.rollouts.holds(device)
    states = {h["version"]: h["state"] for h in store.coefficient_history(next(iter(first_wave)))}
    assert states[2] == "rolled_back" and states[3] == "confirmed"  # v2 the reset, v3 the fleet set again
    assert "abort" in result["reason"] or "regressed" in result["reason"]


def test_a_reset_that_fixes_a_bad_fleet_set_reaches_every_drive(fleet, clock):
    """The fleet sets are wrong by a drift drawn from the seed (a bad method went out); the reset to the
    (right) factory sets is better everywhere: wave after wave, 3 + 5 drives, to 100 %."""
    store, service = fleet
    drifted = drifted_drives(2)
    for device in DEVICES:
        install(store, service, device, shifted(true_bands(device), drifted.get(device, 0.025)))
    service.rollouts.create(
        RolloutSpec(name="reset", change={"kind": "reset_to_factory"}, abort_criteria=REGRESSED_ABORTS, **POLICY)
    )
    result = soak_and_step(store, service, clock)
    assert result["state"] == "completed", result
    assert result["percent_done"] == 100.0 and result["by_state"] == {"succeeded": 8}
    assert [w["size"] for w in result["waves"]] == [3, 5]
    for device in DEVICES:
        version = store.published_version(device)
        assert version == 2 and store.coefficient_set(device, version)["bands"] == true_bands(device)
        assert {h["version"]: h["state"] for h in store.coefficient_history(device)}[2] == "confirmed"


@pytest.mark.parametrize("database", ["sqlite", "postgres"])
def test_a_restart_mid_rollout_resumes_where_it_was(tmp_path, clock, database, request):
    path = tmp_path / "fleet.sqlite" if database == "sqlite" else request.getfixturevalue("postgres_url")
    store, session, service = start(path, clock)
    for device in DEVICES:
        install(store, service, device, shifted(true_bands(device), 0.03))
    service.rollouts.create(
        RolloutSpec(name="reset", change={"kind": "reset_to_factory"}, base_per_minute=2, soak_windows=60)
    )
    service.rollouts.step()  # wave 0 starts: two drives get the reset
    run_on(store, DEVICES[0], 2)  # one of them soaks, then the service dies
    stop(store, session, service)

    store, session, service = start(path, clock)
    try:
        before = service.rollouts.get(1)
        assert before["state"] == "running" and before["by_state"] == {"in_progress": 2, "pending": 6}
        result = soak_and_step(store, service, clock, rounds=20)
        assert result["state"] == "completed" and result["by_state"] == {"succeeded": 8}, result
        assert [w["size"] for w in result["waves"]] == [2, 2, 2, 2]
        for device in DEVICES:  # each drive got the change once
            sets = [h for h in store.coefficient_history(device) if h["version"] >= 2]
            assert [h["version"] for h in sets] == [2], device
    finally:
        stop(store, session, service)


def test_wave_sizes_grow_by_the_factor_and_cover_every_device():
    assert wave_sizes(8, 3, 2.0) == [3, 5]
    assert wave_sizes(100, 1, 2.0) == [1, 2, 4, 8, 16, 32, 37]
    assert wave_sizes(5, 2, 1.0) == [2, 2, 1]
    assert wave_sizes(10, 3, 1.5) == [3, 4, 3]


def test_a_rollout_to_unknown_devices_or_an_empty_fleet_is_the_documented_422_naming_where(fleet):
    """The 422 of a spec naming devices the fleet does not have (or of a fleet with none) is the HTTPValidationError
    the OpenAPI documents, saying where (body, devices) and what: it was {"detail": "<a string>"}, which a client
    reading the documented shape failed on."""
    from fastapi.testclient import TestClient

    from service.api import create_app

    store, service = fleet
    api = TestClient(create_app(store, service))
    spec = {"name": "reset", "change": {"kind": "reset_to_factory"}, "base_per_minute": 2, "soak_windows": 60}
    for body, what in [(spec, "no devices"), ({**spec, "devices": ["drive-404"]}, "unknown devices: drive-404")]:
        r = api.post("/rollouts", json=body)
        assert r.status_code == 422, r.text
        (error,) = r.json()["detail"]
        assert error["loc"] == ["body", "devices"] and what in error["msg"], error
    store.set_online(DEVICE_0, True)
    many = [f"drive-{i:03d}" for i in range(100, 112)]
    r = api.post("/rollouts", json={**spec, "devices": [DEVICE_0, *many]})
    assert r.status_code == 422 and "drive-109 and 2 more" in r.json()["detail"][0]["msg"], r.text
    assert api.get("/rollouts").json() == []  # nothing was made of any of them


def test_rest_creates_pauses_resumes_and_aborts_with_an_admin_token_only(fleet, clock, caplog):
    """The REST API's first mutations: admin token only (compared in constant time, never logged); a paused
    rollout starts nobody new; abort rolls the current wave back and leaves later waves untouched."""
    import logging

    from fastapi.testclient import TestClient

    from service.api import create_app
    from service.auth import TokenAuth

    caplog.set_level(logging.DEBUG)
    store, service = fleet
    for device in DEVICES:
        install(store, service, device, shifted(true_bands(device), 0.03))
    auth = TokenAuth(store)
    _, admin = auth.create("admin")
    _, reader = auth.create("read")
    api = TestClient(create_app(store, service, auth))
    as_admin, as_reader = {"Authorization": f"Bearer {admin}"}, {"Authorization": f"Bearer {reader}"}
    spec = {"name": "reset", "change": {"kind": "reset_to_factory"}, "base_per_minute": 2, "soak_windows": 60}

    assert api.post("/rollouts", json=spec).status_code == 401
    assert api.post("/rollouts", json=spec, headers=as_reader).status_code == 403
    for bad in (
        {**spec, "abort_criteria": [{"failure_type": "oops", "threshold_percentage": 10, "min_executed": 1}]},
        {**spec, "abort_criteria": [{"failure_type": "regressed", "threshold_percentage": 0, "min_executed": 1}]},
        {**spec, "base_per_minute": 0},
        {**spec, "devices": ["drive/01"]},
        {**spec, "change": {"kind": "format_disk"}},
        {**spec, "surprise": 1},
    ):
        assert api.post("/rollouts", json=bad, headers=as_admin).status_code == 422, bad
    unknown = api.post("/rollouts", json={**spec, "devices": ["drive-99"]}, headers=as_admin)
    assert unknown.status_code == 422 and "drive-99" in unknown.json()["detail"][0]["msg"]

    created = api.post("/rollouts", json=spec, headers=as_admin)
    assert created.status_code == 201, created.text
    rollout = created.json()
    assert [w["size"] for w in rollout["waves"]] == [2, 2, 2, 2] and rollout["state"] == "running"
    assert api.post("/rollouts", json=spec, headers=as_admin).status_code == 409  # one change at a time
    service.rollouts.step()  # wave 0 starts
    assert api.get("/rollouts/1", headers=as_reader).json()["by_state"] == {"in_progress": 2, "pending": 6}

    assert api.post("/rollouts/1/pause", headers=as_reader).status_code == 403
    assert api.post("/rollouts/1/pause", headers=as_admin).json()["state"] == "paused"
    assert api.post("/rollouts/1/pause", headers=as_admin).status_code == 409
    for device in DEVICES[:2]:
        run_on(store, device, 2)
    clock.now += 120.0
    service.rollouts.step()  # paused: the soaks are judged, nobody new starts
    paused = api.get("/rollouts/1", headers=as_reader).json()
    assert paused["by_state"] == {"pending": 6, "succeeded": 2} and paused["state"] == "paused"

    assert api.post("/rollouts/1/resume", headers=as_admin).json()["state"] == "running"
    service.rollouts.step()  # wave 1 starts
    wave1 = [d["device"] for d in api.get("/rollouts/1", headers=as_reader).json()["devices"] if d["wave"] == 1]
    aborted = api.post("/rollouts/1/abort", headers=as_admin).json()
    assert aborted["state"] == "aborted" and aborted["by_state"] == {"pending": 4, "rolled_back": 2, "succeeded": 2}
    for device in wave1:  # rolled back to the set it ran before: v2 the reset, v3 v1's bands again
        current = store.coefficient_set(device, store.published_version(device))
        assert current["basis"] == "rollback" and current["restores_version"] == 1
    for device in DEVICES[4:]:  # later waves: never touched
        assert store.published_version(device) == 1 and store.next_version(device) == 2
    assert api.post("/rollouts/1/resume", headers=as_admin).status_code == 409
    assert api.get("/rollouts/7", headers=as_reader).status_code == 404
    assert [r["id"] for r in api.get("/rollouts", headers=as_reader).json()] == [1]
    assert admin not in caplog.text and reader not in caplog.text
    metrics = api.get("/metrics", headers=as_reader).text
    assert 'encoder_fleet_staged_rollouts{state="aborted"} 1.0' in metrics
    assert 'encoder_fleet_staged_rollouts{state="running"} 0.0' in metrics
    bare = TestClient(create_app(store))  # REST of the bare database, no running service: read only
    assert bare.get("/rollouts/1").json()["state"] == "aborted"
    assert bare.post("/rollouts", json=spec).status_code == 503


def test_a_rejected_set_and_a_silent_drive_count_as_failures_and_are_rolled_back(fleet, clock):
    store, service = fleet
    criteria = [{"failure_type": "timed_out", "threshold_percentage": 50, "min_executed": 2, "action": "pause"}]
    service.rollouts.create(four_drives_to_reset(store, service, criteria))
    service.rollouts.step()
    first, second = DEVICES[:2]
    store.insert_ack(wire.ack_message(first, 2, "rejected", 99_999.0, reason="signature does not verify"))
    clock.now += 601.0  # the second drive says nothing for longer than the timeout
    service.rollouts.step()
    result = service.rollouts.get(1)
    outcome = {d["device"]: d for d in result["devices"]}
    assert outcome[first]["state"] == "rejected" and "signature" in outcome[first]["reason"]
    assert outcome[second]["state"] == "timed_out" and "0 of 60" in outcome[second]["reason"]
    for device in (first, second):  # the service's record goes back to what the drive runs
        assert store.coefficient_set(device, store.published_version(device))["restores_version"] == 1
    assert result["state"] == "paused" and "1 of 2 executed timed_out" in result["reason"]
    assert outcome[DEVICES[2]]["state"] == "pending"


def test_a_refit_rollout_publishes_each_drives_own_fit_wave_by_wave(fleet, clock):
    """kind refit (a new refit method or policy): the waves carry each drive's fit from its band sums; the
    fleet sets were wrong by a zero error drawn from the seed, and every drive ends on a confirmed fit."""
    store, service = fleet
    errors = drifted_drives(3)
    for device in DEVICES[:4]:
        install(store, service, device, shifted(true_bands(device), errors.get(device, 0.03)))
        run_on(store, device, 1, hours=2.0)  # enough band sums for a refit
    service.rollouts.create(
        RolloutSpec(
            name="method v2", change={"kind": "refit"}, devices=DEVICES[:4], base_per_minute=1,
            increment_factor=3.0, soak_windows=30, abort_criteria=REGRESSED_ABORTS,
        )
    )  # fmt: skip
    result = soak_and_step(store, service, clock)
    assert result["state"] == "completed" and result["by_state"] == {"succeeded": 4}, result
    assert [w["size"] for w in result["waves"]] == [1, 3]
    for device in DEVICES[:4]:
        current = store.coefficient_set(device, store.published_version(device))
        assert current["basis"] == "fit" and current["version"] == 2
        zero_error = abs(current["bands"][0]["w"][1] - true_bands(device)[0]["w"][1])
        assert zero_error < errors.get(device, 0.03) / 3, (device, zero_error)


def test_a_refit_rollout_says_a_drive_without_a_bench_locus_is_not_refit(fleet, clock):
    """A drive whose factory set carries no bench locus gets no fitted set (service.refit.NO_BENCH_LOCUS): a refit
    rollout records it unchanged with that reason, and the drive with its locus beside it gets its fit."""
    from service.refit import NO_BENCH_LOCUS

    store, service = fleet
    bare, located = DEVICES[:2]
    install(store, service, located, shifted(true_bands(located), 0.03))
    run_on(store, located, 1, hours=2.0)
    factory = factory_message(bare, factory_calibration(drive_model(1), 1))
    factory["bands"] = [{k: v for k, v in band.items() if k != "bench_locus"} for band in factory["bands"]]
    store.set_online(bare, True)
    store.insert_coefficient_set(factory)
    store.mark_published(bare, 0)
    run_on(store, bare, 0, hours=2.0)
    service.rollouts.create(
        RolloutSpec(
            name="method v2", change={"kind": "refit"}, devices=[bare, located], base_per_minute=2, soak_windows=30,
            abort_criteria=REGRESSED_ABORTS,
        )
    )  # fmt: skip
    result = soak_and_step(store, service, clock)
    parts = {d["device"]: d for d in result["devices"]}
    assert parts[bare]["state"] == "unchanged" and parts[bare]["reason"] == f"not refit: {NO_BENCH_LOCUS}", parts
    assert parts[located]["state"] == "succeeded" and store.published_version(bare) == 0, parts


def test_a_set_and_the_rollouts_record_of_it_land_together_or_not_at_all(fleet, clock):
    """The store refuses the rollout's record (a trigger stands in for a disk that fails at that moment): the
    set it would have recorded is not stored or published either, so a restart cannot find a change the
    rollout does not know it made."""
    from service.db import database_errors

    store, service = fleet
    install(store, service, DEVICES[0], shifted(true_bands(DEVICES[0]), 0.03))
    service.rollouts.create(
        RolloutSpec(name="reset", change={"kind": "reset_to_factory"}, base_per_minute=1, soak_windows=60)
    )
    postgres = store.path.startswith("postgresql://")
    with store._tx() as c:
        if postgres:
            c.execute(
                "CREATE FUNCTION refuse() RETURNS trigger LANGUAGE plpgsql AS "
                "$$ BEGIN RAISE EXCEPTION 'the disk failed here'; END $$"
            )
            c.execute(
                "CREATE TRIGGER refuse BEFORE UPDATE OF state ON rollout_devices FOR EACH ROW "
                "WHEN (NEW.state = 'in_progress') EXECUTE FUNCTION refuse()"
            )
        else:
            c.execute(
                "CREATE TRIGGER refuse BEFORE UPDATE OF state ON rollout_devices WHEN NEW.state = 'in_progress' "
                "BEGIN SELECT RAISE(ABORT, 'the disk failed here'); END"
            )
    with pytest.raises(database_errors(), match="the disk failed here"):
        service.rollouts.step()
    assert store.next_version(DEVICE_0) == 2 and store.published_version(DEVICE_0) == 1
    assert service.rollouts.get(1)["by_state"] == {"pending": 1}
    with store._tx() as c:
        c.execute("DROP TRIGGER refuse ON rollout_devices" if postgres else "DROP TRIGGER refuse")
    service.rollouts.step()
    assert service.rollouts.get(1)["devices"][0]["version"] == 2 == store.published_version(DEVICE_0)


def test_the_rollout_command_drives_the_rest_api_as_an_operator_would(fleet, tmp_path):
    """`encoder-fleet rollout` in its own process against the real HTTP server: create, list, show, pause,
    abort with an admin token file; a read token or a bad argument is one line and exit 2."""
    import json
    import subprocess
    import sys

    from fleet_wire.session import free_port
    from service.auth import TokenAuth
    from service.runtime import HttpServer

    store, service = fleet
    for device in DEVICES[:3]:
        install(store, service, device, shifted(true_bands(device), 0.03))
    auth = TokenAuth(store)
    admin, reader = tmp_path / "admin-token", tmp_path / "read-token"
    admin.write_text(auth.create("admin")[1])
    reader.write_text(auth.create("read")[1])
    port = free_port()
    http = HttpServer(store, port, service=service, auth=auth).start()

    def rollout(*args, token=admin):
        cmd = [sys.executable, "-m", "encoder_fleet.cli", "rollout", *args, "--url", f"http://127.0.0.1:{port}"]
        cmd += [] if token is None else ["--token-file", str(token)]
        return subprocess.run(cmd, capture_output=True, text=True, timeout=60)

    try:
        create = ["create", "--name", "back to the bench", "--change", "reset_to_factory", "--base-per-minute", "1"]
        create += ["--increment-factor", "2", "--soak-windows", "30", "--abort", "regressed:10:2"]
        refused = rollout(*create, token=reader)
        assert refused.returncode == 2 and "403 this endpoint needs an admin token" in refused.stderr
        assert len(refused.stderr.strip().splitlines()) == 1 and not refused.stdout
        bad = rollout(*create[:-2], "--abort", "regressed:0:2")
        assert bad.returncode == 2 and "threshold_percentage" in bad.stderr, bad.stderr
        made = rollout(*create, "--json", str(tmp_path / "created.json"))
        assert made.returncode == 0, made.stderr
        assert "back to the bench" in made.stdout and "pending 3" in made.stdout
        assert json.loads((tmp_path / "created.json").read_text())["spec"]["abort_criteria"] == [
            {"failure_type": "regressed", "threshold_percentage": 10.0, "min_executed": 2, "action": "abort"}
        ]
        service.rollouts.step()  # wave 1: one drive
        shown = rollout("show", "1", token=reader)
        assert shown.returncode == 0 and "in_progress" in shown.stdout and "v1 -> v2" in shown.stdout
        assert rollout("pause", "1").returncode == 0
        again = rollout("pause", "1")
        assert again.returncode == 2 and "409 rollout 1 is paused: cannot pause it" in again.stderr
        aborted = rollout("abort", "1")
        assert aborted.returncode == 0 and "aborted" in aborted.stdout and "rolled_back" in aborted.stdout
        listed = rollout("list", token=reader)
        assert listed.returncode == 0 and listed.stdout.split()[:2] == ["1", "aborted"]
        missing = rollout("show", "9", token=reader)
        assert missing.returncode == 2 and "404 no rollout 9" in missing.stderr
        tokenless = rollout("list", token=None)  # a user's first try: the error says which option gives the token
        assert tokenless.returncode == 2 and "401" in tokenless.stderr and "--token-file" in tokenless.stderr
    finally:
        http.stop()


def test_an_abort_by_another_process_while_a_device_starts_lets_no_set_out(fleet, clock):
    """Two service processes share the database: the leader steps the rollout, and an operator's abort reaches
    another member's REST. The abort landed after the leader had read the rollout as running and before it
    wrote the device's set: the set went out, recorded in_progress in an aborted rollout, and nothing rolled it
    back. Now the set's transaction checks the rollout is still running, and the abort marks it first."""
    from service.rollout import Rollouts

    store, service = fleet
    install(store, service, DEVICE_0, shifted(true_bands(DEVICE_0), 0.03))
    service.rollouts.create(
        RolloutSpec(name="reset", change={"kind": "reset_to_factory"}, base_per_minute=1, soak_windows=60)
    )
    other = Rollouts(store, service, clock=clock)  # the member the operator's REST call reached
    publish_bands = service.publish_bands

    def aborted_meanwhile(*args, **kwargs):
        other.abort(1, "aborted by an operator on another member")
        return publish_bands(*args, **kwargs)

    service.publish_bands = aborted_meanwhile
    service.rollouts.step()
    service.publish_bands = publish_bands
    rollout = service.rollouts.get(1)
    assert rollout["state"] == "aborted"
    assert store.published_version(DEVICE_0) == 1 and store.next_version(DEVICE_0) == 2  # nothing issued
    assert rollout["by_state"] == {"pending": 1} and not service.rollouts.holds(DEVICE_0)


def test_failures_decided_while_paused_count_once_the_rollout_resumes(fleet, clock):
    """A paused rollout still judges its soaks. The operator pauses wave 0 (three drives, the change makes the
    drifted ones worse), the soaks end meanwhile, and the operator resumes: the regressions decided during the
    pause must trip the abort criterion, not be forgotten by the resume and let the next, larger wave start."""
    store, service = fleet
    drifted = drifted_drives(0)
    for device in DEVICES:  # as in the first test: a drifted drive's fleet set is the one right for it now
        knocked = drive(device, 0.0, drifted[device]).knocked if device in drifted else None
        right = factory_message(device, factory_calibration(knocked, DEVICES.index(device) + 1)) if knocked else None
        install(store, service, device, right["bands"] if right else shifted(true_bands(device), 0.0),
                knock=drifted.get(device, 0.0))  # fmt: skip
    service.rollouts.create(
        RolloutSpec(name="reset", change={"kind": "reset_to_factory"}, abort_criteria=REGRESSED_ABORTS, **POLICY)
    )
    service.rollouts.step()  # wave 0 starts
    service.rollouts.pause(1)
    for _ in range(12):
        for device in DEVICES:
            if service.rollouts.holds(device):
                run_on(store, device, store.published_version(device), knock=drifted.get(device, 0.0))
        clock.now += 61.0
        service.rollouts.step()
    paused = service.rollouts.get(1)
    assert paused["state"] == "paused" and paused["by_state"].get("regressed", 0) >= 1, paused
    clock.now += 61.0
    service.rollouts.resume(1)
    service.rollouts.step()
    result = service.rollouts.get(1)
    assert result["state"] == "aborted" and "regressed" in result["reason"], result
    for device in DEVICES[3:]:  # the next wave never got the change
        assert store.published_version(device) == 1 and store.next_version(device) == 2, device


def a_trial_it_never_applies(store, service) -> None:
    """DEVICE_0 driven two hours on v1, then a fit v2 put on trial and published, which the drive never applies."""
    run_on(store, DEVICE_0, 1, hours=2.0)
    drive_now = service._drive_now(DEVICE_0)
    trial = wire.coefficients_message(DEVICE_0, 2, drive_now - 4000.0, "fit", shifted(true_bands(DEVICE_0), 0.01))
    store.insert_coefficient_set(trial, state="trial")
    service._publish(trial)


def test_a_device_whose_trial_never_ends_does_not_hold_the_rollout_for_ever(fleet, clock):
    """A drive went offline with a fit on trial it never applied: the guard keeps that trial (it is not kept on no
    evidence), so the rollout's part for the drive cannot start. The wave must still end within timeout_s."""
    store, service = fleet
    for device in DEVICES[:2]:
        install(store, service, device, shifted(true_bands(device), 0.03))
    a_trial_it_never_applies(store, service)
    store.set_online(DEVICE_0, False)  # the drive went offline before it applied v2
    service.rollouts.create(
        RolloutSpec(
            name="reset", change={"kind": "reset_to_factory"}, devices=DEVICES[:2], base_per_minute=2,
            soak_windows=60, timeout_s=600.0,
        )
    )  # fmt: skip
    service.rollouts.step()
    run_on(store, DEVICES[1], store.published_version(DEVICES[1]))
    for _ in range(30):  # five hours of steps
        clock.now += 601.0
        assert service.refit(DEVICE_0) is None  # the guard waits: the drive never ran v2
        service.rollouts.step()
    result = service.rollouts.get(1)
    assert store.state_of(DEVICE_0, 2) == "trial"
    assert result["state"] == "completed", result


def test_a_part_that_never_started_is_not_counted_as_executed(fleet, clock):
    """An online drive with a fit on trial it never applied: its part ends timed_out "not started" (no set of the
    rollout went out). The abort criteria counted it as an executed failure: 1 timed_out of 2 executed tripped a
    50 % criterion and aborted a change that had succeeded on the one drive it was made on."""
    store, service = fleet
    for device in DEVICES[:3]:
        install(store, service, device, shifted(true_bands(device), 0.03))
    a_trial_it_never_applies(store, service)  # online, but it never applies v2
    criteria = [{"failure_type": "timed_out", "threshold_percentage": 50, "min_executed": 1}]
    service.rollouts.create(
        RolloutSpec(
            name="reset", change={"kind": "reset_to_factory"}, devices=DEVICES[:3], base_per_minute=2,
            soak_windows=60, timeout_s=600.0, abort_criteria=criteria,
        )
    )  # fmt: skip
    service.rollouts.step()
    run_on(store, DEVICES[1], store.published_version(DEVICES[1]))
    for _ in range(4):
        clock.now += 601.0
        service.rollouts.step()
        if (v := store.published_version(DEVICES[2])) != 1:
            run_on(store, DEVICES[2], v)
    result = service.rollouts.get(1)
    parts = {d["device"]: d for d in result["devices"]}
    assert parts[DEVICE_0]["state"] == "timed_out" and "not started" in parts[DEVICE_0]["reason"], parts
    assert result["state"] != "aborted", result  # before: "1 of 2 executed timed_out (50 % >= 50 %)"
    assert parts[DEVICES[2]]["state"] != "pending", parts  # the next wave got the change


def reset_rollout_on_a_driven_device(store, service) -> None:
    """DEVICE_0 off its truth and driven for two hours, and a reset-to-factory rollout created for it alone."""
    install(store, service, DEVICE_0, shifted(true_bands(DEVICE_0), 0.03))
    run_on(store, DEVICE_0, 1, hours=2.0)
    service.rollouts.create(
        RolloutSpec(name="reset", change={"kind": "reset_to_factory"}, devices=[DEVICE_0], base_per_minute=1,
                    soak_windows=60)
    )  # fmt: skip


def test_a_refit_and_a_rollouts_start_on_one_device_issue_one_set(fleet, clock):
    """Service processes share the fleet: the leader steps every rollout, while the member serving the device
    refits it. The member read the device as not held and fitted; meanwhile the leader started the rollout's set on
    it. Two sets were then in flight for one drive (the rollout's v2 and the fit v3, both on trial)."""
    from service.rollout import DeviceHeld, Rollouts

    store, service = fleet
    reset_rollout_on_a_driven_device(store, service)
    leader = Rollouts(store, service, clock=clock)  # the process serving partition 0
    fit = service.fit

    def fit_while_the_leader_starts(device, **kwargs):
        result = fit(device, **kwargs)
        leader.step()
        return result

    service.fit = fit_while_the_leader_starts
    try:
        with pytest.raises(DeviceHeld):  # refused: the device is the rollout's now
            service.refit(DEVICE_0)  # the member's refit pass
    finally:
        service.fit = fit
    on_trial = [h["version"] for h in store.coefficient_history(DEVICE_0) if h["state"] == "trial"]
    assert len(on_trial) == 1, store.coefficient_history(DEVICE_0)
    assert service.rollouts.get(1)["devices"][0]["version"] == on_trial[0]


def test_a_rollouts_start_after_a_members_fit_on_one_device_issues_no_second_set(fleet, clock):
    """The other order: the leader read the device (nothing on trial) and the member issued it a fit before the
    leader's set was written. The rollout's set must wait for that trial instead of going out beside it."""
    store, service = fleet
    reset_rollout_on_a_driven_device(store, service)
    publish_bands = service.publish_bands

    def member_refits_meanwhile(*args, **kwargs):
        result = service.fit(DEVICE_0)
        assert result is not None and result.changed
        service.publish_fit(DEVICE_0, result)  # the member serving the device: v2 on trial
        return publish_bands(*args, **kwargs)

    service.publish_bands = member_refits_meanwhile
    try:
        service.rollouts.step()
    finally:
        service.publish_bands = publish_bands
    on_trial = [h["version"] for h in store.coefficient_history(DEVICE_0) if h["state"] == "trial"]
    assert on_trial == [2] and store.next_version(DEVICE_0) == 3, store.coefficient_history(DEVICE_0)
    assert service.rollouts.get(1)["by_state"] == {"pending": 1} and not service.rollouts.holds(DEVICE_0)


def test_two_members_creating_a_rollout_at_once_make_one(postgres_url):
    """Every service process answers POST /rollouts. The check for a running rollout came before the insert's
    transaction, so two members' creations could both find none and both run (a second reader's interleaving on
    PostgreSQL: rollouts 1 and 2 both running). Now the check and the insert are one transaction, one process at a
    time: here another member holds the creation's lock and creates its rollout meanwhile, and this one's creation
    waits for it, then answers 409."""
    import threading

    import psycopg
    from wire_samples import window

    from service.rollout import CREATE_LOCK, RolloutError, Rollouts

    with Store.open(postgres_url) as store:
        store.insert_window(window("drive-001", seq=1))
        other = psycopg.connect(postgres_url)  # the other member, in the middle of its own creation
        other.execute("SELECT pg_advisory_xact_lock(%s)", (CREATE_LOCK,))
        outcome = []

        def create():
            try:
                spec = {"name": "from A", "change": {"kind": "reset_to_factory"}, "base_per_minute": 1}
                outcome.append(Rollouts(store).create(RolloutSpec.model_validate({**spec, "soak_windows": 1})))
            except RolloutError as exc:
                outcome.append(exc)

        mine = threading.Thread(target=create)
        mine.start()
        mine.join(0.5)
        assert mine.is_alive() and not outcome  # it waits for the other member's creation to end
        other.execute(
            "INSERT INTO rollouts (name, spec_json, state, counted_from, created_at, updated_at) "
            "VALUES ('from B', '{}', 'running', 0, 0, 0)"
        )
        other.commit()
        other.close()
        mine.join(10)
        assert isinstance(outcome[0], RolloutError) and outcome[0].status == 409, outcome
        running = store._rows("SELECT name FROM rollouts WHERE state IN ('running', 'paused')")
        assert [r["name"] for r in running] == ["from B"]


def test_a_refused_creation_keeps_the_band_sums_in_memory(fleet, caplog):
    """A creation refused with 409 inside its transaction (a rollout already running) rolled the transaction back as
    a failed write, which drops every band sum kept in memory: the next window of each drive rebuilt its band from
    all its windows (a second reader). Nothing of the sums was written in that transaction: they are kept."""
    import logging

    from service.rollout import RolloutError

    store, service = fleet
    install(store, service, DEVICE_0, shifted(true_bands(DEVICE_0), 0.03))
    spec = RolloutSpec(name="reset", change={"kind": "reset_to_factory"}, base_per_minute=1, soak_windows=60)
    service.rollouts.create(spec)
    with pytest.raises(RolloutError, match="still running"):
        service.rollouts.create(spec)
    caplog.set_level(logging.INFO, logger="service.store")
    seq = store.max_seq(DEVICE_0) + 1
    window = store.windows(DEVICE_0, stats=True)[-1]
    store.insert_window({**window, "seq": seq, "window_start": window["window_end"] + 1.0,
                         "window_end": window["window_end"] + 61.0})  # fmt: skip
    assert "rebuilt" not in caplog.text


def test_a_member_stuck_in_its_creation_does_not_stall_another_for_good(postgres_url):
    """The creation's lock was waited for without a bound, holding this process's writer connection: a member stuck
    inside its own creation's transaction stalled this one's ingest for as long (a second reader). Now the wait is
    bounded, and the creation answers 409 saying another process is creating one."""
    import time

    import psycopg
    from wire_samples import window

    from service.rollout import CREATE_LOCK, RolloutError, Rollouts

    with Store.open(postgres_url) as store:
        store.insert_window(window("drive-001", seq=1))
        stuck = psycopg.connect(postgres_url)
        stuck.execute("SELECT pg_advisory_xact_lock(%s)", (CREATE_LOCK,))  # and never ends its transaction
        try:
            started = time.monotonic()
            spec = {"name": "from A", "change": {"kind": "reset_to_factory"}, "base_per_minute": 1, "soak_windows": 1}
            with pytest.raises(RolloutError, match="another service process is creating a rollout") as refused:
                Rollouts(store).create(RolloutSpec.model_validate(spec))
            assert refused.value.status == 409 and time.monotonic() - started < 10
            assert store.insert_window(window("drive-001", seq=2))  # the writer goes on
        finally:
            stuck.close()
        assert store._rows("SELECT count(*) AS n FROM rollouts")[0]["n"] == 0


def test_a_set_refused_and_then_applied_is_soaked_and_judged_not_rolled_back(fleet, clock):
    """The agent refused the rollout's set (a damaged copy, a check the operator then fixed) and then applied it: an
    ack 'applied' for the same version, or windows run on it whose applied ack has not arrived yet. The rollout took
    the refusal alone: the part ended rejected and the drive was rolled back from the set it runs, counted a failure.
    A refusal the drive's own reports overrule is none (as store.refusals, which the guard answers, has it)."""
    store, service = fleet
    applied, ran = DEVICES[:2]
    for device in (applied, ran):  # the fleet sets are off: the reset to factory is better on both
        install(store, service, device, shifted(true_bands(device), 0.03))
    service.rollouts.create(
        RolloutSpec(name="reset", change={"kind": "reset_to_factory"}, devices=[applied, ran], base_per_minute=2,
                    soak_windows=60)
    )  # fmt: skip
    service.rollouts.step()
    for device in (applied, ran):
        store.insert_ack(wire.ack_message(device, 2, "rejected", 99_999.0, reason="signature does not verify"))
    store.insert_ack(wire.ack_message(applied, 2, "applied", 99_999.5, angle_quality_deg=0.1))
    for device in (applied, ran):
        run_on(store, device, 2)
    clock.now += 61.0
    service.rollouts.step()
    result = service.rollouts.get(1)
    assert {d["device"]: d["state"] for d in result["devices"]} == {applied: "succeeded", ran: "succeeded"}, result
    assert result["state"] == "completed" and result["by_state"] == {"succeeded": 2}
    for device in (applied, ran):  # nothing rolled back: the record is the set the drive runs
        assert store.published_version(device) == 2 and store.next_version(device) == 3
        assert store.state_of(device, 2) == "confirmed"


def test_devices_the_change_leaves_unchanged_are_not_counted_as_executed(fleet, clock):
    """Three drives already run their factory sets (a reset is a no-op there: unchanged), the fourth refuses the
    reset. The abort criteria counted the unchanged parts as executed: 1 rejected of 4 executed (25 %) stayed under
    a 50 % threshold, and the next wave started, while the change had failed on every drive it was made on."""
    store, service = fleet
    for device in DEVICES[:3]:
        install(store, service, device, true_bands(device))
    for device in DEVICES[3:5]:
        install(store, service, device, shifted(true_bands(device), 0.03))
    criteria = [{"failure_type": "rejected", "threshold_percentage": 50, "min_executed": 1}]
    service.rollouts.create(
        RolloutSpec(name="reset", change={"kind": "reset_to_factory"}, devices=DEVICES[:5], base_per_minute=4,
                    soak_windows=60, abort_criteria=criteria)
    )  # fmt: skip
    service.rollouts.step()
    store.insert_ack(wire.ack_message(DEVICES[3], 2, "rejected", 99_999.0, reason="signature does not verify"))
    for _ in range(3):
        clock.now += 61.0
        service.rollouts.step()
    result = service.rollouts.get(1)
    assert result["by_state"] == {"pending": 1, "rejected": 1, "unchanged": 3}, result
    assert result["state"] == "aborted" and "1 of 1 executed rejected" in result["reason"], result
    assert store.published_version(DEVICES[4]) == 1 and store.next_version(DEVICES[4]) == 2  # wave 1: untouched


def test_a_drive_offline_when_its_wave_starts_waits_and_ends_offline_not_as_a_failure(fleet, clock):
    """A drive with no liveliness token when its wave starts was issued the set all the same, timed out unsoaked and
    was rolled back, counted a failure of the change (here it tripped the abort: 1 of 2 executed timed_out) for a
    drive that was not there. Now an offline drive waits for its token, timeout_s from its wave's start at most: one
    back in time gets its part (drive-03), one that is not ends offline (drive-01), no set issued, no failure."""
    store, service = fleet
    criteria = [{"failure_type": "timed_out", "threshold_percentage": 50, "min_executed": 1}]
    spec = four_drives_to_reset(store, service, criteria)
    gone, back = DEVICES[0], DEVICES[2]
    for device in (gone, back):
        store.set_online(device, False)
    service.rollouts.create(spec)
    for _ in range(40):
        parts = {d["device"]: d for d in service.rollouts.get(1)["devices"]}
        if parts[back]["state"] == "pending" and service.rollouts.get(1)["wave"] == 1:
            clock.now += 120.0  # its wave has started without it; the drive comes back within timeout_s
            store.set_online(back, True)
        for device in DEVICES[:4]:  # a drive gone sends no windows
            if service.rollouts.holds(device) and store.device(device)["online"]:
                run_on(store, device, store.published_version(device))
        clock.now += 61.0
        service.rollouts.step()
        if service.rollouts.get(1)["state"] != "running":
            break
    result = service.rollouts.get(1)
    assert result["state"] == "completed" and result["by_state"] == {"offline": 1, "succeeded": 3}, result
    part = {d["device"]: d for d in result["devices"]}[gone]
    assert part["version"] is None and part["before_version"] == 1 and "offline" in part["reason"]
    assert store.published_version(gone) == 1 and store.next_version(gone) == 2  # nothing issued, nothing rolled back
    assert store.published_version(back) == 2 and store.state_of(back, 2) == "confirmed"


def test_the_offline_outcome_migration_keeps_every_rollout_record(tmp_path):
    """Migration 080 makes rollout_devices again (its state's CHECK now takes 'offline'): a database written before
    it keeps every device's part, and takes the new outcome."""
    from service.store import migration_files

    older = tmp_path / "migrations"
    older.mkdir()
    for version, f in migration_files():
        if version < 80:
            (older / f.name).write_text(f.read_text())
    path = tmp_path / "fleet.sqlite"
    with Store.open(path, migrations_dir=older) as store:
        store.set_online(DEVICE_0, True)  # the device row
        with store._tx() as c:
            c.execute(
                "INSERT INTO rollouts (id, name, spec_json, state, counted_from, created_at, updated_at) "
                "VALUES (1, 'reset', '{}', 'aborted', 0, 0, 0)"
            )
            c.execute("INSERT INTO rollout_devices VALUES (1, ?, 0, 'rolled_back', 1, 2, 5.0, 6.0, 'wave rolled back')",
                      (DEVICE_0,))  # fmt: skip
    with Store.open(path) as store:
        assert [dict(r) for r in store._rows("SELECT * FROM rollout_devices")] == [
            {"rollout": 1, "device": DEVICE_0, "wave": 0, "state": "rolled_back", "before_version": 1, "version": 2,
             "started_at": 5.0, "decided_at": 6.0, "reason": "wave rolled back"}
        ]  # fmt: skip
        with store._tx() as c:
            c.execute("UPDATE rollout_devices SET state = 'offline'")
        assert store.rollout_records(DEVICE_0)[0]["state"] == "offline"


def test_a_rollouts_parts_come_in_pages_filtered_by_state_and_wave_and_the_command_reads_them_all(fleet, tmp_path):
    """GET /rollouts/{id} listed every part at once (100,000 drives: 13.9 MB, 0.8 s a read, answered by every
    POST that changes a rollout too); now a page of `limit` in (wave, device) order, `devices_next` naming the next,
    and `state` or `wave` keeping only those. `rollout show` walks every page."""
    import subprocess
    import sys

    from fastapi.testclient import TestClient

    from fleet_wire.session import free_port
    from service.api import create_app
    from service.runtime import HttpServer

    store, service = fleet
    devices = [f"drive-{i:03d}" for i in range(23)]
    for device in devices:
        store.set_online(device, True)
    api = TestClient(create_app(store, service))
    spec = {"name": "reset", "change": {"kind": "reset_to_factory"}, "base_per_minute": 3, "soak_windows": 60}
    spec["increment_factor"] = 2.0  # waves of 3, 6, 12 and the 2 left
    created = api.post("/rollouts", json=spec).json()
    assert len(created["devices"]) == 23 and created["devices_next"] is None
    everything = service.rollouts.get(1)["devices"]
    assert [d["wave"] for d in everything] == sorted(d["wave"] for d in everything)
    pages, after = [], None
    while True:
        page = api.get("/rollouts/1", params={"limit": 5, **({"after": after} if after else {})}).json()
        assert page["devices_total"] == 23 and page["by_state"] == {"pending": 23}  # the whole rollout's counts
        pages.append(page["devices"])
        if not (after := page["devices_next"]):
            break
        assert len(page["devices"]) == 5
    assert [len(p) for p in pages] == [5, 5, 5, 5, 3] and sum(pages, []) == everything
    wave_2 = api.get("/rollouts/1", params={"wave": 2}).json()["devices"]
    assert wave_2 == [d for d in everything if d["wave"] == 2] and len(wave_2) == 12
    service.rollouts.step()  # the first wave starts: three parts in progress (or decided) now
    moved = [d for d in service.rollouts.get(1)["devices"] if d["state"] != "pending"]
    assert len(moved) == 3
    pending = api.get("/rollouts/1", params={"state": "pending", "limit": 100}).json()
    moved_ids = {d["device"] for d in moved}
    assert [d["device"] for d in pending["devices"]] == [
        d["device"] for d in everything if d["device"] not in moved_ids
    ]
    for bad in ({"after": "drive-003"}, {"after": "x:drive-003"}, {"state": "lost"}, {"limit": 0}, {"wave": -1}):
        r = api.get("/rollouts/1", params=bad)
        assert r.status_code == 422 and r.json()["detail"][0]["loc"][0] == "query", (bad, r.text)
    port = free_port()
    http = HttpServer(store, port, service=service).start()
    try:
        cmd = [sys.executable, "-m", "encoder_fleet.cli", "rollout", "show", "1", "--url", f"http://127.0.0.1:{port}"]
        shown = subprocess.run([*cmd, "--json", str(tmp_path / "r.json")], capture_output=True, text=True, timeout=60)
        assert shown.returncode == 0, shown.stderr
        assert len(json.loads((tmp_path / "r.json").read_text())["devices"]) == 23
        third = subprocess.run([*cmd, "--wave", "3"], capture_output=True, text=True, timeout=60)
        assert third.returncode == 0 and third.stdout.count("wave 3 ") == 12 and "wave 2 " not in third.stdout
    finally:
        http.stop()


@pytest.mark.parametrize("backend", ["sqlite", "postgres"])
def test_a_cursor_the_service_never_gave_is_a_422_naming_after_not_a_500(backend, tmp_path, request):
    """`after` is a page's devices_next, WAVE:DEVICE. A wave past a 64-bit integer (SQLite cannot bind it) or of a
    digit Python's isdigit takes and int() does not (²) answered 500; a device no drive can be named read pages
    of nothing. Each is refused with 422 at query.after; a cursor the service gave still reads the next page."""
    from fastapi.testclient import TestClient

    from service.api import create_app
    from service.rollout import Rollouts

    target = tmp_path / "fleet.sqlite" if backend == "sqlite" else request.getfixturevalue("postgres_url")
    with Store.open(target) as store:
        for i in range(5):
            store.set_online(f"drive-{i}", True)
        spec = {"change": {"kind": "reset_to_factory"}, "base_per_minute": 2, "soak_windows": 30}
        Rollouts(store).create(RolloutSpec(name="reset", **spec))
        api = TestClient(create_app(store), raise_server_exceptions=False)
        hostile = ("9" * 30 + ":drive-1", f"{2**63}:drive-1", "²:drive-1", "٣:drive-1", "0:drive-1\x00", "0:drive-1\n")
        for after in (*hostile, "0:-x"):
            r = api.get("/rollouts/1", params={"after": after, "limit": 2})
            assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["query", "after"], (after, r.text)
        first = api.get("/rollouts/1", params={"limit": 2}).json()
        assert first["devices_next"] == "0:drive-1"
        then = api.get("/rollouts/1", params={"limit": 2, "after": first["devices_next"]}).json()
        assert [d["device"] for d in then["devices"]] == ["drive-2", "drive-3"]


def test_a_drive_retired_mid_rollout_is_no_failure_of_the_change_and_gets_no_set_of_it(fleet, clock):
    """A drive retired while its part soaks sends nothing the store keeps: its part timed out unsoaked, counted as a
    failure of the change (here 1 of 2 executed timed_out aborted the rollout and rolled back the drive it had
    succeeded on). One retired before its wave got the change all the same. Now the soaking one is rolled back at
    once, unjudged and not counted, and the later one's part ends unchanged with no set issued."""
    store, service = fleet
    soaking, later = DEVICES[0], DEVICES[2]
    criteria = [{"failure_type": "timed_out", "threshold_percentage": 50, "min_executed": 1}]
    service.rollouts.create(four_drives_to_reset(store, service, criteria))
    service.rollouts.step()
    assert service.rollouts.holds(soaking)
    for device in (soaking, later):
        store.retire_device(device, by="token 1", note="replaced")
    for _ in range(12):
        for device in DEVICES[:4]:  # what a retired drive sends is not stored: it soaks nothing
            if service.rollouts.holds(device) and device not in (soaking, later):
                run_on(store, device, store.published_version(device))
        clock.now += 61.0
        service.rollouts.step()
        if service.rollouts.get(1)["state"] != "running":
            break
    result = service.rollouts.get(1)
    parts = {d["device"]: d for d in result["devices"]}
    assert result["state"] == "completed", result
    assert result["by_state"] == {"rolled_back": 1, "succeeded": 2, "unchanged": 1}, result
    assert "retired" in parts[soaking]["reason"] and "retired" in parts[later]["reason"]
    assert store.coefficient_set(soaking, store.published_version(soaking))["restores_version"] == 1
    assert store.published_version(later) == 1 and store.next_version(later) == 2  # nothing issued to it
    assert store.published_version(DEVICES[1]) == 2 and store.state_of(DEVICES[1], 2) == "confirmed"


def test_a_part_rolled_back_for_its_drives_retirement_is_not_counted_as_executed(fleet, clock):
    """Of a wave of two, one drive is retired mid-soak and the other refuses the reset: the change failed on every
    drive it was judged on. Counted as executed, the retired one's part read as 1 rejected of 2 (50 %), under a 60 %
    criterion, and the next wave started."""
    store, service = fleet
    criteria = [{"failure_type": "rejected", "threshold_percentage": 60, "min_executed": 1}]
    service.rollouts.create(four_drives_to_reset(store, service, criteria))
    service.rollouts.step()
    store.retire_device(DEVICES[0], by="token 1", note="replaced")
    clock.now += 61.0
    service.rollouts.step()
    clock.now += 601.0  # the refusal comes after the retired drive's soak would have timed out
    store.insert_ack(wire.ack_message(DEVICES[1], 2, "rejected", 99_999.0, reason="signature does not verify"))
    service.rollouts.step()
    result = service.rollouts.get(1)
    assert result["by_state"] == {"pending": 2, "rejected": 1, "rolled_back": 1}, result
    assert result["state"] == "aborted" and "1 of 1 executed rejected" in result["reason"], result
