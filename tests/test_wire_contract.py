"""The window Structs (fleet_wire.messages, compiled once by msgspec) and schemas/window.schema.json say
the same: same fields, same required set, and on every mutation of a valid message both accept or both
reject. Every bad input of test_wire is also refused when it arrives as MessagePack, and counted. The
coefficient set's Struct accepts nothing schemas/coefficients.schema.json refuses."""

import copy
import json
import random

import msgspec
import pytest
from jsonschema import Draft202012Validator
from wire_samples import window

from fleet_wire import keys
from fleet_wire import messages as wire

SCHEMA = wire.load_schema("window")
VALIDATOR = Draft202012Validator(SCHEMA)
STRUCTURAL = ("schema", "not_json", "non_finite")  # what a JSON Schema can say; 'inconsistent' it cannot


def struct_fields(cls) -> dict:
    return {f.name: f for f in msgspec.inspect.type_info(cls).fields}


@pytest.mark.parametrize(
    "cls, node",
    [
        (wire.ArrayWindow, SCHEMA),
        (wire.ArrayStats, SCHEMA["properties"]["stats"]),
        (wire.RejectedByReason, SCHEMA["properties"]["rejected_by_reason"]),
    ],
)
def test_struct_fields_are_the_schema_properties(cls, node):
    fields = struct_fields(cls)
    assert list(fields) == list(node["properties"]) or set(fields) == set(node["properties"])
    assert {n for n, f in fields.items() if f.required} == set(node["required"])
    for name, prop in node["properties"].items():
        t = fields[name].type
        if isinstance(t, msgspec.inspect.IntType):
            assert prop["type"] == "integer", name
            assert (t.ge, t.le) == (prop.get("minimum"), prop.get("maximum")), name
            assert prop.get("maximum") is not None and prop["maximum"] <= 2**63 - 1, name  # fits SQLite
        elif isinstance(t, msgspec.inspect.FloatType):
            assert prop["type"] == "number", name
            assert (t.ge, t.le, t.gt) == (prop.get("minimum"), prop.get("maximum"), prop.get("exclusiveMinimum"))


def test_packed_stats_are_the_array_stats_with_bytes():
    packed, arrays = struct_fields(wire.PackedStats), struct_fields(wire.ArrayStats)
    assert list(packed) == list(arrays)
    assert packed["moments"].type.min_length == 8 * arrays["moments"].type.min_length
    assert packed["bins"].type.min_length == 8 * wire.N_BIN_VALUES


def decode_both(msg) -> tuple[str | None, str | None]:
    """(reason of the JSON path or None, reason of the MessagePack path or None)."""
    out = []
    for payload in (json.dumps(msg).encode(), msgpack_of(msg)):
        if payload is None:
            out.append(out[0])
            continue
        try:
            wire.decode("window", payload, key_device=None)
            out.append(None)
        except wire.WireError as exc:
            out.append(exc.reason)
    return tuple(out)


def msgpack_of(msg):
    """The MessagePack an agent would send for msg (arrays packed when they have the right shape)."""
    if not isinstance(msg, dict):
        return msgspec.msgpack.encode(msg)
    m = copy.deepcopy(msg)
    stats = m.get("stats")
    try:
        if isinstance(stats, dict):
            import numpy as np

            for key in ("moments", "bins"):
                flat = stats[key] if key == "moments" else [x for row in stats[key] for x in row]
                if any(isinstance(x, bool) or not isinstance(x, (int, float)) for x in flat):
                    return None  # only arrays of numbers have a packed form
                arr = np.asarray(stats[key], dtype="<f8")
                stats[key] = arr.tobytes()
    except (TypeError, ValueError, KeyError):
        return None  # not representable as packed floats: only the JSON form exists
    return msgspec.msgpack.encode(m)


MUTATIONS = [
    -1, 0, 1, 2**53, 2**63, -(2**63), 1.5, -1e300, 1e300, "x", "", None, True, [], {}, [1.0] * 15,
    -273.16, 300.01, 1e10, 1e10 + 1, -100.5, 180.5, "drive/1", "a" * 65, "encoder-fleet/window/2",
]  # fmt: skip


def leaves(msg, path=()):
    if isinstance(msg, dict):
        for k, v in msg.items():
            if k in ("moments", "bins"):
                yield path + (k,)
                continue
            yield from leaves(v, path + (k,))
    else:
        yield path


def base_value(msg, path):
    for key in path:
        msg = msg[key]
    return msg


