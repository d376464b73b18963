"""Structured logs: one JSON object per line on stderr, so a log shipper needs no parser of its own."""

from __future__ import annotations

import json
import logging
import sys
from contextlib import contextmanager
from pathlib import Path

LEVELS = ("debug", "info", "warning", "error")
# attributes every LogRecord has; anything else was passed as `extra=` and becomes a field of the event
_STANDARD = set(vars(logging.LogRecord("", 0, "", 0, "", None, None))) | {"message", "asctime", "taskName"}


class JsonLines(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        event = {
            "ts": round(record.created, 3),
            "level": record.levelname.lower(),
            "logger": record.name,
            "event": record.getMessage(),
        }
        event.update({k: v for k, v in vars(record).items() if k not in _STANDARD})
        if record.exc_info:
            event["exception"] = self.formatException(record.exc_info)
        return json.dumps(event, default=str)


class _Stderr(logging.StreamHandler):
    """Writes to whatever sys.stderr is when the event comes, not when logging was configured (a command run
    in-process, as the tests do, must not keep writing into a stream that was replaced and closed)."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, _value) -> None:
        pass


def configure(level: str = "warning") -> None:
    handler = _Stderr()
    handler.setFormatter(JsonLines())
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level.upper())


@contextmanager
def to_file(path: Path):
    """Log events go to `path` (JSON lines, appended) instead of stderr while the block runs: a command whose
    stderr shows progress and a summary keeps the events in a file beside its other outputs."""
    handler = logging.FileHandler(path, encoding="utf-8")
    handler.setFormatter(JsonLines())
    root = logging.getLogger()
    kept = root.handlers[:]
    root.handlers[:] = [handler]
    try:
        yield
    finally:
        root.handlers[:] = kept
        handler.close()


def add_level_option(parser) -> None:
    parser.add_argument("--log-level", choices=LEVELS, default="warning", help="log events at this level and above")
