"""Issue 10 with the real router: mutual TLS, the access control generated from the registry, signed coefficient
sets and watermark replies, the service's own checks, REST tokens. Each attack here worked before the security model
(a plain client could connect, speak for any device, publish sets and answer the watermark)."""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys
import time

import httpx2 as httpx
import pytest
import wire_samples as ws
import zenoh
from fastapi.testclient import TestClient

from edge_agent.agent import EdgeAgent
from edge_agent.outbox import Outbox
from edge_agent.sources import SimulatedDrive, drive_model, factory_calibration
from fleet_wire import keys
from fleet_wire import messages as wire
from fleet_wire.security import ROLE_DEVICE, Identity, SetSigner, SetVerifier, access_control, canonical, registry
from fleet_wire.session import free_port, loopback_endpoint, session_config
from service.api import create_app
from service.auth import TokenAuth
from service.guard import service_security
from service.runtime import FleetService, open_session
from service.store import Store

A, B = "drive-a", "drive-b"


def wait_for(predicate, timeout=20.0):  # returns as soon as it holds; long for a loaded machine
    deadline = time.monotonic() + timeout
    while not predicate() and time.monotonic() < deadline:
        time.sleep(0.05)
    return predicate()


class Secured:
    """The service with its embedded router (TLS, mTLS, ACL, signer, guard) and clients by certificate."""

    def __init__(self, tmp_path, pki):
        self.pki = pki
        self.endpoint = loopback_endpoint().replace("tcp/", "tls/")
        self.store = Store.open(tmp_path / "fleet.sqlite")
        self.router = open_session(listen=[self.endpoint], pki=pki)
        self.service = FleetService(self.store, self.router, refit_interval_s=0, **service_security(self.store, pki))
        self.service.start()
        self.sessions = []

    def client(self, name, pki=None):
        identity = Identity.load(pki or self.pki, name, ROLE_DEVICE)
        session = zenoh.open(session_config("client", connect=[self.endpoint], identity=identity))
        self.sessions.append(session)
        return session

    def publish(self, msg: dict) -> dict:
        """What the service does for a new set: sign, store, mark published, put."""
        signed = self.service.signer.sign(msg)
        self.store.insert_coefficient_set(signed)
        self.store.mark_published(msg["device"], msg["version"])
        self.router.put(keys.key(msg["device"], keys.COEFFICIENTS), wire.encode("coefficients", signed))
        return signed

    def close(self):
        for session in self.sessions:
            session.close()
        self.service.stop()
        self.router.close()
        self.store.close()


@pytest.fixture
def secured(tmp_path, pki):
    s = Secured(tmp_path, pki)
    yield s
    s.close()


# --- who may connect ------------------------------------------------------------------------------


def test_a_client_without_a_fleet_certificate_cannot_connect(secured, foreign_pki):
    no_cert = session_config("client", connect=[secured.endpoint])
    no_cert.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(secured.pki / "ca.crt")))
    with pytest.raises(zenoh.ZError):
        zenoh.open(no_cert)
    plain_tcp = session_config("client", connect=[secured.endpoint.replace("tls/", "tcp/")])
    with pytest.raises(zenoh.ZError):
        zenoh.open(plain_tcp)
    with pytest.raises(zenoh.ZError):  # a certificate named drive-a, from the attacker's own CA
        secured.client(A, pki=foreign_pki)
    secured.client(A)  # the real drive-a connects


def test_the_acl_is_generated_from_the_registry(pki):
    acl = access_control(registry(pki))
    assert acl["default_permission"] == "deny"
    subjects = {s["id"]: s["cert_common_names"] for s in acl["subjects"]}
    assert subjects["drive-a"] == ["drive-a"] and "drive-t" in subjects and subjects["service"] == ["service"]
    exprs = {k for r in acl["rules"] if r["id"].startswith("drive-a/") for k in r["key_exprs"]}
    part = keys.partition_chunk(keys.partition("drive-a"))
    assert exprs == {f"encoders/drive-a/{s}/{part}" for s in ("stats", "factory", "ack", "alive", "received")} | {
        "encoders/drive-a/coefficients"
    }
    puts = [r for r in acl["rules"] if r["id"].startswith("drive-a/") and "put" in r["messages"]]
    assert {f for r in puts if "ingress" in r["flows"] for f in r["key_exprs"]} == {
        f"encoders/drive-a/stats/{part}",
        f"encoders/drive-a/factory/{part}",
        f"encoders/drive-a/ack/{part}",
    }


