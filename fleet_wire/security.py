"""The security model on the wire (docs/architecture.md, "Security model"), written once for both sides.

- Identity: mutual TLS. Every agent and the service present a certificate issued by the fleet's CA
  (`encoder-fleet pki`); a device's id is its certificate's common name, its role the certificate's
  organizational unit ("device", "service" or "router"). A device certificate issued again (replaced, or after
  a revocation) names its generation, `NAME#N`: the router admits exactly the common name of the certificate in
  the folder, so an earlier one (stolen with its drive) stays refused. There is no CRL to do it otherwise.
- Access control: the router's `access_control` config, default deny, generated from the device registry
  (the device certificates in the PKI folder) by `access_control()`: a device speaks only on its own keys,
  only the service puts coefficients and answers queries.
- Coefficient sets are signed by the service (Ed25519 over `canonical()` of the set without its
  "signature") and verified by the agent with the public key from provisioning (`signing.pub`). So are the
  watermark replies on `received`, each bound to its question (the device, and the nonce the agent asked with).

The PKI folder (contract): ca.crt, ca.key, NAME.crt + NAME.key per device, service.crt + service.key,
signing.key (the service's Ed25519 key) and signing.pub (what the agents verify with).
"""

from __future__ import annotations

import base64
import binascii
import json
from dataclasses import dataclass
from pathlib import Path

from encoder_core.samples import InputError

from . import keys

ROLE_DEVICE, ROLE_SERVICE, ROLE_ROUTER = "device", "service", "router"
SERVICE_NAME = "service"
CA_NAME = "ca"
SIGNING_KEY, SIGNING_PUB = "signing.key", "signing.pub"
RESERVED_NAMES = {CA_NAME, SERVICE_NAME, "signing"}  # file names in the PKI folder no device may take
GENERATION_SEP = "#"  # `drive-7#2`: drive-7's certificate of generation 2 ('#' is in no device id)


class SecurityError(InputError):
    """A PKI folder or a certificate that cannot be used; one line that says which file and why."""


# --- certificates ---------------------------------------------------------------------------------


def plain_endpoints(endpoints) -> list[str]:
    """The endpoints that are not TLS: a fleet's router takes none (a tcp/, udp/, ws/ ... listener takes clients
    without a certificate, in plain text, and a mesh link over one has no certificate for the peer's ACL)."""
    return [str(e) for e in endpoints if not str(e).startswith("tls/")]


def certificate_identity(path: Path) -> tuple[str, str]:
    """(common name, role) of a PEM certificate; role is its organizational unit ('' if none)."""
    from cryptography import x509
    from cryptography.x509.oid import NameOID

    try:
        cert = x509.load_pem_x509_certificate(Path(path).read_bytes())
    except (OSError, ValueError) as exc:
        raise SecurityError(f"{path}: not a readable PEM certificate: {exc}") from None
    cn = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    ou = cert.subject.get_attributes_for_oid(NameOID.ORGANIZATIONAL_UNIT_NAME)
    return (str(cn[0].value) if cn else "", str(ou[0].value) if ou else "")


def device_of(cn: str) -> str:
    """The device id a certificate's common name stands for: `NAME` and `NAME#N` (its generation N) are NAME."""
    name, sep, generation = cn.partition(GENERATION_SEP)
    return name if not sep or generation.isdigit() else cn


def registry_names(pki_dir: Path) -> dict[str, str]:
    """The device registry: device id -> the common name of its certificate in the PKI folder (the only one the
    router admits for it)."""
    found = {}
    for path in sorted(Path(pki_dir).glob("*.crt")):
        if path.stem in RESERVED_NAMES:
            continue
        cn, role = certificate_identity(path)
        if role == ROLE_DEVICE and device_of(cn) == path.stem and keys.DEVICE_RE.fullmatch(path.stem):
            found[path.stem] = cn
    return found


