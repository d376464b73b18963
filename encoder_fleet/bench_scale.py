"""`encoder-fleet bench-scale`: the fleet spread over several service processes (issue 13).

Every row: a fresh database, a Zenoh router (in this process, as zenohd would be), N real `encoder-fleet
service` processes (`--member svc-K` on PostgreSQL; one plain process on SQLite), and a publisher process that
plays the drives: each announces its factory set, then sends one window per drive-minute, all drives the
same minute before the next. The drive clock runs faster than real time (as fast as the services take the
windows, since the publisher waits for room like an agent does), and the big fleets send fewer minutes.

Measured per row:
- windows_per_s: windows stored (counted in the database) per second, first to last;
- refit_lag_s: from the last window stored until every drive has been refit on its windows (the services'
  own refit counters). A drive refits at its first window and then once per drive-hour, so this is the time
  a full pass over the fleet takes: when it exceeds the refit cadence (an hour), the fleet outgrows its
  processes. Where the pass does not end within the budget, it is the time so far plus what is left at the
  rate measured (`refit_lag_measured` false);
- REST p50/p99: `GET /devices/{id}/health` for random drives, round-robin over the processes, while ingesting.
"""

from __future__ import annotations

import json
import random
import signal
import subprocess
import sys
import tempfile
import threading
import time
import urllib.error
import urllib.request
from contextlib import ExitStack
from pathlib import Path

import numpy as np

from encoder_fleet.bench_fleet import announce_factory_sets, as_device, bench_database, template_messages
from fleet_wire import keys
from fleet_wire import messages as wire
from fleet_wire.session import free_port, loopback_endpoint, session_config

STALL_S = 15.0  # no window stored for this long: the drives send what the watermarks do not cover again
REFIT_BUDGET_S = 60.0  # how long a row waits for the refit pass before it extrapolates
INGEST_TIMEOUT_S = 1800.0


