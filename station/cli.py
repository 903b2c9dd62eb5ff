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
import json
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from station.summary_table import summary_table

EXIT_OK = 0
EXIT_INTERNAL = 1
EXIT_BAD_INPUT = 2
EXIT_CALIBRATION_FAILED = 3
EXIT_FOCUS_AT_EDGE = 4


class UserError(Exception):
    """A problem the user can fix; printed as one line, exit code 2."""


def _progress(label: str) -> Any:
    start = time.monotonic()

    def report(done: int, total: int) -> None:
        if not sys.stderr.isatty() and done not in (1, total) and done % 10:
            return
        elapsed = time.monotonic() - start
        width = 30
        filled = int(width * done / max(total, 1))
        bar = "#" * filled + "-" * (width - filled)
        end = "\n" if done == total or not sys.stderr.isatty() else "\r"
        print(
            f"{label} [{bar}] {done}/{total} {elapsed:6.1f} s", end=end, file=sys.stderr, flush=True
        )

    return report


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
            progress=_progress("simulate"),
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


def _write_json(path: Path, data: dict[str, Any]) -> None:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.tmp")
        tmp.write_text(json.dumps(data, indent=1, allow_nan=False) + "\n", encoding="utf-8")
        tmp.replace(path)
    except OSError as exc:
        raise UserError(f"cannot write {path}: {exc.strerror or exc}") from None


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
    from calibration.archive import ArchiveError
    from calibration.pipeline import CalibrationError, calibrate_archive

    sweep = _archive_location(args.sweep_dir, args.cache_dir)
    if not sweep.exists():
        raise UserError(f"{sweep}: no such sweep directory")
    out = Path(args.out) if args.out else None
    try:
        result = calibrate_archive(sweep, progress=_progress("calibrate"))
    except ArchiveError as exc:
        raise UserError(f"{sweep}: invalid sweep archive: {exc}") from None
    except CalibrationError as exc:
        print(f"lfcal calibrate: {exc}", file=sys.stderr)
        if out is not None and exc.partial is not None:
            _write_json(out, exc.partial)
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
        _write_json(out, data)
        print(f"result written to {out}")
    if args.plots:
        from calibration.report import write_plots

        written = write_plots(data, Path(args.plots))
        print("plots: " + ", ".join(str(p) for p in written))
    return EXIT_OK


# ------------------------------------------------------------------------------ config


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


# -------------------------------------------------------------------------------- demo


def _http(
    method: str,
    url: str,
    *,
    key: str | None = None,
    body: dict[str, Any] | None = None,
    timeout_s: float = 10.0,
) -> tuple[int, dict[str, Any], dict[str, str]]:
    """A small JSON HTTP client on the standard library (the demo talks to 127.0.0.1 only)."""
    import urllib.error
    import urllib.request

    data = None if body is None else json.dumps(body).encode()
    req = urllib.request.Request(url, data=data, method=method)
    req.add_header("Accept", "application/json")
    if data is not None:
        req.add_header("Content-Type", "application/json")
    if key:
        req.add_header("X-API-Key", key)
    try:
        with urllib.request.urlopen(req, timeout=timeout_s) as resp:  # noqa: S310 (loopback)
            return resp.status, json.loads(resp.read() or b"{}"), dict(resp.headers)
    except urllib.error.HTTPError as exc:
        payload = exc.read()
        try:
            parsed = json.loads(payload or b"{}")
        except ValueError:
            parsed = {"detail": payload.decode(errors="replace")}
        return exc.code, parsed, dict(exc.headers)


def _demo_config(config_path: Path, out: Path) -> Path:
    """A copy of the station configuration whose database and archives live under ``out``."""
    import re

    text = config_path.read_text(encoding="utf-8")
    text = re.sub(r"(?m)^data_dir\s*=.*$", f'data_dir = "{(out / "data").resolve()}"', text)
    text = re.sub(
        r"(?m)^database\s*=.*$", f'database = "{(out / "data" / "lfcal.sqlite3").resolve()}"', text
    )
    out.mkdir(parents=True, exist_ok=True)
    copy = out / "station.toml"
    copy.write_text(text, encoding="utf-8")
    # relative paths (a .cti, a white image) keep pointing next to the original
    return copy


def _preset_truth(config_path: Path) -> dict[str, Any] | None:
    """Ground truth of the simulated station's preset (None for real hardware)."""
    from calibration.presets import get_preset
    from station.config import load_config

    cfg = load_config(config_path)
    if cfg.camera.backend != "simulated":
        return None
    o = get_preset(cfg.camera.preset).camera.optics
    u0 = o.u0
    return {
        "a_mm": o.a_f,
        "b_mm": o.b,
        "Q": o.Q_focus,
        "patch_size_px": float(o.patch_px(u0)),
        "focus": {
            "object_distance_mm": u0,
            "rail_mm": (u0 - cfg.rail.zero_object_distance_mm) / cfg.rail.direction,
        },
    }


