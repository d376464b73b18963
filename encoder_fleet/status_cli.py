"""`encoder-fleet status`: the fleet at a glance in a terminal, from the service's REST API (what the fleet page
shows first): the service's checks, drives by state, open alarms and those nobody acknowledged, running rollouts."""

from __future__ import annotations

import json

from encoder_core.samples import InputError
from encoder_fleet.outputs import write_file
from encoder_fleet.rest_client import add_rest_options, request, text_out

from .argtypes import label_name

UNACKED_LISTED = 10  # open alarms nobody acknowledged, the newest, listed


def fleet_status(args) -> dict:
    ready = request(args, "GET", "/readyz", answers=(503,))
    if not (isinstance(ready, dict) and isinstance(ready.get("checks"), dict) and "status" in ready):
        raise InputError(f"{args.url}/readyz: the answer is not the service's checks (is --url the service?)")
    return {
        "ready": ready,
        "health": request(args, "GET", "/fleet/health"),
        "unacknowledged": request(args, "GET", f"/alarms?open=true&acked=false&in_fleet=true&limit={UNACKED_LISTED}"),
        "rollouts": [r for r in request(args, "GET", "/rollouts") if r["state"] in ("running", "paused")],
        **({"by": request(args, "GET", f"/fleet/health/by/{args.by}")} if args.by else {}),
    }


def group_table(by: dict) -> list[str]:
    """The fleet's health a label value a row (GET /fleet/health/by/{label}): drives per state, open alarms, silent."""
    states = list(by["groups"][0]["devices"]) if by["groups"] else []
    values = ["(no label)" if g["value"] is None else g["value"] for g in by["groups"]]
    width = max([20, len(by["label"])] + [len(v) for v in values])  # a value is up to 64: a longer one moved its row
    head = (
        f"{by['label']:<{width}} {'drives':>7}" + "".join(f" {s:>8}" for s in states) + f" {'alarms':>7} {'silent':>7}"
    )
    lines = [head]
    for value, g in zip(values, by["groups"], strict=True):
        counts = "".join(f" {g['devices'][s]:>8,}" for s in states)
        alarms = sum(g["open_alarms"].values())
        lines.append(f"{value:<{width}} {sum(g['devices'].values()):>7,}{counts} {alarms:>7,} {g['silent']:>7,}")
    return lines


def cmd_status(args) -> int:
    from encoder_fleet.alarms_cli import alarm_line
    from encoder_fleet.rollout_cli import summary_line

    status = fleet_status(args)
    out = text_out(args)
    ready, health = status["ready"], status["health"]
    failing = {k: v for k, v in ready["checks"].items() if v != "ok"}
    print(f"service: {ready['status']}" + "".join(f"\n  {k}: {v}" for k, v in failing.items()), file=out)
    drives = ", ".join(f"{n:,} {state}" for state, n in health["devices"].items() if n)
    print(f"drives: {drives or 'none'}", file=out)
    if health.get("silent"):
        named = ", ".join(health.get("silent_devices", []))
        print(f"silent: {health['silent']:,} online but nothing stored for 30 min: {named}", file=out)
    open_alarms = sum(health["open_alarms"].values())
    by_cause = ", ".join(f"{cause} {n:,}" for cause, n in health["open_alarms"].items())
    print(f"open alarms: {open_alarms:,}" + (f" ({by_cause})" if by_cause else ""), file=out)
    unacked = status["unacknowledged"]
    if unacked["alarms"]:
        more = (
            " (the newest; `encoder-fleet alarms list --open --unacked --in-fleet` lists more)"
            if unacked["truncated"]
            else ""
        )
        print(f"not acknowledged{more}:", file=out)
        for a in unacked["alarms"]:
            print("  " + alarm_line(a), file=out)
    for r in status["rollouts"]:
        print("rollout " + summary_line(r).strip(), file=out)
    if "by" in status:
        print("\n".join(group_table(status["by"])), file=out)
    if args.json:
        write_file(args.json, json.dumps(status, indent=2) + "\n")
    return 0 if ready["status"] == "ok" else 1  # a script's check: 1 while a part of the service fails


def register(sub) -> None:
    p = sub.add_parser("status", help="the fleet at a glance: the service's checks, drives, alarms, rollouts")
    p.add_argument(
        "--by",
        type=label_name,
        metavar="LABEL",
        help="also a table of the fleet a value of this label a row, e.g. site",
    )
    add_rest_options(p)
    p.set_defaults(func=cmd_status)
