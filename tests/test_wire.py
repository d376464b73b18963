"""The wire contract: schemas, builders and the decoder agree, and every bad input is named."""

import json

import numpy as np
import pytest
from jsonschema import Draft202012Validator
from wire_samples import ack, coefficients, window

from encoder_core.stats import WindowStats
from fleet_wire import messages as wire

# blake2b-64 of the id, mod 64: changing it would move every device of every fleet to another process
PINNED_PARTITIONS = [15, 7, 47, 13]

BUILT = {"window": window, "coefficients": coefficients, "ack": ack}


@pytest.mark.parametrize("kind", wire.KINDS)
def test_schema_is_valid_2020_12_with_titles(kind):
    schema = wire.load_schema(kind)
    Draft202012Validator.check_schema(schema)
    assert schema["$schema"] == "https://json-schema.org/draft/2020-12/schema"
    assert schema["title"] == wire.SCHEMA_NAME[kind] and schema["description"]
    assert schema["additionalProperties"] is False
    assert all(p.get("description") for p in schema["properties"].values())


def properties(schema, path="$"):
    """Every property schema, nested objects and array items included."""
    for name, prop in schema.get("properties", {}).items():
        yield f"{path}.{name}", prop
        items = prop.get("items", {})
        yield from properties(prop, f"{path}.{name}")
        yield from properties(items, f"{path}.{name}[]")


@pytest.mark.parametrize("kind", wire.KINDS)
def test_every_property_states_its_type(kind):
    """Foxglove builds its message definitions from each property's "type": no $ref, oneOf or bare const."""
    text = json.dumps(wire.load_schema(kind))
    assert "$ref" not in text and "oneOf" not in text
    for path, prop in properties(wire.load_schema(kind)):
        assert "type" in prop, path


@pytest.mark.parametrize("kind", wire.KINDS)
def test_builder_output_validates_and_has_exactly_the_required_keys(kind):
    msg = BUILT[kind]()
    Draft202012Validator(wire.load_schema(kind)).validate(msg)
    assert set(msg) == set(wire.load_schema(kind)["required"])
    assert msg["schema"] == wire.SCHEMA_NAME[kind]


def test_rejected_ack_carries_reason_and_applied_ack_must_not():
    msg = ack(status="rejected")
    assert set(msg) == set(wire.load_schema("ack")["required"]) | {"reason"}
    assert msg["angle_quality_deg"] is None
    with pytest.raises(wire.WireError, match=r"\$") as exc:
        wire.check("ack", {**ack(), "reason": "why"})
    assert exc.value.reason == "schema"
    without_reason = dict(msg)
    del without_reason["reason"]
    with pytest.raises(wire.WireError, match="reason"):
        wire.check("ack", without_reason)


def test_window_derived_fields_come_from_the_statistics():
    msg = window(temp_c=-12.0)
    stats = msg["stats"]
    assert msg["samples"] == stats["moments"][0] == 400
    assert msg["temp_mean_c"] == pytest.approx(stats["temp_sum"] / stats["temp_n"])
    assert msg["band"] == -2  # floor(-12.x / 10)
    assert msg["temp_min_c"] == stats["temp_min"] and msg["temp_max_c"] == stats["temp_max"]


def test_constant_temperature_window_is_consistent():
    # seven readings of 0.1 sum to 0.7 - 1e-16: their mean falls just below the minimum
    stats = WindowStats(scale=1400.0).add(np.full(7, 700.0), np.zeros(7), np.full(7, 0.1))
    assert stats.temp_mean < stats.temp_min
    msg = wire.window_message(
        "d",
        1,
        stats,
        window_start=0.0,
        window_end=1.0,
        temp_rate_c_per_s=0.0,
        coefficients_version=0,
        angle_quality_deg=0.0,
    )
    assert wire.decode("window", wire.encode("window", msg), key_device="d")["band"] == 0


