"""The wire: the one place that knows the JSON messages agents and the service exchange.

docs/wire.md describes them, schemas/*.schema.json are the contract, this module checks both
directions: `decode` for what arrives, `encode` for what leaves, builders for what we create.
Kinds are "window" (key suffix "stats"), "coefficients" and "ack".
"""

from __future__ import annotations

import json
import math
import operator
import re
import secrets
from functools import cache
from importlib import resources
from typing import Annotated, Literal

import msgspec
import numpy as np
from jsonschema import Draft202012Validator
from jsonschema.exceptions import best_match

from encoder_core.physics import BAND_WIDTH_C, band_of
from encoder_core.samples import InputError
from encoder_core.stats import BIN_COLUMNS, MONOMIALS, N_BINS, WindowStats
from encoder_core.thermal import MAX_LAG_S  # the die's lag a set may carry

from . import keys

KINDS = ("window", "coefficients", "ack")
KEY_SUFFIX = {"window": keys.STATS, "coefficients": keys.COEFFICIENTS, "ack": keys.ACK}
SCHEMA_NAME = {kind: f"encoder-fleet/{kind}/1" for kind in KINDS}
MAX_PAYLOAD = 256 * 1024


class WireError(InputError):
    """A message that cannot be accepted. `reason` is a short code, the message says what and where
    (a JSON path). Codes: too_large, too_deep (nested past MAX_DEPTH), not_json (neither JSON nor MessagePack),
    non_finite, schema, inconsistent, device_mismatch, bad_key, unknown_kind; with security on, unsigned and
    bad_signature (fleet_wire.security), and wrong_nonce (a watermark reply to another question).
    service.store.Store.ingest adds unexpected_kind, seq_conflict, clock_backwards, normalisation_mismatch and
    device_retired for well-formed messages it cannot take."""

    def __init__(self, reason: str, message: str):
        super().__init__(message)
        self.reason = reason

    def __reduce__(self):  # pickled with both arguments: a worker process's error reaches its pool intact
        return type(self), (self.reason, str(self))


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

_PLAIN_ARRAY_KEYS = {"type", "minItems", "maxItems", "items", "prefixItems", "description", "title"}
_NUMBER = {"type": "number"}
_INTEGER_KEYS = {"type", "minimum", "maximum"}


def _is_bounded_integer(node) -> bool:
    return isinstance(node, dict) and node.get("type") == "integer" and set(node) <= _INTEGER_KEYS


def _is_plain_numeric_array(node) -> bool:
    """{"type": "array", "minItems", "maxItems", "items": a number or another such array, "prefixItems": bounded
    integers} (a harmonic's [m, a_m, b_m])."""
    return (
        isinstance(node, dict)
        and node.get("type") == "array"
        and set(node) <= _PLAIN_ARRAY_KEYS
        and all(_is_bounded_integer(prefix) for prefix in node.get("prefixItems", []))
        and (node.get("items") == _NUMBER or _is_plain_numeric_array(node.get("items")))
    )


def _is_number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def _integer_ok(node: dict, x) -> bool:
    # JSON Schema's integer: any number with no fractional part (2.0 is an integer)
    if not _is_number(x) or not (isinstance(x, int) or x.is_integer()):
        return False
    return node.get("minimum", -math.inf) <= x <= node.get("maximum", math.inf)


def _numeric_array_ok(node: dict, value) -> bool:
    if not isinstance(value, list) or not node.get("minItems", 0) <= len(value) <= node.get("maxItems", math.inf):
        return False
    prefix = node.get("prefixItems", [])
    if not all(_integer_ok(p, x) for p, x in zip(prefix, value)):
        return False
    rest = value[len(prefix) :]
    if node["items"] == _NUMBER:
        return all(_is_number(x) for x in rest)
    return all(_numeric_array_ok(node["items"], x) for x in rest)


def _cut_arrays(node: dict, path: tuple = ()) -> list[tuple[tuple, dict]]:
    """Replace plain numeric arrays among (nested) object properties, also inside arrays of objects (path
    element "*": every item), by `true`; return their paths and nodes."""
    cut = []
    for name, prop in node.get("properties", {}).items():
        if _is_plain_numeric_array(prop):
            cut.append((path + (name,), prop))
            node["properties"][name] = True
        elif isinstance(prop, dict) and prop.get("type") == "object":
            cut += _cut_arrays(prop, path + (name,))
        elif isinstance(prop, dict) and prop.get("type") == "array" and isinstance(prop.get("items"), dict):
            if prop["items"].get("type") == "object":
                cut += _cut_arrays(prop["items"], path + (name, "*"))
    return cut


