"""Fleet subcommands: agent, service, export, demo, bench-fleet, bench-scale, bench-monitor."""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import signal
import sqlite3
import sys
import threading
from pathlib import Path
from typing import TYPE_CHECKING

from encoder_core.samples import InputError
from encoder_fleet.argtypes import (
    device_name,
    finite_float,
    member_name,
    non_negative_float,
    non_negative_int,
    port,
    positive_float,
    positive_int,
)
from encoder_fleet.logs import add_level_option

if TYPE_CHECKING:
    from service.store import Store


def device_seed(device: str) -> int:
    """A simulated device's seed, stable for its name."""
    return int(hashlib.sha256(device.encode()).hexdigest()[:8], 16)


def cmd_agent(args) -> int:
    import zenoh

    from edge_agent.agent import EdgeAgent
    from edge_agent.outbox import Outbox
    from edge_agent.sources import ReplaySource, SimulatedDrive, drive_model, factory_calibration
    from encoder_core.correction import BandedCorrection
    from fleet_wire import messages as wire
    from fleet_wire.session import agent_session_config, error_line, set_on_signals

    seed = args.seed if args.seed is not None else device_seed(args.device)
    if args.source == "sim":
        model = drive_model(seed)
        knock = None if args.knock_at_hour is None else args.knock_at_hour * 3600.0
        source = SimulatedDrive(seed, hours=args.sim_hours, sample_hz=args.sample_hz, knock_at_s=knock)
        factory = factory_calibration(model, seed)
    elif args.source.startswith("replay:"):
        from encoder_fleet.recording import read_recording

        # a reading below absolute zero costs its sample, as any broken sensor's (EdgeAgent.readable_temperatures)
        recording = read_recording(args.source.split(":", 1)[1], broken_temperatures=True)
        if recording.temp_c is None:
            raise InputError(
                f"{args.source}: a replayed recording needs the temp_c column (windows are banded by temperature)"
            )
        first = float(recording.t[0])  # t increases: its first row is the earliest
        if first < 0:  # the wire refuses a window before 0: each was logged and dropped (fieldsim's first, jittered)
            print(
                f"WARNING: {args.source}: t starts at {first:g} s; replayed with every t moved by {-first:g} s "
                "(the drive clock windows carry starts at 0)",
                file=sys.stderr,
                flush=True,
            )
            recording = dataclasses.replace(recording, t=recording.t - first)
        if float(recording.t[-1]) > wire.MAX_TIME_S:
            raise InputError(
                f"{args.source}: t reaches {float(recording.t[-1]):g} s on its last row, past the drive clock's "
                f"{wire.MAX_TIME_S:g} s (milliseconds? the t column is in seconds)"
            )
        source = ReplaySource(recording)
        factory = None
    else:
        raise InputError(f"--source {args.source!r}: use 'sim' or 'replay:REC.csv'")
    if args.factory:
        try:  # checked as the wire checks a set (schema, types, finite numbers), with its reason
            msg = wire.decode("coefficients", Path(args.factory).read_bytes(), key_device=None)
        except OSError as exc:
            raise InputError(f"--factory {args.factory}: cannot read: {exc.strerror}") from None
        except wire.WireError as exc:
            raise InputError(f"--factory {args.factory}: not a coefficient set: {exc}") from None
        factory = BandedCorrection.from_dict(msg)
    if factory is None:
        raise InputError("a replayed recording needs --factory FILE (a coefficient set as JSON)")
    identity, verifier = agent_security(args)
    outbox_path = args.outbox or Path("out") / "outbox" / f"{args.device}.sqlite"
    try:  # the session first: a --connect that cannot be used leaves no outbox behind
        session = zenoh.open(agent_session_config(args.connect, identity=identity))
    except zenoh.ZError as exc:
        raise InputError(f"cannot connect to {', '.join(args.connect)}: {error_line(exc)}") from None
    try:
        outbox = Outbox(outbox_path)
    except (sqlite3.Error, OSError) as exc:  # a directory there, another kind of file, no room
        session.close()
        raise InputError(f"--outbox {outbox_path}: cannot be used as the agent's outbox: {exc}") from None
    agent = EdgeAgent(
        args.device,
        source,
        session,
        outbox,
        factory,
        window_s=args.window_s,
        verifier=verifier,
        # the wire's range unless the drive's rating is given (the parser of the command line loads no wire module)
        **({} if args.temp_range is None else {"temp_range_c": args.temp_range}),
    )
    stop = threading.Event()
    set_on_signals(stop, signal.SIGTERM)
    try:
        agent.start()
        c = agent.run(real_time_factor=args.real_time_factor, stop=stop)
        print(
            f"{args.device}: {c.windows} windows, {c.resent} resent, {c.offline_syncs} times without the service, "
            f"versions applied {c.applied}, refused {[v for v, _ in c.refused]}, {len(outbox)} left in outbox"
            + (f", watermark replies refused {c.refused_watermarks}" if c.refused_watermarks else ""),
            flush=True,
        )
    finally:
        agent.close()
        session.close()
        outbox.close()
    return 0


