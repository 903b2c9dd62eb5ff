"""``lfcal sweep`` and ``lfcal jobs``: run a sweep job without the server, list stored jobs.

``sweep_main(argv)``::

    lfcal sweep --config FILE [--start MM --stop MM --step MM] [--exposure-us US]
                [--settle-s S] [--no-calibrate] [--resume JOB] [--emulator-speedup X]
                [--sim-frame-cache DIR] [--quiet]

runs one job on the station of ``FILE`` (its devices, its job database) and
shows a progress bar on the terminal (one line per frame when the output is
not a terminal). Ctrl-C stops the job at the next step boundary; it is then
``interrupted`` and ``--resume JOB`` continues it. Exit codes: 0 succeeded, 1
failed or cancelled, 2 bad input (with every problem listed), 3 another
station process holds the database, 130 interrupted.

``jobs_main(argv)``::

    lfcal jobs [--config FILE | --db DATABASE] [--state STATE ...] [--station S]
               [--camera-serial SERIAL] [--json] [JOB [--results]]

lists the stored jobs (id, station, camera, state, frames, created, archive, last
error) of every station sharing the database (the fleet view; ``--station`` and
``--camera-serial`` filter); with ``JOB`` shows one job with its transitions, and
with ``--results`` every version of its result (the station's and each
``lfcal recalibrate``'s, with software version and date). ``--db`` takes a SQLite
file or a ``postgresql://`` URL. It only reads the database (after bringing its
schema up to date).
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

if TYPE_CHECKING:
    from station.events import JobEvent

EXIT_OK = 0
EXIT_FAILED = 1
EXIT_BAD_INPUT = 2
EXIT_BUSY = 3
EXIT_INTERRUPTED = 130


# --------------------------------------------------------------------------- progress


def _duration(seconds: float | None) -> str:
    if seconds is None:
        return "--:--"
    seconds = max(0, int(round(seconds)))
    h, rest = divmod(seconds, 3600)
    m, s = divmod(rest, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


class ProgressBar:
    """A one-line progress bar on a terminal; one line per frame otherwise."""

    def __init__(self, out: TextIO, *, width: int = 30) -> None:
        self.out = out
        self.width = width
        self.tty = bool(getattr(out, "isatty", lambda: False)())
        self._last = ""

    def frame(
        self,
        job_id: int,
        done: int,
        total: int,
        rail_mm: float | None,
        eta_s: float | None,
        phase: str = "sweeping",
    ) -> None:
        """Show ``done`` of ``total`` frames, the rail position (mm) and the ETA (s)."""
        rail = "" if rail_mm is None else f" rail {rail_mm:8.3f} mm"
        if self.tty:
            filled = int(self.width * done / total) if total else 0
            bar = "#" * filled + "." * (self.width - filled)
            line = f"\rjob {job_id} [{bar}] {done}/{total}{rail} ETA {_duration(eta_s)} {phase}"
            self.out.write(line.ljust(len(self._last)))
            self._last = line
        else:
            self.out.write(f"job {job_id}: frame {done}/{total}{rail} ETA {_duration(eta_s)}\n")
        self.out.flush()

    def message(self, text: str) -> None:
        """A line of its own (ends the bar's line on a terminal)."""
        if self.tty and self._last:
            self.out.write("\n")
            self._last = ""
        self.out.write(text + "\n")
        self.out.flush()


# --------------------------------------------------------------------------- sweep


def _sweep_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="lfcal sweep", description="run one calibration sweep job without the server"
    )
    p.add_argument("--config", required=True, help="station configuration (TOML)")
    p.add_argument("--start", type=float, default=None, help="first rail position (mm)")
    p.add_argument("--stop", type=float, default=None, help="last rail position (mm)")
    p.add_argument("--step", type=float, default=None, help="rail step (mm)")
    p.add_argument("--exposure-us", type=float, default=None, help="exposure (µs)")
    p.add_argument("--settle-s", type=float, default=None, help="wait after each move (s)")
    p.add_argument("--no-calibrate", action="store_true", help="acquire only, no calibration")
    p.add_argument(
        "--resume",
        type=int,
        default=None,
        metavar="JOB",
        help="continue an interrupted or failed job instead of starting one",
    )
    p.add_argument(
        "--emulator-speedup",
        type=float,
        default=1.0,
        help="emulated stages move this many times faster (simulation only)",
    )
    p.add_argument(
        "--sim-frame-cache",
        default=None,
        metavar="DIR",
        help="simulated camera only: reuse rendered frames from DIR (sets [camera] frame_cache)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress output")
    return p


