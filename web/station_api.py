"""The thin adapter between the routes and the station (:class:`station.orchestrator.Orchestrator`).

It maps the station's typed errors onto HTTP answers (:class:`web.errors.ApiError`)
and the station's :class:`~station.orchestrator.JobStatus` onto :class:`web.schemas.JobOut`.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from station.orchestrator import FrameNotFound, JobStatus, ResultNotReady
from station.store import IdempotencyConflict, InvalidTransition, JobNotFound, StoreUnavailable
from station.sweep import RequestInvalid
from web.errors import ApiError, storage_error
from web.schemas import JobLinks, JobOut

API = "/api/v1"


@contextmanager
def station_errors() -> Iterator[None]:
    """Turn the station's exceptions into :class:`ApiError` (404, 409, 422, 503, 507)."""
    try:
        yield
    except StoreUnavailable as exc:  # a full disk (507) or a database that cannot be written
        raise storage_error(exc) from None
    except JobNotFound as exc:
        raise ApiError(404, "job_not_found", f"{exc}: list the jobs with GET {API}/jobs") from None
    except FrameNotFound as exc:
        raise ApiError(
            404,
            "frame_not_found",
            f"{exc}; GET {API}/jobs/{exc.job_id} shows frames_done (indices start at 0)",
        ) from None
    except InvalidTransition as exc:
        raise ApiError(409, "invalid_transition", str(exc), context=_state(exc)) from None
    except ResultNotReady as exc:
        raise ApiError(
            409, "result_not_ready", str(exc), context={"state": exc.state.value}
        ) from None
    except IdempotencyConflict as exc:
        raise ApiError(
            409,
            "idempotency_conflict",
            f"{exc}; use a new Idempotency-Key for a different sweep",
            context={"job_id": exc.job_id},
        ) from None
    except RequestInvalid as exc:
        summary = "; ".join(f"{f}: {m}" for f, m in exc.problems)
        raise ApiError(
            422,
            "invalid_request",
            f"the sweep cannot run: {summary}",
            fields=exc.problems,
        ) from None


def _state(exc: InvalidTransition) -> dict[str, Any]:
    return {"state": exc.from_state.value}


def links_dict(job_id: int) -> dict[str, str]:
    """URLs of a job's resources (the :class:`JobLinks` shape)."""
    base = f"{API}/jobs/{job_id}"
    return {
        "self": base,
        "events": f"{base}/events",
        "result": f"{base}/result",
        "archive": f"{base}/archive",
        "focus_plot": f"{base}/plots/focus.png",
        "disparity_plot": f"{base}/plots/disparity.png",
        "render_calibrated": f"{base}/render.png?p=calibrated",
        "render_designed": f"{base}/render.png?p=designed",
    }


def links(job_id: int) -> JobLinks:
    """URLs of a job's resources."""
    return JobLinks.model_validate(links_dict(job_id))


_JOB_FIELDS = tuple(JobOut.model_fields)


def job_dict(status: JobStatus) -> dict[str, Any]:
    """The API view of a job status as a JSON-ready dict (the :class:`JobOut` shape),
    without model validation: the status route is the one clients poll
    (:mod:`web.fast_status`)."""
    data = status.to_dict()
    data["links"] = links_dict(status.id)
    return {k: data.get(k) for k in _JOB_FIELDS}


def job_out(status: JobStatus) -> JobOut:
    """The API view of a job status."""
    return JobOut.model_validate(job_dict(status))


__all__ = ["API", "job_dict", "job_out", "links", "station_errors"]