def insecure_or_pki(args, what: str, *, warn: bool = True) -> None:
    """Secure unless asked: --pki DIR, or --insecure said out loud (the service says it in its start-up
    lines on stdout instead, so its stderr stays one JSON event per line)."""
    import sys

    if args.pki and args.insecure:
        raise InputError("--pki and --insecure exclude each other")
    if not args.pki and not args.insecure:
        raise InputError(
            f"{what} needs --pki DIR (TLS with client certificates, access control, signed coefficient sets; "
            "`encoder-fleet pki init DIR` makes one) or --insecure for local tinkering"
        )
    if args.insecure and warn:
        print(
            f"WARNING: {what} runs --insecure: plain TCP, no certificates, no access control, no signature "
            "checks; anyone who reaches the endpoint can speak for any device. Local tinkering only.",
            file=sys.stderr,
            flush=True,
        )


def agent_security(args):
    """(identity, verifier) of an agent: its certificate (CN = --device) and the service's public key."""
    from fleet_wire.security import ROLE_DEVICE, Identity, SecurityError, SetVerifier

    insecure_or_pki(args, f"agent {args.device}")
    if args.insecure:
        return None, None
    plain = [e for e in args.connect if not e.startswith("tls/")]
    if plain:
        raise SecurityError(f"with --pki every endpoint must be tls/HOST:PORT, not {', '.join(plain)}")
    return Identity.load(args.pki, args.device, ROLE_DEVICE), SetVerifier.load(args.pki)


def temperature_range(text: str) -> tuple[float, float]:
    """`--temp-range LO,HI`, checked as the agent checks it (edge_agent.agent.temperature_range)."""
    from edge_agent.agent import temperature_range as rated

    lo, _, hi = text.partition(",")
    try:
        low, high = finite_float(lo), finite_float(hi)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected LO,HI, two numbers in °C (e.g. -40,150)") from None
    try:
        return rated(low, high)
    except InputError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def cmd_service(args) -> int:
    from service.runtime import run_service

    insecure_or_pki(args, "the service", warn=False)
    horizon = {} if args.band_horizon_h is None else {"band_horizon_h": args.band_horizon_h}
    return run_service(
        pki=args.pki,
        admin_token_file=args.admin_token_file,
        rest_auth=not args.insecure or bool(args.admin_token_file),
        db=args.db,
        listen=args.listen,
        connect=args.connect,
        mesh=args.mesh,
        member=args.member,
        http_host=args.http_host,
        http_port=args.http_port,
        refit_interval_s=args.refit_interval,
        db_max_mb=args.db_max_mb,
        keep_days=args.keep_days,
        **horizon,
    )


def _database_files(db: Path) -> set[Path]:
    """A SQLite database's files: the database, its write-ahead log and its shared memory."""
    db = db.resolve()
    return {db, db.with_name(db.name + "-wal"), db.with_name(db.name + "-shm")}


