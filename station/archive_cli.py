"""``lfcal simulate`` and ``lfcal calibrate``: write a simulated sweep archive
(lfcal-sweep/1, with its ``truth.json``) and calibrate a sweep archive (ESIF), with
their command-line options (:func:`add_archive_commands`).

Units: mm for optics and rail, px for frames. Bad input raises
:class:`station.cli_common.UserError` (exit code 2); a failed calibration returns its
own exit code (3 or 4), see :mod:`station.cli`.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from station.cli_common import EXIT_OK, UserError, progress_bar, write_json
from station.summary_table import summary_table


def _parse_pair(text: str, what: str) -> tuple[float, float]:
    try:
        x, y = (float(v) for v in text.split(","))
    except ValueError:
        raise UserError(f"{what} must be two numbers 'X,Y', got {text!r}") from None
    return x, y


# ---------------------------------------------------------------------------- simulate


def _override_optics(preset: Any, args: argparse.Namespace) -> Any:
    """The preset with the optics given on the command line (focus plane kept unless given)."""
    from dataclasses import replace

    from calibration.optics import optics_focused_at

    o = preset.camera.optics
    given = {
        "F": args.main_focal_mm,
        "f": args.mla_focal_mm,
        "D": args.mla_pitch_mm,
        "b": args.b_mm,
    }
    if all(v is None for v in given.values()) and args.focus_mm is None:
        return preset
    F = o.F if given["F"] is None else given["F"]
    f = o.f if given["f"] is None else given["f"]
    D = o.D if given["D"] is None else given["D"]
    b = o.b if given["b"] is None else given["b"]
    u0 = o.u0 if args.focus_mm is None else args.focus_mm
    try:
        if not (b > f > 0):
            raise ValueError(f"b = {b} mm must exceed f = {f} mm (a = 1/(1/f - 1/b) would be <= 0)")
        if not D > 0:
            raise ValueError(f"D = {D} mm must be a positive pitch")
        optics = optics_focused_at(u0, F=F, f=f, D=D, b=b, delta=o.delta)
        camera = replace(preset.camera, optics=optics)
    except ValueError as exc:
        raise UserError(f"impossible optics: {exc}") from None
    return replace(preset, camera=camera)


def _datasheet(args: argparse.Namespace) -> Any:
    """The ``--datasheet-*`` options: values the manifest states instead of the true ones."""
    from calibration.sim_sweep import DataSheet

    tolerances: tuple[float | None, ...] = (None, None, None)
    if args.datasheet_tolerances:
        parts = args.datasheet_tolerances.split(",")
        try:
            tolerances = tuple(float(p) for p in parts)
        except ValueError:
            tolerances = ()
        if len(tolerances) != 3 or not all(t is not None and t > 0 for t in tolerances):
            raise UserError(
                "--datasheet-tolerances must be three positive numbers F_MM,f_MM,RAIL_MM, "
                f"got {args.datasheet_tolerances!r}"
            )
    sheet = DataSheet(
        main_focal_mm=args.datasheet_main_focal_mm,
        mla_focal_mm=args.datasheet_mla_focal_mm,
        rail_zero_mm=args.datasheet_rail_zero_mm,
        main_focal_tolerance_mm=tolerances[0],
        mla_focal_tolerance_mm=tolerances[1],
        rail_zero_tolerance_mm=tolerances[2],
    )
    return None if sheet == DataSheet() else sheet


def simulated_preset(args: argparse.Namespace) -> Any:
    """The camera and sweep ``lfcal simulate`` renders for its parsed ``args``: the preset
    with the sweep and optics options applied and the frame fitted (``UserError`` for
    impossible values)."""
    from calibration.presets import get_preset, with_sweep
    from calibration.sim_sweep import fit_frame

    try:
        preset = get_preset(args.preset)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    changes: dict[str, Any] = {}
    if args.frames is not None:
        if args.frames < 1:
            raise UserError(f"--frames must be at least 1, got {args.frames}")
        changes["frames"] = args.frames
    if args.start_mm is not None:
        changes["start_mm"] = args.start_mm
    if args.step_mm is not None:
        if args.step_mm <= 0:
            raise UserError(f"--step-mm must be positive, got {args.step_mm}")
        changes["step_mm"] = args.step_mm
    if changes:
        preset = with_sweep(preset, **changes)
    preset = _override_optics(preset, args)
    pp = _parse_pair(args.principal_point, "--principal-point") if args.principal_point else None
    for name in ("width", "height"):
        value = getattr(args, name)
        if value is not None and value < 1:
            raise UserError(f"--{name} must be a positive number of pixels, got {value}")
    try:
        return fit_frame(preset, args.width, args.height, pp)
    except ValueError as exc:
        raise UserError(f"impossible camera: {exc}") from None


def cmd_simulate(args: argparse.Namespace) -> int:
    """``lfcal simulate OUT``: render the sweep archive and its ``truth.json`` into ``OUT``."""
    from calibration.sim_sweep import write_sweep

    preset = simulated_preset(args)
    out = Path(args.out)
    if out.exists() and any(out.iterdir()) and not args.overwrite:
        raise UserError(f"{out} already exists and is not empty (use --overwrite)")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        path = write_sweep(
            out,
            preset,
            seed=args.seed,
            overwrite=args.overwrite,
            progress=progress_bar("simulate"),
            datasheet=_datasheet(args),
        )
    except PermissionError as exc:
        raise UserError(f"cannot write {out}: permission denied ({exc.filename})") from None
    except OSError as exc:
        raise UserError(f"cannot write {out}: {exc.strerror or exc}") from None
    cam = preset.camera
    print(
        f"wrote {path}: preset {preset.name}, {preset.sweep.frames} frames of "
        f"{cam.sensor.width}x{cam.sensor.height} px, principal point "
        f"({cam.sensor.pp[0]:.1f}, {cam.sensor.pp[1]:.1f}), truth in {path / 'truth.json'}"
    )
    return EXIT_OK


# --------------------------------------------------------------------------- calibrate


def _archive_location(location: str, cache_dir: str | None) -> Path:
    """A local directory for ``location``: the path itself, or an ``s3://`` archive
    downloaded (checked against its SHA-256) into the cache (endpoint and keys from
    the usual AWS environment variables)."""
    from station.archive_source import is_remote, local_archive
    from station.store import StoreError

    if not is_remote(location):
        return Path(location)
    cache = Path(cache_dir) if cache_dir else Path.home() / ".cache" / "lfcal" / "archives"
    try:
        return local_archive(location, cache)
    except (StoreError, ValueError) as exc:
        raise UserError(str(exc)) from None


def cmd_calibrate(args: argparse.Namespace) -> int:
    """``lfcal calibrate SWEEP``: calibrate the archive, print the summary table (against
    ``truth.json`` when the archive has one), write the result and plots when asked."""
    from calibration.archive import ArchiveError
    from calibration.pipeline import CalibrationError, calibrate_archive

    sweep = _archive_location(args.sweep_dir, args.cache_dir)
    if not sweep.exists():
        raise UserError(f"{sweep}: no such sweep directory")
    out = Path(args.out) if args.out else None
    try:
        result = calibrate_archive(sweep, progress=progress_bar("calibrate"))
    except ArchiveError as exc:
        raise UserError(f"{sweep}: invalid sweep archive: {exc}") from None
    except CalibrationError as exc:
        print(f"lfcal calibrate: {exc}", file=sys.stderr)
        if out is not None and exc.partial is not None:
            write_json(out, exc.partial)
            print(f"partial results written to {out}", file=sys.stderr)
        return exc.exit_code
    data = result.to_dict()
    truth_path = sweep / "truth.json"
    truth = None
    if truth_path.is_file():
        try:
            truth = json.loads(truth_path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            truth = None
    print(summary_table(data, truth))
    if out is not None:
        write_json(out, data)
        print(f"result written to {out}")
    if args.plots:
        from calibration.report import write_plots

        written = write_plots(data, Path(args.plots))
        print("plots: " + ", ".join(str(p) for p in written))
    return EXIT_OK


# ------------------------------------------------------------------------------ parser


def _add_simulate_command(sub: Any) -> None:
    """``lfcal simulate``: the preset, sweep, frame, optics and data-sheet options."""
    p = sub.add_parser("simulate", help="render a simulated sweep archive (lfcal-sweep/1)")
    p.add_argument("out", help="output directory (created; must not exist unless --overwrite)")
    p.add_argument("--preset", default="paper", help="paper | rotated | noisy (default paper)")
    p.add_argument("--frames", type=int, default=None, help="number of rail positions")
    p.add_argument("--start-mm", type=float, default=None, help="first rail position (mm)")
    p.add_argument("--step-mm", type=float, default=None, help="rail step (mm)")
    p.add_argument("--width", type=int, default=None, help="frame width (px); default 5120")
    p.add_argument("--height", type=int, default=None, help="frame height (px); default 5120")
    p.add_argument(
        "--principal-point",
        default=None,
        metavar="X,Y",
        help="principal point (px); default keeps both corners in view",
    )
    p.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    p.add_argument("--main-focal-mm", type=float, default=None, help="override F (mm)")
    p.add_argument("--mla-focal-mm", type=float, default=None, help="override f (mm)")
    p.add_argument("--mla-pitch-mm", type=float, default=None, help="override D (mm)")
    p.add_argument("--b-mm", type=float, default=None, help="override b, MLA to sensor (mm)")
    p.add_argument(
        "--focus-mm",
        type=float,
        default=None,
        help="object distance of the focus plane (mm); sets L",
    )
    p.add_argument(
        "--datasheet-main-focal-mm",
        type=float,
        default=None,
        help="F the manifest states (the render uses the true F)",
    )
    p.add_argument(
        "--datasheet-mla-focal-mm", type=float, default=None, help="f the manifest states"
    )
    p.add_argument(
        "--datasheet-rail-zero-mm",
        type=float,
        default=None,
        help="rail zero object distance the manifest states",
    )
    p.add_argument(
        "--datasheet-tolerances",
        default=None,
        metavar="F,f,RAIL",
        help="1-sigma tolerances (mm) the manifest states for F, f and the rail zero",
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing archive")
    p.set_defaults(func=cmd_simulate)


def _add_calibrate_command(sub: Any) -> None:
    """``lfcal calibrate``: the archive (a directory or an ``s3://`` URL) and outputs."""
    p = sub.add_parser("calibrate", help="calibrate a sweep archive (ESIF)")
    p.add_argument(
        "sweep_dir", help="an lfcal-sweep/1 directory, or its s3://bucket/prefix/... URL"
    )
    p.add_argument(
        "--cache-dir",
        default=None,
        help="where an archive from object storage is kept (default ~/.cache/lfcal/archives)",
    )
    p.add_argument("--out", default=None, help="write the result JSON here")
    p.add_argument("--plots", default=None, help="write La(u) and Q(u) PNG plots to this directory")
    p.set_defaults(func=cmd_calibrate)


def add_archive_commands(sub: Any) -> None:
    """Add ``simulate`` and ``calibrate`` to the ``lfcal`` sub-command parser."""
    _add_simulate_command(sub)
    _add_calibrate_command(sub)


__all__ = ["add_archive_commands", "cmd_calibrate", "cmd_simulate", "simulated_preset"]
