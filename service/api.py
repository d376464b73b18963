"""REST API over the Store: fleet health, coefficient history, windows, MCAP export, ingest rejections.

FastAPI's bigger-applications layout: one router per resource, the Store reached through a
dependency (app.state.store, set by create_app), no globals, so tests and the service each build
their own app around their own Store.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from importlib import resources
from typing import TYPE_CHECKING, Annotated, Literal

from fastapi import APIRouter, Depends, FastAPI, HTTPException, Query, Request
from fastapi import Path as FastAPIPath
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse, Response, StreamingResponse
from fastapi.staticfiles import StaticFiles
from fastapi_offline import FastAPIOffline
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from pydantic import BaseModel, ConfigDict, Field, field_validator

from .auth import CONTROL_CHARACTERS, TokenAuth, authorize, require_admin, tokens
from .labels import MAX_LABELS, NAME_RE, NAME_RULE, VALUE_RULE, check_labels, parse_selectors
from .mcap_export import iter_mcap
from .monitor import device_state, device_states, fleet_health, fleet_health_by
from .observability import health_checks, metrics_registry
from .rollout import DEVICES_PAGE, OUTCOMES, RolloutError, Rollouts, RolloutSpec
from .store import Store, StoreError

if TYPE_CHECKING:
    from .runtime import FleetService

LIVENESS = ("process", "database", "router", "storage")  # /healthz; /readyz asks every check

# --- dependencies -------------------------------------------------------------------------------


def get_store(request: Request) -> Store:
    return request.app.state.store


StoreDep = Annotated[Store, Depends(get_store)]


def known_device(device_id: str, store: StoreDep) -> dict:
    device = store.device(device_id)
    if device is None:
        raise HTTPException(status_code=404, detail=f"unknown device {device_id!r}")
    return device


DeviceDep = Annotated[dict, Depends(known_device)]


@dataclass
class TimeRange:
    t_from: float | None
    t_to: float | None


def time_range(
    t_from: Annotated[
        float | None, Query(alias="from", allow_inf_nan=False, description="Start, s on the drive's clock (inclusive).")
    ] = None,
    t_to: Annotated[
        float | None, Query(alias="to", allow_inf_nan=False, description="End, s on the drive's clock (inclusive).")
    ] = None,
) -> TimeRange:
    if t_from is not None and t_to is not None and t_from > t_to:
        # the same shape as every other 422, so the OpenAPI spec's HTTPValidationError describes it
        message = f"'from' ({t_from}) is after 'to' ({t_to})"
        raise RequestValidationError(
            [{"type": "value_error", "loc": ("query", "from"), "msg": message, "input": t_from}]
        )
    return TimeRange(t_from, t_to)


RangeDep = Annotated[TimeRange, Depends(time_range)]


def label_selector(
    label: Annotated[
        list[str] | None,
        Query(
            description="NAME=VALUE: only devices that carry this label (PUT /devices/{id}/labels); "
            "several: devices that carry them all."
        ),
    ] = None,
) -> dict[str, str] | None:
    try:
        return parse_selectors(label) or None
    except ValueError as exc:  # the same shape as every other 422
        raise RequestValidationError(
            [{"type": "value_error", "loc": ("query", "label"), "msg": str(exc), "input": label}]
        ) from None


LabelsDep = Annotated[dict[str, str] | None, Depends(label_selector)]


# --- response models (for the OpenAPI docs; wire messages stay plain JSON objects) -------------


class ErrorMessage(BaseModel):
    detail: str


class Retired(BaseModel):
    at: float = Field(description="Service clock, unix s.")
    by: str = Field(description='The REST token that retired it, e.g. "token 3 (ops desk)".')
    note: str


class Device(BaseModel):
    id: str
    first_seen: float = Field(description="Service clock, unix s.")
    last_seen: float = Field(description="Service clock, unix s: last window, ack or liveliness change.")
    online: bool = Field(description="Liveliness token held.")
    current_version: int | None = Field(description="Coefficient version the agent last reported using.")
    windows: int = Field(description="Windows stored.")
    state: str = Field(
        "unknown",
        description="ok | watch | alarm | offline | unknown (the drift monitor, /devices/{id}/health), or retired.",
    )
    retired: Retired | None = Field(
        None, description="Taken out of the fleet (POST /devices/{id}/retire): who, when, why; null while in the fleet."
    )
    labels: dict[str, str] = Field(default_factory=dict, description="NAME: VALUE, as PUT /devices/{id}/labels set.")


class DeviceLabels(BaseModel):
    model_config = ConfigDict(extra="forbid")
    labels: dict[str, str] = Field(
        description=f"Every label of the device (replacing those it had; {{}} removes them): at most {MAX_LABELS}, "
        f"names {NAME_RULE}, values {VALUE_RULE}.",
        examples=[{"site": "plant-3", "line": "7"}],
    )

    @field_validator("labels")
    @classmethod
    def by_the_rules(cls, labels: dict[str, str]) -> dict[str, str]:
        return check_labels(labels)


class Retirement(BaseModel):
    retired_at: float = Field(description="Service clock, unix s.")
    retired_by: str
    note: str
    reinstated_at: float | None = Field(description="Service clock, unix s; null: still retired.")
    reinstated_by: str | None
    reinstate_note: str | None


class DeviceDetail(Device):
    retirements: list[Retirement] = Field(description="Every retirement of the device, oldest first.")


class CoefficientsInUse(BaseModel):
    in_use: int | None = Field(description="coefficients_version of the newest window (0 = factory).")
    latest_published: int | None = Field(description="Newest coefficient set published to the agent.")
    latest: int | None = Field(description="Newest coefficient set created (published or not).")


class AngleError(BaseModel):
    latest_deg: float | None = Field(description="angle_quality_deg of the newest window.")
    mean_recent_deg: float | None = Field(description="Mean angle_quality_deg of the newest windows.")
    recent_windows: int


class BandFit(BaseModel):
    band: int
    fit_id: int
    created_at: float
    samples: int
    quality: dict


class Alarm(BaseModel):
    id: int
    device: str
    cause: str = Field(
        description="offset_step, gain_step, axis_step, accelerated_aging, magnet_weakening, harmonic_growth, "
        "outliers, adc_clipping or offline (docs/architecture.md, Alarms)."
    )
    parameters: dict = Field(description="The cause's parameters.")
    evidence: str = Field(description="One sentence: what the monitor saw.")
    raised_at: float = Field(description="Drive clock, s: end of the window that made the alarm certain.")
    cleared_at: float | None = Field(description="Drive clock, s; null while the alarm is open.")
    acked_at: float | None = Field(None, description="Service clock, unix s, when an operator acknowledged it.")
    acked_by: str | None = Field(None, description="The REST token that acknowledged it.")
    ack_note: str | None = Field(None, description="What the operator said (seen, and what will be done).")


class OperatorNote(BaseModel):
    """An operator's note on an action (kept with it, shown on one line)."""

    model_config = ConfigDict(extra="forbid")
    note: str = Field(min_length=1, max_length=500, description="Why: kept with the action.")

    @field_validator("note")
    @classmethod
    def one_line(cls, note: str) -> str:
        if CONTROL_CHARACTERS.search(note) or not note.strip():
            raise ValueError("a note is one line of text: no control characters (newline, tab, NUL, ESC), not blank")
        return note


