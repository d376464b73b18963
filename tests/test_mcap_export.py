"""MCAP export read back with mcap's own reader, compared with the database, and every schema checked
against the rules of Foxglove's JSON-Schema parser (so each channel loads in Foxglove)."""

import io
import json

import pytest
from jsonschema import Draft202012Validator
from mcap.reader import make_reader
from wire_samples import ack, coefficients, window

from service.mcap_export import SCHEMAS, TOPICS, export_mcap, iter_mcap, window_record
from service.store import Store

T0 = 1.7e9  # service clock, unix s: log times are real dates, not 1970


@pytest.fixture
def store(tmp_path):
    with Store.open(tmp_path / "fleet.db") as s:
        for seq in range(1, 7):
            msg = window(seq=seq, version=0 if seq < 4 else 1, temp_c=20.0 + 3 * seq)
            s.insert_window(msg, received_at=T0 + 60 * seq)
        s.insert_window(window("drive-002", 1))
        s.insert_coefficient_set(coefficients(version=1, created_at=150.0))
        s.mark_published("drive-001", 1, at=T0 + 150)
        s.insert_coefficient_set(coefficients(version=2, created_at=330.0, bands=(2, 3)))
        s.mark_published("drive-001", 2, at=T0 + 330)
        s.insert_ack(ack(version=1, at=170.0), received_at=T0 + 171)
        s.insert_ack(ack(version=2, at=340.0, status="rejected"), received_at=T0 + 341)
        yield s


def read(data: bytes):
    reader = make_reader(io.BytesIO(data))
    return reader, list(reader.iter_messages())


def foxglove_problems(schema: dict, path: str = "$") -> list[str]:
    """What Foxglove's JSON-Schema parser (mcap-support parseJsonSchema) would refuse: objects need
    "type": "object" with properties; a field is boolean, string (plain or base64), number, integer, a
    nested object, an array of one of those (no arrays of arrays), or a oneOf of numeric consts. No
    null, no list of types."""
    if schema.get("type") != "object" or not isinstance(schema.get("properties"), dict):
        return [f"{path}: not an object with properties"]
    problems = []
    for name, field in schema["properties"].items():
        where = f"{path}.{name}"
        if "oneOf" in field:
            if not all(isinstance(alt.get("const"), int) for alt in field["oneOf"]):
                problems.append(f"{where}: oneOf alternatives must be numeric consts")
            continue
        kind = field.get("type")
        if kind in ("boolean", "number", "integer"):
            continue
        if kind == "string":
            if field.get("contentEncoding") not in (None, "base64"):
                problems.append(f"{where}: contentEncoding {field['contentEncoding']}")
        elif kind == "object":
            problems += foxglove_problems(field, where)
        elif kind == "array":
            item = field.get("items", {})
            if item.get("type") == "object":
                problems += foxglove_problems(item, f"{where}[]")
            elif item.get("type") not in ("boolean", "number", "integer", "string") or "contentEncoding" in item:
                problems.append(f"{where}: array of {item.get('type')!r}")
        else:
            problems.append(f"{where}: type {kind!r}")
    return problems


def test_every_exported_schema_is_one_foxglove_can_parse():
    for name, schema in SCHEMAS.items():
        assert foxglove_problems(schema) == [], name
    assert foxglove_problems({"type": "object", "properties": {"x": {"type": ["number", "null"]}}})
    assert foxglove_problems(
        {"type": "object", "properties": {"b": {"type": "array", "items": {"type": "array", "items": {}}}}}
    )


