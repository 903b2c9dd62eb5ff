"""``lfcal recalibrate``: run the calibration again over stored archives on a Dask cluster.

::

    lfcal recalibrate (--config FILE | --database DB) [--station S ...] [--since DATE]
                      [--all] [--scheduler tcp://HOST:PORT] [--workers N] [--json]

Which jobs: every succeeded job (of every station, or of ``--station``; created on
or after ``--since``, a date or date-time in UTC) whose archive is on a local disk
or in object storage, except -- unless ``--all`` -- those that already have a
result of this software version (so an interrupted batch continues where it
stopped).

Where: on the Dask distributed scheduler ``--scheduler``, else on a LocalCluster of
``--workers`` processes (default 2, one thread each) on 127.0.0.1 with the dashboard
off. Each task reads the archive through :mod:`station.archive_source` (the local
directory when the worker sees it, else a download from object storage into the
worker's cache, checked against the stored SHA-256) and runs
:func:`calibration.pipeline.calibrate_archive` on it in the worker process.

What: every new result is stored as a new version beside the old ones
(:mod:`station.result_versions`: software version, date); a table shows for each
job the previous and the new a, b, Q and focus plane with the change. Exit codes: 0
every job recalibrated (or none to do), 1 some failed (listed), 2 bad input
(configuration, database or object store unreachable, bad date, scheduler not
reachable).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import logging
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

from station.store import JobRecord, JobState, JobStore

EXIT_OK = 0
EXIT_FAILED = 1
EXIT_BAD_INPUT = 2

COMPARED = (
    ("a (mm)", ("a_mm",)),
    ("b (mm)", ("b_mm",)),
    ("Q", ("Q",)),
    ("focus u (mm)", ("focus", "object_distance_mm")),
)
"""Result values shown in the change table: label, path in the result JSON."""


@dataclass
class TaskOutcome:
    """What one recalibration task returned (plain data: it crosses processes)."""

    job_id: int
    result: dict[str, Any] | None
    error: str | None
    seconds: float
    worker: str = ""
    cpu_s: float = 0.0


@dataclass
class Recalibrated:
    """One job's line of the change table."""

    job: JobRecord
    outcome: TaskOutcome
    previous: dict[str, Any] | None
    previous_software: str | None
    version: int | None = None
    changes: dict[str, tuple[float | None, float | None]] = field(default_factory=dict)


def recalibrate_task(
    job_id: int,
    archive_dir: str,
    archive_url: str | None,
    cache_dir: str,
    s3_settings: dict[str, Any] | None,
) -> TaskOutcome:
    """Calibrate one archive again (runs on a Dask worker; plain arguments and result)."""
    import os
    import socket

    from calibration.pipeline import CalibrationError, calibrate_archive
    from station.archive_source import fetch_archive

    started = time.perf_counter()
    cpu = time.process_time()
    worker = f"{socket.gethostname()}:{os.getpid()}"
    try:
        local = Path(archive_dir)
        if not (local / "sweep.json").is_file():
            if not archive_url:
                raise FileNotFoundError(f"the archive {archive_dir} is not on this machine")
            local = fetch_archive(archive_url, Path(cache_dir), settings=s3_settings)
        result = calibrate_archive(local, workers=1).to_dict()
        return TaskOutcome(
            job_id, result, None, time.perf_counter() - started, worker,
            time.process_time() - cpu,
        )  # fmt: skip
    except CalibrationError as exc:
        error = f"calibration failed: {exc}"
    except Exception as exc:  # noqa: BLE001 - reported per job, the batch goes on
        error = f"{type(exc).__name__}: {exc}"
    return TaskOutcome(
        job_id, None, error, time.perf_counter() - started, worker, time.process_time() - cpu
    )


def _value(result: dict[str, Any] | None, path: tuple[str, ...]) -> float | None:
    node: Any = result
    for key in path:
        if not isinstance(node, dict):
            return None
        node = node.get(key)
    return float(node) if isinstance(node, int | float) else None


def parse_since(text: str) -> float:
    """``2025-01-31`` or ``2025-01-31T12:00[:00]`` (UTC unless an offset is given) -> Unix s."""
    try:
        when = dt.datetime.fromisoformat(text)
    except ValueError:
        raise ValueError(f"--since: not a date (YYYY-MM-DD[THH:MM[:SS]]): {text!r}") from None
    if when.tzinfo is None:
        when = when.replace(tzinfo=dt.UTC)
    return when.timestamp()