class AlarmList(BaseModel):
    alarms: list[Alarm] = Field(description="Newest first.")
    truncated: bool = Field(description="More alarms match: ask for the next page with `before` = `next`.")
    next: int | None = Field(description="`before` of the next page (the last alarm's id) when truncated, else null.")


class FleetHealth(BaseModel):
    devices: dict[str, int] = Field(description="Devices per state: ok, watch, alarm, offline, unknown, retired.")
    open_alarms: dict[str, int] = Field(description="Open alarms per cause, retired devices' left out.")
    silent: int = Field(
        0, description="Drives online (liveliness token up) with nothing stored for 30 min: no alarm can see them."
    )
    silent_devices: list[str] = Field(default_factory=list, description="The first 100 of them, by id.")


class FleetGroup(BaseModel):
    value: str | None = Field(description="The label's value; null: the devices that do not carry the label.")
    devices: dict[str, int] = Field(description="Devices per state: ok, watch, alarm, offline, unknown, retired.")
    open_alarms: dict[str, int] = Field(description="Open alarms per cause, retired devices' left out.")
    silent: int = Field(description="Drives online with nothing stored for 30 min.")


class FleetHealthBy(BaseModel):
    label: str
    groups: list[FleetGroup] = Field(description="One per value, in order; the devices without the label last.")


class Health(BaseModel):
    device: str
    online: bool
    last_seen: float
    coefficients: CoefficientsInUse
    angle_error: AngleError
    bands: list[BandFit] = Field(description="Quality of the newest fit of each temperature band.")
    windows: int
    samples: int
    rejected: int
    rejected_share: float | None = Field(description="rejected / (samples + rejected) over all windows.")
    state: str = Field(
        "unknown",
        description="Drift monitor: ok | watch (a detector half way to an alarm, or absurd windows lately) | "
        "alarm | offline | unknown (no band judged yet); retired for a drive out of the fleet.",
    )
    alarms: list[Alarm] = Field(default_factory=list, description="The device's open alarms, newest first.")


class BandAngleError(BaseModel):
    band: int
    basis: str = Field(description="'factory' (windows run on version 0) or 'fleet' (on any later set).")
    temp_c: float = Field(description="Mean temperature of those windows.")
    angle_error_deg: float
    windows: int


