"""What a lab does with a calibration: ``lfcal render``, ``lfcal export``, ``lfcal report``.

- ``lfcal render RAW --result RESULT.json [--white WHITE] [--p calibrated|designed|PX]
  [--object-distance-mm U] [--designed-b-mm B [--designed-a-mm A]] [--tile-px N]
  [--out OUT.png]``: Georgiev–Lumsdaine rendering of any raw frame of the calibrated
  camera (8/16-bit PNG or TIFF), upright, with its artefact score.
- ``lfcal export RESULT --format lfcal|compote|csv|toml [--out FILE]``.
- ``lfcal report JOB_OR_RESULT --out report.html [--config FILE] [--designed-b-mm B]
  [--no-verify]``: the self-contained HTML calibration report of a station job
  (a job id with ``--config``), a result file, or an archive directory.

Bad input (a missing or corrupt file, a frame of another size or another camera,
an unknown format) is one line on stderr and exit code 2 (:class:`station.cli.UserError`).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any


def _user_error(message: str) -> Exception:
    from station.cli import UserError

    return UserError(message)


def load_result_file(path: Path) -> dict[str, Any]:
    """A result JSON (``RESULT`` or ``DIR/result.json``) as a dict; one-line errors."""
    if path.is_dir():
        if not (path / "result.json").is_file():
            raise _user_error(
                f"{path} has no result.json: calibrate it first "
                f"(lfcal calibrate {path} --out {path / 'result.json'})"
            )
        path = path / "result.json"
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise _user_error(f"{path}: no such file") from None
    except OSError as exc:
        raise _user_error(f"{path}: cannot be read ({exc.strerror or exc})") from None
    except ValueError as exc:
        raise _user_error(f"{path}: not a JSON file ({exc})") from None
    if not isinstance(data, dict) or data.get("format") != "lfcal-result/1":
        raise _user_error(f"{path}: not an lfcal-result/1 calibration result")
    return data


def _local(location: str, *, archive: bool = False) -> str:
    """A local path for ``location``: itself, or an ``s3://`` object (a file, or with
    ``archive`` a whole archive prefix) fetched into ``~/.cache/lfcal/archives``,
    checked against its stored SHA-256 (endpoint and keys from the AWS environment)."""
    from station.archive_source import default_cache_dir, is_remote, local_archive, local_file
    from station.db import StoreError

    if not is_remote(location):
        return location
    try:
        if archive:
            return str(local_archive(location, default_cache_dir()))
        return str(local_file(location))
    except (StoreError, ValueError) as exc:
        raise _user_error(str(exc)) from None


def _write(path: Path, data: bytes) -> None:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.tmp")
        tmp.write_bytes(data)
        tmp.replace(path)
    except OSError as exc:
        raise _user_error(f"cannot write {path}: {exc.strerror or exc}") from None


def designed_from(args: argparse.Namespace, result: dict[str, Any]) -> float | None:
    """The designed ESIF patch size from ``--designed-b-mm/--designed-a-mm`` (or the result's
    ``inputs.optics.designed_b_mm``), None when neither gives one."""
    from calibration.export_model import designed_patch_px

    optics = (result.get("inputs") or {}).get("optics") or {}
    camera = (result.get("inputs") or {}).get("camera") or {}
    b = args.designed_b_mm if args.designed_b_mm is not None else optics.get("designed_b_mm")
    a = args.designed_a_mm if args.designed_a_mm is not None else optics.get("designed_a_mm")
    if b is None:
        return None
    try:
        return designed_patch_px(
            b_mm=float(b),
            a_mm=None if a is None else float(a),
            f_mm=float(optics["mla_focal_mm"]),
            D_mm=float(optics["mla_pitch_mm"]),
            delta_mm=float(camera["pixel_pitch_mm"]),
        )
    except (KeyError, TypeError) as exc:
        raise _user_error(f"the result lacks the optics priors ({exc})") from None
    except ValueError as exc:
        raise _user_error(f"impossible designed optics: {exc}") from None


def _patch_choice(text: str) -> str | float:
    if text in ("calibrated", "designed"):
        return text
    try:
        return float(text)
    except ValueError:
        raise _user_error(
            f"--p must be calibrated, designed or a patch size in pixels, got {text!r}"
        ) from None


# ----------------------------------------------------------------------------- render


def cmd_render(args: argparse.Namespace) -> int:
    from calibration.export_model import CalibratedCamera, ResultError
    from calibration.plots import render_png
    from calibration.raw_image import RawImageError, read_raw_file
    from calibration.raw_render import FrameMismatch, choose_patch, render_frame_with

    args.result, args.raw = _local(args.result), _local(args.raw)
    args.white = _local(args.white) if args.white else args.white
    result = load_result_file(Path(args.result))
    try:
        camera = CalibratedCamera.from_result(result)
    except ResultError as exc:
        raise _user_error(f"{args.result}: {exc}") from None
    choice = _patch_choice(args.p)
    if args.object_distance_mm is not None and choice != "calibrated":
        raise _user_error("--object-distance-mm applies to --p calibrated (the calibrated model)")
    try:
        raw = read_raw_file(args.raw)
        white = read_raw_file(args.white) if args.white else None
        designed = designed_from(args, result) if choice == "designed" else None
        if choice == "designed" and designed is None:
            raise _user_error(
                "--p designed needs the designed optics: give --designed-b-mm B "
                "(and --designed-a-mm A; default: the microlens conjugate of b)"
            )
        patch = choose_patch(
            camera, choice, object_distance_mm=args.object_distance_mm, designed_px=designed
        )
        rendered = render_frame_with(raw, camera, patch, white=white, tile_px=args.tile_px)
    except (RawImageError, FrameMismatch) as exc:
        raise _user_error(str(exc)) from None
    except ValueError as exc:
        raise _user_error(str(exc)) from None
    out = Path(args.out) if args.out else Path(f"{Path(args.raw).stem}-rendered.png")
    _write(out, render_png(None, rendered.image))
    where = (
        f"u = {args.object_distance_mm:g} mm"
        if args.object_distance_mm is not None
        else f"the focus plane u0 = {camera.focus_mm:.2f} mm"
    )
    what = {"calibrated": f"calibrated model at {where}", "designed": "designed optics"}.get(
        str(choice), "given"
    )
    h, w = rendered.image.shape
    print(
        f"rendered {args.raw} ({camera.width}x{camera.height} px) with p = "
        f"{rendered.patch_px:.3f} px ({what}); rendering patch {rendered.render_patch_px:.3f} px, "
        f"{rendered.tile_px} px per patch -> {w}x{h} px"
        + (", flat-fielded with the white image" if white is not None else "")
    )
    print(
        f"artefact score {rendered.score:.3f} (seam discontinuity / inside; about 1 is "
        "seam-free, larger is worse)"
    )
    print(f"wrote {out} (render {rendered.render_s:.2f} s, score {rendered.score_s:.2f} s)")
    return 0


# ----------------------------------------------------------------------------- export


def cmd_export(args: argparse.Namespace) -> int:
    from calibration.export import FORMATS, ExportError, export_text

    if args.format not in FORMATS:
        raise _user_error(
            f"unknown export format {args.format!r}: choose one of {', '.join(FORMATS)}"
        )
    result = load_result_file(Path(args.result))
    try:
        text = export_text(result, args.format)
    except ExportError as exc:
        raise _user_error(f"{args.result}: {exc}") from None
    if args.out:
        _write(Path(args.out), text.encode("utf-8"))
        print(f"wrote {args.out} ({args.format})", file=sys.stderr)
    else:
        sys.stdout.write(text)
    return 0


# ----------------------------------------------------------------------------- report


def _job_source(args: argparse.Namespace, job_id: int) -> tuple[dict[str, Any], Path, Any]:
    """Result, archive directory and configuration of station job ``job_id``."""
    from station.archive_source import ArchiveReader
    from station.config import ConfigError, load_config
    from station.db import StoreError
    from station.ownership import open_store
    from station.store import JobNotFound, JobState

    if not args.config:
        raise _user_error(
            f"{job_id} is a job id: give the station configuration (--config FILE) to find its "
            "database, or pass a result file or an archive directory"
        )
    try:
        config = load_config(args.config)
    except ConfigError as exc:
        raise _user_error("; ".join(exc.format_problems())) from None
    except OSError as exc:
        raise _user_error(f"cannot read {args.config}: {exc.strerror or exc}") from None
    db = config.storage.database_path
    if db is not None and not db.is_file():
        raise _user_error(f"no job database at {db} (no job has run yet)")
    try:
        with open_store(config) as store:  # SQLite file or PostgreSQL
            job = store.get_job(job_id, with_result=True)
    except JobNotFound as exc:
        raise _user_error(str(exc)) from None
    except StoreError as exc:
        raise _user_error(str(exc)) from None
    if job.state is not JobState.SUCCEEDED or not job.result or "a_mm" not in job.result:
        raise _user_error(
            f"job {job_id} is {job.state.value} without a calibration result: nothing to report"
        )
    try:  # the local archive, else its copy in object storage
        reader = ArchiveReader(config.storage.cache_dir, config.storage.s3)
        archive = reader.local_dir(job.archive_dir, job.archive_url)
    except StoreError as exc:
        raise _user_error(str(exc)) from None
    return job.result, archive, config


def cmd_report(args: argparse.Namespace) -> int:
    from calibration.export_model import designed_patch_px
    from calibration.report_archive import archive_of, report_from_archive

    target = args.target
    config = None
    archive: Path | None
    if target.isdigit() and not Path(target).exists():
        job_id: int | None = int(target)
        result, archive, config = _job_source(args, int(target))
        source = f"job {target} of {args.config}"
    else:
        job_id = None
        remote_archive = not Path(target.rstrip("/")).suffix  # s3://.../job-...: an archive
        path = Path(_local(target, archive=remote_archive))
        if not path.exists():
            raise _user_error(f"{path}: no such result file, archive directory or job")
        result = load_result_file(path)
        archive = archive_of(result, path)
        source = str(path)
    if "a_mm" not in result:
        raise _user_error(f"{target}: the calibration failed, there is nothing to report")
    designed = designed_from(args, result)
    if designed is None and config is not None and config.optics.designed_b_mm is not None:
        o = config.optics
        designed = designed_patch_px(
            b_mm=o.designed_b_mm,
            a_mm=o.designed_a_mm,
            f_mm=o.mla_focal_mm,
            D_mm=o.mla_pitch_mm,
            delta_mm=o.pixel_pitch_mm,
        )
    t0 = time.perf_counter()
    html = report_from_archive(
        result,
        archive,
        designed_px=designed,
        verify=not args.no_verify,
        source=source,
        job_id=job_id,
    )
    out = Path(args.out)
    _write(out, html.encode("utf-8"))
    print(
        f"wrote {out} ({len(html.encode('utf-8')) / 1024:.0f} kB, {time.perf_counter() - t0:.1f} s)"
        + ("" if archive else "; the sweep archive was not found: no identity, checksum or images")
    )
    return 0


# ----------------------------------------------------------------------------- parser


def _designed_options(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--designed-b-mm", type=float, default=None, help="designed MLA-to-sensor distance b (mm)"
    )
    p.add_argument(
        "--designed-a-mm",
        type=float,
        default=None,
        help="designed a (mm); default: the microlens conjugate f·b/(b − f)",
    )


def add_lab_commands(sub: Any) -> None:
    """Add ``render``, ``export`` and ``report`` to the ``lfcal`` sub-command parser."""
    p = sub.add_parser("render", help="render a raw frame with a calibration (patch rendering)")
    p.add_argument("raw", help="a raw frame of the calibrated camera (8/16-bit PNG or TIFF)")
    p.add_argument("--result", required=True, help="the calibration (lfcal-result/1 JSON)")
    p.add_argument("--white", default=None, help="a white image of the camera (flat field)")
    p.add_argument(
        "--p",
        default="calibrated",
        help="calibrated (default), designed, or the ESIF patch size p = Q·D/δ in px",
    )
    p.add_argument(
        "--object-distance-mm",
        type=float,
        default=None,
        help="object distance of the scene (mm): p(u) from the calibrated model "
        "(default: the focus plane)",
    )
    _designed_options(p)
    p.add_argument("--tile-px", type=int, default=None, help="output pixels per patch")
    p.add_argument("--out", default=None, help="output PNG (default: RAW-rendered.png)")
    p.set_defaults(func=cmd_render)

    p = sub.add_parser("export", help="export a calibration to other tools' formats")
    p.add_argument("result", help="a result JSON (or a directory holding result.json)")
    p.add_argument(
        "--format", default="lfcal", help="lfcal (JSON, schema-checked), compote, csv or toml"
    )
    p.add_argument("--out", default=None, help="output file (default: standard output)")
    p.set_defaults(func=cmd_export)

    p = sub.add_parser("report", help="write the HTML calibration report of a job or result")
    p.add_argument(
        "target",
        help="a job id (with --config), a result JSON or an archive directory (or its s3:// URL)",
    )
    p.add_argument("--out", default="report.html", help="output HTML (default report.html)")
    p.add_argument("--config", default=None, help="station configuration (for a job id)")
    _designed_options(p)
    p.add_argument(
        "--no-verify",
        action="store_true",
        help="do not re-read the archive's files to verify their checksums",
    )
    p.set_defaults(func=cmd_report)


__all__ = ["add_lab_commands", "cmd_export", "cmd_render", "cmd_report", "load_result_file"]
