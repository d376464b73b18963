"""`encoder-fleet alarms`: the drift monitor's alarms through the service's REST API, as an operator on shift reads
and acknowledges them (GET /alarms, POST /alarms/{id}/ack)."""

from __future__ import annotations

import json
import urllib.parse

from encoder_core.monitor_causes import CAUSES
from encoder_fleet.outputs import write_file
from encoder_fleet.rest_client import add_rest_options, request, text_out

from .argtypes import device_name, positive_int


def alarm_line(a: dict) -> str:
    state = "open" if a["cleared_at"] is None else f"cleared {a['cleared_at'] / 3600:.2f} h"
    acked = f"  [acknowledged by {a['acked_by']}: {a['ack_note']}]" if a.get("acked_by") else ""
    return f"{a['id']:>6} {a['device']:<24} {a['cause']:<18} {a['raised_at'] / 3600:>9.2f} h  {state:<16}{acked}"


def cmd_alarms(args) -> int:
    if args.alarms_command == "ack":
        result = request(args, "POST", f"/alarms/{args.id}/ack", {"note": args.note})
        lines = [alarm_line(result)]
    else:
        query = {"limit": args.limit}
        for name, value in (("device", args.device), ("cause", args.cause)):
            if value:
                query[name] = value
        if args.open:
            query["open"] = "true"
        if args.unacked:
            query["acked"] = "false"
        if args.in_fleet:
            query["in_fleet"] = "true"
        result = request(args, "GET", f"/alarms?{urllib.parse.urlencode(query)}")
        lines = [alarm_line(a) for a in result["alarms"]] or ["no alarms"]
        if result["truncated"]:
            lines.append(f"... more match: --limit, or GET /alarms?before={result['next']}")
    if args.json:
        write_file(args.json, json.dumps(result, indent=2) + "\n")
    print("\n".join(lines), file=text_out(args))
    return 0


def register(sub) -> None:
    p = sub.add_parser("alarms", help="the drift alarms over the service's REST API: list, acknowledge")
    asub = p.add_subparsers(dest="alarms_command", required=True)
    q = asub.add_parser("list", help="alarms, newest first (drive hours)")
    q.add_argument("--device", type=device_name, help="only this drive's")
    # the monitor's causes only: the service filters by any word, and a misspelt one listed "no alarms"
    q.add_argument("--cause", choices=tuple(CAUSES), metavar="CAUSE", help=f"only this cause's: {', '.join(CAUSES)}")
    q.add_argument("--open", action="store_true", help="open alarms only")
    q.add_argument("--unacked", action="store_true", help="only those nobody acknowledged")
    q.add_argument("--in-fleet", action="store_true", help="leave out retired drives' alarms (`devices retire`)")
    q.add_argument("--limit", type=positive_int, default=100, help="most alarms listed (default 100)")
    add_rest_options(q)
    q = asub.add_parser("ack", help="acknowledge an alarm (admin token): seen, and what will be done")
    q.add_argument("id", type=positive_int, help="the alarm's id (alarms list)")
    q.add_argument("--note", required=True, help="what will be done, kept with the alarm")
    add_rest_options(q)
    p.set_defaults(func=cmd_alarms)
