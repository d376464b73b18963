"""The fleet's PKI, on the cryptography package: a CA, a certificate per device, one for the service (and one
per external router), the service's Ed25519 key that signs coefficient sets. Private keys are written 0600.

    encoder-fleet pki init DIR                 -> DIR/ca.crt, DIR/ca.key
    encoder-fleet pki issue DIR NAME           -> DIR/NAME.crt, DIR/NAME.key       (a device; CN = NAME, NAME#N again)
    encoder-fleet pki issue DIR --service      -> DIR/service.crt, DIR/service.key, DIR/signing.key, DIR/signing.pub
    encoder-fleet pki issue DIR --router NAME  -> DIR/NAME.crt, DIR/NAME.key       (an external router, e.g. zenohd)
    encoder-fleet pki router-config DIR ...    -> a zenohd config: TLS, mTLS, the ACL of the registry, mesh links

A certificate's role (device, service, router) is its organizational unit; the device registry is the set
of device certificates in DIR (fleet_wire.security.registry). DIR/issued-devices.txt keeps every device
certificate ever issued (name, generation, serial): a device issued again (`--force`, or after its NAME.crt was
removed to revoke it) gets the common name NAME#N of a new generation N, and the router admits only the
common name of NAME.crt, so the certificates issued before it (a stolen drive's) stay refused.
"""

from __future__ import annotations

import datetime
import ipaddress
import json
import os
from pathlib import Path

from encoder_fleet.outputs import write_file
from fleet_wire import keys
from fleet_wire.security import (
    CA_NAME,
    GENERATION_SEP,
    RESERVED_NAMES,
    ROLE_DEVICE,
    ROLE_ROUTER,
    ROLE_SERVICE,
    SERVICE_NAME,
    SIGNING_KEY,
    SIGNING_PUB,
    SecurityError,
    access_control,
    certificate_identity,
    plain_endpoints,
    registry,
    registry_names,
)

CA_DAYS = 3650
LEAF_DAYS = 825
LOCAL_HOSTS = ("localhost", "127.0.0.1", "::1")
ISSUED = "issued-devices.txt"  # every device certificate issued: "NAME GENERATION SERIAL", one a line
MAX_CN = 64  # X.509's upper bound on a common name


def _generations(pki_dir: Path) -> dict[str, int]:
    """The newest generation issued of each device, from the folder's ledger."""
    newest: dict[str, int] = {}
    try:
        lines = (pki_dir / ISSUED).read_text(encoding="utf-8").splitlines()
    except FileNotFoundError:
        return newest
    for line in lines:
        parts = line.split()
        if len(parts) >= 2 and parts[1].isdigit():
            newest[parts[0]] = max(newest.get(parts[0], -1), int(parts[1]))
    return newest


def _device_common_name(pki_dir: Path, name: str) -> tuple[str, int]:
    """(common name, generation) of a new certificate for device `name`: NAME the first time, NAME#N once any
    certificate was issued for it before (the ledger says so, or a NAME.crt of a folder older than the ledger):
    every certificate of an earlier generation then names another subject than the one the router admits."""
    before = _generations(pki_dir).get(name)
    if before is None and (pki_dir / f"{name}.crt").exists():
        before = 0
    generation = 0 if before is None else before + 1
    cn = name if generation == 0 else f"{name}{GENERATION_SEP}{generation}"
    if len(cn) > MAX_CN:
        raise SecurityError(
            f"device {name!r}: generation {generation}'s common name {cn!r} is longer than {MAX_CN} characters; "
            "a device id this long cannot be issued again (give the drive a new id, or make a new CA)"
        )
    return cn, generation


def _write(path: Path, data: bytes, *, private: bool) -> None:
    """Write a file; a private key is created 0600 from the start (never readable by others, not even briefly)."""
    write_file(path, data, perms=0o600 if private else 0o644)


def _pem_private(key) -> bytes:
    from cryptography.hazmat.primitives import serialization

    return key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )


