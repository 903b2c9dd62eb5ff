"""Routes for what a lab does with a calibration, and the operator page's live frame view.

- ``POST /api/v1/render``: render an uploaded raw frame with a calibration (a job's,
  or a result sent along) and return the PNG; headers carry the patch size and
  the artefact score.
- ``GET /api/v1/jobs/{id}/report.html``: the job's self-contained calibration report.
- ``GET /api/v1/jobs/{id}/frames/{index}/corners``: the corners the streaming
  analysis measured in a frame (for the overlay on the live preview).

The upload is JSON (the API guard accepts JSON bodies only, up to ``[server]
max_body_bytes``): the PNG or TIFF file base64-encoded in ``image_base64``.
"""

from __future__ import annotations

import base64
import binascii
import functools
import pathlib
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Path, Request
from fastapi.responses import JSONResponse, Response
from pydantic import BaseModel, Field
from starlette.concurrency import run_in_threadpool

from calibration.export_model import CalibratedCamera, ResultError
from calibration.plots import render_png
from calibration.raw_image import RawImageError, decode_raw
from calibration.raw_render import FrameMismatch, choose_patch, render_frame_with
from calibration.report_archive import report_from_archive
from station.orchestrator import Orchestrator
from station.sweep import HARD_MAX_FRAMES
from web.errors import ApiError, error_responses
from web.media import BytesCache, designed_patch_px
from web.schemas import MAX_ID, JobId
from web.security import check_key
from web.station_api import API, station_errors

PNG = {"content": {"image/png": {}}, "description": "the rendered image (PNG, upright)"}
HTML = {"content": {"text/html": {}}, "description": "the report (self-contained HTML)"}


class RenderRequest(BaseModel):
    """A raw frame to render, and the calibration to render it with."""

    image_base64: str = Field(
        min_length=1,
        description="the raw frame: an 8- or 16-bit grey PNG or TIFF file, base64-encoded",
    )
    job_id: int | None = Field(
        default=None, ge=1, le=MAX_ID, description="use this job's calibration result"
    )
    result: dict[str, Any] | None = Field(
        default=None, description="or: an lfcal-result/1 calibration sent along"
    )
    p: str | float = Field(
        default="calibrated",
        description="calibrated (default), designed (the station's designed optics), or the "
        "ESIF patch size p = Q·D/δ in px",
        examples=["calibrated"],
    )
    object_distance_mm: float | None = Field(
        default=None,
        gt=0,
        description="object distance of the scene (mm): p(u) from the calibrated model",
    )
    white_base64: str | None = Field(
        default=None, description="optional: a white image of the camera (flat field), base64"
    )


def _b64(text: str, field: str) -> bytes:
    try:
        return base64.b64decode(text, validate=True)
    except (binascii.Error, ValueError):
        raise ApiError(
            422,
            "invalid_request",
            f"{field} is not valid base64",
            fields=[(field, "must be a base64-encoded PNG or TIFF file")],
        ) from None


def _station(request: Request) -> Orchestrator:
    station: Orchestrator = request.app.state.station
    return station


def _calibrated_camera(station: Orchestrator, body: RenderRequest) -> CalibratedCamera:
    """The camera model of the request's calibration: the job's result or the one sent."""
    if (body.job_id is None) == (body.result is None):
        raise ApiError(
            422,
            "invalid_request",
            "give exactly one of job_id (a job's calibration) or result (an lfcal-result/1)",
            fields=[("job_id", "exactly one of job_id and result")],
        )
    if body.job_id is not None:
        with station_errors():
            result = station.result(body.job_id)
    else:
        assert body.result is not None
        result = body.result
    try:
        return CalibratedCamera.from_result(result)
    except ResultError as exc:
        raise ApiError(422, "invalid_result", str(exc), fields=[("result", str(exc))]) from None


async def _rendered_response(
    camera: CalibratedCamera,
    body: RenderRequest,
    raw_bytes: bytes,
    white_bytes: bytes | None,
    designed: float | None,
) -> Response:
    """Decode and render the upload in the thread pool; the PNG with the patch headers."""

    def work() -> tuple[bytes, Any]:
        raw = decode_raw(raw_bytes, name="the uploaded image")
        white = None if white_bytes is None else decode_raw(white_bytes, name="the white image")
        patch = choose_patch(
            camera,
            body.p,
            object_distance_mm=body.object_distance_mm,
            designed_px=designed,
        )
        rendered = render_frame_with(raw, camera, patch, white=white)
        return render_png(None, rendered.image), rendered

    try:
        data, rendered = await run_in_threadpool(work)
    except RawImageError as exc:
        raise ApiError(
            422, "invalid_image", str(exc), fields=[("image_base64", str(exc))]
        ) from None
    except FrameMismatch as exc:
        raise ApiError(422, "frame_mismatch", str(exc)) from None
    except ValueError as exc:
        raise ApiError(422, "cannot_render", str(exc), fields=[("p", str(exc))]) from None
    return Response(
        content=data,
        media_type="image/png",
        headers={
            "Cache-Control": "no-store",
            "X-Patch-Size-Px": f"{rendered.patch_px:.6f}",
            "X-Render-Patch-Px": f"{rendered.render_patch_px:.6f}",
            "X-Artefact-Score": f"{rendered.score:.6f}",
        },
    )


