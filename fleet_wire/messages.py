"""The wire: the one place that knows the JSON messages agents and the service exchange.

docs/wire.md describes them, schemas/*.schema.json are the contract, this module checks both
directions: `decode` for what arrives, `encode` for what leaves, builders for what we create.
Kinds are "window" (key suffix "stats"), "coefficients" and "ack".
"""

from __future__ import annotations

import json
import math
from functools import cache
from importlib import resources

from jsonschema import Draft202012Validator
from jsonschema.exceptions import best_match

from encoder_core.physics import BAND_WIDTH_C, band_of
from encoder_core.samples import InputError
from encoder_core.stats import WindowStats

from . import keys

KINDS = ("window", "coefficients", "ack")
KEY_SUFFIX = {"window": keys.STATS, "coefficients": keys.COEFFICIENTS, "ack": keys.ACK}
SCHEMA_NAME = {kind: f"encoder-fleet/{kind}/1" for kind in KINDS}
MAX_PAYLOAD = 256 * 1024


class WireError(InputError):
    """A message that cannot be accepted. `reason` is a short code, the message says what and where
    (a JSON path). Codes: too_large, not_json, non_finite, schema, inconsistent, device_mismatch,
    bad_key, unknown_kind. service.store.Store.ingest adds unexpected_kind, seq_conflict and
    normalisation_mismatch for well-formed messages it cannot take."""

    def __init__(self, reason: str, message: str):
        super().__init__(message)
        self.reason = reason


def schema_bytes(kind: str) -> bytes:
    """The published JSON Schema file of a message kind (package data: schemas/ in the repository)."""
    if kind not in KINDS:
        raise WireError("unknown_kind", f"unknown message kind {kind!r}; expected one of {', '.join(KINDS)}")
    return resources.files("fleet_wire.schemas").joinpath(f"{kind}.schema.json").read_bytes()


def load_schema(kind: str) -> dict:
    """The JSON Schema of a message kind, freshly parsed (callers may change their copy)."""
    return json.loads(schema_bytes(kind))


@cache
def _validator(kind: str) -> Draft202012Validator:
    schema = load_schema(kind)
    Draft202012Validator.check_schema(schema)
    return Draft202012Validator(schema)


# jsonschema walks the ~400 numbers of a window's moments and bins one by one (~4 ms, 15x the rest
# of the message). So the common, valid case takes a fast path: the schema with its plain numeric
# arrays cut out, plus a Python check of those arrays against the same schema nodes. Anything the
# fast path refuses goes through the full validator, which names the error.

_PLAIN_ARRAY_KEYS = {"type", "minItems", "maxItems", "items", "description", "title"}
_NUMBER = {"type": "number"}


def _is_plain_numeric_array(node) -> bool:
    """{"type": "array", "minItems", "maxItems", "items": a number or another such array}."""
    return (
        isinstance(node, dict)
        and node.get("type") == "array"
        and set(node) <= _PLAIN_ARRAY_KEYS
        and (node.get("items") == _NUMBER or _is_plain_numeric_array(node.get("items")))
    )


def _numeric_array_ok(node: dict, value) -> bool:
    if not isinstance(value, list) or not node.get("minItems", 0) <= len(value) <= node.get("maxItems", math.inf):
        return False
    if node["items"] == _NUMBER:
        return all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in value)
    return all(_numeric_array_ok(node["items"], x) for x in value)


def _cut_arrays(node: dict, path: tuple = ()) -> list[tuple[tuple, dict]]:
    """Replace plain numeric arrays among (nested) object properties by `true`; return their paths and nodes."""
    cut = []
    for name, prop in node.get("properties", {}).items():
        if _is_plain_numeric_array(prop):
            cut.append((path + (name,), prop))
            node["properties"][name] = True
        elif isinstance(prop, dict) and prop.get("type") == "object":
            cut += _cut_arrays(prop, path + (name,))
    return cut


@cache
def _fast_validator(kind: str) -> tuple[Draft202012Validator, list[tuple[tuple, dict]]]:
    schema = load_schema(kind)
    arrays = _cut_arrays(schema)
    return Draft202012Validator(schema), arrays


def _fast_valid(kind: str, msg) -> bool:
    validator, arrays = _fast_validator(kind)
    if not validator.is_valid(msg):
        return False
    for path, node in arrays:
        value = msg
        for key in path:  # the cut schema still requires each parent object and key
            value = value[key]
        if not _numeric_array_ok(node, value):
            return False
    return True


# --- keys -------------------------------------------------------------------------------------


def key_for(kind: str, device: str) -> str:
    return keys.key(device, KEY_SUFFIX[kind])


def parse_key(key_expr: str) -> tuple[str, str]:
    """`encoders/<device>/<suffix>` of a message kind -> (device, kind)."""
    kinds = {suffix: kind for kind, suffix in KEY_SUFFIX.items()}
    parts = keys.split(key_expr)
    if parts is None or parts[1] not in kinds:
        raise WireError("bad_key", f"key {key_expr!r} is not {keys.PREFIX}/<device>/<{'|'.join(kinds)}>")
    return parts[0], kinds[parts[1]]


