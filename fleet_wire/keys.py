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

What an agent sends to the service carries the device's partition as a last chunk,
`encoders/<device>/<suffix>/p<NN>` (stats, ack, factory, received, alive): a stable hash of the device id
into PARTITIONS, so that each of several service processes subscribes to its own partitions and receives
only its devices' messages (service/cluster.py). A coefficient set (published, or asked for by an agent
that starts: any service process answers it from the shared history) and an alarm keep
`encoders/<device>/<suffix>`. Watch every window with `encoders/*/stats/*`.
"""

from __future__ import annotations

import hashlib
import re
from functools import lru_cache

PREFIX = "encoders"
STATS, ACK, FACTORY, COEFFICIENTS, RECEIVED, ALIVE = "stats", "ack", "factory", "coefficients", "received", "alive"
ALARMS = "alarms"
SUFFIXES = (STATS, ACK, FACTORY, COEFFICIENTS, RECEIVED, ALIVE, ALARMS)
TO_SERVICE = (STATS, ACK, FACTORY, RECEIVED, ALIVE)  # partitioned: what only the device's own process takes
# fixed for the life of a fleet (agents compute it): the most service processes that can share the work
PARTITIONS = 64
# liveliness tokens of the running service processes (`_` never begins a device id)
SERVICES = f"{PREFIX}/_services"
# a Zenoh key segment that is no wildcard and no path trick: '.', '..' and '-' are not devices
DEVICE_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")


def key(device: str, suffix: str) -> str:
    """`encoders/<device>/<suffix>`, with `/p<NN>` (the device's partition) for an agent-to-service suffix."""
    plain = f"{PREFIX}/{device}/{suffix}"
    return f"{plain}/{partition_chunk(partition(device))}" if suffix in TO_SERVICE else plain


@lru_cache(maxsize=1 << 16)  # every window's key is checked against it: a fleet's ids, hashed once each
def partition(device: str) -> int:
    """The device's partition: a hash that is the same in every process, on every machine, forever."""
    return int.from_bytes(hashlib.blake2b(device.encode(), digest_size=8).digest(), "big") % PARTITIONS


def partition_chunk(number: int) -> str:
    return f"p{number:02d}"


def every(suffix: str, part: int | None = None) -> str:
    """The key expression matching `suffix` of every device; for an agent-to-service suffix, of every device
    in partition `part` (None: of all partitions)."""
    if suffix not in TO_SERVICE:
        return f"{PREFIX}/*/{suffix}"
    return f"{PREFIX}/*/{suffix}/{'*' if part is None else partition_chunk(part)}"


def every_to_service(part: int | None = None) -> str:
    """The key expression matching every agent-to-service key (TO_SERVICE, any suffix) of every device in partition
    `part` (None: of all partitions): one subscriber then sees a device's windows and acks in the order sent."""
    return f"{PREFIX}/*/*/{'*' if part is None else partition_chunk(part)}"


def split(key_expr) -> tuple[str, str] | None:
    """A fleet key -> (device, suffix) for a well-formed device id whose agent-to-service keys carry its own
    partition (and only those); None otherwise."""
    parts = str(key_expr).split("/")
    if len(parts) not in (3, 4) or parts[0] != PREFIX or not DEVICE_RE.fullmatch(parts[1]):
        return None
    device, suffix = parts[1], parts[2]
    if (len(parts) == 4) != (suffix in TO_SERVICE):
        return None
    if len(parts) == 4 and parts[3] != partition_chunk(partition(device)):
        return None
    return device, suffix
