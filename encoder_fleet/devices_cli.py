"""`encoder-fleet devices`: one drive as the service knows it, and taking a drive out of the fleet or back in
(GET /devices/{id}, POST /devices/{id}/retire, POST /devices/{id}/reinstate), through the service's REST API."""

from __future__ import annotations

import json
import time

from encoder_fleet.outputs import write_file
from encoder_fleet.rest_client import add_rest_options, request, text_out

from .argtypes import device_name


def _when(t: float) -> str:
    return time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime(t))


def device_lines(d: dict) -> list[str]:
    version = "–" if d["current_version"] is None else f"v{d['current_version']}"
    lines = [
        f"{d['id']}: {d['state']}, {'online' if d['online'] else 'offline'}, runs {version}, {d['windows']} windows, "
        f"last heard {_when(d['last_seen'])}"
    ]
    for r in d.get("retirements", []):
        lines.append(f"  retired {_when(r['retired_at'])} by {r['retired_by']}: {r['note']}")
        if r["reinstated_at"] is not None:
            lines.append(f"  reinstated {_when(r['reinstated_at'])} by {r['reinstated_by']}: {r['reinstate_note']}")
    return lines


def cmd_devices(args) -> int:
    path = f"/devices/{args.device}"
    if args.devices_command == "show":
        result = request(args, "GET", path)
    else:
        result = request(args, "POST", f"{path}/{args.devices_command}", {"note": args.note})
    if args.json:
        write_file(args.json, json.dumps(result, indent=2) + "\n")
    print("\n".join(device_lines(result)), file=text_out(args))
    return 0


def register(sub) -> None:
    p = sub.add_parser("devices", help="one drive over the service's REST API: show, retire, reinstate")
    dsub = p.add_subparsers(dest="devices_command", required=True)
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
