"""`encoder-fleet bench-soak`: agents publish while the service (and the router in it) is killed and
restarted at random, agents are killed and restarted, bad messages are mixed in and the disk fills and
frees. At the end every window an agent issued is counted in the database: stored once, lost, doubled
(a seq stored twice, or a stretch of drive time held by two windows), and the service's memory over time.

Everything runs as separate processes on loopback, insecure (the security model has its own tests):
the service (`encoder-fleet service`), one `encoder-fleet agent` per drive, and a bad actor in this
process. "Disk full" is the service restarted with a quota below its database (`--db-max-mb`): every
write fails as on a full disk, and the next restart without it frees the space.
"""

from __future__ import annotations

import json
import random
import sqlite3
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from fleet_wire import keys

REAL_TIME_FACTOR = 600.0  # drive seconds per real second: a 60 s window every 0.1 s per agent
SAMPLE_HZ = 2.0
BAD_MESSAGES = [  # (key suffix, payload): what a broken or hostile peer sends
    (keys.STATS, b"not json at all"),
    (keys.STATS, b'{"device": "soak-bad", "seq": 1e999}'),
    (keys.ACK, b'{"device":"soak-bad","x":' + b"[" * 1500 + b"]" * 1500 + b"}"),
    (keys.ACK, json.dumps({"device": "soak-bad", "version": 2**70, "status": "applied"}).encode()),
    (keys.STATS, b"\x82\xa6device\xa8soak-bad\xa5stats" + b"\x91" * 3000 + b"\xc0"),
    (keys.STATS, b"x" * 300_000),
]


@dataclass
class SoakResult:
    sent: int = 0
    stored: int = 0
    lost: int = 0
    doubled: int = 0
    memory_mb: list[float] = field(default_factory=list)  # the service's RSS, one sample a second
    events: list[str] = field(default_factory=list)
    bad_sent: int = 0
    restarts: int = 0

    def to_json(self) -> dict:
        return {
            "sent": self.sent,
            "stored": self.stored,
            "lost": self.lost,
            "doubled": self.doubled,
            "memory_mb": self.memory_mb,
        }


