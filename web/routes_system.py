"""Station routes: ``GET /devices`` and ``GET /healthz``."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Depends, Request
from fastapi.responses import JSONResponse

from calibration.version import software_version
from station.orchestrator import Orchestrator
from station.store import ACTIVE_STATES, JobState, StoreError
from web.errors import ApiError, error_responses
from web.schemas import DevicesOut, Health
from web.security import check_key
from web.station_api import API


def device_problems(info: dict[str, Any]) -> list[str]:
    """What is down in a device description (empty: everything is up)."""
    if info.get("busy") and not info.get("connected") and not info.get("error"):
        return []
    problems = []
    if info.get("error"):
        problems.append(str(info["error"]))
    for name in ("camera", "rail", "xy_stage"):
        entry = info.get(name)
        if isinstance(entry, dict) and entry.get("error"):
            problems.append(f"{name}: {entry['error']}")
        if isinstance(entry, dict):
            for axis in ("x", "y"):
                sub = entry.get(axis)
                if isinstance(sub, dict) and sub.get("error"):
                    problems.append(f"{name}.{axis}: {sub['error']}")
    if not problems and not info.get("connected") and not info.get("busy"):
        problems.append("the devices are not connected")
    return problems


def device_state(info: dict[str, Any]) -> str:
    """``connected``, ``busy`` (a job owns them), ``opening`` or ``down``."""
    if device_problems(info):
        return "down"
    if info.get("busy"):
        return "busy" if info.get("connected") else "opening"
    return "connected"


def build_system_router(*, read_key: bool) -> APIRouter:
    """``/devices`` (keyed when ``read_key``) and ``/healthz`` (always open)."""
    router = APIRouter(prefix=API, tags=["station"])
    deps = [Depends(check_key)] if read_key else []

    @router.get(
        "/devices",
        response_model=DevicesOut,
        dependencies=deps,
        responses=error_responses(401, 403, 503),
        summary="Devices: connection, identity, position, homed, camera (503 when one is down)",
    )
    def devices(request: Request) -> DevicesOut:
        """While a job runs the devices belong to it: the last description is returned
        with ``busy: true`` and the live rail position."""
        station: Orchestrator = request.app.state.station
        info = station.devices_info()
        state = device_state(info)
        if state == "down":
            problems = "; ".join(device_problems(info))
            raise ApiError(
                503,
                "device_unavailable",
                f"a device is down: {problems}; check cables and power, then start a job "
                "(the station reopens the devices for it) or restart the server",
                context={"devices": info},
            )
        if state == "opening":
            raise ApiError(
                503,
                "devices_opening",
                "the station is still opening and homing the devices; try again in a moment",
                headers={"Retry-After": "1"},
            )
        return DevicesOut.model_validate(info)

    @router.get(
        "/healthz",
        response_model=Health,
        responses={503: {"model": Health, "description": "the station cannot run jobs"}},
        summary="Health: what is down and why (503 when the station cannot run jobs; "
        "never needs a key)",
    )
    def healthz(request: Request) -> JSONResponse:
        """``status``: ``ok``, or ``degraded`` with one sentence per problem in
        ``problems`` while a component (hardware worker, job store, disk space,
        devices, analysis processes) is down; HTTP 503 when the station cannot run
        jobs (worker down or stopping, store not writable, a disk full, a device down)."""
        station: Orchestrator = request.app.state.station
        report = station.health()
        info = station.devices_info()
        devices = device_state(info)
        report["components"]["devices"] = {"state": devices, "problems": device_problems(info)}
        if devices == "down":
            report["problems"].append("devices: " + "; ".join(device_problems(info)))
            report["can_run_jobs"] = False
            report["status"] = "degraded"
        try:
            active: int | None = len(
                station.store.list_jobs(states={JobState.QUEUED, *ACTIVE_STATES})
            )
        except StoreError:
            active = None
        body = Health(
            status=report["status"],
            version=software_version(),
            devices=devices,
            read_only_requires_key=request.app.state.config.server.read_only_requires_key,
            jobs_active=active,
            can_run_jobs=report["can_run_jobs"],
            problems=report["problems"],
            components=report["components"],
        )
        return JSONResponse(
            body.model_dump(),
            status_code=200 if body.can_run_jobs else 503,
            headers={"Cache-Control": "no-store"},
        )

    return router


__all__ = ["build_system_router", "device_problems", "device_state"]