def test_a_stolen_device_certificate_stays_refused_once_its_drive_is_issued_again(tmp_path):
    """The drive's key is stolen; the operator replaces its certificate (`pki issue --force`), or revokes it (removes
    NAME.crt, restarts) and later provisions the drive again under its id. Each time the new certificate speaks for
    the drive and the stolen one speaks for nothing: before, both carried the common name the router admits."""
    import shutil

    from conftest import make_pki

    from encoder_fleet.pki import issue
    from fleet_wire.security import certificate_identity

    pki = make_pki(tmp_path / "pki", [A])
    stolen = tmp_path / "stolen"
    stolen.mkdir()
    for name in ("ca.crt", f"{A}.crt", f"{A}.key"):
        shutil.copy(pki / name, stolen / name)

    def stored_by(seq, folders):
        (tmp_path / f"run{seq}").mkdir()
        s = Secured(tmp_path / f"run{seq}", pki)
        try:
            for i, folder in enumerate(folders):
                s.client(A, pki=folder).put(keys.key(A, keys.STATS), wire.encode("window", ws.window(A, seq + i)))
            seqs = lambda: {w["seq"] for w in s.store.windows(A)}  # noqa: E731
            wait_for(lambda: seq + len(folders) - 1 in seqs(), timeout=10)  # the last folder's is the drive's
            time.sleep(0.5)
            return [i for i in range(len(folders)) if seq + i in seqs()]
        finally:
            s.close()

    assert stored_by(1, [stolen]) == [0]  # the attack: while its certificate is the drive's, it is the drive
    issue(pki, A, force=True)  # replaced
    assert stored_by(10, [stolen, pki]) == [1]  # before: [0, 1], the stolen certificate still spoke for the drive
    assert certificate_identity(pki / f"{A}.crt") == (f"{A}#1", "device")
    assert Identity.load(pki, A, ROLE_DEVICE).name == A
    (pki / f"{A}.crt").unlink()  # revoked
    (pki / f"{A}.key").unlink()
    assert registry(pki) == []
    issue(pki, A)  # the drive provisioned again under its id
    assert stored_by(20, [stolen, pki]) == [1]
    assert certificate_identity(pki / f"{A}.crt") == (f"{A}#2", "device")
    from fleet_wire.security import registry_names

    acl = access_control(registry_names(pki))
    assert {s["id"]: s["cert_common_names"] for s in acl["subjects"]}[A] == [f"{A}#2"]


# --- a device speaks only for itself ----------------------------------------------------------------


def test_device_a_cannot_put_b_stats(secured):
    a = secured.client(A)
    time.sleep(0.2)
    for seq in range(1, 6):  # the pre-load attack: B's seqs taken before B speaks
        a.put(keys.key(B, keys.STATS), wire.encode("window", ws.window(B, seq)))
    a.put(keys.key(A, keys.STATS), wire.encode("window", ws.window(A, 1)))
    assert wait_for(lambda: (secured.store.device(A) or {}).get("windows") == 1)
    time.sleep(0.3)
    assert secured.store.device(B) is None
    assert secured.store.rejection_counts() == {}  # stopped at the router, not even a dead letter


def test_device_a_cannot_hold_b_liveliness_token(secured):
    a = secured.client(A)
    held = [a.liveliness().declare_token(keys.key(d, keys.ALIVE)) for d in (B, A)]  # undeclared when dropped
    a.put(keys.key(A, keys.STATS), wire.encode("window", ws.window(A, 1)))  # a device appears when it speaks
    assert wait_for(lambda: (secured.store.device(A) or {}).get("online"))
    assert secured.store.device(B) is None
    del held


def test_device_a_cannot_put_any_coefficients(secured):
    a, b, a_again = secured.client(A), secured.client(B), secured.client(A)
    got_b, got_a = [], []
    b.declare_subscriber(keys.key(B, keys.COEFFICIENTS), lambda s: got_b.append(json.loads(s.payload.to_bytes())))
    a_again.declare_subscriber(keys.key(A, keys.COEFFICIENTS), lambda s: got_a.append(s.payload.to_bytes()))
    time.sleep(0.3)
    evil = ws.coefficients(B, version=2**53 - 1)
    evil["bands"][0]["zero_offset_rad"] = 3.0
    a.put(keys.key(B, keys.COEFFICIENTS), wire.encode("coefficients", evil))
    a.put(keys.key(A, keys.COEFFICIENTS), wire.encode("coefficients", ws.coefficients(A, version=2**53 - 1)))
    time.sleep(0.3)
    secured.publish(ws.coefficients(B, version=1))
    assert wait_for(lambda: got_b)
    time.sleep(0.2)
    assert [m["version"] for m in got_b] == [1] and got_a == []  # only the service's set arrived


def test_device_a_cannot_subscribe_to_b_coefficients(secured):
    a, b = secured.client(A), secured.client(B)
    seen_by_a, seen_by_b = [], []
    a.declare_subscriber(keys.key(B, keys.COEFFICIENTS), lambda s: seen_by_a.append(1))
    a.declare_subscriber("encoders/**", lambda s: seen_by_a.append(2))
    b.declare_subscriber(keys.key(B, keys.COEFFICIENTS), lambda s: seen_by_b.append(1))
    time.sleep(0.3)
    secured.publish(ws.coefficients(B, version=1))
    assert wait_for(lambda: seen_by_b)
    time.sleep(0.2)
    assert seen_by_a == []


def test_device_a_cannot_answer_the_watermark_or_the_coefficients_query(secured):
    a, b, a_agent = secured.client(A), secured.client(B), secured.client(A)  # a_agent: drive-a's real agent
    lie = lambda q: q.reply(q.key_expr, wire.watermark_reply(str(q.key_expr).split("/")[1], 10**9))  # noqa: E731
    for expr in (keys.key(B, keys.RECEIVED), keys.key(A, keys.RECEIVED), keys.every(keys.RECEIVED)):
        a.declare_queryable(expr, lie)
    a.declare_queryable(keys.every(keys.COEFFICIENTS), lambda q: q.reply(q.key_expr, b"{}"))
    time.sleep(0.3)
    for session, device in ((b, B), (a_agent, A)):
        replies = [r.ok.payload.to_bytes() for r in session.get(keys.key(device, keys.RECEIVED), timeout=1.0) if r.ok]
        assert [wire.parse_watermark(p, device) for p in replies] == [0]  # the service's answer only
        assert [r for r in session.get(keys.key(device, keys.COEFFICIENTS), timeout=0.5) if r.ok] == []


