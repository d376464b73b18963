"""`encoder-fleet devices`: the drives as the service knows them, their labels, and taking a drive out of the fleet
or back in (GET /devices, GET /devices/{id}, PUT /devices/{id}/labels, POST /devices/{id}/retire and /reinstate),
through the service's REST API."""

from __future__ import annotations

import json
import time
import urllib.parse

from encoder_core.samples import InputError
from encoder_fleet.outputs import write_file
from encoder_fleet.rest_client import add_rest_options, request, text_out

from .argtypes import device_name, label_dict, label_pair, positive_int

STATES = ("ok", "watch", "alarm", "offline", "unknown", "retired")  # service/monitor.py's
PAGE = 1000  # devices a GET /devices asks for at a time


def _when(t: float) -> str:
    return time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime(t))


def _labels(d: dict) -> str:
    return " ".join(f"{k}={v}" for k, v in sorted(d.get("labels", {}).items()))


def device_line(d: dict) -> str:
    version = "–" if d["current_version"] is None else f"v{d['current_version']}"
    return f"{d['id']:<24} {d['state']:<8} {'online' if d['online'] else 'offline':<7} {version:>5} {_labels(d)}"


def device_lines(d: dict) -> list[str]:
    version = "–" if d["current_version"] is None else f"v{d['current_version']}"
    labels = f", labels {_labels(d)}" if d.get("labels") else ""
    lines = [
        f"{d['id']}: {d['state']}, {'online' if d['online'] else 'offline'}, runs {version}, {d['windows']} windows, "
        f"last heard {_when(d['last_seen'])}{labels}"
    ]
    for r in d.get("retirements", []):
        lines.append(f"  retired {_when(r['retired_at'])} by {r['retired_by']}: {r['note']}")
        if r["reinstated_at"] is not None:
            lines.append(f"  reinstated {_when(r['reinstated_at'])} by {r['reinstated_by']}: {r['reinstate_note']}")
    return lines


def every_device(args) -> list[dict]:
    """GET /devices page after page (those carrying --label), those in --state of them."""
    query = [("limit", PAGE)] + [("label", pair) for pair in args.label or []]
    found, after = [], None
    while True:
        page = request(args, "GET", "/devices?" + urllib.parse.urlencode(query + ([("after", after)] if after else [])))
        found += [d for d in page if args.state is None or d["state"] == args.state]
        if len(page) < PAGE or (args.limit is not None and len(found) >= args.limit):
            return found[: args.limit]
        after = page[-1]["id"]


def cmd_devices(args) -> int:
    action = args.devices_command
    if action == "list":
        result = every_device(args)
        lines = [device_line(d) for d in result] or ["no devices"]
    else:
        path = f"/devices/{args.device}"
        if action == "show":
            result = request(args, "GET", path)
        elif action == "label":
            if bool(args.labels) == args.clear:  # an empty list replaces them all: said, not typed by mistake
                raise InputError("give the drive's labels as NAME=VALUE, or --clear to remove every label it has")
            labels = label_dict(args.labels, "labels")
            result = request(args, "PUT", f"{path}/labels", {"labels": labels})
        else:
            result = request(args, "POST", f"{path}/{action}", {"note": args.note})
        lines = device_lines(result)
    if args.json:
        write_file(args.json, json.dumps(result, indent=2) + "\n")
    print("\n".join(lines), file=text_out(args))
    return 0


def register(sub) -> None:
    p = sub.add_parser("devices", help="drives over the service's REST API: list, show, label, retire, reinstate")
    dsub = p.add_subparsers(dest="devices_command", required=True)
    q = dsub.add_parser("list", help="drives by id: state, liveliness, the set each runs, labels")
    q.add_argument(
        "--label", type=label_pair, action="append", metavar="NAME=VALUE", help="only drives carrying it (repeatable)"
    )
    q.add_argument("--state", choices=STATES, help="only drives in this state")
    q.add_argument("--limit", type=positive_int, help="most drives listed (default: every one)")
    add_rest_options(q)
    q = dsub.add_parser("label", help="set a drive's labels (admin token), replacing those it had: site=plant-3 …")
    q.add_argument("device", type=device_name, help="the drive's id")
    q.add_argument("labels", type=label_pair, nargs="*", metavar="NAME=VALUE", help="its labels, every one")
    q.add_argument("--clear", action="store_true", help="remove every label the drive has (instead of NAME=VALUE)")
    add_rest_options(q)
    q = dsub.add_parser("show", help="a drive's state, the set it runs, and its retirements")
    q.add_argument("device", type=device_name, help="the drive's id")
    add_rest_options(q)
    q = dsub.add_parser(
        "retire",
        help="take a drive out of the fleet (admin token): replaced or scrapped; out of the counts, alarms, refits "
        "and rollouts, its history kept",
    )
    q.add_argument("device", type=device_name, help="the drive's id")
    q.add_argument("--note", required=True, help="why, kept with the retirement")
    add_rest_options(q)
    q = dsub.add_parser("reinstate", help="bring a retired drive back into the fleet (admin token)")
    q.add_argument("device", type=device_name, help="the drive's id")
    q.add_argument("--note", required=True, help="why, kept with the retirement")
    add_rest_options(q)
    p.set_defaults(func=cmd_devices)