class AngleErrorByBand(BaseModel):
    device: str
    metric: str = Field(description="Which per-window estimate is averaged.")
    bands: list[BandAngleError]


class CoefficientSet(BaseModel):
    version: int
    created_at: float
    basis: str
    published_at: float | None
    state: str = Field(description="trial (outcome being measured), confirmed, or rolled_back.")
    state_reason: str | None = Field(description="Why the guard put the set in this state.")
    restores_version: int | None = Field(description="For basis 'rollback': the confirmed set it restores.")
    message: dict = Field(description="The encoder-fleet/coefficients/1 message.")
    acks: list[dict] = Field(description="encoder-fleet/ack/1 messages for this version, oldest first.")


class SetEvent(BaseModel):
    version: int
    state: str
    at: float = Field(description="Drive clock of the newest window the decision saw, s.")
    decided_at: float = Field(description="Service clock, unix s.")
    reason: str


class CoefficientHistory(BaseModel):
    device: str
    sets: list[CoefficientSet] = Field(description="Newest first.")
    events: list[SetEvent] = Field(description="The guard's transitions (trial, confirmed, rolled_back), oldest first.")


class WindowList(BaseModel):
    device: str
    count: int
    truncated: bool = Field(description="More windows match: ask for the next page with `after` = `next`.")
    next: int | None = Field(description="`after` of the next page (the last window's seq) when truncated, else null.")
    windows: list[dict] = Field(
        description="encoder-fleet/window/1 messages by window_start, then seq (stats only if asked)."
    )


class DeadLetter(BaseModel):
    id: int
    received_at: float
    key_expr: str
    reason: str
    detail: str
    payload_bytes: int
    payload_sha256: str = Field(description="SHA-256 of the whole payload (empty for letters kept before it was).")
    payload_preview: str = Field(description="First 200 bytes, undecodable bytes replaced.")


class Checks(BaseModel):
    status: str = Field(description="'ok' when every check is ok, else 'failing'.")
    checks: dict[str, str] = Field(description="Component -> 'ok' or what is wrong with it.")


class Rejections(BaseModel):
    counts: dict[str, int] = Field(description="Dead letters by reason.")
    total: int
    latest: list[DeadLetter] = Field(description="Newest first.")
    truncated: bool = Field(description="More dead letters match: ask for the next page with `before` = `next`.")
    next: int | None = Field(
        description="`before` of the next page (the last letter's id) when truncated and limit > 0, else null."
    )


# --- routers ------------------------------------------------------------------------------------

_UNKNOWN_DEVICE = {404: {"model": ErrorMessage, "description": "No device with this id."}}
devices = APIRouter(prefix="/devices", tags=["devices"])
coefficients = APIRouter(prefix="/devices", tags=["coefficients"], responses=_UNKNOWN_DEVICE)
windows = APIRouter(prefix="/devices", tags=["windows"], responses=_UNKNOWN_DEVICE)
export = APIRouter(prefix="/devices", tags=["export"], responses=_UNKNOWN_DEVICE)
ingest = APIRouter(prefix="/ingest", tags=["ingest"])
operations = APIRouter(tags=["operations"])
alarms = APIRouter(tags=["alarms"])
page = APIRouter(tags=["page"])


_NEXT_PAGE = {
    "Link": {
        "description": 'When the list was cut at `limit`: `<URL of the next page>; rel="next"` (RFC 8288).',
        "schema": {"type": "string"},
    }
}


@devices.get(
    "",
    response_model=list[Device],
    responses={200: {"headers": _NEXT_PAGE}},
    summary="All devices, by id (a page of them with `limit`)",
)
def list_devices(
    store: StoreDep,
    request: Request,
    response: Response,
    limit: Annotated[
        int | None, Query(ge=1, le=10000, description="Most devices listed; none: every device, in one list.")
    ] = None,
    after: Annotated[
        str | None,
        Query(max_length=64, description="Only devices of a higher id: the last id of the page before."),
    ] = None,
    labels: LabelsDep = None,
):
    # paged by id in the body's own shape (a list, as the fleet page and older clients read it): the next page is
    # named in a Link header, and a device seen meanwhile lands on whichever page its id falls in, moving no other
    found = store.devices(after=after, limit=None if limit is None else limit + 1, labels=labels)
    if limit is not None and len(found) > limit:
        found = found[:limit]
        url = request.url.include_query_params(limit=limit, after=found[-1]["id"])
        response.headers["Link"] = f'<{url}>; rel="next"'
    # the fleet page's "Devices by state" reads `state`: without it, it showed online/offline only, an alarm never
    states = device_states(store, *_monitor_view(request), ids=[d["id"] for d in found])
    return [{**d, "state": states.get(d["id"], "unknown")} for d in found]


@devices.get("/{device_id}", response_model=DeviceDetail, responses=_UNKNOWN_DEVICE, summary="One device")
def get_device(device: DeviceDep, store: StoreDep, request: Request):
    return _device_detail(store, device, request)


