"""`encoder-fleet bench-fleet-accuracy --through-service`: the issue's own measurement, through the real parts.

Each drive of a fleet (encoder_fleet/fieldsim.py, calibrated at the end of the line as `run_drive` does) is
written as a recording and its factory set as JSON; then an `encoder-fleet service` process (embedded router,
SQLite file) and one `encoder-fleet agent --source replay:REC.csv --factory F.json --real-time-factor F` process
per drive run as a user would run them, over loopback. What each drive ran is read back from the service's
database: the factory set, then every set from the drive time its agent acknowledged applying it. It is scored
on true angle by the same code as the in-process loop (`fleet_accuracy.score`).

The in-process loop runs the service's rules on the drive's clock; here the service runs on the wall clock, so
a replay at F times real time also measures whether the service keeps its drive-time pace when an hour of
windows comes in 3600 / F seconds (it did not, before its passes ran as soon as windows were stored).
"""

from __future__ import annotations

import json
import signal
import socket
import sqlite3
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from edge_agent.agent import factory_message
from encoder_core.correction import BandedCorrection
from encoder_fleet.fleet_accuracy import DriveResult, DriveSpec, drive_of, scored
from encoder_fleet.recording import write_recording
from fleet_wire.session import loopback_endpoint

STARTUP_S = 30.0  # the service's router must listen within this


def replay_fleet(specs: list[DriveSpec], *, real_time_factor: float, progress=None) -> list[DriveResult]:
    """Every drive of `specs` at once through one service; one DriveResult per drive, in order."""
    say = progress or (lambda text: None)
    with tempfile.TemporaryDirectory(prefix="fleet-replay-") as tmp:
        folder = Path(tmp)
        drives = []
        for spec in specs:
            _, factory, run = drive_of(spec)
            write_recording(run.samples, folder / f"{spec.name}.csv")
            (folder / f"{spec.name}-factory.json").write_text(json.dumps(factory_message(spec.name, factory)))
            drives.append((spec, factory, run))
        hours = max(spec.days for spec in specs) * 24
        say(f"{len(specs)} drives through encoder-fleet service and agents at {real_time_factor:g}x "
            f"({hours:g} drive-hours in ~{hours * 3600 / real_time_factor:.0f} s)")  # fmt: skip
        database = folder / "fleet.sqlite"
        _run_fleet(folder, database, [spec.name for spec in specs], specs[0].window_s, real_time_factor)
        with sqlite3.connect(database) as conn:
            results = [_result(conn, spec, factory, run) for spec, factory, run in drives]
            for spec, result in zip(specs, results):
                if result.versions_applied == 0 and spec.motion != "dwell":
                    say(f"{spec.name} applied no set: {_what_the_service_holds(conn, spec.name)}")
            say(_set_latency(conn, specs[0].window_s))
            return results


def _set_latency(conn: sqlite3.Connection, window_s: float) -> str:
    """How long, in drive time, the sets took from being made (the newest window the service held) to being
    applied by their drives: the pace the service kept. The in-process loop applies a set at the next window."""
    lags = sorted(
        (at - made) / 60.0
        for at, made in conn.execute(
            "SELECT a.at, s.created_at FROM acks a JOIN coefficient_sets s ON s.device = a.device AND "
            "s.version = a.version WHERE a.status = 'applied' AND a.version > 0"
        )
    )
    if not lags:
        return "no set was applied"
    median, p90 = lags[len(lags) // 2], lags[min(len(lags) - 1, int(0.9 * len(lags)))]
    return (
        f"{len(lags)} sets applied, {median:.1f} drive-minutes after they were made (median; 90th percentile "
        f"{p90:.1f}, worst {lags[-1]:.1f}; a window is {window_s / 60:g} min)"
    )


def _run_fleet(folder: Path, database: Path, names: list[str], window_s: float, real_time_factor: float) -> None:
    endpoint = loopback_endpoint()
    cli = [sys.executable, "-m", "encoder_fleet.cli"]
    quiet = ["--insecure", "--log-level", "error"]  # the transport is not what this bench measures
    service = subprocess.Popen(
        [*cli, "service", "--db", str(database), "--listen", endpoint, "--http-port", "0", *quiet],
        stdout=subprocess.DEVNULL,
    )
    agents = []
    try:
        _wait_listening(endpoint, service)
        for name in names:
            agents.append(
                subprocess.Popen(
                    [*cli, "agent", "--device", name, "--connect", endpoint, "--source", f"replay:{folder / name}.csv",
                     "--factory", str(folder / f"{name}-factory.json"), "--window-s", f"{window_s:g}",
                     "--real-time-factor", f"{real_time_factor:g}", "--outbox", str(folder / f"{name}-outbox.sqlite"),
                     *quiet],
                    stdout=subprocess.DEVNULL,
                    stderr=subprocess.DEVNULL,  # each says it runs --insecure; a failure shows in its exit status
                )
            )  # fmt: skip
        failed = [name for name, agent in zip(names, agents) if agent.wait() != 0]
        if failed:
            raise RuntimeError(f"the agents of {', '.join(failed)} failed (exit status not 0)")
        time.sleep(2.0)  # the last windows' refit and monitor passes
    finally:
        for agent in agents:
            if agent.poll() is None:
                agent.kill()
        service.send_signal(signal.SIGTERM)  # a graceful stop: what the writer holds is stored
        try:
            service.wait(60)
        except subprocess.TimeoutExpired:
            service.kill()


def _wait_listening(endpoint: str, service: subprocess.Popen) -> None:
    host, port = endpoint.split("/", 1)[1].rsplit(":", 1)
    deadline = time.monotonic() + STARTUP_S
    while time.monotonic() < deadline:
        if service.poll() is not None:
            raise RuntimeError(f"encoder-fleet service exited with status {service.returncode} at start-up")
        try:
            with socket.create_connection((host, int(port)), timeout=0.5):
                return
        except OSError:
            time.sleep(0.1)
    raise RuntimeError(f"encoder-fleet service did not listen on {endpoint} within {STARTUP_S:g} s")


def _what_the_service_holds(conn: sqlite3.Connection, device: str) -> str:
    """Why a drive that turns ran its factory set all along, as far as the database tells."""
    counts = [
        conn.execute(sql, (device,)).fetchone()[0]
        for sql in (
            "SELECT count(*) FROM windows WHERE device = ?",
            "SELECT count(*) FROM coefficient_sets WHERE device = ? AND version = 0",
            "SELECT count(*) FROM coefficient_sets WHERE device = ? AND version > 0",
            "SELECT count(*) FROM acks WHERE device = ? AND status = 'rejected'",
            "SELECT count(*) FROM dead_letters WHERE key_expr LIKE '%' || ? || '%'",
        )
    ]
    return "{} windows, factory set {}, {} sets made, {} refused by the agent, {} dead letters".format(
        counts[0], "known" if counts[1] else "never announced", *counts[2:]
    )


def _result(conn: sqlite3.Connection, spec: DriveSpec, factory: BandedCorrection, run) -> DriveResult:
    """What the drive ran, from its applied acks, scored on true angle."""
    timeline = [(float(run.samples.t[0]), factory)]
    applied = conn.execute(
        "SELECT s.body_json, a.at FROM acks a JOIN coefficient_sets s ON s.device = a.device AND s.version = a.version"
        " WHERE a.device = ? AND a.status = 'applied' AND a.version > 0 ORDER BY a.at, a.id",
        (spec.name,),
    ).fetchall()
    timeline += [(float(at), BandedCorrection.from_dict(json.loads(body))) for body, at in applied]
    return scored(spec, factory, run, timeline)
