"""Server-Sent Events of a job: ``GET /api/v1/jobs/{id}/events``.

Each event is ``event: <type>`` with ``data: <JSON>`` (``{"job_id", "type", "id",
"at", "data"}``, see :mod:`station.events`). ``step`` events carry the step
index as the SSE ``id``, so a client that reconnects with ``Last-Event-ID: 7``
(browsers do this by themselves) gets the recorded steps 8, 9, ... replayed from
the job store, then the live events. Other events (``analysis``, ``state``,
``phase``, ``fault``) carry no id. The stream starts with the replay (every
recorded step with its analysis summary, then the current ``state``) and ends
after the job reaches a final state; a comment line is sent every 15 s to keep
the connection open. When the server stops (SIGTERM), the running job is
stopped first (``interrupted`` at its next step boundary) and every stream ends
with a ``state`` event: the job's state at that moment.

:class:`EventBridge` forwards the station's events (published in the station's
threads) to the asyncio queues of the connected clients with one
``loop.call_soon_threadsafe`` per event, so the station never waits for a slow
client; each event is serialised once on the event loop, whatever the number of
clients; a client that falls more than ``maxsize`` events behind is
re-synchronised from the store.
"""

from __future__ import annotations

import asyncio
import json
import threading
from collections.abc import AsyncIterator
from typing import Annotated

from fastapi import APIRouter, Depends, Header, Query, Request
from fastapi.responses import StreamingResponse
from starlette.concurrency import run_in_threadpool

from station.events import JobEvent
from station.orchestrator import FINAL_STATES, Orchestrator
from web.errors import error_responses
from web.schemas import JobId
from web.security import check_key
from web.station_api import API, station_errors

KEEPALIVE_S = 15.0
FINAL = frozenset(s.value for s in FINAL_STATES)


_Item = tuple[JobEvent, str] | None
"""An event with its SSE text, or None: the server stops."""


class _Client:
    def __init__(self, job_id: int, maxsize: int) -> None:
        self.job_id = job_id
        self.queue: asyncio.Queue[_Item] = asyncio.Queue(maxsize)
        self.overflowed = False

    def offer(self, item: _Item) -> None:
        try:
            self.queue.put_nowait(item)
        except asyncio.QueueFull:
            self.overflowed = True


class EventBridge:
    """Station events -> asyncio queues of SSE clients (see the module docstring)."""

    def __init__(self, station: Orchestrator, *, maxsize: int = 2000) -> None:
        self.station = station
        self.maxsize = maxsize
        self._clients: set[_Client] = set()
        self._lock = threading.Lock()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stopping = False
        station.add_listener(self._on_event)

    def close(self) -> None:
        """Stop forwarding events and end every open stream."""
        self.station.remove_listener(self._on_event)
        self.stop_streams()

    def stop_streams(self) -> None:
        """End every open stream (server shutdown); callable from any thread."""
        self._stopping = True
        self._broadcast(None)

    @property
    def clients(self) -> int:
        """Connected SSE clients."""
        with self._lock:
            return len(self._clients)

    def open(self, job_id: int) -> _Client:
        """A new client of ``job_id`` (call from the event loop)."""
        self._loop = asyncio.get_running_loop()
        client = _Client(job_id, self.maxsize)
        with self._lock:
            self._clients.add(client)
        if self._stopping:
            client.offer(None)
        return client

    def discard(self, client: _Client) -> None:
        with self._lock:
            self._clients.discard(client)

    def _on_event(self, event: JobEvent) -> None:
        self._broadcast(event)

    def _broadcast(self, event: JobEvent | None) -> None:
        """In the publishing thread: the clients connected now get the event (one
        hand-over to the event loop, whatever their number)."""
        loop = self._loop
        if loop is None or loop.is_closed():
            return
        with self._lock:
            targets = [c for c in self._clients if event is None or c.job_id == event.job_id]
        if not targets:
            return
        try:
            loop.call_soon_threadsafe(self._deliver, event, targets)
        except RuntimeError:  # the loop has closed
            return

    @staticmethod
    def _deliver(event: JobEvent | None, targets: list[_Client]) -> None:
        """On the event loop: serialise the event once, queue it for every target."""
        item = None if event is None else (event, format_event(event))
        for client in targets:
            client.offer(item)


