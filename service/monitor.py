"""The drift monitor in the service: feeds stored windows to each device's monitor (encoder_core.monitor),
keeps its state and alarms in SQLite (migration 020), publishes alarms on `encoders/<device>/alarms`.

Windows are read back from the store in seq order, only up to the device's contiguous watermark, so each is
seen exactly once and in order even when an agent catches up out of order; the monitor's state, the last seq
it saw and the alarms it raised are written in one transaction. A restart loads the states and goes on from
the last seq: a drift in progress is not forgotten, an alarm is not raised twice (a unique index allows one
open alarm per device and cause).
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Callable

from encoder_core.monitor import DeviceMonitor, FleetRates, Settings, ellipse_fits, window_features
from fleet_wire import alarms as alarm_wire

from .refit import STEP_CAUSES
from .store import Store

log = logging.getLogger("service.monitor")
STATES = ("ok", "watch", "alarm", "offline", "unknown", "retired")  # retired: out of the fleet (Store.retire_device)
# an online drive with nothing stored for this long (service clock) is silent: three of the longest windows (600 s)
SILENT_S = 1800.0
SILENT_LISTED = 100  # silent drives named in GET /fleet/health (all are counted)
PAGE = 500  # windows read and committed at a time (a device that sends 10,000 at once is taken in pages)
# a device's state is written with its alarms at once, and otherwise after this many windows or this much drive time
# since it was last written: a restart goes on from the state written and feeds the windows since then again (all
# stored, read in the same order: the same state; no alarm is fed twice, since every alarm is written at once). At
# every window, writing a state of ~27 KB of JSON was 58 % of the monitor's time (a fleet replayed at 3,600x)
SAVE_EVERY_WINDOWS = 12
SAVE_EVERY_S = 3600.0


class Monitor:
    def __init__(
        self,
        store: Store,
        *,
        publish: Callable[[str, bytes], None] | None = None,
        settings: Settings | None = None,
    ):
        self.store = store
        self.publish = publish
        self.settings = settings or Settings()
        self.fleet = FleetRates(self.settings)
        self.devices: dict[str, DeviceMonitor] = {}
        self.last_seq: dict[str, int] = {}
        self._unsaved: dict[str, tuple[int, float]] = {}  # device -> (windows fed, first one's end) since written
        self._lags: dict[tuple[str, int], float] = {}
        self._forgotten: set[str] = set()  # devices whose state in memory was dropped after a failed write
        self._lock = threading.RLock()
        self.reload(lambda device: True)

    def reload(self, which: Callable[[str], bool]) -> None:
        """(Re)read the saved state of the devices `which` selects: at start, and when this process takes over
        devices another process monitored (service/cluster.py)."""
        with self._lock:
            for device in [d for d in self.devices if which(d)]:
                del self.devices[device]
                del self.last_seq[device]
                self._unsaved.pop(device, None)
            self._adopt({d: saved for d, saved in self.store.monitor_states().items() if which(d)})

    def _adopt(self, states: dict[str, tuple[dict | None, int]]) -> None:
        """Take saved states (Store.monitor_states) as the devices' monitors."""
        with self._lock:
            for device, (state, last_seq) in states.items():
                try:
                    if state is None:
                        raise ValueError("its saved state is not a JSON object")
                    mon = DeviceMonitor.from_dict(state, self.settings)
                except (KeyError, TypeError, ValueError) as exc:  # a state from an incompatible version: start over
                    mon = self._start_over(device, last_seq)
                    log.warning(
                        "monitor state unreadable, starting over",
                        extra={"device": device, "error": str(exc), "open": sorted(mon.open)},
                    )
                self.devices[device] = mon
                self.last_seq[device] = last_seq
                self.fleet.report(device, mon.rate_estimates())

    def _start_over(self, device: str, last_seq: int) -> DeviceMonitor:
        """A new monitor for a device whose saved state is lost, holding the alarms the lost one left open: a monitor
        that did not know of them never cleared them (open in the store for good, the device's state "ok" beside
        them, a later raise of the cause skipped as already open). Held, each is cleared by the rule that clears
        it from any monitor (a refit applied, a rate back down, the token back), judged from the windows since."""
        mon = DeviceMonitor(device, self.settings)
        for alarm in self.store.alarms(device, open_=True, limit=None):
            mon.open[alarm["cause"]] = {
                "raised_at": alarm["raised_at"],
                "parameters": alarm["parameters"],
                "quiet_since": None,
            }
        mon.online = "offline" not in mon.open  # as the last token heard said
        # the drive time it had reached (the last window fed): a clear dated 0 s would come before its raise
        last = self.store.monitor_windows(device, last_seq - 1, last_seq, limit=1) if last_seq > 0 else []
        mon.last_t = last[0]["window_end"] if last else None
        return mon

    def _known(self, device: str) -> DeviceMonitor | None:
        """The device's monitor, read again as written last where it was dropped (see _forget); None if none."""
        if device in self._forgotten:
            self._adopt(self.store.monitor_states(device))
            self._forgotten.discard(device)
        return self.devices.get(device)

    def _device(self, device: str) -> DeviceMonitor:
        mon = self._known(device)
        if mon is None:
            mon = self.devices[device] = DeviceMonitor(device, self.settings)
            self.last_seq[device] = 0
        return mon

    def _forget(self, device: str) -> None:
        """A state the database refused to write (busy, full): the one in memory has run ahead of it (windows
        fed, alarms opened), and kept it would feed the next windows twice and never raise an alarm it holds open
        already. Dropped, it is read again as written when next needed, and the windows since are fed again: the
        same state, every alarm written once (as after a restart)."""
        self.devices.pop(device, None)
        self.last_seq.pop(device, None)
        self._unsaved.pop(device, None)
        self._forgotten.add(device)

    # --- feeding ------------------------------------------------------------------------------------

    def leave_out(self, devices) -> None:
        """Devices out of the fleet (retired): their rates, frozen when they left (often those of a drive replaced
        for ageing), are no reference for the fleet's; a reinstated one's count again."""
        with self._lock:
            self.fleet.leave_out(devices)

    def process(self, device: str) -> list[dict]:
        """Feed the device's stored windows it has not seen yet; returns the alarms raised or cleared."""
        written = []
        try:
            with self._lock:
                self._feed(device, written)
        finally:  # what was written before a failure is published all the same
            self._publish(written)
        return written

    def _feed(self, device: str, written: list[dict]) -> None:
        mon = self._device(device)
        try:
            through = self.store.contiguous_seq(device, start=self.last_seq[device])
            while self.last_seq[device] < through:
                rows = self.store.monitor_windows(device, self.last_seq[device], through, limit=PAGE)
                if not rows:
                    break
                events = []
                # stored windows were checked on the way in; never let one stop the monitor
                rows_fed = [row for row in rows if row["stats"] is not None]
                for row, fits in zip(rows_fed, ellipse_fits([row["stats"] for row in rows_fed])):
                    f = window_features(
                        row["stats"],
                        t=row["window_end"],
                        temp_c=row["temp_mean_c"],
                        band=row["band"],
                        rejected_by_reason=row["rejected_by_reason"],
                        start=row["window_start"],
                        temp_rate=row["temp_rate_c_per_s"],
                        lag_used_s=self._lag_of(device, row["coefficients_version"]),
                        fits=fits,
                    )
                    events += mon.update(f, self.fleet)
                events += self._refit_clears(device, mon)
                fed, since = self._unsaved.get(device, (0, rows[0]["window_end"]))
                fed += len(rows)
                if events or fed >= SAVE_EVERY_WINDOWS or rows[-1]["window_end"] - since >= SAVE_EVERY_S:
                    written += self._save(device, mon, rows[-1]["seq"], events)
                else:
                    self.last_seq[device] = rows[-1]["seq"]
                    self._unsaved[device] = (fed, since)
        except BaseException:
            self._forget(device)
            raise

    def flush(self) -> None:
        """Write every state fed since it was last written (the service stops)."""
        with self._lock:
            for device in list(self._unsaved):
                self._save(device, self.devices[device], self.last_seq[device], [])

    def _lag_of(self, device: str, version: int) -> float:
        """The die lag the agent wrote a window's temperatures with: the τ of the set it ran (sets never change)."""
        key = (device, version)
        if key not in self._lags:
            msg = self.store.coefficient_set(device, version)
            if msg is None:
                return 0.0  # a set this service does not hold: the agent's factory set, or not stored yet
            self._lags[key] = float(msg.get("thermal_lag_s", 0.0))
        return self._lags[key]

    def thermal_lag(self, device: str) -> tuple[float, float] | None:
        """The device's die lag (τ s, standard error) as its windows measure it, or None."""
        with self._lock:
            mon = self._known(device)
            return mon.thermal_lag() if mon is not None else None

    def watches_held_positions(self, device: str) -> bool:
        """Whether the monitor would name a step of the positions the device holds (DeviceMonitor's)."""
        with self._lock:
            mon = self._known(device)
            return mon is not None and mon.watches_held_positions()

    def step_measured(self, device: str, at: float) -> bool:
        """Whether the step the device's monitor raised at `at` was measured as its alarm names it
        (DeviceMonitor.step_measured): only then is the running set moved by the alarm's parameters."""
        with self._lock:
            mon = self._known(device)
            return mon is None or mon.step_measured(at)

    def _refit_clears(self, device: str, mon: DeviceMonitor) -> list:
        """A step (offset, gain or axes) is cleared once the fleet has re-corrected the drive: a coefficient set
        created after the step has been applied by the agent (the refit history)."""
        open_steps = {cause: mon.open[cause] for cause in STEP_CAUSES if cause in mon.open}
        acks = self.store.acks(device) if open_steps else []
        cleared = []
        for cause, alarm in open_steps.items():
            for ack in acks:
                if ack["status"] != "applied" or ack["at"] < alarm["raised_at"]:
                    continue
                msg = self.store.coefficient_set(device, ack["version"])
                if msg is not None and msg["created_at"] >= alarm["raised_at"]:
                    why = f"coefficient set v{ack['version']}, made after the step, was applied by the agent."
                    if msg["basis"] == "rollback" and msg.get("restores_version") == 0:
                        # said as it is (a second reader: the clear read as if the drive were corrected for the
                        # step): the clear lets the monitor name the next step, as with any set made since, and
                        # bench-fleet-accuracy's loop judges the refit on that rule
                        why = (
                            f"coefficient set v{ack['version']}, the factory set again (its bands from the bench, "
                            "before the step), was applied by the agent: the step is not corrected for until a "
                            "refit measures it from the windows since."
                        )
                    cleared += mon.clear(cause, ack["at"], why)
                    break
        return cleared

    def set_online(self, device: str, online: bool) -> list[dict]:
        """From the liveliness token: offline raised when it goes, cleared when it is back."""
        with self._lock:
            mon = self._device(device)
            # none of its windows fed yet (a gap before them): its offline alarm is dated at the last one stored
            last = self.store.last_window(device) if mon.last_t is None else None
            events = mon.set_online(online, last[1] if last else None)
            if online and events:
                events = [self._outage_said(device, e) for e in events]
            try:
                written = self._save(device, mon, self.last_seq[device], events) if events else []
            except BaseException:  # the state as written stands (this change of the token is lost, and logged)
                self._forget(device)
                raise
        self._publish(written)
        return written

    def _outage_said(self, device: str, event):
        """The offline alarm's clear says how long the token was gone, on the service's clock: on the drive's, the
        outage ends where it began (no window of it was stored meanwhile; those the agent held come after the token),
        so raised_at and cleared_at alone read as no outage at all."""
        if event.kind != "clear" or event.cause != "offline":
            return event
        opened = self.store.alarms(device, "offline", True, limit=1, audit=True)
        if not opened:
            return event
        gone_s = max(0.0, time.time() - opened[0]["created_at"])
        said = (
            f"the agent's liveliness token is back after {_span(gone_s)} (service clock); the windows it held "
            "meanwhile arrive after it, so on the drive's clock the outage ends where it began."
        )
        return dataclasses.replace(event, evidence=said)

    def _save(self, device: str, mon: DeviceMonitor, last_seq: int, events) -> list[dict]:
        plain = [
            {"kind": e.kind, "cause": e.cause, "at": e.at, "parameters": e.parameters, "evidence": e.evidence}
            for e in events
        ]
        written = self.store.save_monitor(device, mon.to_dict(), last_seq, plain, device_state=mon.state())
        self.last_seq[device] = last_seq
        self._unsaved.pop(device, None)
        for a in written:
            log.warning(
                "alarm " + ("raised" if a["cleared_at"] is None else "cleared"),
                extra={"device": device, "cause": a["cause"], "raised_at": a["raised_at"], "evidence": a["evidence"]},
            )
        return written

    def _publish(self, written: list[dict]) -> None:
        if self.publish is None:
            return
        for alarm in written:
            try:
                key, payload = alarm_wire.encode(alarm)
                self.publish(key, payload)
            except Exception:  # publishing is best effort: the alarm is stored and listed either way
                log.exception("publishing an alarm failed")

    # --- reading ----------------------------------------------------------------------------------

    def state(self, device: str, online: bool | None = None) -> str:
        with self._lock:
            mon = self._known(device)
            if mon is None:
                return "offline" if online is False else "unknown"
            return mon.state()