def open_evidence(db: str, migrate: bool, *, out) -> Store:
    """The service's database opened to read evidence from (export, audit): refused, one line, when it does not exist,
    is empty, is the file `out` would write, or lacks migrations and `migrate` was not given (reading evidence
    changes no file unasked)."""
    from service.db import is_postgres, sqlite_path
    from service.store import Store, unapplied_migrations

    db_file = None if is_postgres(db) else Path(sqlite_path(db))
    if db_file is not None and not db_file.exists():
        raise InputError(f"--db {db}: no such database")
    if db_file is not None and db_file.stat().st_size == 0:  # reading evidence makes no database
        raise InputError(f"--db {db}: an empty file, not the service's database")
    if db_file is not None and Path(out).resolve() in _database_files(db_file):
        raise InputError(f"--out {out} is the database itself (or its WAL): name another file")
    behind = [] if db_file is None else unapplied_migrations(db_file)
    if behind and not migrate:  # the service's own start migrates it
        raise InputError(
            f"--db {db} was written by an older encoder-fleet (it lacks migration(s) {', '.join(behind)}): "
            "reading it here would change the file. Start the service on it once, or pass --migrate to migrate it here"
        )
    return Store.open(db)


def add_evidence_options(p, what: str) -> None:
    """--db and --migrate of a command that reads evidence from the service's database (open_evidence)."""
    p.add_argument("--db", default="out/fleet.sqlite", help="the service's history: a SQLite path or postgresql:// URL")
    p.add_argument(
        "--migrate",
        action="store_true",
        help="migrate a database an older encoder-fleet wrote, in place, first (without it such a database is "
        f"refused: {what} changes no file it reads)",
    )


def cmd_export(args) -> int:
    from encoder_fleet.outputs import is_stdout, replaced
    from service.mcap_export import export_mcap

    if args.t_from is not None and args.t_to is not None and args.t_from > args.t_to:
        raise InputError(f"--from {args.t_from} is after --to {args.t_to}")
    to_stdout = is_stdout(args.out)
    store = open_evidence(args.db, args.migrate, out=args.out)
    try:
        if store.device(args.device) is None:
            raise InputError(f"device {args.device!r} is not in {args.db}")
        with replaced(args.out, "wb") as out:  # whole or not at all: a failed export leaves no half file
            export_mcap(store, args.device, out, t_from=args.t_from, t_to=args.t_to)
    finally:
        store.close()
    print(f"wrote {args.out}", file=sys.stderr if to_stdout else sys.stdout)  # the MCAP file on stdout alone
    return 0


def cmd_demo(args) -> int:
    from encoder_fleet.demo import run_demo

    json_path = None if args.json is None else Path(args.json)
    return run_demo(
        devices=args.devices,
        sim_hours=args.sim_hours,
        out_dir=Path(args.out),
        json_path=json_path,
        insecure=args.insecure,
    )


def size_list(text: str) -> list[int]:
    """'10,100,1000' -> [10, 100, 1000]; each a positive integer."""
    try:
        return [positive_int(part) for part in text.split(",")]
    except Exception:
        raise argparse.ArgumentTypeError(f"{text!r} is not a comma-separated list of positive integers") from None


def cmd_bench_fleet(args) -> int:
    from encoder_fleet.bench_fleet import run_bench

    return run_bench(
        sizes=args.sizes or args.devices,
        windows_per_device=args.windows,
        security=args.security,
        json_path=args.json,
        postgres=args.postgres,
    )


def cmd_bench_scale(args) -> int:
    from encoder_fleet.bench_scale import run_bench as run_scale_bench
    from encoder_fleet.pgserver import NoPostgres

    try:
        return run_scale_bench(args.sizes, args.processes, args.postgres, json_path=args.json, stores=args.stores)
    except NoPostgres as exc:
        raise InputError(f"bench-scale needs PostgreSQL: {exc}; give --postgres URL") from None


def cmd_bench_monitor(args) -> int:
    from encoder_fleet.bench_monitor import run_bench as run_monitor_bench

    return run_monitor_bench(
        drives=args.drives,
        days=args.days,
        seed=args.seed,
        window_s=args.window_s,
        sample_hz=args.sample_hz,
        json_path=args.json,
    )


