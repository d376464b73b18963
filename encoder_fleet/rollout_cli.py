"""`encoder-fleet rollout`: staged rollouts through the service's REST API (service/rollout.py), as an operator
runs them: create, list, show, pause, resume, abort. A thin client of the same endpoints curl would call."""

from __future__ import annotations

import argparse
import json
import urllib.parse

from encoder_fleet.outputs import write_file
from encoder_fleet.rest_client import add_rest_options, request, text_out

from .argtypes import label_dict, label_pair, positive_float, positive_int


def parse_abort(text: str) -> dict:
    """FAILURE:PERCENT:MIN_EXECUTED[:ACTION], e.g. regressed:10:5 or timed_out:20:10:pause."""
    parts = text.split(":")
    if len(parts) not in (3, 4):  # ArgumentTypeError: argparse says this, not "invalid parse_abort value"
        raise argparse.ArgumentTypeError(f"{text!r}: expected FAILURE:PERCENT:MIN_EXECUTED[:abort|pause]")
    try:
        criterion = {"failure_type": parts[0], "threshold_percentage": float(parts[1]), "min_executed": int(parts[2])}
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{text!r}: PERCENT is a number and MIN_EXECUTED a whole number (FAILURE:PERCENT:MIN_EXECUTED)"
        ) from None
    if len(parts) == 4:
        criterion["action"] = parts[3]
    return criterion


def summary_line(r: dict) -> str:
    outcomes = ", ".join(f"{state} {n}" for state, n in r["by_state"].items())
    wave = f"wave {r['wave'] + 1}/{len(r['waves'])}"
    return f"{r['id']:>4} {r['state']:<9} {wave:<10} {r['percent_done']:>5.1f} %  {r['name']}  [{outcomes}]"


def show(r: dict, out=None) -> None:
    print(summary_line(r), file=out)
    if r.get("reason"):
        print(f"     {r['reason']}", file=out)
    for part in r.get("devices", []):
        version = "–" if part["version"] is None else f"v{part['before_version']} -> v{part['version']}"
        where = f"wave {part['wave'] + 1:<3} {part['device']:<24}"
        print(f"     {where} {part['state']:<12} {version:<12} {part['reason'] or ''}", file=out)
    if r.get("devices_next"):
        print(
            f"     ... the first {len(r['devices'])} of {r['devices_total']} parts: `rollout show {r['id']}` lists all",
            file=out,
        )


def _count(n: int, what: str) -> str:
    return f"{n:,} {what}" + ("" if n == 1 else "s")


def plan_lines(plan: dict) -> str:
    """POST /rollouts/plan, as `rollout create --dry-run` prints it."""
    waves = plan["waves"]
    sizes = ", ".join(str(n) for n in waves[:8]) + (f", … ({len(waves)} waves)" if len(waves) > 8 else "")
    named = ", ".join(plan["devices"]) + (" …" if plan["devices_total"] > len(plan["devices"]) else "")
    drives, n_waves = _count(plan["devices_total"], "drive"), _count(len(waves), "wave")
    return (
        f"would roll out to {drives} ({plan['offline']:,} offline now) in {n_waves} of {sizes}; "
        f"the last starts {plan['last_wave_after_min']:,} min after the first at the earliest\n"
        f"     {named}\n"
        + (f"refused now: {plan['refused']}\n" if plan.get("refused") else "")
        + "nothing created (--dry-run)"
    )


def every_part(args) -> dict:
    """GET /rollouts/{id}, page after page (the service lists at most 10,000 parts at once): every part asked for."""
    query = {"limit": 10_000}
    if args.state:
        query["state"] = args.state
    if args.wave is not None:
        query["wave"] = args.wave - 1  # the service counts waves from 0, this command (as it prints them) from 1
    result = request(args, "GET", f"/rollouts/{args.id}?{urllib.parse.urlencode(query)}")
    while result.get("devices_next"):
        page = request(
            args, "GET", f"/rollouts/{args.id}?{urllib.parse.urlencode({**query, 'after': result['devices_next']})}"
        )
        result["devices"] += page["devices"]
        result["devices_next"] = page["devices_next"]
    return result