def cmd_demo(args: argparse.Namespace) -> int:
    """Start the HTTP station on the simulated devices, run a calibration over HTTP, print it."""
    import os
    import queue
    import secrets
    import signal
    import subprocess
    import threading

    from station.config import ConfigError, load_config

    config_path = Path(args.config)
    try:
        load_config(config_path)
    except ConfigError as exc:
        raise UserError(f"{config_path}: " + "; ".join(exc.format_problems())) from None
    out = Path(args.out)
    demo_config = _demo_config(config_path, out)
    key = secrets.token_hex(16)
    env = dict(os.environ, LFCAL_API_KEYS=key)
    log = (out / "server.log").open("w")
    server = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys; from station.cli import main; sys.exit(main())",
            "serve",
            "--config",
            str(demo_config),
            "--host",
            "127.0.0.1",
            "--port",
            str(args.port or 0),
            "--emulator-speedup",
            str(args.emulator_speedup),
        ],
        env=env,
        stdout=subprocess.PIPE,
        stderr=None if args.verbose else log,
        text=True,
    )
    lines: queue.Queue[str] = queue.Queue()

    def pump() -> None:  # the server's stdout: its first line says where it listens
        assert server.stdout is not None
        for line in server.stdout:
            lines.put(line)
            if args.verbose:
                print(line, end="")

    threading.Thread(target=pump, daemon=True).start()
    try:
        base = ""
        deadline = time.monotonic() + 120.0
        while not base:
            try:
                line = lines.get(timeout=0.5)
            except queue.Empty:
                line = ""
            if "listening on" in line:
                base = line.split("listening on", 1)[1].strip().rstrip("/")
            elif server.poll() is not None:
                log.flush()
                detail = (out / "server.log").read_text()[-2000:]
                raise UserError(f"the server exited with code {server.returncode}: {detail}")
            elif time.monotonic() > deadline:
                raise UserError("the server did not start listening within 120 s")
        while True:
            try:
                status, _, _ = _http("GET", f"{base}/api/v1/healthz", timeout_s=2.0)
                if status == 200:
                    break
            except OSError:
                pass
            if time.monotonic() > deadline:
                raise UserError("the server did not answer /api/v1/healthz within 120 s")
            time.sleep(0.25)
        print(f"server up at {base}/ (operator page); starting a calibration over HTTP")
        body: dict[str, Any] = {}
        if args.frames:
            body = {"start_mm": 0.0, "stop_mm": 99.0, "step_mm": 99.0 / (args.frames - 1)}
        status, job, headers = _http("POST", f"{base}/api/v1/jobs", key=key, body=body)
        if status != 202:
            raise UserError(f"POST /api/v1/jobs answered {status}: {job}")
        location = headers.get("Location") or headers.get("location") or f"/api/v1/jobs/{job['id']}"
        url = location if location.startswith("http") else base + location
        report = _progress("sweep")
        shown = -1
        while True:
            status, job, _ = _http("GET", url)
            if status != 200:
                raise UserError(f"GET {url} answered {status}: {job}")
            done = int(job.get("frames_done") or 0)
            if job.get("frames_total") and done != shown:
                report(done, int(job["frames_total"]))
                shown = done
            if job["state"] in ("succeeded", "failed", "cancelled", "interrupted"):
                break
            time.sleep(1.0)
        if job["state"] != "succeeded":
            print(f"the job ended {job['state']}: {job.get('last_error')}", file=sys.stderr)
            return EXIT_CALIBRATION_FAILED
        status, result, _ = _http("GET", f"{url}/result")
        if status != 200:
            raise UserError(f"GET {url}/result answered {status}: {result}")
        print(summary_table(result, _preset_truth(config_path)))
        _write_json(out / "result.json", result)
        print(f"result written to {out / 'result.json'}; archive in {job.get('archive_dir')}")
        if args.keep_serving:
            print(f"operator page: {base}/  (API key for this run: {key}); Ctrl-C stops the server")
            server.wait()
        return EXIT_OK
    finally:
        if server.poll() is None:
            server.send_signal(signal.SIGINT)
            try:
                server.wait(timeout=30)
            except subprocess.TimeoutExpired:
                server.kill()
        log.close()


# -------------------------------------------------------------------------------- main


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="lfcal",
        description="Calibration station for focused plenoptic cameras (ESIF method).",
    )
    sub = parser.add_subparsers(dest="command", required=True)

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

    p = sub.add_parser(
        "demo",
        help="start the HTTP station on the simulated devices, calibrate over HTTP, print it",
    )
    p.add_argument("--config", default="config/simulated.toml", help="station configuration")
    p.add_argument("--out", default="out/demo", help="output directory (default out/demo)")
    p.add_argument(
        "--frames",
        type=int,
        default=None,
        help="frames over the rail's 0..99 mm (default: the configuration's sweep)",
    )
    p.add_argument("--port", type=int, default=None, help="port (default: a free one)")
    p.add_argument(
        "--emulator-speedup",
        type=float,
        default=1.0,
        help="run the emulated stages K times faster than real time",
    )
    p.add_argument(
        "--keep-serving",
        action="store_true",
        help="leave the server (and the operator page) up until Ctrl-C",
    )
    p.add_argument("--verbose", action="store_true", help="show the server's log")
    p.set_defaults(func=cmd_demo)

    from station.lab_cli import add_lab_commands  # render, export, report

    add_lab_commands(sub)
    return parser


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


if __name__ == "__main__":
    sys.exit(main())