def test_a_device_cannot_query_another_devices_keys(secured):
    secured.publish(ws.coefficients(B, version=1))
    a = secured.client(A)
    assert [r for r in a.get(keys.key(B, keys.COEFFICIENTS), timeout=0.5) if r.ok] == []
    assert [r for r in a.get(keys.key(B, keys.RECEIVED), timeout=0.5) if r.ok] == []


# --- signed coefficient sets ----------------------------------------------------------------------


def make_agent(secured, session, tmp_path, device=A):
    seed = 3
    return EdgeAgent(
        device,
        SimulatedDrive(seed, hours=1),
        session,
        Outbox(tmp_path / f"{device}.outbox"),
        factory_calibration(drive_model(seed), seed),
        verifier=SetVerifier.load(secured.pki),
    )


def plausible_set(agent, version):
    from edge_agent.agent import factory_message

    return {**factory_message(agent.device, agent.factory), "version": version, "basis": "fit", "created_at": 60.0}


def test_agent_refuses_sets_not_signed_by_the_service(secured, foreign_pki, tmp_path):
    """Defence in depth: what the router's own session (a router or path that is not trusted) delivers."""
    agent = make_agent(secured, secured.client(A), tmp_path)
    agent.start()
    assert wait_for(lambda: secured.store.current_coefficients(A) is not None)  # its factory set, announced
    forged = SetSigner.load(foreign_pki).sign(plausible_set(agent, 5))
    unsigned = plausible_set(agent, 6)
    tampered = secured.service.signer.sign(plausible_set(agent, 7))
    tampered["bands"][0]["zero_offset_rad"] = 3.0
    for msg in (forged, unsigned, tampered):
        secured.router.put(keys.key(A, keys.COEFFICIENTS), wire.encode("coefficients", msg))
    secured.publish(plausible_set(agent, 8))
    assert wait_for(lambda: agent.inbox.qsize() >= 4)
    agent.apply_inbox()
    assert agent.version == 8 and agent.counters.applied == [8]
    assert agent.counters.bad_signatures == 3
    reasons = dict(agent.counters.refused)
    assert "does not verify" in reasons[5] and "not signed" in reasons[6] and "does not verify" in reasons[7]
    agent.step()  # acknowledges 8 with the quality it sees
    assert wait_for(lambda: any(a["version"] == 8 for a in secured.store.acks(A)))
    # the rejections were acknowledged, and the service refused those acks: it never published 5, 6, 7
    assert wait_for(lambda: secured.store.rejection_counts().get("forged_ack") == 3)
    agent.close()


def test_agent_does_not_resume_with_an_unsigned_saved_set(secured, tmp_path):
    agent = make_agent(secured, secured.client(A), tmp_path)
    agent.outbox.save_coefficients(wire.encode("coefficients", plausible_set(agent, 2**53 - 1)))  # the old attack
    agent.outbox.close()
    again = make_agent(secured, secured.client(A), tmp_path)
    assert again.version == 0 and again.counters.bad_signatures == 1


def test_signature_is_over_the_canonical_set():
    signer_key = __import__("cryptography.hazmat.primitives.asymmetric.ed25519", fromlist=["x"]).Ed25519PrivateKey
    key = signer_key.generate()
    signer, verifier = SetSigner(key), SetVerifier(key.public_key())
    msg = signer.sign(ws.coefficients(A, version=3))
    round_trip = wire.decode("coefficients", wire.encode("coefficients", msg), key_device=A)
    verifier.verify(round_trip)
    assert canonical(round_trip) == canonical({k: v for k, v in msg.items() if k != "signature"})
    for change in ({"version": 4}, {"device": B}, {"created_at": 1.0}):
        with pytest.raises(wire.WireError):
            verifier.verify({**round_trip, **change})


# --- signed watermark replies ----------------------------------------------------------------------


class RouterOnly:
    """A secure router with no service behind drive-a's `received`: what answers there is the test's queryable, on
    the router's own session, which the ACL does not filter (a meshed router whose key was stolen: its certificate
    is trusted as the service's, and the ACL lets it answer any question)."""

    def __init__(self, pki):
        self.pki = pki
        self.endpoint = loopback_endpoint().replace("tcp/", "tls/")
        self.router = open_session(listen=[self.endpoint], pki=pki)
        self.answer = lambda nonce: None  # the reply's body for the question's nonce (None: no reply)
        self.asked = []
        self.router.declare_queryable(keys.key(A, keys.RECEIVED), self._on_query)
        self.sessions = []

    def _on_query(self, query):
        payload = query.payload.to_bytes() if query.payload is not None else b""
        nonce = json.loads(payload).get("nonce") if payload else None  # by hand: agents before nonces send none
        self.asked.append(nonce)
        body = self.answer(nonce)
        if body is not None:
            query.reply(query.key_expr, json.dumps(body).encode())

    def client(self, name):
        identity = Identity.load(self.pki, name, ROLE_DEVICE)
        session = zenoh.open(session_config("client", connect=[self.endpoint], identity=identity))
        self.sessions.append(session)
        return session

    def close(self):
        for session in self.sessions:
            session.close()
        self.router.close()


