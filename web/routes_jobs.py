"""Job routes: submit, list, status, pause/resume/cancel, result.

Handlers are plain functions (run in the server's thread pool): the station's
methods are thread-safe and return quickly. ``GET /jobs/{id}``, the route that
operators and scripts poll, is a coroutine run on the event loop itself: the
status is a memory read, serialised once per change (:class:`web.fast_status.StatusBodies`),
and its plain successful case is answered by :class:`web.fast_status.FastStatus`
before the router (``bench/bench_web.py``); this handler answers the rest (404 ...)
and documents the route.
"""

# No ``from __future__ import annotations``: FastAPI needs the per-station body
# model in the handler's annotation as a real object.

from typing import Annotated, Any

from fastapi import APIRouter, Body, Depends, Header, Query, Request, Response
from pydantic import BaseModel

from station.orchestrator import Orchestrator
from station.ownership import live_stations, station_alive
from station.store import JobNotFound, JobState
from web.errors import ApiError, error_responses
from web.fast_status import StatusBodies
from web.schemas import (
    CalibrationResult,
    JobId,
    JobList,
    JobOut,
    ResultVersionList,
    ResultVersionOut,
)
from web.security import check_key
from web.station_api import API, job_out, station_errors

IdempotencyKey = Annotated[
    str | None,
    Header(
        alias="Idempotency-Key",
        min_length=1,
        max_length=200,
        pattern=r"^[!-~]+$",
        description="repeat a POST safely: the same key with the same sweep returns the same "
        "job (printable ASCII, no spaces)",
    ),
]


def station_of(request: Request) -> Orchestrator:
    """The station behind the app."""
    station: Orchestrator = request.app.state.station
    return station


def _submit_job(station: Orchestrator, data: dict[str, Any], idempotency_key: str | None) -> JobOut:
    """Queue the sweep ``data`` on ``station``, its errors mapped to HTTP."""
    with station_errors():
        try:
            status = station.submit(data, idempotency_key=idempotency_key)
        except JobNotFound as exc:
            message = f"there is no job {exc.job_id} to take the white image from"
            raise ApiError(
                422,
                "invalid_request",
                f"the sweep cannot run: white_from_job: {message}",
                fields=[("white_from_job", message)],
            ) from None
        except RuntimeError as exc:
            raise ApiError(503, "station_stopping", str(exc)) from None
    return job_out(status)


def _job_list(
    station: Orchestrator,
    *,
    states: list[JobState] | None,
    limit: int,
    station_id: str | None,
    camera_serial: str | None,
) -> JobList:
    """The newest ``limit`` matching jobs of the fleet, oldest first, with ``station_alive``."""
    with station_errors():
        records = station.store.list_jobs(
            states=set(states) if states else None,
            station=station_id,
            camera_serial=camera_serial,
        )[-limit:]
        live = live_stations(station.store)
    out = []
    for record in records:
        try:
            job = job_out(station.status(record.id))
        except KeyError:  # vanished meanwhile (never in practice: jobs are not deleted)
            continue
        job.station_alive = station_alive(station.store, record.station_id, live)
        out.append(job)
    return JobList(jobs=out)


def _add_submit_route(router: APIRouter, body_model: type[BaseModel], write: list[Any]) -> None:
    """``POST /jobs``."""

    @router.post(
        "/jobs",
        status_code=202,
        response_model=JobOut,
        dependencies=write,
        responses=error_responses(400, 401, 403, 408, 409, 413, 415, 422, 503, 507),
        summary="Start a calibration run (queue a sweep)",
    )
    def create_job(
        request: Request,
        response: Response,
        body: Annotated[body_model | None, Body()] = None,  # type: ignore[valid-type]
        idempotency_key: IdempotencyKey = None,
    ) -> JobOut:
        """Queue a sweep; 202 with ``Location`` of the job. Every field is optional.

        With an ``Idempotency-Key`` already used for the same sweep, the existing job is
        returned (202); for a different sweep 409. 507 (``storage_full``) when the disk
        holding the job database or the archives is full; 503 when the database cannot
        be written or the station is stopping.
        """
        data: dict[str, Any] = {} if body is None else body.model_dump(exclude_none=True)
        job = _submit_job(station_of(request), data, idempotency_key)
        response.headers["Location"] = f"{API}/jobs/{job.id}"
        return job


def _add_list_route(router: APIRouter, read: list[Any]) -> None:
    """``GET /jobs``."""

    @router.get(
        "/jobs",
        response_model=JobList,
        dependencies=read,
        responses=error_responses(401, 403, 422),
        summary="List jobs (optionally by state, station, camera)",
    )
    def list_jobs(
        request: Request,
        state: Annotated[
            list[JobState] | None,
            Query(description="only jobs in this state (repeatable)"),
        ] = None,
        limit: Annotated[int, Query(ge=1, le=1000, description="at most this many (newest)")] = 100,
        station_id: Annotated[
            str | None,
            Query(
                alias="station",
                min_length=1,
                max_length=64,
                description="only jobs of this station (stations sharing one database)",
            ),
        ] = None,
        camera_serial: Annotated[
            str | None,
            Query(min_length=1, max_length=200, description="only jobs of this camera"),
        ] = None,
    ) -> JobList:
        """Jobs of every station sharing the database (the fleet view), oldest first;
        the newest ``limit`` of them, each with ``station_alive``: whether its
        station's process is running."""
        return _job_list(
            station_of(request),
            states=state,
            limit=limit,
            station_id=station_id,
            camera_serial=camera_serial,
        )