def _values_at(value, path: tuple):
    """The values at `path` ("*" walks every item of a list); a key that is absent holds nothing to check:
    the cut schema has already said whether it may be absent."""
    if not path:
        yield value
        return
    key, rest = path[0], path[1:]
    if key == "*":
        for item in value:
            yield from _values_at(item, rest)
    elif key in value:
        yield from _values_at(value[key], rest)


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
        if not all(_numeric_array_ok(node, value) for value in _values_at(msg, path)):
            return False
    return True


# --- windows: typed Structs, compiled once (msgspec) ---------------------------------------------
#
# A window is ~400 floats of statistics. On the wire it is MessagePack with `moments` and `bins` as
# packed little-endian float64 bytes (~3.6 KB, decoded in a few µs); JSON windows (first byte `{`) of
# older agents are still accepted. Both decode into the Structs below, whose fields, types and bounds
# are those of schemas/window.schema.json (tests/test_wire.py proves they agree); the decoded form, the
# dict of window_to_dict(), has the arrays as lists of numbers and validates against the schema file.

MAX_INT = 2**63 - 1  # what an SQLite INTEGER holds
N_MOMENTS = len(MONOMIALS)
N_BIN_VALUES = N_BINS * len(BIN_COLUMNS)
_F8 = np.dtype("<f8")

Count = Annotated[int, msgspec.Meta(ge=0, le=MAX_INT)]
TEMP_MIN_C, TEMP_MAX_C = -273.15, 300.0  # a window's temperatures: past them a reading is a broken sensor's
Temp = Annotated[float, msgspec.Meta(ge=TEMP_MIN_C, le=TEMP_MAX_C)]
MAX_TIME_S = 1e10  # a drive clock in seconds: 300 years
Time = Annotated[float, msgspec.Meta(ge=0, le=MAX_TIME_S)]
Device = Annotated[str, msgspec.Meta(pattern=keys.DEVICE_RE.pattern)]
NONCE_BYTES = 16  # a question's nonce on `received`: 32 hex characters
NONCE_RE = re.compile(f"[0-9a-f]{{{2 * NONCE_BYTES}}}")


class RejectedByReason(msgspec.Struct, forbid_unknown_fields=True):
    non_finite: Count
    clipped: Count
    outlier: Count


class _StatsBase(msgspec.Struct, forbid_unknown_fields=True):
    scale: Annotated[float, msgspec.Meta(gt=0)]
    center_d: float
    center_q: float


class _StatsTail(msgspec.Struct, forbid_unknown_fields=True):
    temp_n: Count
    temp_sum: float
    temp_sq_sum: Annotated[float, msgspec.Meta(ge=0)]
    temp_min: Temp | None
    temp_max: Temp | None
    rejected: Count


class PackedStats(msgspec.Struct, forbid_unknown_fields=True):
    """WindowStats with its arrays as little-endian float64 bytes: the MessagePack wire form and the stored blob."""

    scale: Annotated[float, msgspec.Meta(gt=0)]
    center_d: float
    center_q: float
    moments: Annotated[bytes, msgspec.Meta(min_length=8 * N_MOMENTS, max_length=8 * N_MOMENTS)]
    bins: Annotated[bytes, msgspec.Meta(min_length=8 * N_BIN_VALUES, max_length=8 * N_BIN_VALUES)]
    temp_n: Count
    temp_sum: float
    temp_sq_sum: Annotated[float, msgspec.Meta(ge=0)]
    temp_min: Temp | None
    temp_max: Temp | None
    rejected: Count

    def moments_array(self) -> np.ndarray:
        return np.frombuffer(self.moments, _F8)

    def bins_array(self) -> np.ndarray:
        return np.frombuffer(self.bins, _F8).reshape(N_BINS, len(BIN_COLUMNS))

    def window_stats(self) -> WindowStats:
        return WindowStats(
            scale=self.scale,
            center_d=self.center_d,
            center_q=self.center_q,
            moments=self.moments_array(),
            bins=self.bins_array(),
            temp_n=self.temp_n,
            temp_sum=self.temp_sum,
            temp_sq_sum=self.temp_sq_sum,
            temp_min=float("inf") if self.temp_min is None else self.temp_min,
            temp_max=float("-inf") if self.temp_max is None else self.temp_max,
            rejected=self.rejected,
        )

    def to_dict(self) -> dict:
        """The decoded form: WindowStats.to_dict()'s shape, arrays as lists."""
        d = msgspec.structs.asdict(self)
        d["moments"] = self.moments_array().tolist()
        d["bins"] = self.bins_array().tolist()
        return d