def _print_result(out: TextIO, result: dict[str, Any]) -> None:
    focus = result.get("focus") or {}
    unc = result.get("uncertainty") or {}
    rows = [
        ("a (mm)", result.get("a_mm"), unc.get("a_mm")),
        ("b (mm)", result.get("b_mm"), unc.get("b_mm")),
        ("Q = b/a", result.get("Q"), unc.get("Q")),
        ("patch size p (px)", result.get("patch_size_px"), unc.get("patch_size_px")),
        ("focus plane u (mm)", focus.get("object_distance_mm"), focus.get("uncertainty_mm")),
        ("focus rail position (mm)", focus.get("rail_mm"), focus.get("uncertainty_mm")),
    ]
    for name, value, se in rows:
        v = "n/a" if not isinstance(value, int | float) else f"{value:.5f}"
        s = "" if not isinstance(se, int | float) else f" ± {se:.5f}"
        out.write(f"  {name:26s} {v}{s}\n")
    for w in result.get("warnings", []):
        out.write(f"  warning: {w}\n")


def _sweep_request(args: argparse.Namespace) -> dict[str, Any]:
    """The sweep request of ``lfcal sweep``'s options (only those given)."""
    request: dict[str, Any] = {}
    for key, value in (
        ("start_mm", args.start),
        ("stop_mm", args.stop),
        ("step_mm", args.step),
        ("exposure_us", args.exposure_us),
        ("settle_s", args.settle_s),
    ):
        if value is not None:
            request[key] = value
    if args.no_calibrate:
        request["calibrate"] = False
    return request


class _JobFollower:
    """Follows one job's events (set :attr:`job_id` once known): progress on the bar
    (unless ``quiet``), :attr:`finished` set when the job reaches a final state."""

    def __init__(self, bar: ProgressBar, *, quiet: bool) -> None:
        self.bar = bar
        self.quiet = quiet
        self.job_id: int | None = None
        self.finished = threading.Event()

    def on_event(self, event: JobEvent) -> None:
        """An event listener (:meth:`station.orchestrator.Orchestrator.add_listener`)."""
        if self.job_id is None or event.job_id != self.job_id:
            return
        if not self.quiet:
            self._show(event)
        if event.type == "state":
            from station.orchestrator import FINAL_STATES
            from station.store import JobState

            if JobState(event.data["state"]) in FINAL_STATES:
                self.finished.set()

    def _show(self, event: JobEvent) -> None:
        bar = self.bar
        if event.type == "step":
            d = event.data
            bar.frame(
                event.job_id, d["frames_done"], d["frames_total"], d["actual_mm"], d.get("eta_s")
            )
        elif event.type == "phase" and event.data["phase"] != "sweeping":
            detail = f": {event.data['detail']}" if event.data.get("detail") else ""
            bar.message(f"job {event.job_id}: {event.data['phase']}{detail}")
        elif event.type == "fault":
            bar.message(f"job {event.job_id}: recovered from {event.data['error']}")
        elif event.type == "state":
            bar.message(f"job {event.job_id}: {event.data['state']} ({event.data['reason']})")