def mutated(base: dict):
    """(path, value, message) for every leaf of base set to each of MUTATIONS, deleted, or given a sibling."""
    for path in leaves(base):
        for value in MUTATIONS + ["DELETE", "EXTRA"]:
            msg = copy.deepcopy(base)
            target = msg
            for key in path[:-1]:
                target = target[key]
            if value == "DELETE":
                del target[path[-1]]
            elif value == "EXTRA":
                target["unexpected"] = 1
            else:
                target[path[-1]] = value
            yield path, value, msg


def test_code_and_schema_file_agree_on_mutated_windows():
    rng = random.Random(7)
    base = window()
    base["rejected_by_reason"] = {"non_finite": 0, "clipped": 0, "outlier": 0}
    checked = 0
    for path, value, msg in mutated(base):
        if isinstance(value, float) and value.is_integer() and type(base_value(base, path)) is int:
            # the one deliberate narrowing: JSON Schema counts 1e10 as an integer, the Structs want an
            # integer literal (what every encoder writes for an int), so SQLite never gets a REAL seq
            continue
        schema_ok = VALIDATOR.is_valid(msg)
        reasons = decode_both(msg)
        for reason in reasons:
            code_ok = reason is None or reason not in STRUCTURAL
            assert code_ok == schema_ok, (path, value, reasons, schema_ok)
        checked += 1
    # arrays: wrong lengths, wrong types, one bad value somewhere
    for _ in range(60):
        msg = copy.deepcopy(base)
        key = rng.choice(["moments", "bins"])
        arr = msg["stats"][key]
        what = rng.choice(["short", "long", "str", "bool", "inner"])
        if what == "short":
            arr.pop()
        elif what == "long":
            arr.append(arr[0])
        elif what == "str":
            arr[rng.randrange(len(arr))] = "1"
        elif what == "bool":
            arr[rng.randrange(len(arr))] = True
        elif key == "bins":
            arr[rng.randrange(len(arr))] = [0.0] * rng.choice([5, 7])
        else:
            arr[rng.randrange(len(arr))] = [0.0]
        schema_ok = VALIDATOR.is_valid(msg)
        for reason in decode_both(msg):
            assert (reason is None or reason not in STRUCTURAL) == schema_ok, (key, what, reason)
        checked += 1
    assert checked > 500


def test_decoded_form_validates_against_the_schema_file():
    msg = window()
    msg["rejected_by_reason"] = {"non_finite": 0, "clipped": 0, "outlier": 0}
    payload = wire.encode("window", msg)
    assert payload[0] in wire._MSGPACK_MAP
    decoded = wire.decode("window", payload, key_device="drive-001")
    VALIDATOR.validate(decoded)
    assert decoded == msg


def test_json_windows_of_older_agents_are_accepted_and_stored_alike():
    msg = window()
    a = wire.decode_window(wire.encode_json("window", msg), key_device="drive-001")
    b = wire.decode_window(wire.encode("window", msg), key_device="drive-001")
    assert a == b and wire.pack_stats(a.stats) == wire.pack_stats(b.stats)


def with_extra() -> bytes:
    return msgspec.msgpack.encode(
        {**msgspec.to_builtins(wire.window_from_dict(window()), builtin_types=(bytes,)), "x": 1}
    )


NAN = b"\x00\x00\x00\x00\x00\x00\xf8\x7f"  # little-endian float64 NaN


def packed_mutation(**changes):
    msg = window()
    win = msgspec.structs.replace(wire.window_from_dict(msg), **changes)
    return msgspec.msgpack.encode(win)


def stats_mutation(**changes):
    win = wire.window_from_dict(window())
    return msgspec.msgpack.encode(msgspec.structs.replace(win, stats=msgspec.structs.replace(win.stats, **changes)))


@pytest.mark.parametrize(
    "data, reason, where",
    [
        (packed_mutation(angle_quality_deg=float("nan")), "non_finite", "$.angle_quality_deg"),
        (stats_mutation(scale=float("-inf")), "non_finite", "$.stats.scale"),
        (packed_mutation(window_end=float("inf")), "non_finite", "$.window_end"),
        (stats_mutation(moments=b"\x00" * 8 * 14 + NAN), "non_finite", "$.stats.moments[14]"),
        (stats_mutation(bins=b"\x00" * (8 * wire.N_BIN_VALUES - 8) + b"\x00\x00\x00\x00\x00\x00\xf0\x7f"), "non_finite",
         "$.stats.bins[63][5]"),
        (stats_mutation(moments=b"\x00" * 8 * 14), "schema", "$.stats.moments"),
        (stats_mutation(bins=[[0.0] * 6] * 64), "schema", "$.stats.bins"),
        (packed_mutation(seq=0), "schema", "$.seq"),
        (packed_mutation(seq=2**63), "schema", "$.seq"),
        (packed_mutation(samples=2**63), "schema", "$.samples"),
        (packed_mutation(device="drive/001"), "schema", "$.device"),
        (packed_mutation(samples=True), "schema", "$.samples"),
        (packed_mutation(samples=399), "inconsistent", "$.samples"),
        (packed_mutation(band=7), "inconsistent", "$.band"),
        (with_extra(), "schema", "'x'"),
        (b"\x8f\xc1", "not_json", "MessagePack"),
    ],
)  # fmt: skip
def test_bad_msgpack_window_is_named(data, reason, where):
    with pytest.raises(wire.WireError) as exc:
        wire.decode("window", data, key_device="drive-001")
    assert exc.value.reason == reason
    assert where in str(exc.value)


