"""Liveness, readiness and Prometheus metrics of the service.

Metric names follow Prometheus' conventions: the `encoder_fleet_` prefix, base units, `_total` for
counters, no per-device label (a fleet of 100,000 drives must not become 100,000 series).
The counters live in the service (service.runtime.ServiceCounters); this collector reads them and the
store at scrape time, so there is one place that counts and no second bookkeeping.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import TYPE_CHECKING

from prometheus_client import CollectorRegistry
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

from .monitor import SILENT_S
from .rollout import OUTCOMES, ROLLOUT_STATES, Rollouts
from .store import Store

if TYPE_CHECKING:
    from .runtime import FleetService

# what the ingest writer calls a message it stored or skipped; every other status is a rejection reason
INGESTED_OK = ("stored", "duplicate")


def health_checks(store: Store, service: FleetService | None) -> dict[str, str]:
    """component -> 'ok' or what is wrong with it. Without a running service (a bare REST app over a
    store, as in tests) only the process and the database are checked."""
    checks = {"process": "ok", "database": store.check()}
    if service is not None:
        checks.update(service.checks())
    return checks


class FleetCollector(Collector):
    def __init__(self, store: Store, service: FleetService | None):
        self.store = store
        self.service = service

    def collect(self) -> Iterator[Metric]:
        devices = self.store.device_counts()
        yield gauge("encoder_fleet_devices", "Devices known, by liveliness state.", "state", devices, sorted(devices))
        staged, parts = Rollouts(self.store).counts()
        yield gauge("encoder_fleet_staged_rollouts", "Staged rollouts, by state.", "state", staged, ROLLOUT_STATES)
        yield gauge(
            "encoder_fleet_rollout_devices",
            "Devices of the running and paused staged rollouts, by their part's state.",
            "state",
            parts,
            ("pending", "in_progress", *OUTCOMES),
        )
        yield CounterMetricFamily(
            "encoder_fleet_wal_checkpoint_failures",
            "Passes copying the SQLite WAL into the database file that the disk refused; the WAL grows meanwhile.",
            value=self.store.checkpoint_failures,
        )
        if self.service is None:
            return
        counters = self.service.counters.snapshot()
        ingested = counters["ingested"]
        windows = CounterMetricFamily(
            "encoder_fleet_messages_ingested", "Messages taken by the ingest writer, by outcome.", labels=["outcome"]
        )
        for outcome in INGESTED_OK:
            windows.add_metric([outcome], ingested.get(outcome, 0))
        yield windows
        rejected = CounterMetricFamily(
            "encoder_fleet_ingest_rejections",
            "Messages refused and kept as dead letters, by reason.",
            labels=["reason"],
        )
        for reason, count in sorted(ingested.items()):
            if reason not in INGESTED_OK:
                rejected.add_metric([reason], count)
        yield rejected
        yield CounterMetricFamily("encoder_fleet_refits", "Device refits run.", value=counters["refits"])
        yield GaugeMetricFamily(
            "encoder_fleet_partitions_served",
            "Device partitions this process serves (all of them when it runs alone).",
            value=len(self.service.partitions.held),
        )
        rollouts = CounterMetricFamily("encoder_fleet_rollouts", "Coefficient sets by outcome.", labels=["outcome"])
        rollouts.add_metric(["published"], counters["rollouts"])
        rollouts.add_metric(["rolled_back"], counters["rollbacks"])
        yield rollouts
        yield CounterMetricFamily(
            "encoder_fleet_storage_failures",
            "Ingest batches the database refused (disk full, read-only, I/O); the agents resend them.",
            value=counters["storage_failures"],
        )
        pruned = CounterMetricFamily(
            "encoder_fleet_pruned", "Rows deleted by retention (service --keep-days), by table.", labels=["table"]
        )
        pruned.add_metric(["windows"], counters["pruned_windows"])
        pruned.add_metric(["dead_letters"], counters["pruned_dead_letters"])
        yield pruned
        yield from self.service.counters.ingest_latency.collect()
        yield from self.service.counters.refit_latency.collect()
        alarms = self.store.open_alarm_counts()
        yield gauge("encoder_fleet_open_alarms", "Open drift alarms, by cause.", "cause", alarms, alarms)
        yield GaugeMetricFamily(
            "encoder_fleet_devices_silent",
            "Drives online (their token up) with nothing stored for 30 minutes: a fault no drift alarm can see.",
            value=len(self.store.silent_devices(SILENT_S)),
        )
        unacked = self.store.open_alarm_counts(unacked=True)
        yield gauge(
            "encoder_fleet_unacknowledged_alarms",
            "Open drift alarms no operator acknowledged (POST /alarms/{id}/ack), by cause.",
            "cause",
            unacked,
            alarms,  # a cause with open alarms all acknowledged reads 0, not absent: an alert on it resolves
        )


def gauge(name: str, documentation: str, label: str, counts: dict[str, int], values) -> GaugeMetricFamily:
    """One gauge per label value in `values`, from `counts` (a value it lacks reads 0)."""
    family = GaugeMetricFamily(name, documentation, labels=[label])
    for value in values:
        family.add_metric([value], counts.get(value, 0))
    return family


def metrics_registry(store: Store, service: FleetService | None) -> CollectorRegistry:
    registry = CollectorRegistry()
    registry.register(FleetCollector(store, service))
    return registry