def test_window_needs_temperature():
    stats = WindowStats(scale=1400.0).add(np.full(10, 700.0), np.zeros(10))
    with pytest.raises(wire.WireError, match="no temperature"):
        wire.window_message(
            "d",
            1,
            stats,
            window_start=0.0,
            window_end=1.0,
            temp_rate_c_per_s=0.0,
            coefficients_version=0,
            angle_quality_deg=0.0,
        )


@pytest.mark.parametrize("kind", wire.KINDS)
def test_encode_decode_round_trip(kind):
    msg = BUILT[kind]()
    assert wire.decode(kind, wire.encode(kind, msg), key_device="drive-001") == msg


def payload(msg) -> bytes:
    return json.dumps(msg).encode()


def mutate(path, value):
    msg = window()
    target = msg
    for key in path[:-1]:
        target = target[key]
    if value is KeyError:
        del target[path[-1]]
    else:
        target[path[-1]] = value
    return payload(msg)


@pytest.mark.parametrize(
    "data, reason, where",
    [
        (b"{" + b" " * (wire.MAX_PAYLOAD + 1) + b"}", "too_large", "exceeds"),
        (b"seq=1", "not_json", "not JSON"),
        (b"\xff\xfe{}", "not_json", "UTF-8"),
        (
            payload(window()).replace(b'"angle_quality_deg": 0.08', b'"angle_quality_deg": NaN'),
            "non_finite",
            "$.angle_quality_deg",
        ),
        (payload(window()).replace(b'"scale": 1400.0', b'"scale": -Infinity'), "non_finite", "$.stats.scale"),
        (payload(window()).replace(b'"window_end": 60.0', b'"window_end": 1e999'), "non_finite", "$.window_end"),
        # an integer no float holds overflows as 1e999 does (it reached numpy as an object and raised a TypeError)
        (
            payload(window()).replace(b'"window_end": 60.0', b'"window_end": 1' + 400 * b"0"),
            "non_finite",
            "$.window_end",
        ),
        (mutate(["seq"], KeyError), "schema", "'seq'"),
        (mutate(["samples"], "400"), "schema", "$.samples"),
        (mutate(["seq"], -1), "schema", "$.seq"),
        (mutate(["seq"], 0), "schema", "$.seq"),
        (mutate(["seq"], True), "schema", "$.seq"),
        (mutate(["device"], "drive/001"), "schema", "$.device"),
        (mutate(["extra"], 1), "schema", "extra"),
        (mutate(["stats", "moments"], [1.0] * 14), "schema", "$.stats.moments"),
        (mutate(["stats", "bins"], [[0.0] * 6] * 63), "schema", "$.stats.bins"),
        (mutate(["stats", "bins"], [[0.0] * 6] * 63 + [[0.0] * 7]), "schema", "$.stats.bins[63]"),
        (mutate(["stats", "bins"], [[0.0] * 6] * 63 + [[0.0] * 5 + ["x"]]), "schema", "$.stats.bins[63][5]"),
        (mutate(["stats", "moments"], [1.0] * 14 + [True]), "schema", "$.stats.moments[14]"),
        (mutate(["stats", "moments"], {"0": 1.0}), "schema", "$.stats.moments"),
        (mutate(["angle_quality_deg"], -0.1), "schema", "$.angle_quality_deg"),
        (mutate(["samples"], 399), "inconsistent", "$.samples"),
        (mutate(["rejected"], 2), "inconsistent", "$.rejected"),
        (mutate(["temp_mean_c"], 40.0), "inconsistent", "$.temp_mean_c"),
        (mutate(["window_end"], -1.0), "schema", "$.window_end"),
        (mutate(["band"], 7), "inconsistent", "$.band"),
        (payload([1, 2]), "schema", "$"),
        (payload(window()).replace(b'"seq": 1,', b'"seq": 1, "seq": 2,'), "not_json", "'seq' appears twice"),
        (mutate(["window_start"], 2e10), "schema", "$.window_start"),
        # valid JSON that Python's int() will not read (it raised a bare ValueError, which took its batch down)
        (payload(window()).replace(b'"seq": 1,', b'"seq": ' + b"9" * 5000 + b","), "not_json", "5000 digits"),
        # msgspec raises UnicodeDecodeError, no DecodeError, for a MessagePack string that is not UTF-8
        (wire.encode("window", window()).replace(b"\xa9drive-001", b"\xa9\xffrive-001"), "not_json", "MessagePack"),
    ],
)
def test_bad_window_input_is_named(data, reason, where):
    with pytest.raises(wire.WireError) as exc:
        wire.decode("window", data, key_device="drive-001")
    assert exc.value.reason == reason
    assert where in str(exc.value)
    assert isinstance(exc.value, ValueError)