def test_agent_keeps_its_windows_on_a_forged_unsigned_or_replayed_watermark_reply(pki, foreign_pki, tmp_path, caplog):
    """The watermark reply tells the agent which windows it may drop from its outbox. It was unsigned, and whoever
    may answer a question (the service's policy in the ACL: the service and its meshed routers) could forge one; a
    meshed router's stolen key answered drive-a with a watermark of 10**9 and the agent dropped windows the service
    never stored. Now the service signs each reply, with the nonce of the question it answers: forged, unsigned,
    tampered, another drive's, or a genuine one recorded for an earlier question (after an outbox lost and
    renumbered, its higher watermark drops windows never stored) are refused, counted and logged, and the outbox
    keeps everything; the service's reply to this question still trims it."""
    import logging

    service_key, foreign_key = SetSigner.load(pki), SetSigner.load(foreign_pki)

    def body(nonce, seq, device=A):  # what wire.watermark_reply says for a question with a nonce, before signing
        return {"device": device, "contiguous_seq": seq, "acked_version": 0, "nonce": nonce}

    r = RouterOnly(pki)
    try:
        r.answer = lambda nonce: service_key.sign(body(nonce, 0))  # the service, which has nothing of drive-a yet
        agent = make_agent(r, r.client(A), tmp_path)
        agent.start()
        assert agent.resumed
        for _ in range(3):
            assert agent.step()
        assert len(agent.outbox) == 3
        recorded = service_key.sign(body(r.asked[-1], 10**9))  # as if the service had said so to an earlier question

        def tampered(nonce):
            genuine = service_key.sign(body(nonce, 0))
            return {**genuine, "contiguous_seq": 10**9}

        forged = {
            "signed by another key": lambda nonce: foreign_key.sign(body(nonce, 10**9)),
            "unsigned": lambda nonce: body(nonce, 10**9),
            "tampered": tampered,
            "recorded for another question": lambda nonce: recorded,
            "another drive's": lambda nonce: service_key.sign(body(nonce, 10**9, device=B)),
            "a signature that is no string": lambda nonce: {**body(nonce, 10**9), "signature": 7},
        }
        offline = agent.counters.offline_syncs
        with caplog.at_level(logging.WARNING, logger="edge_agent"):
            for what, answer in forged.items():
                r.answer = answer
                synced = agent.sync()
                assert len(agent.outbox) == 3 and agent.watermark == 0, what  # before: emptied, watermark 10**9
                assert not synced and agent.counters.offline_syncs == offline + 1, what  # as with no reply
                offline += 1
        assert agent.counters.refused_watermarks == {"bad_signature": 3, "unsigned": 1, "wrong_nonce": 1, "schema": 1}
        assert "refused a watermark reply, the outbox keeps its windows" in caplog.text
        assert "not signed by the service (a service before signed watermark replies? upgrade it)" in caplog.text
        assert "signed for another question" in caplog.text
        assert len(set(r.asked)) == len(r.asked) and None not in r.asked  # a fresh nonce at every question
        r.answer = lambda nonce: service_key.sign(body(nonce, 2))
        assert agent.sync()
        assert len(agent.outbox) == 1 and agent.watermark == 2
        agent.close()
    finally:
        r.close()


def test_a_forged_or_replayed_retired_reply_silences_no_secured_agent(pki, foreign_pki, tmp_path):
    """`retired` in a watermark reply stops an agent sending (docs/wire.md): only the service's reply, signed for
    the question just asked, may say it. Unsigned, signed by another key, added to a genuine reply, or a genuine
    `retired` recorded for an earlier question: refused, and the agent goes on as before; the service's own says it."""
    service_key, foreign_key = SetSigner.load(pki), SetSigner.load(foreign_pki)

    def body(nonce, retired=True):
        return {
            "device": A,
            "contiguous_seq": 0,
            "acked_version": 0,
            "nonce": nonce,
            **({"retired": True} if retired else {}),
        }

    r = RouterOnly(pki)
    try:
        r.answer = lambda nonce: service_key.sign(body(nonce, retired=False))
        agent = make_agent(r, r.client(A), tmp_path)
        agent.start()
        assert agent.resumed and not agent.retired
        recorded = service_key.sign(body(r.asked[-1]))  # the service's, for a question asked before
        forged = {
            "unsigned": lambda nonce: body(nonce),
            "signed by another key": lambda nonce: foreign_key.sign(body(nonce)),
            "added to a genuine reply": lambda nonce: {**service_key.sign(body(nonce, retired=False)), "retired": True},
            "recorded for another question": lambda nonce: recorded,
        }
        for what, answer in forged.items():
            r.answer = answer
            assert not agent.sync() and not agent.retired, what
            assert agent.step() and not agent.retired, what
        # each refused twice: at the sync, and at the step's after its window went out
        assert agent.counters.refused_watermarks == {"unsigned": 2, "bad_signature": 4, "wrong_nonce": 2}
        r.answer = lambda nonce: service_key.sign(body(nonce))
        assert agent.sync() and agent.retired
        agent.close()
    finally:
        r.close()


@pytest.mark.parametrize("forged_first", [True, False])
def test_a_forged_watermark_reply_beside_the_genuine_one_hides_it_not(pki, tmp_path, forged_first):
    """Two answers to one question, the service's and a forged one on the same key: the agent hears both, refuses
    the forged and takes the genuine. Zenoh's default keeps the latest reply per key, so the forged one, sent after
    the genuine, hid it and the agent could not sync at all while the stolen key answered."""
    service_key = SetSigner.load(pki)

    def body(nonce, seq):
        return {"device": A, "contiguous_seq": seq, "acked_version": 0, "nonce": nonce}

    r = RouterOnly(pki)

    def genuine(nonce):
        return service_key.sign(body(nonce, 2))

    def forge(query):
        nonce = json.loads(query.payload.to_bytes()).get("nonce")
        query.reply(query.key_expr, json.dumps(body(nonce, 10**9)).encode())  # unsigned

    r.answer = lambda nonce: None
    forger = None
    try:
        if forged_first:
            forger = r.router.declare_queryable(keys.key(A, keys.RECEIVED), forge)
        agent = make_agent(r, r.client(A), tmp_path)
        r.answer = genuine
        if not forged_first:
            forger = r.router.declare_queryable(keys.key(A, keys.RECEIVED), forge)
        agent.start()
        for _ in range(3):
            assert agent.step()
        assert agent.sync()
        assert len(agent.outbox) == 1 and agent.watermark == 2
        assert agent.counters.refused_watermarks.get("unsigned", 0) >= 1
        agent.close()
    finally:
        if forger is not None:
            forger.undeclare()
        r.close()