def format_event(event: JobEvent) -> str:
    """One SSE message (``id`` only for ``step`` events)."""
    data = json.dumps(event.to_dict(), separators=(",", ":"), default=str)
    head = f"id: {event.id}\n" if event.type == "step" and event.id is not None else ""
    return f"{head}event: {event.type}\ndata: {data}\n\n"


async def event_stream(bridge: EventBridge, job_id: int, after: int | None) -> AsyncIterator[str]:
    """Replay from the store after step ``after``, then live events until a final state."""
    client = bridge.open(job_id)  # subscribe first: nothing between replay and live is lost
    station = bridge.station
    try:
        yield "retry: 2000\n\n"
        last_step = -1 if after is None else after
        replay = await run_in_threadpool(station.replay, job_id, after)
        for old in replay:
            if old.type == "step" and old.id is not None:
                last_step = max(last_step, old.id)
            yield format_event(old)
        if replay and replay[-1].data.get("state") in FINAL:
            return
        while True:
            try:
                item = await asyncio.wait_for(client.queue.get(), KEEPALIVE_S)
            except TimeoutError:
                yield ": keep-alive\n\n"
                continue
            if item is None:  # the server stops: end with the job's state (from the store)
                try:
                    final = await run_in_threadpool(station.replay, job_id, last_step)
                except Exception:  # noqa: BLE001 - the stream ends either way
                    return
                for again in final:
                    yield format_event(again)
                return
            if client.overflowed:  # fell behind: re-synchronise from the store
                client.overflowed = False
                while not client.queue.empty():
                    client.queue.get_nowait()
                for again in await run_in_threadpool(station.replay, job_id, last_step):
                    if again.type == "step" and again.id is not None:
                        last_step = max(last_step, again.id)
                    yield format_event(again)
                    if again.type == "state" and again.data.get("state") in FINAL:
                        return
                continue
            event, text = item
            if event.type == "step" and event.id is not None:
                if event.id <= last_step:
                    continue
                last_step = event.id
            yield text
            if event.type == "state" and event.data.get("state") in FINAL:
                return
    finally:
        bridge.discard(client)


def build_events_router(*, read_key: bool) -> APIRouter:
    """The SSE route (``read_key``: it requires the API key)."""
    deps = [Depends(check_key)] if read_key else []
    router = APIRouter(prefix=API, tags=["jobs"], dependencies=deps)

    @router.get(
        "/jobs/{job_id}/events",
        response_class=StreamingResponse,
        responses={
            200: {
                "content": {"text/event-stream": {}},
                "description": "step (id = step index), analysis, state and phase events",
            },
            **error_responses(401, 403, 404, 422),
        },
        summary="Live events of a job (Server-Sent Events, replay from Last-Event-ID)",
    )
    async def events(
        request: Request,
        job_id: JobId,
        last_event_id: Annotated[
            int | None,
            Header(alias="Last-Event-ID", ge=-1, le=10**9, description="last step index seen"),
        ] = None,
        after: Annotated[
            int | None,
            Query(ge=-1, le=10**9, description="replay steps after this index (as Last-Event-ID)"),
        ] = None,
    ) -> StreamingResponse:
        """The job's events; the stream ends when the job reaches a final state."""
        bridge: EventBridge = request.app.state.events
        station = bridge.station
        with station_errors():
            await run_in_threadpool(station.record, job_id)
        start = last_event_id if last_event_id is not None else after
        return StreamingResponse(
            event_stream(bridge, job_id, start),
            media_type="text/event-stream",
            headers={"Cache-Control": "no-store", "X-Accel-Buffering": "no"},
        )

    return router


__all__ = ["EventBridge", "build_events_router", "event_stream", "format_event"]