def test_finite_numbers_whose_sum_overflows_are_accepted_and_a_lone_nan_is_still_named():
    # the non-finite check sums a window's numbers first: a sum that overflows must not refuse finite numbers
    msg = window()
    msg["stats"]["temp_sum"] = msg["stats"]["temp_sq_sum"] = 1.5e308
    msg["stats"]["moments"][3] = msg["stats"]["moments"][4] = 1.5e308
    packed = wire.encode_window(wire.window_from_dict(msg))  # MessagePack, as agents send it
    assert wire.decode_window(packed, key_device="drive-001").stats.temp_sum == 1.5e308
    msg["stats"]["bins"][5][2] = float("nan")
    with pytest.raises(wire.WireError, match=r"\$\.stats\.bins\[5\]\[2\]") as exc:
        wire.decode_window(wire.encode_window(wire.window_from_dict(msg)), key_device="drive-001")
    assert exc.value.reason == "non_finite"


def test_fast_path_cuts_exactly_the_plain_numeric_arrays():
    _, arrays = wire._fast_validator("window")
    assert sorted(path for path, _ in arrays) == [("stats", "bins"), ("stats", "moments")]
    assert wire._fast_valid("window", window())
    _, arrays = wire._fast_validator("coefficients")  # inside every band: w and the harmonics [m, a_m, b_m]
    assert sorted(path for path, _ in arrays) == [("bands", "*", "harmonics"), ("bands", "*", "w")]


@pytest.mark.parametrize(
    "harmonics",
    [
        [[2, 0.01, -0.02]],
        [[2.0, 0.01, -0.02]],  # JSON Schema's integer: no fractional part
        [[2.5, 0.01, -0.02]],
        [[0, 0.01, -0.02]],
        [[65, 0.01, -0.02]],
        [[True, 0.01, -0.02]],
        [[2, 0.01]],
        [[2, 0.01, -0.02, 0.0]],
        [[2, "0.01", -0.02]],
        [[2, 0.01, None]],
        [[m, 0.0, 0.0] for m in range(1, 66)],
        [],
        "none",
    ],
)
def test_fast_path_agrees_with_the_schema_on_harmonics(harmonics):
    msg = json.loads(json.dumps(coefficients(bands=(1, 2))))
    msg["bands"][1]["harmonics"] = harmonics
    assert wire._fast_valid("coefficients", msg) == wire._validator("coefficients").is_valid(msg)


def test_device_in_body_must_match_key():
    with pytest.raises(wire.WireError, match=r"\$\.device.*drive-002") as exc:
        wire.decode("ack", wire.encode("ack", ack()), key_device="drive-002")
    assert exc.value.reason == "device_mismatch"


def test_coefficient_bands_are_checked():
    msg = coefficients(bands=(1, 2))
    bad = json.loads(json.dumps(msg))
    bad["bands"][0]["w"] = [1.0, 0.0, 1.0]
    with pytest.raises(wire.WireError, match=r"\$\.bands\[0\]\.w"):
        wire.decode("coefficients", payload(bad), key_device=None)
    bad = json.loads(json.dumps(msg))
    bad["bands"][1]["band"] = bad["bands"][0]["band"]
    with pytest.raises(wire.WireError, match="twice") as exc:
        wire.decode("coefficients", payload(bad), key_device=None)
    assert exc.value.reason == "inconsistent"


def test_encode_refuses_what_decode_would_refuse():
    msg = coefficients()
    msg["bands"][0]["w5"] = float("nan")
    with pytest.raises(wire.WireError, match=r"\$\.bands\[0\]\.w5") as exc:
        wire.encode("coefficients", msg)
    assert exc.value.reason == "non_finite"