def test_export_matches_the_database(store, tmp_path):
    path = tmp_path / "drive-001.mcap"
    with open(path, "wb") as out:
        export_mcap(store, "drive-001", out)
    reader, messages = read(path.read_bytes())

    summary = reader.get_summary()
    topics = {c.topic: c for c in summary.channels.values()}
    assert set(topics) == {f"/encoders/drive-001/{suffix}" for suffix in TOPICS}
    by_topic = {}
    for schema, channel, message in messages:
        assert channel.message_encoding == "json" and schema.encoding == "jsonschema"
        assert foxglove_problems(json.loads(schema.data)) == []
        body = json.loads(message.data)
        Draft202012Validator(json.loads(schema.data)).validate(body)  # each message matches its channel's schema
        assert None not in body.values()
        assert message.publish_time == message.log_time
        by_topic.setdefault(channel.topic.rsplit("/", 1)[1], []).append((message.log_time, body))

    windows = list(store.iter_windows("drive-001", with_received_at=True))
    assert [b for _, b in by_topic["stats"]] == [window_record(w) for w in windows]
    assert [t for t, _ in by_topic["stats"]] == [round((T0 + 60 * s) * 1e9) for s in range(1, 7)]
    assert all(len(b["stats"]["bins"]) == 64 * 6 for _, b in by_topic["stats"])
    assert [b["angle_quality_deg"] for _, b in by_topic["metrics"]] == [w["angle_quality_deg"] for w in windows]
    assert [b["version"] for _, b in by_topic["coefficients"]] == [1, 2]
    assert [t for t, _ in by_topic["coefficients"]] == [round((T0 + 150) * 1e9), round((T0 + 330) * 1e9)]
    assert [(b["version"], b["status"], b["at"]) for _, b in by_topic["ack"]] == [
        (1, "applied", 170.0),
        (2, "rejected", 340.0),
    ]
    log = [b for _, b in by_topic["log"]]
    assert [entry["level"] for entry in log] == [2, 2, 2, 3]  # published, published, applied, refused
    assert "v2 refused" in log[-1]["message"] and log[-1]["timestamp"]["sec"] == int(T0 + 341)

    times = [m.log_time for _, _, m in messages]
    assert times == sorted(times)  # the reader replays by log time
    assert summary.statistics.message_count == 2 * 6 + 2 * 2 + 2 * 2


def _topics(data: bytes) -> list[tuple[str, dict]]:
    _, messages = read(data)
    return [(c.topic.rsplit("/", 1)[1], json.loads(m.data)) for _, c, m in messages]


def test_time_range_selects_each_kind_by_its_drive_time(store):
    got = _topics(b"".join(iter_mcap(store, "drive-001", 120.0, 300.0)))
    assert [b["seq"] for t, b in got if t == "stats"] == [3, 4, 5, 6]  # window_start 120..300
    assert [b["version"] for t, b in got if t == "coefficients"] == [1]
    assert [b["version"] for t, b in got if t == "ack"] == [1]


def test_a_range_holds_the_set_in_force_when_it_begins(store):
    """An audit of 200..300 s must see what the drive ran then: v1, made at 150 s (before, the range held no set,
    and the acks in it named a version the file did not carry)."""
    got = _topics(b"".join(iter_mcap(store, "drive-001", 200.0, 300.0)))
    assert [b["version"] for t, b in got if t == "coefficients"] == [1]
    (line,) = [b["message"] for t, b in got if t == "log" and "v1 published" in b["message"]]
    assert "in force when the range begins" in line
    got = _topics(b"".join(iter_mcap(store, "drive-001", 331.0, 400.0)))
    assert [b["version"] for t, b in got if t == "coefficients"] == [2]


def test_a_range_holds_every_alarm_open_in_it_with_what_cleared_it(store):
    """Alarms by the time they were open (raised before the range's end, not cleared before its start), not by when
    they were raised alone: an alarm raised before `from` and cleared inside the range was left out."""
    events = [  # (raised, cleared): before the range, across its start, inside, after
        ("offline", 50.0, 100.0), ("offset_step", 150.0, 250.0), ("gain_step", 220.0, None), ("axis_step", 400.0, None)
    ]  # fmt: skip
    for cause, raised, cleared in events:
        store.save_monitor("drive-001", {}, 6, [{"kind": "raise", "cause": cause, "at": raised,
                                                "parameters": {}, "evidence": f"{cause} seen"}])  # fmt: skip
        if cleared is not None:
            store.save_monitor("drive-001", {}, 6, [{"kind": "clear", "cause": cause, "at": cleared,
                                                    "parameters": {}, "evidence": f"{cause} gone"}])  # fmt: skip
    got = [b for t, b in _topics(b"".join(iter_mcap(store, "drive-001", 200.0, 300.0))) if t == "alarms"]
    assert [b["cause"] for b in got] == ["offset_step", "gain_step"]
    assert got[0]["clear_evidence"] == "offset_step gone" and "clear_evidence" not in got[1]


