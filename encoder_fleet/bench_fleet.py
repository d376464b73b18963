"""`encoder-fleet bench-fleet`: windows ingested per second and refits per second for fleets of
several sizes, through a real Zenoh router and a real SQLite file.

A publisher process (the fleet's agents, condensed) sends pre-built windows for every device as
fast as it can; the service in this process validates, deduplicates and stores them. Then one
refit pass over every device is timed.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
import zlib
from contextlib import contextmanager
from pathlib import Path

import msgspec

from edge_agent.agent import factory_message
from edge_agent.sources import SimulatedDrive, drive_model, factory_calibration
from encoder_core.stats import WindowStats, normalisation_scale, window_stats
from fleet_wire import keys
from fleet_wire import messages as wire
from fleet_wire.session import loopback_endpoint, session_config

TEMPLATE_SEED = 1
FIRST_PUT = "first put at "  # the publisher's one line on stdout, then its CLOCK_MONOTONIC time


def template_windows(
    count: int, samples_per_window: int = 3000, steady: bool = False
) -> list[tuple[WindowStats, float]]:
    """Window statistics of one simulated drive across its 12 h temperature cycle, reused for every device;
    steady: over `count` consecutive drive-minutes instead."""
    factory = factory_calibration(drive_model(TEMPLATE_SEED), TEMPLATE_SEED)
    scale = normalisation_scale(factory)
    hours, window_s = (count / 60 + 0.1, 60.0) if steady else (12.0, 12.0 * 3600 / count)
    source = SimulatedDrive(TEMPLATE_SEED, hours=hours, sample_hz=samples_per_window / window_s)
    out = []
    while len(out) < count and (block := source.read(window_s)) is not None:
        out.append((window_stats(block, scale), float(block.t[0])))
    return out


def announce_factory_sets(session, names: list[str]) -> None:
    """Every drive's factory set, as an agent announces it at its first start."""
    import zenoh

    factory = factory_calibration(drive_model(TEMPLATE_SEED), TEMPLATE_SEED)
    for name in names:
        payload = wire.encode("coefficients", factory_message(name, factory))
        session.put(keys.key(name, keys.FACTORY), payload, congestion_control=zenoh.CongestionControl.BLOCK)


def template_messages(count: int, steady: bool = False) -> list[wire.Window]:
    """template_windows as wire window structs, one a drive-minute; each drive's copy only changes `device`.
    steady: `count` consecutive one-minute windows instead, as a fleet sends them (a band or two), where the
    template's windows spread over the 12 h cycle (13 bands in 20 windows: most windows start a band's sum)."""
    return [
        wire.window_from_dict(
            wire.window_message(
                "template",
                seq,
                stats,
                window_start=start,
                window_end=start + 60.0,
                temp_rate_c_per_s=0.0,
                coefficients_version=0,
                angle_quality_deg=0.5,
            )
        )
        for seq, (stats, start) in enumerate(template_windows(count, steady=steady), start=1)
    ]


def as_device(win: wire.Window, name: str) -> wire.Window:
    """The template window as device `name` sends it: its channels' centre moved by under a thousandth of a count,
    its own (physically nothing), so no two drives' statistics are the same bytes, as in a real fleet, and no
    cache keyed by content (service.refit.FIT_MEMO) serves one drive's fit to another."""
    shift = 1e-3 * zlib.crc32(name.encode()) / 2**32
    return msgspec.structs.replace(
        win, device=name, stats=msgspec.structs.replace(win.stats, center_d=win.stats.center_d + shift)
    )


def publish(endpoint: str, devices: int, windows: int, pki: str | None = None) -> None:
    """The publisher process: factory sets, then every device's windows, round-robin."""

    import zenoh

    block = zenoh.CongestionControl.BLOCK  # like the agents: wait for room rather than drop
    templates = template_messages(windows)
    identity = None
    if pki:
        from fleet_wire.security import ROLE_DEVICE, Identity

        identity = Identity.load(pki, PUBLISHER, ROLE_DEVICE)
    session = zenoh.open(session_config("client", connect=[endpoint], identity=identity))
    try:
        names = [f"bench-{i:05d}" for i in range(devices)]
        announce_factory_sets(session, names)
        # pre-encoded MessagePack windows (as wire.encode makes them): the bench times the service, not the encoder
        encoder = msgspec.msgpack.Encoder()
        puts = []
        for win in templates:
            for name in names:
                puts.append((keys.key(name, keys.STATS), encoder.encode(as_device(win, name))))
        put = session.put
        # the service times its windows from this moment (CLOCK_MONOTONIC is one clock for every process here)
        print(f"{FIRST_PUT}{time.monotonic():.6f}", flush=True)
        for key, payload in puts:
            put(key, payload, congestion_control=block)
        # closing a session drops what it has not sent yet: like an agent, wait until the service has it all
        deadline = time.monotonic() + 300
        for name in names:
            while time.monotonic() < deadline:
                replies = [
                    r.ok.payload.to_bytes() for r in session.get(keys.key(name, keys.RECEIVED), timeout=5) if r.ok
                ]
                if replies and wire.parse_watermark(replies[0], name) >= len(templates):
                    break
                time.sleep(0.05)
    finally:
        session.close()