def test_keys():
    from fleet_wire import keys

    part = keys.partition_chunk(keys.partition("drive-001"))
    assert wire.key_for("window", "drive-001") == f"encoders/drive-001/stats/{part}"
    assert wire.key_for("coefficients", "drive-001") == "encoders/drive-001/coefficients"  # from the service
    assert wire.parse_key(f"encoders/drive-001/stats/{part}") == ("drive-001", "window")
    assert wire.device_from_key(keys.key("d.7_x", keys.ACK)) == "d.7_x"
    wrong = keys.partition_chunk((keys.partition("drive-001") + 1) % keys.PARTITIONS)
    for key in (
        "encoders/drive-001",
        "encoders/a/b/stats",
        "other/drive-001/ack",
        "encoders/drive-001/alive",
        "encoders/*/stats",
        "encoders/drive-001/stats",  # no partition
        f"encoders/drive-001/stats/{wrong}",  # another device's partition
        f"encoders/drive-001/coefficients/{part}",  # the service's keys carry none
    ):
        with pytest.raises(wire.WireError) as exc:
            wire.parse_key(key)
        assert exc.value.reason == "bad_key"


def test_partitions_are_stable_and_spread():
    """The partition is part of the wire contract: agents and services on other machines, other Python builds
    and other releases must agree on it, so it is pinned here, and a fleet spreads evenly over the partitions."""
    from fleet_wire import keys

    assert [keys.partition(d) for d in ("drive-001", "drive-002", "a", "Z" * 64)] == PINNED_PARTITIONS
    counts = np.bincount([keys.partition(f"drive-{i:05d}") for i in range(6400)], minlength=keys.PARTITIONS)
    assert counts.min() > 60 and counts.max() < 145  # 100 expected each


def test_unknown_kind():
    with pytest.raises(wire.WireError) as exc:
        wire.decode("telemetry", b"{}", key_device=None)
    assert exc.value.reason == "unknown_kind"


def test_device_id_rule_is_one_rule_in_code_and_schema_files():
    from fleet_wire import keys

    for kind in wire.KINDS:
        assert wire.load_schema(kind)["properties"]["device"]["pattern"] == keys.DEVICE_RE.pattern
    for bad in (".", "..", "-", "-x", "*", "a/b", "a" * 65, "", "drive-001\n"):
        assert keys.split(f"encoders/{bad}/stats/p00") is None, bad
    for good in ("d", "drive-001", "d.7_x", "A" * 64):
        assert keys.split(keys.key(good, keys.STATS)) == (good, "stats")


def test_errors_with_a_reason_survive_pickling():
    """A pool worker's error is pickled back to the parent; an error that cannot be rebuilt from its args
    (reason, message) leaves multiprocessing's pool waiting forever (the accuracy bench hung that way)."""
    import pickle

    from service.rollout import RolloutError
    from service.store import StoreError

    for err in (wire.WireError("schema", "window: $.seq"), StoreError("seq_conflict", "#4"), RolloutError(409, "x")):
        back = pickle.loads(pickle.dumps(err))
        assert type(back) is type(err) and str(back) == str(err)
        assert getattr(back, "reason", None) == getattr(err, "reason", None)
        assert getattr(back, "status", None) == getattr(err, "status", None)