def cmd_rollout(args) -> int:
    action = args.rollout_command
    if action == "create":
        spec = {
            "name": args.name,
            "change": {"kind": args.change},
            "base_per_minute": args.base_per_minute,
            "increment_factor": args.increment_factor,
            "soak_windows": args.soak_windows,
            "timeout_s": args.timeout_s,
            "abort_criteria": args.abort or [],
        }
        if args.devices:
            spec["devices"] = args.devices.split(",")
        if args.label:
            spec["labels"] = label_dict(args.label, "--label")
        result = request(args, "POST", "/rollouts/plan" if args.dry_run else "/rollouts", spec)
    elif action == "list":
        result = request(args, "GET", "/rollouts")
    elif action == "show":
        result = every_part(args)
    else:  # pause | resume | abort
        result = request(args, "POST", f"/rollouts/{args.id}/{action}")
    if args.json:
        write_file(args.json, json.dumps(result, indent=2) + "\n")
    out = text_out(args)
    if action == "create" and args.dry_run:
        print(plan_lines(result), file=out)
    elif action != "list":
        show(result, out)
    for r in result if action == "list" else []:
        print(summary_line(r), file=out)
    if action == "list" and not result:
        print("no rollouts", file=out)
    return 1 if action == "create" and args.dry_run and result.get("refused") else 0  # a script's check


def register(sub) -> None:
    p = sub.add_parser("rollout", help="staged rollouts over the service's REST API (create, list, pause, ...)")
    rsub = p.add_subparsers(dest="rollout_command", required=True)

    q = rsub.add_parser("create", help="start a rollout: waves, soak and abort criteria")
    q.add_argument("--name", required=True, help="what the change is, for the audit trail")
    q.add_argument("--change", choices=["reset_to_factory", "refit"], required=True, help="what every drive gets")
    q.add_argument("--devices", help="comma-separated device ids (default: every device in the fleet)")
    q.add_argument(
        "--label",
        type=label_pair,
        action="append",
        metavar="NAME=VALUE",
        help="instead of --devices: the drives carrying this label (repeatable: all of them)",
    )
    q.add_argument("--base-per-minute", type=positive_int, required=True, help="devices in the first wave")
    q.add_argument("--increment-factor", type=positive_float, default=1.0, help="each wave this many times the last")
    q.add_argument("--soak-windows", type=positive_int, required=True, help="windows each drive runs before judging")
    q.add_argument("--timeout-s", type=positive_float, default=3600.0, help="seconds a drive has to soak")
    q.add_argument(
        "--abort",
        type=parse_abort,
        action="append",
        metavar="FAILURE:PERCENT:MIN[:ACTION]",
        help="abort criterion, repeatable: failure rejected|timed_out|regressed, e.g. regressed:10:5",
    )
    q.add_argument(
        "--dry-run",
        action="store_true",
        help="say which drives and waves it would take; create nothing (exit 1: create would be refused now)",
    )
    add_rest_options(q)
    q = rsub.add_parser("list", help="every rollout, newest first")
    add_rest_options(q)
    for name, text in (
        ("show", "one rollout, with every device's part"),
        ("pause", "start nobody new (soaks are still judged)"),
        ("resume", "go on; abort criteria count again from now"),
        ("abort", "stop and roll the current wave back"),
    ):
        q = rsub.add_parser(name, help=text)
        q.add_argument("id", type=positive_int, help="the rollout's id (rollout list)")
        if name == "show":
            q.add_argument("--state", help="only the parts in this state (pending, in_progress, succeeded, ...)")
            q.add_argument("--wave", type=positive_int, help="only the parts of this wave (1: the first)")
        add_rest_options(q)
    p.set_defaults(func=cmd_rollout)