def test_the_service_signs_its_watermark_reply_for_the_question_and_the_agent_takes_it(secured, tmp_path):
    """The service's side: its reply carries the question's nonce and its signature over the reply (the signing key
    of its sets, `fleet_wire.security.canonical`), so an agent that checks takes it and drops what it stored."""
    agent = make_agent(secured, secured.client(A), tmp_path)
    agent.start()
    for _ in range(3):
        assert agent.step()
    assert wait_for(lambda: secured.store.contiguous_seq(A) == 3)
    nonce = "0123456789abcdef" * 2
    question = json.dumps({"device": A, "nonce": nonce}).encode()
    replies = secured.client(A).get(agent.keys["received"], payload=question, timeout=2.0)
    (reply,) = [r.ok.payload.to_bytes() for r in replies if r.ok]
    body = json.loads(reply)
    assert body.get("nonce") == nonce and body["contiguous_seq"] == 3  # before: no nonce, no signature
    SetVerifier.load(secured.pki).verify(body, "watermark reply")
    assert wire.parse_watermark_reply(reply, A, verifier=SetVerifier.load(secured.pki), nonce=nonce) == (3, 0)
    assert secured.store.rejection_counts() == {}  # before: the question with a nonce was dead-lettered as schema
    assert agent.sync() and len(agent.outbox) == 0 and agent.watermark == 3
    assert agent.counters.refused_watermarks == {} and agent.counters.offline_syncs == 0
    agent.close()


# --- the service checks too ------------------------------------------------------------------------


def test_service_refuses_forged_replayed_and_unregistered_messages(secured):
    """Through the router's own session, i.e. as if an external router's ACL let them pass."""
    put = lambda key, msg, kind: secured.router.put(key, wire.encode(kind, msg))  # noqa: E731
    put(keys.key(A, keys.ACK), ws.ack(A, version=9), "ack")  # never published
    secured.publish(ws.coefficients(A, version=1))
    put(keys.key(A, keys.ACK), ws.ack(A, version=1), "ack")
    put(keys.key(A, keys.ACK), ws.ack(A, version=1), "ack")  # the same ack again: the agent's resend
    put(keys.key(A, keys.ACK), ws.ack(A, version=1, at=999.0), "ack")  # another one for the same verdict
    put(keys.key("drive-zz", keys.STATS), ws.window("drive-zz", 1), "window")  # no certificate in the registry
    put(keys.key("drive-zz", keys.FACTORY), {**ws.coefficients("drive-zz", 0), "basis": "factory"}, "coefficients")
    expected = {"forged_ack": 1, "replayed_ack": 1, "unknown_device": 2}
    assert wait_for(lambda: secured.store.rejection_counts() == expected), secured.store.rejection_counts()
    assert [a["version"] for a in secured.store.acks(A)] == [1]
    assert secured.store.device("drive-zz") is None
    assert {k: secured.service.counters.ingested.get(k) for k in expected} == expected
    assert secured.service.counters.ingested.get("duplicate") == 1


# --- REST tokens ------------------------------------------------------------------------------------


@pytest.fixture
def rest(tmp_path):
    store = Store.open(tmp_path / "rest.sqlite")
    auth = TokenAuth(store)
    _, read = auth.create("read", "reader")
    _, admin = auth.create("admin", "admin")
    yield TestClient(create_app(store, auth=auth)), read, admin, auth
    store.close()


def test_rest_needs_a_token_everywhere_but_healthz_and_the_page_shell(rest):
    client, read, admin, _ = rest
    ids = {"{device_id}": "drive-a", "{token_id}": "1", "{rollout_id}": "1"}
    routes = []
    for path, operations in client.app.openapi()["paths"].items():
        for name, value in ids.items():
            path = path.replace(name, value)
        routes += [(method.upper(), path) for method in operations]
    paths = {path for _, path in routes}
    assert "/healthz" in paths and "/metrics" in paths and "/tokens" in paths and "/rollouts" in paths
    for method, path in routes:
        if path in ("/healthz", "/"):  # liveness, and the fleet page's HTML shell (its data needs a token)
            assert client.get(path).status_code == 200
            continue
        for headers in ({}, {"Authorization": "Bearer nope"}, {"Authorization": f"Basic {read}"}):
            response = client.request(method, path, headers=headers)
            assert response.status_code == 401, (path, headers, response.text)
            assert response.headers["www-authenticate"] == "Bearer"
    assert client.get("/static/plotly.min.js").status_code == 200  # the page's code loads without a token
    good = {"Authorization": f"Bearer {read}"}
    assert client.get("/devices", headers=good).status_code == 200
    assert client.get("/metrics", headers=good).status_code == 200
    assert client.get("/readyz", headers=good).status_code == 200