def _stored_state(saved: tuple[dict | None, int] | None) -> str:
    if saved is None:
        return "unknown"
    try:
        return DeviceMonitor.from_dict(saved[0]).state()
    except (KeyError, TypeError, ValueError):
        return "unknown"


def device_state(
    store: Store, device: str, monitor: Monitor | None = None, serves: Callable[[str], bool] | None = None
) -> str:
    """ok | watch | alarm | offline | unknown: from the running monitor where this process monitors the device
    (`serves`: its partitions; None, every device), else as stored; retired for a device out of the fleet. In a
    cluster the monitor in memory holds the other members' devices as they stood when this process started (or last
    handed them over): read from it, GET /devices/{id}/health said "unknown" or "ok" beside the open alarms the other
    member wrote."""
    if device in store.retired_device_ids():
        return "retired"
    if monitor is not None and (serves is None or serves(device)):
        return monitor.state(device)
    return _stored_states(store, [device])[device]


def device_states(
    store: Store,
    monitor: Monitor | None = None,
    serves: Callable[[str], bool] | None = None,
    *,
    ids: list[str] | None = None,
) -> dict[str, str]:
    """Every device's state (device_state), or those of `ids`."""
    ids = store.device_ids() if ids is None else ids
    retired = store.retired_device_ids()
    in_fleet = [d for d in ids if d not in retired]
    if monitor is None:
        states = _stored_states(store, in_fleet)
    else:
        others = _stored_states(store, [d for d in in_fleet if serves is not None and not serves(d)])
        states = {d: others[d] if d in others else monitor.state(d) for d in in_fleet}
    return {d: states.get(d, "retired") for d in ids}


