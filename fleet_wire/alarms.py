"""Alarm messages on `encoders/<device>/alarms` (service → anyone listening): schemas/alarm.schema.json.

Kept beside messages.py rather than in it: the alarm is what GET /alarms lists, plus its schema and the
event (raised or cleared), JSON like the REST answer.
"""

from __future__ import annotations

import json
from functools import cache
from importlib import resources

from jsonschema import Draft202012Validator

from . import keys

SCHEMA_NAME = "encoder-fleet/alarm/1"
FIELDS = ("id", "device", "cause", "parameters", "evidence", "raised_at", "cleared_at")


@cache
def _validator() -> Draft202012Validator:
    schema = json.loads(resources.files("fleet_wire.schemas").joinpath("alarm.schema.json").read_bytes())
    Draft202012Validator.check_schema(schema)
    return Draft202012Validator(schema)


def alarm_message(alarm: dict) -> dict:
    """An alarm as GET /alarms lists it -> the message published for it (checked against the schema)."""
    msg = {
        "schema": SCHEMA_NAME,
        "event": "raised" if alarm["cleared_at"] is None else "cleared",
        **{k: alarm[k] for k in FIELDS},
    }
    _validator().validate(msg)
    return msg


def encode(alarm: dict) -> tuple[str, bytes]:
    """(key, payload) to put for an alarm."""
    msg = alarm_message(alarm)
    return keys.key(alarm["device"], keys.ALARMS), json.dumps(msg, separators=(",", ":"), allow_nan=False).encode()


def decode(payload: bytes) -> dict:
    msg = json.loads(payload)
    _validator().validate(msg)
    return msg