class ArrayStats(msgspec.Struct, forbid_unknown_fields=True):
    """The same statistics with arrays of numbers: JSON windows and the decoded form."""

    scale: Annotated[float, msgspec.Meta(gt=0)]
    center_d: float
    center_q: float
    moments: Annotated[list[float], msgspec.Meta(min_length=N_MOMENTS, max_length=N_MOMENTS)]
    bins: Annotated[
        list[Annotated[list[float], msgspec.Meta(min_length=len(BIN_COLUMNS), max_length=len(BIN_COLUMNS))]],
        msgspec.Meta(min_length=N_BINS, max_length=N_BINS),
    ]
    temp_n: Count
    temp_sum: float
    temp_sq_sum: Annotated[float, msgspec.Meta(ge=0)]
    temp_min: Temp | None
    temp_max: Temp | None
    rejected: Count

    def packed(self) -> PackedStats:
        d = msgspec.structs.asdict(self)
        d["moments"] = np.asarray(self.moments, _F8).tobytes()
        d["bins"] = np.asarray(self.bins, _F8).tobytes()
        return PackedStats(**d)


class _WindowFields(msgspec.Struct, forbid_unknown_fields=True):
    schema: Literal["encoder-fleet/window/1"]
    device: Device
    seq: Annotated[int, msgspec.Meta(ge=1, le=2**53 - 1)]
    window_start: Time
    window_end: Time
    samples: Count
    rejected: Count
    temp_mean_c: Temp
    temp_min_c: Temp
    temp_max_c: Temp
    temp_rate_c_per_s: Annotated[float, msgspec.Meta(ge=-100, le=100)]
    band: Annotated[int, msgspec.Meta(ge=-28, le=30)]
    coefficients_version: Count
    angle_quality_deg: Annotated[float, msgspec.Meta(ge=0, le=180)]


class Window(_WindowFields, forbid_unknown_fields=True):
    """A window as the service handles it: statistics packed (PackedStats)."""

    stats: PackedStats
    rejected_by_reason: RejectedByReason | msgspec.UnsetType = msgspec.UNSET


class ArrayWindow(_WindowFields, forbid_unknown_fields=True):
    """A JSON window (and the decoded form): statistics as arrays of numbers."""

    stats: ArrayStats
    rejected_by_reason: RejectedByReason | msgspec.UnsetType = msgspec.UNSET

    def packed(self) -> Window:
        d = {f: getattr(self, f) for f in self.__struct_fields__}
        d["stats"] = self.stats.packed()
        return Window(**d)


_FLOAT_FIELDS = tuple(
    f.name for f in msgspec.inspect.type_info(_WindowFields).fields if isinstance(f.type, msgspec.inspect.FloatType)
)
_STATS_FLOATS = ("scale", "center_d", "center_q", "temp_sum", "temp_sq_sum", "temp_min", "temp_max")
_window_msgpack = msgspec.msgpack.Decoder(Window)
_msgpack_encoder = msgspec.msgpack.Encoder()
_MSGPACK_MAP = frozenset([*range(0x80, 0x90), 0xDE, 0xDF])  # a MessagePack map's first byte


# --- coefficient sets: a Struct compiled once as the schema's fast acceptance ------------------------------
#
# A refit pass checks every set it rolls out; the schema file checked in Python took ~3.8 ms a set. A set the
# Structs below accept is valid against schemas/coefficients.schema.json (their bounds are the file's, band
# entries and quality stay open to other properties as the file has them); one they refuse goes to the file's
# validator, which names what is wrong (or accepts what the Structs are stricter about, such as 2.0 for an
# integer). tests/test_wire_contract.py: no mutated set the file refuses is accepted here.

MAX_VERSION = 2**53 - 1  # a coefficient set's version: exact in every JSON reader
_Version = Annotated[int, msgspec.Meta(ge=0, le=MAX_VERSION)]
_NonNegative = Annotated[float, msgspec.Meta(ge=0)]


class _Quality(msgspec.Struct):
    samples: Annotated[int, msgspec.Meta(ge=0)]
    residual_rms_rad: _NonNegative | None | msgspec.UnsetType = msgspec.UNSET
    radius_ripple_rad: _NonNegative | None | msgspec.UnsetType = msgspec.UNSET
    estimated_error_deg: Annotated[float, msgspec.Meta(ge=0, le=180)] | msgspec.UnsetType = msgspec.UNSET