def _pem_cert(cert) -> bytes:
    from cryptography.hazmat.primitives import serialization

    return cert.public_bytes(serialization.Encoding.PEM)


def _name(cn: str, role: str | None = None):
    from cryptography import x509
    from cryptography.x509.oid import NameOID

    attrs = [x509.NameAttribute(NameOID.ORGANIZATION_NAME, "encoder-fleet")]
    if role:
        attrs.append(x509.NameAttribute(NameOID.ORGANIZATIONAL_UNIT_NAME, role))
    attrs.append(x509.NameAttribute(NameOID.COMMON_NAME, cn))
    return x509.Name(attrs)


def _key_usage(*, ca: bool):
    from cryptography import x509

    return x509.KeyUsage(
        digital_signature=True,
        content_commitment=False,
        key_encipherment=False,
        data_encipherment=False,
        key_agreement=False,
        key_cert_sign=ca,
        crl_sign=ca,
        encipher_only=False,
        decipher_only=False,
    )


def init_ca(pki_dir, *, force: bool = False) -> Path:
    """A new CA in pki_dir (ECDSA P-256). Refuses to overwrite one unless force."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.hazmat.primitives.asymmetric import ec

    pki_dir = Path(pki_dir)
    if (pki_dir / f"{CA_NAME}.key").exists() and not force:
        raise SecurityError(f"{pki_dir} already holds a CA ({CA_NAME}.key); use another folder or --force")
    pki_dir.mkdir(parents=True, exist_ok=True)
    os.chmod(pki_dir, 0o700)
    key = ec.generate_private_key(ec.SECP256R1())
    now = datetime.datetime.now(datetime.UTC)
    name = _name("encoder-fleet CA")
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=CA_DAYS))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(_key_usage(ca=True), critical=True)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
    _write(pki_dir / f"{CA_NAME}.key", _pem_private(key), private=True)
    _write(pki_dir / f"{CA_NAME}.crt", _pem_cert(cert), private=False)
    return pki_dir / f"{CA_NAME}.crt"


def _load_ca(pki_dir: Path):
    from cryptography import x509
    from cryptography.hazmat.primitives import serialization

    try:
        cert = x509.load_pem_x509_certificate((pki_dir / f"{CA_NAME}.crt").read_bytes())
        key = serialization.load_pem_private_key((pki_dir / f"{CA_NAME}.key").read_bytes(), password=None)
    except (OSError, ValueError) as exc:
        raise SecurityError(f"{pki_dir}: no usable CA ({exc}); run `encoder-fleet pki init {pki_dir}` first") from None
    return cert, key


def _san(hosts) -> list:
    from cryptography import x509

    names = []
    for host in dict.fromkeys(hosts):
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(host)))
        except ValueError:
            names.append(x509.DNSName(host))
    return names


def issue(pki_dir, name: str, role: str = ROLE_DEVICE, *, hosts: tuple[str, ...] = (), force: bool = False) -> Path:
    """A key and a certificate for `name` signed by the CA in pki_dir. Devices authenticate as clients;
    the service and routers also serve TLS, so they get server names (localhost and `hosts`)."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID

    pki_dir = Path(pki_dir)
    if role == ROLE_DEVICE and (not keys.DEVICE_RE.fullmatch(name) or name in RESERVED_NAMES):
        raise SecurityError(
            f"device {name!r}: a device id is 1-64 of A-Z a-z 0-9 _ . - and not one of {sorted(RESERVED_NAMES)}"
        )
    if role == ROLE_ROUTER and (not keys.DEVICE_RE.fullmatch(name) or name in RESERVED_NAMES):
        raise SecurityError(f"router {name!r}: not a usable name")
    crt = pki_dir / f"{name}.crt"
    if crt.exists() and not force:
        cn, old_role = certificate_identity(crt)
        raise SecurityError(f"{crt} already exists (issued to {cn!r} as {old_role!r}); use --force to replace it")
    ca_cert, ca_key = _load_ca(pki_dir)
    cn, generation = _device_common_name(pki_dir, name) if role == ROLE_DEVICE else (name, None)
    key = ec.generate_private_key(ec.SECP256R1())
    now = datetime.datetime.now(datetime.UTC)
    server = role in (ROLE_SERVICE, ROLE_ROUTER)
    usages = [ExtendedKeyUsageOID.CLIENT_AUTH] + ([ExtendedKeyUsageOID.SERVER_AUTH] if server else [])
    serial = x509.random_serial_number()
    builder = (
        x509.CertificateBuilder()
        .subject_name(_name(cn, role))
        .issuer_name(ca_cert.subject)
        .public_key(key.public_key())
        .serial_number(serial)
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(min(now + datetime.timedelta(days=LEAF_DAYS), ca_cert.not_valid_after_utc))
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(_key_usage(ca=False), critical=True)
        .add_extension(x509.ExtendedKeyUsage(usages), critical=False)
        .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
    )
    if server:
        builder = builder.add_extension(x509.SubjectAlternativeName(_san((*LOCAL_HOSTS, *hosts))), critical=False)
    cert = builder.sign(ca_key, hashes.SHA256())
    _write(pki_dir / f"{name}.key", _pem_private(key), private=True)
    if generation is not None:  # in the ledger before the certificate is in the folder: no generation is used twice
        ledger = pki_dir / ISSUED
        old = ledger.read_text(encoding="utf-8") if ledger.exists() else ""
        write_file(ledger, old + f"{name} {generation} {serial:x}\n", perms=0o644)
    _write(crt, _pem_cert(cert), private=False)
    if role == ROLE_SERVICE:
        _signing_key(pki_dir, force=force)
    return crt


