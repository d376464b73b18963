"""Hidden events replayed through the real parts: the service (embedded router, SQLite) in this process,
`encoder-fleet agent --source replay:REC.csv --factory F.json` processes over loopback. Each planted event
is named with its cause after its onset, alarms are published on encoders/<device>/alarms, and a clean
drive raises nothing."""

import subprocess
import sys
import time

from encoder_fleet.drift_events import draw_drive, write_drive
from fleet_wire import alarms as alarm_wire
from fleet_wire.session import loopback_endpoint
from service.runtime import FleetService, open_session
from service.store import Store

ONSET = 14 * 3600.0


def replay(spec, folder, endpoint):
    rec, factory = write_drive(spec, folder, sample_hz=2.0)
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "encoder_fleet.cli",
            "agent",
            "--device",
            spec.name,
            "--connect",
            endpoint,
            "--source",
            f"replay:{rec}",
            "--factory",
            factory,
            "--window-s",
            "300",
            "--outbox",
            str(folder / f"{spec.name}-outbox.sqlite"),
            "--insecure",  # the wiring under test here is the monitor's; security has its own tests
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


def test_planted_events_are_named_through_service_and_agents(tmp_path):
    specs = [
        draw_drive(31, 1.25, "offset_step", onset_range_s=(ONSET, ONSET)),
        draw_drive(32, 1.25, "adc_clipping", onset_range_s=(ONSET, ONSET)),
        draw_drive(33, 1.25, None),
    ]
    endpoint = loopback_endpoint()
    store = Store.open(tmp_path / "fleet.sqlite")
    session = open_session(listen=[endpoint])
    heard = []
    sub = session.declare_subscriber(
        "encoders/*/alarms", lambda s: heard.append(alarm_wire.decode(s.payload.to_bytes()))
    )
    service = FleetService(store, session, refit_interval_s=0.5, monitor_interval_s=0.2).start()
    try:
        agents = [replay(spec, tmp_path, endpoint) for spec in specs]
        outputs = [a.communicate(timeout=240)[0] for a in agents]
        assert all(a.returncode == 0 for a in agents), outputs
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:  # the last windows judged, the liveliness tokens gone (offline)
            if len(store.alarms(cause="offline")) == len(specs):
                break
            time.sleep(0.2)
    finally:
        service.stop()
        sub.undeclare()
        session.close()
    try:
        for spec in specs:
            raised = [a for a in store.alarms(spec.name) if a["cause"] != "offline"]
            if spec.event is None:
                assert raised == [], raised
                continue
            seen = [(a["cause"], a["raised_at"] / 3600, a["parameters"]) for a in raised]
            assert [a["cause"] for a in raised] == [spec.event.cause], seen
            delay_h = (raised[0]["raised_at"] - spec.event.onset_s) / 3600
            assert 0 <= delay_h <= 2, delay_h
        assert len(store.alarms(cause="offline")) == len(specs)  # the agents ended: liveliness gone
        causes = {(m["device"], m["cause"]) for m in heard if m["event"] == "raised"}
        assert {(s.name, s.event.cause) for s in specs if s.event} <= causes
    finally:
        store.close()
