"""Image and file routes: frame previews, plots, rendered images, the archive."""

from __future__ import annotations

import functools
import pathlib
from enum import StrEnum
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Path, Query, Request
from fastapi.responses import Response, StreamingResponse

from calibration.report import disparity_plot, focus_plot
from station.orchestrator import Orchestrator
from station.store import JobState
from station.sweep import HARD_MAX_FRAMES
from web.errors import ApiError, error_responses
from web.media import (
    BytesCache,
    MediaError,
    designed_patch_px,
    focus_frame_index,
    preview_png,
    read_raw,
    rendered_png,
    zip_stream,
)
from web.schemas import JobId
from web.security import check_key
from web.station_api import API, station_errors

PNG = {"content": {"image/png": {}}, "description": "a PNG image"}
NO_STORE = {"Cache-Control": "no-store"}
IMMUTABLE = {"Cache-Control": "private, max-age=3600"}


class PatchChoice(StrEnum):
    """Which patch size renders the image."""

    calibrated = "calibrated"
    designed = "designed"


def _station(request: Request) -> Orchestrator:
    station: Orchestrator = request.app.state.station
    return station


def _cache(request: Request) -> BytesCache:
    cache: BytesCache = request.app.state.media_cache
    return cache


def _result(station: Orchestrator, job_id: int) -> dict[str, Any]:
    with station_errors():
        return station.result(job_id)


def _png(data: bytes, headers: dict[str, str]) -> Response:
    return Response(content=data, media_type="image/png", headers=headers)


def _add_frame_route(router: APIRouter, reads: dict[int | str, dict[str, Any]]) -> None:
    """``GET /jobs/{id}/frames/{index}``: the frame's preview."""

    @router.get(
        "/jobs/{job_id}/frames/{index}",
        response_class=Response,
        responses={200: PNG, **reads},
        summary="A recorded frame, downscaled (PNG preview)",
    )
    def frame_preview(
        request: Request,
        job_id: JobId,
        index: Annotated[
            int, Path(ge=0, le=HARD_MAX_FRAMES, description="frame index", examples=[0])
        ],
        width: Annotated[
            int, Query(ge=16, le=8192, description="largest width of the preview (px)")
        ] = 640,
    ) -> Response:
        """The raw frame ``index`` scaled down to at most ``width`` px, contrast-stretched."""
        with station_errors():
            path = _station(request).frame_path(job_id, index)
        try:
            return _png(preview_png(path, width), IMMUTABLE)
        except MediaError as exc:
            raise ApiError(409, "frame_unreadable", str(exc)) from None


def _add_plot_route(
    router: APIRouter, reads: dict[int | str, dict[str, Any]], name: str, make: Any, summary: str
) -> None:
    """``GET /jobs/{id}/plots/<name>.png``: ``make(result)``, cached per job."""

    def handler(request: Request, job_id: JobId) -> Response:
        station = _station(request)
        result = _result(station, job_id)
        data = _cache(request).get_or_make((job_id, name), lambda: make(result))
        return _png(data, IMMUTABLE)

    handler.__name__ = f"{name}_plot"
    handler.__doc__ = summary
    router.add_api_route(
        f"/jobs/{{job_id}}/plots/{name}.png",
        handler,
        methods=["GET"],
        response_class=Response,
        responses={200: PNG, **reads},
        summary=summary,
    )


def _rendered_frame(
    station: Orchestrator,
    job_id: int,
    result: dict[str, Any],
    p: PatchChoice,
    frame: int | None,
) -> bytes:
    """Frame ``frame`` (default: the one nearest focus) rendered with patch size ``p`` (PNG)."""
    try:
        index = focus_frame_index(result) if frame is None else frame
        patch = (
            float(result["patch_size_px"])
            if p is PatchChoice.calibrated
            else designed_patch_px(station.config)
        )
        with station_errors():
            path = station.frame_path(job_id, index)
        return rendered_png(read_raw(path), result, patch)
    except MediaError as exc:
        raise ApiError(409, "cannot_render", str(exc)) from None


def _add_render_route(router: APIRouter, reads: dict[int | str, dict[str, Any]]) -> None:
    """``GET /jobs/{id}/render.png``."""

    @router.get(
        "/jobs/{job_id}/render.png",
        response_class=Response,
        responses={200: PNG, **reads},
        summary="A frame rendered with the calibrated or the designed patch size (PNG)",
    )
    def render(
        request: Request,
        job_id: JobId,
        p: Annotated[PatchChoice, Query(description="calibrated or designed patch size")] = (
            PatchChoice.calibrated
        ),
        frame: Annotated[
            int | None,
            Query(ge=0, le=HARD_MAX_FRAMES, description="frame index; default: nearest focus"),
        ] = None,
    ) -> Response:
        """Georgiev–Lumsdaine patch rendering (upright), patches on micro-image centres with
        the seam-free patch ``p − (μ − D/δ)`` for ESIF ``p`` (calibrated or designed)."""
        station = _station(request)
        result = _result(station, job_id)
        make = functools.partial(_rendered_frame, station, job_id, result, p, frame)
        return _png(
            _cache(request).get_or_make((job_id, "render", p.value, frame), make), IMMUTABLE
        )


def _finished_archive(station: Orchestrator, job_id: int) -> pathlib.Path:
    """The job's archive directory; 409 while the job runs or when it has none."""
    with station_errors():
        status = station.status(job_id)
    if status.state in (JobState.QUEUED, JobState.RUNNING, JobState.PAUSED):
        raise ApiError(
            409,
            "archive_not_ready",
            f"job {job_id} is {status.state.value}: the archive can be downloaded once the "
            "job has stopped (succeeded, failed, cancelled or interrupted)",
            context={"state": status.state.value},
        )
    directory = station.archive_dir(job_id)
    if not directory.is_dir():
        raise ApiError(
            409, "archive_missing", f"job {job_id} has no archive directory ({directory.name})"
        )
    return directory


def _add_archive_route(router: APIRouter, reads: dict[int | str, dict[str, Any]]) -> None:
    """``GET /jobs/{id}/archive``: the archive as a streamed zip."""

    @router.get(
        "/jobs/{job_id}/archive",
        response_class=StreamingResponse,
        responses={
            200: {"content": {"application/zip": {}}, "description": "the archive as a zip"},
            **reads,
        },
        summary="The job's sweep archive (lfcal-sweep/1) as a zip, streamed",
    )
    def archive(request: Request, job_id: JobId) -> StreamingResponse:
        """``sweep.json``, ``white.png``, ``frames/NNNN.png`` (and ``result.json``); 409 while
        the job is queued, running or paused (the archive is still being written)."""
        directory = _finished_archive(_station(request), job_id)
        name = directory.name
        return StreamingResponse(
            zip_stream(directory, name),
            media_type="application/zip",
            headers={"Content-Disposition": f'attachment; filename="{name}.zip"', **NO_STORE},
        )


def build_media_router(*, read_key: bool) -> APIRouter:
    """The image and file routes (``read_key``: they require the API key)."""
    deps = [Depends(check_key)] if read_key else []
    router = APIRouter(prefix=API, tags=["results"], dependencies=deps)
    reads = error_responses(401, 403, 404, 409, 422)
    _add_frame_route(router, reads)
    _add_plot_route(
        router, reads, "focus", focus_plot, "La(u) with Ls, Lr and the focus plane (PNG)"
    )
    _add_plot_route(
        router, reads, "disparity", disparity_plot, "Q(u) per frame with the global model (PNG)"
    )
    _add_render_route(router, reads)
    _add_archive_route(router, reads)
    return router


__all__ = ["PatchChoice", "build_media_router"]