def registry(pki_dir: Path) -> list[str]:
    """The device registry: ids of the devices whose certificates are issued into the PKI folder."""
    return list(registry_names(pki_dir))


@dataclass(frozen=True)
class Identity:
    """Who this process is in the fleet's PKI: its certificate and key, and the CA it trusts."""

    pki_dir: Path
    name: str  # certificate common name: a device id, "service", or a router's name

    @property
    def ca(self) -> Path:
        return self.pki_dir / f"{CA_NAME}.crt"

    @property
    def cert(self) -> Path:
        return self.pki_dir / f"{self.name}.crt"

    @property
    def key(self) -> Path:
        return self.pki_dir / f"{self.name}.key"

    @classmethod
    def load(cls, pki_dir, name: str, role: str) -> Identity:
        """Check that the folder holds the CA and `name`'s certificate and key, issued for `role`."""
        ident = cls(Path(pki_dir), name)
        for path in (ident.ca, ident.cert, ident.key):
            if not path.is_file():
                raise SecurityError(
                    f"--pki {pki_dir}: {path.name} is missing (encoder-fleet pki init / pki issue make it)"
                )
        cn, got_role = certificate_identity(ident.cert)
        if device_of(cn) != name or got_role != role:
            raise SecurityError(
                f"{ident.cert}: issued to {cn!r} as {got_role or 'no role'!r}, not {name!r} as {role!r}"
            )
        return ident

    def tls(self, *, listen: bool, connect: bool) -> dict[str, object]:
        """Zenoh config entries (path -> value) for TLS with mutual authentication."""
        base = "transport/link/tls/"
        entries: dict[str, object] = {base + "root_ca_certificate": str(self.ca), base + "enable_mtls": True}
        if listen:
            entries[base + "listen_private_key"] = str(self.key)
            entries[base + "listen_certificate"] = str(self.cert)
        if connect:
            entries[base + "connect_private_key"] = str(self.key)
            entries[base + "connect_certificate"] = str(self.cert)
            entries[base + "verify_name_on_connect"] = True  # the router's certificate names its host
        return entries


# --- access control -------------------------------------------------------------------------------


def device_rules(device: str) -> list[dict]:
    """What one device may do on the router: its own keys only."""
    own = lambda suffix: keys.key(device, suffix)  # noqa: E731
    rule = lambda name, messages, flow, exprs: {  # noqa: E731
        "id": f"{device}/{name}",
        "messages": messages,
        "flows": [flow],
        "permission": "allow",
        "key_exprs": exprs,
    }
    return [
        rule("put", ["put"], "ingress", [own(keys.STATS), own(keys.FACTORY), own(keys.ACK)]),
        rule("alive", ["liveliness_token"], "ingress", [own(keys.ALIVE)]),
        rule("query", ["query"], "ingress", [own(keys.COEFFICIENTS), own(keys.RECEIVED)]),
        rule("reply", ["reply"], "egress", [own(keys.COEFFICIENTS), own(keys.RECEIVED)]),
        rule("subscribe", ["declare_subscriber"], "ingress", [own(keys.COEFFICIENTS)]),
        rule("receive", ["put"], "egress", [own(keys.COEFFICIENTS)]),
    ]


SERVICE_MESSAGES = [
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "declare_queryable",
    "reply",
    "liveliness_token",
    "declare_liveliness_subscriber",
    "liveliness_query",
]


