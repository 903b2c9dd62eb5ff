"""``lfcal emulate-stage``: serve emulated Zaber devices until Ctrl-C.

Examples::

    lfcal emulate-stage --pty                      # prints the /dev/pts/N to open
    lfcal emulate-stage --tcp 9000 --devices 2     # socket://127.0.0.1:9000, devices 1 and 2
    lfcal emulate-stage --pty --axes 2 --speedup 10

The TCP server listens on 127.0.0.1 only.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from collections.abc import Callable, Sequence
from typing import Any, TextIO

from drivers.sim.emulator_links import Transport
from drivers.sim.zaber_emulator import AxisSpec, DeviceSpec, ZaberEmulator


def build_parser() -> argparse.ArgumentParser:
    """Command-line options of ``lfcal emulate-stage``."""
    parser = argparse.ArgumentParser(
        prog="lfcal emulate-stage",
        description="Emulate a chain of Zaber ASCII stages on a pty or a 127.0.0.1 TCP port.",
    )
    where = parser.add_mutually_exclusive_group()
    where.add_argument(
        "--pty", action="store_true", help="serve on a new pseudo-terminal (default)"
    )
    where.add_argument(
        "--tcp", type=int, metavar="PORT", help="serve on 127.0.0.1:PORT (0 = any free port)"
    )
    parser.add_argument("--devices", type=int, default=1, help="devices on the chain (1..N)")
    parser.add_argument("--axes", type=int, default=1, help="axes per device")
    parser.add_argument("--speedup", type=float, default=1.0, help="motion runs this much faster")
    parser.add_argument("--microstep-um", type=float, default=0.1, help="microstep size (um)")
    parser.add_argument("--travel-mm", type=float, default=100.0, help="travel of each axis (mm)")
    parser.add_argument("--speed-mm-s", type=float, default=20.0, help="initial maxspeed (mm/s)")
    parser.add_argument("--accel-mm-s2", type=float, default=200.0, help="initial accel (mm/s^2)")
    parser.add_argument(
        "--firmware",
        type=int,
        choices=(6, 7),
        default=7,
        help="firmware series to behave like: 6 (deviceid, no move speed arguments) or 7",
    )
    return parser


def _check(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    if not 1 <= args.devices <= 99:
        parser.error("--devices must be 1-99")
    if not 1 <= args.axes <= 9:
        parser.error("--axes must be 1-9")
    if args.tcp is not None and not 0 <= args.tcp <= 65535:
        parser.error("--tcp PORT must be 0-65535")
    for name in ("speedup", "microstep_um", "travel_mm", "speed_mm_s", "accel_mm_s2"):
        if not getattr(args, name) > 0:
            parser.error(f"--{name.replace('_', '-')} must be positive")


def main(
    argv: Sequence[str] | None = None,
    *,
    stop: threading.Event | None = None,
    out: TextIO | None = None,
    on_ready: Callable[[str], None] | None = None,
) -> int:
    """Run the emulator until Ctrl-C / SIGTERM (or until ``stop`` is set). Returns 0.

    ``stop``, ``out`` and ``on_ready`` (called with the URL) are for embedding and tests.
    """
    parser = build_parser()
    args = parser.parse_args(list(argv) if argv is not None else None)
    _check(parser, args)
    out = out or sys.stdout
    axis = AxisSpec(
        microstep_um=args.microstep_um,
        travel_mm=args.travel_mm,
        speed_mm_s=args.speed_mm_s,
        accel_mm_s2=args.accel_mm_s2,
    )
    devices = [
        DeviceSpec(address=n, axes=(axis,) * args.axes, serial=100000 + n, firmware=args.firmware)
        for n in range(1, args.devices + 1)
    ]
    transport: Transport = "tcp" if args.tcp is not None else "pty"
    stop = stop or threading.Event()
    restore: list[tuple[signal.Signals, Any]] = []
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            restore.append((sig, signal.signal(sig, lambda *_: stop.set())))
    try:
        emulator = ZaberEmulator(
            devices, transport=transport, tcp_port=args.tcp or 0, speedup=args.speedup
        )
        with emulator:
            print(
                f"Zaber ASCII emulator: {args.devices} device(s) x {args.axes} axis(es), "
                f"firmware {args.firmware}, microstep {args.microstep_um} um, "
                f"travel {args.travel_mm} mm, "
                f"speedup x{args.speedup:g}",
                file=out,
            )
            print(f"serving on {emulator.url}   (Ctrl-C to stop)", file=out, flush=True)
            if on_ready is not None:
                on_ready(emulator.url)
            while not stop.wait(0.5):
                pass
        print("emulator stopped", file=out, flush=True)
    except OSError as exc:
        print(f"lfcal emulate-stage: cannot serve: {exc}", file=sys.stderr)
        return 1
    finally:
        for sig, handler in restore:
            signal.signal(sig, handler)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