def _device_detail(store: Store, device: dict, request: Request) -> dict:
    """A device as GET /devices/{id} answers it: its row, its state, its retirements."""
    state = device_state(store, device["id"], *_monitor_view(request))
    return {**device, "state": state, "retirements": store.retirements(device["id"])}


def _operator(request: Request) -> str:
    """Who makes a change, as its record keeps it: the request's token ("token 3 (ops desk)"), or none."""
    return getattr(request.state, "token", None) or "no token (REST open)"


def _retirement_change(change: Callable, device_id: str, body: OperatorNote, store: Store, request: Request):
    require_admin(request)
    try:
        device = change(device_id, by=_operator(request), note=body.note)
    except KeyError:
        raise HTTPException(status_code=404, detail=f"unknown device {device_id!r}") from None
    except StoreError as e:
        raise HTTPException(status_code=409, detail=str(e)) from None
    return _device_detail(store, device, request)


@devices.put(
    "/{device_id}/labels",
    response_model=DeviceDetail,
    responses=_UNKNOWN_DEVICE,
    summary="Set a device's labels (admin): site, line, axis…, by which devices are listed and rolled out to",
)
def set_device_labels(device_id: str, body: DeviceLabels, store: StoreDep, request: Request):
    require_admin(request)
    try:
        store.set_labels(device_id, body.labels)
    except KeyError:
        raise HTTPException(status_code=404, detail=f"unknown device {device_id!r}") from None
    return _device_detail(store, store.device(device_id), request)


@devices.post(
    "/{device_id}/retire",
    response_model=DeviceDetail,
    responses={**_UNKNOWN_DEVICE, 409: {"model": ErrorMessage, "description": "Already retired."}},
    summary="Retire a device (admin): out of the fleet's counts, refits and rollouts; its history stays",
)
def retire_device(device_id: str, body: OperatorNote, store: StoreDep, request: Request):
    return _retirement_change(store.retire_device, device_id, body, store, request)


@devices.post(
    "/{device_id}/reinstate",
    response_model=DeviceDetail,
    responses={**_UNKNOWN_DEVICE, 409: {"model": ErrorMessage, "description": "Not retired."}},
    summary="Bring a retired device back into the fleet (admin)",
)
def reinstate_device(device_id: str, body: OperatorNote, store: StoreDep, request: Request):
    return _retirement_change(store.reinstate_device, device_id, body, store, request)


@devices.get("/{device_id}/health", response_model=Health, responses=_UNKNOWN_DEVICE, summary="Health of one device")
def device_health(device: DeviceDep, store: StoreDep, request: Request):
    dev_id = device["id"]
    summary = store.window_summary(dev_id, recent=10)
    recent = summary["recent"]
    published = store.current_coefficients(dev_id, published_only=True)
    latest = store.current_coefficients(dev_id)
    seen = summary["samples"] + summary["rejected"]
    return Health(
        device=dev_id,
        online=device["online"],
        last_seen=device["last_seen"],
        coefficients=CoefficientsInUse(
            in_use=recent[0]["coefficients_version"] if recent else None,
            latest_published=published["version"] if published else None,
            latest=latest["version"] if latest else None,
        ),
        angle_error=AngleError(
            latest_deg=recent[0]["angle_quality_deg"] if recent else None,
            mean_recent_deg=(sum(w["angle_quality_deg"] for w in recent) / len(recent) if recent else None),
            recent_windows=len(recent),
        ),
        bands=[
            BandFit(
                band=f["band"], fit_id=f["id"], created_at=f["created_at"], samples=f["samples"], quality=f["quality"]
            )
            for f in store.latest_fits(dev_id)
        ],
        windows=summary["windows"],
        samples=summary["samples"],
        rejected=summary["rejected"],
        rejected_share=summary["rejected"] / seen if seen else None,
        state=device_state(store, dev_id, *_monitor_view(request)),
        alarms=store.alarms(dev_id, open_=True),
    )


def _monitor_view(request: Request) -> tuple:
    """(the running monitor, which devices it monitors): in a cluster only its own partitions' states are current
    in memory; the other members' devices are read as stored (service/monitor.py, device_state)."""
    service = request.app.state.service
    partitions = getattr(service, "partitions", None)
    return getattr(service, "monitor", None), getattr(partitions, "serves", None)