def _signing_key(pki_dir: Path, *, force: bool) -> None:
    """The service's Ed25519 key for coefficient sets (signing.key, 0600) and its public half (signing.pub),
    which provisioning gives every agent. Kept if it exists (agents already trust it) unless force."""
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

    if (pki_dir / SIGNING_KEY).exists() and (pki_dir / SIGNING_PUB).exists() and not force:
        return
    key = Ed25519PrivateKey.generate()
    public = key.public_key().public_bytes(serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo)
    _write(pki_dir / SIGNING_KEY, _pem_private(key), private=True)
    _write(pki_dir / SIGNING_PUB, public, private=False)


def router_config(
    pki_dir,
    name: str,
    *,
    listen: list[str],
    container_dir: str | None = None,
    connect: list[str] = (),
    peers: list[str] = (),
) -> dict:
    """A zenohd configuration: TLS with mutual authentication on `listen`, and the access control generated
    from the registry. container_dir: where zenohd sees pki_dir (paths in the config are zenohd's).
    Meshed routers: `connect` to other routers (with this router's certificate); `peers`, the certificate names
    of the routers meshed with this one either way, whom its access control trusts as it trusts the service."""
    # TLS only, as the service's own router (service.guard.router_security)
    for option, endpoints in (("--listen", listen), ("--connect", connect)):
        plain = plain_endpoints(endpoints)
        if plain:
            raise SecurityError(
                f"router-config {option} {plain[0]}: not TLS; every endpoint of the fleet's router is "
                "tls/HOST:PORT (mutual TLS: the certificates and the ACL)"
            )
    pki_dir = Path(pki_dir)
    where = Path(container_dir) if container_dir else pki_dir.resolve()
    tls = {
        "root_ca_certificate": str(where / f"{CA_NAME}.crt"),
        "listen_private_key": str(where / f"{name}.key"),
        "listen_certificate": str(where / f"{name}.crt"),
        "enable_mtls": True,
    }
    conf = {
        "mode": "router",
        "listen": {"endpoints": listen},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": {"link": {"tls": tls}},
        "access_control": access_control(registry_names(pki_dir), routers=list(peers)),
    }
    if connect:
        conf["connect"] = {"endpoints": list(connect)}
        tls.update(
            connect_private_key=str(where / f"{name}.key"),
            connect_certificate=str(where / f"{name}.crt"),
            verify_name_on_connect=True,
        )
    return conf


