"""The archive writer thread: frames go to disk while the rail already moves on.

The hardware thread hands each grabbed frame to :meth:`FrameWriter.put` (a
bounded queue: when the disk is slower than the sweep, ``put`` waits, so at
most ``maxsize`` frames are ever held in memory). The writer thread, for each
frame in order:

1. :meth:`calibration.archive.SweepWriter.add_frame` -- PNG to a temporary
   file, ``fsync``, rename, manifest rewritten atomically (free space checked
   *before* writing: :class:`calibration.archive.DiskFull`);
2. :meth:`station.store.JobStore.record_step` -- the step row (SQLite commit);
3. ``on_written(step)`` -- analysis submission, progress, ``step`` event.

PNG compression adapts to the load: zlib level 1 (the archive's default,
~40 % smaller files) while the writer keeps up, level 0 (stored, about twice
as fast to write) for a frame that has others waiting behind it, so a fast
camera never waits for the compressor. Readers see ordinary PNG files either way.

The first error stops the writer: later frames are not written (they were
never recorded, so a resumed job captures them again) and :attr:`error` holds
the error for the hardware thread, which checks it at every step boundary.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from calibration.archive import SweepWriter
from station.store import JobStore, StepRecord


@dataclass
class CapturedFrame:
    """A grabbed frame on its way to the archive.

    Attributes:
        index: frame index in the sweep.
        commanded_mm: commanded rail position (mm).
        actual_mm: read-back rail position (mm); the manifest's ``rail_mm``.
        pixels: the raw counts ``(height, width)``.
        started_at: Unix time (s) the step's move started.
        captured_at: Unix time (s) the frame arrived.
        extra: more manifest keys (frame id, exposure ...), JSON-ready.
    """

    index: int
    commanded_mm: float
    actual_mm: float
    pixels: np.ndarray
    started_at: float
    captured_at: float
    extra: dict[str, Any] = field(default_factory=dict)


_STOP = object()


class FrameWriter:
    """Writes captured frames in order on its own thread (see the module docstring).

    Args:
        writer: the job's archive writer.
        store: the job store.
        job_id: the job.
        on_written: called on the writer thread after each recorded step.
        maxsize: frames that may wait in memory.
        compression: zlib level used while the writer keeps up (0..9).
    """

    def __init__(
        self,
        writer: SweepWriter,
        store: JobStore,
        job_id: int,
        *,
        on_written: Callable[[StepRecord], None] | None = None,
        maxsize: int = 2,
        compression: int = 1,
    ) -> None:
        self._writer = writer
        self._compression = compression
        self._store = store
        self._job_id = job_id
        self._on_written = on_written
        self._queue: queue.Queue[Any] = queue.Queue(maxsize)
        self._error: BaseException | None = None
        self._idle = threading.Condition()
        self._busy = 0
        self._closed = False
        self._thread = threading.Thread(
            target=self._run, name=f"archive-writer-job-{job_id}", daemon=True
        )
        self._thread.start()

    @property
    def error(self) -> BaseException | None:
        """The error that stopped the writer, or None."""
        return self._error

    def put(self, frame: CapturedFrame) -> None:
        """Queue a frame (waits while ``maxsize`` frames are pending).

        Raises the writer's error instead if it has stopped.
        """
        if self._error is not None:
            raise self._error
        with self._idle:
            self._busy += 1
        self._queue.put(frame)

    def drain(self) -> None:
        """Wait until every queued frame is written (or the writer stopped)."""
        with self._idle:
            while self._busy > 0 and self._thread.is_alive():
                self._idle.wait(1.0)

    def close(self) -> None:
        """Write what is queued, stop the thread (idempotent)."""
        if self._closed:
            return
        self._closed = True
        self._queue.put(_STOP)
        self._thread.join()

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is _STOP:
                return
            try:
                if self._error is None:
                    self._write(item)
            except BaseException as exc:  # noqa: BLE001 - reported to the hardware thread
                self._error = exc
            finally:
                with self._idle:
                    self._busy -= 1
                    self._idle.notify_all()

    def _write(self, frame: CapturedFrame) -> None:
        extra = dict(frame.extra)
        extra.update(
            commanded_rail_mm=frame.commanded_mm,
            started_at=frame.started_at,
            captured_at=frame.captured_at,
        )
        # frames waiting behind this one: store uncompressed (twice as fast)
        self._writer.compression = 0 if self._queue.qsize() > 0 else self._compression
        record = self._writer.add_frame(frame.index, frame.actual_mm, frame.pixels, **extra)
        step = StepRecord(
            job_id=self._job_id,
            index=frame.index,
            commanded_mm=frame.commanded_mm,
            actual_mm=frame.actual_mm,
            file=record.file,
            sha256=record.sha256,
            started_at=frame.started_at,
            captured_at=frame.captured_at,
            written_at=time.time(),
        )
        self._store.record_step(step)
        if self._on_written is not None:
            self._on_written(step)


__all__ = ["CapturedFrame", "FrameWriter"]
