"""Streaming frame analysis in worker processes, so acquisition never waits for it.

:class:`AnalysisPool` is one ``ProcessPoolExecutor`` (``spawn`` start method: the
station process has threads, so it never forks) kept for the life of the
orchestrator. A job opens an :class:`AnalysisSession` with its
:class:`calibration.pipeline.FrameAnalyzer` (fitted once on the white image;
it pickles to a few kB and is cached in each worker per job), submits each
frame **by file name** as soon as it is in the archive -- the worker reads the
PNG itself, so no frame crosses the process boundary -- and gets a
:class:`calibration.pipeline.FrameSummary` back through a callback. At the end
:meth:`AnalysisSession.wait` returns every summary, and
:meth:`AnalysisSession.combine` runs the final calibration in a worker too.

A worker process that dies (killed, out of memory) breaks the executor: the
pool notices at once (the frame's future fails with ``BrokenProcessPool``),
starts a new executor and submits the frames that were in flight again, once;
what still fails is analysed in the calling process by ``wait``. So a result
is never silently missing a frame. :meth:`AnalysisPool.health` reports the
restarts and the last fault.

Workers run at a lower CPU priority (:func:`lower_cpu_priority`): on a busy
machine, the hardware thread and the HTTP server come first.
"""

from __future__ import annotations

import functools
import math
import multiprocessing
import os
import pickle
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import Any

from calibration.archive import read_image
from calibration.blas_threads import single_blas_thread
from calibration.heap_reuse import reuse_freed_memory
from calibration.pipeline import (
    CalibrationError,
    FrameAnalyzer,
    FrameSummary,
    SweepGeometry,
    combine,
)

# --------------------------------------------------------------------------- worker side

_CACHE: dict[str, FrameAnalyzer] = {}


ANALYSIS_NICENESS = 10
"""How much nicer than the station process the analysis workers run (Unix nice)."""


def lower_cpu_priority() -> None:
    """Raise the calling process's nice value by :data:`ANALYSIS_NICENESS` (where allowed).

    Analysis workers call it: when the cores are busy, the hardware thread and the
    HTTP server come first (about 90 % of a contended core), and the streaming
    analysis catches up between steps (it is not on the acquisition's critical
    path). Nice rather than Linux ``SCHED_IDLE``: the workers still progress when
    another program keeps every core busy.
    """
    if hasattr(os, "nice"):
        try:
            os.nice(ANALYSIS_NICENESS)
        except OSError:  # not permitted here: run at the normal priority
            pass


def _init_worker() -> None:
    """Runs first in every worker: lower its CPU priority (:func:`lower_cpu_priority`),
    one BLAS thread (:mod:`calibration.blas_threads`: the pool is the parallelism), freed
    array memory kept for reuse (:mod:`calibration.heap_reuse`); exit when the station
    process ends, even by ``kill -9``.

    (A pool worker otherwise waits for work forever once its parent is gone.)
    """
    lower_cpu_priority()
    single_blas_thread()
    reuse_freed_memory()
    parent = multiprocessing.parent_process()
    if parent is None:
        return

    def watch() -> None:
        parent.join()  # returns when the parent's sentinel closes, i.e. it has ended
        os._exit(0)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def _warm_up() -> int:
    """Runs in a new worker: imports are done by then; returns the worker's pid."""
    return os.getpid()


def _analyze_file(
    key: str,
    blob: bytes,
    index: int,
    rail_mm: float,
    path: str,
    shape: tuple[int, int],
    bit_depth: int,
) -> FrameSummary:
    """Worker: analyse the frame file ``path`` taken at ``rail_mm`` (mm)."""
    image = read_image(path, expected_shape=shape, bit_depth=bit_depth)
    return _analyzer_for(key, blob).analyze(index, rail_mm, image)


def _analyzer_for(key: str, blob: bytes) -> FrameAnalyzer:
    """Worker: the job's analyzer, unpickled once per job and worker."""
    analyzer = _CACHE.get(key)
    if analyzer is None:
        _CACHE.clear()  # one job at a time: drop the previous job's analyzer
        analyzer = pickle.loads(blob)
        _CACHE[key] = analyzer
    return analyzer