def sweep_main(argv: Sequence[str] | None = None) -> int:
    """``lfcal sweep``: run (or resume) one job; returns the exit code."""
    from station.config import load_config_or_report, with_frame_cache
    from station.orchestrator import FINAL_STATES, Orchestrator, StationBusy
    from station.store import InvalidTransition, JobNotFound, StoreError
    from station.sweep import RequestInvalid

    args = _sweep_parser().parse_args(list(sys.argv[1:] if argv is None else argv))
    out, err = sys.stdout, sys.stderr
    config = load_config_or_report(args.config, "lfcal sweep", err)
    if config is None:
        return EXIT_BAD_INPUT
    if not args.emulator_speedup > 0:
        err.write("lfcal sweep: --emulator-speedup must be positive\n")
        return EXIT_BAD_INPUT
    request = _sweep_request(args)
    station = Orchestrator(
        with_frame_cache(config, args.sim_frame_cache),
        emulator_speedup=args.emulator_speedup,
        run_queued=False,
    )
    try:
        station.start()
    except StationBusy as exc:
        err.write(f"lfcal sweep: {exc}\n")
        return EXIT_BUSY
    except StoreError as exc:  # database or object store unreachable, schema too new
        err.write(f"lfcal sweep: {exc}\n")
        return EXIT_BAD_INPUT
    bar = ProgressBar(err)
    follow = _JobFollower(bar, quiet=args.quiet)
    finished = follow.finished
    job_id: int | None = None
    interrupted = False
    previous = signal.getsignal(signal.SIGINT)
    try:
        station.add_listener(follow.on_event)
        try:
            if args.resume is not None:
                job_id = follow.job_id = args.resume
                status = station.resume(args.resume, "resumed from the command line")
            else:
                status = station.submit(request)
                job_id = follow.job_id = status.id
        except RequestInvalid as exc:
            err.write("lfcal sweep: the sweep cannot run:\n")
            for field, message in exc.problems:
                err.write(f"  {field}: {message}\n")
            return EXIT_BAD_INPUT
        except (InvalidTransition, JobNotFound) as exc:
            err.write(f"lfcal sweep: {exc}\n")
            return EXIT_BAD_INPUT
        if not args.quiet:
            bar.message(f"job {job_id}: {status.frames_total} frames, archive {status.archive_dir}")
        if station.status(job_id).state in FINAL_STATES:
            finished.set()
        try:
            while not finished.wait(0.5):
                if station.status(job_id).state in FINAL_STATES:
                    break
        except KeyboardInterrupt:
            interrupted = True
            signal.signal(signal.SIGINT, signal.SIG_IGN)
            bar.message(f"job {job_id}: stopping at the next step boundary (Ctrl-C) ...")
            station.close()
    finally:
        station.close()
        signal.signal(signal.SIGINT, previous)
    assert job_id is not None
    return _report(config, job_id, out, err, interrupted)


def _report(config: Any, job_id: int, out: TextIO, err: TextIO, interrupted: bool) -> int:
    from station.ownership import open_store
    from station.store import JobState

    with open_store(config) as store:
        job = store.get_job(job_id, with_result=True)
        frames = store.step_count(job_id)
    out.write(
        f"job {job.id}: {job.state.value}, {frames} of {job.frames_total} frames in "
        f"{job.archive_dir}\n"
    )
    if job.state is JobState.SUCCEEDED:
        if job.result is not None:
            _print_result(out, job.result)
        return EXIT_OK
    if job.last_error:
        err.write(f"lfcal sweep: {job.last_error}\n")
    if job.state is JobState.INTERRUPTED or interrupted:
        err.write(f"lfcal sweep: resume with: lfcal sweep --config FILE --resume {job.id}\n")
        return EXIT_INTERRUPTED
    return EXIT_FAILED


# --------------------------------------------------------------------------- jobs


def _jobs_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="lfcal jobs", description="list the stored sweep jobs")
    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument("--config", help="station configuration (its [storage] database)")
    where.add_argument("--db", help="the job database: a SQLite file or a postgresql:// URL")
    p.add_argument(
        "--state", action="append", default=None, help="only jobs in this state (repeatable)"
    )
    p.add_argument("--station", default=None, help="only jobs of this station")
    p.add_argument("--camera-serial", default=None, help="only jobs of the camera with this serial")
    p.add_argument("--results", action="store_true", help="with JOB: every version of its result")
    p.add_argument("--json", action="store_true", help="JSON output")
    p.add_argument("job", nargs="?", type=int, help="show this job with its transitions")
    return p