def _stored_states(store: Store, ids: list[str]) -> dict[str, str]:
    """The states the monitors wrote (a ~36 KB state parsed only where written before migration 075)."""
    if not ids:
        return {}
    written = store.monitor_device_states(ids[0] if len(ids) == 1 else None)
    out = {d: written.get(d) or "unknown" for d in ids}
    for d in [d for d in ids if d in written and written[d] is None]:
        out[d] = _stored_state(store.monitor_states(d).get(d))
    return out


def fleet_health(
    store: Store,
    monitor: Monitor | None = None,
    serves: Callable[[str], bool] | None = None,
    *,
    labels: dict[str, str] | None = None,
) -> dict:
    """Devices per state, open alarms per cause, and the drives online but silent (SILENT_S); labels: of the devices
    that carry all of them only (a site, a line)."""
    counts = dict.fromkeys(STATES, 0)
    ids = None if labels is None else store.device_ids(labels=labels)
    for state in device_states(store, monitor, serves, ids=ids).values():
        counts[state] += 1
    silent = store.silent_devices(SILENT_S, labels=labels)
    return {
        "devices": counts,
        "open_alarms": store.open_alarm_counts(labels=labels),
        "silent": len(silent),
        "silent_devices": silent[:SILENT_LISTED],
    }


def fleet_health_by(
    store: Store, name: str, monitor: Monitor | None = None, serves: Callable[[str], bool] | None = None
) -> list[dict]:
    """fleet_health for each value of label `name` (a site, a line), one group per value in order, and last the
    devices that do not carry it (value None): the fleet at a glance, a site a row."""
    values = store.label_values(name)
    groups: dict[str | None, dict] = {}

    def group(value: str | None) -> dict:
        if value not in groups:
            groups[value] = {"value": value, "devices": dict.fromkeys(STATES, 0), "open_alarms": {}, "silent": 0}
        return groups[value]

    for device, state in device_states(store, monitor, serves).items():
        group(values.get(device))["devices"][state] += 1
    for value, causes in store.open_alarm_counts_by(name).items():
        group(value)["open_alarms"] = dict(sorted(causes.items()))
    for device in store.silent_devices(SILENT_S):
        group(values.get(device))["silent"] += 1
    return sorted(groups.values(), key=lambda g: (g["value"] is None, g["value"] or ""))


def _span(seconds: float) -> str:
    """A duration as an operator reads it: 42 s, 12 min, 3.2 h, 2.1 days."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    if seconds < 172800:
        return f"{seconds / 3600:.1f} h"
    return f"{seconds / 86400:.1f} days"