class Soak:
    def __init__(self, folder: Path, agents: int, minutes: float, seed: int):
        self.folder = folder
        from fleet_wire.session import loopback_endpoint

        self.rng = random.Random(seed)
        self.endpoint = loopback_endpoint()
        self.db = folder / "fleet.sqlite"
        self.devices = [f"soak-{i:02d}" for i in range(agents)]
        self.duration_s = minutes * 60.0
        self.sim_hours = self.duration_s * REAL_TIME_FACTOR / 3600.0
        self.started = time.monotonic()
        self.service: subprocess.Popen | None = None
        self.agents: dict[str, subprocess.Popen] = {}
        self.result = SoakResult()
        self._stop = threading.Event()

    # --- processes ---------------------------------------------------------------------------------

    def start_service(self, *, quota_mb: float | None = None) -> None:
        cmd = [sys.executable, "-m", "encoder_fleet.cli", "service", "--db", str(self.db), "--listen", self.endpoint]
        cmd += ["--http-port", "0", "--refit-interval", "1", "--insecure", "--log-level", "error"]
        if quota_mb is not None:
            cmd += ["--db-max-mb", str(quota_mb)]
        self.service = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        ready = self.service.stdout.readline()
        if not ready.startswith("service:"):
            raise RuntimeError(f"the service did not start: {ready!r}")

    def kill_service(self) -> None:
        if self.service is not None and self.service.poll() is None:
            self.service.kill()
            self.service.wait()
        self.result.restarts += 1

    def start_agent(self, device: str) -> None:
        elapsed_h = (time.monotonic() - self.started) * REAL_TIME_FACTOR / 3600.0
        hours = max(0.05, self.sim_hours - elapsed_h)  # a restarted drive runs what is left of the soak
        cmd = [sys.executable, "-m", "encoder_fleet.cli", "agent", "--device", device, "--connect", self.endpoint]
        cmd += ["--seed", str(self.devices.index(device)), "--sim-hours", f"{hours:.4f}", "--insecure"]
        cmd += ["--sample-hz", str(SAMPLE_HZ), "--real-time-factor", str(REAL_TIME_FACTOR)]
        cmd += ["--outbox", str(self.folder / f"{device}.outbox"), "--log-level", "error"]
        self.agents[device] = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)

    # --- background: memory and bad messages ------------------------------------------------------

    def _sample_memory(self) -> None:
        while not self._stop.wait(1.0):
            proc = self.service
            try:
                status = Path(f"/proc/{proc.pid}/status").read_text()
                rss_kb = int(next(line for line in status.splitlines() if line.startswith("VmRSS:")).split()[1])
                self.result.memory_mb.append(round(rss_kb / 1024.0, 1))
            except (OSError, StopIteration, AttributeError, ValueError):
                pass  # between a kill and the restart

    def _bad_actor(self) -> None:
        import zenoh

        from fleet_wire.session import agent_session_config

        session = zenoh.open(agent_session_config([self.endpoint]))  # rides out the router's restarts
        try:
            i = 0
            while not self._stop.wait(0.2):
                suffix, payload = BAD_MESSAGES[i % len(BAD_MESSAGES)]
                session.put(keys.key("soak-bad", suffix), payload)
                self.result.bad_sent += 1
                i += 1
        finally:
            session.close()

    # --- the run -----------------------------------------------------------------------------------

    def log(self, what: str) -> None:
        line = f"{time.monotonic() - self.started:7.1f} s  {what}"
        self.result.events.append(line)
        print(line, flush=True)

    def run(self) -> SoakResult:
        self.start_service()
        for device in self.devices:
            self.start_agent(device)
        threads = [threading.Thread(target=f, daemon=True) for f in (self._sample_memory, self._bad_actor)]
        for t in threads:
            t.start()
        chaos_until = self.started + self.duration_s * 0.85  # the last stretch lets everyone catch up
        try:
            while time.monotonic() < chaos_until:
                time.sleep(self.rng.uniform(4.0, 10.0))
                if time.monotonic() >= chaos_until:
                    break
                self.one_fault()
            self.log("faults end; the agents finish and drain")
            for device, proc in self.agents.items():
                try:
                    proc.wait(timeout=self.duration_s + 120)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    self.log(f"{device} did not finish")
        finally:
            self._stop.set()
            for t in threads:
                t.join(timeout=10)
            for proc in self.agents.values():
                if proc.poll() is None:
                    proc.kill()
            if self.service is not None and self.service.poll() is None:
                self.service.terminate()
                self.service.wait(timeout=30)
        self.count()
        return self.result

    def one_fault(self) -> None:
        fault = self.rng.choice(["kill service", "kill service", "disk full", "kill agent"])
        if fault == "kill service":
            self.kill_service()
            self.log("service (and its router) killed")
            time.sleep(self.rng.uniform(0.5, 3.0))
            self.start_service()
            self.log("service restarted")
        elif fault == "disk full":
            self.kill_service()
            self.start_service(quota_mb=0.001)  # below what it holds: not one page more
            self.log("service restarted on a full disk")
            time.sleep(self.rng.uniform(2.0, 5.0))
            self.kill_service()
            self.start_service()
            self.log("space freed, service restarted")
        else:
            device = self.rng.choice(self.devices)
            proc = self.agents[device]
            if proc.poll() is None:
                proc.kill()
                proc.wait()
                self.log(f"agent {device} killed")
                time.sleep(self.rng.uniform(0.2, 2.0))
            self.start_agent(device)
            self.log(f"agent {device} restarted (its drive's clock at 0 again)")

    def count(self) -> None:
        """Sent: every seq an agent issued (its outbox's last_seq). Stored once, lost and doubled from the
        database: a seq missing, or a stretch of one drive's time held by two windows."""
        r = self.result
        conn = sqlite3.connect(f"file:{self.db}?mode=ro", uri=True)
        try:
            for device in self.devices:
                outbox = sqlite3.connect(f"file:{self.folder / f'{device}.outbox'}?mode=ro", uri=True)
                try:
                    row = outbox.execute("SELECT value FROM meta WHERE key = 'last_seq'").fetchone()
                finally:
                    outbox.close()
                sent = int(row[0]) if row else 0
                rows = conn.execute(
                    "SELECT seq, window_start, window_end FROM windows WHERE device = ? ORDER BY seq", (device,)
                ).fetchall()
                seqs = [s for s, _, _ in rows]
                r.sent += sent
                r.stored += len(set(seqs) & set(range(1, sent + 1)))
                r.lost += len(set(range(1, sent + 1)) - set(seqs))
                r.doubled += len(seqs) - len(set(seqs))
                r.doubled += sum(b[1] < a[2] for a, b in zip(rows, rows[1:]))  # overlapping drive time
        finally:
            conn.close()


