"""`encoder-fleet`: one command, a subcommand per job. Bad input exits 2 with a one-line reason."""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import sys

import numpy as np

from encoder_core.samples import InputError
from encoder_fleet.argtypes import finite_float, positive_float


def _unlike(value, default) -> str | None:
    """What is wrong with `value` for a model parameter whose default is `default` (None: nothing): the same kind
    (a flag, a number, a list), and every number in it finite."""

    def numbers(x):
        return [n for v in x for n in numbers(v)] if isinstance(x, list) else [x]

    kinds = ((bool, "takes true or false"), ((int, float), "takes a number"), ((list, tuple), "takes a list"))
    for kind, says in kinds:  # the first kind the default is (a flag is an int too)
        if isinstance(default, kind):
            if not isinstance(value, kind) or (kind is not bool and isinstance(value, bool)):
                return says
            break
    if any(isinstance(n, float) and not math.isfinite(n) for n in numbers(value)):
        return "takes finite numbers only"
    return None


def cmd_simulate(args) -> int:
    from encoder_core.simulator import EncoderModel, bench_profile, field_profile, record, typical_drive
    from encoder_fleet.recording import write_recording

    rng = np.random.default_rng(args.seed)
    model = typical_drive(rng) if args.typical else EncoderModel()
    changes = {}
    for item in args.set or []:
        key, _, value = item.partition("=")
        if key not in EncoderModel.__dataclass_fields__:
            raise InputError(
                f"--set {item!r}: unknown model parameter {key!r} "
                f"(known: {', '.join(EncoderModel.__dataclass_fields__)})"
            )
        try:
            parsed = json.loads(value)
        except json.JSONDecodeError:
            raise InputError(f"--set {item!r}: value must be JSON (a number, true/false or a list)") from None
        problem = _unlike(parsed, model.to_dict()[key])
        if problem:
            raise InputError(f"--set {item!r}: {key} {problem}")
        changes[key] = parsed
    model = EncoderModel.from_dict({**model.to_dict(), **changes})
    if args.scenario == "bench":
        profile = bench_profile(tuple(args.plateaus), rng=rng)
    else:
        profile = field_profile(args.days, sample_s=args.sample_s, rng=rng)
    samples = record(
        model, profile, rng, reference=not args.no_reference, temperature=not args.no_temperature, halls=args.halls
    )
    write_recording(samples, args.out, halls=args.halls)
    print(f"wrote {len(samples)} rows to {args.out}")
    return 0


def cmd_bench_methods(args) -> int:
    from encoder_fleet.bench_methods import main as bench_main

    return bench_main(json_path=args.json, png_path=args.png, seed=args.seed)


def package_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("encoder-fleet")
    except PackageNotFoundError:  # run from a checkout that was never installed
        return "unknown (not installed)"


class OneLineParser(argparse.ArgumentParser):
    """A bad argument is one line on stderr and exit 2 (the usage is one --help away)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        # a word beginning with a minus and a digit is a value, never an option (none is named so): argparse's own
        # rule takes only -40 and -.5 so, and refused `--temp-range -40,150` or `--from -1e3` as "expected one argument"
        self._negative_number_matcher = re.compile(r"^-\.?\d")

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(prog="encoder-fleet", description=__doc__)
    parser.add_argument("--version", action="version", version=f"%(prog)s {package_version()}")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("simulate", help="write a simulated recording (CSV contract of docs/architecture.md)")
    p.add_argument(
        "--scenario",
        choices=["bench", "field"],
        default="bench",
        help="bench: seed 000's rig, 3600 positions per plateau with ramps; field: a drive for days",
    )
    p.add_argument("--out", required=True, help="the recording CSV to write")
    p.add_argument("--seed", type=int, default=0, help="random seed of the simulation")
    p.add_argument("--typical", action="store_true", help="start from a randomly drawn production encoder")
    p.add_argument(
        "--set", action="append", metavar="KEY=JSON", help="set a model parameter, e.g. thermal_lag_tau_s=300"
    )
    p.add_argument(
        "--plateaus",
        type=finite_float,
        nargs="+",
        default=[20.0, -40.0, 60.0, 20.0],
        help="bench: temperature plateaus in °C, in order",
    )
    p.add_argument("--days", type=positive_float, default=3.0, help="field: days of operation")
    p.add_argument("--sample-s", type=positive_float, default=10.0, help="field: seconds between samples")
    p.add_argument("--no-reference", action="store_true", help="leave out the theta_ref_deg column")
    p.add_argument("--no-temperature", action="store_true", help="leave out the temp_c column")
    p.add_argument("--halls", action="store_true", help="write the four hall columns instead of d, q")
    p.set_defaults(func=cmd_simulate)

    p = sub.add_parser("bench-methods", help="every compensation method on every scenario, one table")
    p.add_argument("--json", metavar="FILE", help="also write the table as JSON")
    p.add_argument("--png", metavar="FILE", help="also write error-against-angle plots")
    p.add_argument("--seed", type=int, default=0, help="random seed of the simulated bench runs")
    p.set_defaults(func=cmd_bench_methods)

    for register in _extensions():
        register(sub)
    return parser


def _extensions():
    """Subcommands that live beside their code (diagnose, fleet): each module offers register(sub)."""
    import importlib

    found = []
    for name in (
        "encoder_fleet.diagnose_cli",
        "encoder_fleet.fleet_cli",
        "encoder_fleet.pki",
        "encoder_fleet.tokens_cli",
        "encoder_fleet.rollout_cli",
        "encoder_fleet.calibrate",
        "encoder_fleet.bench_soak",
        "encoder_fleet.backup",
        "encoder_fleet.audit",
        "encoder_fleet.alarms_cli",
        "encoder_fleet.status_cli",
        "encoder_fleet.devices_cli",
    ):
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name != name:
                raise
            continue
        found.append(module.register)
    return found


def main(argv=None) -> int:
    from encoder_fleet.logs import configure

    args = build_parser().parse_args(argv)
    configure(getattr(args, "log_level", "warning"))
    try:
        return int(args.func(args) or 0)
    except InputError as exc:
        print(f"encoder-fleet {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError as exc:
        if not _stdout_reader_gone():  # a socket's or another pipe's: an error like any other
            print(f"encoder-fleet {args.command}: error: {exc}", file=sys.stderr)
            return 2
        # `... | head`: the reader has what it wanted; no error, and nothing left to flush at exit
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141  # what a shell reports for a writer stopped by SIGPIPE
    except OSError as exc:  # a path or the machine, not the code: a file that cannot be written, a full disk, ...
        print(f"encoder-fleet {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


def _stdout_reader_gone() -> bool:
    """stdout is a pipe whose reading end is closed (poll says POLLERR for it)."""
    import select

    try:
        poller = select.poll()
        poller.register(sys.stdout.fileno(), select.POLLOUT)
        return any(events & select.POLLERR for _, events in poller.poll(0))
    except (OSError, ValueError, AttributeError):  # no poll here, or stdout is not a file
        return False


if __name__ == "__main__":
    sys.exit(main())