def register(sub) -> None:
    p = sub.add_parser("agent", help="run an edge agent next to a drive")
    p.add_argument("--device", required=True, type=device_name, help="the drive's id (its Zenoh key segment)")
    p.add_argument("--connect", action="append", required=True, metavar="ENDPOINT", help="e.g. tcp/127.0.0.1:7447")
    p.add_argument("--source", default="sim", help="sim, or replay:REC.csv")
    p.add_argument("--seed", type=int, help="simulated drive's seed (default: from the device name)")
    p.add_argument("--sim-hours", type=positive_float, default=24.0, help="sim: hours of drive time to run")
    p.add_argument("--sample-hz", type=positive_float, default=20.0, help="sim: samples per second")
    p.add_argument("--window-s", type=positive_float, default=60.0, help="seconds of drive time per window")
    p.add_argument(
        "--temp-range",
        type=temperature_range,
        metavar="LO,HI",
        help="°C the drive's thermistor can read (its rating, e.g. -40,150): a reading outside is a broken sensor's, "
        "rejected, and the angle corrected at the last good temperature (default: the wire's whole range, from "
        "absolute zero to 300 °C)",
    )
    p.add_argument(
        "--real-time-factor",
        type=non_negative_float,
        default=0.0,
        help="pace the drive clock (simulated or replayed) at this many times real time (0: as fast as possible)",
    )
    p.add_argument("--outbox", help="the durable outbox file (default out/outbox/DEVICE.sqlite)")
    p.add_argument(
        "--knock-at-hour",
        type=non_negative_float,
        help="simulated drive only: knock its magnet at this drive hour (offsets jump by 1.5 %% of the amplitude)",
    )
    p.add_argument("--factory", help="the factory coefficient set, JSON (required for replay)")
    add_security_options(p, "DEVICE.crt/.key, ca.crt and signing.pub")
    add_level_option(p)
    p.set_defaults(func=cmd_agent)

    p = sub.add_parser("service", help="run the central service (embeds a Zenoh router by default)")
    p.add_argument(
        "--db",
        default="out/fleet.sqlite",
        help="the history: a SQLite file (path or sqlite:///path, created if missing) or postgresql://user@host:port/db",
    )
    p.add_argument(
        "--listen",
        action="append",
        metavar="ENDPOINT",
        help="router endpoint (default tls/127.0.0.1:7447, tcp/ with --insecure)",
    )
    p.add_argument("--connect", action="append", metavar="ENDPOINT", help="join external routers instead")
    p.add_argument(
        "--mesh",
        action="append",
        metavar="ENDPOINT",
        help="the embedded router also connects to this router (another service's or a zenohd): routers meshed",
    )
    p.add_argument(
        "--member",
        type=member_name,
        help="share the fleet with other service processes on the same PostgreSQL database: this process's "
        "unique name; it serves the device partitions that fall to it among the live members",
    )
    p.add_argument("--http-host", default="127.0.0.1", help="REST address (0.0.0.0 in a container)")
    p.add_argument("--http-port", type=port, default=8000, help="REST port (0: no REST)")
    p.add_argument(
        "--refit-interval",
        type=positive_float,
        default=2.0,
        help="the longest wait between refit passes, in seconds (a pass also runs as soon as windows are stored)",
    )
    p.add_argument(
        "--band-horizon-h",
        type=non_negative_float,
        help="drive hours of windows each temperature band's sum remembers, so refits follow aging "
        "(0: all history; default: the service's, 12 h)",
    )
    p.add_argument(
        "--db-max-mb",
        type=positive_float,
        help="a quota on the database: past it, writes fail as on a full disk (/healthz says so, agents buffer)",
    )
    p.add_argument(
        "--keep-days",
        type=positive_float,
        help="retention: delete windows that ended more than this many days of a drive's own time before its newest "
        "(those the refit, the monitor, a trial or the watermark still need stay) and dead letters this old; "
        "coefficient sets, acks, fits and alarms are kept for good (default: keep every window)",
    )
    add_security_options(p, "service.crt/.key, ca.crt, signing.key and the device certificates (the registry)")
    p.add_argument(
        "--admin-token-file",
        help="where the first admin REST token is written (0600) at first start (default: beside --db); "
        "with --insecure, REST tokens are required only when this is given",
    )
    add_level_option(p)
    p.set_defaults(func=cmd_service)

    p = sub.add_parser("export", help="write a device's windows, coefficient sets and acks to MCAP")
    add_evidence_options(p, "an export")
    p.add_argument("--device", required=True, type=device_name, help="the device to export")
    p.add_argument("--out", required=True, help="the MCAP file to write")
    p.add_argument("--from", dest="t_from", type=finite_float, help="start, s on the drive's clock")
    p.add_argument("--to", dest="t_to", type=finite_float, help="end, s on the drive's clock")
    p.set_defaults(func=cmd_export)

    p = sub.add_parser("demo", help="a simulated fleet, the service and the rollout, with a summary")
    p.add_argument("--devices", type=positive_int, default=4, help="simulated drives, one agent process each")
    p.add_argument("--sim-hours", type=positive_float, default=24.0, help="hours of drive time")
    p.add_argument("--out", default="out/demo", help="folder for the database, plots and MCAP exports")
    p.add_argument("--json", metavar="FILE", help="also write the summary as JSON")
    p.add_argument("--insecure", action="store_true", help="no PKI: plain TCP, no ACL, unsigned sets, open REST")
    add_level_option(p)
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("bench-fleet", help="windows ingested and refits per second for fleets of several sizes")
    p.add_argument("--sizes", type=size_list, help="fleet sizes to run, comma-separated (default 10,100,1000)")
    p.add_argument("--devices", type=positive_int, nargs="+", default=[10, 100, 1000], help="fleet sizes, spaced")
    p.add_argument("--windows", type=positive_int, default=20, help="windows per device")
    p.add_argument("--json", metavar="FILE", help='also write {"rows": [...]} to FILE')
    p.add_argument(
        "--security",
        choices=["both", "off", "on"],
        default="both",
        help="plain TCP, TLS + ACL + signed sets, or both side by side (the cost of the security model)",
    )
    p.add_argument(
        "--postgres",
        metavar="URL",
        help="also run each size on PostgreSQL: an admin URL (postgresql://user@host:port/db) that may create "
        "and drop a database per run",
    )
    p.set_defaults(func=cmd_bench_fleet)

    p = sub.add_parser(
        "bench-scale",
        help="drives at one window a drive-minute against 1, 2, 4 service processes on PostgreSQL and one on SQLite",
    )
    p.add_argument("--sizes", type=size_list, default=[1000, 10000, 100000], help="fleet sizes, comma-separated")
    p.add_argument(
        "--processes", type=size_list, default=[1, 2, 4], help="service processes on PostgreSQL, comma-separated"
    )
    p.add_argument(
        "--postgres",
        metavar="URL",
        help="an admin URL that may create and drop a database per row (default: a throwaway server started "
        "from this machine's PostgreSQL binaries)",
    )
    p.add_argument(
        "--stores",
        type=lambda text: [w for w in text.split(",") if w],
        default=["sqlite", "postgresql"],
        help="sqlite,postgresql (default both; SQLite runs one process)",
    )
    p.add_argument("--json", metavar="FILE", help='also write {"rows": [...]} to FILE (after every row)')
    p.set_defaults(func=cmd_bench_scale)

    p = sub.add_parser(
        "bench-monitor",
        help="the drift monitor on seeded hidden events: recall, cause precision, false alarms, delays, cost",
    )
    p.add_argument("--drives", type=positive_int, default=36, help="drives (a quarter clean, the others one event)")
    p.add_argument("--days", type=positive_float, default=3.0, help="simulated days per drive")
    p.add_argument("--seed", type=non_negative_int, default=1, help="seed of the hidden-event set")
    p.add_argument("--window-s", type=positive_float, default=300.0, help="window length, s of drive time")
    p.add_argument("--sample-hz", type=positive_float, default=2.0, help="samples per second in each window")
    p.add_argument("--json", metavar="FILE", help="also write the figures, every planted event and every alarm")
    p.set_defaults(func=cmd_bench_monitor)
    register_fleet_accuracy(sub)