def select_jobs(
    store: JobStore,
    *,
    stations: Sequence[str] | None = None,
    since: float | None = None,
    include_done: bool = False,
    software_version: str | None = None,
) -> list[JobRecord]:
    """The succeeded jobs to recalibrate (see the module docstring)."""
    from station.result_versions import jobs_with_software

    jobs: list[JobRecord] = []
    for station in stations or [None]:  # type: ignore[list-item]
        jobs.extend(store.list_jobs(states={JobState.SUCCEEDED}, station=station, since=since))
    jobs.sort(key=lambda j: j.id)
    if not include_done and software_version is not None:
        done = jobs_with_software(store, software_version)
        jobs = [j for j in jobs if j.id not in done]
    return [j for j in jobs if (j.archive_dir / "sweep.json").is_file() or j.archive_url]


def open_client(scheduler: str | None, workers: int) -> tuple[Any, Any]:
    """A Dask client on ``scheduler``, else on a new LocalCluster (127.0.0.1, no
    dashboard); returns ``(client, cluster or None)``."""
    from distributed import Client, LocalCluster

    if scheduler:
        return Client(scheduler, timeout="10s"), None
    cluster = LocalCluster(
        n_workers=workers,
        threads_per_worker=1,
        processes=True,
        host="127.0.0.1",
        dashboard_address=None,
        silence_logs=logging.ERROR,
    )
    return Client(cluster), cluster


def run_recalibration(
    store: JobStore,
    jobs: Sequence[JobRecord],
    *,
    client: Any,
    cache_dir: Path,
    s3_settings: dict[str, Any] | None = None,
    on_done: Callable[[Recalibrated], None] | None = None,
) -> list[Recalibrated]:
    """Recalibrate ``jobs`` on the Dask ``client`` and store each new result as a new
    version; returns the change table's lines in job order."""
    from distributed import as_completed

    from station.result_versions import add_result_version, latest_result

    previous = {job.id: latest_result(store, job.id) for job in jobs}
    futures = [
        client.submit(
            recalibrate_task,
            job.id,
            str(job.archive_dir),
            job.archive_url,
            str(cache_dir),
            s3_settings,
            key=f"recalibrate-job-{job.id}-{time.time_ns()}",
            pure=False,
        )
        for job in jobs
    ]
    by_id = {job.id: job for job in jobs}
    lines: dict[int, Recalibrated] = {}
    for future in as_completed(futures):
        outcome: TaskOutcome = future.result()
        job = by_id[outcome.job_id]
        before = previous.get(job.id)
        line = Recalibrated(
            job,
            outcome,
            None if before is None else before.result,
            None if before is None else before.software_version,
        )
        if outcome.result is not None:
            stored = add_result_version(store, job.id, outcome.result)
            line.version = stored.version
            for label, path in COMPARED:
                line.changes[label] = (_value(line.previous, path), _value(outcome.result, path))
        lines[job.id] = line
        if on_done is not None:
            on_done(line)
    return [lines[j.id] for j in jobs]


def _num(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.5f}"


def change_table(lines: Sequence[Recalibrated]) -> str:
    """What changed, one row per job (old -> new, and the difference)."""
    head = ["job", "station", "camera", "software", "version"]
    head += [label for label, _ in COMPARED]
    rows = [head]
    for line in lines:
        new_sw = (line.outcome.result or {}).get("software", {}).get("version", "?")
        row = [
            str(line.job.id),
            line.job.station_id or "-",
            line.job.camera_serial or "-",
            f"{line.previous_software or '-'} -> {new_sw if line.outcome.result else 'failed'}",
            "-" if line.version is None else str(line.version),
        ]
        for label, _ in COMPARED:
            old, new = line.changes.get(label, (None, None))
            if line.outcome.result is None:
                row.append("-")
            elif old is None or new is None:
                row.append(f"{_num(old)} -> {_num(new)}")
            else:
                row.append(f"{_num(old)} -> {_num(new)} ({new - old:+.5f})")
        rows.append(row)
    widths = [max(len(r[i]) for r in rows) for i in range(len(head))]
    out = ["  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip() for r in rows]
    for line in lines:
        if line.outcome.error:
            out.append(f"job {line.job.id}: {line.outcome.error}")
    return "\n".join(out)


def _progress(err: TextIO, line: Recalibrated) -> None:
    err.write(
        f"  job {line.job.id}: {'done' if line.outcome.result else 'FAILED'} "
        f"in {line.outcome.seconds:.1f} s on {line.outcome.worker}\n"
    )


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="lfcal recalibrate",
        description="run the calibration again over stored archives on a Dask cluster",
    )
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--config", help="station configuration (its [storage])")
    src.add_argument("--database", help="job database: SQLite file or postgresql:// URL")
    p.add_argument("--station", action="append", help="only this station's jobs (repeatable)")
    p.add_argument("--since", help="only jobs created on or after this date (UTC)")
    p.add_argument(
        "--all",
        action="store_true",
        help="also jobs that already have a result of this software version",
    )
    p.add_argument("--scheduler", help="Dask scheduler tcp://HOST:PORT (default: a LocalCluster)")
    p.add_argument("--workers", type=int, default=2, help="LocalCluster worker processes")
    p.add_argument("--cache-dir", help="where archives from object storage are kept")
    p.add_argument("--json", action="store_true", help="print the outcome as JSON")
    return p