class _BandEntry(msgspec.Struct):
    band: Annotated[int, msgspec.Meta(ge=-28, le=30)]
    temp_c: Temp | None
    w: Annotated[list[float], msgspec.Meta(min_length=4, max_length=4)]
    w5: float
    zero_offset_rad: Annotated[float, msgspec.Meta(ge=-7, le=7)]
    harmonics: Annotated[
        list[tuple[Annotated[int, msgspec.Meta(ge=1, le=64)], float, float]], msgspec.Meta(max_length=64)
    ]
    quality: _Quality


class _CoefficientSet(msgspec.Struct, forbid_unknown_fields=True):
    schema: Literal["encoder-fleet/coefficients/1"]
    device: Device
    version: _Version
    created_at: Time
    basis: Literal["factory", "fit", "rollback"]
    bands: Annotated[list[_BandEntry], msgspec.Meta(min_length=1, max_length=64)]
    signature: Annotated[str, msgspec.Meta(pattern=r"^[A-Za-z0-9+/]{86}==$")] | msgspec.UnsetType = msgspec.UNSET
    restores_version: _Version | msgspec.UnsetType = msgspec.UNSET
    thermal_lag_s: Annotated[float, msgspec.Meta(ge=0, le=MAX_LAG_S)] | msgspec.UnsetType = msgspec.UNSET


_COMPILED = {"coefficients": _CoefficientSet}
_COMPILED_JSON = {kind: msgspec.json.Decoder(struct) for kind, struct in _COMPILED.items()}


def _compiled_valid(kind: str, text: str | None) -> bool:
    """True when the kind's Struct accepts the message's JSON text (then the schema file accepts the message);
    False: ask the file. From the text (`_finite_json`), because sets made in-process carry numpy floats, which
    msgspec takes for another type."""
    if text is None:
        return False
    try:
        _COMPILED_JSON[kind].decode(text.encode())
    except (msgspec.ValidationError, msgspec.DecodeError):
        return False
    return True


def window_to_dict(win: Window) -> dict:
    """The decoded form: the wire-shaped dict the rest of the code and the schema file know."""
    d = msgspec.structs.asdict(win)
    d["stats"] = win.stats.to_dict()
    if win.rejected_by_reason is msgspec.UNSET:
        del d["rejected_by_reason"]
    else:
        d["rejected_by_reason"] = msgspec.structs.asdict(win.rejected_by_reason)
    return d


def window_from_dict(msg: dict) -> Window:
    """A wire-shaped window dict (arrays as lists) -> Window, checked as the wire checks a window: the same
    Structs, then the non-finite numbers and the relations a schema cannot state (a NaN in the statistics'
    arrays passes the Structs' types, and a caller storing the window would keep it)."""
    try:
        win = msgspec.convert(msg, ArrayWindow).packed()
    except msgspec.ValidationError as exc:
        raise WireError("schema", f"window message: {_where(exc)}") from None
    return _check_window(win)


def pack_stats(stats: PackedStats) -> bytes:
    """The canonical bytes of a window's statistics (what the store keeps and compares)."""
    return _msgpack_encoder.encode(stats)


def unpack_stats(blob: bytes) -> PackedStats:
    """Stored bytes -> PackedStats, unchecked (the store wrote them; a band's sum may round a bound)."""
    return PackedStats(**msgspec.msgpack.decode(blob))


def packed_stats(stats: WindowStats) -> PackedStats:
    finite = stats.temp_n > 0
    return PackedStats(
        scale=float(stats.scale),
        center_d=float(stats.center_d),
        center_q=float(stats.center_q),
        moments=np.ascontiguousarray(stats.moments, _F8).tobytes(),
        bins=np.ascontiguousarray(stats.bins, _F8).tobytes(),
        temp_n=int(stats.temp_n),
        temp_sum=float(stats.temp_sum),
        temp_sq_sum=float(stats.temp_sq_sum),
        temp_min=float(stats.temp_min) if finite else None,
        temp_max=float(stats.temp_max) if finite else None,
        rejected=int(stats.rejected),
    )


def encode_window(win: Window) -> bytes:
    return _msgpack_encoder.encode(win)


def _where(exc: msgspec.ValidationError) -> str:
    """msgspec's message with its path first, as '$.a.b: what' like the rest of the wire's errors."""
    text = str(exc).replace("`", "'")
    what, sep, path = text.rpartition(" - at ")
    if not sep:
        return f"$: {text}"
    return f"{path.strip(chr(39))}: {what}"


