"""`encoder-fleet audit`: every coefficient set the service published, fleet-wide, as one CSV an auditor reads.

One row a set (the factory's, fits, moves, rollbacks, rollouts' sets), in the order they went out on the service's
clock, with whether and when the drive applied or rejected it, its guard state, what a rollback restored, the
rollout it was part of and the SHA-256 of the message as stored. The per-device MCAP export has the same sets with
the windows around them; this is the view across the fleet ("what changed on which drives in March"). A reason a
spreadsheet would run as a formula is written with a leading ' (as_text)."""

from __future__ import annotations

import csv
import datetime as dt
import hashlib
import sys
from collections import Counter
from pathlib import Path

from encoder_core.samples import InputError

COLUMNS = (
    "published_utc",
    "device",
    "version",
    "basis",
    "restores_version",
    "state",
    "state_reason",
    "rollout",
    "created_at_drive_s",
    "outcome",
    "applied_utc",
    "rejected_utc",
    "rejected_reason",
    "message_sha256",
)
TEXT_COLUMNS = ("state_reason", "rejected_reason")  # free text: the guard's words and the drive's own
FORMULA_START = ("=", "+", "-", "@", "\t", "\r")  # what a spreadsheet runs as a formula, begun with
PAGE = 5000  # sets read at a time (an audit of a year of a big fleet is millions of rows: never all in memory)


def service_time(text: str) -> float:
    """A time on the service's clock: unix seconds, or an ISO 8601 date or date-time (UTC unless it says)."""
    if len(text) == 8 and text.isascii() and text.isdigit() and _is_date(text):
        # ISO 8601's basic date (`date +%Y%m%d`) read as seconds is a day of 1970: an audit of nothing, said as such
        raise InputError(
            f"{text!r}: the date {text[:4]}-{text[4:6]}-{text[6:]} or unix seconds? Write the date so, or {text}.0"
        )
    try:
        return float(text) if text.replace(".", "", 1).isdigit() else _iso(text)
    except ValueError:
        raise InputError(
            f"{text!r}: not a time (unix seconds, or ISO 8601 such as 2026-03-01 or 2026-03-01T08:00Z)"
        ) from None


def _is_date(text: str) -> bool:
    try:
        dt.date.fromisoformat(text)
    except ValueError:
        return False
    return True


def _iso(text: str) -> float:
    when = dt.datetime.fromisoformat(text.replace("Z", "+00:00"))
    return (when if when.tzinfo else when.replace(tzinfo=dt.UTC)).timestamp()