def test_read_token_on_an_admin_endpoint_is_403(rest):
    client, read, admin, auth = rest
    as_reader, as_admin = {"Authorization": f"Bearer {read}"}, {"Authorization": f"Bearer {admin}"}
    assert client.get("/tokens", headers=as_reader).status_code == 403
    assert client.post("/tokens", json={"scope": "admin"}, headers=as_reader).status_code == 403
    assert client.delete("/tokens/1", headers=as_reader).status_code == 403
    listed = client.get("/tokens", headers=as_admin).json()
    assert {t["name"] for t in listed} == {"reader", "admin"} and read not in json.dumps(listed)
    created = client.post("/tokens", json={"scope": "read", "name": "grafana"}, headers=as_admin)
    assert created.status_code == 201 and created.json()["token"].startswith("efr_")
    assert client.get("/devices", headers={"Authorization": f"Bearer {created.json()['token']}"}).status_code == 200
    assert client.delete(f"/tokens/{created.json()['id']}", headers=as_admin).status_code == 204
    assert client.get("/devices", headers={"Authorization": f"Bearer {created.json()['token']}"}).status_code == 401


@pytest.mark.parametrize("name", ["ops\nadmin", "\x1b[2Jwiped", "nul\x00", "x" * 201])
def test_a_token_name_is_one_line_of_text_on_rest_and_the_command_line(rest, tmp_path, name):
    """A token's name is shown as who acknowledged an alarm or retired a drive (`alarms list`, `devices show`, the
    fleet page): an escape sequence in it reached the operator's terminal. Refused on REST (422) and by `token
    create` (one line, exit 2), and no token is made."""
    client, _, admin, auth = rest
    before = len(auth.tokens())
    refused = client.post("/tokens", json={"scope": "read", "name": name}, headers={"Authorization": f"Bearer {admin}"})
    assert refused.status_code == 422, refused.text
    if "\x00" in name:
        return  # no command line can carry a NUL
    db = tmp_path / "fleet.sqlite"
    cmd = [sys.executable, "-m", "encoder_fleet.cli", "token", "create", "--scope", "read", "--name", name]
    done = subprocess.run([*cmd, "--db", str(db), "--create-db"], capture_output=True, text=True)
    assert done.returncode == 2 and "--name" in done.stderr and len(done.stderr.strip().splitlines()) == 1
    assert not done.stdout and not db.exists() and len(auth.tokens()) == before


def test_tokens_are_stored_hashed_and_never_logged(tmp_path, pki):
    db, token_file, http_port = tmp_path / "fleet.sqlite", tmp_path / "secrets" / "admin-token", free_port()
    command = [sys.executable, "-m", "encoder_fleet.cli", "service", "--db", str(db), "--pki", str(pki)]
    command += ["--listen", f"tls/127.0.0.1:{free_port()}", "--http-port", str(http_port)]
    command += ["--admin-token-file", str(token_file), "--log-level", "debug"]
    service = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    tokens = []
    try:
        first, second = service.stdout.readline(), service.stdout.readline()
        assert first.startswith("service: zenoh router on tls/") and str(token_file) in second, (first, second)
        assert stat.S_IMODE(os.stat(token_file).st_mode) == 0o600
        admin = token_file.read_text().strip()
        made = subprocess.run(
            [sys.executable, "-m", "encoder_fleet.cli", "token", "create", "--scope", "read", "--db", str(db)],
            capture_output=True,
            text=True,
        )
        read = made.stdout.splitlines()[0]
        tokens = [admin, read]
        base = f"http://127.0.0.1:{http_port}"
        with httpx.Client(base_url=base, timeout=10) as http:
            assert http.get("/devices", headers={"Authorization": f"Bearer {read}"}).status_code == 200
            assert http.get("/tokens", headers={"Authorization": f"Bearer {read}"}).status_code == 403
            assert http.get("/devices", headers={"Authorization": f"Bearer {read}x"}).status_code == 401
            assert http.get(f"/devices?token={read}").status_code == 401  # refused there, and not logged (below)
            assert http.get("/docs").status_code == 200 and http.get("/redoc").status_code == 200  # no data
            new = http.post("/tokens", json={"scope": "read"}, headers={"Authorization": f"Bearer {admin}"})
            tokens.append(new.json()["token"])
            assert http.get("/metrics", headers={"Authorization": f"Bearer {tokens[-1]}"}).status_code == 200
    finally:
        service.terminate()
        out, err = service.communicate(timeout=30)
    assert service.returncode == 0, err
    assert '"GET /devices HTTP/1.1" 200' in err or "/devices" in err  # the requests were logged ...
    for token in tokens:  # ... the tokens were not, and the database keeps only their hashes
        assert token not in out and token not in err
        assert token.encode() not in db.read_bytes()


