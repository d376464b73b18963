"""Zenoh session configuration shared by the agent, the service and the tests."""

from __future__ import annotations

import json
import re
import socket

import zenoh


def session_config(
    mode: str,
    *,
    listen: list[str] | None = None,
    connect: list[str] | None = None,
    identity=None,
    access_control: dict | None = None,
) -> zenoh.Config:
    """Multicast scouting off and explicit endpoints only: nothing leaves the endpoints we name.
    identity (fleet_wire.security.Identity): TLS with mutual authentication; access_control: the router's
    ACL (fleet_wire.security.access_control)."""
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(listen))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(connect))
    if identity is not None:
        for path, value in identity.tls(listen=bool(listen), connect=bool(connect)).items():
            conf.insert_json5(path, json.dumps(value))
    if access_control is not None:
        conf.insert_json5("access_control", json.dumps(access_control))
    return conf


def agent_session_config(connect: list[str], *, identity=None) -> zenoh.Config:
    """A drive's session: it opens with no router reachable and Zenoh's own connector keeps trying in the
    background (a Zenoh client gives up at open), so the agent buffers in its outbox until a router appears.
    A peer that listens on nothing and gossips its way to routers only, never to other drives."""
    conf = session_config("peer", connect=connect, identity=identity)
    conf.insert_json5("listen/endpoints", "[]")
    conf.insert_json5("connect/timeout_ms", "-1")
    conf.insert_json5("connect/exit_on_failure", "false")
    conf.insert_json5("connect/retry", json.dumps(CONNECT_RETRY))
    conf.insert_json5("scouting/gossip/autoconnect", json.dumps(["router"]))
    return conf


CONNECT_RETRY = {"period_init_ms": 250, "period_max_ms": 4000, "period_increase_factor": 2}


def error_line(exc: zenoh.ZError) -> str:
    """Zenoh's error in one line for a person: its first line, without the Rust source file it came from."""
    first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
    wrapped = re.match(r'^\w+Err\(Message \{ msg: "(.*?)", location', first)  # a config error: the message inside
    if wrapped:
        first = wrapped.group(1)
    return re.sub(r"\s+at /\S+\.rs:\d+\.?", "", first).strip() or type(exc).__name__


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def loopback_endpoint(port: int | None = None) -> str:
    return f"tcp/127.0.0.1:{port or free_port()}"


def set_on_signals(event, *signums: int) -> None:
    """SIGTERM/SIGINT set `event`, from a helper thread: the handler runs in the main thread between bytecodes,
    and if that thread is inside `event.wait()` holding the event's (non-reentrant) lock, a direct `event.set()`
    deadlocks the process (seen: a service that ignored SIGTERM)."""
    import signal
    import threading

    for signum in signums or (signal.SIGTERM, signal.SIGINT):
        signal.signal(signum, lambda *_: threading.Thread(target=event.set, daemon=True).start())