def memory_flat(samples: list[float]) -> tuple[float, float, bool]:
    """(median of the first third, median of the last third, flat: the last within 25 % of the first)."""
    if len(samples) < 6:
        return float("nan"), float("nan"), False
    third = len(samples) // 3
    first = sorted(samples[:third])[third // 2]
    last = sorted(samples[-third:])[third // 2]
    return first, last, last <= 1.25 * first


def run(minutes: float, agents: int, seed: int, json_path: str | None, out: str | None) -> int:
    folder = Path(out) if out else Path(tempfile.mkdtemp(prefix="encoder-fleet-soak-"))
    folder.mkdir(parents=True, exist_ok=True)
    for old in folder.glob("*.sqlite*"):
        old.unlink()
    for old in folder.glob("*.outbox*"):
        old.unlink()
    soak = Soak(folder, agents, minutes, seed)
    print(
        f"bench-soak: {agents} agents, {minutes:g} min, {soak.sim_hours:.1f} drive hours each at "
        f"{REAL_TIME_FACTOR:g}x real time; faults at random (seed {seed}); files in {folder}",
        flush=True,
    )
    r = soak.run()
    first, last, flat = memory_flat(r.memory_mb)
    print()
    print("| sent | stored once | lost | doubled | bad messages | service restarts | memory MB (first → last, max) |")
    print("|---|---|---|---|---|---|---|")
    print(
        f"| {r.sent} | {r.stored} | {r.lost} | {r.doubled} | {r.bad_sent} | {r.restarts} | "
        f"{first:.0f} → {last:.0f}, max {max(r.memory_mb, default=float('nan')):.0f} |"
    )
    print(f"memory {'flat' if flat else 'NOT flat'}; {'PASS' if r.lost == 0 and r.doubled == 0 and flat else 'FAIL'}")
    if json_path:
        Path(json_path).write_text(json.dumps(r.to_json(), indent=1) + "\n")
    return 0 if r.lost == 0 and r.doubled == 0 else 1


def register(sub) -> None:
    from .argtypes import non_negative_int, positive_float, positive_int

    p = sub.add_parser(
        "bench-soak",
        help="agents publishing while the service, the router and agents are killed, bad messages mixed in and "
        "the disk filled and freed: windows sent, stored once, lost, doubled, and the service's memory",
    )
    p.add_argument("--minutes", type=positive_float, default=5.0, help="how long the soak runs")
    p.add_argument("--agents", type=positive_int, default=3, help="agent processes")
    p.add_argument("--seed", type=non_negative_int, default=0, help="seed of the fault schedule")
    p.add_argument("--out", help="folder for the database and outboxes (default: a new temporary folder)")
    p.add_argument("--json", metavar="FILE", help='also write {"sent", "stored", "lost", "doubled", "memory_mb"}')
    p.set_defaults(func=lambda args: run(args.minutes, args.agents, args.seed, args.json, args.out))