def _name_non_finite(win: Window) -> None:
    """Raise naming the first non-finite number of a window, if there is one."""
    for name in _FLOAT_FIELDS:
        value = getattr(win, name)
        if not math.isfinite(value):
            raise WireError("non_finite", f"window message: $.{name}: non-finite number {value!r}")
    stats = win.stats
    for name in _STATS_FLOATS:
        value = getattr(stats, name)
        if value is not None and not math.isfinite(value):
            raise WireError("non_finite", f"window message: $.stats.{name}: non-finite number {value!r}")
    for name, arr in (("moments", stats.moments_array()), ("bins", stats.bins_array())):
        finite = np.isfinite(arr)
        if not finite.all():
            where = "".join(f"[{i}]" for i in np.argwhere(~finite)[0])
            raise WireError("non_finite", f"window message: $.stats.{name}{where}: non-finite number")


_window_floats = operator.attrgetter(*_FLOAT_FIELDS)
_stats_floats = operator.attrgetter(*_STATS_FLOATS)


def _check_window(win: Window) -> Window:
    """Non-finite numbers (MessagePack carries NaN and infinities) and the relations a schema cannot state."""
    stats = win.stats
    arrays = np.frombuffer(stats.moments + stats.bins, _F8)  # the moments, then the bins
    # a sum of numbers is finite unless one is not (or the sum overflows): one sum and one array test are the
    # usual window's whole check, ~15x faster than naming each number; the walk runs only to say where
    scalars = sum(v for v in (*_window_floats(win), *_stats_floats(stats)) if v is not None)
    if not (math.isfinite(scalars) and np.isfinite(arrays).all()):
        _name_non_finite(win)

    def bad(path: str, text: str):
        raise WireError("inconsistent", f"window message: {path}: {text}")

    if win.window_end < win.window_start:
        bad("$.window_end", f"{win.window_end} is before window_start {win.window_start}")
    if win.rejected != stats.rejected:
        bad("$.rejected", f"{win.rejected} differs from stats.rejected = {stats.rejected}")
    rbr = win.rejected_by_reason
    if rbr is not msgspec.UNSET and rbr.non_finite + rbr.clipped + rbr.outlier != win.rejected:
        bad("$.rejected_by_reason", f"{msgspec.structs.asdict(rbr)} does not sum to rejected = {win.rejected}")
    n = float(arrays[0])
    if win.samples != round(n):
        bad("$.samples", f"{win.samples} differs from stats.moments[0] = {n}")
    slack = 1e-9 * max(1.0, abs(win.temp_min_c), abs(win.temp_max_c))  # Σt/n rounds past min/max
    if not win.temp_min_c - slack <= win.temp_mean_c <= win.temp_max_c + slack:
        bad("$.temp_mean_c", f"{win.temp_mean_c} is outside [temp_min_c, temp_max_c]")
    if win.band != band_of(win.temp_mean_c):
        bad("$.band", f"{win.band} is not floor(temp_mean_c / {BAND_WIDTH_C:g}) = {band_of(win.temp_mean_c)}")
    return win


MAX_DEPTH = 32  # no message nests deeper than 5; the parser recurses, so depth is bounded before it runs


def _nesting_depth(text: str) -> int:
    """How deep arrays and objects nest in JSON text, brackets inside strings not counted."""
    if text.count("[") + text.count("{") <= MAX_DEPTH:  # the usual case, without a scan
        return 0
    depth = deepest = 0
    in_string = escaped = False
    for ch in text:
        if in_string:
            if escaped:
                escaped = False
            elif ch == "\\":
                escaped = True
            elif ch == '"':
                in_string = False
        elif ch == '"':
            in_string = True
        elif ch in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif ch in "]}":
            depth -= 1
    return deepest