def _add_render_route(router: APIRouter) -> None:
    """``POST /render`` (always with the API key)."""

    @router.post(
        "/render",
        response_class=Response,
        responses={200: PNG, **error_responses(400, 401, 403, 404, 409, 413, 415, 422)},
        dependencies=[Depends(check_key)],
        summary="Render an uploaded raw frame with a calibration (patch rendering, PNG)",
    )
    async def render(request: Request, body: RenderRequest) -> Response:
        """Georgiev–Lumsdaine rendering of any raw frame of the calibrated camera (a scene,
        not only the board). The calibration is a job's result (``job_id``) or one sent
        along (``result``). 422 for a corrupt image, a frame of another size or of another
        camera; 409 when the job has no result. Headers: ``X-Patch-Size-Px`` (ESIF p),
        ``X-Render-Patch-Px`` (seam-free rendering patch), ``X-Artefact-Score``."""
        station = _station(request)
        camera = _calibrated_camera(station, body)
        raw_bytes = _b64(body.image_base64, "image_base64")
        white_bytes = None if body.white_base64 is None else _b64(body.white_base64, "white_base64")
        designed = None
        if body.p == "designed":
            try:
                designed = designed_patch_px(station.config)
            except ValueError as exc:
                raise ApiError(409, "no_designed_optics", str(exc)) from None
        return await _rendered_response(camera, body, raw_bytes, white_bytes, designed)


def _report_html(
    result: dict[str, Any], archive: pathlib.Path, designed: float | None, job_id: int
) -> bytes:
    """The job's report page (UTF-8), from its archive where it has one."""
    html = report_from_archive(
        result,
        archive if (archive / "sweep.json").is_file() else None,
        designed_px=designed,
        verify=False,
        source=f"station job {job_id}",
        job_id=job_id,
    )
    return html.encode("utf-8")


def _add_report_route(router: APIRouter, read_deps: list[Any]) -> None:
    """``GET /jobs/{id}/report.html``."""

    @router.get(
        "/jobs/{job_id}/report.html",
        response_class=Response,
        responses={200: HTML, **error_responses(401, 403, 404, 409, 422)},
        dependencies=read_deps,
        summary="The job's calibration report (one self-contained, printable HTML page)",
    )
    async def report(request: Request, job_id: JobId) -> Response:
        """Camera identity, station and board, acceptance checks (priors against calibrated
        values, PASS/FAIL), calibrated values with uncertainties, focus, disparity and
        residual plots, crops rendered with the calibrated and designed p, software and
        archive checksum (as recorded: ``lfcal report`` re-reads the files). 409 until the
        job succeeded with a result."""
        station = _station(request)
        with station_errors():
            result = station.result(job_id)
            archive = station.archive_dir(job_id)
        try:
            designed: float | None = designed_patch_px(station.config)
        except ValueError:
            designed = None
        cache: BytesCache = request.app.state.media_cache
        make = functools.partial(_report_html, result, archive, designed, job_id)
        data = await run_in_threadpool(cache.get_or_make, (job_id, "report"), make)
        return Response(
            content=data,
            media_type="text/html; charset=utf-8",
            headers={"Cache-Control": "private, max-age=3600"},
        )


def _corners_body(station: Orchestrator, job_id: int, index: int) -> dict[str, Any]:
    """The corners measured in frame ``index`` of the job (404 for an unknown job or frame)."""
    with station_errors():
        station.frame_path(job_id, index)  # 404 for an unknown job or frame
        step = station.store.step(job_id, index)
        camera = _frame_size(station, job_id)
    summary = (step.summary if step is not None else None) or {}
    rows = summary.get("corners") or {}

    def xy(name: str) -> list[list[float]]:
        return [[r[2], r[3]] for r in rows.get(name) or [] if len(r) >= 4]

    return {
        "index": index,
        "analysed": bool(summary),
        "rail_mm": None if step is None else step.actual_mm,
        "width": camera[0],
        "height": camera[1],
        "standard": xy("standard"),
        "reference": xy("reference"),
        "edge_width_px": summary.get("edge_width_px"),
        "error": summary.get("error") or None,
    }


def _add_corners_route(router: APIRouter, read_deps: list[Any]) -> None:
    """``GET /jobs/{id}/frames/{index}/corners``."""

    @router.get(
        "/jobs/{job_id}/frames/{index}/corners",
        responses=error_responses(401, 403, 404, 422),
        dependencies=read_deps,
        summary="The board corners the streaming analysis measured in a frame",
    )
    def corners(
        request: Request,
        job_id: JobId,
        index: Annotated[int, Path(ge=0, le=HARD_MAX_FRAMES, description="frame index")],
    ) -> JSONResponse:
        """Corner positions (px, raw-frame coordinates) in every used micro-image, for the
        standard and the reference corner; ``analysed`` is false until the frame's analysis
        finished. ``width``/``height``: the frame size, to scale an overlay."""
        return JSONResponse(_corners_body(_station(request), job_id, index))


def build_lab_router(*, read_key: bool) -> APIRouter:
    """``/render``, ``/jobs/{id}/report.html`` and ``/jobs/{id}/frames/{i}/corners``."""
    read_deps = [Depends(check_key)] if read_key else []
    router = APIRouter(prefix=API, tags=["using a calibration"])
    _add_render_route(router)
    _add_report_route(router, read_deps)
    _add_corners_route(router, read_deps)
    return router


def _frame_size(station: Orchestrator, job_id: int) -> tuple[int | None, int | None]:
    """Width and height of the job's frames, from its manifest (None when unreadable)."""
    import json

    try:
        manifest = json.loads((station.archive_dir(job_id) / "sweep.json").read_text())
        return int(manifest["camera"]["width"]), int(manifest["camera"]["height"])
    except (OSError, ValueError, KeyError, TypeError):
        return None, None


__all__ = ["RenderRequest", "build_lab_router"]