def access_control(devices, service: str = SERVICE_NAME, routers: list[str] = ()) -> dict:
    """The router's `access_control` config, default deny, generated from the device registry.

    devices: device ids (each admitted by the common name equal to it), or {device id: certificate common name}
    (`registry_names`: a re-issued device is admitted by its current certificate's name only, `NAME#N`).

    The service is a subject too (it needs rules when it is a client of an external router, as in compose);
    an embedded router's own session is not filtered. `routers`: the certificate names of the routers this one
    is meshed with, trusted as the service is (the fleet's traffic crosses their links both ways). Zenoh key
    expressions cannot refer to the subject's common name, so there is one subject and one policy per device."""
    rules = [
        {
            "id": f"{service}/all",
            "messages": SERVICE_MESSAGES,
            "flows": ["ingress", "egress"],
            "permission": "allow",
            "key_exprs": [f"{keys.PREFIX}/**"],
        }
    ]
    subjects = [{"id": service, "cert_common_names": [service, *routers]}]
    policies = [{"id": f"{service}/policy", "rules": [f"{service}/all"], "subjects": [service]}]
    names = dict(devices) if isinstance(devices, dict) else {d: d for d in devices}
    for device in sorted(names):
        if not keys.DEVICE_RE.fullmatch(device) or device in RESERVED_NAMES or device_of(names[device]) != device:
            raise SecurityError(f"device {device!r} cannot have access rules: not a valid device id")
        own = device_rules(device)
        rules += own
        subjects.append({"id": device, "cert_common_names": [names[device]]})
        policies.append({"id": f"{device}/policy", "rules": [r["id"] for r in own], "subjects": [device]})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


# --- signed coefficient sets ----------------------------------------------------------------------


def canonical(msg: dict) -> bytes:
    """The bytes a signature covers: the message without "signature", JSON with sorted keys, no spaces,
    ASCII only (floats as Python's shortest round-trip repr)."""
    body = {k: v for k, v in msg.items() if k != "signature"}
    return json.dumps(body, sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=False).encode()


class SetSigner:
    """The service's side: adds "signature" to a coefficient set, or to a watermark reply."""

    def __init__(self, private_key):
        self._key = private_key

    @classmethod
    def load(cls, pki_dir) -> SetSigner:
        from cryptography.hazmat.primitives import serialization
        from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

        path = Path(pki_dir) / SIGNING_KEY
        try:
            key = serialization.load_pem_private_key(path.read_bytes(), password=None)
        except (OSError, ValueError) as exc:
            raise SecurityError(f"{path}: no signing key ({exc}); `pki issue DIR --service` makes it") from None
        if not isinstance(key, Ed25519PrivateKey):
            raise SecurityError(f"{path}: not an Ed25519 private key")
        return cls(key)

    def sign(self, msg: dict) -> dict:
        signature = self._key.sign(canonical(msg))
        return {**msg, "signature": base64.b64encode(signature).decode("ascii")}


class SetVerifier:
    """The agent's side: refuses a set (version >= 1) that is unsigned or whose signature does not verify."""

    def __init__(self, public_key):
        self._key = public_key

    @classmethod
    def load(cls, pki_dir) -> SetVerifier:
        from cryptography.hazmat.primitives import serialization
        from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey

        path = Path(pki_dir) / SIGNING_PUB
        try:
            key = serialization.load_pem_public_key(path.read_bytes())
        except (OSError, ValueError) as exc:
            raise SecurityError(f"{path}: no service public key ({exc}); provisioning copies it from the PKI") from None
        if not isinstance(key, Ed25519PublicKey):
            raise SecurityError(f"{path}: not an Ed25519 public key")
        return cls(key)

    def verify(self, msg: dict, what: str | None = None) -> None:
        """WireError('unsigned' | 'bad_signature') unless the message (a set; `what` names another kind) carries
        the service's valid signature."""
        from cryptography.exceptions import InvalidSignature

        from .messages import WireError  # here, not at the top: `encoder-fleet diagnose` loads no wire code

        what = what or f"coefficient set {msg.get('version')}"
        signature = msg.get("signature")
        if not signature:
            raise WireError("unsigned", f"{what}: not signed by the service")
        try:  # TypeError: a signature that is no string (a set's schema says string, a watermark reply has none)
            raw = base64.b64decode(signature, validate=True)
            self._key.verify(raw, canonical(msg))
        except (binascii.Error, ValueError, TypeError, InvalidSignature):
            raise WireError("bad_signature", f"{what}: signature does not verify (tampered?)") from None