def test_zenohd_config_from_pki_router_config_admits_the_service_and_confines_devices(tmp_path, pki):
    """compose's setup, with the Python package's router standing in for zenohd (same zenoh 1.10.2): the config
    of `encoder-fleet pki router-config`, the service as its client, a device confined to its own keys."""
    from encoder_fleet.pki import issue, router_config
    from fleet_wire.security import ROLE_ROUTER

    issue(pki, "zenohd-test", ROLE_ROUTER, force=True)
    endpoint = loopback_endpoint().replace("tcp/", "tls/")
    conf = router_config(pki, "zenohd-test", listen=[endpoint])
    router = zenoh.open(zenoh.Config.from_json5(json.dumps(conf)))
    store = Store.open(tmp_path / "fleet.sqlite")
    service_session = open_session(connect=[endpoint], pki=pki)
    service = FleetService(store, service_session, refit_interval_s=0, **service_security(store, pki)).start()
    a = zenoh.open(session_config("client", connect=[endpoint], identity=Identity.load(pki, A, ROLE_DEVICE)))
    b = zenoh.open(session_config("client", connect=[endpoint], identity=Identity.load(pki, B, ROLE_DEVICE)))
    try:
        # drive A's stolen key answers B's watermark question high: B's agent would drop windows never stored
        a.declare_queryable(keys.key(B, keys.RECEIVED), lambda q: q.reply(q.key_expr, wire.watermark_reply(B, 10**9)))
        time.sleep(0.3)
        a.put(keys.key(B, keys.STATS), wire.encode("window", ws.window(B, 1)))
        a.put(keys.key(A, keys.STATS), wire.encode("window", ws.window(A, 1)))
        assert wait_for(lambda: (store.device(A) or {}).get("windows") == 1)
        replies = [r.ok.payload.to_bytes() for r in a.get(keys.key(A, keys.RECEIVED), timeout=2.0) if r.ok]
        assert [wire.parse_watermark(p, A) for p in replies] == [1]  # the service answers through zenohd
        assert store.device(B) is None
        replies = [r.ok.payload.to_bytes() for r in b.get(keys.key(B, keys.RECEIVED), timeout=2.0) if r.ok]
        assert [wire.parse_watermark(p, B) for p in replies] == [0]  # the service's answer only
    finally:
        a.close()
        b.close()
        service.stop()
        service_session.close()
        router.close()
        store.close()


def test_only_the_service_and_its_meshed_routers_may_answer_a_query_in_the_router_acl(pki):
    """What keeps a device's certificate (a stolen drive key) from answering another drive's `received` question, so
    that its agent drops windows never stored, is the router's ACL, default deny: a device's rules allow `reply` only
    egress (the answers to its own questions) and never `declare_queryable`; only the service's policy (the service
    and the meshed routers) may answer. A meshed router is trusted as the service is: the reply's signature keeps it
    honest (test_agent_keeps_its_windows_on_a_forged_unsigned_or_replayed_watermark_reply)."""
    from encoder_fleet.pki import router_config

    acl = router_config(pki, "zenohd-a", listen=["tls/0.0.0.0:7447"], peers=["zenohd-b"])["access_control"]
    assert acl["enabled"] and acl["default_permission"] == "deny"
    rules = {r["id"]: r for r in acl["rules"]}
    subjects = {s["id"]: s["cert_common_names"] for s in acl["subjects"]}
    answering = set()
    for policy in acl["policies"]:
        for rule in map(rules.get, policy["rules"]):
            if rule["permission"] == "allow" and (
                "declare_queryable" in rule["messages"] or ("reply" in rule["messages"] and "ingress" in rule["flows"])
            ):
                answering.update(name for s in policy["subjects"] for name in subjects[s])
    assert answering == {"service", "zenohd-b"}
    assert subjects[A] == [A]


def test_a_command_whose_reader_has_gone_stops_quietly(pki):
    """`encoder-fleet pki router-config ... | head`: stdout's reader closed, the command ends with no error line (it
    printed "error: [Errno 32] Broken pipe") and SIGPIPE's exit status, as a shell tool does."""
    read_end, write_end = os.pipe()
    os.close(read_end)  # the reader gone before the first byte: every write breaks
    try:
        command = [sys.executable, "-m", "encoder_fleet.cli", "pki", "router-config", str(pki), "--name", "zenohd"]
        done = subprocess.run(command, stdout=write_end, stderr=subprocess.PIPE, text=True)
    finally:
        os.close(write_end)
    assert done.returncode == 141 and done.stderr == "", done.stderr


def test_pki_router_config_refuses_an_endpoint_that_is_not_tls(tmp_path, pki):
    """`pki router-config --listen tcp/...` (or a --connect mesh link over tcp/) wrote a config with that endpoint
    beside the TLS one: a listener that takes clients without a certificate, in plain text, and a mesh link with no
    certificate for the peer's ACL. Now it is refused as the service's own router refuses it: one line naming the
    endpoint, exit 2, no config written."""
    command = [sys.executable, "-m", "encoder_fleet.cli", "pki", "router-config", str(pki), "--name", "zenohd-test"]
    out = tmp_path / "zenohd.json5"
    for option, endpoint in (("--listen", "tcp/0.0.0.0:7448"), ("--connect", "tcp/zenohd-a:7447")):
        args = [option, endpoint] + (["--listen", "tls/0.0.0.0:7447"] if option == "--connect" else [])
        done = subprocess.run([*command, *args, "--out", str(out)], capture_output=True, text=True)
        assert done.returncode == 2 and f"{option} {endpoint}: not TLS" in done.stderr, done.stderr
        assert len(done.stderr.strip().splitlines()) == 1 and "Traceback" not in done.stderr
        assert not out.exists()
    done = subprocess.run([*command, "--connect", "tls/zenohd-a:7447", "--out", str(out)], capture_output=True)
    assert done.returncode == 0 and json.loads(out.read_text())["connect"]["endpoints"] == ["tls/zenohd-a:7447"]