def add_security_options(p, holds: str) -> None:
    p.add_argument("--pki", metavar="DIR", help=f"the PKI folder ({holds}): TLS, mTLS, signed coefficient sets")
    p.add_argument(
        "--insecure",
        action="store_true",
        help="plain TCP, no certificates, no access control, no signature checks (local tinkering only)",
    )


def cmd_bench_fleet_accuracy(args) -> int:
    import json

    from encoder_fleet.fleet_accuracy import format_report, run_bench

    if args.explain or args.plot:
        return explain_one(args)
    rates = [float(r) for r in args.rates.split(",")]
    seeds = [int(s) for s in args.seeds.split(",")]
    windows = {}
    if args.window_s:
        windows = {rate: args.window_s for rate in rates}
    report = run_bench(
        drives=args.drives,
        days=args.days,
        seeds=seeds,
        rates=rates,
        windows=windows,
        events=not args.no_events,
        processes=args.processes,
        through_service=args.through_service,
    )
    print(format_report(report))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(report, f, indent=1)
        print(f"wrote {args.json}")
    return 0


def explain_one(args) -> int:
    """`bench-fleet-accuracy --explain DRIVE [--plot PNG]`: one drive, every decision, every hour."""
    from encoder_fleet.fleet_accuracy import explain_drive, format_explanation, plot_explanation, spec_named

    if not args.explain:
        raise InputError("--plot draws the drive --explain names")
    if args.through_service:
        raise InputError("--explain runs the in-process loop, not --through-service")
    spec = spec_named(
        args.explain, drives=args.drives, days=args.days, window_s=args.window_s, events=not args.no_events
    )
    explanation = explain_drive(spec)
    print(format_explanation(explanation))
    if args.plot:
        plot_explanation(explanation, args.plot)
        print(f"wrote {args.plot}")
    return 0


