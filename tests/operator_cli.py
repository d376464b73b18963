"""An operator's command against the real service's REST API: the HTTP server on a free port with an admin token
("night shift") and a read token, and the command run in its own process as an operator runs it."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from fleet_wire.session import free_port
from service.auth import TokenAuth
from service.runtime import HttpServer


@contextmanager
def operator_cli(store, tmp_path, command: str) -> Iterator[Callable[..., subprocess.CompletedProcess]]:
    """run(*args, token="admin" | "read"): `encoder-fleet COMMAND ARGS --url … --token-file …`."""
    auth = TokenAuth(store)
    tokens = {"admin": tmp_path / "admin-token", "read": tmp_path / "read-token"}
    tokens["admin"].write_text(auth.create("admin", "night shift")[1])
    tokens["read"].write_text(auth.create("read")[1])
    port = free_port()
    http = HttpServer(store, port, auth=auth).start()

    def run(*args: str, token: str = "admin") -> subprocess.CompletedProcess:
        cmd = [sys.executable, "-m", "encoder_fleet.cli", command, *args, "--url", f"http://127.0.0.1:{port}"]
        return subprocess.run([*cmd, "--token-file", str(tokens[token])], capture_output=True, text=True, timeout=60)

    try:
        yield run
    finally:
        http.stop()