def device_from_key(key_expr: str) -> str:
    """The <device> of any fleet key (stats, ack, coefficients, factory, received, alive)."""
    parts = keys.split(key_expr)
    if parts is None or parts[1] not in keys.SUFFIXES:
        raise WireError("bad_key", f"key {key_expr!r} is not {keys.PREFIX}/<device>/<{'|'.join(keys.SUFFIXES)}>")
    return parts[0]


# --- checking ---------------------------------------------------------------------------------


class _NonFinite:
    """Stands in for a NaN/Infinity token or an overflowing number while parsing, so we can say where it was."""

    def __init__(self, token: str):
        self.token = token


def _parse_float(token: str):
    value = float(token)
    return value if math.isfinite(value) else _NonFinite(token)


class _DuplicateKey(ValueError):
    pass


def _unique_keys(pairs: list) -> dict:
    """JSON objects with a key twice would silently keep the last value; refuse them instead."""
    obj = {}
    for key, value in pairs:
        if key in obj:
            raise _DuplicateKey(key)
        obj[key] = value
    return obj


def _find_non_finite(value, path: str = "$") -> tuple[str, str] | None:
    if isinstance(value, _NonFinite):
        return path, value.token
    if isinstance(value, float) and not math.isfinite(value):
        return path, repr(value)
    if isinstance(value, dict):
        items = ((f"{path}.{k}", v) for k, v in value.items())
    elif isinstance(value, (list, tuple)):
        items = ((f"{path}[{i}]", v) for i, v in enumerate(value))
    else:
        return None
    for sub_path, sub in items:
        found = _find_non_finite(sub, sub_path)
        if found:
            return found
    return None


def check(kind: str, msg) -> dict:
    """Raise WireError unless msg is a valid message of this kind; returns msg."""
    found = _find_non_finite(msg)
    if found:
        raise WireError(
            "non_finite", f"{kind} message: {found[0]}: non-finite number {found[1]} (JSON allows finite numbers only)"
        )
    error = None if _fast_valid(kind, msg) else best_match(_validator(kind).iter_errors(msg))
    if error is not None:
        text = error.message if len(error.message) <= 200 else error.message[:200] + "…"
        raise WireError("schema", f"{kind} message: {error.json_path}: {text}")
    _check_consistency(kind, msg)
    return msg


def _check_consistency(kind: str, msg: dict) -> None:
    """What a JSON Schema cannot say: relations between fields."""

    def bad(path: str, text: str):
        raise WireError("inconsistent", f"{kind} message: {path}: {text}")

    if kind == "window":
        if msg["window_end"] < msg["window_start"]:
            bad("$.window_end", f"{msg['window_end']} is before window_start {msg['window_start']}")
        if msg["rejected"] != msg["stats"]["rejected"]:
            bad("$.rejected", f"{msg['rejected']} differs from stats.rejected = {msg['stats']['rejected']}")
        if "rejected_by_reason" in msg and sum(msg["rejected_by_reason"].values()) != msg["rejected"]:
            bad("$.rejected_by_reason", f"{msg['rejected_by_reason']} does not sum to rejected = {msg['rejected']}")
        if msg["samples"] != round(msg["stats"]["moments"][0]):
            bad("$.samples", f"{msg['samples']} differs from stats.moments[0] = {msg['stats']['moments'][0]}")
        slack = 1e-9 * max(1.0, abs(msg["temp_min_c"]), abs(msg["temp_max_c"]))  # Σt/n rounds past min/max
        if not msg["temp_min_c"] - slack <= msg["temp_mean_c"] <= msg["temp_max_c"] + slack:
            bad("$.temp_mean_c", f"{msg['temp_mean_c']} is outside [temp_min_c, temp_max_c]")
        if msg["band"] != band_of(msg["temp_mean_c"]):
            bad("$.band", f"{msg['band']} is not floor(temp_mean_c / {BAND_WIDTH_C:g}) = {band_of(msg['temp_mean_c'])}")
    elif kind == "coefficients":
        if (msg["basis"] == "rollback") != ("restores_version" in msg):
            bad("$.restores_version", "a rollback set names the version it restores, and only a rollback set does")
        bands = [b["band"] for b in msg["bands"]]
        if len(set(bands)) != len(bands):
            bad("$.bands", f"a band appears twice: {bands}")


