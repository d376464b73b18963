"""Staged rollouts (issue 12): a change that touches many drives goes out in waves, under control.

Anchors: AWS IoT Jobs (an exponential rollout rate `base_per_minute` x `increment_factor`^wave, abort criteria
`failure_type` / `threshold_percentage` / `min_executed`) and Eclipse hawkBit (a group starts when the one
before it has soaked; an error threshold stops the rollout).

- Wave k holds floor(base_per_minute * increment_factor**k) devices and starts at least a minute after wave
  k-1 started, and only once every device of wave k-1 has an outcome: so no more than the wave's rate starts
  per minute, and nothing new starts while the last wave is unproven.
- A device's part: an offline device (no liveliness token) waits for its token, `timeout_s` at most from the wave's
  start: then its part ends offline, no set issued and no failure counted (a drive that was not there says nothing
  of the change; one that goes away after its set went out does: timed_out, below).
  The change publishes a new set on trial (a device with a set on trial waits for its verdict,
  `timeout_s` at most from the wave's start: then its part ends timed_out, and no set of the rollout is
  issued); the soak is `soak_windows` windows the drive ran on it (the agent labels each window with the set it
  ran). Then the guard's own judge (service/trial.py)
  compares it with the set the device ran before on those windows: not worse -> succeeded, worse -> regressed
  and rolled back at once. An ack that refuses the set -> rejected, unless the drive overruled it before the part
  was decided (an ack 'applied' for the set, or windows run on it: it soaks as any other); the first outcome decided
  is final (a later 'applied' is answered by the rollback's set, delivered again while the drive's windows show an
  older one). No soak within `timeout_s` -> timed_out and rolled back (never worse: an unproven change does not
  stay).
- A drive retired since the rollout was made (Store.retire_device: what it sends is not stored) gets no set of it
  when its wave starts (unchanged), and one retired mid-soak is rolled back at once, unjudged: neither is counted.
- Abort criteria count outcomes decided since the rollout started or a criterion last paused it (executed: the parts
  a set of the rollout went out to; not `unchanged`, `offline`, or a part that never started, its trial unjudged):
  the outcomes decided while it is paused (its soaks are still judged) count once it is resumed. A criterion that
  trips pauses the rollout or aborts it; abort (tripped or asked for over REST) rolls the current wave back:
  every device of it still running the rollout's set gets the set it ran before again. Devices of later
  waves are never touched.
- All state is in the database (migrations/060_rollouts.sql, 080_rollout_offline.sql): a restarted service resumes
  where it was.
"""

from __future__ import annotations

import json
import logging
import math
import re
import threading
import time
from collections import Counter
from collections.abc import Callable
from typing import TYPE_CHECKING, Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, StringConstraints, field_validator, model_validator

from fleet_wire import keys

from .labels import MAX_LABELS, NAME_RULE, VALUE_RULE, check_labels
from .store import NothingWritten

if TYPE_CHECKING:
    from .runtime import FleetService
    from .store import Store

log = logging.getLogger("service.rollout")

FAILURE_TYPES = ("rejected", "timed_out", "regressed")
ROLLOUT_STATES = ("running", "paused", "aborted", "completed")
OUTCOMES = ("succeeded", "unchanged", "offline", *FAILURE_TYPES, "rolled_back")  # a device's part, once decided
WAVE_SPACING_S = 60.0  # the rate is per minute: wave k+1 starts no sooner than a minute after wave k


class AbortCriterion(BaseModel):
    model_config = ConfigDict(extra="forbid")
    failure_type: Literal["rejected", "timed_out", "regressed"]
    threshold_percentage: float = Field(gt=0, le=100, description="Trips when failures / executed reach this.")
    min_executed: int = Field(
        ge=1, le=10_000_000, description="Executed outcomes (a set of the rollout went out) needed before it may trip."
    )
    action: Literal["abort", "pause"] = Field("abort", description="abort rolls the current wave back.")


