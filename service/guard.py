"""The service's own checks on what arrives over Zenoh, behind the router's access control (defence in depth
for a router whose ACL is stale, misconfigured or absent):

- a message's device (its key, and the message's "device", which the wire decoder matches to the key) must
  be a device of the registry: the only identities the router can have authenticated. On a router with the
  generated ACL a certificate may put only on its own keys, so key device == certificate common name.
  (The Python API does not hand a subscriber the sender's certificate, so the key is where the
  authenticated identity shows.)
- an ack must be for a version the service made for that device (else: forged), and each
  (device, version, status) is taken once: the same ack again is the agent's resend (agents resend acks until
  the watermark confirms them; the store drops it as a duplicate), another one is replayed.
"""

from __future__ import annotations

import threading

from fleet_wire import keys
from fleet_wire import messages as wire

from .store import Store

ACK_MEMORY = 100_000  # (device, version, status) remembered in memory, beside the acks table


class IngestGuard:
    def __init__(self, store: Store, devices: list[str] | None):
        self.store = store
        self.devices = None if devices is None else set(devices)
        self._acks: dict[tuple[str, int, str], float] = {}  # -> the drive time the ack was sent at
        self._lock = threading.Lock()

    def refuse(self, key_expr: str, payload: bytes) -> tuple[str, str] | None:
        """(reason, detail) if the message must not be taken; None lets it through to the usual decoding."""
        parsed = keys.split(key_expr)
        if parsed is None:
            return None  # the decoder dead-letters malformed keys with its own reason
        device, suffix = parsed
        if self.devices is not None and device not in self.devices:
            return "unknown_device", f"{key_expr}: {device!r} holds no certificate of this fleet's registry"
        if suffix == keys.ACK:
            return self._check_ack(device, payload)
        return None

    def _check_ack(self, device: str, payload: bytes) -> tuple[str, str] | None:
        # the wire's own checks first: an ack they refuse is the decoder's to refuse and count, and must leave no mark
        # here (a malformed ack once poisoned the replay memory, and the genuine one after it was refused as
        # replayed; a version past any SQLite INTEGER made the look-up below raise)
        try:
            msg = wire.decode("ack", payload, key_device=device)
        except wire.WireError:
            return None
        version, status = msg["version"], msg["status"]
        # a set the service made (stored before it is put: an agent's ack may beat mark_published)
        if version < 1 or self.store.coefficient_set(device, version) is None:
            return "forged_ack", f"ack from {device} for version {version}, which the service never published to it"
        mark, at = (device, version, status), msg.get("at")
        with self._lock:
            taken = self._acks.get(mark)
            if taken is None:
                taken = next(
                    (a["at"] for a in self.store.acks(device) if a["version"] == version and a["status"] == status),
                    None,
                )
            if taken is not None and taken != at:
                return "replayed_ack", f"ack from {device} for version {version} ({status}) was already taken"
            if len(self._acks) >= ACK_MEMORY:
                self._acks.clear()  # the acks table still remembers; this dict only covers the ingest queue
            self._acks[mark] = at
        return None

    def admits(self, device: str) -> bool:
        return self.devices is None or device in self.devices


def router_security(pki, *, listen: list[str] | None, connect: list[str] | None, mesh: list[str] | None = None):
    """(identity, access control) of the service's Zenoh session: (None, None) when insecure. Every endpoint
    must be TLS when a PKI is given (a tcp/ listener would take clients without a certificate). An embedded
    router meshed with others connects to them as the service (their access control lets it through)."""
    if pki is None:
        return None, None
    from fleet_wire.security import (
        ROLE_SERVICE,
        SERVICE_NAME,
        Identity,
        SecurityError,
        access_control,
        plain_endpoints,
        registry_names,
    )

    plain = plain_endpoints(connect or [*(listen or []), *(mesh or [])])
    if plain:
        raise SecurityError(f"with --pki every endpoint must be tls/HOST:PORT, not {', '.join(plain)}")
    identity = Identity.load(pki, SERVICE_NAME, ROLE_SERVICE)
    return identity, None if connect else access_control(registry_names(pki))


def service_security(store: Store, pki) -> dict:
    """FleetService's signer and guard for a PKI folder (none when insecure)."""
    if pki is None:
        return {}
    from fleet_wire.security import SetSigner, registry

    return {"signer": SetSigner.load(pki), "guard": IngestGuard(store, registry(pki))}