def _fit_remote(geometry: SweepGeometry, white: Any) -> FrameAnalyzer:
    """Worker: the MLA grid fit on the white image (:meth:`FrameAnalyzer.from_white`)."""
    return FrameAnalyzer.from_white(geometry, white)


def _combine_remote(
    key: str, blob: bytes, summaries: list[FrameSummary], geometry: SweepGeometry
) -> tuple[str, Any]:
    """Worker: :func:`calibration.pipeline.combine` -> ``("ok", result dict)``, or
    ``("error", (exception class, message, partial))`` for a :class:`CalibrationError`
    (whose ``partial`` would not survive pickling the exception itself)."""
    grid = _analyzer_for(key, blob).grid
    try:
        return "ok", combine(summaries, geometry, grid).to_dict()
    except CalibrationError as exc:
        return "error", (type(exc), str(exc), exc.partial)


# --------------------------------------------------------------------------- summaries

_FLOAT_FIELDS = (
    "rail_mm",
    "object_distance_mm",
    "Q",
    "Q_se",
    "Q_eq3",
    "Ls_px",
    "Lr_px",
    "edge_width_px",
    "edge_spread_px",
)


def summary_from_dict(data: dict[str, Any]) -> FrameSummary:
    """Rebuild a :class:`FrameSummary` from its ``to_dict()`` (JSON ``null`` -> NaN)."""
    values = {k: v for k, v in data.items() if k in FrameSummary.__dataclass_fields__}
    for key in _FLOAT_FIELDS:
        if values.get(key) is None and key in values:
            values[key] = math.nan
    return FrameSummary(**values)


# --------------------------------------------------------------------------- pool


def default_workers() -> int:
    """Analysis processes: one per core, at most 4. They run at a lower priority
    (:func:`lower_cpu_priority`), so acquisition and the HTTP server still come first."""
    return max(1, min(4, os.cpu_count() or 2))


class AnalysisPool:
    """The worker processes of one orchestrator (started lazily, restarted if broken).

    Args:
        workers: number of processes (None: :func:`default_workers`).
    """

    def __init__(self, workers: int | None = None) -> None:
        self.workers = workers or default_workers()
        self._lock = threading.Lock()
        self._executor: ProcessPoolExecutor | None = None
        self.restarts = 0
        self.last_fault: str | None = None
        self._broken_at: float | None = None

    def executor(self) -> ProcessPoolExecutor:
        """The executor, started (and warmed up in the background) on first use."""
        with self._lock:
            if self._executor is None:
                ctx = multiprocessing.get_context("spawn")
                self._executor = ProcessPoolExecutor(
                    self.workers, mp_context=ctx, initializer=_init_worker
                )
                for _ in range(self.workers):
                    self._executor.submit(_warm_up)
            return self._executor

    def start(self) -> None:
        """Start the processes now (they import the calibration core meanwhile)."""
        self.executor()

    def reset(self, broken: ProcessPoolExecutor | None = None, why: str = "") -> None:
        """Drop a broken executor (only ``broken``, if given: not a newer one);
        the next use starts a new one."""
        with self._lock:
            executor = self._executor
            if executor is None or (broken is not None and executor is not broken):
                return
            self._executor = None
            self.restarts += 1
            self.last_fault = why or "an analysis worker process died"
            self._broken_at = time.time()
        executor.shutdown(wait=False, cancel_futures=True)

    def health(self) -> dict[str, Any]:
        """``state`` (``ok``; ``down`` while a broken executor is not replaced yet),
        ``workers``, ``restarts``, ``last_fault``, ``pids`` of the live workers."""
        with self._lock:
            executor = self._executor
            broken = executor is not None and bool(getattr(executor, "_broken", False))
            processes = dict(getattr(executor, "_processes", None) or {})
            out: dict[str, Any] = {
                "state": "down" if broken else "ok",
                "workers": self.workers,
                "restarts": self.restarts,
                "last_fault": self.last_fault,
                "last_fault_at": self._broken_at,
            }
        out["pids"] = sorted(int(pid) for pid, proc in processes.items() if proc.is_alive())
        return out

    def close(self) -> None:
        """Stop the processes (pending work is cancelled)."""
        with self._lock:
            executor, self._executor = self._executor, None
        if executor is not None:
            executor.shutdown(wait=True, cancel_futures=True)

    def fit_analyzer(self, geometry: SweepGeometry, white: Any) -> FrameAnalyzer:
        """:meth:`FrameAnalyzer.from_white` in a worker process: seconds of Python-level
        work that would otherwise hold the station process's GIL while the HTTP server
        answers pollers. Falls back to this process if the pool is unavailable; raises
        ``ValueError`` as ``from_white`` does."""
        try:
            return self.executor().submit(_fit_remote, geometry, white).result()
        except (BrokenProcessPool, RuntimeError) as exc:
            self.reset(None, f"the MLA grid fit's worker process failed ({exc})")
            return FrameAnalyzer.from_white(geometry, white)

    def session(
        self,
        key: str,
        analyzer: FrameAnalyzer,
        *,
        shape: tuple[int, int],
        bit_depth: int,
        on_summary: Callable[[FrameSummary], None] | None = None,
    ) -> AnalysisSession:
        """A new session for one job run (``key`` must be unique per run)."""
        return AnalysisSession(self, key, analyzer, shape, bit_depth, on_summary)