def _add_status_route(router: APIRouter, read: list[Any]) -> None:
    """``GET /jobs/{id}`` (its plain successful case is answered before the router)."""

    @router.get(
        "/jobs/{job_id}",
        response_model=JobOut,
        dependencies=read,
        responses=error_responses(401, 403, 404, 422),
        summary="A job's state and progress",
    )
    async def get_job(request: Request, job_id: JobId) -> Response:
        """State, frames done/total, rail position, ETA, last error."""
        bodies: StatusBodies = request.app.state.status_bodies
        with station_errors():
            body = bodies.body(job_id)
        return Response(body, media_type="application/json")


def _add_action_route(
    router: APIRouter, write: list[Any], name: str, summary: str, doc: str
) -> None:
    """``POST /jobs/{id}/<name>``: the station's method ``name`` on the job."""

    def handler(request: Request, job_id: JobId) -> JobOut:
        station = station_of(request)
        with station_errors():
            try:
                status = getattr(station, name)(job_id)
            except RuntimeError as exc:  # shutting down
                raise ApiError(503, "station_stopping", str(exc)) from None
        return job_out(status)

    handler.__name__ = f"{name}_job"
    handler.__doc__ = doc
    router.add_api_route(
        f"/jobs/{{job_id}}/{name}",
        handler,
        methods=["POST"],
        response_model=JobOut,
        dependencies=write,
        responses=error_responses(400, 401, 403, 404, 408, 409, 413, 415, 422, 503, 507),
        summary=summary,
    )


def _add_action_routes(router: APIRouter, write: list[Any]) -> None:
    """``POST /jobs/{id}/pause``, ``.../resume`` and ``.../cancel``."""
    _add_action_route(
        router,
        write,
        "pause",
        "Pause a running job",
        "Pause at the next step boundary (409 unless running; pausing a paused job is a no-op).",
    )
    _add_action_route(
        router,
        write,
        "resume",
        "Resume a paused job (or re-queue an interrupted/failed one)",
        "Resume a paused job, or re-queue an interrupted or failed one (409 otherwise).",
    )
    _add_action_route(
        router,
        write,
        "cancel",
        "Cancel a job",
        "Cancel: queued or interrupted at once, running or paused at the next step boundary "
        "(409 for a finished job).",
    )


def _add_result_routes(router: APIRouter, read: list[Any]) -> None:
    """``GET /jobs/{id}/result`` and ``GET /jobs/{id}/results``."""

    @router.get(
        "/jobs/{job_id}/result",
        response_model=CalibrationResult,
        dependencies=read,
        responses=error_responses(401, 403, 404, 409, 422),
        summary="The calibration result (409 until the job succeeded)",
    )
    def get_result(request: Request, job_id: JobId) -> CalibrationResult:
        """a, b, Q, p, focus plane, uncertainties and the per-frame values (``frames``)."""
        with station_errors():
            result = station_of(request).result(job_id)
        return CalibrationResult.model_validate(result)

    @router.get(
        "/jobs/{job_id}/results",
        response_model=ResultVersionList,
        dependencies=read,
        responses=error_responses(401, 403, 404, 422),
        summary="Every version of the job's result (the station's and each recalibration's)",
    )
    def get_result_versions(
        request: Request,
        job_id: JobId,
        software_version: Annotated[
            str | None,
            Query(min_length=1, max_length=100, description="only results of this version"),
        ] = None,
        with_results: Annotated[
            bool, Query(description="include each version's result JSON")
        ] = True,
    ) -> ResultVersionList:
        """Version 0 is the station's own result; ``lfcal recalibrate`` adds 1, 2, ...
        with the software version and date; none replaces another."""
        from station.result_versions import result_versions

        with station_errors():
            versions = result_versions(
                station_of(request).store,
                job_id,
                with_results=with_results,
                software_version=software_version,
            )
        return ResultVersionList(
            versions=[ResultVersionOut.model_validate(v.to_dict()) for v in versions]
        )


def build_jobs_router(body_model: type[BaseModel], *, read_key: bool) -> APIRouter:
    """The job routes for a station whose sweep body model is ``body_model``.

    ``read_key``: read-only routes require the API key too (OpenAPI security).
    Registered in this order: submit, list, status, pause/resume/cancel, results.
    """
    write = [Depends(check_key)]
    read = write if read_key else []
    router = APIRouter(prefix=API, tags=["jobs"])
    _add_submit_route(router, body_model, write)
    _add_list_route(router, read)
    _add_status_route(router, read)
    _add_action_routes(router, write)
    _add_result_routes(router, read)
    return router


__all__ = ["build_jobs_router", "station_of"]