def _job_dict(job: Any, frames: int, alive: bool | None = None) -> dict[str, Any]:
    return {
        "id": job.id,
        "station_id": job.station_id,
        "station_alive": alive,
        "camera_serial": job.camera_serial,
        "state": job.state.value,
        "frames_done": frames,
        "frames_total": job.frames_total,
        "created_at": job.created_at,
        "archive_dir": str(job.archive_dir),
        "archive_url": job.archive_url,
        "archive_uploaded_at": job.archive_uploaded_at,
        "last_error": job.last_error,
    }


def _show_results(store: Any, job_id: int, as_json: bool, out: TextIO) -> int:
    from station.result_versions import result_versions

    versions = result_versions(store, job_id, with_results=True)
    if as_json:
        out.write(json.dumps([v.to_dict() for v in versions], indent=1) + "\n")
        return EXIT_OK
    if not versions:
        out.write(f"job {job_id}: no result\n")
        return EXIT_OK
    for v in versions:
        result = v.result or {}
        focus = result.get("focus") or {}
        values = "  ".join(
            f"{name} {val:.5f}"
            for name, val in (
                ("a", result.get("a_mm")),
                ("b", result.get("b_mm")),
                ("focus", focus.get("object_distance_mm")),
            )
            if isinstance(val, int | float)
        )
        out.write(
            f"  version {v.version}  {v.source:<11} software {v.software_version:<12} "
            f"{_when(v.created_at)}  {values}\n"
        )
    return EXIT_OK


def _when(t: float) -> str:
    return time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(t))


def _jobs_database(args: argparse.Namespace, err: TextIO) -> str | Path | None:
    """The database of ``--db`` or of ``--config``'s station; None (reported) when unusable."""
    from station.db_postgres import is_postgres_url

    db: str | Path
    if args.db is not None:
        db = args.db if is_postgres_url(args.db) else Path(args.db)
    else:
        from station.config import load_config_or_report

        config = load_config_or_report(args.config, "lfcal jobs", err)
        if config is None:
            return None
        db = config.storage.database
    if isinstance(db, Path) and not db.is_file():
        err.write(f"lfcal jobs: no job database at {db} (no job has run yet)\n")
        return None
    return db


def _job_detail(job: Any, frames: int, transitions: list[Any]) -> dict[str, Any]:
    """One job with its sweep and transitions (``lfcal jobs --json JOB``)."""
    return {
        **_job_dict(job, frames),
        "request": job.request,
        "updated_at": job.updated_at,
        "has_result": job.has_result,
        "transitions": [
            {
                "from": t.from_state.value if t.from_state else None,
                "to": t.to_state.value,
                "at": t.at,
                "reason": t.reason,
            }
            for t in transitions
        ],
    }


def _show_job(store: Any, args: argparse.Namespace, out: TextIO, err: TextIO) -> int:
    """``lfcal jobs JOB [--results]``: one job with its transitions (or its results)."""
    from station.store import JobNotFound, JobState

    try:
        job = store.get_job(args.job, with_result=True)
    except JobNotFound as exc:
        err.write(f"lfcal jobs: {exc}\n")
        return EXIT_BAD_INPUT
    if args.results:
        return _show_results(store, job.id, args.json, out)
    frames = store.step_count(job.id)
    transitions = store.transitions(job.id)
    if args.json:
        out.write(json.dumps(_job_detail(job, frames, transitions), indent=1) + "\n")
        return EXIT_OK
    out.write(f"job {job.id}: {job.state.value}, {frames}/{job.frames_total} frames\n")
    out.write(f"  station: {job.station_id or '-'}, camera {job.camera_serial or '-'}\n")
    out.write(f"  sweep: {json.dumps(job.request)}\n")
    out.write(f"  archive: {job.archive_dir}\n")
    if job.archive_url:
        uploaded = "uploaded" if job.archive_uploaded_at else "not completely uploaded yet"
        out.write(f"  archive URL: {job.archive_url} ({uploaded})\n")
    if job.last_error:
        out.write(f"  last error: {job.last_error}\n")
    for t in transitions:
        frm = t.from_state.value if t.from_state else "-"
        out.write(f"  {_when(t.at)}  {frm:>11} -> {t.to_state.value:<11} {t.reason}\n")
    if job.result is not None and job.state is JobState.SUCCEEDED:
        _print_result(out, job.result)
    return EXIT_OK