def _utc(t: float | None) -> str:
    if t is None:
        return ""
    return dt.datetime.fromtimestamp(t, dt.UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


_SETS = (
    "SELECT s.device, s.version, s.basis, s.restores_version, s.state, s.state_reason, s.created_at, "
    "s.published_at, s.body_json, "
    "(SELECT min(a.received_at) FROM acks a WHERE a.device = s.device AND a.version = s.version "
    "AND a.status = 'applied') AS applied_at, "
    "(SELECT min(a.received_at) FROM acks a WHERE a.device = s.device AND a.version = s.version "
    "AND a.status = 'rejected') AS rejected_at, "
    "(SELECT a.reason FROM acks a WHERE a.device = s.device AND a.version = s.version AND a.status = 'rejected' "
    "ORDER BY a.id LIMIT 1) AS rejected_reason, "
    "(SELECT min(r.rollout) FROM rollout_devices r WHERE r.device = s.device AND r.version = s.version) AS rollout "
    "FROM coefficient_sets s WHERE s.published_at IS NOT NULL AND s.published_at >= ? AND s.published_at < ? "
)


def _outcome(r) -> str:
    """What became of the set on the drive: its agent's ack (the first, if it sent both), or the factory's own."""
    if r["basis"] == "factory":
        return "the drive's own"  # announced by its agent, which runs it from the start: no ack
    if r["applied_at"] is not None and (r["rejected_at"] is None or r["applied_at"] <= r["rejected_at"]):
        return "applied"
    return "rejected" if r["rejected_at"] is not None else "no ack"


def audit_rows(store, t_from: float, t_to: float, devices: list[str] | None = None):
    """The published sets in [t_from, t_to) of the service's clock, in publishing order, a page at a time."""
    where, args = "", []
    if devices:
        where = f"AND s.device IN ({', '.join('?' * len(devices))}) "
        args = list(devices)
    after: tuple = (float("-inf"), "", -1)
    while True:
        page = store._rows(
            _SETS + where + "AND (s.published_at > ? OR (s.published_at = ? AND (s.device > ? OR "
            "(s.device = ? AND s.version > ?)))) ORDER BY s.published_at, s.device, s.version LIMIT ?",
            (t_from, t_to, *args, after[0], after[0], after[1], after[1], after[2], PAGE),
        )
        for r in page:
            yield {
                "published_utc": _utc(r["published_at"]),
                "device": r["device"],
                "version": r["version"],
                "basis": r["basis"],
                "restores_version": "" if r["restores_version"] is None else r["restores_version"],
                "state": r["state"],
                "state_reason": r["state_reason"] or "",
                "rollout": "" if r["rollout"] is None else r["rollout"],
                "created_at_drive_s": r["created_at"],
                "outcome": _outcome(r),
                "applied_utc": _utc(r["applied_at"]),
                "rejected_utc": _utc(r["rejected_at"]),
                "rejected_reason": r["rejected_reason"] or "",
                "message_sha256": hashlib.sha256(r["body_json"].encode()).hexdigest(),
            }
        if len(page) < PAGE:
            return
        last = page[-1]
        after = (last["published_at"], last["device"], last["version"])


def as_text(row: dict) -> dict:
    """The row as the CSV holds it: a free-text cell that a spreadsheet would run as a formula (a drive's rejection
    reason is anything it sends: =HYPERLINK(...)) begins with a ', which a spreadsheet shows as text."""
    return {k: "'" + v if k in TEXT_COLUMNS and v.startswith(FORMULA_START) else v for k, v in row.items()}


def cmd_audit(args) -> int:
    from encoder_fleet.fleet_cli import open_evidence
    from encoder_fleet.outputs import is_stdout, replaced

    t_from = float("-inf") if args.t_from is None else service_time(args.t_from)
    t_to = float("inf") if args.t_to is None else service_time(args.t_to)
    if t_from >= t_to:
        raise InputError(f"--from {args.t_from} is not before --to {args.t_to}")
    to_stdout = is_stdout(args.out)
    store = open_evidence(args.db, args.migrate, out=args.out)
    by_basis: dict[str, Counter] = {}
    devices = set()
    try:
        unknown = [d for d in args.device or [] if store.device(d) is None]
        if unknown:
            raise InputError(f"device(s) not in {args.db}: {', '.join(unknown)}")
        with replaced(args.out, "w") as out:  # whole or not at all
            writer = csv.DictWriter(out, COLUMNS, lineterminator="\n")
            writer.writeheader()
            for row in audit_rows(store, t_from, t_to, args.device):
                writer.writerow(as_text(row))
                by_basis.setdefault(row["basis"], Counter())[row["outcome"]] += 1
                devices.add(row["device"])
    finally:
        store.close()
    total = sum(sum(c.values()) for c in by_basis.values())
    summary = sys.stderr if to_stdout else sys.stdout  # the CSV on stdout is the CSV alone
    print(f"wrote {args.out}: {total:,} coefficient sets published to {len(devices):,} drives", file=summary)
    print("| basis | sets | applied | rejected | no ack | the drive's own |\n|---|---|---|---|---|---|", file=summary)
    for basis, c in sorted(by_basis.items()):
        counts = " | ".join(f"{c[k]:,}" for k in ("applied", "rejected", "no ack", "the drive's own"))
        print(f"| {basis} | {sum(c.values()):,} | {counts} |", file=summary)
    return 0


def register(sub) -> None:
    from encoder_fleet.argtypes import device_name
    from encoder_fleet.fleet_cli import add_evidence_options

    p = sub.add_parser("audit", help="every coefficient set published, fleet-wide, as a CSV (applied, rejected, why)")
    add_evidence_options(p, "an audit")
    p.add_argument("--out", required=True, type=Path, help="the CSV file to write")
    p.add_argument("--from", dest="t_from", help="sets published from (service clock: unix s or ISO 8601, UTC)")
    p.add_argument("--to", dest="t_to", help="… until, not included")
    p.add_argument("--device", action="append", type=device_name, help="only this drive (repeatable)")
    p.set_defaults(func=cmd_audit)