def decode(kind: str, payload: bytes, *, key_device: str | None) -> dict:
    """Bytes off the wire -> a checked message. key_device: the <device> of the key it arrived on."""
    if len(payload) > MAX_PAYLOAD:
        raise WireError("too_large", f"{kind} message: payload of {len(payload)} bytes exceeds {MAX_PAYLOAD} bytes")
    try:
        text = bytes(payload).decode("utf-8")
    except UnicodeDecodeError as exc:
        raise WireError("not_json", f"{kind} message: not UTF-8 at byte {exc.start}") from None
    try:
        msg = json.loads(text, parse_constant=_NonFinite, parse_float=_parse_float, object_pairs_hook=_unique_keys)
    except json.JSONDecodeError as exc:
        raise WireError(
            "not_json", f"{kind} message: not JSON: {exc.msg} at line {exc.lineno} column {exc.colno}"
        ) from None
    except _DuplicateKey as exc:
        raise WireError("not_json", f"{kind} message: key {exc.args[0]!r} appears twice in one object") from None
    check(kind, msg)
    if key_device is not None and msg["device"] != key_device:
        raise WireError(
            "device_mismatch",
            f"{kind} message: $.device: {msg['device']!r} differs from the key's device {key_device!r}",
        )
    return msg


def encode(kind: str, msg: dict) -> bytes:
    """A message -> bytes to send, after the same checks the receiver makes."""
    check(kind, msg)
    payload = json.dumps(msg, separators=(",", ":"), allow_nan=False).encode("utf-8")
    if len(payload) > MAX_PAYLOAD:
        raise WireError("too_large", f"{kind} message: payload of {len(payload)} bytes exceeds {MAX_PAYLOAD} bytes")
    return payload


# --- builders ---------------------------------------------------------------------------------


def window_message(
    device: str,
    seq: int,
    stats: WindowStats,
    *,
    window_start: float,
    window_end: float,
    temp_rate_c_per_s: float,
    coefficients_version: int,
    angle_quality_deg: float,
    rejected_by_reason: dict[str, int] | None = None,
) -> dict:
    """A window message; samples, rejected, temperatures and band come from the statistics.
    rejected_by_reason (optional): the rejected samples per reason (non_finite, clipped, outlier)."""
    if stats.temp_n == 0:
        raise WireError("schema", "window message: the statistics hold no temperature; a window needs one for its band")
    temp_mean = float(stats.temp_mean)
    extra = (
        {} if rejected_by_reason is None else {"rejected_by_reason": {k: int(v) for k, v in rejected_by_reason.items()}}
    )
    return check(
        "window",
        {
            "schema": SCHEMA_NAME["window"],
            "device": device,
            "seq": int(seq),
            "window_start": float(window_start),
            "window_end": float(window_end),
            "samples": stats.n,
            "rejected": int(stats.rejected),
            "temp_mean_c": temp_mean,
            "temp_min_c": float(stats.temp_min),
            "temp_max_c": float(stats.temp_max),
            "temp_rate_c_per_s": float(temp_rate_c_per_s),
            "band": band_of(temp_mean),
            "coefficients_version": int(coefficients_version),
            "angle_quality_deg": float(angle_quality_deg),
            "stats": stats.to_dict(),
            **extra,
        },
    )


def band_entry(band: int, correction: dict, quality: dict) -> dict:
    """One entry of a coefficient set: Correction.to_dict() plus band and quality."""
    return {"band": int(band), **correction, "quality": dict(quality)}


def coefficients_message(
    device: str, version: int, created_at: float, basis: str, bands: list[dict], *, restores_version: int | None = None
) -> dict:
    """bands: entries from band_entry(), in any order (sent sorted by band). restores_version: only for
    basis 'rollback', the confirmed set it carries again."""
    msg = {
        "schema": SCHEMA_NAME["coefficients"],
        "device": device,
        "version": int(version),
        "created_at": float(created_at),
        "basis": basis,
        "bands": sorted(bands, key=lambda b: b["band"]),
    }
    if restores_version is not None:
        msg["restores_version"] = int(restores_version)
    return check("coefficients", msg)


def ack_message(
    device: str,
    version: int,
    status: str,
    at: float,
    *,
    angle_quality_deg: float | None = None,
    reason: str | None = None,
) -> dict:
    msg = {
        "schema": SCHEMA_NAME["ack"],
        "device": device,
        "version": int(version),
        "status": status,
        "angle_quality_deg": None if angle_quality_deg is None else float(angle_quality_deg),
        "at": float(at),
    }
    if reason is not None:
        msg["reason"] = reason
    return check("ack", msg)


def watermark_reply(device: str, contiguous_seq: int) -> bytes:
    """The service's answer on `received`: every window of `device` with seq <= contiguous_seq is stored."""
    return json.dumps({"device": device, "contiguous_seq": int(contiguous_seq)}).encode()


def parse_watermark(payload: bytes, device: str) -> int:
    """The contiguous_seq of a watermark reply for `device`; WireError when it is not one."""
    try:
        body = json.loads(payload)
        seq = body["contiguous_seq"]
        if body["device"] != device or not isinstance(seq, int) or isinstance(seq, bool) or seq < 0:
            raise TypeError
    except (ValueError, KeyError, TypeError):
        raise WireError("schema", f"not a watermark reply for {device}: {bytes(payload)[:200]!r}") from None
    return seq