PUBLISHER = "bench-publisher"  # the condensed fleet's one certificate when the bench runs secured


def secured_router(workdir: Path, endpoint: str, names: list[str], store):
    """The service's router as `encoder-fleet service --pki` runs it (TLS, mTLS, the ACL of `names`, signed
    sets, the guard), plus one policy that lets the bench's single publisher speak for every device."""
    import zenoh

    from encoder_fleet.pki import init_ca, issue
    from fleet_wire.security import ROLE_SERVICE, SERVICE_NAME, Identity, SetSigner, access_control
    from service.guard import IngestGuard

    pki = workdir / "pki"
    if not (pki / "ca.crt").exists():
        init_ca(pki)
        issue(pki, SERVICE_NAME, ROLE_SERVICE)
        issue(pki, PUBLISHER)
    acl = access_control(names)
    acl["rules"].append(
        {
            "id": "bench/all-devices",
            "messages": ["put", "query", "reply"],
            "flows": ["ingress", "egress"],
            "permission": "allow",
            "key_exprs": [keys.every(keys.STATS), keys.every(keys.FACTORY), keys.every(keys.RECEIVED)],
        }
    )
    acl["subjects"].append({"id": PUBLISHER, "cert_common_names": [PUBLISHER]})
    acl["policies"].append({"id": "bench/policy", "rules": ["bench/all-devices"], "subjects": [PUBLISHER]})
    identity = Identity.load(pki, SERVICE_NAME, ROLE_SERVICE)
    session = zenoh.open(session_config("router", listen=[endpoint], identity=identity, access_control=acl))
    return pki, session, {"signer": SetSigner.load(pki), "guard": IngestGuard(store, names)}


@contextmanager
def bench_database(workdir: Path, name: str, postgres: str | None):
    """A fresh database for one run: a SQLite file, or a PostgreSQL database created (and then dropped) through
    the admin URL `postgres`."""
    if postgres is None:
        yield str(workdir / f"{name}.sqlite")
        return
    import psycopg

    database = f"{name.replace('-', '_')}_{os.getpid()}"
    with psycopg.connect(postgres, autocommit=True) as admin:
        admin.execute(f"DROP DATABASE IF EXISTS {database}")
        admin.execute(f"CREATE DATABASE {database}")
    try:
        yield postgres.rsplit("/", 1)[0] + "/" + database
    finally:
        with psycopg.connect(postgres, autocommit=True) as admin:
            admin.execute(f"DROP DATABASE IF EXISTS {database} WITH (FORCE)")


def run_size(devices: int, windows: int, workdir: Path, secure: bool = False, postgres: str | None = None) -> dict:
    with bench_database(workdir, f"bench-{devices}-{'tls' if secure else 'tcp'}", postgres) as target:
        row = _run_size(devices, windows, workdir, target, secure)
    return {"store": "postgresql" if postgres else "sqlite", **row}