def test_every_refusal_is_counted(tmp_path):
    from test_wire import test_bad_window_input_is_named as named

    from service.store import Store

    cases = named.pytestmark[0].args[1]
    with Store.open(tmp_path / "f.db") as store:
        outcomes = [store.ingest(keys.key("drive-001", keys.STATS), data) for data, _, _ in cases]
        assert outcomes == [reason for _, reason, _ in cases]
        expected = {}
        for _, reason, _ in cases:
            expected[reason] = expected.get(reason, 0) + 1
        assert store.rejection_counts() == expected


def coefficient_set() -> dict:
    """A signed-looking refit set of three bands, quality as the refit writes it (open properties included)."""
    band = {
        "temp_c": 25.0,
        "w": [0.00065, -0.01, 0.00066, 0.02],
        "w5": 0.001,
        "zero_offset_rad": 0.3,
        "harmonics": [[2, 0.001, -0.0005], [3, 0.0002, 0.0001]],
        "quality": {
            "samples": 5000,
            "residual_rms_rad": 0.001,
            "radius_ripple_rad": None,
            "estimated_error_deg": 0.01,
            "drift_terms": {"offset_d": 0.0},
        },
        "bench_locus": {"temp_c": 20.0},
    }
    bands = [{"band": b, **copy.deepcopy(band), "temp_c": 10.0 * b + 5} for b in (-1, 2, 3)]
    msg = wire.coefficients_message("drive-1", 4, 3600.0, "rollback", bands, restores_version=2)
    msg["signature"] = "A" * 86 + "=="
    return msg


def test_code_and_schema_file_agree_on_mutated_coefficient_sets():
    """Coefficient sets are accepted by a Struct compiled once (fleet_wire.messages._CoefficientSet) and only what
    it refuses goes to the schema file's validator: no set the file refuses may pass the Struct, and check() says
    what the file says (band uniqueness and the rollback rule are beyond a JSON Schema)."""
    validator = Draft202012Validator(wire.load_schema("coefficients"))
    base = coefficient_set()
    assert wire._compiled_valid("coefficients", wire._finite_json(base)) and validator.is_valid(base)
    checked = fast = 0
    for path, value, msg in mutated(base):
        schema_ok = validator.is_valid(msg)
        compiled_ok = wire._compiled_valid("coefficients", wire._finite_json(msg))
        assert not compiled_ok or schema_ok, (path, value)  # the Struct never accepts what the file refuses
        try:
            wire.check("coefficients", msg)
            reason = None
        except wire.WireError as exc:
            reason = exc.reason
        assert (reason is None or reason not in STRUCTURAL) == schema_ok, (path, value, reason)
        checked += 1
        fast += compiled_ok
    # whole lists: bands and harmonics of wrong shapes
    for mutate in (
        lambda m: m["bands"].clear(),
        lambda m: m["bands"].extend(copy.deepcopy(m["bands"][0]) | {"band": 10 + k} for k in range(62)),
        lambda m: m["bands"][1]["harmonics"].append([65, 0.0, 0.0]),
        lambda m: m["bands"][1]["harmonics"].append([2, 0.0]),
        lambda m: m["bands"][1]["harmonics"].append([2.5, 0.0, 0.0]),
        lambda m: m["bands"][1]["w"].append(1.0),
        lambda m: m["bands"][1].pop("quality"),
    ):
        msg = copy.deepcopy(base)
        mutate(msg)
        schema_ok = validator.is_valid(msg)
        assert not wire._compiled_valid("coefficients", wire._finite_json(msg)) or schema_ok
        assert schema_ok is False
        with pytest.raises(wire.WireError):
            wire.check("coefficients", msg)
        checked += 1
    assert checked > 200 and fast > 10  # the fast path is taken (a valid mutation: 1.5 for a weight, …)
