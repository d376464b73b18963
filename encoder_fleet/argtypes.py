"""Argument types for the CLI: a bad value is refused by argparse in one line (see cli.OneLineParser)."""

from __future__ import annotations

import argparse
import math

from fleet_wire.keys import DEVICE_RE


def finite_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
    return value


def positive_float(text: str) -> float:
    value = finite_float(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"{text} must be greater than 0")
    return value


def non_negative_float(text: str) -> float:
    value = finite_float(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"{text} must be 0 or more")
    return value


def _integer(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None


def positive_int(text: str) -> int:
    value = _integer(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"{text} must be 1 or more")
    return value


def non_negative_int(text: str) -> int:
    value = _integer(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"{text} must be 0 or more")
    return value


def port(text: str) -> int:
    value = _integer(text)
    if not 0 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"{text} is not a TCP port (0-65535)")
    return value


def device_name(text: str) -> str:
    if not DEVICE_RE.fullmatch(text):
        raise argparse.ArgumentTypeError(
            f"{text!r} is not a device id: a letter or digit, then up to 63 letters, digits, '_', '.' or '-'"
        )
    return text


def member_name(text: str) -> str:
    if not DEVICE_RE.fullmatch(text):  # the same shape: it is one chunk of a Zenoh key
        raise argparse.ArgumentTypeError(
            f"{text!r} is not a member name: a letter or digit, then up to 63 letters, digits, '_', '.' or '-'"
        )
    return text


def label_pair(text: str) -> str:
    """NAME=VALUE, a device label (the service checks the rules: service/labels.py)."""
    if "=" not in text:
        raise argparse.ArgumentTypeError(f"{text!r} is not NAME=VALUE (a label, e.g. site=plant-3)")
    return text


def label_dict(pairs: list[str] | None, option: str) -> dict[str, str]:
    """label_pair's NAME=VALUE as {NAME: VALUE}; InputError for a name given two values: the last one won unsaid
    (`rollout create --label site=plant-3 --label site=plant-7` rolled out to plant-7 alone)."""
    from encoder_core.samples import InputError  # here: the parser loads no numpy

    labels: dict[str, str] = {}
    for name, value in (pair.split("=", 1) for pair in pairs or []):
        if labels.setdefault(name, value) != value:
            raise InputError(f"{option}: {name} given twice ({labels[name]!r} and {value!r}): a drive carries one")
    return labels


def label_name(text: str) -> str:
    """A device label's name (`status --by site`), by the service's rule."""
    from service.labels import NAME_RE, NAME_RULE  # at parse time, only for the commands that take one

    if not NAME_RE.fullmatch(text):
        raise argparse.ArgumentTypeError(f"{text!r} is not a label name: {NAME_RULE}")
    return text
