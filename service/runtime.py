"""The running service: Zenoh ingest and queries, the refit-and-rollout loop, liveliness.

By default it embeds a Zenoh router (mode "router", listening on a local endpoint); with connect
endpoints it joins external routers as a client instead.
"""

from __future__ import annotations

import ipaddress
import itertools
import json
import logging
import math
import queue
import socket
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import zenoh
from prometheus_client import Histogram

from encoder_core.correction import BandedCorrection
from encoder_core.monitor_causes import cause as cause_of
from encoder_core.samples import InputError
from encoder_core.stats import WindowStats, normalisation_scale
from encoder_core.thermal import lag_to_send
from fleet_wire import keys
from fleet_wire import messages as wire
from fleet_wire.session import set_on_signals
from service.cluster import Partitions
from service.db import is_postgres, redacted, sqlite_path
from service.monitor import Monitor
from service.refit import (
    MIN_BAND_SAMPLES,
    NO_BENCH_LOCUS,
    STEP_CAUSES,
    STEP_OPEN_S,
    RefitResult,
    bench_anchors,
    prefetch_band_fits,
    refit_device,
    step_moved_bands,
)
from service.rollout import DeviceHeld, Rollouts
from service.store import Store
from service.trial import WATCH_S, TrialEvidence, Verdict, changed_bands, watch_against_factory
from service.trial import judge as default_judge

log = logging.getLogger("service")
MAX_BATCH = 500  # messages per ingest transaction
MIN_PASS_S = 0.05  # the least wall time between two refit (or monitor) passes: at 3,600x, 3 drive-minutes
MAX_QUEUED = 20_000  # messages waiting for the writer (~80 MB of windows at most)
QUEUE_WAIT_S = 2.0  # how long a message's hand-off (the pump's, or Zenoh's callback's) waits for room, then dropped
PUMP_CAPACITY = 1_000  # windows waiting in Zenoh's channel for the thread that queues them (PumpedSubscriber)
PUMP_DRAIN_S = 5.0  # how long undeclaring waits for that thread to hand on what the channel still holds
# storing comes first: while more than a batch waits for the writer, the monitor and refit passes wait between
# devices, up to STORE_FIRST_MAX_WAIT_S each (analysis catches up; a flood never starves it)
STORE_FIRST_BACKLOG = MAX_BATCH
STORE_FIRST_MAX_WAIT_S = 0.25
RATE_PER_KEY = 200.0  # messages/s one key may send on average (an agent sends one window a minute) …
BURST_PER_KEY = 2_000.0  # … and at once (a catch-up resends at most 500 per sync)
# liveliness, factory sets and queries waiting for the control thread: a process's whole share of tokens at
# start (each item is a reference, not a payload)
MAX_CONTROL = 200_000
# after this process takes its partitions (a start, a hand-over): how long agents get to reconnect before a device
# stored as online with no liveliness token is taken as gone (one that left while no process served it sends no
# "left" event, and stayed online and ok for good)
ONLINE_RECHECK_S = 60.0
MAX_FACTORY_RUN = 100  # factory sets stored in one transaction: the writer waits for at most one such commit
_NO_JOB = object()  # the control loop holds no job taken from its queue (None there means stop)
LAG_RETRY_AFTER_S = 86_400.0  # a lag refused this long before the agent came back online is offered again
MAX_ALIVE_UNKNOWN = 10_000  # liveliness tokens of devices not yet heard from, remembered for when they speak
# drive hours a band's sum remembers: short enough to follow a step within half a day, long enough for the
# drift model that pools all bands (bench-fleet-accuracy: 12 h beat 24 h and a week at 0.5 and 20 Hz)
BAND_HORIZON_H = 12.0
# drive time a set stays on trial at most: a set whose changed bands the drive does not visit meanwhile is kept on
# the refit's own uncertainty rather than freezing the device's refits until the temperature comes back
# (bench-fleet-accuracy at 0.5 Hz: with no limit the guard cut the median gain from 3.0x to 1.2x)
TRIAL_MAX_S = 3600.0
# drive time between two refits of one device: the cadence bench-fleet-accuracy measured the refit at, and what
# keeps the refit loop ahead of the fleet (a refit costs ~75 ms; once per window it would be 1,000 drives per core,
# once per drive-hour ~48,000). A set on trial is judged at every pass, and an offset step refits at once.
REFIT_EVERY_S = 3600.0
# drive time between two watches of one device's running set against its factory set (service/trial.py): a step
# the monitor does not name (gain, axis) is caught within this, not at the next refit (bench-fleet-accuracy, 48
# drives: worse hours 21 -> 16 at 0.5 Hz and 52 -> 40 at 20 Hz)
WATCH_EVERY_S = 900.0
PREFETCH_DEVICES = 32  # a pass fits the band sums of this many due devices in one batch (prefetch_band_fits)
# wall seconds after which a set the drive's windows do not show yet is put again: a set is otherwise put once, and
# an agent cut off from the router at that moment would run its old set for good (the agent ignores a version it has)
RESEND_AFTER_S = 60.0
# … or after this much drive time, whichever comes first: a fleet replayed at 3,600x real time would otherwise wait
# 60 drive-hours for it (an agent applies a set at its next window: a few windows of the longest, 600 s)
RESEND_AFTER_DRIVE_S = 1800.0
# wall seconds between two retention passes (`service --keep-days`): each deletes what has aged out since the last
PRUNE_EVERY_S = 600.0
# … and the most one pass takes of the refit thread: the rest of a backlog (the first pass over a year of windows,
# hours) goes on in the next passes, a refit pass between, from the device it stopped at
PRUNE_PASS_S = 2.0


@dataclass
class ServiceCounters:
    ingested: dict[str, int] = field(default_factory=dict)  # status -> count ('stored', 'duplicate', reasons)
    refits: int = 0
    rollouts: int = 0  # sets published: fits and rollbacks
    rollbacks: int = 0
    resends: int = 0  # sets put again: the drive's windows did not show them RESEND_AFTER_S after they went out
    storage_failures: int = 0  # batches the database refused (disk full, read-only, I/O): agents resend them
    storage_error: str | None = None  # the last refusal, until a batch is stored again (/healthz fails meanwhile)
    database_reconnects: int = 0  # PostgreSQL sessions lost (server restart, failover) and opened again
    analysis_waited_s: float = 0.0  # the monitor and refit passes' waits for a backlog to be stored (_store_first)
    pruned_windows: int = 0  # deleted by retention (--keep-days)
    pruned_dead_letters: int = 0
    # windows and acks this process stored, by the device's partition (GET /cluster: who served what)
    stored_by_partition: list[int] = field(default_factory=lambda: [0] * keys.PARTITIONS)
    # seconds from a message's arrival to its commit, and of one device's refit (read by service.observability)
    ingest_latency: Histogram = field(
        default_factory=lambda: Histogram(
            "encoder_fleet_ingest_latency_seconds",
            "Seconds from a message's arrival to the commit of its batch.",
            buckets=(0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0),
            registry=None,
        )
    )
    refit_latency: Histogram = field(
        default_factory=lambda: Histogram(
            "encoder_fleet_refit_latency_seconds",
            "Seconds one device's refit (or trial judgement) took.",
            buckets=(0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5),
            registry=None,
        )
    )

    def count(self, status: str) -> None:
        self.ingested[status] = self.ingested.get(status, 0) + 1

    def snapshot(self) -> dict:
        return {
            "ingested": dict(self.ingested),
            "refits": self.refits,
            "rollouts": self.rollouts,
            "rollbacks": self.rollbacks,
            "resends": self.resends,
            "storage_failures": self.storage_failures,
            "database_reconnects": self.database_reconnects,
            "analysis_waited_s": self.analysis_waited_s,
            "pruned_windows": self.pruned_windows,
            "pruned_dead_letters": self.pruned_dead_letters,
        }


class KeyRateLimit:
    """A token bucket per Zenoh key: `rate` messages/s on average, `burst` at once. Bounded memory: buckets
    that have refilled are forgotten when there are too many."""

    MAX_KEYS = 200_000

    def __init__(self, rate: float, burst: float):
        self.rate, self.burst = rate, burst
        self._buckets: dict[str, tuple[float, float]] = {}  # key -> (tokens, at)
        self._lock = threading.Lock()

    def allow(self, key: str) -> bool:
        now = time.monotonic()
        with self._lock:
            tokens, at = self._buckets.get(key, (self.burst, now))
            tokens = min(self.burst, tokens + max(0.0, now - at) * self.rate)
            if len(self._buckets) >= self.MAX_KEYS:
                self._buckets = {k: v for k, v in self._buckets.items() if v[0] + (now - v[1]) * self.rate < self.burst}
            if tokens < 1.0:
                self._buckets[key] = (tokens, now)
                return False
            self._buckets[key] = (tokens - 1.0, now)
            return True


class PumpedSubscriber:
    """A subscriber whose samples wait in Zenoh's FIFO channel (up to PUMP_CAPACITY, then Zenoh waits: the senders'
    congestion control) and are handed to `handler` by a thread of ours, as fast as it takes them. A callback runs on
    Zenoh's thread, which takes the interpreter lock for every sample: at a few thousand windows a second the writer
    then waits for the lock at every one of them (bench-fleet, 1,000 devices: the first second's batches of 500
    stored at 100-320 ms each instead of ~40, and 7,300-8,600 windows/s end to end against 9,800-10,200 pumped)."""

    def __init__(self, session: zenoh.Session, key_expr: str, handler: Callable[[zenoh.Sample], None]):
        self._subscriber = session.declare_subscriber(key_expr, zenoh.handlers.FifoChannel(PUMP_CAPACITY))
        self._thread = threading.Thread(target=self._pump, args=(handler,), name=f"pump {key_expr}", daemon=True)
        self._thread.start()

    def _pump(self, handler: Callable[[zenoh.Sample], None]) -> None:
        for sample in self._subscriber:  # ends when the subscriber is undeclared
            try:
                handler(sample)
            except Exception:  # the pump must outlive one sample, as Zenoh's callback thread does
                log.exception("handling a sample failed")

    def undeclare(self) -> None:
        """Undeclare the subscriber, then wait until what its channel held has been handed on (a healthy writer
        takes a full channel in well under a second), PUMP_DRAIN_S at most: a writer that has stopped taking windows
        would hold a stop or a partition's hand-over for QUEUE_WAIT_S a window. What is left the agents send again."""
        self._subscriber.undeclare()
        self._thread.join(PUMP_DRAIN_S)
        if self._thread.is_alive():
            log.warning(
                "%s: windows still waiting after %.0f s are left to their agents to send again",
                self._thread.name,
                PUMP_DRAIN_S,
            )