def test_pki_commands_write_the_contract_files_with_private_keys_0600(tmp_path):
    from encoder_fleet.cli import main
    from fleet_wire.security import certificate_identity

    d = tmp_path / "pki"
    assert main(["pki", "init", str(d)]) == 0
    assert main(["pki", "issue", str(d), "drive-x"]) == 0
    assert main(["pki", "issue", str(d), "--service", "--host", "fleet.example"]) == 0
    for name in ("ca.crt", "ca.key", "drive-x.crt", "drive-x.key", "service.crt", "service.key", "signing.pub"):
        assert (d / name).is_file(), name
    for key in ("ca.key", "drive-x.key", "service.key", "signing.key"):
        assert stat.S_IMODE(os.stat(d / key).st_mode) == 0o600, key
    assert certificate_identity(d / "drive-x.crt") == ("drive-x", "device")
    assert certificate_identity(d / "service.crt") == ("service", "service")
    assert registry(d) == ["drive-x"]
    assert main(["pki", "issue", str(d), "drive-x"]) == 2  # no silent overwrite
    assert main(["pki", "issue", str(d), "signing"]) == 2  # reserved: would clash with the signing key
    assert main(["pki", "init", str(d)]) == 2


def test_a_signed_fleet_s_agent_announces_its_factory_set_until_the_service_has_it_not_at_every_window(
    secured, tmp_path
):
    """The service keeps a drive's factory set (v0) as announced, unsigned; an agent that checks signatures took
    that answer for no set at all and announced its factory set again at every window, until its first signed
    refit, for ever on a drive whose refits changed nothing. The service's copy of the agent's own factory set
    now counts as its set; a signed-looking copy of another set does not."""
    agent = make_agent(secured, secured.client(A), tmp_path)
    said = []
    put = agent.put

    def noted(key, payload):
        said.append(key)
        put(key, payload)

    agent.put = noted
    agent.start()
    assert wait_for(lambda: secured.store.current_coefficients(A) is not None)  # its factory set, announced
    announced = said.count(agent.keys["factory"])
    for _ in range(6):
        assert agent.step()
    assert announced >= 1 and said.count(agent.keys["factory"]) == announced, said
    assert agent.service_has_set
    other = {**plausible_set(agent, 0), "basis": "factory"}
    other["bands"][0]["w"][0] *= 1.5
    assert not agent._is_own_factory(wire.encode("coefficients", other))
    agent.close()


def test_the_first_admin_token_is_never_readable_by_others_nor_written_through_a_link(tmp_path):
    """The first admin token was written into the file at --admin-token-file as it stood and made 0600 after: an
    existing 0644 file held the token readable by anyone until the chmod, and a symlink there sent it wherever it
    pointed (a security review). Now it is a new 0600 file renamed over the path; and a write that fails revokes
    the token, so the next start writes one again (it had stayed live with nobody holding it, and no first token
    was ever written again)."""
    with Store.open(tmp_path / "fleet.sqlite") as store:
        auth = TokenAuth(store)
        elsewhere = tmp_path / "elsewhere"
        elsewhere.write_text("not a token\n")
        os.chmod(elsewhere, 0o644)
        link = tmp_path / "admin-token"
        link.symlink_to(elsewhere)
        assert auth.first_admin_token(link) == link
        assert not link.is_symlink() and stat.S_IMODE(link.stat().st_mode) == 0o600
        assert elsewhere.read_text() == "not a token\n" and auth.scope_of(link.read_text().strip()) == "admin"
    with Store.open(tmp_path / "other.sqlite") as store:
        auth = TokenAuth(store)
        blocked = tmp_path / "a-folder"  # a folder where the token file should go: the rename fails
        blocked.mkdir()
        (blocked / "kept").write_text("x")
        with pytest.raises(OSError):
            auth.first_admin_token(blocked)
        assert auth.count() == 0 and not list(tmp_path.glob(".a-folder*"))  # revoked, no temporary file left
        assert auth.first_admin_token(tmp_path / "ok-token") is not None


def test_token_list_escapes_a_name_made_before_names_were_one_line(tmp_path):
    """A token named before the one-line rule keeps its name; `token list` prints it escaped, not as the escape
    sequence it holds (which reached the operator's terminal)."""
    db = tmp_path / "fleet.sqlite"
    with Store.open(db) as store:
        TokenAuth(store).create("read", "wallboard")
        with store._tx() as c:
            c.execute("UPDATE api_tokens SET name = ?", ("\x1b[2Jwiped",))
    listed = subprocess.run(
        [sys.executable, "-m", "encoder_fleet.cli", "token", "list", "--db", str(db)], capture_output=True, text=True
    )
    assert listed.returncode == 0 and "\x1b" not in listed.stdout and "'\\x1b[2Jwiped'" in listed.stdout


def test_a_change_made_with_a_token_named_before_names_were_one_line_records_it_escaped(tmp_path):
    """Who retired a drive is the token's name as the change records it, printed by `devices show` and `alarms list`:
    a name made before the one-line rule reached the operator's terminal through them as the escape sequence it held
    (only `token list` escaped it). The record holds it escaped, as `token list` prints it."""
    with Store.open(tmp_path / "fleet.sqlite") as store:
        store.insert_window(ws.window("drive-001", 1))
        auth = TokenAuth(store)
        token_id, token = auth.create("admin", "ops desk")
        with store._tx() as c:
            c.execute("UPDATE api_tokens SET name = ?", ("\x1b[2Jwiped",))
        api = TestClient(create_app(store, auth=auth))
        r = api.post(
            "/devices/drive-001/retire", json={"note": "replaced"}, headers={"Authorization": f"Bearer {token}"}
        )
        assert r.status_code == 200, r.text
        assert r.json()["retired"]["by"] == f"token {token_id} ('\\x1b[2Jwiped')"
        assert "\x1b" not in store.retirements("drive-001")[0]["retired_by"]