def windows_for(devices: int) -> int:
    """Drive-minutes per drive: a dozen for small fleets, two for the big ones (the machine has 2 cores)."""
    return int(min(12, max(2, 24_000 // devices)))


# --- the drives (a process of its own) ------------------------------------------------------------------


def publish(endpoint: str, devices: int, windows: int) -> None:
    """Factory sets; a line on stdin (they are stored); minute after minute of windows for every drive. Then,
    for each `resend` line, what the service's watermarks do not cover is sent again, as agents do from their
    outboxes (an overloaded service or router drops what it cannot take). Ends when stdin closes."""
    import msgspec
    import zenoh

    block = zenoh.CongestionControl.BLOCK
    session = zenoh.open(session_config("client", connect=[endpoint]))
    encoder = msgspec.msgpack.Encoder()

    def put(name: str, win) -> None:
        payload = encoder.encode(as_device(win, name))
        session.put(keys.key(name, keys.STATS), payload, congestion_control=block)

    try:
        names = [f"scale-{i:06d}" for i in range(devices)]
        announce_factory_sets(session, names)
        wins = template_messages(windows)
        print("factory sets sent", flush=True)
        sys.stdin.readline()
        for win in wins:  # minute after minute, every drive
            for name in names:
                put(name, win)
        print("sent", flush=True)
        for line in sys.stdin:
            if line.strip() == "resend":
                marks = _watermarks(session, names)
                for name in names:
                    for win in wins[marks.get(name, 0) :]:
                        put(name, win)
                print("sent", flush=True)
    finally:
        session.close()


def _watermarks(session, names: list[str], in_flight: int = 500) -> dict[str, int]:
    """Each drive's watermark, asked `in_flight` drives at a time (the gets run concurrently)."""
    marks = {}
    for i in range(0, len(names), in_flight):
        asked = [(name, session.get(keys.key(name, keys.RECEIVED), timeout=10)) for name in names[i : i + in_flight]]
        for name, replies in asked:
            for reply in replies:
                if reply.ok is not None:
                    marks[name] = max(marks.get(name, 0), wire.parse_watermark(reply.ok.payload.to_bytes(), name))
    return marks


# --- one row --------------------------------------------------------------------------------------------


def _get(url: str, timeout: float = 10.0):
    with urllib.request.urlopen(url, timeout=timeout) as reply:
        return reply.read()


def _metric(port: int, name: str) -> float:
    from prometheus_client.parser import text_string_to_metric_families

    text = _get(f"http://127.0.0.1:{port}/metrics").decode()
    for family in text_string_to_metric_families(text):
        for sample in family.samples:
            if sample.name in (name, name + "_total"):
                return sample.value
    return 0.0


class _Counter:
    """The windows table's row count, read on its own connection (kept open: a row polls it every 0.2 s)."""

    def __init__(self, target: str):
        from service.store import Store

        self.store = Store.open(target)

    def __call__(self) -> int:
        return self.store._rows("SELECT count(*) AS n FROM windows")[0]["n"]

    def factory_sets(self) -> int:
        return self.store._rows("SELECT count(*) AS n FROM coefficient_sets WHERE version = 0")[0]["n"]


def _rest_load(ports: list[int], names: list[str], stop: threading.Event, latencies: list[float]) -> None:
    rng = random.Random(0)
    while not stop.is_set():
        port = ports[len(latencies) % len(ports)]
        start = time.perf_counter()
        try:
            _get(f"http://127.0.0.1:{port}/devices/{rng.choice(names)}/health")
        except urllib.error.HTTPError:
            pass  # a drive not heard yet: 404 is an answer too, timed like the others
        latencies.append(time.perf_counter() - start)
        stop.wait(0.02)


def run_row(devices: int, processes: int, store: str, workdir: Path, postgres: str | None) -> dict:
    windows = windows_for(devices)
    expected = devices * windows
    name = f"scale-{devices}-{processes}-{store}"
    with ExitStack() as stack:
        target = stack.enter_context(bench_database(workdir, name, postgres if store == "postgresql" else None))
        import zenoh

        endpoint = loopback_endpoint()
        router = zenoh.open(session_config("router", listen=[endpoint]))
        stack.callback(router.close)
        ports, services = [], []
        for k in range(processes):
            port = free_port()
            member = ["--member", f"svc-{k}"] if store == "postgresql" else []
            proc = subprocess.Popen(
                [sys.executable, "-m", "encoder_fleet.cli", "service", "--connect", endpoint, "--db", target]
                + ["--insecure", "--http-port", str(port), "--refit-interval", "1", "--log-level", "warning"]
                + member,
                stdout=subprocess.DEVNULL,
            )
            stack.callback(_stop, proc)
            ports.append(port)
            services.append(proc)
        _wait_served(ports, services)
        counter = _Counter(target)
        stack.callback(counter.store.close)
        publisher = subprocess.Popen(
            [sys.executable, "-m", "encoder_fleet.bench_scale", "--publish", endpoint, str(devices), str(windows)],
            stdin=subprocess.PIPE,
            stdout=subprocess.DEVNULL,
            text=True,
        )
        stack.callback(_stop, publisher)
        # every drive announces its factory set first (as agents do at their first start): refits anchor on it
        started = time.perf_counter()
        while counter.factory_sets() < devices and publisher.poll() is None:
            assert time.perf_counter() - started < INGEST_TIMEOUT_S, "factory sets not stored in time"
            time.sleep(0.5)
        factory_s = time.perf_counter() - started
        publisher.stdin.write("go\n")
        publisher.stdin.flush()
        names = [f"scale-{i:06d}" for i in range(devices)]
        latencies: list[float] = []
        stop_rest = threading.Event()
        rest = threading.Thread(target=_rest_load, args=(ports, names, stop_rest, latencies), daemon=True)
        rest.start()
        deadline = time.monotonic() + INGEST_TIMEOUT_S
        stored, first_at, resends = 0, None, 0
        progress_at, progress = time.monotonic(), 0
        while stored < expected and time.monotonic() < deadline and publisher.poll() is None:
            stored = counter()
            if first_at is None and stored:
                first_at = time.perf_counter()
            if stored > progress:
                progress_at, progress = time.monotonic(), stored
            elif time.monotonic() - progress_at > STALL_S:  # windows were dropped on the way: as agents would
                publisher.stdin.write("resend\n")
                publisher.stdin.flush()
                resends += 1
                progress_at = time.monotonic() + STALL_S * resends  # its watermark pass takes a while
            time.sleep(0.2)
        last_at = time.perf_counter()
        stop_rest.set()
        rest.join()
        publisher.stdin.close()
        refit_lag, measured = _refit_lag(ports, devices)
        lat = np.array(latencies) * 1000.0
        return {
            "devices": devices,
            "processes": processes,
            "store": store,
            "windows_per_drive": windows,
            "windows": stored,
            "expected": expected,
            "factory_sets_s": factory_s,
            "resend_passes": resends,
            "ingest_s": last_at - (first_at or last_at),
            "windows_per_s": stored / (last_at - first_at) if first_at and last_at > first_at else float("nan"),
            "refit_lag_s": refit_lag,
            "refit_lag_measured": measured,
            "rest_requests": int(lat.size),
            "rest_p50_ms": float(np.percentile(lat, 50)) if lat.size else float("nan"),
            "rest_p99_ms": float(np.percentile(lat, 99)) if lat.size else float("nan"),
        }


def _wait_served(ports: list[int], services: list[subprocess.Popen]) -> None:
    """Until every process answers and, together, they serve every partition exactly once."""
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        if any(p.poll() is not None for p in services):
            raise RuntimeError("a service process exited at start (see its output above)")
        try:
            served = [json.loads(_get(f"http://127.0.0.1:{port}/cluster"))["served"] for port in ports]
        except OSError:
            served = None
        if served is not None and sorted(p for s in served for p in s) == [
            keys.partition_chunk(p) for p in range(keys.PARTITIONS)
        ]:
            return
        time.sleep(0.3)
    raise RuntimeError("the service processes did not share out the partitions within 60 s")


def _refit_lag(ports: list[int], devices: int) -> tuple[float, bool]:
    start = time.perf_counter()
    done = 0.0
    while time.perf_counter() - start < REFIT_BUDGET_S:
        done = sum(_metric(port, "encoder_fleet_refits") for port in ports)
        if done >= devices:
            return time.perf_counter() - start, True
        time.sleep(0.5)
    elapsed = time.perf_counter() - start
    before = done
    time.sleep(5.0)
    done = sum(_metric(port, "encoder_fleet_refits") for port in ports)
    rate = (done - before) / 5.0
    return (elapsed + 5.0 + (devices - done) / rate if rate > 0 else float("inf")), False


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


# --- the table ------------------------------------------------------------------------------------------


def run_bench(
    sizes: list[int], processes: list[int], postgres: str | None, json_path=None, stores=("sqlite", "postgresql")
) -> int:
    from encoder_fleet.pgserver import throwaway_postgres

    rows = []
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # stopped: the services and the server stop too
    with ExitStack() as stack, tempfile.TemporaryDirectory() as tmp:
        if postgres is None and "postgresql" in stores:
            postgres = stack.enter_context(throwaway_postgres(fsync=True))
            print("… a throwaway PostgreSQL server (fsync on) from this machine's binaries", file=sys.stderr)
        plan = [(n, 1, "sqlite") for n in sizes if "sqlite" in stores]
        plan += [(n, k, "postgresql") for n in sizes for k in processes if "postgresql" in stores]
        plan.sort(key=lambda r: (r[0], r[2] == "postgresql", r[1]))
        for i, (n, k, store) in enumerate(plan, start=1):
            print(
                f"… [{i}/{len(plan)}] {n} drives × {windows_for(n)} minutes, {k} × service on {store}", file=sys.stderr
            )
            rows.append(run_row(n, k, store, Path(tmp), postgres))
            _print_row(rows[-1], header=i == 1)
            if json_path:  # after every row: a long run stopped halfway keeps what it measured
                Path(json_path).write_text(json.dumps({"rows": rows}, indent=1) + "\n")
    print(
        "\nwindows/s: stored, counted in the database, first to last window; refit lag: from the last window stored"
        "\nuntil every drive was refit on its windows (~: extrapolated from the rate over the last 5 s of a 60 s"
        "\nbudget); REST: GET /devices/{id}/health round-robin over the processes while ingesting."
    )
    return 0


def _print_row(r: dict, header: bool) -> None:
    if header:
        print(
            f"\n{'drives':>8} {'processes':>9} {'store':>10} {'windows':>9} {'windows/s':>10} {'refit lag s':>12}"
            f" {'REST p50 ms':>12} {'REST p99 ms':>12}",
            flush=True,
        )
    lag = f"{'' if r['refit_lag_measured'] else '~'}{r['refit_lag_s']:.0f}"
    print(
        f"{r['devices']:>8} {r['processes']:>9} {r['store']:>10} {r['windows']:>9} {r['windows_per_s']:>10.0f}"
        f" {lag:>12} {r['rest_p50_ms']:>12.1f} {r['rest_p99_ms']:>12.1f}",
        flush=True,
    )


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser()
    parser.add_argument("--publish", nargs=3, metavar=("ENDPOINT", "DEVICES", "WINDOWS"), required=True)
    a = parser.parse_args()
    publish(a.publish[0], int(a.publish[1]), int(a.publish[2]))
