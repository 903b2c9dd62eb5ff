"""Opening the ``lfcal-sweep/1`` archive of a sweep run (its prepare phase).

:func:`open_job_archive` resumes the archive in the job's directory after
:func:`station.recovery.reconcile` verified what is on disk (the camera must still
deliver the archive's frame size and bit depth), or creates it with a manifest
header that records the station's view of the job: the sweep request, the camera
settings in force, the principal point in the delivered frames' coordinates
(:func:`principal_point_px`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from calibration.archive import ArchiveError, SweepWriter
from drivers.camera import CameraSettings, Roi
from station.config import StationConfig
from station.recovery import VerifyReport, reconcile
from station.run_control import JobFailed, RunContext
from station.store import JobRecord
from station.sweep import SweepPlan


def principal_point_px(
    config: StationConfig, roi: Roi | None, camera_pp: tuple[float, float] | None = None
) -> tuple[float, float]:
    """Principal point (px) in the coordinates of the delivered frames.

    From ``camera.principal_point_px`` if configured, else the camera's own
    (``camera_pp``: :attr:`drivers.camera.CameraInfo.principal_point_px`, known to a
    simulated camera), else the sensor centre; minus the ROI offset.
    """
    cam = config.camera
    pp = cam.principal_point_px if cam.principal_point_px is not None else camera_pp
    if pp is None:
        w, h = cam.sensor_size_px
        pp = ((w - 1) / 2.0, (h - 1) / 2.0)
    ox, oy = (roi.offset_x, roi.offset_y) if roi is not None else (0, 0)
    return (float(pp[0]) - ox, float(pp[1]) - oy)


def camera_settings(config: StationConfig, exposure_us: float) -> CameraSettings:
    """The camera settings of a sweep: the configured format, gain and ROI, this exposure."""
    cam = config.camera
    roi = None
    if cam.roi is not None:
        roi = Roi(cam.roi.width, cam.roi.height, cam.roi.offset_x, cam.roi.offset_y)
    return CameraSettings(
        pixel_format=cam.pixel_format, exposure_us=exposure_us, gain=cam.gain, roi=roi
    )


def open_job_archive(
    job: JobRecord,
    plan: SweepPlan,
    devices: Any,
    ctx: RunContext,
    settings: CameraSettings,
    roi: Roi,
    depth: int,
) -> tuple[SweepWriter, VerifyReport]:
    """The job's archive writer and what was verified of the archive on disk.

    Args:
        job: the running job; its ``archive_dir`` holds the archive.
        plan: the job's sweep.
        devices: ``station.devices.StationDevices`` (the camera is asked for its
            principal point once per ROI; ``bench`` marks a simulated station).
        ctx: orchestrator services (store, config, principal point cache).
        settings: the camera settings in force (recorded in a new manifest).
        roi: the delivered frames' region of the sensor (px).
        depth: the delivered frames' bit depth.

    Raises:
        JobFailed: the archive cannot be resumed (or no longer fits the camera's
            frames) or cannot be created.
    """
    job_dir = Path(job.archive_dir)
    if (job_dir / "sweep.json").is_file():
        return _resume(job, ctx, roi, depth)
    cfg = ctx.config
    pp = _cached_principal_point(ctx, devices, roi)
    header = cfg.manifest_header(
        width=roi.width, height=roi.height, bit_depth=depth, principal_point_px=pp
    )
    header["station"] = {
        "job_id": job.id,
        "created_at": job.created_at,
        "sweep": plan.to_dict(),
        "camera": {
            "pixel_format": settings.pixel_format,
            "exposure_us": settings.exposure_us,
            "gain": settings.gain,
            "roi": [roi.width, roi.height, roi.offset_x, roi.offset_y],
            "black_level": settings.black_level,
            "trigger": settings.trigger,
            "flat_field": settings.flat_field,
        },
    }
    if devices.bench is not None:
        header["simulated"] = {"preset": cfg.camera.preset}
    try:
        writer = SweepWriter.in_place(job_dir, header)
    except (ArchiveError, OSError) as exc:
        raise JobFailed(f"cannot create the job's archive {job_dir}: {exc}") from exc
    return writer, VerifyReport(archive_exists=True)


def _resume(
    job: JobRecord, ctx: RunContext, roi: Roi, depth: int
) -> tuple[SweepWriter, VerifyReport]:
    job_dir = Path(job.archive_dir)
    try:
        try:
            report = reconcile(ctx.store, job.id, job_dir)
        finally:
            ctx.row_changed(job.id)
        writer = SweepWriter.resume(job_dir)
    except (ArchiveError, OSError) as exc:
        raise JobFailed(f"the job's archive {job_dir} cannot be resumed: {exc}") from exc
    cam = writer.manifest.camera
    if (cam.width, cam.height, cam.bit_depth) != (roi.width, roi.height, depth):
        raise JobFailed(
            f"the camera delivers {roi.width}x{roi.height} px at {depth} bits, but the "
            f"job's archive holds {cam.width}x{cam.height} px at {cam.bit_depth} bits: "
            "restore the camera settings of the job (ROI, pixel format) to resume it"
        )
    return writer, report


def _cached_principal_point(ctx: RunContext, devices: Any, roi: Roi) -> tuple[float, float]:
    """:func:`principal_point_px` for this ROI, asked of the camera once per ROI."""
    key = f"{roi.width}x{roi.height}+{roi.offset_x}+{roi.offset_y}"
    pp = ctx.principal_point_cache.get(key)
    if pp is None:
        pp = principal_point_px(ctx.config, roi, devices.camera.info().principal_point_px)
        ctx.principal_point_cache[key] = pp
    return pp


__all__ = ["camera_settings", "open_job_archive", "principal_point_px"]