def test_the_device_s_part_in_staged_rollouts_is_exported(store):
    """Every rollout record of the device (wave, outcome, the set before and the set published, why), on its own
    channel and as log lines; a range keeps those whose published set is in it."""
    with store._tx() as c:
        for rollout, name in ((1, "winter refit"), (2, "spring")):
            c.execute(
                "INSERT INTO rollouts (id, name, spec_json, state, wave, counted_from, created_at, updated_at) "
                "VALUES (?, ?, '{}', 'completed', 1, ?, ?, ?)",
                (rollout, name, T0, T0 + rollout, T0 + rollout),
            )
        c.execute(
            "INSERT INTO rollout_devices VALUES (1, 'drive-001', 0, 'succeeded', 0, 1, ?, ?, 'no worse after 1 h')",
            (T0 + 150, T0 + 200),
        )
        c.execute(
            "INSERT INTO rollout_devices VALUES (2, 'drive-001', 1, 'rejected', 1, 2, ?, ?, 'the agent refused it')",
            (T0 + 330, T0 + 341),
        )
    got = _topics(b"".join(iter_mcap(store, "drive-001")))
    rows = [b for t, b in got if t == "rollout"]
    assert [(b["rollout"], b["state"], b["before_version"], b["version"]) for b in rows] == [
        (1, "succeeded", 0, 1),
        (2, "rejected", 1, 2),
    ]
    assert rows[1]["reason"] == "the agent refused it" and rows[0]["name"] == "winter refit"
    lines = [b["message"] for t, b in got if t == "log" and b["message"].startswith("rollout")]
    assert len(lines) == 4 and "rollout 2 (spring): rejected: the agent refused it" in lines
    ranged = [b for t, b in _topics(b"".join(iter_mcap(store, "drive-001", 331.0, 400.0))) if t == "rollout"]
    assert [b["rollout"] for b in ranged] == [2]


def test_large_export_streams_in_several_chunks(tmp_path):
    with Store.open(tmp_path / "big.db") as s:
        msg = window()
        for seq in range(1, 401):
            s.insert_window({**msg, "seq": seq, "window_start": 60.0 * seq, "window_end": 60.0 * seq + 60.0})
        chunks = list(iter_mcap(s, "drive-001"))
        assert len(chunks) > 2
        _, messages = read(b"".join(chunks))
        stats = [json.loads(m.data)["seq"] for _, c, m in messages if c.topic.endswith("/stats")]
        assert stats == list(range(1, 401))


def test_unknown_device(store):
    with pytest.raises(KeyError, match="drive-404"):
        export_mcap(store, "drive-404", io.BytesIO())


def test_empty_range_is_a_valid_file(store):
    """A range after every record: a valid file that holds only the set the drive runs then (and its log line)."""
    reader, messages = read(b"".join(iter_mcap(store, "drive-001", 1e6, 2e6)))
    assert [c.topic.rsplit("/", 1)[1] for _, c, _ in messages] == ["coefficients", "log"]
    assert len(reader.get_summary().channels) == len(TOPICS)


def _alarms(data: bytes) -> list[dict]:
    _, messages = read(data)
    return [json.loads(m.data) for _, c, m in messages if c.topic.endswith("/alarms")]


def test_every_alarm_of_the_device_is_exported_not_the_newest_thousand(store):
    """A drive whose link flaps raises (and clears) many offline alarms; the audit must hold every one."""
    for i in range(1005):
        store.save_monitor(
            "drive-001",
            {},
            6,
            [
                {"kind": "raise", "cause": "offline", "at": 400.0 + i, "parameters": {"since": 400.0 + i},
                 "evidence": "gone"},
                {"kind": "clear", "cause": "offline", "at": 400.5 + i, "parameters": {}, "evidence": "back"},
            ],
        )  # fmt: skip
    store.ack_alarm(7, by="token 2 (ops desk)", note="the site's switch", at=T0 + 5)
    alarms = _alarms(b"".join(iter_mcap(store, "drive-001")))
    assert [a["id"] for a in alarms] == list(range(1, 1006))
    # who acknowledged what is part of the audit too (absent where nobody did, as the schema says)
    assert [(a["id"], a["acked_by"], a["ack_note"], a["acked_at"]) for a in alarms if "acked_at" in a] == [
        (7, "token 2 (ops desk)", "the site's switch", T0 + 5)
    ]


def test_every_cause_keeps_its_parameters(store):
    from encoder_core.monitor_causes import CAUSES

    events = []
    for n, (name, cause) in enumerate(CAUSES.items()):
        params = {p: 0.5 + n for p in cause.alarm_params}
        events.append({"kind": "raise", "cause": name, "at": 400.0 + n, "parameters": params, "evidence": name})
    store.save_monitor("drive-001", {}, 6, events)
    reader, messages = read(b"".join(iter_mcap(store, "drive-001")))
    for schema, channel, message in messages:
        if channel.topic.endswith("/alarms"):
            Draft202012Validator(json.loads(schema.data)).validate(json.loads(message.data))
    for alarm in _alarms(b"".join(iter_mcap(store, "drive-001"))):
        expected = CAUSES[alarm["cause"]].alarm_params
        assert {p: alarm.get(p) for p in expected} == store.alarms("drive-001", ids=[alarm["id"]])[0]["parameters"]