@alarms.get("/alarms", response_model=AlarmList, summary="Drift alarms (times on the drive's clock)")
def list_alarms(
    store: StoreDep,
    device: Annotated[str | None, Query(description="Only this device's alarms.")] = None,
    cause: Annotated[str | None, Query(description="Only alarms of this cause.")] = None,
    open: Annotated[bool | None, Query(description="true: open alarms only; false: cleared ones only.")] = None,
    before: Annotated[
        int | None, Query(ge=1, le=2**63 - 1, description="Only alarms of a lower id: the `next` of the page before.")
    ] = None,
    limit: Annotated[int, Query(ge=1, le=10000, description="Most alarms listed.")] = 1000,
    acked: Annotated[
        bool | None, Query(description="true: acknowledged alarms only; false: those nobody acknowledged.")
    ] = None,
    in_fleet: Annotated[
        bool | None, Query(description="true: retired devices' alarms left out; false: only theirs.")
    ] = None,
):
    # paged by id, newest first: an alarm raised meanwhile has a higher id and moves no page after the first
    found = store.alarms(device, cause, open, before=before, limit=limit + 1, acked=acked, in_fleet=in_fleet)
    truncated = len(found) > limit
    return AlarmList(alarms=found[:limit], truncated=truncated, next=found[limit - 1]["id"] if truncated else None)


@alarms.post(
    "/alarms/{alarm_id}/ack",
    response_model=Alarm,
    responses={
        404: {"model": ErrorMessage, "description": "No such alarm."},
        409: {"model": ErrorMessage, "description": "Already acknowledged (the first acknowledgement stands)."},
    },
    summary="Acknowledge an alarm (admin): seen, with a note; it stays open until its condition clears",
)
def ack_alarm(
    alarm_id: Annotated[int, FastAPIPath(ge=1, le=2**62)], body: OperatorNote, store: StoreDep, request: Request
):
    require_admin(request)
    try:
        return store.ack_alarm(alarm_id, by=_operator(request), note=body.note)
    except KeyError:
        raise HTTPException(status_code=404, detail=f"no alarm {alarm_id}") from None
    except StoreError as e:
        raise HTTPException(status_code=409, detail=str(e)) from None


@alarms.get("/fleet/health", response_model=FleetHealth, summary="Devices per state and open alarms per cause")
def get_fleet_health(store: StoreDep, request: Request, labels: LabelsDep = None):
    return fleet_health(store, *_monitor_view(request), labels=labels)


@alarms.get(
    "/fleet/health/by/{label}",
    response_model=FleetHealthBy,
    summary="The fleet's health for each value of a label: a site, a line a row",
)
def get_fleet_health_by(
    label: Annotated[str, FastAPIPath(pattern=f"^{NAME_RE.pattern}$", description=f"A label's name: {NAME_RULE}.")],
    store: StoreDep,
    request: Request,
):
    return {"label": label, "groups": fleet_health_by(store, label, *_monitor_view(request))}


@devices.get(
    "/{device_id}/angle-error",
    response_model=AngleErrorByBand,
    responses=_UNKNOWN_DEVICE,
    summary="Angle error against temperature: factory set against fleet sets",
)
def angle_error(device: DeviceDep, store: StoreDep):
    return AngleErrorByBand(
        device=device["id"], metric="angle_quality_deg", bands=store.angle_error_by_band(device["id"])
    )


@coefficients.get(
    "/{device_id}/coefficients", response_model=CoefficientHistory, summary="Coefficient history with acks"
)
def coefficient_history(device: DeviceDep, store: StoreDep):
    acks = store.acks(device["id"])
    return CoefficientHistory(
        device=device["id"],
        sets=[
            CoefficientSet(**h, acks=[a for a in acks if a["version"] == h["version"]])
            for h in store.coefficient_history(device["id"])
        ],
        events=store.set_events(device["id"]),
    )


@windows.get("/{device_id}/windows", response_model=WindowList, summary="Windows in a time range")
def list_windows(
    device: DeviceDep,
    store: StoreDep,
    span: RangeDep,
    stats: Annotated[bool, Query(description="Include the (large) statistics of each window.")] = False,
    limit: Annotated[int, Query(ge=1, le=10000, description="Most windows returned.")] = 1000,
    after: Annotated[
        int | None,
        Query(
            ge=1,
            le=2**53 - 1,
            description="Only windows after this seq's (by window_start, then seq): the `next` of the page before.",
        ),
    ] = None,
):
    # paged by (window_start, seq), the order listed, from the seq of the page's last window (a seq names one window
    # of a device; a window_start alone may be shared)
    cursor = None
    if after is not None:
        start = store.window_start_of(device["id"], after)
        if start is None:
            message = f"device {device['id']!r} has no window of seq {after}"
            # deleted by retention (or lost by the agent) since the page before was read
            if after < store.seq_floor(device["id"]):
                message += " any more (retention deleted the oldest windows): page again from the range's start"
            raise RequestValidationError([{"type": "value_error", "loc": ("query", "after"), "msg": message}])
        cursor = (start, after)
    found = store.windows(device["id"], span.t_from, span.t_to, stats=stats, limit=limit + 1, after=cursor)
    truncated = len(found) > limit
    found = found[:limit]
    return WindowList(
        device=device["id"],
        count=len(found),
        truncated=truncated,
        next=found[-1]["seq"] if truncated else None,
        windows=found,
    )


