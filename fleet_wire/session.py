"""Zenoh session configuration shared by the agent, the service and the tests."""

from __future__ import annotations

import json
import socket

import zenoh


def session_config(mode: str, *, listen: list[str] | None = None, connect: list[str] | None = None) -> zenoh.Config:
    """Multicast scouting off and explicit endpoints only: nothing leaves the endpoints we name."""
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(listen))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(connect))
    return conf


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def loopback_endpoint(port: int | None = None) -> str:
    return f"tcp/127.0.0.1:{port or free_port()}"
