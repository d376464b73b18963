"""MCAP export of one device's history, for audits in Foxglove.

Channels (JSON messages, each with a JSON Schema that Foxglove's schema parser accepts: one plain type
per field, no nulls (a missing value is a missing field), no arrays of arrays):

| topic                          | schema                        | one message per                          |
|--------------------------------|-------------------------------|------------------------------------------|
| /encoders/<device>/stats       | encoder_fleet.Window          | window: the wire fields, `bins` flattened |
| /encoders/<device>/metrics     | encoder_fleet.DriveMetrics    | window: flat numbers for the Plot panel  |
| /encoders/<device>/coefficients| encoder_fleet.CoefficientSet  | coefficient set, harmonics flattened     |
| /encoders/<device>/ack         | encoder_fleet.Ack             | ack                                      |
| /encoders/<device>/log         | foxglove.Log                  | rollout decision, alarm raised, retired  |
| /encoders/<device>/alarms      | encoder_fleet.Alarm           | drift alarm, parameters flattened        |
| /encoders/<device>/rollout     | encoder_fleet.RolloutDevice   | the device's part in a staged rollout    |

log_time is Unix time in ns: when the service received the window or ack, or published the set. The
drive's clock stays a field (window_end, created_at, at). The time range (from, to) selects by the drive's
clock, as the REST API does, both ends included: windows by their start, acks by `at`, sets by `created_at`, and
also the set published last before `from` (the one the drive ran when the range begins); alarms open at any time
in the range (raised before `to`, not cleared before `from`); a staged rollout's record when the set it published
is in the range (every record when no range is given: they carry the service's clock only); every retirement and
reinstatement of the device, whatever the range (the service's clock only, and few: whether it was in the fleet is
part of any audit of it). The file is produced
as a stream of byte chunks, so the REST endpoint never holds it; messages are written kind by kind, and MCAP's index
lets readers replay them by log_time.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from typing import BinaryIO

from mcap.writer import Writer

from encoder_core.monitor_causes import CAUSES
from encoder_core.stats import BIN_COLUMNS, N_BINS
from fleet_wire import keys

from .rollout import OUTCOMES
from .store import Store

NUMBER, INTEGER, STRING = {"type": "number"}, {"type": "integer"}, {"type": "string"}


def _object(title: str, properties: dict, description: str = "") -> dict:
    return {"title": title, "description": description, "type": "object", "properties": properties}


def _numbers(description: str) -> dict:
    return {"type": "array", "items": NUMBER, "description": description}


WINDOW_NUMBERS = ("window_start", "window_end", "temp_mean_c", "temp_min_c", "temp_max_c", "temp_rate_c_per_s")
WINDOW_NUMBERS += ("angle_quality_deg", "band")  # band is signed: Foxglove reads "integer" as uint32
WINDOW_INTEGERS = ("seq", "samples", "rejected", "coefficients_version")
STATS_NUMBERS = ("scale", "center_d", "center_q", "temp_sum", "temp_sq_sum", "temp_min", "temp_max")

SCHEMAS = {
    "encoder_fleet.Window": _object(
        "encoder_fleet.Window",
        {
            **{f: NUMBER for f in WINDOW_NUMBERS},
            **{f: INTEGER for f in WINDOW_INTEGERS},
            "received_at": {**NUMBER, "description": "Service clock, unix s."},
            "stats": _object(
                "encoder_fleet.WindowStats",
                {
                    **{f: NUMBER for f in STATS_NUMBERS},
                    "temp_n": INTEGER,
                    "rejected": INTEGER,
                    "moments": _numbers("Sums of x^i·y^j, i + j <= 4 (encoder_core/stats.py MONOMIALS order)."),
                    "bins": _numbers(
                        f"{N_BINS} angle bins × ({', '.join(BIN_COLUMNS)}), row-major: bin k's {BIN_COLUMNS[0]} "
                        f"is bins[{len(BIN_COLUMNS)}·k]."
                    ),
                },
                "The window's additive statistics (temp_min/temp_max absent when it held no temperature).",
            ),
        },
        "One window of additive statistics (docs/wire.md), as received.",
    ),
    "encoder_fleet.DriveMetrics": _object(
        "encoder_fleet.DriveMetrics",
        {
            "drive_time_s": {**NUMBER, "description": "window_end on the drive's clock."},
            "angle_quality_deg": NUMBER,
            "temp_mean_c": NUMBER,
            "rejected_share": {**NUMBER, "description": "rejected / (samples + rejected) in the window."},
            "coefficients_version": NUMBER,
        },
        "Flat numbers per window, for Foxglove's Plot panel.",
    ),
    "encoder_fleet.CoefficientSet": _object(
        "encoder_fleet.CoefficientSet",
        {
            "version": INTEGER,
            "created_at": {**NUMBER, "description": "Drive clock, s."},
            "basis": STRING,
            "published_at": {**NUMBER, "description": "Service clock, unix s (absent: never published)."},
            "state": {**STRING, "description": "The guard's state now: trial, confirmed or rolled_back."},
            "restores_version": {**INTEGER, "description": "Basis rollback only: the confirmed set it restores."},
            "thermal_lag_s": {**NUMBER, "description": "The die's lag the agent reads the bands at, s (absent: 0)."},
            "bands": {
                "type": "array",
                "items": _object(
                    "encoder_fleet.Band",
                    {
                        "band": NUMBER,
                        "temp_c": NUMBER,
                        "w": _numbers("w1, w2, w3, w4 (docs/wire.md)."),
                        "w5": NUMBER,
                        "zero_offset_rad": NUMBER,
                        "harmonic_orders": _numbers("m of each angle harmonic."),
                        "harmonic_a": _numbers("a_m (rad), same order."),
                        "harmonic_b": _numbers("b_m (rad), same order."),
                        "samples": NUMBER,
                        "residual_rms_rad": NUMBER,
                        "radius_ripple_rad": NUMBER,
                        "estimated_error_deg": NUMBER,
                    },
                ),
            },
        },
        "A coefficient set (docs/wire.md) with its band entries flattened.",
    ),
    "encoder_fleet.Ack": _object(
        "encoder_fleet.Ack",
        {
            "version": INTEGER,
            "status": STRING,
            "reason": STRING,
            "angle_quality_deg": NUMBER,
            "at": {**NUMBER, "description": "Drive clock, s."},
            "received_at": {**NUMBER, "description": "Service clock, unix s."},
        },
        "An agent's answer to a coefficient set.",
    ),
    # the well-known Foxglove schema, so the Log panel lists rollout decisions
    "foxglove.Log": _object(
        "foxglove.Log",
        {
            "timestamp": _object("Time", {"sec": INTEGER, "nsec": INTEGER}, "Time of the event"),
            "level": {
                "title": "LogLevel: Log level",
                "oneOf": [
                    {"title": name, "const": value}
                    for value, name in enumerate(("UNKNOWN", "DEBUG", "INFO", "WARNING", "ERROR", "FATAL"))
                ],
            },
            "message": STRING,
            "name": STRING,
            "file": STRING,
            "line": INTEGER,
        },
        "A log message",
    ),
}
# every cause's parameters (the contract's, encoder_core/monitor_causes.py), all numbers: a list written out by
# hand here once lacked gain_step's delta_imbalance and axis_step's delta_skew, and their alarms lost them
ALARM_PARAMETERS = tuple(dict.fromkeys(p for cause in CAUSES.values() for p in cause.alarm_params))
SCHEMAS["encoder_fleet.Alarm"] = _object(
    "encoder_fleet.Alarm",
    {
        "id": INTEGER,
        "cause": STRING,
        "evidence": STRING,
        "raised_at": {**NUMBER, "description": "Drive clock, s: end of the window that made the alarm certain."},
        "cleared_at": {**NUMBER, "description": "Drive clock, s; absent while the alarm is open."},
        "clear_evidence": {**STRING, "description": "What cleared it; absent while the alarm is open."},
        "acked_at": {**NUMBER, "description": "Service clock, unix s: an operator acknowledged it; absent if none."},
        "acked_by": {**STRING, "description": "The REST token that acknowledged it."},
        "ack_note": {**STRING, "description": "What the operator said."},
        **{
            p: {**NUMBER, "description": "A parameter of the cause (present for its causes only)."}
            for p in ALARM_PARAMETERS
        },
    },
    "A drift alarm (GET /alarms), logged when the service raised it.",
)
SCHEMAS["encoder_fleet.RolloutDevice"] = _object(
    "encoder_fleet.RolloutDevice",
    {
        "rollout": INTEGER,
        "name": STRING,
        "wave": INTEGER,
        "state": {**STRING, "description": "pending, in_progress or an outcome: " + ", ".join(OUTCOMES)},
        "before_version": {**INTEGER, "description": "The confirmed set the device ran when the change reached it."},
        "version": {**INTEGER, "description": "The set the change published to the device."},
        "started_at": {**NUMBER, "description": "Service clock, unix s."},
        "decided_at": {**NUMBER, "description": "Service clock, unix s; absent until its soak is decided."},
        "reason": STRING,
    },
    "The device's part in a staged rollout (GET /rollouts/{id}), logged when it was decided (or started).",
)
INFO, WARNING = 2, 3
TOPICS = {  # topic suffix -> schema
    "stats": "encoder_fleet.Window",
    "metrics": "encoder_fleet.DriveMetrics",
    "coefficients": "encoder_fleet.CoefficientSet",
    "ack": "encoder_fleet.Ack",
    "log": "foxglove.Log",
    "alarms": "encoder_fleet.Alarm",
    "rollout": "encoder_fleet.RolloutDevice",
}


def _present(record: dict) -> dict:
    """Leave out what is unknown instead of sending null (Foxglove's parser has no null type)."""
    return {k: v for k, v in record.items() if v is not None}


def window_record(msg: dict) -> dict:
    stats = msg["stats"]
    flat_stats = {k: stats.get(k) for k in (*STATS_NUMBERS, "temp_n", "rejected", "moments")}
    flat_stats["bins"] = [value for row in stats["bins"] for value in row]
    fields = (*WINDOW_NUMBERS, *WINDOW_INTEGERS, "received_at")
    return _present({**{f: msg.get(f) for f in fields}, "stats": _present(flat_stats)})


def metrics_record(msg: dict) -> dict:
    seen = msg["samples"] + msg["rejected"]
    return {
        "drive_time_s": msg["window_end"],
        "angle_quality_deg": msg["angle_quality_deg"],
        "temp_mean_c": msg["temp_mean_c"],
        "rejected_share": msg["rejected"] / seen if seen else 0.0,
        "coefficients_version": msg["coefficients_version"],
    }


def coefficient_set_record(entry: dict) -> dict:
    msg = entry["message"]
    bands = []
    for band in msg["bands"]:
        harmonics = band.get("harmonics", [])
        bands.append(
            _present(
                {
                    **{k: band.get(k) for k in ("band", "temp_c", "w", "w5", "zero_offset_rad")},
                    "harmonic_orders": [h[0] for h in harmonics],
                    "harmonic_a": [h[1] for h in harmonics],
                    "harmonic_b": [h[2] for h in harmonics],
                    **band.get("quality", {}),
                }
            )
        )
    return _present(
        {
            "version": msg["version"],
            "created_at": msg["created_at"],
            "basis": msg["basis"],
            "published_at": entry["published_at"],
            "state": entry["state"],
            "restores_version": entry["restores_version"],
            "thermal_lag_s": msg.get("thermal_lag_s"),
            "bands": bands,
        }
    )


def alarm_record(alarm: dict) -> dict:
    params = {k: float(v) for k, v in alarm["parameters"].items() if k in ALARM_PARAMETERS}
    fields = (
        "id",
        "cause",
        "evidence",
        "raised_at",
        "cleared_at",
        "clear_evidence",
        "acked_at",
        "acked_by",
        "ack_note",
    )
    return _present({**{k: alarm.get(k) for k in fields}, **params})


def rollout_record(row: dict) -> dict:
    fields = ("rollout", "name", "wave", "state", "before_version", "version", "started_at", "decided_at", "reason")
    return _present({k: row[k] for k in fields})


def ack_record(ack: dict) -> dict:
    return _present({k: ack.get(k) for k in ("version", "status", "reason", "angle_quality_deg", "at", "received_at")})


def log_record(unix_s: float, level: int, message: str, device: str) -> dict:
    ns = _ns(unix_s)
    return {
        "timestamp": {"sec": ns // 10**9, "nsec": ns % 10**9},
        "level": level,
        "message": message,
        "name": f"encoder-fleet/{device}",
        "file": "",
        "line": 0,
    }


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


def _ns(unix_s: float) -> int:
    return max(int(round(unix_s * 1e9)), 0)


def _in_range(t: float, t_from: float | None, t_to: float | None) -> bool:
    return (t_from is None or t >= t_from) and (t_to is None or t <= t_to)


def _events(store: Store, device: str, t_from, t_to) -> Iterator[tuple[float, str, dict]]:
    """(log time unix s, topic suffix, record): sets and acks with their log lines, then windows."""
    published = [e for e in reversed(store.coefficient_history(device)) if e["published_at"] is not None]
    # the set the drive ran when the range begins: an audit of the range must see what was in force at its start
    earlier = [e for e in published if t_from is not None and e["created_at"] < t_from]
    in_force = earlier[-1]["message"]["version"] if earlier else None
    versions = set()
    for entry in published:  # oldest first
        msg = entry["message"]
        if msg["version"] != in_force and not _in_range(entry["created_at"], t_from, t_to):
            continue
        versions.add(msg["version"])
        yield entry["published_at"], "coefficients", coefficient_set_record(entry)
        bands = ", ".join(str(b["band"]) for b in msg["bands"])
        text = f"coefficient set v{msg['version']} published (basis {msg['basis']}; bands {bands})"
        if msg["version"] == in_force:
            text += f"; the set in force when the range begins (drive clock {t_from:g} s)"
        yield entry["published_at"], "log", log_record(entry["published_at"], INFO, text, device)
    for row in store.rollout_records(device):
        if (t_from is not None or t_to is not None) and row["version"] not in versions:
            continue
        at = row["decided_at"] or row["started_at"] or row["created_at"]
        yield at, "rollout", rollout_record(row)
        if row["started_at"] is not None:
            text = f"rollout {row['rollout']} ({row['name']}), wave {row['wave']}: v{row['version']} published"
            text += f" (the drive ran v{row['before_version']})" if row["before_version"] is not None else ""
            yield row["started_at"], "log", log_record(row["started_at"], INFO, text, device)
        if row["decided_at"] is not None:
            level = INFO if row["state"] in ("succeeded", "unchanged", "offline") else WARNING  # offline: untouched
            text = f"rollout {row['rollout']} ({row['name']}): {row['state'].replace('_', ' ')}: {row['reason'] or ''}"
            yield row["decided_at"], "log", log_record(row["decided_at"], level, text.rstrip(": "), device)
    for event in store.set_events(device):  # the guard: trial, confirmed, rolled_back
        if not _in_range(event["at"], t_from, t_to):
            continue
        level = WARNING if event["state"] == "rolled_back" else INFO
        text = f"coefficient set v{event['version']} {event['state'].replace('_', ' ')}: {event['reason']}"
        yield event["decided_at"], "log", log_record(event["decided_at"], level, text, device)
    for ack in store.acks(device, with_received_at=True):
        if not _in_range(ack["at"], t_from, t_to):
            continue
        yield ack["received_at"], "ack", ack_record(ack)
        if ack["status"] == "applied":
            text, level = f"coefficient set v{ack['version']} applied by the agent", INFO
        else:
            text, level = f"coefficient set v{ack['version']} refused by the agent: {ack.get('reason', '')}", WARNING
        yield ack["received_at"], "log", log_record(ack["received_at"], level, text, device)
    for alarm in reversed(store.alarms(device, audit=True, limit=None)):  # oldest first
        if (t_to is not None and alarm["raised_at"] > t_to) or (
            t_from is not None and alarm["cleared_at"] is not None and alarm["cleared_at"] < t_from
        ):
            continue  # open at no time of the range
        yield alarm["created_at"], "alarms", alarm_record(alarm)
        text = f"alarm {alarm['cause']} raised at {alarm['raised_at'] / 3600:.2f} h drive time: {alarm['evidence']}"
        yield alarm["created_at"], "log", log_record(alarm["created_at"], WARNING, text, device)
    for r in store.retirements(device):
        text = f"retired from the fleet by {r['retired_by']}: {r['note']}"
        yield r["retired_at"], "log", log_record(r["retired_at"], WARNING, text, device)
        if r["reinstated_at"] is not None:
            text = f"reinstated in the fleet by {r['reinstated_by']}: {r['reinstate_note']}"
            yield r["reinstated_at"], "log", log_record(r["reinstated_at"], INFO, text, device)
    for msg in store.iter_windows(device, t_from, t_to, with_received_at=True):
        yield msg["received_at"], "stats", window_record(msg)
        yield msg["received_at"], "metrics", metrics_record(msg)


def iter_mcap(store: Store, device: str, t_from: float | None = None, t_to: float | None = None) -> Iterator[bytes]:
    """The MCAP file as byte chunks (one per finished MCAP chunk, about 1 MiB before compression)."""
    if store.device(device) is None:
        raise KeyError(f"unknown device {device!r}")
    sink = _Sink()
    writer = Writer(sink)
    writer.start(profile="", library="encoder-fleet")
    schema_ids = {
        name: writer.register_schema(name=name, encoding="jsonschema", data=json.dumps(schema).encode())
        for name, schema in SCHEMAS.items()
    }
    channels = {
        suffix: writer.register_channel(
            topic=f"/{keys.PREFIX}/{device}/{suffix}",  # the record, not the route: no partition
            message_encoding="json",
            schema_id=schema_ids[schema],
            metadata={"device": device},
        )
        for suffix, schema in TOPICS.items()
    }
    writer.add_metadata(
        "encoder-fleet export",
        {"device": device, "from": "" if t_from is None else repr(t_from), "to": "" if t_to is None else repr(t_to)},
    )
    sequence = dict.fromkeys(TOPICS, 0)
    for unix_s, suffix, record in _events(store, device, t_from, t_to):
        data = json.dumps(record, separators=(",", ":"), allow_nan=False).encode("utf-8")
        sequence[suffix] += 1
        log_time = _ns(unix_s)
        writer.add_message(
            channels[suffix], log_time=log_time, data=data, publish_time=log_time, sequence=sequence[suffix]
        )
        chunk = sink.take()
        if chunk:
            yield chunk
    writer.finish()
    yield sink.take()


def export_mcap(
    store: Store, device: str, out: BinaryIO, t_from: float | None = None, t_to: float | None = None
) -> None:
    """Write the device's windows, coefficient sets, acks and rollout log in [t_from, t_to] to `out` as MCAP."""
    for chunk in iter_mcap(store, device, t_from, t_to):
        out.write(chunk)
