"""MCAP export read back with mcap's own reader and compared with the database."""

import io
import json

import pytest
from jsonschema import Draft202012Validator
from mcap.reader import make_reader
from wire_samples import ack, coefficients, window

from fleet_wire import messages as wire
from service.mcap_export import export_mcap, iter_mcap
from service.store import Store


@pytest.fixture
def store(tmp_path):
    with Store.open(tmp_path / "fleet.db") as s:
        for seq in range(1, 7):
            s.insert_window(window(seq=seq, version=0 if seq < 4 else 1, temp_c=20.0 + 3 * seq))
        s.insert_window(window("drive-002", 1))
        s.insert_coefficient_set(coefficients(version=1, created_at=150.0))
        s.insert_coefficient_set(coefficients(version=2, created_at=330.0, bands=(2, 3)))
        s.insert_ack(ack(version=1, at=170.0))
        s.insert_ack(ack(version=2, at=340.0, status="rejected"))
        yield s


def read(data: bytes):
    reader = make_reader(io.BytesIO(data))
    return reader, list(reader.iter_messages())


def test_export_matches_the_database(store, tmp_path):
    path = tmp_path / "drive-001.mcap"
    with open(path, "wb") as out:
        export_mcap(store, "drive-001", out)
    reader, messages = read(path.read_bytes())

    summary = reader.get_summary()
    topics = {c.topic: c for c in summary.channels.values()}
    assert set(topics) == {"/encoders/drive-001/stats", "/encoders/drive-001/coefficients", "/encoders/drive-001/ack"}
    for channel in topics.values():
        schema = summary.schemas[channel.schema_id]
        assert channel.message_encoding == "json" and schema.encoding == "jsonschema"
        kind = {"stats": "window"}.get(channel.topic.rsplit("/", 1)[1], channel.topic.rsplit("/", 1)[1])
        assert json.loads(schema.data) == wire.load_schema(kind) and schema.name == wire.SCHEMA_NAME[kind]

    by_topic = {}
    for schema, channel, message in messages:
        body = json.loads(message.data)
        Draft202012Validator(json.loads(schema.data)).validate(body)  # each message matches its channel's schema
        assert message.publish_time == message.log_time
        by_topic.setdefault(channel.topic.rsplit("/", 1)[1], []).append((message.log_time, body))

    assert [b for _, b in by_topic["stats"]] == list(store.iter_windows("drive-001"))
    assert [t for t, _ in by_topic["stats"]] == [int(round(w["window_end"] * 1e9)) for w in store.windows("drive-001")]
    assert [b for _, b in by_topic["coefficients"]] == [
        h["message"] for h in reversed(store.coefficient_history("drive-001"))
    ]
    assert [b for _, b in by_topic["ack"]] == store.acks("drive-001")
    assert [t for t, _ in by_topic["ack"]] == [170_000_000_000, 340_000_000_000]

    times = [m.log_time for _, _, m in messages]
    assert times == sorted(times) and len(messages) == 6 + 2 + 2
    assert summary.statistics.message_count == 10


def test_time_range_selects_each_kind_by_its_time(store):
    data = b"".join(iter_mcap(store, "drive-001", 120.0, 300.0))
    _, messages = read(data)
    got = [(c.topic.rsplit("/", 1)[1], json.loads(m.data)) for _, c, m in messages]
    assert [b["seq"] for t, b in got if t == "stats"] == [3, 4, 5, 6]  # window_start 120..300
    assert [b["version"] for t, b in got if t == "coefficients"] == [1]
    assert [b["version"] for t, b in got if t == "ack"] == [1]
    order = [(t, b.get("seq", b.get("version"))) for t, b in got]
    assert order == [("coefficients", 1), ("ack", 1), ("stats", 3), ("stats", 4), ("stats", 5), ("stats", 6)]


def test_large_export_streams_in_several_chunks(tmp_path):
    with Store.open(tmp_path / "big.db") as s:
        msg = window()
        for seq in range(1, 401):
            s.insert_window({**msg, "seq": seq, "window_start": 60.0 * seq, "window_end": 60.0 * seq + 60.0})
        chunks = list(iter_mcap(s, "drive-001"))
        assert len(chunks) > 2
        _, messages = read(b"".join(chunks))
        assert [json.loads(m.data)["seq"] for _, _, m in messages] == list(range(1, 401))


def test_unknown_device(store):
    with pytest.raises(KeyError, match="drive-404"):
        export_mcap(store, "drive-404", io.BytesIO())


def test_empty_range_is_a_valid_file(store):
    reader, messages = read(b"".join(iter_mcap(store, "drive-001", 1e6, 2e6)))
    assert messages == [] and len(reader.get_summary().channels) == 3