def _query_jobs(
    store: Any, states: set[Any] | None, args: argparse.Namespace
) -> tuple[list[Any], dict[int, int], dict[int, bool | None]]:
    """The matching jobs, their frame counts and whether their stations are alive."""
    from station.ownership import live_stations, station_alive

    jobs = store.list_jobs(states=states, station=args.station, camera_serial=args.camera_serial)
    counts = {j.id: store.step_count(j.id) for j in jobs}
    live = live_stations(store)
    # a reader is no station: liveness only where the database can tell (PostgreSQL)
    alive = {j.id: None if live is None else station_alive(store, j.station_id, live) for j in jobs}
    return jobs, counts, alive


def _print_jobs(
    jobs: list[Any],
    counts: dict[int, int],
    alive: dict[int, bool | None],
    as_json: bool,
    out: TextIO,
) -> int:
    """``lfcal jobs``: the listing as a table (or JSON)."""
    from station.store import ACTIVE_STATES

    if as_json:
        rows = [_job_dict(j, counts[j.id], alive[j.id]) for j in jobs]
        out.write(json.dumps(rows, indent=1) + "\n")
        return EXIT_OK
    if not jobs:
        out.write("no jobs\n")
        return EXIT_OK
    station_w = max(7, *(len(j.station_id) for j in jobs))
    camera_w = max(6, *(len(j.camera_serial or "-") for j in jobs))
    out.write(
        f"{'id':>5}  {'station':<{station_w}}  {'camera':<{camera_w}}  {'state':<11} "
        f"{'frames':>9}  {'created':<19}  archive / last error\n"
    )
    for j in jobs:
        done = f"{counts[j.id]}/{j.frames_total}"
        tail = j.archive_url or str(j.archive_dir)
        if j.state in ACTIVE_STATES and alive[j.id] is False:
            tail += f"  (station {j.station_id} is down: no worker until it restarts)"
        if j.last_error:
            tail += f"  ({j.last_error[:100]})"
        out.write(
            f"{j.id:>5}  {j.station_id or '-':<{station_w}}  {j.camera_serial or '-':<{camera_w}}  "
            f"{j.state.value:<11} {done:>9}  {_when(j.created_at)}  {tail}\n"
        )
    return EXIT_OK


def jobs_main(argv: Sequence[str] | None = None) -> int:
    """``lfcal jobs``: list the stored jobs (or show one); returns the exit code."""
    from station.db import StoreError
    from station.store import JobState, JobStore

    args = _jobs_parser().parse_args(list(sys.argv[1:] if argv is None else argv))
    out, err = sys.stdout, sys.stderr
    db = _jobs_database(args, err)
    if db is None:
        return EXIT_BAD_INPUT
    if args.results and args.job is None:
        err.write("lfcal jobs: --results needs a JOB\n")
        return EXIT_BAD_INPUT
    states = None
    if args.state:
        try:
            states = {JobState(s) for s in args.state}
        except ValueError:
            valid = ", ".join(s.value for s in JobState)
            err.write(f"lfcal jobs: --state must be one of {valid}\n")
            return EXIT_BAD_INPUT
    try:
        store = JobStore(db, station_id="")
    except StoreError as exc:
        err.write(f"lfcal jobs: {exc}\n")
        return EXIT_BAD_INPUT
    with store:
        if args.job is not None:
            return _show_job(store, args, out, err)
        try:
            jobs, counts, alive = _query_jobs(store, states, args)
        except StoreError as exc:
            err.write(f"lfcal jobs: {exc}\n")
            return EXIT_BAD_INPUT
    return _print_jobs(jobs, counts, alive, args.json, out)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m station.jobs_cli sweep|jobs ...`` (until ``lfcal`` wires them)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] not in ("sweep", "jobs"):
        sys.stderr.write("usage: python -m station.jobs_cli sweep|jobs [options]\n")
        return EXIT_BAD_INPUT
    return sweep_main(argv[1:]) if argv[0] == "sweep" else jobs_main(argv[1:])


if __name__ == "__main__":
    sys.exit(main())
