"""Operating the commands: --version, --log-level with one JSON event per line."""

from __future__ import annotations

import json
import subprocess
import sys

from fleet_wire.session import free_port


def test_version_is_the_installed_package_version():
    from importlib.metadata import version

    done = subprocess.run([sys.executable, "-m", "encoder_fleet.cli", "--version"], capture_output=True, text=True)
    assert done.returncode == 0 and done.stdout.strip() == f"encoder-fleet {version('encoder-fleet')}"


def test_service_logs_one_json_event_per_line_at_the_level_asked(tmp_path):
    command = [sys.executable, "-m", "encoder_fleet.cli", "service", "--db", str(tmp_path / "f.sqlite")]
    command += [
        "--insecure",
        "--listen",
        f"tcp/127.0.0.1:{free_port()}",
        "--http-port",
        str(free_port()),
        "--log-level",
        "info",
    ]
    service = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert service.stdout.readline().startswith("service:")
    finally:
        service.terminate()
        _, err = service.communicate(timeout=30)
    assert service.returncode == 0, err
    events = [json.loads(line) for line in err.splitlines() if line.strip()]  # every line is one JSON event
    assert {"ts", "level", "logger", "event"} <= set(events[0])
    started = [e for e in events if e["event"] == "service started"]
    assert started and started[0]["level"] == "info" and started[0]["database"].endswith("f.sqlite")
    assert any(e["logger"].startswith("uvicorn") for e in events)  # the web server logs the same way

    quiet = subprocess.Popen(command[:-1] + ["warning"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        quiet.stdout.readline()
    finally:
        quiet.terminate()
        _, err = quiet.communicate(timeout=30)
    assert "service started" not in err