class FleetService:
    def __init__(
        self,
        store: Store,
        session: zenoh.Session,
        *,
        refit_interval_s: float = 2.0,
        min_band_samples: int = MIN_BAND_SAMPLES,
        signer=None,
        guard=None,
        monitor_interval_s: float = 0.5,
        judge: Callable[[TrialEvidence], Verdict] = default_judge,
        max_queued: int = MAX_QUEUED,
        rate_per_key: float = RATE_PER_KEY,
        burst_per_key: float = BURST_PER_KEY,
        queue_wait_s: float = QUEUE_WAIT_S,
        clock: Callable[[], float] = time.time,
        refit_every_s: float = REFIT_EVERY_S,
        member: str | None = None,
        resend_after_s: float = RESEND_AFTER_S,
        online_recheck_s: float = ONLINE_RECHECK_S,
        keep_days: float | None = None,
    ):
        self.store = store
        # retention (prune): windows older than this in each drive's own time, dead letters in the service's; None
        # keeps everything. Needs the store's band horizon: without one a band's sum holds every window it had.
        if keep_days is not None and not (keep_days > 0 and store.band_horizon_s):
            raise InputError("--keep-days needs a positive number of days and a band horizon (--band-horizon-h)")
        self.keep_s = None if keep_days is None else keep_days * 86_400.0
        self._pruned_at: float | None = None  # monotonic: the last retention pass
        self._prune_resume: str | None = None  # the device a pass out of time stopped at: the next one begins there
        self.online_recheck_s = online_recheck_s
        self._online_recheck_at: float | None = None  # monotonic; set when partitions are taken
        self._token_seen: dict[str, float] = {}  # device -> when (monotonic) its token last came or went
        self.judge = judge  # the guard's verdict on a set on trial (service/trial.py)
        self.signer = signer  # fleet_wire.security.SetSigner: every published set is signed
        self.guard = guard  # service.guard.IngestGuard: registry, forged and replayed acks
        self.session = session
        self.refit_interval_s = refit_interval_s
        self.min_band_samples = min_band_samples
        self.counters = ServiceCounters()
        self._declared: list = []
        self._stop = threading.Event()
        # the refit and monitor passes run as soon as windows are stored (at most every MIN_PASS_S), not only every
        # refit_interval_s / monitor_interval_s: their rules are in drive time, and a drive replayed at 3,600 times
        # real time sends an hour of windows in a second (see _paced)
        self._wake_refit, self._wake_monitor = threading.Event(), threading.Event()
        self._thread: threading.Thread | None = None
        self._watermarks: dict[str, int] = {}
        # bounded: when the writer falls behind, the pump waits (back-pressure to the router and to agents
        # that put with CongestionControl.BLOCK) rather than memory growing; past QUEUE_WAIT_S it drops and counts
        self._inbox: queue.Queue = queue.Queue(maxsize=max_queued)
        self._rate = KeyRateLimit(rate_per_key, burst_per_key)
        self.queue_wait_s = queue_wait_s
        self._writer = threading.Thread(target=self._write_loop, name="ingest", daemon=True)
        self._changed: set[str] = set()  # devices with windows stored since their last refit
        self.refit_every_s = refit_every_s
        self._fitted_at: dict[str, float] = {}  # device -> drive time of its last refit
        self._no_bench_locus_said: set[str] = set()  # devices whose missing bench locus was logged (fit)
        self._watched_at: dict[str, float] = {}  # device -> drive time of its last watch against the factory
        self.resend_after_s = resend_after_s
        self._clock = clock
        self._resent: dict[str, tuple[int, float, float]] = {}  # device -> (version, wall, drive time) of last resend
        self._refit_now: set[str] = set()  # devices whose next pass refits regardless of the cadence (a step)
        self._resume_pending: set[str] = set()  # devices whose step the database refused to act on: taken up again
        self._step_moves: dict[str, tuple] = {}  # device -> the step the monitor measured (cause, size, raised_at)
        # device -> raised_at of the newest step whose band memory this process restarted (or found restarted)
        self._restarted_for: dict[str, float] = {}
        self._corrections: dict[tuple[str, int], BandedCorrection] = {}  # decoded coefficient sets
        self._lock = threading.Lock()
        self._alive_unknown: dict[str, float] = {}  # tokens of devices that have sent nothing valid yet
        # drift monitor (service/monitor.py): devices with windows it has not seen, fed on its own thread
        self.monitor = Monitor(store, publish=self._publish_alarm)
        self.monitor_interval_s = monitor_interval_s
        self._monitor_changed: set[str] = set()
        self._monitor_thread: threading.Thread | None = None
        # staged rollouts (service/rollout.py): stepped on the refit thread, after each refit pass
        self.rollouts = Rollouts(store, self, clock=clock)
        # which devices' keys this process serves (service/cluster.py): all of them unless `member` names it
        # one of several processes sharing the fleet
        self.partitions = Partitions(self, member)
        # factory sets, liveliness and queries touch the database: one thread answers them in turn, so that
        # Zenoh's own threads only hand over (and a process serving many partitions needs no thread for each)
        self._control: queue.Queue = queue.Queue(maxsize=MAX_CONTROL)
        self._control_thread = threading.Thread(target=self._control_loop, name="control", daemon=True)

    # --- lifecycle ---------------------------------------------------------------------------------

    def start(self) -> FleetService:
        self._control_thread.start()
        # any process answers for any device from the shared history: an agent that starts asks for its set here
        self._declared.append(
            self.session.declare_queryable(keys.every(keys.COEFFICIENTS), self._handed(self._on_coefficients_query))
        )
        self.partitions.start()
        if self.partitions.standalone:  # after a restart, look at everyone once (a cluster member: as it adopts)
            self._changed.update(d["id"] for d in self.store.devices())
            self._monitor_changed.update(self._changed)
            self._resume_step_moves(lambda device: True)
            self._online_recheck_at = time.monotonic() + self.online_recheck_s
        if self.monitor_interval_s > 0:
            self._monitor_thread = threading.Thread(target=self._monitor_loop, name="monitor", daemon=True)
            self._monitor_thread.start()
        self._writer.start()
        if self.refit_interval_s > 0:
            self._thread = threading.Thread(target=self._refit_loop, name="refit", daemon=True)
            self._thread.start()
        return self

    def stop(self) -> None:
        self.partitions.stop_receiving()
        for entity in reversed(self._declared):
            entity.undeclare()
        self._declared.clear()
        self._stop.set()
        self._wake_refit.set()
        self._wake_monitor.set()
        self._control.put(None)
        self._control_thread.join()
        if self._thread is not None:
            self._thread.join()
        self._inbox.put(None)  # the writer stores what is queued, then ends
        self._writer.join()
        if self._monitor_thread is not None:
            self._monitor_thread.join()
        self.monitor_pass()  # what the writer stored last is monitored too
        self.monitor.flush()
        self.partitions.release()  # only now: the partitions' last batch is written under their locks

    # --- partitions (service/cluster.py) -----------------------------------------------------------

    def _declare_partition(self, part: int | None) -> list:
        """The Zenoh entities that serve one partition's devices (None: every partition). Windows and acks wait in
        one Zenoh channel for a thread of ours that hands them to the writer's queue in the order they came
        (PumpedSubscriber); the other callbacks run on Zenoh's thread and hand their work to the control thread."""
        s = self.session
        return [
            PumpedSubscriber(s, keys.every_to_service(part), self._enqueue_in_order),
            s.declare_subscriber(keys.every(keys.FACTORY, part), self._handed(self._on_factory)),
            s.declare_queryable(keys.every(keys.RECEIVED, part), self._handed(self._on_received_query)),
            s.liveliness().declare_subscriber(keys.every(keys.ALIVE, part), self._handed(self._on_alive), history=True),
        ]

    def _handed(self, handler: Callable) -> zenoh.handlers.Callback:
        """A Zenoh callback that hands the sample or query to the control thread (never waiting: a query not
        answered is asked again, a factory set announced again, a token seen at the next start)."""

        def hand(item) -> None:
            try:
                self._control.put_nowait((handler, item))
            except queue.Full:
                with self._lock:
                    self.counters.count("overloaded")
                if isinstance(item, zenoh.Query):
                    item.drop()

        return zenoh.handlers.Callback(hand, indirect=False)

    def _control_loop(self) -> None:
        job = self._control.get()
        while job is not None:  # None: stop
            handler, item = job
            if handler != self._on_factory:
                self._control_job(handler, item)
                job = self._control.get()
                continue
            # a fleet of agents starting at once announces its factory sets together: a run of them queued in a row
            # is stored in one transaction (one disk sync), in the order they came, as the writer stores windows. One
            # at a time, each commit held the store's lock from the writer (bench-fleet, 1,000 devices: 4 ms each,
            # the last stored 2 s after the last window). The job that ends the run (or the stop) is the next one.
            run, job = [item], _NO_JOB
            while len(run) < MAX_FACTORY_RUN and job is _NO_JOB:
                try:
                    job = self._control.get_nowait()
                except queue.Empty:
                    break
                if job is not None and job[0] == self._on_factory:
                    run.append(job[1])
                    job = _NO_JOB
            self._control_job(self._on_factories, run)
            if job is _NO_JOB:
                job = self._control.get()

    def _control_job(self, handler: Callable, item) -> None:
        try:
            handler(item)
        except Exception:
            what = f"a run of {len(item)}" if isinstance(item, list) else getattr(item, "key_expr", item)
            log.exception("%s failed on %s", handler.__name__, what)
        finally:
            if isinstance(item, zenoh.Query):
                item.drop()  # the query's final answer: replies end here

    def forget_partitions(self, parts: set[int]) -> None:
        """Drop what this process remembers of some partitions' devices: another process may write them now."""
        with self._lock:
            self._watermarks = {d: m for d, m in self._watermarks.items() if keys.partition(d) not in parts}
            self._fitted_at = {d: t for d, t in self._fitted_at.items() if keys.partition(d) not in parts}
            self._watched_at = {d: t for d, t in self._watched_at.items() if keys.partition(d) not in parts}
            self._step_moves = {d: m for d, m in self._step_moves.items() if keys.partition(d) not in parts}
            self._restarted_for = {d: t for d, t in self._restarted_for.items() if keys.partition(d) not in parts}
            self._resume_pending = {d for d in self._resume_pending if keys.partition(d) not in parts}
        self.store.forget_partitions(parts)
        self.monitor.reload(lambda device: keys.partition(device) in parts)

    def cluster(self) -> dict:
        """What this process serves among the live service processes (GET /cluster)."""
        with self._lock:
            stored = list(self.counters.stored_by_partition)
        held = sorted(self.partitions.held)
        return {
            "member": self.partitions.member,
            "members": self.partitions.members(),
            "partitions": keys.PARTITIONS,
            "served": [keys.partition_chunk(p) for p in held],
            "leads_rollouts": self.partitions.leads(),
            "stored_by_partition": {keys.partition_chunk(p): n for p, n in enumerate(stored) if n},
        }

    def adopt_partitions(self, parts: set[int]) -> None:
        """Partitions just taken: their devices are looked at once, as after a restart."""
        devices = [d for d in self.store.device_ids() if keys.partition(d) in parts]
        with self._lock:
            self._changed.update(devices)
            self._monitor_changed.update(devices)
            self._online_recheck_at = time.monotonic() + self.online_recheck_s
        self._resume_step_moves(lambda device: keys.partition(device) in parts)

    def _resume_step_moves(self, owned: Callable[[str], bool]) -> None:
        """The steps whose move no set has made yet, pending again as the monitor's alarm left them: the process
        that raised one kept its move in memory only, so a restart or a partition handed over lost it, and the
        drive ran the set from before the step until band memory refilled (a day, for a drive that dwells)."""
        newest: dict[str, dict] = {}  # device -> its newest open step alarm
        for cause in STEP_CAUSES:
            for alarm in self.store.alarms(cause=cause, open_=True, limit=1_000_000):
                known = newest.get(alarm["device"])
                if owned(alarm["device"]) and (known is None or alarm["raised_at"] > known["raised_at"]):
                    newest[alarm["device"]] = alarm
        for device, alarm in newest.items():
            with self.partitions.serving(device) as mine:  # band memory restarted: not while handed over
                if not mine:
                    continue
                since = self.store.versions_since(device, alarm["raised_at"])
                if any(self._bands_made_at(device, v) >= alarm["raised_at"] for v in since):
                    with self._lock:  # its memory was restarted when the step was published, and a set made since
                        self._restarted_for[device] = alarm["raised_at"]
                    continue  # a set with bands made since (the move, or a fit after the step; a rollback's are older)
                # the process may have stopped between storing the alarm and publishing it (which restarts band
                # memory): restart it here too (it keeps the same windows if it was)
                self.store.restart_band_memory(device, after=alarm["raised_at"])
                with self._lock:
                    self._restarted_for[device] = alarm["raised_at"]
                    pending = self._step_moves.get(device)
                    if pending is None or pending[2] < alarm["raised_at"]:  # the newest step's move, as _act_on_alarm
                        self._step_moves[device] = (alarm["cause"], alarm["parameters"], alarm["raised_at"])
                        self._changed.add(device)
                        self._refit_now.add(device)

    def checks(self) -> dict[str, str]:
        """Component -> 'ok' or what is wrong (for /healthz and /readyz)."""
        return {
            "router": "closed" if self.session.is_closed() else "ok",
            "ingest": "ok" if self._writer.is_alive() else "the ingest writer is not running",
            "refit": "ok" if self._thread is None or self._thread.is_alive() else "the refit loop is not running",
            "storage": "ok" if self.counters.storage_error is None else self.counters.storage_error,
        }

    # --- ingest ------------------------------------------------------------------------------------

    def _enqueue_in_order(self, sample: zenoh.Sample) -> None:
        """Windows and acks to the writer's queue, from the one channel that keeps them in the order they came (the
        store sets a device's current version from an ack and the windows before it in that order). The other
        agent-to-service keys that channel matches have handlers of their own (factory sets, the received query)."""
        # the suffix alone, not keys.split: a window whose key is malformed in another way still goes on, to be
        # dead-lettered and counted as bad_key by the store
        parts = str(sample.key_expr).split("/")
        if len(parts) == 4 and parts[2] in (keys.STATS, keys.ACK):
            self._enqueue(sample)

    def _enqueue(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        if not self._rate.allow(key):
            # a peer sending faster than any agent does: dropped unread and counted; a real agent's windows
            # are still in its outbox and come again
            with self._lock:
                self.counters.count("rate_limited")
            return
        payload = sample.payload.to_bytes()
        if not self._admitted(key, payload):
            return
        try:
            self._inbox.put((key, payload, time.monotonic()), timeout=self.queue_wait_s)
        except queue.Full:
            with self._lock:
                self.counters.count("overloaded")

    def _admitted(self, key: str, payload: bytes) -> bool:
        """The guard's checks (service/guard.py); what it refuses is dead-lettered and counted."""
        refused = self.guard.refuse(key, payload) if self.guard is not None else None
        if refused is None:
            return True
        self.store.dead_letter(key, refused[0], refused[1], payload)
        with self._lock:
            self.counters.count(refused[0])
        return False

    def _write_loop(self) -> None:
        """Group commit: whatever arrived while the last batch was written goes in one transaction."""
        done = False
        while not done:
            batch = [self._inbox.get()]
            while len(batch) < MAX_BATCH and not self._inbox.empty():
                batch.append(self._inbox.get_nowait())
            done = any(item is None for item in batch)
            arrived = [item[2] for item in batch if item is not None]
            items = [item[:2] for item in batch if item is not None]
            if not items:
                continue
            try:
                self._renew_if_lost()
                with self.partitions.lock:  # a partition changes hands between batches, never inside one
                    items, statuses = self._store_served(items)
            except Exception as exc:  # the disk, not the data: nothing of the batch was committed, so no watermark
                log.exception("storing %d messages failed; the agents will resend them", len(items))
                with self._lock:  # seen in /healthz and /metrics until a batch is stored again
                    self.counters.storage_failures += 1
                    self.counters.storage_error = f"the database refused the last batch: {exc}"
                continue  # moved past it, and the loop must keep serving what comes next
            committed = time.monotonic()
            for t in arrived:
                self.counters.ingest_latency.observe(committed - t)
            came_alive = []
            with self._lock:
                self.counters.storage_error = None
                for (key, _), status in zip(items, statuses):
                    self.counters.count(status)
                    if status != "stored":
                        continue
                    device, suffix = keys.split(key)  # a stored message had a well-formed key
                    self.counters.stored_by_partition[keys.partition(device)] += 1
                    if suffix == keys.STATS:
                        self._changed.add(device)
                        self._monitor_changed.add(device)
                    elif suffix == keys.ACK:
                        self._changed.add(device)  # a refused set is answered in the next refit pass
                    if self._alive_unknown and (since := self._alive_unknown.pop(device, None)) is not None:
                        came_alive.append((device, since))
            if "stored" in statuses:
                self._wake_monitor.set()
                self._wake_refit.set()
            for device, since in came_alive:  # its token came before its first valid message
                try:
                    self.store.set_online(device, True)
                except Exception:  # the writer must go on (it died here): the device's next stored message retries
                    log.exception("marking %s online failed; retried with its next stored message", device)
                    with self._lock:
                        self._alive_unknown.setdefault(device, since)

    def _renew_if_lost(self) -> None:
        """PostgreSQL dropped the session (restarted, failed over): open it again, and take the partitions again
        (their locks went with the session). Called outside the partitions' lock, from the loops that write."""
        try:
            if self.store.reconnect_if_lost():
                log.warning("the database connection was lost and is open again")
                with self._lock:
                    self.counters.database_reconnects += 1
                self.partitions.connection_renewed()
        except Exception:
            log.exception("reopening the database connection failed")

    def _store_served(self, items: list[tuple[str, bytes]]) -> tuple[list, list[str]]:
        """Store the messages of the partitions this process holds; the rest (queued before a hand-over) are
        dropped and counted: their agents send them again, to the partition's new process."""
        if not self.partitions.standalone:
            held = self.partitions.held
            served = [(k, p) for k, p in items if (parts := keys.split(k)) is None or keys.partition(parts[0]) in held]
            if len(served) < len(items):
                with self._lock:
                    for _ in range(len(items) - len(served)):
                        self.counters.count("not_served")
            items = served
        return items, (self.store.ingest_many(items) if items else [])

    def _on_factories(self, samples: list[zenoh.Sample]) -> None:
        """Factory sets in one transaction; each in a savepoint of its own, so a bad one alone is refused."""
        with self.store.transaction():
            for sample in samples:
                self._control_job(self._on_factory, sample)
                if not self.store.transaction_open:  # the database ended it (a full disk): the agents announce again
                    break

    def _on_factory(self, sample: zenoh.Sample) -> None:
        """An agent that found no set here tells what its factory wrote: it becomes version 0."""
        key, payload = str(sample.key_expr), sample.payload.to_bytes()
        if not self._admitted(key, payload):
            return
        try:
            device = wire.device_from_key(key)
            msg = wire.decode("coefficients", payload, key_device=device)
            if msg["basis"] != "factory" or msg["version"] != 0:
                raise wire.WireError("schema", f"{key}: a factory set must have basis 'factory' and version 0")
        except wire.WireError as exc:
            self.store.dead_letter(key, exc.reason, str(exc), payload)
            return
        # the look-up, the set and its publication together, in a savepoint of the run: one that fails is undone
        # alone (on PostgreSQL a failed statement outside it would abort the whole run's transaction)
        with self.store.transaction():
            if self.store.current_coefficients(device) is None:
                self.store.insert_coefficient_set(msg)
                self.store.mark_published(device, 0)

    def _on_alive(self, sample: zenoh.Sample) -> None:
        try:
            device = wire.device_from_key(sample.key_expr)
        except wire.WireError:
            return
        if self.guard is not None and not self.guard.admits(device):
            return
        with self._lock:
            self._token_seen[device] = time.monotonic()
        with self.partitions.serving(device) as mine:  # a token of a partition handed over is its new owner's
            if mine:
                self._alive(device, sample.kind == zenoh.SampleKind.PUT)

    def _recheck_online_if_due(self) -> None:
        """Devices the database has online whose liveliness token is not there, ONLINE_RECHECK_S after this process
        took their partitions: each is gone as if its token had left now (stored offline, the monitor's offline
        alarm). A token that leaves while no process serves the device is heard by nobody, and the replay of the
        tokens present at start names only those still there: a drive that stopped while the service was down was
        online and ok for good (a second reader)."""
        with self._lock:
            due = self._online_recheck_at is not None and time.monotonic() >= self._online_recheck_at
            if due:
                self._online_recheck_at = None
        if not due:
            return
        asked_at = time.monotonic()
        try:
            replies = self.session.liveliness().get(keys.every(keys.ALIVE), timeout=5.0)
            alive = {str(r.ok.key_expr) for r in replies if r.ok is not None}
            online = self.store.online_device_ids()
        except Exception:  # the session or the database: asked again at the next pass
            log.exception("asking which devices hold a liveliness token failed")
            with self._lock:
                self._online_recheck_at = time.monotonic()
            return
        for device in online:
            if keys.key(device, keys.ALIVE) not in alive and self.partitions.serves(device):
                try:
                    self._control.put_nowait((self._gone_unheard, (device, asked_at)))
                except queue.Full:
                    with self._lock:
                        self._online_recheck_at = time.monotonic()  # the next pass asks again

    def _gone_unheard(self, item: tuple[str, float]) -> None:
        device, asked_at = item
        with self._lock:
            if self._token_seen.get(device, -math.inf) > asked_at:
                return  # its token came (or went, heard) since the question: that event said it
        with self.partitions.serving(device) as mine:
            if mine:
                log.warning("no liveliness token since the partitions were taken: offline", extra={"device": device})
                self._alive(device, False)

    def _alive(self, device: str, online: bool) -> None:
        if self.store.device(device) is None:
            # a token alone makes no device: it appears with its first valid message (_write_loop)
            with self._lock:
                self._alive_unknown.pop(device, None)
                if online and len(self._alive_unknown) < MAX_ALIVE_UNKNOWN:
                    self._alive_unknown[device] = time.time()
            if self.store.device(device) is None:
                return
            with self._lock:  # its first window was stored meanwhile
                self._alive_unknown.pop(device, None)
        elif self._alive_unknown:
            with self._lock:  # a retry _write_loop kept must not undo this newer token
                self._alive_unknown.pop(device, None)
        self.store.set_online(device, online)
        try:
            self.monitor.process(device)  # what it sent before it went (or came back) is judged first
            self.monitor.set_online(device, online)
        except Exception:
            log.exception("monitor: liveliness of %s", device)

    # --- drift monitor -----------------------------------------------------------------------------

    def _monitor_loop(self) -> None:
        for _ in self._paced(self._wake_monitor, self.monitor_interval_s):
            self._renew_if_lost()  # also when no window comes to make the writer notice
            try:
                self._recheck_online_if_due()
            except Exception:  # a read the database refused: asked again after the next hand-over or start
                log.exception("checking which stored-online devices hold a token failed")
            try:
                self.monitor_pass()
            except Exception:  # the thread must outlive a pass: a dead one would never watch again
                log.exception("monitor pass failed")

    def _paced(self, wake: threading.Event, interval_s: float) -> Iterator[None]:
        """Pass after pass until stopped: the next one when `wake` is set (windows stored, a step raised) or
        `interval_s` has gone by, and never sooner than MIN_PASS_S after the last one began. A wall-clock interval
        alone made the service's drive-time pace depend on the replay's speed: `agent --real-time-factor 3600`
        ran the passes two drive-hours apart, so every trial ran twice as long and every step's move came up to
        two hours late (bench e2e, 12 drives at 0.5 Hz: median 3.05x and 6 worse hours, against 3.50x and 1)."""
        while not self._stop.is_set():
            wake.wait(interval_s)
            wake.clear()
            if self._stop.is_set():
                return
            began = time.monotonic()
            yield
            self._stop.wait(max(0.0, MIN_PASS_S - (time.monotonic() - began)))

    def monitor_pass(self) -> int:
        """Feed every device with new windows to the monitor; returns the alarms raised or cleared."""
        with self._lock:
            changed, self._monitor_changed = sorted(self._monitor_changed), set()
        self.monitor.leave_out(self.store.retired_device_ids())  # another member's retirements too
        n = 0
        for device in filter(self.partitions.serves, changed):
            self._store_first()
            with self.partitions.serving(device) as mine:  # as a refit: not handed over in the middle of a page
                if not mine:
                    continue
                try:
                    n += len(self.monitor.process(device))
                except Exception:  # one device's failure must not stop the others; the next pass feeds it again
                    log.exception("%s: monitor failed", device)
                    with self._lock:
                        self._monitor_changed.add(device)
        return n

    def _store_first(self) -> None:
        """Wait, up to STORE_FIRST_MAX_WAIT_S, while more than STORE_FIRST_BACKLOG messages wait for the writer.
        The passes share one interpreter lock with it: every step they take while a backlog waits (a fleet
        sending its outboxes after an outage, a flood) is taken from storing, and what is not stored is what an
        agent's outbox must keep holding (bench-fleet, 1,000 devices: 3.6x the writer's py-spy samples)."""
        waited = 0.0
        while self._inbox.qsize() > STORE_FIRST_BACKLOG and waited < STORE_FIRST_MAX_WAIT_S:
            if self._stop.wait(0.005):
                break
            waited += 0.005
        if waited:
            with self._lock:
                self.counters.analysis_waited_s += waited

    def _publish_alarm(self, key: str, payload: bytes) -> None:
        alarm = json.loads(payload)
        try:
            self._act_on_alarm(alarm)
        except Exception:
            # the database refused the band memory's restart (busy, full): without a retry the device would wait
            # for a move no pass makes and refit nothing until the process restarted. The next refit pass takes
            # the step up again from its stored alarm, as a restart does (_resume_step_moves)
            if alarm["cause"] in STEP_CAUSES:
                with self._lock:
                    self._resume_pending.add(alarm["device"])
                self._wake_refit.set()
            raise
        finally:  # the restart first: a put that fails must not leave the sums mixing the drive before a step
            self.session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)

    def _act_on_alarm(self, alarm: dict) -> None:
        if alarm["cause"] in STEP_CAUSES and alarm["event"] == "raised":
            # memory is drive time and a detected step restarts it: refits learn the drive as it is now
            bands = self.store.restart_band_memory(alarm["device"], after=alarm["raised_at"])
            with self._lock:
                self._restarted_for[alarm["device"]] = alarm["raised_at"]
                self._changed.add(alarm["device"])
                self._refit_now.add(alarm["device"])
                self._step_moves[alarm["device"]] = (alarm["cause"], alarm["parameters"], alarm["raised_at"])
            self._wake_refit.set()  # the step's move goes out in the next pass, not a refit interval later
            log.info(
                "band memory restarted after a step",
                extra={"device": alarm["device"], "cause": alarm["cause"], "bands": bands},
            )

    # --- queries -----------------------------------------------------------------------------------

    def _on_coefficients_query(self, query: zenoh.Query) -> None:
        try:
            device = wire.device_from_key(query.key_expr)
        except wire.WireError:
            return  # a wildcard or foreign key: one device per question
        current = self.store.current_coefficients(device, published_only=True)
        if current is not None:
            query.reply(query.key_expr, wire.encode("coefficients", current))

    def _on_received_query(self, query: zenoh.Query) -> None:
        try:
            device = wire.device_from_key(query.key_expr)
        except wire.WireError:
            return
        if self.guard is not None and not self.guard.admits(device):
            return  # as for its windows: an id out of the registry (revoked) gets no watermark and moves no floor
        payload = query.payload.to_bytes() if query.payload is not None else b""
        try:  # a write the database refuses below: the watermark is still answered (reads work)
            try:
                gone_below, nonce = wire.parse_received_query(payload, device)
            except wire.WireError as exc:  # kept and counted; answered with no nonce (a checking agent refuses it)
                gone_below = nonce = None
                self.store.dead_letter(str(query.key_expr), exc.reason, str(exc), payload)
                with self._lock:
                    self.counters.count(exc.reason)
            if gone_below is not None:
                self._take_gone_below(device, gone_below)
        except Exception:
            log.exception("%s: the received question's floor could not be stored", device)
        mark, acked, last = self.watermark(device), self.store.acked_version(device), self.store.last_window(device)
        # signed for this question (security on): whoever else can answer it (a meshed router's stolen key) cannot forge
        # a higher watermark, nor replay an old or another drive's reply, to make the agent drop windows never stored
        retired = self.store.is_retired(device)
        reply = wire.watermark_reply(device, mark, acked, last, nonce=nonce, signer=self.signer, retired=retired)
        query.reply(query.key_expr, reply)

    def _take_gone_below(self, device: str, gone_below: int) -> None:
        """An agent whose full outbox dropped windows names the seq below which what we lack is gone: without it the
        watermark waits at the first of them for ever, and the drift monitor with it (it reads up to the mark)."""
        if self.store.mark_gone_below(device, gone_below):
            log.warning(
                "windows below seq %d lost by the agent (its outbox full): the watermark steps over them",
                gone_below,
                extra={"device": device},
            )
            with self._lock:  # the monitor waited at the gap: it reads on now, with or without a new window
                self._monitor_changed.add(device)
            self._wake_monitor.set()

    def watermark(self, device: str) -> int:
        """Highest seq with every window up to it stored (so the agent may forget them)."""
        with self._lock:
            mark = self._watermarks.get(device, 0)
            mark = self.store.contiguous_seq(device, start=mark)
            self._watermarks[device] = mark
            return mark

    # --- refit and rollout -------------------------------------------------------------------------

    def _refit_loop(self) -> None:
        for _ in self._paced(self._wake_refit, self.refit_interval_s):
            self._renew_if_lost()
            try:
                self.refit_all()
            except Exception:  # the thread must outlive a pass: a dead one would never refit again
                log.exception("refit pass failed")
            if self.keep_s is not None and (
                self._pruned_at is None
                or self._prune_resume is not None
                or time.monotonic() - self._pruned_at > PRUNE_EVERY_S
            ):
                self._pruned_at = time.monotonic()
                try:
                    self.prune(budget_s=PRUNE_PASS_S)
                except Exception:  # the next pass tries again; nothing is lost by pruning late
                    log.exception("retention pass failed")
            if not self.partitions.leads():
                continue  # one process steps the rollouts; every process records and judges from the database
            try:
                self.rollouts.step()
            except Exception:  # logged with its trace; the next pass tries again from what is stored
                log.exception("rollout step failed")

    def refit_all(self) -> list[int]:
        """Refit every device that sent windows since its last refit and is due (REFIT_EVERY_S of drive time
        since then, a set on trial to judge, or a step); returns the versions published."""
        with self._lock:
            resume, self._resume_pending = self._resume_pending, set()
        if resume:
            try:
                self._resume_step_moves(lambda device: device in resume and self.partitions.serves(device))
            except Exception:  # refused again: the next pass tries again
                log.exception("taking up %d step(s) again failed", len(resume))
                with self._lock:
                    self._resume_pending |= resume
        with self._lock:
            pending, self._changed = deque(sorted(self._changed)), set()
        # a retired drive gets no set (what it sends is not stored, so it comes here only from before it was retired)
        done = self.store.retired_device_ids()
        published, later, prefetched = [], set(), set()
        while (device := self._next_in_pass(pending, done)) is not None:
            self._store_first()
            if device not in prefetched:
                ahead = [device] + [d for d in itertools.islice(pending, PREFETCH_DEVICES - 1) if d not in done]
                prefetched.update(ahead)
                self._prefetch_fits(ahead)
            # the device's partition is not handed over while this works on it (a hand-over now: left to its new owner)
            with self.partitions.serving(device) as mine:
                if not mine:
                    continue
                try:
                    drive_now = self._drive_now(device)
                except Exception:  # a read the database refused (a dropped session): the device waits for the next pass
                    log.exception("%s: reading its drive time failed", device)
                    later.add(device)
                    continue
                try:
                    version = self.answer_refusal(device)
                except Exception:
                    log.exception("%s: answering a refused set failed", device)
                    version = None
                try:
                    if version is None:
                        version = self.deliver(device, drive_now)
                except Exception:
                    log.exception("%s: delivering its set failed", device)
                    version = None
                try:
                    if version is None and self._watch_due(device, drive_now):
                        version = self.watch(device, drive_now)
                except Exception:
                    log.exception("%s: watch failed", device)
                    version = None
                if version is not None:
                    published.append(version)
                    continue
                try:
                    due = self._refit_due(device, drive_now)
                except Exception:  # as above: the refit thread died of this once (test_cluster, sessions dropped)
                    log.exception("%s: checking whether a refit is due failed", device)
                    due = False
                if not due:
                    later.add(device)
                    continue
                try:
                    with self.counters.refit_latency.time():
                        version = self.refit(device)
                except DeviceHeld as held:  # the rollout's now: its step judges it
                    log.info("%s", held, extra={"device": device})
                    continue
                except Exception:  # one bad device must not stop the others; the error is logged with its trace
                    log.exception("%s: refit failed", device)
                    continue
                if version is not None:
                    published.append(version)
        with self._lock:
            self._changed |= later
        return published

    def prune(self, budget_s: float | None = None) -> dict[str, int]:
        """Retention (`--keep-days`): delete each served device's windows that ended more than keep_s of its own
        drive time before its newest, in small transactions with the writer served first. Kept whatever their age:
        every window above the contiguous watermark (the agent may still fill a gap below them), not yet seen by
        the drift monitor, run on a set on trial, or in a band's sum (Store.prune_windows), and each device's newest
        (its drive time, its offline alarm's date). Dead letters older than keep_s of the service's clock go too.
        A pass ends after the batch that passes `budget_s` (wall s; None: none) or once the service stops, and the
        next begins at the device it stopped at. Returns {"windows": n, "dead_letters": n} deleted."""
        if self.keep_s is None:
            return {"windows": 0, "dead_letters": 0}
        began = time.monotonic()

        def out_of_time() -> bool:
            return self._stop.is_set() or (budget_s is not None and time.monotonic() - began >= budget_s)

        windows, resume, self._prune_resume = 0, self._prune_resume, None
        devices = [d for d in self.store.device_ids() if resume is None or d >= resume]
        for i, device in enumerate(filter(self.partitions.serves, devices)):
            if i and out_of_time():  # a fleet's walk alone may take its time
                self._prune_resume = device
                break
            self._store_first()
            with self.partitions.serving(device) as mine:
                last = self.store.last_window(device) if mine else None
                if last is None:
                    continue
                below = min(self.watermark(device) + 1, last[0])
                if self.monitor_interval_s > 0:  # the monitor reads its windows back, and its last one at a restart
                    below = min(below, self.store.monitor_states(device).get(device, (None, 0))[1])
                trial = self.store.set_on_trial(device)
                keep_version = None if trial is None else trial["version"]
                while n := self.store.prune_windows(
                    device, ended_before=last[1] - self.keep_s, below_seq=below, keep_version=keep_version
                ):
                    windows += n
                    if out_of_time():  # the device may have more: the next pass begins with it
                        self._prune_resume = device
                        break
                    self._store_first()
            if self._prune_resume is not None:
                break
        dead_letters = 0
        if self._prune_resume is None and self.partitions.leads():  # the whole fleet's table: one process prunes it
            while n := self.store.prune_dead_letters(self._clock() - self.keep_s):
                dead_letters += n
                if out_of_time():
                    self._prune_resume = ""  # before every device id: the next pass is a whole one
                    break
                self._store_first()
        with self._lock:
            self.counters.pruned_windows += windows
            self.counters.pruned_dead_letters += dead_letters
        if windows or dead_letters:
            log.info("retention pass", extra={"windows": windows, "dead_letters": dead_letters})
        return {"windows": windows, "dead_letters": dead_letters}

    def _next_in_pass(self, pending: deque, done: set[str]) -> str | None:
        """The next device a refit pass serves: one with a step just raised first, even one the monitor raised
        while the pass ran (at 3,600x a pass over a dozen drives took a quarter of a drive-hour, and the step's
        move waited for it); then the pass's own, in order. None when the pass is done."""
        while True:
            with self._lock:
                urgent = sorted(self._refit_now - done)
            if urgent:
                device = urgent[0]
            elif pending:
                device = pending.popleft()
            else:
                return None
            if device not in done:
                done.add(device)
                if self.partitions.serves(device):
                    return device

    def _prefetch_fits(self, devices: list[str]) -> None:
        """The band fits of the devices a pass is about to refit, in one batch into the fit memo
        (service.refit.prefetch_band_fits: half the cost of a device's fits, the same fits). Only devices whose
        refit is due by its cadence and that nothing else holds (a set on trial is judged, a rollout's device and a
        pending step's are not fitted): a fit prefetched for nothing costs as much as one. Best effort: a device
        whose reads fail here is fitted by its own refit, as without the batch."""
        drives, unread = [], []
        for device in devices:
            try:
                if self._fit_likely(device) and (anchors := bench_anchors(self._correction(device, 0))):
                    drives.append((self._band_stats(device), anchors))
            except Exception as exc:  # the refit reads it again, and says so if it fails there too
                unread.append(f"{device}: {exc}")
        if unread:  # one line for the batch: a database that refuses every read would otherwise log each drive twice
            log.warning("%d device(s) left out of the batch of band fits: %s", len(unread), "; ".join(unread[:3]))
        try:
            prefetch_band_fits(drives, self.min_band_samples)
        except Exception:
            log.exception("fitting %d devices' bands in one batch failed", len(drives))

    def _fit_likely(self, device: str) -> bool:
        """Whether this pass will fit the device's bands, as far as a cheap look tells (refit decides)."""
        with self._lock:
            if device in self._step_moves:
                return False
            forced = device in self._refit_now
        if not self.partitions.serves(device) or self.rollouts.holds(device) or self.store.set_on_trial(device):
            return False
        last = self._fitted_at.get(device)
        return forced or last is None or self._drive_now(device) - last >= self.refit_every_s

    def _band_stats(self, device: str) -> dict[int, WindowStats]:
        """band -> the device's merged window statistics there (the store keeps them in memory)."""
        return {band: stats for band, (stats, _, _) in self.store.band_stats(device).items()}

    def _refit_due(self, device: str, drive_now: float) -> bool:
        with self._lock:
            if device in self._refit_now:
                self._refit_now.discard(device)
                return True
            if device in self._step_moves:  # a move waits for a trial's verdict: the next pass may make it
                return True
        last = self._fitted_at.get(device)
        if last is None or self.store.set_on_trial(device) is not None:
            return True
        return drive_now - last >= self.refit_every_s

    def _watch_due(self, device: str, drive_now: float) -> bool:
        last = self._watched_at.get(device)
        return last is None or drive_now - last >= WATCH_EVERY_S

    def watch(self, device: str, drive_now: float) -> int | None:
        """The first rule between refits: where the newest drive-hour of windows shows the running set worse than
        the factory's (service/trial.py: watch_against_factory), the factory set again (basis rollback, restores
        v0, confirmed: it is the reference-measured set), a set on trial rolled back with it, and band memory
        restarted at that hour, so the next refit learns the drive as it is now. Returns the version published."""
        self._watched_at[device] = drive_now
        running_version = self.store.published_version(device)
        runs = self.store.running_version(device)
        if runs and runs != running_version and self.store.state_of(device, runs) == "rolled_back":
            running_version = runs  # its rollback was refused: the drive runs a set the guard rolled back
        if not running_version or self.rollouts.holds(device):
            return None  # the factory set itself runs (or nothing yet), or a rollout has the device
        factory, running = self._correction(device, 0), self._correction(device, running_version)
        if factory is None or running is None:
            return None
        # windows from before a step the monitor named show a drive that is no more (a moved set is right after it)
        since = max(drive_now - WATCH_S, self._last_step_at(device) or 0.0)
        found = watch_against_factory(self.store.stats_since(device, since), running, factory)
        if not found:
            return None
        version = self._factory_again(device, "worse than the factory set: " + "; ".join(f.reason for f in found))
        self.store.restart_band_memory(device, after=drive_now - WATCH_S)
        self._fitted_at[device] = drive_now  # the next refit an hour on, from what the drive is now
        return version

    def deliver(self, device: str, drive_now: float) -> int | None:
        """What the service means the drive to run reaches it. A set stored but never put (the put, or the record
        of it, failed after the set's commit: a rollback marked in the database while the drive ran on) is
        published now; returns its version. The newest published set, when the drive's windows still show an
        older one `resend_after_s` after it went out, is put again (counted; returns None)."""
        newest = self.store.newest_set(device)
        if newest is None or newest["version"] == 0:
            return None  # the factory set is the agent's own
        if newest["published_at"] is None:
            self._publish(self.store.coefficient_set(device, newest["version"]))
            log.warning(
                "a set stored but never published is published", extra={"device": device, "version": newest["version"]}
            )
            return newest["version"]
        runs = self.store.running_version(device)
        if runs is None or runs >= newest["version"]:
            self._resent.pop(device, None)
            return None
        resent_version, resent_at, resent_drive = self._resent.get(device, (None, 0.0, -math.inf))
        again = resent_version == newest["version"]
        last = max(newest["published_at"], resent_at if again else 0.0)
        last_drive = max(newest["created_at"], resent_drive if again else -math.inf)
        now = self._clock()
        if now - last < self.resend_after_s and drive_now - last_drive < RESEND_AFTER_DRIVE_S:
            return None
        self._put(self.store.coefficient_set(device, newest["version"]))
        self._resent[device] = (newest["version"], now, drive_now)
        with self._lock:
            self.counters.resends += 1
        log.info(
            "coefficient set sent again: the drive's windows still show an older one",
            extra={"device": device, "version": newest["version"], "runs": runs},
        )
        return None

    def answer_refusal(self, device: str) -> int | None:
        """The newest published set was refused by the drive's agent (an ack `rejected`: a set its checks, its
        signature check or its schema do not accept), so the drive still runs one before it. The refused set ends
        rolled back with the agent's words, and the set the drive runs goes out again (basis rollback; the last
        confirmed one if the drive has not said), so the record says what the drive runs: a refused trial was
        otherwise confirmed after TRIAL_MAX_S on no evidence, and the watch judged a set the drive never ran.
        A refused rollback is not answered with another (that would not end): it is marked, logged, and the drive
        runs on what it ran. Returns the version published."""
        refusals = self.store.refusals(device)  # one query per device and pass: most have none
        if not refusals:
            return None
        version = self.store.published_version(device)
        if not version or self.rollouts.holds(device):
            return None  # the factory set cannot be refused; a staged rollout answers its own refusals
        for late in {r["version"]: r for r in refusals if r["version"] < version}.values():
            # refused after a newer set went out: nothing to send (the newer one is what counts now), but the
            # record says the drive never ran it, and no rollback restores it
            if self.store.state_of(device, late["version"]) not in (None, "rolled_back"):
                why = f"the agent refused v{late['version']}: {late['reason']}"
                self.store.set_state(device, late["version"], "rolled_back", at=self._drive_now(device), reason=why)
        refused = [r for r in refusals if r["version"] == version]
        if not refused:
            return None
        reason = f"the agent refused v{version}: {refused[0]['reason']}"
        runs = self.store.running_version(device)
        if runs is not None and runs < version and self.store.state_of(device, runs) != "rolled_back":
            before = self.store.coefficient_set(device, runs)
        else:  # the drive has not said, or it runs a set the guard has rolled back: the last confirmed one
            before = self.store.last_confirmed(device, before=version)
        if before is None or self.store.coefficient_set(device, version)["basis"] == "rollback":
            self.store.set_state(device, version, "rolled_back", at=self._drive_now(device), reason=reason)
            log.error("a refused set is not answered again", extra={"device": device, "version": version})
            return None
        # the set's own lag (_issue_set drops a lag the agent refused)
        return self.roll_back(device, version, before, reason, thermal_lag_s=before.get("thermal_lag_s", 0.0))

    def _lag_refused(self, device: str) -> bool:
        """The device's agent refused a set for carrying `thermal_lag_s` (its schema is older than the field:
        docs/wire.md): it is sent no lag again, until it has come back online (restarted, perhaps upgraded) more
        than a day after refusing (an upgraded agent takes the lag; one still old refuses once more and is rolled
        back once more; a token that flaps with the network does not make it ask every time)."""
        back = self.store.online_since(device)
        since = None if back is None else min(back, time.time() - LAG_RETRY_AFTER_S)
        return any(
            "thermal_lag_s" in r["reason"] and ("unexpected" in r["reason"] or "unknown field" in r["reason"])
            for r in self.store.refusals(device, since=since)
        )

    def _correction(self, device: str, version: int) -> BandedCorrection | None:
        """A stored set, decoded once: (device, version) never changes content (insert refuses a reuse)."""
        key = (device, version)
        corr = self._corrections.get(key)
        if corr is None:
            msg = self.store.coefficient_set(device, version)
            if msg is None:
                return None
            corr = self._corrections[key] = BandedCorrection.from_dict(msg)  # the bands and the die lag
        return corr

    def refit(self, device: str) -> int | None:
        """Judge the set on trial, if there is one (the device gets nothing new meanwhile); otherwise, right after
        a step (offset, gain or axes), publish the running set moved by it (publish_step_move); otherwise refit and
        publish what changed. New sets go out on trial. Returns the version published (a fit, a move or a
        rollback). A device a staged rollout holds (service/rollout.py) is left to the rollout."""
        with self._lock:
            step = self._step_moves.get(device)
        held = self.rollouts.holds(device)
        trial = None if held else self.store.set_on_trial(device)
        unmeasured = step is not None and not self.monitor.step_measured(device, step[2])
        if trial is None or unmeasured or (step is not None and trial["message"]["created_at"] >= step[2]):
            # a rollout goes first (the refit after it sees the step); a set on trial fitted after the step has
            # nothing to move; otherwise the move waits for the trial's verdict, then moves what runs (s4-20hz-08:
            # an axis step during a trial was dropped, and the drive ran 0.13-0.22° for a day against 0.02-0.04°);
            # a step the monitor could not measure brings the factory set now, whatever is on trial
            with self._lock:  # only the step read above: one the monitor raised since waits for the next pass
                if self._step_moves.get(device) is step:
                    self._step_moves.pop(device, None)
        if held:
            return None
        if unmeasured:
            version = self._keeping_step(device, step, lambda: self.back_to_factory(device, step))
            self._refitted(device)
            return version
        if trial is not None:
            return self._judge_trial(device, trial)
        if step is not None:
            version = self._keeping_step(device, step, lambda: self.publish_step_move(device, *step[:2]))
            if version is not None:
                self._refitted(device)
                return version
        if (version := self.publish_lag(device)) is not None:
            self._refitted(device)
            return version
        result = self.fit(device)
        self._refitted(device)
        return self.publish_fit(device, result) if result is not None and result.changed else None

    def _keeping_step(self, device: str, step: tuple, act: Callable[[], int | None]) -> int | None:
        """act(), the step's move that refit took from the pending ones; if the database refuses it (busy, full), the
        step is pending again and the next pass visits the device, with or without new windows (it was dropped)."""
        try:
            return act()
        except Exception:
            with self._lock:
                self._step_moves.setdefault(device, step)
                self._refit_now.add(device)
            raise

    def _refitted(self, device: str) -> None:
        """A refit pass was made for the device (a fit or a move): its cadence restarts, and it is counted."""
        self._fitted_at[device] = self._drive_now(device)
        with self._lock:
            self.counters.refits += 1

    def publish_step_move(self, device: str, cause: str, step: dict) -> int | None:
        """The set the device runs, moved by the step (offset_step, gain_step or axis_step) the drift monitor
        measured, on trial: right at once for the step, where a refit must first gather windows after it (band
        memory restarts with the step), which a drive that holds a few positions gives slowly."""
        running_version = self.store.published_version(device)
        factory = self._correction(device, 0)
        running = self.store.coefficient_set(device, running_version) if running_version is not None else None
        if factory is None or running is None:
            return None
        scale = normalisation_scale(factory)  # the agent's statistics scale, in which the monitor measures
        bands = step_moved_bands(running["bands"], cause, step, scale)
        reason = f"{cause.replace('_', ' ')}: v{running_version} moved for it ({cause_of(cause).state(**step)})"
        return self._issue_set(device, "fit", bands, state="trial", reason=reason)

    def back_to_factory(self, device: str, step: tuple) -> int | None:
        """A step the drift monitor could not measure (DeviceMonitor.step_measured: the positions held across it moved
        as an offset step and as one channel's gain alike): the factory set again (basis rollback, restores v0,
        confirmed), a set on trial rolled back with it. Moved the wrong way, the running set would leave twice the
        step's error around the circle; unmoved, its drift correction and the step's error may add where the
        factory set's cancel (s2-20hz-22: 0.13-0.16° for six hours against 0.05-0.14°). Band memory restarted with
        the alarm, and the refit measures which step it was from the positions held since (held_drift_model).
        Returns the version published, None when the factory set already runs."""
        running_version = self.store.published_version(device)
        if not running_version:
            return None
        cause, parameters, _ = step
        reason = (
            f"{cause.replace('_', ' ')} ({cause_of(cause).state(**parameters)}) not told from one channel's gain by "
            "the positions the drive holds: the reference-measured set until the refit measures which"
        )
        return self._factory_again(device, reason)

    def _factory_again(self, device: str, reason: str) -> int:
        """The factory set published again (basis rollback, restores v0, confirmed), a set on trial rolled back."""
        trial = self.store.set_on_trial(device)
        return self.roll_back(
            device, trial["version"] if trial is not None else None, self.store.coefficient_set(device, 0), reason
        )

    def publish_lag(self, device: str) -> int | None:
        """Where the windows measure the die's lag clear of the one the drive runs (encoder_core/thermal.py): the
        running bands with the new lag, confirmed (the bands are the ones the guard confirmed; what changes is the
        temperature they are read at). Returns the version published. Band memory is kept: its older windows,
        written at the reported temperature, carry the lag's bias as every window did before, and fade out with
        the horizon (restarting it cost a reversing drive its cold bands, refitted from the curve's reach instead:
        s3-0.5hz-07, three worse hours)."""
        running_version = self.store.published_version(device)
        if running_version is None:
            return None
        estimate = self.monitor.thermal_lag(device)
        running_lag = self._running_lag(device, running_version)
        lag = lag_to_send(estimate, running_lag)
        if lag is None:
            return None
        if self._lag_refused(device):
            return None  # an agent older than the field refused it once: it would refuse it again
        running = self.store.coefficient_set(device, running_version)
        reason = (
            f"die lag {lag:.0f} s (± {estimate[1]:.0f} s) measured from the windows' amplitude against temperature "
            f"and its rate; v{running_version} ran {running_lag:.0f} s"
        )
        return self._issue_set(device, "fit", running["bands"], state="confirmed", reason=reason, thermal_lag_s=lag)

    def _running_lag(self, device: str, version: int | None = None) -> float:
        """The die lag of the set the device runs (version: its published version, when the caller has it; 0
        before any set carries one)."""
        version = self.store.published_version(device) if version is None else version
        corr = self._correction(device, version) if version is not None else None
        return corr.thermal_lag_s if corr is not None else 0.0

    def fit(self, device: str, *, min_band_samples: int | None = None) -> RefitResult | None:
        """The refit of the device's band sums against the set it runs; None when no set is known yet, when the
        device is never refit (never_refit), or while a step's band memory restart is pending
        (_memory_restarted_since)."""
        running_version = self.store.published_version(device)
        if running_version is None:
            return None  # no factory set known yet: nothing to anchor a rollout to
        if (why := self.never_refit(device)) is not None:  # before the reads below, which would be for nothing
            if device not in self._no_bench_locus_said:  # once a process: the refit passes come back every hour
                self._no_bench_locus_said.add(device)
                log.warning("%s: not refit: %s", device, why, extra={"device": device})
            return None
        newest_step = self._newest_step(device)
        step_at = None if newest_step is None else newest_step["raised_at"]
        if not self._memory_restarted_since(device, newest_step):
            # a step the monitor stored and will publish at the end of its pass, which restarts band memory: the
            # sums still mix the drive before and after it, and a set made now would also stand for the step's move
            # (refit: a set fitted after the step has nothing to move). The publication asks for the refit at once.
            return None
        factory = self._correction(device, 0)
        axis_steps = self.store.alarms(device, cause="axis_step")
        running = self._correction(device, running_version)
        band_stats = self._band_stats(device)
        bin_temps = {band: stats.bin_temps() for band, stats in band_stats.items()}
        return refit_device(
            band_stats,
            running,
            factory,
            min_samples=self.min_band_samples if min_band_samples is None else min_band_samples,
            bin_temps=bin_temps,
            after_step=self._stepped_recently(device, step_at)
            and self._bands_made_at(device, running_version) < step_at,
            stepped_since_bench=step_at is not None,
            no_axis_step=not axis_steps,
            axis_turn=sum(a["parameters"]["delta_skew"] for a in axis_steps),
            held_watched=self.monitor.watches_held_positions(device),
            before_step=self._set_before_unmeasured_step(device, step_at),
        )

    def never_refit(self, device: str) -> str | None:
        """Why no refit is made for the device whatever it sends (service.refit.NO_BENCH_LOCUS), or None."""
        return None if bench_anchors(self._correction(device, 0)) else NO_BENCH_LOCUS

    def _set_before_unmeasured_step(self, device: str, step_at: float | None) -> BandedCorrection | None:
        """The set the drive ran before its newest step, when the monitor could not measure that step (the drive
        went back to its factory set: back_to_factory) and the set's bands are the fleet's, not the factory's."""
        if step_at is None or self.monitor.step_measured(device, step_at):
            return None
        version = self.store.confirmed_before(device, step_at)
        if version is None or self._bands_made_at(device, version) == -math.inf:
            return None
        return self._correction(device, version)

    def _issue_set(
        self,
        device: str,
        basis: str,
        bands: list[dict],
        *,
        state: str,
        reason: str | None,
        restores_version: int | None = None,
        before: Callable[[int, float], None] | None = None,
        after: Callable[[int], None] | None = None,
        thermal_lag_s: float | None = None,
    ) -> int:
        """A new set in one transaction (`before(version, drive_now)` and `after(version)` run inside it, around
        the set's insert: what belongs with the set lands with it, or nothing does), then published. Every set
        carries the die lag the device runs (a property of the drive, not of a fit) unless given a new one. A set
        that is not a rollout's own (`after` None) is refused with DeviceHeld when a rollout holds the device, as
        checked inside the transaction: the rollouts' leader may have started it since this process read it."""
        drive_now = self._drive_now(device)
        lag = self._running_lag(device) if thermal_lag_s is None else thermal_lag_s
        if lag and self._lag_refused(device):
            lag = 0.0
        with self.store.transaction():
            version = self.store.next_version(device)
            if after is None and self.rollouts.holds(device):
                raise DeviceHeld(f"{device}: a staged rollout started on it meanwhile")
            if before is not None:
                before(version, drive_now)
            msg = wire.coefficients_message(
                device, version, drive_now, basis, bands, restores_version=restores_version, thermal_lag_s=lag
            )
            msg = self._publishable(msg)
            self.store.insert_coefficient_set(msg, state=state, reason=reason)
            if after is not None:
                after(version)
        self._publish(msg)
        return version

    def publish_fit(
        self, device: str, result: RefitResult, *, reason: str | None = None, then: Callable[[int], None] | None = None
    ) -> int:
        """Store the fits and the set they make (on trial) in one transaction, then publish it. `then(version)`
        runs inside that transaction (a rollout records its part with the set, or neither lands)."""

        def record_fits(version: int, drive_now: float) -> None:
            fits = [
                (d.band, {k: v for k, v in d.candidate.items() if k not in ("band", "quality")},
                 d.candidate["quality"], d.adopted)
                for d in result.decisions
            ]  # fmt: skip
            self.store.record_fits(device, fits, created_at=drive_now, version=version)

        version = self._issue_set(
            device, "fit", result.bands, state="trial", reason=reason, before=record_fits, after=then
        )
        log.info(
            "published coefficient set on trial",
            extra={"device": device, "version": version, "bands_adopted": sum(d.adopted for d in result.decisions)},
        )
        return version

    def publish_bands(
        self, device: str, bands: list[dict], *, restores_version: int, reason: str, then: Callable[[int], None]
    ) -> int:
        """Publish, on trial, a set that carries the bands of confirmed set `restores_version` again (a reset
        to factory is restores_version 0); `then(version)` runs inside the set's transaction."""
        return self._issue_set(
            device, "rollback", bands, state="trial", reason=reason, restores_version=restores_version, after=then
        )

    def _judge_trial(self, device: str, trial: dict) -> int | None:
        """Confirm, roll back (a new set, basis rollback, carrying the last confirmed set again) or wait."""
        before = self.store.last_confirmed(device, before=trial["version"])
        if before is None:  # nothing to go back to (cannot happen once the factory set is stored)
            self.store.set_state(
                device, trial["version"], "confirmed", at=self._drive_now(device), reason="no set before"
            )
            return None
        verdict = self.judge_set(device, trial["message"], before)
        drive_now = self._drive_now(device)
        if verdict.action == "wait" and drive_now - trial["message"]["created_at"] >= TRIAL_MAX_S:
            runs = self.store.running_version(device)
            if runs is not None and runs < trial["version"]:
                return None  # the drive has not run it: not kept on no evidence (deliver sends it again)
            verdict.action = "confirm"
            verdict.reason = f"{verdict.reason}; not measured within {TRIAL_MAX_S / 3600:g} drive hours: kept"
        if verdict.action == "wait":
            return None
        if verdict.action == "confirm":
            self.store.set_state(device, trial["version"], "confirmed", at=drive_now, reason=verdict.reason)
            log.info("coefficient set confirmed", extra={"device": device, "version": trial["version"]})
            return None
        return self.roll_back(device, trial["version"], before, verdict.reason)

    def judge_set(self, device: str, trial: dict, before: dict) -> Verdict:
        """The guard's verdict on set `trial` against `before`, from the windows the drive ran on `trial`."""
        bands = changed_bands(trial, before)
        soak = self.store.stats_run_on(device, trial["version"], bands)
        return self.judge(TrialEvidence(trial, before, soak, factory=self.store.coefficient_set(device, 0)))

    def roll_back(
        self,
        device: str,
        version: int | None,
        before: dict,
        reason: str,
        then: Callable[[], None] | None = None,
        *,
        thermal_lag_s: float | None = None,
    ) -> int:
        """Mark set `version` rolled back (None: a confirmed set runs, nothing to mark) and publish `before`'s bands
        again (basis rollback, confirmed; with the running die lag unless given one); `then()` runs inside that
        transaction."""

        def mark_rolled_back(_: int, drive_now: float) -> None:
            if version is not None:
                self.store.set_state(device, version, "rolled_back", at=drive_now, reason=reason)

        new_version = self._issue_set(
            device,
            "rollback",
            [dict(b) for b in before["bands"]],
            state="confirmed",
            reason=f"restores v{before['version']}: {reason}",
            restores_version=before["version"],
            before=mark_rolled_back,
            after=None if then is None else lambda _: then(),
            thermal_lag_s=thermal_lag_s,
        )
        with self._lock:
            self.counters.rollbacks += 1
        log.warning(
            "coefficient set rolled back",
            extra={"device": device, "version": version, "restored": before["version"], "new_version": new_version},
        )
        return new_version

    def _publishable(self, msg: dict) -> dict:
        # stored signed: the queryable replies with the same content the subscribers got
        return self.signer.sign(msg) if self.signer is not None else msg

    def _publish(self, msg: dict) -> None:
        self._put(msg)
        self.store.mark_published(msg["device"], msg["version"])
        with self._lock:
            self.counters.rollouts += 1

    def _put(self, msg: dict) -> None:
        self.session.put(
            keys.key(msg["device"], keys.COEFFICIENTS),
            wire.encode("coefficients", msg, checked=True),  # made by _issue_set's coefficients_message
            congestion_control=zenoh.CongestionControl.BLOCK,
        )

    def _bands_made_at(self, device: str, version: int) -> float:
        """Drive time the bands of a set were made at: a rollback's are the restored set's, a new die lag's (the
        same bands) the set's before it, the factory's the bench's (-inf). After a step only a set whose bands
        predate it has unvisited bands to move for it: moving a set made since (the step's own move, or a fit
        after it) again by what its fitted bands disagree with it moved the cold bands of a dwelling drive
        further at every refit (s6-20hz-10: 40 -> 218 millidegrees, three hours worse than the factory set)."""
        msg = self.store.coefficient_set(device, version)
        while True:  # versions only go down along the chain
            if msg is None or msg["basis"] == "factory":
                return -math.inf
            if msg["basis"] == "rollback" and msg.get("restores_version") is not None:
                restored = self.store.coefficient_set(device, msg["restores_version"])
                if restored is None or restored["version"] >= msg["version"]:
                    return float(msg["created_at"])
                msg = restored
                continue
            before = self.store.coefficient_set(device, msg["version"] - 1) if msg["version"] > 0 else None
            if before is None or before["bands"] != msg["bands"]:
                return float(msg["created_at"])
            msg = before

    def _stepped_recently(self, device: str, step_at: float | None) -> bool:
        """A step raised (at `step_at`, _last_step_at's) within STEP_OPEN_S of drive time: the refit may move
        bands it has no data for."""
        return step_at is not None and self._drive_now(device) - step_at < STEP_OPEN_S

    def _newest_step(self, device: str) -> dict | None:
        """The newest step alarm (offset, gain or axes) the monitor raised for the device, open or cleared."""
        newest = [a for cause in STEP_CAUSES for a in self.store.alarms(device, cause=cause, limit=1)]
        return max(newest, key=lambda a: a["raised_at"], default=None)

    def _last_step_at(self, device: str) -> float | None:
        """Drive time of the newest step (offset, gain or axes) the monitor raised for the device."""
        newest = self._newest_step(device)
        return None if newest is None else newest["raised_at"]

    def _memory_restarted_since(self, device: str, newest_step: dict | None) -> bool:
        """The device's band sums hold only the drive since its newest step (_newest_step's), as a refit after a
        step needs: restarted when this process published the step or took it over (_resume_step_moves), or long
        ago (the alarm cleared: a set made after it was applied). Not a step the monitor has stored but not yet
        published: it publishes after its pass, and the publication restarts them (_publish_alarm)."""
        if newest_step is None:
            return True
        with self._lock:
            if self._restarted_for.get(device) == newest_step["raised_at"]:
                return True
        return newest_step["cleared_at"] is not None

    def _drive_now(self, device: str) -> float:
        """The device's newest window end: message times are on the drive's clock."""
        last = self.store.last_window(device)  # by the primary key (window_summary also counted every window)
        return 0.0 if last is None else last[1]