class Change(BaseModel):
    model_config = ConfigDict(extra="forbid")
    kind: Literal["reset_to_factory", "refit"] = Field(
        description="reset_to_factory: every drive runs its factory set again. refit: a refit now from the "
        "band sums (after a new refit method or policy), published through the waves instead of at once."
    )
    min_band_samples: int | None = Field(None, ge=1, description="refit only: the policy's samples per band.")


DeviceId = Annotated[str, StringConstraints(pattern=keys.DEVICE_RE.pattern)]
_WAVE = re.compile(r"[0-9]{1,10}")  # a wave in a page's cursor (devices_next): at most 2**31, as GET's wave


class RolloutSpec(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: str = Field(min_length=1, max_length=200)
    change: Change
    devices: list[DeviceId] | None = Field(
        None,
        min_length=1,
        max_length=1_000_000,
        description="Known devices to include; left out, every device in the fleet (or those `labels` select).",
    )
    labels: dict[str, str] | None = Field(
        None,
        description="Instead of `devices`: every device in the fleet that carries all these labels "
        f"(PUT /devices/{{id}}/labels), as they are when the rollout is created; at most {MAX_LABELS}, names "
        f"{NAME_RULE}, values {VALUE_RULE}.",
        examples=[{"site": "plant-3"}],
    )
    base_per_minute: int = Field(ge=1, le=1_000_000, description="Devices in the first wave.")
    increment_factor: float = Field(1.0, ge=1.0, le=10.0, description="Each wave is this many times the last.")
    soak_windows: int = Field(ge=1, le=100_000, description="Windows a drive runs on the new set before judging.")
    timeout_s: float = Field(3600.0, gt=0, le=30 * 86400, description="Service seconds a device has to soak.")
    abort_criteria: list[AbortCriterion] = Field(default_factory=list, max_length=10)

    @field_validator("labels")
    @classmethod
    def by_the_rules(cls, labels: dict[str, str] | None) -> dict[str, str] | None:
        if labels is not None and not labels:
            raise ValueError("select by at least one label, or leave `labels` out")
        return labels if labels is None else check_labels(labels)

    @model_validator(mode="after")
    def devices_or_labels(self) -> RolloutSpec:
        if self.devices is not None and self.labels is not None:
            raise ValueError("name the devices or select them by labels, not both")
        return self


# a rollout's parts in one page of GET /rollouts/{id}: 100,000 of them (waves of 100) made 13.9 MB, 0.8 s a read
DEVICES_PAGE = 1000
CREATE_LOCK = 0x454E4352  # the advisory lock ('ENCR') that makes a rollout's creation one step across processes


class RolloutStopped(NothingWritten):
    """The rollout was paused or aborted while this process started one of its devices, or another process issued
    the device a set meanwhile: the rollout's set is not issued."""


class DeviceHeld(NothingWritten):
    """A rollout started on the device while this process made it a set of its own (a refit, a rollback): that set
    is not issued, the device is the rollout's (service processes share the fleet: one steps every rollout)."""


class RolloutError(ValueError):
    """A request the rollouts cannot take: `status` is the HTTP status that says so."""

    def __init__(self, status: int, message: str, loc: tuple = ()):
        super().__init__(message)
        self.status = status
        self.loc = loc  # where in the request, for a 422 (the shape of FastAPI's own: ("body", "devices"))

    def __reduce__(self):  # pickled with every argument: a worker process's error reaches its pool intact
        return type(self), (self.status, str(self), self.loc)


class RolloutRefused(RolloutError, NothingWritten):
    """A creation refused inside its transaction, before it wrote anything (service.store.NothingWritten)."""


def wave_sizes(total: int, base: int, factor: float) -> list[int]:
    sizes, placed = [], 0  # the running sum: summed anew at every wave, 100,000 waves of 1 took 40 s
    while placed < total:
        sizes.append(min(max(1, math.floor(base * factor ** len(sizes) + 1e-9)), total - placed))
        placed += sizes[-1]
    return sizes


class Rollouts:
    """The rollouts in one store; with the running service (`service`) they can be stepped and changed,
    without it (the REST app of a bare Store) only read."""

    def __init__(self, store: Store, service: FleetService | None = None, *, clock: Callable[[], float] = time.time):
        self.store = store
        self.service = service
        self.clock = clock
        self._lock = threading.RLock()  # REST calls and the refit thread's steps take turns

    # --- the operator's side (REST) ----------------------------------------------------------------

    def _devices_of(self, spec: RolloutSpec) -> list[str]:
        """The drives the spec takes, in the order their waves take them; RolloutError (422) for a spec that takes
        none or names one the fleet does not have (unknown, or retired)."""
        if spec.labels is not None:  # the store's own selection: known and in the fleet, so nothing more to check
            devices = self.store.device_ids(in_fleet=True, labels=spec.labels)
            if not devices:
                selected = ", ".join(f"{k}={v}" for k, v in spec.labels.items())
                raise RolloutError(422, f"no device in the fleet carries {selected}", ("body", "labels"))
            return devices
        known = self.store.device_ids()
        retired = self.store.retired_device_ids()
        devices = [d for d in known if d not in retired] if spec.devices is None else list(dict.fromkeys(spec.devices))
        for what, names in (("unknown", set(devices) - set(known)), ("retired", set(devices) & retired)):
            if names:
                names = sorted(names)
                more = f" and {len(names) - 10} more" if len(names) > 10 else ""
                raise RolloutError(422, f"{what} devices: {', '.join(names[:10])}{more}", ("body", "devices"))
        if not devices:
            why = "every device is retired" if known else "the fleet has none yet"
            raise RolloutError(422, f"no devices to roll out to: {why}", ("body", "devices"))
        return devices

    _BUSY = "SELECT id, name FROM rollouts WHERE state IN ('running', 'paused') ORDER BY id LIMIT 1"

    @staticmethod
    def _busy(row) -> str | None:
        """Why create refuses a rollout while the one in `row` (_BUSY's) runs, or None."""
        return None if row is None else f"rollout {row['id']} ({row['name']!r}) is still running or paused"

    def plan(self, spec: RolloutSpec, *, listed: int = 20) -> dict:
        """What create(spec) would do now, creating nothing: the drives it takes (the first `listed` named), its
        waves' sizes, and the least time before its last wave starts (a minute between waves, if each soaks at
        once), how many are offline now, and why create would refuse it now (409: another rollout runs) or None;
        the same 422 as create for a spec that takes none."""
        with self._lock:
            devices = self._devices_of(spec)
            running = self.store._rows(self._BUSY)
            busy = self._busy(running[0] if running else None)
        sizes = wave_sizes(len(devices), spec.base_per_minute, spec.increment_factor)
        return {
            "devices_total": len(devices),
            "devices": devices[:listed],
            "waves": sizes,
            "last_wave_after_min": len(sizes) - 1,
            # offline now: such a drive's part waits for its token, timeout_s at most, then ends offline
            "offline": len(set(devices) - set(self.store.online_device_ids())),
            # a dry run while another rollout runs said "would roll out", and create then answered 409
            "refused": busy,
        }

    def create(self, spec: RolloutSpec) -> int:
        with self._lock:
            devices = self._devices_of(spec)
            now = self.clock()
            sizes = wave_sizes(len(devices), spec.base_per_minute, spec.increment_factor)
            waves = [wave for wave, size in enumerate(sizes) for _ in range(size)]
            with self.store._tx() as c:
                # the check inside the insert's transaction, one process at a time: two members' REST each creating
                # one (every member answers POST /rollouts) both found none running and both ran
                if not self.store.serialise_transaction(CREATE_LOCK):
                    raise RolloutRefused(409, "another service process is creating a rollout: try again")
                busy = self._busy(c.execute(self._BUSY).fetchone())
                if busy:  # one change at a time: outcomes of two changes on one drive could not be told apart
                    raise RolloutRefused(409, busy)
                # no "labels": null in a spec without them: a service before labels (a member not yet upgraded, one
                # rolled back to) refuses the field, and stepping every rollout failed on it, not only those by label
                stored = spec.model_dump_json(exclude={"labels"} if spec.labels is None else None)
                cur = c.execute(
                    "INSERT INTO rollouts (name, spec_json, state, counted_from, created_at, updated_at) "
                    "VALUES (?, ?, 'running', ?, ?, ?)",
                    (spec.name, stored, now, now, now),
                )
                rollout = cur.lastrowid
                c.executemany(
                    "INSERT INTO rollout_devices (rollout, device, wave, state) VALUES (?, ?, ?, 'pending')",
                    [(rollout, device, wave) for device, wave in zip(devices, waves, strict=True)],
                )
            log.info("rollout created", extra={"rollout": rollout, "devices": len(devices), "waves": len(sizes)})
            return rollout

    def pause(self, rollout: int, reason: str = "paused by an operator") -> dict:
        with self._lock:
            self._expect(rollout, ("running",), "pause")
            self._set_state(rollout, "paused", reason)
            return self.get(rollout, limit=DEVICES_PAGE)

    def resume(self, rollout: int) -> dict:
        with self._lock:
            self._expect(rollout, ("paused",), "resume")
            # counted_from is kept: the outcomes decided while paused count now (a criterion that paused it moved it
            # past the outcomes that tripped it)
            self._update(rollout, state="running", reason="resumed by an operator")
            return self.get(rollout, limit=DEVICES_PAGE)

    def abort(self, rollout: int, reason: str = "aborted by an operator") -> dict:
        with self._lock:
            self._expect(rollout, ("running", "paused"), "abort")
            self._abort(rollout, reason)
            return self.get(rollout, limit=DEVICES_PAGE)

    # --- what the service reads ---------------------------------------------------------------------

    def holds(self, device: str) -> bool:
        """The device is soaking a rollout's set: the automatic refit leaves it alone."""
        return bool(
            self.store._rows("SELECT 1 FROM rollout_devices WHERE device = ? AND state = 'in_progress'", (device,))
        )

    def counts(self) -> tuple[dict[str, int], dict[str, int]]:
        """(rollouts by state, devices of running and paused rollouts by state): for /metrics."""
        by_state = self.store._rows("SELECT state, count(*) AS n FROM rollouts GROUP BY state")
        devices = self.store._rows(
            "SELECT d.state, count(*) AS n FROM rollout_devices d JOIN rollouts r ON r.id = d.rollout "
            "WHERE r.state IN ('running', 'paused') GROUP BY d.state"
        )
        return {r["state"]: r["n"] for r in by_state}, {r["state"]: r["n"] for r in devices}

    def list(self) -> list[dict]:
        rows = self.store._rows("SELECT id FROM rollouts ORDER BY id DESC")
        return [self.get(r["id"], with_devices=False) for r in rows]

    def get(
        self,
        rollout: int,
        *,
        with_devices: bool = True,
        limit: int | None = None,
        after: str | None = None,
        state: str | None = None,
        wave: int | None = None,
    ) -> dict:
        """The rollout, its counts by wave and state, and (with_devices) its parts in (wave, device) order: all of
        them, or a page of `limit` after the cursor `after` (a page's `devices_next`: "WAVE:DEVICE"), only those in
        `state` or `wave` when given. A page that stops short names the next in `devices_next` (None: the last)."""
        rows = self.store._rows("SELECT * FROM rollouts WHERE id = ?", (rollout,))
        if not rows:
            raise RolloutError(404, f"no rollout {rollout}")
        r = rows[0]
        waves: dict[int, Counter] = {}
        paged = limit is not None or after is not None or state is not None or wave is not None
        devices = self._devices(rollout) if with_devices and not paged else None
        if devices is not None:  # the counts from the same read as the parts listed
            counted = [{"wave": d["wave"], "state": d["state"], "n": 1} for d in devices]
        else:  # by the database: a summary (GET /rollouts, every refresh of the fleet page) read every part
            counted = self.store._rows(
                "SELECT wave, state, count(*) AS n FROM rollout_devices WHERE rollout = ? GROUP BY wave, state",
                (rollout,),
            )
        for c in counted:
            waves.setdefault(c["wave"], Counter())[c["state"]] += c["n"]
        by_state = sum(waves.values(), Counter())
        total = sum(by_state.values())
        done = sum(n for state, n in by_state.items() if state in OUTCOMES)
        out = {
            "id": r["id"],
            "name": r["name"],
            "spec": json.loads(r["spec_json"]),
            "state": r["state"],
            "reason": r["reason"],
            "wave": r["wave"],
            "wave_started_at": r["wave_started_at"],
            "created_at": r["created_at"],
            "updated_at": r["updated_at"],
            "devices_total": total,
            "devices_done": done,
            "percent_done": round(100.0 * done / total, 1) if total else 100.0,
            "by_state": dict(sorted(by_state.items())),
            "waves": [
                {"wave": w, "size": sum(c.values()), "by_state": dict(sorted(c.items()))}
                for w, c in sorted(waves.items())
            ],
        }
        if devices is not None:
            out["devices"], out["devices_next"] = devices, None
        elif with_devices:
            out["devices"], out["devices_next"] = self._devices_page(rollout, limit, after, state, wave)
        return out

    _PART = "SELECT device, wave, state, before_version, version, started_at, decided_at, reason FROM rollout_devices "

    def _devices(self, rollout: int) -> list[dict]:
        rows = self.store._rows(self._PART + "WHERE rollout = ? ORDER BY wave, device", (rollout,))
        return [dict(r) for r in rows]

    def _devices_page(self, rollout: int, limit, after, state, wave) -> tuple[list[dict], str | None]:
        where, args = ["rollout = ?"], [rollout]
        if after is not None:
            after_wave, _, after_device = after.partition(":")
            # ASCII digits no longer than a wave can be, and a device's name: as a page's devices_next says it (a
            # wave past 64 bits, which SQLite cannot bind, or a digit int() refuses (²) answered 500)
            valid = _WAVE.fullmatch(after_wave) and int(after_wave) <= 2**31 and keys.DEVICE_RE.fullmatch(after_device)
            if not valid or len(after) > 100:
                raise RolloutError(
                    422, f"after {after!r}: expected WAVE:DEVICE, a page's devices_next", ("query", "after")
                )
            where.append("(wave > ? OR (wave = ? AND device > ?))")
            args += [int(after_wave), int(after_wave), after_device]
        if state is not None:
            where.append("state = ?")
            args.append(state)
        if wave is not None:
            where.append("wave = ?")
            args.append(wave)
        limit = DEVICES_PAGE if limit is None else limit
        rows = self.store._rows(
            self._PART + f"WHERE {' AND '.join(where)} ORDER BY wave, device LIMIT ?", (*args, limit + 1)
        )
        parts = [dict(r) for r in rows[:limit]]
        more = len(rows) > limit and parts
        return parts, f"{parts[-1]['wave']}:{parts[-1]['device']}" if more else None

    # --- the controller (the refit thread) ----------------------------------------------------------

    def step(self) -> None:
        """Decide what the soaks say, apply the abort criteria, start the next devices."""
        with self._lock:
            for r in self.store._rows("SELECT * FROM rollouts WHERE state IN ('running', 'paused') ORDER BY id"):
                self._step_one(r)

    def _step_one(self, r) -> None:
        rollout, spec = r["id"], RolloutSpec.model_validate_json(r["spec_json"])
        now = self.clock()
        devices = self._devices(rollout)
        retired = self.store.retired_device_ids()  # out of the fleet since the rollout was made (Store.retire_device)
        for d in devices:  # a paused rollout still decides its soaks: a regressed drive is rolled back at once
            if d["state"] == "in_progress":
                self._decide(rollout, spec, d, now, retired)
        if r["state"] == "paused":
            return
        devices = self._devices(rollout)
        tripped = self._tripped(spec, devices, r["counted_from"])
        if tripped is not None:
            criterion, reason = tripped
            if criterion.action == "pause":  # the outcomes that tripped it are not counted again after a resume
                self._update(rollout, state="paused", reason=reason, counted_from=math.nextafter(now, math.inf))
            else:
                self._abort(rollout, reason)
            log.warning("rollout abort criterion tripped", extra={"rollout": rollout, "reason": reason})
            return
        wave = r["wave"]
        in_wave = [d for d in devices if d["wave"] == wave]
        if r["wave_started_at"] is None or any(d["state"] == "pending" for d in in_wave):
            if r["wave_started_at"] is None:
                self._update(rollout, wave_started_at=now)
            wave_started_at = now if r["wave_started_at"] is None else r["wave_started_at"]
            for d in in_wave:
                if d["state"] == "pending":
                    self._start(rollout, spec, d["device"], now, wave_started_at, retired)
            return
        if any(d["state"] not in OUTCOMES for d in in_wave):
            return  # the wave is soaking
        if wave == max(d["wave"] for d in devices):
            counts = Counter(d["state"] for d in devices)
            self._set_state(rollout, "completed", ", ".join(f"{n} {s}" for s, n in sorted(counts.items())))
            log.info("rollout completed", extra={"rollout": rollout})
            return
        if now - r["wave_started_at"] >= WAVE_SPACING_S:
            self._update(rollout, wave=wave + 1, wave_started_at=None)
            self._step_one(self.store._rows("SELECT * FROM rollouts WHERE id = ?", (rollout,))[0])

    def _start(
        self, rollout: int, spec: RolloutSpec, device: str, now: float, wave_started_at: float, retired: set[str]
    ) -> None:
        """Publish the change to one device, on trial. An offline device (no liveliness token) waits for its token,
        and a device with a set already on trial waits for that trial's verdict, timeout_s from the wave's start at
        most (a drive gone offline before it ran its trial set keeps that trial for good: the guard keeps no set on
        no evidence, and the wave would never end). A device retired since the rollout was made gets none."""
        store = self.store
        if device in retired:
            reason = "retired from the fleet before its wave: no set issued"
            self._record(rollout, device, "unchanged", now, before=store.published_version(device), reason=reason)
            return
        online = store._rows("SELECT online FROM devices WHERE id = ?", (device,))
        if not (online and online[0]["online"]):
            # no liveliness token: a set issued now would time out unsoaked and count as a failure of the change,
            # and roll back, for a drive that was not there. It waits; not back in time, it ends offline, untouched.
            if now - wave_started_at >= spec.timeout_s:
                reason = f"offline from its wave's start for {spec.timeout_s:g} s: no set issued"
                self._record(rollout, device, "offline", now, before=store.published_version(device), reason=reason)
            return
        if (trial := store.set_on_trial(device)) is not None:
            if now - wave_started_at >= spec.timeout_s:
                reason = f"its set on trial v{trial['version']} was not judged within {spec.timeout_s:g} s: not started"
                self._record(rollout, device, "timed_out", now, before=store.published_version(device), reason=reason)
            return  # the guard is judging a fit: the change starts after it, on a known-good base
        running = store.published_version(device)
        before = store.coefficient_set(device, running) if running is not None else None
        if before is None:
            self._record(rollout, device, "unchanged", now, reason="no set known for the device")
            return
        why = f"rollout {rollout}: {spec.change.kind}"

        def started(version: int) -> None:  # inside the set's transaction: a crash keeps both or neither
            with store._tx() as c:
                # still running, checked where the set is written: an abort or pause by another process (a REST
                # call on any member) between this step's read and here must not let its set out
                cur = c.execute("UPDATE rollouts SET updated_at = ? WHERE id = ? AND state = 'running'", (now, rollout))
                if cur.rowcount != 1:
                    raise RolloutStopped(f"rollout {rollout} is no longer running")
                # nothing issued to the device since `running` was read (another process serves it and may have
                # refitted it meanwhile): two sets in flight for one drive could not be told apart
                newer = c.execute(
                    "SELECT version FROM coefficient_sets WHERE device = ? AND version > ? AND version < ? "
                    "AND state != 'rolled_back' LIMIT 1",
                    (device, running, version),
                ).fetchone()
                if newer is not None:
                    raise RolloutStopped(f"v{newer[0]} was issued to {device} meanwhile: it starts after it")
                c.execute(
                    "UPDATE rollout_devices SET state = 'in_progress', before_version = ?, version = ?, "
                    "started_at = ? WHERE rollout = ? AND device = ?",
                    (running, version, now, rollout, device),
                )

        try:
            if spec.change.kind == "reset_to_factory":
                factory = store.coefficient_set(device, 0)
                if factory is None or _same_bands(factory["bands"], before["bands"]):
                    reason = "already runs its factory set"
                    self._record(rollout, device, "unchanged", now, before=running, reason=reason)
                    return
                self.service.publish_bands(device, factory["bands"], restores_version=0, reason=why, then=started)
            else:
                result = self.service.fit(device, min_band_samples=spec.change.min_band_samples)
                if result is None or not result.changed:
                    never = self.service.never_refit(device) if result is None else None
                    reason = "the refit changes nothing" if never is None else f"not refit: {never}"
                    self._record(rollout, device, "unchanged", now, before=running, reason=reason)
                    return
                self.service.publish_fit(device, result, reason=why, then=started)
        except RolloutStopped as stopped:
            log.info("rollout set not issued: %s", stopped, extra={"rollout": rollout, "device": device})

    def _decide(self, rollout: int, spec: RolloutSpec, d: dict, now: float, retired: set[str]) -> None:
        device, version = d["device"], d["version"]
        if device in retired:
            # what it sends is not stored, so no soak comes: timed out, it counted as a failure of the change (and
            # tripped aborts). Rolled back unjudged now, as an abort's wave: an unproven change does not stay
            self._revert(rollout, d, "rolled_back", "retired from the fleet before its soak was judged", now)
            return
        soaked = self.store._rows(
            "SELECT count(*) AS n FROM windows WHERE device = ? AND coefficients_version = ?", (device, version)
        )[0]["n"]
        # a refusal the drive overruled (an ack 'applied' for the set after it: store.refusals leaves those out, or
        # windows run on it) is none: rolling back then would revert a set the drive runs, and count it a failure
        refused = [r for r in self.store.refusals(device) if r["version"] == version] if not soaked else []
        if refused:  # the drive still runs the set before: the service's record says so again
            self._revert(rollout, d, "rejected", f"the agent refused v{version}: {refused[0]['reason']}", now)
            return
        late = now - d["started_at"] >= spec.timeout_s
        if soaked < spec.soak_windows:
            if late:
                reason = f"{soaked} of {spec.soak_windows} soak windows within {spec.timeout_s:g} s"
                self._revert(rollout, d, "timed_out", reason, now)
            return
        trial = self.store.coefficient_set(device, version)
        before = self.store.coefficient_set(device, d["before_version"])
        verdict = self.service.judge_set(device, trial, before)
        if verdict.action == "rollback":
            self._revert(rollout, d, "regressed", verdict.reason, now)
            return
        if verdict.action == "confirm":
            reason = verdict.reason
        elif late:  # soaked, but the windows cannot tell the sets apart: kept, as the guard keeps a trial
            reason = f"{verdict.reason}; not measurable within {spec.timeout_s:g} s: kept"
        else:
            return  # soaking on
        drive_now = self.service._drive_now(device)
        with self.store.transaction():  # the set's state and the rollout's record land together
            self.store.set_state(device, version, "confirmed", at=drive_now, reason=f"rollout {rollout}: {reason}")
            self._record(rollout, device, "succeeded", now, reason=reason)

    def _tripped(self, spec: RolloutSpec, devices: list[dict], counted_from: float):
        # executed: a set of the rollout went out (its version recorded). A no-op is none: counted, 3 unchanged beside
        # 1 regressed read as 25 % failed, not 100 %; nor a part that never started (offline, or its trial unjudged),
        # nor one rolled back unjudged (its drive retired mid-soak: it says nothing of the change)
        decided = [
            d
            for d in devices
            if d["state"] in OUTCOMES
            and d["state"] != "rolled_back"
            and d["version"] is not None
            and d["decided_at"] >= counted_from
        ]
        executed = len(decided)
        for criterion in spec.abort_criteria:
            failures = sum(d["state"] == criterion.failure_type for d in decided)
            if executed >= criterion.min_executed and 100.0 * failures / executed >= criterion.threshold_percentage:
                share = 100.0 * failures / executed
                return criterion, (
                    f"{failures} of {executed} executed {criterion.failure_type} ({share:.0f} % >= "
                    f"{criterion.threshold_percentage:g} %)"
                )
        return None

    def _abort(self, rollout: int, reason: str) -> None:
        """Stop, and roll the current wave back: its devices still on the rollout's set run their set before.
        The state first: a device another process starts after it is refused (`started`), one it started before
        is in the list read after it."""
        now = self.clock()
        self._set_state(rollout, "aborted", reason)
        wave = self.store._rows("SELECT wave FROM rollouts WHERE id = ?", (rollout,))[0]["wave"]
        for d in self._devices(rollout):
            if d["wave"] != wave or d["state"] not in ("in_progress", "succeeded"):
                continue
            newest = self.store.newest_set(d["device"])
            if newest is None or newest["version"] != d["version"]:
                continue  # the device has moved on since (a later fit): that set is the guard's, not ours
            # (its set may not be published yet: a put that failed; rolled back here, deliver does not send it)
            self._revert(rollout, d, "rolled_back", f"wave rolled back: {reason}", now)
        log.warning("rollout aborted", extra={"rollout": rollout, "reason": reason})

    def _revert(self, rollout: int, d: dict, outcome: str, reason: str, now: float) -> None:
        """The device gets the set it ran before the rollout again, and its part ends as `outcome`, in one
        transaction (a crash between them would roll it back twice)."""
        device = d["device"]
        before = self.store.coefficient_set(device, d["before_version"])

        def record() -> None:
            self._record(rollout, device, outcome, now, reason=reason)

        self.service.roll_back(device, d["version"], before, f"rollout {rollout}: {reason}", then=record)

    def _record(self, rollout: int, device: str, state: str, now: float, *, reason: str, before=None) -> None:
        with self.store._tx() as c:
            c.execute(
                "UPDATE rollout_devices SET state = ?, decided_at = ?, reason = ?, "
                "before_version = coalesce(before_version, ?) WHERE rollout = ? AND device = ?",
                (state, now, reason, before, rollout, device),
            )

    def _expect(self, rollout: int, states: tuple[str, ...], what: str) -> None:
        rows = self.store._rows("SELECT state FROM rollouts WHERE id = ?", (rollout,))
        if not rows:
            raise RolloutError(404, f"no rollout {rollout}")
        state = rows[0]["state"]
        if state not in states:
            raise RolloutError(409, f"rollout {rollout} is {state}: cannot {what} it")

    def _set_state(self, rollout: int, state: str, reason: str) -> None:
        self._update(rollout, state=state, reason=reason)

    def _update(self, rollout: int, **values) -> None:
        values["updated_at"] = self.clock()
        assignments = ", ".join(f"{column} = ?" for column in values)  # column names are this module's own
        with self.store._tx() as c:
            c.execute(f"UPDATE rollouts SET {assignments} WHERE id = ?", (*values.values(), rollout))


def _same_bands(a: list[dict], b: list[dict]) -> bool:
    return _band_keys(a) == _band_keys(b)


def _band_keys(bands: list[dict]) -> list[str]:
    return sorted(json.dumps({k: v for k, v in band.items() if k != "quality"}, sort_keys=True) for band in bands)