def _parse_json(kind: str, payload: bytes):
    """JSON text -> Python values, refusing what JSON parsers disagree on (duplicate keys) and naming
    non-finite numbers where they stand."""
    try:
        text = bytes(payload).decode("utf-8")
    except UnicodeDecodeError as exc:
        raise WireError("not_json", f"{kind} message: not UTF-8 at byte {exc.start}") from None
    depth = _nesting_depth(text)
    if depth > MAX_DEPTH:
        raise WireError("too_deep", f"{kind} message: JSON nested {depth} deep, more than {MAX_DEPTH}")
    try:
        msg = json.loads(
            text,
            parse_constant=_NonFinite,
            parse_float=_parse_float,
            parse_int=_parse_int,
            object_pairs_hook=_unique_keys,
        )
    except json.JSONDecodeError as exc:
        raise WireError(
            "not_json", f"{kind} message: not JSON: {exc.msg} at line {exc.lineno} column {exc.colno}"
        ) from None
    except _DuplicateKey as exc:
        raise WireError("not_json", f"{kind} message: key {exc.args[0]!r} appears twice in one object") from None
    except ValueError as exc:  # valid JSON Python will not read: an integer of more than 4300 digits
        raise WireError("not_json", f"{kind} message: unreadable JSON: {str(exc).split(';')[0]}") from None
    found = _find_non_finite(msg)
    if found:
        raise WireError(
            "non_finite", f"{kind} message: {found[0]}: non-finite number {found[1]} (JSON allows finite numbers only)"
        )
    return msg


def decode_window(payload: bytes, *, key_device: str | None) -> Window:
    """Bytes off the wire (MessagePack, or JSON from older agents) -> a checked Window."""
    if len(payload) > MAX_PAYLOAD:
        raise WireError("too_large", f"window message: payload of {len(payload)} bytes exceeds {MAX_PAYLOAD} bytes")
    if payload[:1] and payload[0] in _MSGPACK_MAP:
        try:
            win = _window_msgpack.decode(payload)
        except msgspec.ValidationError as exc:
            try:
                found = _find_non_finite(msgspec.msgpack.decode(payload))  # a NaN also fails its bound: name it
            except (msgspec.DecodeError, UnicodeDecodeError) as bad:
                raise WireError("not_json", f"window message: not MessagePack: {bad}") from None
            except RecursionError:
                raise WireError(
                    "too_deep", "window message: MessagePack nested deeper than the decoder allows"
                ) from None
            if found:
                raise WireError("non_finite", f"window message: {found[0]}: non-finite number {found[1]}") from None
            raise WireError("schema", f"window message: {_where(exc)}") from None
        except (msgspec.DecodeError, UnicodeDecodeError) as exc:  # msgspec raises the latter for a string not UTF-8
            raise WireError("not_json", f"window message: not MessagePack: {exc}") from None
        _check_window(win)
    else:
        win = window_from_dict(_parse_json("window", payload))
    if key_device is not None and win.device != key_device:
        raise WireError(
            "device_mismatch", f"window message: $.device: {win.device!r} differs from the key's device {key_device!r}"
        )
    return win


# --- keys -------------------------------------------------------------------------------------


def key_for(kind: str, device: str) -> str:
    return keys.key(device, KEY_SUFFIX[kind])


def _key_shape(suffixes) -> str:
    return f"{keys.PREFIX}/<device>/<{'|'.join(suffixes)}>[/p<device's partition>]"


def parse_key(key_expr: str) -> tuple[str, str]:
    """`encoders/<device>/<suffix>` of a message kind -> (device, kind)."""
    kinds = {suffix: kind for kind, suffix in KEY_SUFFIX.items()}
    parts = keys.split(key_expr)
    if parts is None or parts[1] not in kinds:
        raise WireError("bad_key", f"key {key_expr!r} is not {_key_shape(kinds)}")
    return parts[0], kinds[parts[1]]


def device_from_key(key_expr: str) -> str:
    """The <device> of any fleet key (stats, ack, coefficients, factory, received, alive)."""
    parts = keys.split(key_expr)
    if parts is None or parts[1] not in keys.SUFFIXES:
        raise WireError("bad_key", f"key {key_expr!r} is not {_key_shape(keys.SUFFIXES)}")
    return parts[0]


# --- checking ---------------------------------------------------------------------------------


class _NonFinite:
    """Stands in for a NaN/Infinity token or an overflowing number while parsing, so we can say where it was."""

    def __init__(self, token: str):
        self.token = token


def _parse_float(token: str):
    value = float(token)
    return value if math.isfinite(value) else _NonFinite(token)


def _parse_int(token: str):
    """An integer no float holds (past ~1.8e308) overflows every number it meets, as 1e400 does."""
    value = int(token)
    try:
        float(value)
    except OverflowError:
        return _NonFinite(token)
    return value


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


def _finite_json(value) -> str | None:
    """value as JSON text when every number in it is finite; None for a non-finite number or a type JSON has no
    form for. Decided by the C JSON encoder in one pass (~30x faster than the walk on a coefficient set of
    ~1,000 numbers)."""
    try:
        return json.dumps(value, allow_nan=False)
    except (ValueError, TypeError):
        return None