def open_session(
    *, listen: list[str] | None = None, connect: list[str] | None = None, mesh: list[str] | None = None, pki=None
) -> zenoh.Session:
    """The service's session: an embedded router on `listen` (connected to the routers on `mesh`, if any), or a
    client of external routers.
    A router that cannot listen (a port taken, an endpoint malformed) raises InputError in one line.
    pki (a PKI folder): TLS with mutual authentication as the service's certificate; an embedded router
    also enforces the access control generated from the device registry (service/guard.py)."""
    from fleet_wire.session import error_line, session_config

    from .guard import router_security

    identity, acl = router_security(pki, listen=listen, connect=connect, mesh=mesh)
    try:
        if connect:
            return zenoh.open(session_config("client", connect=connect, identity=identity))
        return zenoh.open(session_config("router", listen=listen, connect=mesh, identity=identity, access_control=acl))
    except zenoh.ZError as exc:
        where = ", ".join(connect or listen or [])
        raise InputError(
            f"cannot open the Zenoh {'client of' if connect else 'router on'} {where}: {error_line(exc)}"
        ) from None


def _is_ip(host: str) -> bool:
    """A literal address (a name is left to Zenoh, which resolves it as it likes)."""
    try:
        ipaddress.ip_address(host)
    except ValueError:
        return False
    return True