def recalibrate_main(argv: Sequence[str] | None = None, out: TextIO | None = None) -> int:
    """``lfcal recalibrate`` (see the module docstring); returns the exit code."""
    from calibration.version import software_version
    from station.config import load_config_or_report
    from station.db import StoreError

    out = out or sys.stdout
    err = sys.stderr
    args = _parser().parse_args(list(sys.argv[1:] if argv is None else argv))
    if args.workers < 1:
        err.write("lfcal recalibrate: --workers must be at least 1\n")
        return EXIT_BAD_INPUT
    try:
        since = None if args.since is None else parse_since(args.since)
    except ValueError as exc:
        err.write(f"lfcal recalibrate: {exc}\n")
        return EXIT_BAD_INPUT
    s3_settings: dict[str, Any] | None = None
    cache_dir = Path(args.cache_dir) if args.cache_dir else None
    if args.config:
        config = load_config_or_report(args.config, "lfcal recalibrate", err)
        if config is None:
            return EXIT_BAD_INPUT
        database: str | Path = config.storage.database
        s3_settings = config.storage.s3.model_dump()
        cache_dir = cache_dir or config.storage.cache_dir
    else:
        database = args.database
    cache_dir = cache_dir or Path.home() / ".cache" / "lfcal" / "archives"
    try:
        store = JobStore(database, station_id="")
    except StoreError as exc:
        err.write(f"lfcal recalibrate: {exc}\n")
        return EXIT_BAD_INPUT
    try:
        software = software_version()
        jobs = select_jobs(
            store,
            stations=args.station,
            since=since,
            include_done=args.all,
            software_version=software,
        )
        if not jobs:
            out.write(f"nothing to recalibrate (software {software}; --all to redo)\n")
            return EXIT_OK
        try:
            client, cluster = open_client(args.scheduler, args.workers)
        except (OSError, TimeoutError) as exc:
            err.write(
                f"lfcal recalibrate: the Dask scheduler {args.scheduler} is unreachable: {exc}\n"
            )
            return EXIT_BAD_INPUT
        where = args.scheduler or f"a LocalCluster of {args.workers} workers on 127.0.0.1"
        err.write(f"lfcal recalibrate: {len(jobs)} archives on {where} (software {software})\n")
        started = time.perf_counter()
        try:
            lines = run_recalibration(
                store,
                jobs,
                client=client,
                cache_dir=Path(cache_dir),
                s3_settings=s3_settings,
                on_done=lambda line: _progress(err, line),
            )
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
        elapsed = time.perf_counter() - started
        failed = [line for line in lines if line.outcome.result is None]
        if args.json:
            payload = [
                {
                    "job_id": line.job.id,
                    "station_id": line.job.station_id,
                    "camera_serial": line.job.camera_serial,
                    "version": line.version,
                    "software_version": software if line.outcome.result else None,
                    "previous_software_version": line.previous_software,
                    "changes": {k: list(v) for k, v in line.changes.items()},
                    "error": line.outcome.error,
                    "seconds": line.outcome.seconds,
                }
                for line in lines
            ]
            out.write(json.dumps(payload, indent=1) + "\n")
        else:
            out.write(change_table(lines) + "\n")
            out.write(
                f"{len(lines) - len(failed)} of {len(lines)} recalibrated in {elapsed:.1f} s "
                f"({len(lines) / elapsed:.2f} archives/s)\n"
            )
        return EXIT_FAILED if failed else EXIT_OK
    except StoreError as exc:
        err.write(f"lfcal recalibrate: {exc}\n")
        return EXIT_BAD_INPUT
    finally:
        store.close()


__all__ = [
    "Recalibrated",
    "TaskOutcome",
    "change_table",
    "open_client",
    "parse_since",
    "recalibrate_main",
    "recalibrate_task",
    "run_recalibration",
    "select_jobs",
]