def _find_non_finite(value) -> tuple[str, str] | None:
    """Where the first non-finite number is, or None; the walk runs only when the encoder refuses, to say where."""
    return None if _finite_json(value) is not None else _walk_non_finite(value, "$")


def _walk_non_finite(value, path: str) -> tuple[str, str] | None:
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
        found = _walk_non_finite(sub, sub_path)
        if found:
            return found
    return None


def check(kind: str, msg) -> dict:
    """Raise WireError unless msg is a valid message of this kind; returns msg."""
    if kind == "window":
        if not isinstance(msg, dict):
            raise WireError("schema", f"window message: $: expected an object, got {type(msg).__name__}")
        _find = _find_non_finite(msg)
        if _find:
            raise WireError("non_finite", f"window message: {_find[0]}: non-finite number {_find[1]}")
        window_from_dict(msg)
        return msg
    text = _finite_json(msg)  # once: the finite check, and the compiled Struct's input
    found = None if text is not None else _walk_non_finite(msg, "$")
    if found:
        raise WireError(
            "non_finite", f"{kind} message: {found[0]}: non-finite number {found[1]} (JSON allows finite numbers only)"
        )
    fast = _compiled_valid(kind, text) if kind in _COMPILED else _fast_valid(kind, msg)
    error = None if fast else best_match(_validator(kind).iter_errors(msg))
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
    if kind == "window":
        return window_to_dict(decode_window(payload, key_device=key_device))
    if kind not in KINDS:
        raise WireError("unknown_kind", f"unknown message kind {kind!r}; expected one of {', '.join(KINDS)}")
    if len(payload) > MAX_PAYLOAD:
        raise WireError("too_large", f"{kind} message: payload of {len(payload)} bytes exceeds {MAX_PAYLOAD} bytes")
    msg = _parse_json(kind, payload)
    check(kind, msg)
    if key_device is not None and msg["device"] != key_device:
        raise WireError(
            "device_mismatch",
            f"{kind} message: $.device: {msg['device']!r} differs from the key's device {key_device!r}",
        )
    return msg


def encode(kind: str, msg: dict, *, checked: bool = False) -> bytes:
    """A message -> bytes to send, after the same checks the receiver makes. Windows go as MessagePack
    (statistics packed), the rare messages as JSON. checked: msg was made by this module's constructor for its
    kind (coefficients_message, ...), which made those checks already (a coefficient set's schema pass is most of
    the cost of rolling it out); JSON still refuses a non-finite number."""
    if kind == "window":
        check(kind, msg)
        payload = encode_window(window_from_dict(msg))
    else:
        if not checked:
            check(kind, msg)
        payload = json.dumps(msg, separators=(",", ":"), allow_nan=False).encode("utf-8")
    if len(payload) > MAX_PAYLOAD:
        raise WireError("too_large", f"{kind} message: payload of {len(payload)} bytes exceeds {MAX_PAYLOAD} bytes")
    return payload


def encode_json(kind: str, msg: dict) -> bytes:
    """A message as JSON text (what agents before MessagePack windows sent; still accepted)."""
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
    device: str,
    version: int,
    created_at: float,
    basis: str,
    bands: list[dict],
    *,
    restores_version: int | None = None,
    thermal_lag_s: float = 0.0,
) -> dict:
    """bands: entries from band_entry(), in any order (sent sorted by band). restores_version: only for
    basis 'rollback', the confirmed set it carries again. thermal_lag_s: the die's lag the agent reads the bands
    with (encoder_core/thermal.py), sent when above 0."""
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
    if thermal_lag_s:
        msg["thermal_lag_s"] = float(thermal_lag_s)
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


def watermark_reply(
    device: str,
    contiguous_seq: int,
    acked_version: int = 0,
    last: tuple[int, float] | None = None,
    *,
    nonce: str | None = None,
    signer=None,
    retired: bool = False,
) -> bytes:
    """The service's answer on `received`: every window of `device` with seq <= contiguous_seq is stored, and
    an ack for every coefficient version <= acked_version (the agent stops resending those). `last`: the highest
    seq stored and that window's end (drive clock), where an agent that lost its outbox resumes. `nonce`: the one
    the question carried; `signer` (fleet_wire.security.SetSigner, security on) signs the reply with it, so an
    agent takes it for its own question only. `retired`: the drive is out of the fleet, and nothing it sends is
    stored (the agent holds its windows until it is reinstated; signed with the rest, so no forged reply silences
    a drive of a secured fleet)."""
    body = {"device": device, "contiguous_seq": int(contiguous_seq), "acked_version": int(acked_version)}
    if last is not None:
        body.update(max_seq=int(last[0]), last_window_end=float(last[1]))
    if retired:
        body["retired"] = True
    if nonce is not None:
        body["nonce"] = nonce
    if signer is not None:
        body = signer.sign(body)
    return json.dumps(body).encode()