class AnalysisSession:
    """The frames of one job run being analysed (see :meth:`AnalysisPool.session`)."""

    def __init__(
        self,
        pool: AnalysisPool,
        key: str,
        analyzer: FrameAnalyzer,
        shape: tuple[int, int],
        bit_depth: int,
        on_summary: Callable[[FrameSummary], None] | None,
    ) -> None:
        self._pool = pool
        self._key = key
        self._analyzer = analyzer
        self._blob = pickle.dumps(analyzer)
        self._shape = shape
        self._bit_depth = bit_depth
        self._on_summary = on_summary
        self._lock = threading.Lock()
        self._done: dict[int, FrameSummary] = {}
        self._pending: dict[int, tuple[Future[FrameSummary], float, str]] = {}
        self._retried: set[int] = set()
        self._resubmitting = 0
        self._cancelled = False
        self._all_done = threading.Condition(self._lock)

    @property
    def analyzer(self) -> FrameAnalyzer:
        """The analyzer (its ``grid`` is needed by :func:`calibration.pipeline.combine`)."""
        return self._analyzer

    def add_known(self, summary: FrameSummary) -> None:
        """A summary already known (stored by an earlier run of the job)."""
        with self._lock:
            self._done[summary.index] = summary

    def submit(self, index: int, rail_mm: float, path: Path) -> None:
        """Analyse frame ``index`` (file ``path``, rail position ``rail_mm`` mm) in a worker."""
        executor = None
        try:
            executor = self._pool.executor()
            future = executor.submit(
                _analyze_file,
                self._key,
                self._blob,
                index,
                rail_mm,
                str(path),
                self._shape,
                self._bit_depth,
            )
        except (BrokenProcessPool, RuntimeError) as exc:
            self._pool.reset(executor, f"an analysis worker process died ({exc})")
            future = Future()
            future.set_exception(BrokenProcessPool("analysis pool unavailable"))
        with self._lock:
            self._pending[index] = (future, rail_mm, str(path))
        future.add_done_callback(functools.partial(self._finished, index, executor))

    def _finished(
        self, index: int, executor: ProcessPoolExecutor | None, future: Future[FrameSummary]
    ) -> None:
        if future.cancelled() or future.exception() is not None:
            error = None if future.cancelled() else future.exception()
            retry = False
            with self._lock:
                if (
                    isinstance(error, BrokenProcessPool)
                    and not self._cancelled
                    and index not in self._retried
                    and index not in self._done
                ):
                    self._retried.add(index)
                    self._resubmitting += 1
                    retry = True
                    _, rail_mm, path = self._pending[index]
                self._all_done.notify_all()
            if retry:  # a worker died: a new executor, the frame submitted once more
                self._pool.reset(executor, f"an analysis worker process died ({error})")
                threading.Thread(
                    target=self._resubmit,
                    args=(index, rail_mm, Path(path)),
                    name=f"analysis-resubmit-{index}",
                    daemon=True,
                ).start()
            return  # else analysed again in wait()
        summary = future.result()
        with self._lock:
            if index in self._done:
                return
            self._done[index] = summary
            self._pending.pop(index, None)
            self._all_done.notify_all()
        if self._on_summary is not None:
            self._on_summary(summary)

    def _resubmit(self, index: int, rail_mm: float, path: Path) -> None:
        try:
            self.submit(index, rail_mm, path)
        finally:
            with self._lock:
                self._resubmitting -= 1
                self._all_done.notify_all()

    def done_count(self) -> int:
        """Frames analysed so far."""
        with self._lock:
            return len(self._done)

    def wait(self, timeout_s: float | None = None) -> dict[int, FrameSummary]:
        """Every summary (index -> summary), waiting for the workers.

        Frames whose analysis failed, whose worker died, or that are still
        unfinished after ``timeout_s`` seconds are analysed here, in this process.
        """
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        with self._lock:
            while self._resubmitting or any(not f.done() for f, _, _ in self._pending.values()):
                left = 1.0 if deadline is None else deadline - time.monotonic()
                if left <= 0:
                    break
                self._all_done.wait(min(left, 1.0))
            leftovers = sorted(self._pending.items())
        for index, (future, rail_mm, path) in leftovers:
            with self._lock:
                if index in self._done:
                    continue
            error = None
            if future.done() and not future.cancelled():
                error = future.exception()
            else:
                future.cancel()
            if future.done() and not future.cancelled() and error is None:
                summary = future.result()
            else:
                summary = self._local(index, rail_mm, path)
            with self._lock:
                if index in self._done:
                    continue
                self._done[index] = summary
                self._pending.pop(index, None)
            if self._on_summary is not None:
                self._on_summary(summary)
        with self._lock:
            return dict(self._done)

    def _local(self, index: int, rail_mm: float, path: str) -> FrameSummary:
        try:
            image = read_image(path, expected_shape=self._shape, bit_depth=self._bit_depth)
            return self._analyzer.analyze(index, rail_mm, image)
        except Exception as exc:  # noqa: BLE001 - an analysis failure is a frame's error
            geometry = self._analyzer.geometry
            return FrameSummary(
                index=index,
                rail_mm=rail_mm,
                object_distance_mm=geometry.object_distance_mm(rail_mm),
                error=f"analysis failed: {exc}",
            )

    def combine(self, summaries: list[FrameSummary], geometry: SweepGeometry) -> dict[str, Any]:
        """The calibration result (``CalibrationResult.to_dict()``) of ``summaries``.

        Runs :func:`calibration.pipeline.combine` in a worker process: its least-squares
        fits are seconds of Python-level work that would otherwise hold this process's
        GIL while the HTTP server answers pollers. Falls back to this process if the pool
        is unavailable. Raises :class:`CalibrationError` as ``combine`` does.
        """
        try:
            future = self._pool.executor().submit(
                _combine_remote, self._key, self._blob, summaries, geometry
            )
            status, payload = future.result()
        except (BrokenProcessPool, RuntimeError) as exc:  # pool broken or shut down
            self._pool.reset(None, f"the final calibration's worker process failed ({exc})")
            with single_blas_thread():
                return combine(summaries, geometry, self._analyzer.grid).to_dict()
        if status == "ok":
            return dict(payload)
        cls, message, partial = payload
        raise cls(message, partial)

    def cancel(self) -> None:
        """Cancel the frames not started yet (the job stops without a result)."""
        with self._lock:
            self._cancelled = True
            futures = [f for f, _, _ in self._pending.values()]
        for f in futures:
            f.cancel()


__all__ = ["AnalysisPool", "AnalysisSession", "default_workers", "summary_from_dict"]