@export.get(
    "/{device_id}/export.mcap",
    summary="MCAP file of windows, coefficient sets and acks",
    response_class=StreamingResponse,
    responses={200: {"content": {"application/octet-stream": {}}, "description": "MCAP; opens in Foxglove."}},
)
def export_mcap(device: DeviceDep, store: StoreDep, span: RangeDep):
    return StreamingResponse(
        iter_mcap(store, device["id"], span.t_from, span.t_to),
        media_type="application/octet-stream",
        headers={"Content-Disposition": f'attachment; filename="{device["id"]}.mcap"'},
    )


@ingest.get("/rejections", response_model=Rejections, summary="Rejected input: counts and the latest dead letters")
def rejections(
    store: StoreDep,
    limit: Annotated[int, Query(ge=0, le=1000, description="Dead letters listed.")] = 20,
    before: Annotated[
        int | None, Query(ge=1, le=2**63 - 1, description="Only letters of a lower id: the `next` of the page before.")
    ] = None,
):
    # paged by id, newest first, as /alarms: a letter kept meanwhile has a higher id and moves no page after the first
    counts = store.rejection_counts()
    found = store.dead_letters(limit + 1, before=before)
    truncated = len(found) > limit
    latest = [
        DeadLetter(
            payload_bytes=d["payload_bytes"],
            payload_sha256=d["payload_sha256"] or "",
            payload_preview=bytes(d["payload"][:200]).decode("utf-8", errors="replace"),
            **{k: d[k] for k in ("id", "received_at", "key_expr", "reason", "detail")},
        )
        for d in found[:limit]
    ]
    next_page = found[limit - 1]["id"] if truncated and limit > 0 else None
    return Rejections(counts=counts, total=sum(counts.values()), latest=latest, truncated=truncated, next=next_page)


def _checks_response(request: Request, names: tuple[str, ...] | None) -> JSONResponse:
    checks = health_checks(request.app.state.store, request.app.state.service)
    if names is not None:
        checks = {k: v for k, v in checks.items() if k in names}
    ok = all(v == "ok" for v in checks.values())
    body = Checks(status="ok" if ok else "failing", checks=checks)
    return JSONResponse(body.model_dump(), status_code=200 if ok else 503)


_FAILING = {503: {"model": Checks, "description": "A check failed; `checks` says which and why."}}


# GET and HEAD: a load balancer's or an uptime monitor's probe may ask with HEAD (FastAPI answers only the methods
# named: 405 for HEAD on a GET route). HEAD is left out of the OpenAPI document: one route with both methods gives
# both one operation id, and FastAPI warns on stderr when /docs loads it
@operations.get("/healthz", response_model=Checks, responses=_FAILING, summary="Liveness: process, router, database")
@operations.head("/healthz", include_in_schema=False)
def healthz(request: Request):
    return _checks_response(request, LIVENESS)


@operations.get("/readyz", response_model=Checks, responses=_FAILING, summary="Readiness: every part running")
@operations.head("/readyz", include_in_schema=False)
def readyz(request: Request):
    return _checks_response(request, None)


@operations.get(
    "/metrics",
    summary="Prometheus metrics",
    response_class=Response,
    responses={200: {"content": {CONTENT_TYPE_LATEST: {}}, "description": "Prometheus text exposition format."}},
)
def metrics(request: Request):
    return Response(generate_latest(request.app.state.metrics), media_type=CONTENT_TYPE_LATEST)


class Cluster(BaseModel):
    member: str | None = Field(description="This process's name among the service processes; null when it runs alone.")
    members: list[str] = Field(description="The live service processes sharing the fleet (empty when alone).")
    partitions: int = Field(description="Partitions of the fleet (a stable hash of the device id, in its keys).")
    served: list[str] = Field(description="The partitions this process serves: it receives only their devices' keys.")
    leads_rollouts: bool = Field(description="Whether this process steps the staged rollouts.")
    stored_by_partition: dict[str, int] = Field(
        description="Messages this process stored since it started, by partition."
    )


@operations.get(
    "/cluster",
    response_model=Cluster,
    responses={503: {"model": ErrorMessage, "description": "No running service in this process."}},
    summary="Which device partitions this service process serves",
)
def cluster(request: Request):
    service = request.app.state.service
    if service is None:
        raise HTTPException(status_code=503, detail="no running service in this process")
    return service.cluster()


# --- staged rollouts (service/rollout.py): the API's mutations, admin token only ------------------------

rollouts = APIRouter(prefix="/rollouts", tags=["rollouts"])
RolloutId = Annotated[int, FastAPIPath(ge=1, le=2**62)]
_ROLLOUT_ERRORS = {
    404: {"model": ErrorMessage, "description": "No such rollout."},
    409: {"model": ErrorMessage, "description": "The rollout's state does not allow it, or another is running."},
}
_ROLLOUT_CHANGE_ERRORS = {
    **_ROLLOUT_ERRORS,
    503: {"model": ErrorMessage, "description": "No running service in this process to publish the change."},
}