def check_port_free(host: str, port: int, what: str) -> None:
    """InputError unless host:port can be bound now (the same SO_REUSEADDR rule servers use)."""
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((host, port))
        except OSError as exc:
            raise InputError(f"{what} port {host}:{port} cannot be used: {exc.strerror or exc}") from None


class _NoQueries(logging.Filter):
    """uvicorn's access lines with each query string cut: a client may put a token there (`?token=…`), which the
    service refuses but the line would keep; tokens are never logged."""

    def filter(self, record: logging.LogRecord) -> bool:
        args = record.args
        if isinstance(args, tuple) and len(args) == 5 and isinstance(args[2], str) and "?" in args[2]:
            record.args = (*args[:2], args[2].split("?", 1)[0] + "?…", *args[3:])
        return True


def _access_log_without_queries() -> None:
    access = logging.getLogger("uvicorn.access")
    if not any(isinstance(f, _NoQueries) for f in access.filters):
        access.addFilter(_NoQueries())


class HttpServer:
    """The REST API on a background thread (uvicorn), stoppable."""

    def __init__(
        self, store: Store, port: int, host: str = "127.0.0.1", service: FleetService | None = None, auth=None
    ):
        import uvicorn

        from service.api import create_app

        app = create_app(store, service, auth)
        # log_config=None: uvicorn's loggers go through the process's own (structured) handlers and level
        config = uvicorn.Config(app, host=host, port=port, log_config=None, log_level=logging.getLogger().level)
        _access_log_without_queries()
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self.server.run, name="http", daemon=True)

    def start(self) -> HttpServer:
        config = self.server.config
        check_port_free(config.host, config.port, "REST")
        self.thread.start()
        deadline = time.monotonic() + 10
        while not self.server.started and self.thread.is_alive() and time.monotonic() < deadline:
            time.sleep(0.05)
        if not self.server.started:
            self.stop()
            raise InputError(f"the REST server did not start on {config.host}:{config.port}")
        return self

    def stop(self) -> None:
        self.server.should_exit = True
        self.thread.join(timeout=10)


