"""Device labels (migration 100): `name=value` pairs an operator gives a drive, such as site=plant-3 or line=7. A
fleet of thousands is read by them (GET /devices?label=site=plant-3, GET /fleet/health?label=...) and changed by
them (a rollout to the drives that carry them). The rules here are the REST API's and the command line's."""

from __future__ import annotations

import re

MAX_LABELS = 16  # per device
# both used with fullmatch: match() and "$" let a name or value end in a newline (a second line in `devices list`)
NAME_RE = re.compile(r"[a-z][a-z0-9_-]{0,31}")
# one line of text an operator reads, with no "=" (a selector is NAME=VALUE) nor "," (a list of them); spaces inside
VALUE_RE = re.compile(r"[^\x00-\x1f\x7f-\x9f=, ](?:[^\x00-\x1f\x7f-\x9f=,]{0,62}[^\x00-\x1f\x7f-\x9f=, ])?")
NAME_RULE = "a lower-case letter, then up to 31 lower-case letters, digits, '_' or '-'"
VALUE_RULE = "1 to 64 characters of one line, no '=' or ',', not beginning or ending with a space"


def check_labels(labels: dict[str, str]) -> dict[str, str]:
    """The labels as given, or ValueError saying which one breaks which rule."""
    if len(labels) > MAX_LABELS:
        raise ValueError(f"at most {MAX_LABELS} labels a device, not {len(labels)}")
    for name, value in labels.items():
        if not isinstance(name, str) or not NAME_RE.fullmatch(name):
            raise ValueError(f"label name {name!r}: {NAME_RULE}")
        if not isinstance(value, str) or not VALUE_RE.fullmatch(value):
            raise ValueError(f"label {name}={value!r}: a value is {VALUE_RULE}")
    return labels


def parse_selector(text: str) -> tuple[str, str]:
    """NAME=VALUE (a `label` query parameter, a command's argument) as (name, value), or ValueError."""
    name, sep, value = text.partition("=")
    if not sep:
        raise ValueError(f"{text!r} is not NAME=VALUE")
    check_labels({name: value})
    return name, value


def parse_selectors(texts: list[str] | None) -> dict[str, str]:
    """Several NAME=VALUE, all of which a device must carry; ValueError for a bad one, a name given twice, or more
    names than a device carries."""
    selected: dict[str, str] = {}
    for text in texts or []:
        name, value = parse_selector(text)
        if name in selected and selected[name] != value:
            raise ValueError(f"label {name} selected twice ({selected[name]!r} and {value!r}): no device has both")
        selected[name] = value
    # no device carries more; past 1000 (a term of the query each) SQLite refused the query, a 500
    if len(selected) > MAX_LABELS:
        raise ValueError(f"at most {MAX_LABELS} labels selected (a device carries no more), not {len(selected)}")
    return selected