def _run_size(devices: int, windows: int, workdir: Path, target: str, secure: bool) -> dict:
    from service.runtime import FleetService, open_session
    from service.store import Store

    endpoint = loopback_endpoint()
    store = Store.open(target)
    names = [f"bench-{i:05d}" for i in range(devices)]
    pki_args, security = [], {}
    if secure:
        endpoint = endpoint.replace("tcp/", "tls/", 1)
        pki, session, security = secured_router(workdir, endpoint, names, store)
        pki_args = ["--pki", str(pki)]
    else:
        session = open_session(listen=[endpoint])
    service = FleetService(store, session, refit_interval_s=0, min_band_samples=2000, **security).start()
    proc = None
    try:
        total = devices * windows
        proc = subprocess.Popen(
            [sys.executable, "-m", "encoder_fleet.bench_fleet", "--publish", endpoint, str(devices), str(windows)]
            + pki_args,
            stdout=subprocess.PIPE,
            text=True,
        )
        # timed from the publisher's first window put to the last one stored (its start-up, building the windows,
        # aside); from the first window *stored* instead, a first batch slow to commit while the rest queued up
        # was left out of the time
        said = proc.stdout.readline()  # "" when the publisher died first: nothing timed
        first_put = float(said.removeprefix(FIRST_PUT)) if said.startswith(FIRST_PUT) else float("nan")
        deadline = time.monotonic() + 600
        stored = 0
        while time.monotonic() < deadline:
            stored = service.counters.ingested.get("stored", 0)
            if stored >= total or proc.poll() is not None:
                break
            time.sleep(0.002)
        ingest_s = time.monotonic() - first_put
        proc.wait()
        proc.stdout.close()
        # the drift monitor reads every stored window after the writer (it waits while a backlog is stored):
        # windows/s above is storing; this is when the analysis of the same windows was done
        while time.monotonic() < deadline and any(service.monitor.last_seq.get(n, 0) < windows for n in names):
            time.sleep(0.01)
        monitored_s = time.monotonic() - first_put
        start = time.perf_counter()
        published = service.refit_all()
        refit_s = time.perf_counter() - start
        return {
            "security": "mTLS+ACL+signed" if secure else "none",
            "devices": devices,
            "windows": stored,
            "expected": total,
            "ingest_s": ingest_s,
            "windows_per_s": stored / ingest_s if ingest_s > 0 else float("nan"),
            "monitored_s": monitored_s,
            "monitored_windows_per_s": stored / monitored_s if monitored_s > 0 else float("nan"),
            "refits": devices,
            "refit_s": refit_s,
            "refits_per_s": devices / refit_s,
            "rollouts": len(published),
            "rejected": sum(v for k, v in service.counters.ingested.items() if k not in ("stored", "duplicate")),
        }
    finally:
        if proc is not None and proc.poll() is None:  # failed or timed out on the way: the publisher goes too
            proc.kill()
            proc.wait()
        service.stop()
        session.close()
        store.close()


def store_ceilings(devices: int, windows: int, workdir: Path) -> dict:
    """What bounds windows/s, measured in the same run: the same windows without Zenoh and the publisher, through
    `Store.ingest_many` in the service's batches (decode, checks, band sums, SQLite), and then the rows it wrote
    through bare `executemany` into a fresh file with the same schema (SQLite alone, no Python per window). And
    the store alone on a steady fleet's windows (consecutive minutes: few new band sums; template_messages)."""
    from service.runtime import MAX_BATCH
    from service.store import Store

    encoder = msgspec.msgpack.Encoder()
    names = [f"bench-{i:05d}" for i in range(devices)]

    def fleet_items(steady: bool) -> list[tuple[str, bytes]]:
        wins = template_messages(windows, steady=steady)
        return [(keys.key(name, keys.STATS), encoder.encode(as_device(win, name))) for win in wins for name in names]

    def stored_per_s(store, items) -> float:
        start = time.perf_counter()
        for k in range(0, len(items), MAX_BATCH):
            store.ingest_many(items[k : k + MAX_BATCH])
        return len(items) / (time.perf_counter() - start)

    with Store.open(str(workdir / f"ceiling-steady-{devices}.sqlite")) as store:
        steady_per_s = stored_per_s(store, fleet_items(steady=True))
    items = fleet_items(steady=False)
    store = Store.open(str(workdir / f"ceiling-store-{devices}.sqlite"))
    try:
        store_per_s = stored_per_s(store, items)
        source = store._conn
        device_rows = [tuple(r) for r in source.execute("SELECT * FROM devices")]
        window_rows = [tuple(r) for r in source.execute("SELECT * FROM windows ORDER BY rowid")]
    finally:
        store.close()
    bare = Store.open(str(workdir / f"ceiling-sqlite-{devices}.sqlite"))
    try:
        conn = bare._conn
        conn.executemany(f"INSERT INTO devices VALUES ({', '.join('?' * len(device_rows[0]))})", device_rows)
        insert = f"INSERT INTO windows VALUES ({', '.join('?' * len(window_rows[0]))})"
        start = time.perf_counter()
        for k in range(0, len(window_rows), MAX_BATCH):
            conn.execute("BEGIN IMMEDIATE")
            conn.executemany(insert, window_rows[k : k + MAX_BATCH])
            conn.execute("COMMIT")
        sqlite_s = time.perf_counter() - start
    finally:
        bare.close()
    return {
        "store_alone_windows_per_s": store_per_s,
        "store_alone_steady_windows_per_s": steady_per_s,
        "sqlite_alone_rows_per_s": len(window_rows) / sqlite_s,
    }