def run_service(
    *,
    db: str,
    listen: list[str] | None,
    connect: list[str] | None,
    mesh: list[str] | None = None,
    member: str | None = None,
    http_host: str = "127.0.0.1",
    http_port: int | None,
    refit_interval_s: float,
    band_horizon_h: float | None = BAND_HORIZON_H,
    pki=None,
    admin_token_file=None,
    rest_auth: bool = True,
    db_max_mb: float | None = None,
    keep_days: float | None = None,
) -> int:
    """`encoder-fleet service`: until SIGINT or SIGTERM. pki: TLS, mTLS, ACL and signed sets (None: insecure);
    rest_auth: bearer tokens on REST, the first admin token written to admin_token_file."""
    from contextlib import ExitStack
    from pathlib import Path

    listen = listen or ([] if connect else ["tls/127.0.0.1:7447" if pki else "tcp/127.0.0.1:7447"])
    with ExitStack() as running:  # whatever started is stopped again, in reverse, on any error
        if http_port:
            check_port_free(http_host, http_port, "REST")
        for endpoint in listen:  # before the database is made: a start that cannot listen leaves nothing behind
            proto, _, address = endpoint.partition("/")
            host, _, port = address.rpartition(":")
            if proto in ("tcp", "tls") and port.isdigit() and int(port) and _is_ip(host.strip("[]")):
                check_port_free(host.strip("[]"), int(port), f"Zenoh listen ({endpoint})")
        postgres = is_postgres(db)
        if member is not None and not postgres:
            raise InputError("--member shares the fleet through one PostgreSQL database; a SQLite file has one process")
        if connect and mesh:
            raise InputError("--mesh connects the embedded router to others; --connect means no embedded router")
        if postgres and db_max_mb is not None:
            raise InputError("--db-max-mb is a quota on a SQLite file; give PostgreSQL its own limits")
        if keep_days is not None and not band_horizon_h:
            raise InputError(
                "--keep-days needs a band horizon: with --band-horizon-h 0 a band's sum holds every window"
            )
        try:
            if not postgres:
                Path(sqlite_path(db)).parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise InputError(f"database {db}: its folder cannot be created: {exc.strerror or exc}") from None
        horizon_s = band_horizon_h * 3600.0 if band_horizon_h else None
        # the session first: a router that cannot listen (an endpoint malformed, a name taken) leaves no database
        session = open_session(listen=listen, connect=connect, mesh=mesh, pki=pki)
        running.callback(session.close)
        store = Store.open(db, band_horizon_s=horizon_s, check_integrity=True, max_mb=db_max_mb)
        running.callback(store.close)
        from .guard import service_security

        secured = service_security(store, pki)
        service = FleetService(
            store, session, refit_interval_s=refit_interval_s, member=member, keep_days=keep_days, **secured
        ).start()
        running.callback(service.stop)
        auth, written = None, None
        if rest_auth:
            from .auth import TokenAuth

            auth = TokenAuth(store)
            token_file = admin_token_file or (Path("out") if postgres else Path(sqlite_path(db)).parent) / "admin-token"
            written = auth.first_admin_token(token_file)
        if http_port:
            running.callback(HttpServer(store, http_port, host=http_host, service=service, auth=auth).start().stop)
        stop = threading.Event()
        set_on_signals(stop)
        where = ", ".join(connect or listen) + (f" meshed with {', '.join(mesh)}" if mesh else "")
        print(
            f"service: zenoh {'client of ' if connect else 'router on '}{where}; database {redacted(db)}"
            + (f"; member {member} of a shared fleet" if member else "")
            + (f"; REST http://{http_host}:{http_port}/docs" if http_port else ""),
            flush=True,
        )
        print(security_summary(pki, connect, auth, written), flush=True)
        log.info(
            "service started",
            extra={"zenoh": where, "database": redacted(db), "http_port": http_port or None, "member": member},
        )
        stop.wait()
        log.info("service stopping")
    return 0


def security_summary(pki, connect, auth, token_file) -> str:
    """One line on what protects this service; loud when something does not."""
    parts = []
    if pki is None:
        parts.append("INSECURE: plain TCP, no client certificates, no access control, coefficient sets unsigned")
    else:
        acl = "the external router's access control" if connect else "access control from the device registry"
        parts.append(f"TLS with client certificates from {pki}, {acl}, coefficient sets signed")
    if auth is None:
        parts.append("INSECURE: REST needs no token")
    elif token_file is not None:
        parts.append(f"first admin REST token written to {token_file} (0600)")
    else:
        parts.append("REST needs a bearer token")
    return "service: " + "; ".join(parts)