def test_a_received_question_names_where_the_agent_s_lost_windows_end_and_refuses_a_bad_one():
    """The agent's question on `received`: no payload (what every agent asks while its outbox dropped nothing and
    security is off), the seq below which what the service lacks is gone, the nonce the signed reply must carry, or
    both. Anything else is refused by name."""
    nonce = wire.new_nonce()
    assert wire.parse_received_query(wire.received_query("d-1", 7), "d-1") == (7, None)
    assert wire.parse_received_query(wire.received_query("d-1", nonce=nonce), "d-1") == (None, nonce)
    assert wire.parse_received_query(wire.received_query("d-1", 7, nonce), "d-1") == (7, nonce)
    assert wire.received_query("d-1") is None  # nothing to say: no payload
    assert wire.parse_received_query(None, "d-1") == (None, None) == wire.parse_received_query(b"", "d-1")
    for bad in (b"7", b"{", b"[]", b'{"device": "d-2", "gone_below": 7}', b'{"device": "d-1", "gone_below": -1}',
                b'{"device": "d-1", "gone_below": true}', b'{"device": "d-1", "gone_below": 7.5}',
                b'{"device": "d-1", "gone_below": 1e999}', b'{"device": "d-1"}',
                b'{"device": "d-1", "gone_below": 7, "also": 1}', b'{"device": "d-1", "gone_below": null}',
                b'{"device": "d-1", "gone_below": 99999999999999999999}', b"\xff\xfe",
                b'{"device": "d-1", "nonce": 7}', b'{"device": "d-1", "nonce": "' + b"A" * 32 + b'"}',
                b'{"device": "d-1", "nonce": "' + b"a" * 4096 + b'"}'):  # fmt: skip
        with pytest.raises(wire.WireError, match="not a received question for d-1"):
            wire.parse_received_query(bad, "d-1")


def test_a_watermark_reply_carries_the_resume_point_and_refuses_a_bad_one():
    """Where an agent that lost its outbox goes on (the service's last seq and its window's end): read back, absent
    from a service that has no window of the device, and a reply with a bad one refused by name."""
    reply = wire.watermark_reply("d-1", 5, 2, (7, 420.5))
    assert wire.parse_watermark_reply(reply, "d-1") == (5, 2)
    assert wire.parse_resume_point(reply, "d-1") == (7, 420.5)
    assert wire.parse_resume_point(wire.watermark_reply("d-1", 0), "d-1") is None
    for bad in ({"max_seq": -1, "last_window_end": 1.0}, {"max_seq": 3}, {"max_seq": 3, "last_window_end": "x"},
                {"max_seq": True, "last_window_end": 1.0}):  # fmt: skip
        body = json.dumps({"device": "d-1", "contiguous_seq": 1, **bad}).encode()
        with pytest.raises(wire.WireError, match="bad resume point"):
            wire.parse_resume_point(body, "d-1")
    body = json.dumps({"device": "d-1", "contiguous_seq": 1, "max_seq": 3, "last_window_end": float("nan")})
    with pytest.raises(wire.WireError, match="bad resume point"):
        wire.parse_resume_point(body.encode(), "d-1")


def test_every_field_the_watermark_reply_can_carry_is_in_its_contract(pki):
    """The watermark reply has no JSON Schema: docs/wire.md's section on `received` and fleet_wire/messages.py are
    its contract, and every field the service may send is named there (`retired` was sent and not written)."""
    from pathlib import Path

    from fleet_wire.security import SetSigner

    reply = wire.watermark_reply(
        "d-1", 5, 2, (7, 420.5), nonce=wire.new_nonce(), signer=SetSigner.load(pki), retired=True
    )
    text = (Path(__file__).parent.parent / "docs" / "wire.md").read_text()
    section = text.split("### encoders/<device>/received")[1].split("\n### ")[0]
    missing = [k for k in json.loads(reply) if f"`{k}`" not in section and f'"{k}"' not in section]
    assert not missing, f"docs/wire.md does not name {missing} of the watermark reply"
    assert wire.says_retired(reply) and not wire.says_retired(wire.watermark_reply("d-1", 5))


def test_a_device_id_ending_in_a_newline_is_no_device_id():
    """The rule's "$" matched before a trailing newline (re.match), so "drive-001\n" passed the key parser, the
    command line's device ids, the store's and the certificate names; every check is a full match now."""
    import argparse

    from encoder_fleet.argtypes import device_name
    from fleet_wire import keys

    with pytest.raises(wire.WireError):
        wire.parse_key(f"encoders/drive-001\n/stats/{keys.partition_chunk(keys.partition('drive-001'))}")
    with pytest.raises(argparse.ArgumentTypeError):
        device_name("drive-001\n")