# --- the command --------------------------------------------------------------------------------------


def cmd_pki(args) -> int:
    if args.pki_command == "init":
        init_ca(args.dir, force=args.force)
        print(f"CA written: {Path(args.dir) / 'ca.crt'} (its key ca.key is 0600: keep it offline)")
        return 0
    if args.pki_command == "issue":
        chosen = [bool(args.name), args.service, bool(args.router)]
        if sum(chosen) != 1:
            raise SecurityError("pki issue: give exactly one of NAME (a device), --service or --router NAME")
        if args.service:
            crt = issue(args.dir, SERVICE_NAME, ROLE_SERVICE, hosts=tuple(args.host or ()), force=args.force)
            print(f"service certificate: {crt}; coefficient sets signed with {Path(args.dir) / SIGNING_KEY}")
            print(f"agents verify with {Path(args.dir) / SIGNING_PUB} (copy it to each drive with ca.crt)")
        elif args.router:
            crt = issue(args.dir, args.router, ROLE_ROUTER, hosts=tuple(args.host or ()), force=args.force)
            print(f"router certificate: {crt}")
        else:
            crt = issue(args.dir, args.name, ROLE_DEVICE, force=args.force)
            cn, _ = certificate_identity(crt)
            again = "" if cn == args.name else " (issued again: the certificates before it are refused)"
            print(f"device certificate: {crt} (CN {cn}{again}); restart the service so its router admits it")
        return 0
    if args.pki_command == "router-config":
        conf = router_config(
            args.dir,
            args.name,
            listen=args.listen or ["tls/0.0.0.0:7447"],
            container_dir=args.as_dir,
            connect=args.connect or [],
            peers=args.peer or [],
        )
        text = json.dumps(conf, indent=1)
        if args.out:
            write_file(args.out, text + "\n")
            print(f"wrote {args.out}: {len(registry(args.dir))} devices admitted")
        else:
            print(text)
        return 0
    raise SecurityError(f"unknown pki command {args.pki_command!r}")


def register(sub) -> None:
    p = sub.add_parser("pki", help="the fleet's certificates: a CA, devices, the service (TLS, ACL, signatures)")
    pki_sub = p.add_subparsers(dest="pki_command", required=True)
    q = pki_sub.add_parser("init", help="a new CA in DIR (DIR/ca.crt, DIR/ca.key)")
    q.add_argument("dir", help="the PKI folder (created 0700)")
    q.add_argument("--force", action="store_true", help="replace an existing CA (every certificate must be reissued)")
    q = pki_sub.add_parser("issue", help="a key and certificate: a device (NAME), the service, or a router")
    q.add_argument("dir", help="the PKI folder holding the CA")
    q.add_argument("name", nargs="?", help="device id (the certificate's common name)")
    q.add_argument("--service", action="store_true", help="the service: service.crt/.key and the signing key")
    q.add_argument("--router", metavar="NAME", help="an external router (zenohd in compose)")
    q.add_argument("--host", action="append", help="a host name or address the service or router is reached at")
    q.add_argument("--force", action="store_true", help="replace an existing certificate")
    q = pki_sub.add_parser("router-config", help="a zenohd config: TLS, mTLS and the ACL of the device registry")
    q.add_argument("dir", help="the PKI folder (its device certificates are the registry)")
    q.add_argument("--name", default="zenohd", help="the router's certificate name (pki issue DIR --router NAME)")
    q.add_argument("--listen", action="append", metavar="ENDPOINT", help="default tls/0.0.0.0:7447")
    q.add_argument("--as-dir", help="the folder as zenohd sees it (e.g. /pki in a container)")
    q.add_argument("--connect", action="append", metavar="ENDPOINT", help="mesh: connect to this router too")
    q.add_argument(
        "--peer", action="append", metavar="NAME", help="mesh: a router certificate name to trust as the service"
    )
    q.add_argument("--out", help="write here instead of stdout")
    p.set_defaults(func=cmd_pki)
