"""The ``lfcal`` console command.

Exit codes (documented in README):

- 0: success;
- 2: bad input (usage, unreadable or invalid archive/config, impossible optics,
  unwritable output), one line on stderr naming the problem;
- 3: calibration failed (too few frames with a board corner); partial results
  are written when ``--out`` is given;
- 4: the focus plane is at the edge of the sweep (extend the range); partial
  results are written when ``--out`` is given;
- 1: an unexpected internal error (a bug: please report it with the traceback).
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from collections.abc import Sequence
from typing import Any

from station.archive_cli import add_archive_commands, cmd_calibrate, cmd_simulate, simulated_preset
from station.cli_common import EXIT_BAD_INPUT, UserError
from station.cli_common import EXIT_CALIBRATION_FAILED as EXIT_CALIBRATION_FAILED
from station.cli_common import EXIT_FOCUS_AT_EDGE as EXIT_FOCUS_AT_EDGE
from station.cli_common import EXIT_INTERNAL as EXIT_INTERNAL
from station.cli_common import EXIT_OK as EXIT_OK
from station.demo_cli import add_demo_command, cmd_demo

# ---------------------------------------------------------------------------- station


def cmd_config_check(args: argparse.Namespace) -> int:
    from station.config import config_check_main

    return config_check_main(args.file)


def cmd_devices(args: argparse.Namespace) -> int:
    from station.devices_cli import devices_main

    return devices_main(args.config, home=args.home, check=args.check)


def cmd_sweep(args: argparse.Namespace, rest: list[str]) -> int:
    from station.jobs_cli import sweep_main

    return sweep_main(rest)


def cmd_jobs(args: argparse.Namespace, rest: list[str]) -> int:
    from station.jobs_cli import jobs_main

    return jobs_main(rest)


def cmd_recalibrate(args: argparse.Namespace, rest: list[str]) -> int:
    from station.recalibrate import recalibrate_main

    return recalibrate_main(rest)


def cmd_serve(args: argparse.Namespace, rest: list[str]) -> int:
    # the web layer sits above the station: loaded by name so station never imports web
    module = importlib.import_module("web.server")
    return int(module.serve_main(rest))


def cmd_emulate_stage(args: argparse.Namespace, rest: list[str]) -> int:
    # the emulator is simulated code: loaded by name so production code never imports it
    module = importlib.import_module("drivers.sim.emulate_stage_cli")
    return int(module.main(rest))


# ------------------------------------------------------------------------------ parser


def _add_station_commands(sub: Any) -> None:
    """Add the station's commands: ``config check``, ``sweep``, ``jobs``, ``recalibrate``,
    ``serve``, ``devices`` and ``emulate-stage`` (the passthrough ones parse their own
    arguments: :func:`main` hands them the rest of the command line)."""
    p = sub.add_parser("config", help="station configuration tools")
    csub = p.add_subparsers(dest="config_command", required=True)
    c = csub.add_parser("check", help="check a station configuration TOML file")
    c.add_argument("file")
    c.set_defaults(func=cmd_config_check)

    sub.add_parser(
        "sweep",
        add_help=False,
        help="run a calibration sweep without the server (lfcal sweep --help)",
    )
    sub.add_parser("jobs", add_help=False, help="list stored jobs (lfcal jobs --help)")
    sub.add_parser(
        "recalibrate",
        add_help=False,
        help="calibrate stored archives again on a Dask cluster (lfcal recalibrate --help)",
    )
    sub.add_parser(
        "serve",
        add_help=False,
        help="start the HTTP service and operator page (lfcal serve --help)",
    )

    p = sub.add_parser("devices", help="connect to every configured device and describe it")
    p.add_argument("--config", default="config/simulated.toml", help="station configuration")
    p.add_argument("--home", action="store_true", help="home the stages first (moves them)")
    p.add_argument(
        "--check",
        action="store_true",
        help="bring-up report: PASS/FAIL per check, a test grab, a short move of each axis "
        "(homes and moves the stages); exit 2 on any FAIL",
    )
    p.set_defaults(func=cmd_devices)

    p = sub.add_parser(
        "emulate-stage",
        add_help=False,
        help="run a Zaber ASCII stage emulator (pty or TCP on 127.0.0.1)",
    )
    p.set_defaults(func=cmd_emulate_stage, passthrough=True)


def build_parser() -> argparse.ArgumentParser:
    """The ``lfcal`` argument parser, its sub-commands in the order ``lfcal --help`` lists them."""
    parser = argparse.ArgumentParser(
        prog="lfcal",
        description="Calibration station for focused plenoptic cameras (ESIF method).",
    )
    sub = parser.add_subparsers(dest="command", required=True)

    add_archive_commands(sub)  # simulate, calibrate
    _add_station_commands(sub)
    add_demo_command(sub)

    from station.lab_cli import add_lab_commands  # render, export, report

    add_lab_commands(sub)
    return parser


# -------------------------------------------------------------------------------- main


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    passthrough = {
        "emulate-stage": cmd_emulate_stage,
        "sweep": cmd_sweep,
        "jobs": cmd_jobs,
        "recalibrate": cmd_recalibrate,
        "serve": cmd_serve,
    }
    if argv and argv[0] in passthrough:
        return passthrough[argv[0]](argparse.Namespace(), argv[1:])
    args = parser.parse_args(argv)
    try:
        return int(args.func(args))
    except UserError as exc:
        print(f"lfcal {args.command}: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # the reader went away (``lfcal calibrate X | head``): stop quietly, as cat does
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 141


# the exit codes (EXIT_*) are importable from here too; they are defined in station.cli_common
__all__ = [
    "UserError",
    "build_parser",
    "cmd_calibrate",
    "cmd_config_check",
    "cmd_demo",
    "cmd_devices",
    "cmd_emulate_stage",
    "cmd_jobs",
    "cmd_recalibrate",
    "cmd_serve",
    "cmd_simulate",
    "cmd_sweep",
    "main",
    "simulated_preset",
]


if __name__ == "__main__":
    sys.exit(main())