PartState = Literal[("pending", "in_progress", *OUTCOMES)]  # type: ignore[valid-type]


class RolloutDevice(BaseModel):
    device: str
    wave: int
    state: str = Field(description=f"pending, in_progress or an outcome: {', '.join(OUTCOMES)}.")
    before_version: int | None = Field(description="The set the device ran when the change reached it.")
    version: int | None = Field(description="The set the change published to it.")
    started_at: float | None = Field(description="Service clock, unix s.")
    decided_at: float | None = Field(description="Service clock, unix s.")
    reason: str | None


class RolloutWave(BaseModel):
    wave: int
    size: int
    by_state: dict[str, int]


class RolloutSummary(BaseModel):
    id: int
    name: str
    spec: RolloutSpec
    state: str = Field(description="running, paused, aborted or completed.")
    reason: str | None = Field(description="Why it paused, aborted or completed.")
    wave: int = Field(description="The wave in progress (the last one once ended).")
    wave_started_at: float | None
    created_at: float
    updated_at: float
    devices_total: int
    devices_done: int
    percent_done: float
    by_state: dict[str, int]
    waves: list[RolloutWave]


class RolloutDetail(RolloutSummary):
    devices: list[RolloutDevice] = Field(
        description="The parts in (wave, device) order: a page of `limit` (the counts above are the whole rollout's)."
    )
    devices_next: str | None = Field(
        description="Pass as `after` for the next page of parts; null on the last page.", examples=["3:drive-0042"]
    )


def rollout_registry(request: Request) -> Rollouts:
    service = request.app.state.service
    return service.rollouts if service is not None else Rollouts(request.app.state.store)


RolloutsDep = Annotated[Rollouts, Depends(rollout_registry)]


def running_rollouts(request: Request, registry: RolloutsDep) -> Rollouts:
    """Changes need the running service (it publishes the sets) and, with tokens, an admin one."""
    require_admin(request)
    if request.app.state.service is None:
        raise HTTPException(status_code=503, detail="rollouts are changed through the running service")
    return registry


MutableRolloutsDep = Annotated[Rollouts, Depends(running_rollouts)]


def _rollout_call(call, *args):
    try:
        return call(*args)
    except RolloutError as e:
        if e.status == 422:  # the documented 422 (HTTPValidationError: where and what), not a bare string
            raise RequestValidationError([{"type": "value_error", "loc": e.loc, "msg": str(e)}]) from None
        raise HTTPException(status_code=e.status, detail=str(e)) from None


@rollouts.get("", response_model=list[RolloutSummary], summary="Staged rollouts, newest first")
def list_rollouts(registry: RolloutsDep):
    return registry.list()


@rollouts.get("/{rollout_id}", response_model=RolloutDetail, responses=_ROLLOUT_ERRORS, summary="A rollout")
def get_rollout(
    rollout_id: RolloutId,
    registry: RolloutsDep,
    limit: Annotated[int, Query(ge=1, le=10_000, description="Parts in this page.")] = DEVICES_PAGE,
    after: Annotated[
        str | None, Query(max_length=100, description="The `devices_next` of the page before: WAVE:DEVICE.")
    ] = None,
    state: Annotated[PartState | None, Query(description="Only the parts in this state.")] = None,
    wave: Annotated[
        int | None, Query(ge=0, le=2**31, description="Only the parts of this wave (0: the first).")
    ] = None,
):
    return _rollout_call(lambda: registry.get(rollout_id, limit=limit, after=after, state=state, wave=wave))


@rollouts.post(
    "",
    response_model=RolloutDetail,
    status_code=201,
    responses=_ROLLOUT_CHANGE_ERRORS,
    summary="Start a staged rollout (admin): waves, soak, abort criteria",
)
def create_rollout(spec: RolloutSpec, registry: MutableRolloutsDep):
    rollout_id = _rollout_call(registry.create, spec)
    return registry.get(rollout_id, limit=DEVICES_PAGE)


class RolloutPlan(BaseModel):
    devices_total: int = Field(description="The drives the rollout would take now.")
    devices: list[str] = Field(description="The first 20 of them, in the order the waves take them.")
    waves: list[int] = Field(description="Each wave's size.")
    last_wave_after_min: int = Field(description="The least minutes before the last wave starts (one between waves).")
    offline: int = Field(description="Of the drives, those offline now (each waits timeout_s at most, then is passed).")
    refused: str | None = Field(
        description="Why POST /rollouts would refuse it now (409: another rollout is running or paused), or null."
    )