def run_bench(
    sizes: list[int], windows_per_device: int, security: str = "both", json_path=None, postgres: str | None = None
) -> int:
    rows, ceilings = [], []
    modes = {"both": (False, True), "off": (False,), "on": (True,)}[security]
    stores = (None, postgres) if postgres else (None,)
    with tempfile.TemporaryDirectory() as tmp:
        for n in sizes:
            for secure in modes:
                for store_url in stores:
                    what = ("TLS, ACL, signed sets" if secure else "plain TCP") + (", PostgreSQL" if store_url else "")
                    print(f"… {n} devices × {windows_per_device} windows, {what}", file=sys.stderr, flush=True)
                    rows.append(run_size(n, windows_per_device, Path(tmp), secure=secure, postgres=store_url))
            print(f"… {n} devices × {windows_per_device} windows: the store alone, then SQLite alone", file=sys.stderr)
            ceilings.append(
                {"devices": n, "windows": n * windows_per_device, **store_ceilings(n, windows_per_device, Path(tmp))}
            )
    print(
        f"\n{'store':>10} {'security':>16} {'devices':>8} {'windows':>9} {'ingest s':>9} {'windows/s':>10}"
        f" {'monitored/s':>12}"
        f" {'refit s':>8} {'refits/s':>9}"
        f" {'rollouts':>9} {'rejected':>9}"
    )
    for r in rows:
        print(
            f"{r['store']:>10} {r['security']:>16} {r['devices']:>8} {r['windows']:>9} {r['ingest_s']:>9.2f} "
            f"{r['windows_per_s']:>10.0f} {r['monitored_windows_per_s']:>12.0f} "
            f"{r['refit_s']:>8.2f} {r['refits_per_s']:>9.1f} {r['rollouts']:>9} {r['rejected']:>9}"
        )
    print(
        "\nwindows/s: validated, deduplicated and stored (with the band sums) through a real router and the store,"
        "\ntimed from the publisher's first window put to the last one stored;"
        "\nmonitored/s: the same windows read and analysed by the drift monitor, timed from the same first put"
        " (it waits while a backlog is stored)."
        "\nrefits/s: one refit pass over every device (drift fit per band against the bench locus, drift curve,"
        " adoption, rollout: guard, signed set, stored and published)."
        "\nmTLS+ACL+signed: TLS with client certificates, the router's ACL of the whole fleet, the service's guard,"
        "\nand every rolled-out set signed (Ed25519)."
    )
    print(f"\n{'what bounds windows/s (same run, same windows, SQLite file)':<56} {'devices':>8} {'windows/s':>10}")
    for c in ceilings:
        for what, value in (
            ("end to end (publisher, router, service, store; above)", end_to_end(rows, c)),
            ("the store alone (Store.ingest_many, no Zenoh)", c["store_alone_windows_per_s"]),
            ("the store alone, a steady fleet's consecutive windows", c["store_alone_steady_windows_per_s"]),
            ("SQLite alone (the same rows, bare executemany)", c["sqlite_alone_rows_per_s"]),
        ):
            print(f"{what:<56} {c['devices']:>8} {value:>10.0f}")
    print(signature_cost())
    if json_path:
        Path(json_path).write_text(json.dumps({"rows": rows, "ceilings": ceilings}, indent=1) + "\n")
    return 0


def end_to_end(rows: list[dict], ceiling: dict) -> float:
    """The first plain-SQLite row of the same fleet size: the end-to-end figure beside its ceilings."""
    same = [r for r in rows if r["devices"] == ceiling["devices"] and r["store"] == "sqlite"]
    return same[0]["windows_per_s"] if same else float("nan")


def signature_cost(n: int = 2000) -> str:
    """Ed25519 over a real coefficient set: the service signs each rollout, the agent verifies each set."""
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

    from fleet_wire.security import SetSigner, SetVerifier

    key = Ed25519PrivateKey.generate()
    signer, verifier = SetSigner(key), SetVerifier(key.public_key())
    factory = factory_calibration(drive_model(TEMPLATE_SEED), TEMPLATE_SEED)
    msg = {**factory_message("bench-00000", factory), "version": 1, "basis": "fit"}
    start = time.perf_counter()
    signed = [signer.sign(msg) for _ in range(n)]
    sign_us = (time.perf_counter() - start) / n * 1e6
    start = time.perf_counter()
    for m in signed:
        verifier.verify(m)
    verify_us = (time.perf_counter() - start) / n * 1e6
    return f"signature per coefficient set: sign {sign_us:.0f} µs (service), verify {verify_us:.0f} µs (agent)"


if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("--publish", nargs=3, metavar=("ENDPOINT", "DEVICES", "WINDOWS"), required=True)
    parser.add_argument("--pki")
    a = parser.parse_args()
    publish(a.publish[0], int(a.publish[1]), int(a.publish[2]), a.pki)
