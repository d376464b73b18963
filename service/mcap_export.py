"""MCAP export of one device's history, for audits in Foxglove.

Three channels, /encoders/<device>/stats, /coefficients and /ack, JSON messages exactly as on the
wire, each channel's schema the schemas/ file (encoding "jsonschema"), so Foxglove can plot any
field. Times are the drive's clock in ns: a window at its window_end, a set at created_at, an ack
at `at`. The file is produced as a stream of byte chunks, so the REST endpoint never holds it.
"""

from __future__ import annotations

import heapq
import json
from collections.abc import Iterator
from typing import BinaryIO

from mcap.writer import Writer

from fleet_wire import messages as wire

from .store import Store

ORDER = ("coefficients", "window", "ack")  # at equal times: a set, then windows, then the ack to it


class _Sink:
    """The write-only stream mcap's Writer needs (write and tell), handing its bytes out as they come."""

    def __init__(self):
        self._parts: list[bytes] = []
        self._pos = 0

    def write(self, data) -> int:
        self._parts.append(bytes(data))
        self._pos += len(data)
        return len(data)

    def tell(self) -> int:
        return self._pos

    def flush(self) -> None:
        pass

    def take(self) -> bytes:
        data = b"".join(self._parts)
        self._parts.clear()
        return data


def _ns(seconds: float) -> int:
    return int(round(seconds * 1e9))


def _in_range(t: float, t_from: float | None, t_to: float | None) -> bool:
    return (t_from is None or t >= t_from) and (t_to is None or t <= t_to)


def _timeline(store: Store, device: str, t_from, t_to) -> Iterator[tuple[int, int, str, dict]]:
    """(log_time ns, tie order, kind, message), in time order. Windows are selected by window_start
    (as the REST listing), sets by created_at, acks by `at`."""
    windows = (
        (_ns(m["window_end"]), ORDER.index("window"), "window", m) for m in store.iter_windows(device, t_from, t_to)
    )
    sets = [
        (_ns(h["created_at"]), ORDER.index("coefficients"), "coefficients", h["message"])
        for h in store.coefficient_history(device)
        if _in_range(h["created_at"], t_from, t_to)
    ]
    sets.sort(key=lambda item: item[:2])
    acks = [
        (_ns(a["at"]), ORDER.index("ack"), "ack", a) for a in store.acks(device) if _in_range(a["at"], t_from, t_to)
    ]
    # store.acks is already in time order (at, then arrival)
    return heapq.merge(windows, sets, acks, key=lambda item: item[:2])


def iter_mcap(store: Store, device: str, t_from: float | None = None, t_to: float | None = None) -> Iterator[bytes]:
    """The MCAP file as byte chunks (one per finished MCAP chunk, about 1 MiB before compression)."""
    if store.device(device) is None:
        raise KeyError(f"unknown device {device!r}")
    sink = _Sink()
    writer = Writer(sink)
    writer.start(profile="", library="encoder-fleet")
    channels = {}
    for kind in wire.KINDS:
        schema_id = writer.register_schema(
            name=wire.SCHEMA_NAME[kind],
            encoding="jsonschema",
            data=wire.schema_bytes(kind),
        )
        channels[kind] = writer.register_channel(
            topic=f"/{wire.key_for(kind, device)}",
            message_encoding="json",
            schema_id=schema_id,
            metadata={"device": device},
        )
    writer.add_metadata(
        "encoder-fleet export",
        {"device": device, "from": "" if t_from is None else repr(t_from), "to": "" if t_to is None else repr(t_to)},
    )
    for log_time, _, kind, msg in _timeline(store, device, t_from, t_to):
        # stored messages were checked on the way in; re-validating each one would dominate the export
        data = json.dumps(msg, separators=(",", ":"), allow_nan=False).encode("utf-8")
        sequence = msg.get("seq", msg.get("version", 0)) % 2**32
        writer.add_message(channels[kind], log_time=log_time, data=data, publish_time=log_time, sequence=sequence)
        chunk = sink.take()
        if chunk:
            yield chunk
    writer.finish()
    yield sink.take()


def export_mcap(
    store: Store, device: str, out: BinaryIO, t_from: float | None = None, t_to: float | None = None
) -> None:
    """Write the device's windows, coefficient sets and acks in [t_from, t_to] to `out` as MCAP."""
    for chunk in iter_mcap(store, device, t_from, t_to):
        out.write(chunk)