@rollouts.post(
    "/plan",
    response_model=RolloutPlan,
    summary="What a rollout would do now, creating nothing: the drives, the waves (a dry run)",
)
def plan_rollout(spec: RolloutSpec, registry: RolloutsDep):
    return _rollout_call(registry.plan, spec)


@rollouts.post(
    "/{rollout_id}/pause", response_model=RolloutDetail, responses=_ROLLOUT_CHANGE_ERRORS, summary="Pause (admin)"
)
def pause_rollout(rollout_id: RolloutId, registry: MutableRolloutsDep):
    return _rollout_call(registry.pause, rollout_id)


@rollouts.post(
    "/{rollout_id}/resume", response_model=RolloutDetail, responses=_ROLLOUT_CHANGE_ERRORS, summary="Resume (admin)"
)
def resume_rollout(rollout_id: RolloutId, registry: MutableRolloutsDep):
    return _rollout_call(registry.resume, rollout_id)


@rollouts.post(
    "/{rollout_id}/abort",
    response_model=RolloutDetail,
    responses=_ROLLOUT_CHANGE_ERRORS,
    summary="Abort (admin): the current wave is rolled back, later waves never start",
)
def abort_rollout(rollout_id: RolloutId, registry: MutableRolloutsDep):
    return _rollout_call(registry.abort, rollout_id)


STATIC = resources.files("service") / "static"


@page.get("/", response_class=FileResponse, summary="The fleet page (HTML)")
def fleet_page():
    return FileResponse(STATIC / "fleet.html", media_type="text/html")


@page.get("/static/plotly.min.js", include_in_schema=False)
def plotly_js():
    # the charting library ships inside the plotly package: served from here, the page needs no internet
    return FileResponse(resources.files("plotly") / "package_data" / "plotly.min.js", media_type="text/javascript")


MAX_BODY = 1 << 20  # bytes of a request body: a rollout of 10,000 named devices is ~0.3 MB


async def _validation_failed(request: Request, exc: RequestValidationError) -> JSONResponse:
    """422 with where and what was wrong (HTTPValidationError's loc, msg, type), not the input itself: FastAPI's own
    handler sent the input back, which failed as a 500 for one JSON cannot carry (NaN, 1e999, a lone surrogate) and
    sent a 100 MB input back whole."""
    detail = [{"loc": list(e.get("loc", ())), "msg": str(e.get("msg", "")), "type": str(e.get("type", ""))}
              for e in exc.errors()]  # fmt: skip
    return JSONResponse(status_code=422, content={"detail": detail})


class BodyLimit:
    """413 for a request body over MAX_BODY, before it is read whole (by its Content-Length, or as it streams in):
    without it a client with no token made the service read 50 MB before its 401, and one with a token 100 MB."""

    def __init__(self, app, max_bytes: int = MAX_BODY):  # a Starlette middleware: app is the rest of the stack
        self.app, self.max_bytes = app, max_bytes

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        length = dict(scope.get("headers") or []).get(b"content-length", b"0")
        if not length.isdigit() or int(length) > self.max_bytes:
            return await self._refuse(send, length)
        seen = 0

        async def counted():
            nonlocal seen
            message = await receive()
            seen += len(message.get("body", b""))
            if seen > self.max_bytes:
                raise _BodyTooLarge
            return message

        try:
            await self.app(scope, counted, send)
        except _BodyTooLarge:
            await self._refuse(send, str(seen).encode())

    async def _refuse(self, send, length: bytes) -> None:
        body = f'{{"detail":"request body of {length.decode(errors="replace")[:20]} bytes: at most {self.max_bytes}"}}'
        await send({"type": "http.response.start", "status": 413, "headers": [(b"content-type", b"application/json")]})
        await send({"type": "http.response.body", "body": body.encode()})


class _BodyTooLarge(Exception):
    pass


def create_app(store: Store, service: FleetService | None = None, auth: TokenAuth | None = None) -> FastAPI:
    """The REST app around one Store (and, in the service, the running FleetService for its health and
    counters); the caller owns both. Swagger UI and ReDoc assets are served by the app itself
    (fastapi-offline), so /docs works on a plant network with no internet.
    auth: every endpoint but /healthz needs a bearer token (service/auth.py); None leaves REST open."""
    app = FastAPIOffline(
        dependencies=[Depends(authorize)],
        title="encoder-fleet service",
        description="Fleet health, coefficient history, window statistics and MCAP export "
        "for magneto-electric encoders.",
        version="1",
    )
    app.state.store = store
    app.state.service = service
    app.state.auth = auth
    app.state.metrics = metrics_registry(store, service)
    for router in (devices, coefficients, windows, export, ingest, operations, alarms, rollouts, page):
        app.include_router(router)
    app.mount("/static", StaticFiles(directory=str(STATIC)), name="static")
    if auth is not None:
        app.include_router(tokens)
    app.add_exception_handler(RequestValidationError, _validation_failed)
    app.add_middleware(BodyLimit)
    return app