def new_nonce() -> str:
    """A fresh nonce for one question on `received` (128 random bits, hex)."""
    return secrets.token_hex(NONCE_BYTES)


def received_query(device: str, gone_below: int | None = None, nonce: str | None = None) -> bytes | None:
    """The agent's question on `received`, None when it has nothing to say (no payload). `gone_below`: once its
    outbox has dropped windows (full while the service was away), every window of `device` with a seq below it that
    the service does not have is gone for good, so its contiguous watermark steps over them instead of waiting at
    the first one for ever. `nonce` (security on): the signed reply must carry it."""
    body: dict = {"device": device}
    if gone_below is not None:
        body["gone_below"] = int(gone_below)
    if nonce is not None:
        body["nonce"] = nonce
    return json.dumps(body).encode() if len(body) > 1 else None


def parse_received_query(payload: bytes | None, device: str) -> tuple[int | None, str | None]:
    """(gone_below, nonce) of an agent's question on `received`, each None when it carries none (a question without
    a payload: what agents asked before either); WireError when it is not one."""
    if not payload:
        return None, None
    try:
        body = json.loads(payload)
        seq, nonce = body.get("gone_below"), body.get("nonce")
        if (
            body["device"] != device
            or not {"device"} < set(body) <= {"device", "gone_below", "nonce"}
            or ("gone_below" in body and not _count(seq))
            or ("nonce" in body and not (isinstance(nonce, str) and NONCE_RE.fullmatch(nonce)))
        ):
            raise TypeError
    except (ValueError, KeyError, TypeError, AttributeError, RecursionError):
        raise WireError("schema", f"not a received question for {device}: {bytes(payload)[:200]!r}") from None
    return seq, nonce


def parse_watermark_reply(payload: bytes, device: str, *, verifier=None, nonce: str | None = None) -> tuple[int, int]:
    """(contiguous_seq, acked_version) of a watermark reply for `device` (acked_version 0 from services that
    do not send it); WireError when it is not one. With `verifier` (fleet_wire.security.SetVerifier, security on)
    also 'unsigned' or 'bad_signature' unless the service signed it, and 'wrong_nonce' unless it answers the
    question asked with `nonce` (a reply recorded earlier, or for another drive, is not this question's)."""
    try:
        body = json.loads(payload)
        seq, acked = body["contiguous_seq"], body.get("acked_version", 0)
        if body["device"] != device or not all(_count(v) for v in (seq, acked)):
            raise TypeError
    except (ValueError, KeyError, TypeError, AttributeError, RecursionError):
        raise WireError("schema", f"not a watermark reply for {device}: {bytes(payload)[:200]!r}") from None
    if verifier is not None:
        what = f"watermark reply for {device} (contiguous_seq {seq})"
        verifier.verify(body, what)
        if body.get("nonce") != nonce:
            raise WireError("wrong_nonce", f"{what}: signed for another question, not the one just asked (replayed?)")
    return seq, acked


def says_retired(payload: bytes) -> bool:
    """Whether a watermark reply (checked by parse_watermark_reply first) says the drive is retired."""
    return json.loads(payload).get("retired") is True


def parse_resume_point(payload: bytes, device: str) -> tuple[int, float] | None:
    """(max_seq, last_window_end) of a watermark reply for `device`, None when it names none (no window stored,
    or a service that does not send them); WireError when it is not a watermark reply."""
    parse_watermark_reply(payload, device)
    body = json.loads(payload)
    seq, end = body.get("max_seq"), body.get("last_window_end")
    if seq is None and end is None:
        return None
    bad_end = isinstance(end, bool) or not isinstance(end, (int, float)) or not 0 <= end <= MAX_TIME_S
    if not _count(seq) or bad_end:  # past the windows' own time bound, every window moved after it would be refused
        raise WireError("schema", f"a watermark reply for {device} with a bad resume point: {bytes(payload)[:200]!r}")
    return seq, float(end)


def parse_watermark(payload: bytes, device: str) -> int:
    """The contiguous_seq of a watermark reply for `device`; WireError when it is not one."""
    return parse_watermark_reply(payload, device)[0]


def _count(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and 0 <= value <= MAX_INT
