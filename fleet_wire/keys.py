"""Every Zenoh key of the fleet, written once: `encoders/<device>/<suffix>`.

| suffix       | what                                   | who puts / answers           |
|--------------|----------------------------------------|------------------------------|
| stats        | a window of statistics                 | agent → service              |
| ack          | an applied or refused coefficient set  | agent → service              |
| factory      | the agent's factory set (version 0)    | agent → service, once        |
| coefficients | a coefficient set; also a queryable    | service → agent              |
| received     | the delivery watermark (a queryable)   | service answers the agent    |
| alive        | the agent's liveliness token           | agent                        |
| alarms       | a drift alarm raised or cleared        | service → anyone listening   |
"""

from __future__ import annotations

import re

PREFIX = "encoders"
STATS, ACK, FACTORY, COEFFICIENTS, RECEIVED, ALIVE = "stats", "ack", "factory", "coefficients", "received", "alive"
ALARMS = "alarms"
SUFFIXES = (STATS, ACK, FACTORY, COEFFICIENTS, RECEIVED, ALIVE, ALARMS)
# a Zenoh key segment that is no wildcard and no path trick: '.', '..' and '-' are not devices
DEVICE_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")


def key(device: str, suffix: str) -> str:
    """`encoders/<device>/<suffix>`."""
    return f"{PREFIX}/{device}/{suffix}"


def every(suffix: str) -> str:
    """The key expression matching `suffix` of every device (what the service subscribes to)."""
    return f"{PREFIX}/*/{suffix}"


def split(key_expr) -> tuple[str, str] | None:
    """`encoders/<device>/<suffix>` -> (device, suffix) for a well-formed device id; None otherwise."""
    parts = str(key_expr).split("/")
    if len(parts) != 3 or parts[0] != PREFIX or not DEVICE_RE.match(parts[1]):
        return None
    return parts[1], parts[2]