def register_fleet_accuracy(sub) -> None:
    """`bench-fleet-accuracy`: registered here so the harness (and the service it imports) loads only when run."""
    p = sub.add_parser(
        "bench-fleet-accuracy", help="fleet against factory on independently simulated drives (true angle error)"
    )
    p.add_argument("--json", metavar="FILE", help="also write the report as JSON")
    p.add_argument("--drives", type=positive_int, default=12, help="drives per fleet")
    p.add_argument("--days", type=positive_float, default=3.0, help="simulated days per drive")
    p.add_argument("--seeds", default="1,2,3", help="fleet seeds, comma-separated")
    p.add_argument("--rates", default="0.5,20", help="sample rates in Hz, comma-separated")
    p.add_argument("--window-s", type=positive_float, help="window length (default: 300 s below 2 Hz, else 60 s)")
    p.add_argument("--no-events", action="store_true", help="clean drives only (aging and noise, no planted step)")
    p.add_argument("--processes", type=positive_int, default=2, help="worker processes (one fleet regime each)")
    p.add_argument(
        "--through-service",
        nargs="?",
        type=positive_float,
        const=3600.0,
        metavar="FACTOR",
        help="replay each fleet through `encoder-fleet service` and one `agent --source replay:` process per drive at "
        "FACTOR times real time (default 3600), instead of the in-process loop; recordings take ~50 MB per drive-day "
        "at 20 Hz",
    )
    p.add_argument(
        "--explain",
        metavar="DRIVE",
        help="run one drive of the table (e.g. s8-20hz-10-dwell, in the fleet --drives, --days and --window-s "
        "describe) and print every decision the fleet took beside its error hour by hour",
    )
    p.add_argument("--plot", metavar="PNG", help="with --explain: also draw the drive's hours into this file")
    p.set_defaults(func=cmd_bench_fleet_accuracy)
