"""Fleet benchmark: batch recalibration on Dask, and the cost of PostgreSQL + S3 per step.

* **Recalibration throughput**: ``--archives`` (default 50) stored small sweeps
  (``lfcal simulate``, ``rotated`` camera, 12 frames of 640×400 px; ``--distinct``
  (default 5) different seeds rendered once into ``out/bench/fleet-sweeps``, each
  stored as several jobs through hard-linked copies) are calibrated again
  (:func:`station.recalibrate.recalibrate_task`, the function every Dask worker
  runs) one after the other in this process, then on a LocalCluster of 2 worker
  processes (127.0.0.1, no dashboard) through :func:`station.recalibrate.run_recalibration`,
  results stored as new versions. The ratio of the throughputs (archives/s) is the
  speed-up; the cluster's start-up is reported on its own line.
* **Per-step overhead** of a sweep (the station's own work per step: the hardware
  thread's time minus move, settle and grab; :class:`station.run_control.StepTiming`) on
  the simulated station (``paper`` preset, 3000×1000 px, ``--steps`` 1 mm steps) with
  SQLite + local disk, then with PostgreSQL + S3 (a throw-away PostgreSQL cluster and
  moto's S3 server on 127.0.0.1, :mod:`bench.fleet_servers`), and how long after the
  job's end its archive is uploaded and verified. Frames are cached in
  ``out/bench/station-frames`` (shared with ``bench_station``).

Run: ``python -m bench fleet`` or ``python -m bench.bench_fleet [--archives N] [--steps N]``.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
SWEEPS = ROOT / "out" / "bench" / "fleet-sweeps"
STATION_FRAMES = ROOT / "out" / "bench" / "station-frames"
TARGET_SPEEDUP = 1.5
"""2 workers on 2 cores should give at least 1.5 times the throughput of one process."""


def _row(name: str, value: float, unit: str, target: float | None = None, *,
         higher_is_better: bool = False) -> dict[str, Any]:  # fmt: skip
    ok = None
    if target is not None:
        ok = bool(value >= target) if higher_is_better else bool(value <= target)
    return {"name": name, "value": float(value), "unit": unit, "target": target, "ok": ok}


def simulated_sweeps(distinct: int) -> list[Path]:
    """``distinct`` small simulated archives (rendered once, then cached)."""
    out = []
    for seed in range(1, distinct + 1):
        path = SWEEPS / f"rotated-640x400-12-seed{seed}"
        if not (path / "sweep.json").is_file():
            subprocess.run(
                [sys.executable, "-m", "station.cli", "simulate", str(path), "--preset",
                 "rotated", "--frames", "12", "--step-mm", "8", "--width", "640", "--height",
                 "400", "--seed", str(seed), "--overwrite"],
                check=True, cwd=ROOT, stdout=subprocess.DEVNULL,
            )  # fmt: skip
        out.append(path)
    return out


def recalibration_rows(archives: int, distinct: int, workers: int) -> list[dict[str, Any]]:
    from station.recalibrate import open_client, recalibrate_task, run_recalibration
    from station.store import JobState, JobStore

    sweeps = simulated_sweeps(distinct)
    with tempfile.TemporaryDirectory(prefix="lfcal-bench-fleet-") as tmp:
        root = Path(tmp)
        store = JobStore(root / "fleet.sqlite3", station_id="bench")
        try:
            for k in range(archives):
                job, _ = store.create_job({}, archive_root=root / "data", frames_total=12)
                shutil.copytree(sweeps[k % len(sweeps)], job.archive_dir, copy_function=os.link)
                store.transition(job.id, JobState.RUNNING, "started")
                store.transition(job.id, JobState.SUCCEEDED, "done", result={"a_mm": 0.0})
            jobs = store.list_jobs(states={JobState.SUCCEEDED})
            t0 = time.perf_counter()
            serial = [
                recalibrate_task(j.id, str(j.archive_dir), None, str(root / "cache"), None)
                for j in jobs
            ]
            one_s = time.perf_counter() - t0
            if any(o.error for o in serial):
                raise RuntimeError(next(o.error for o in serial if o.error))
            t0 = time.perf_counter()
            client, cluster = open_client(None, workers)
            startup_s = time.perf_counter() - t0
            try:
                client.submit(len, [1]).result()  # workers up and importing
                t0 = time.perf_counter()
                lines = run_recalibration(store, jobs, client=client, cache_dir=root / "cache")
                cluster_s = time.perf_counter() - t0
            finally:
                client.close()
                cluster.close()
            failed = [ln for ln in lines if ln.outcome.result is None]
            if failed:
                raise RuntimeError(
                    f"{len(failed)} recalibrations failed: {failed[0].outcome.error}"
                )
            b_values = [float(ln.outcome.result["b_mm"]) for ln in lines if ln.outcome.result]
            cpu_one = statistics.median(o.cpu_s for o in serial)
            cpu_cluster = statistics.median(ln.outcome.cpu_s for ln in lines)
        finally:
            store.close()
    one_rate, cluster_rate = archives / one_s, archives / cluster_s
    return [
        _row(f"recalibrate {archives} archives, one process", one_rate, "1/s"),
        _row(
            f"recalibrate {archives} archives, LocalCluster of {workers} workers",
            cluster_rate,
            "1/s",
        ),  # fmt: skip
        _row(
            f"throughput ratio {workers} workers / one process",
            cluster_rate / one_rate,
            "x",
            TARGET_SPEEDUP,
            higher_is_better=True,
        ),  # fmt: skip
        _row(f"LocalCluster start-up ({workers} workers)", startup_s, "s"),
        _row("CPU time per archive, one process, median", cpu_one, "s"),
        _row("CPU time per archive, on a cluster worker, median", cpu_cluster, "s"),
        _row(
            "load average (1 min) at the end: other work on this machine", os.getloadavg()[0], ""
        ),  # fmt: skip
        _row(
            "recalibrated b spread over the archives (truth 2.45 mm)",
            max(b_values) - min(b_values),
            "mm",
        ),  # fmt: skip
    ]


def _station_config(directory: Path, storage: str, width: int, height: int) -> Path:
    text = (ROOT / "config" / "simulated.toml").read_text(encoding="utf-8")
    for pattern, value in {
        r"^width = \d+": f"width = {width}",
        r"^height = \d+": f"height = {height}",
    }.items():
        text, n = re.subn(pattern, value, text, count=1, flags=re.MULTILINE)
        if n != 1:
            raise RuntimeError(f"config/simulated.toml has no line matching {pattern!r}")
    head, rest = text.split("[storage]", 1)
    after = rest[rest.index("\n[", 1) :] if "\n[" in rest[1:] else ""
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / "station.toml"
    path.write_text(head + "[storage]\n" + storage + after, encoding="utf-8")
    return path


def _sweep_overhead(config_path: Path, steps: int) -> tuple[list[float], float | None, Any]:
    """Per-step overhead (ms) of one sweep, and the upload lag after the job's end (s)."""
    from station.config import load_config, with_frame_cache
    from station.orchestrator import Orchestrator
    from station.store import JobState

    config = load_config(config_path)
    station = Orchestrator(with_frame_cache(config, STATION_FRAMES)).start()
    try:
        start = 50.0 - steps // 2
        job = station.submit(
            {"start_mm": start, "stop_mm": start + steps - 1, "step_mm": 1.0, "calibrate": False}
        )
        done = station.wait_for(job.id, {JobState.SUCCEEDED, JobState.FAILED}, timeout_s=3600)
        if done.state is not JobState.SUCCEEDED:
            raise RuntimeError(f"the benchmark sweep ended {done.state.value}: {done.last_error}")
        ended = time.time()
        lag = None
        if station.uploader is not None:
            deadline = time.monotonic() + 300
            while station.store.get_job(job.id).archive_uploaded_at is None:
                if time.monotonic() > deadline:
                    raise RuntimeError("the archive was not uploaded within 300 s")
                time.sleep(0.05)
            uploaded = station.store.get_job(job.id).archive_uploaded_at
            lag = float(uploaded) - ended if uploaded is not None else None
        overhead = [t.overhead_s * 1000.0 for t in station.step_timings(job.id)]
        status = station.uploader.status() if station.uploader is not None else None
    finally:
        station.close()
    return overhead, lag, status


def _store_latency_ms(database: str | Path, count: int = 200) -> tuple[float, float]:
    """Median time (ms) of ``record_step`` (a committed write) and of a status read."""
    from station.store import JobState, JobStore, StepRecord

    with JobStore(database, station_id="bench-latency") as store:
        job, _ = store.create_job({}, archive_root="/nonexistent", frames_total=count)
        store.transition(job.id, JobState.RUNNING, "started")
        writes, reads = [], []
        for i in range(count):
            step = StepRecord(job.id, i, float(i), float(i), f"frames/{i:04d}.png", "0" * 64,
                              1.0, 1.0, 1.0)  # fmt: skip
            t0 = time.perf_counter()
            store.record_step(step)
            t1 = time.perf_counter()
            store.get_job(job.id)
            store.step_count(job.id)
            t2 = time.perf_counter()
            writes.append((t1 - t0) * 1000.0)
            reads.append((t2 - t1) * 1000.0)
    return statistics.median(writes), statistics.median(reads)


def overhead_rows(steps: int, width: int, height: int) -> list[dict[str, Any]]:
    from bench.fleet_servers import postgres_server, s3_server

    with tempfile.TemporaryDirectory(prefix="lfcal-bench-fleet-") as tmp:
        root = Path(tmp)
        local = _station_config(
            root / "local", 'data_dir = "data"\ndatabase = "data/lfcal.sqlite3"\n', width, height
        )
        base, _, _ = _sweep_overhead(local, steps)
        sqlite_write, sqlite_read = _store_latency_ms(root / "latency.sqlite3")
        with postgres_server(durable=True) as pg, s3_server() as s3:
            pg_write, pg_read = _store_latency_ms(pg.create_database("latency"))
            s3.create_bucket("bench-archives")
            storage = (
                f'data_dir = "data"\ndatabase = "{pg.url()}"\nstation_id = "bench"\n'
                'archive_url = "s3://bench-archives/fleet"\n[storage.s3]\n'
                f'endpoint_url = "{s3.endpoint}"\naccess_key_id = "k"\n'
                'secret_access_key = "s"\nregion = "us-east-1"\n'
            )
            fleet, lag, status = _sweep_overhead(
                _station_config(root / "fleet", storage, width, height), steps
            )
    label = f"{width}x{height}, {steps} steps"
    return [
        _row(
            f"overhead per step, SQLite + local disk ({label}), median",
            statistics.median(base),
            "ms",
            30.0,
        ),  # fmt: skip
        _row(
            f"overhead per step, PostgreSQL + S3 ({label}), median",
            statistics.median(fleet),
            "ms",
            30.0,
        ),  # fmt: skip
        _row(
            "overhead per step, PostgreSQL + S3 minus SQLite + local, median",
            statistics.median(fleet) - statistics.median(base),
            "ms",
        ),  # fmt: skip
        _row(
            f"overhead per step, PostgreSQL + S3 ({label}), p95",
            statistics.quantiles(fleet, n=20, method="inclusive")[-1],
            "ms",
        ),  # fmt: skip
        _row("record_step (committed write), SQLite, median", sqlite_write, "ms"),
        _row(
            "record_step (committed write), PostgreSQL on 127.0.0.1 (fsync on), median",
            pg_write,
            "ms",
        ),  # fmt: skip
        _row("job status read (row + step count), SQLite, median", sqlite_read, "ms"),
        _row("job status read (row + step count), PostgreSQL, median", pg_read, "ms"),
        _row("archive uploaded and verified, after the job's end", lag or 0.0, "s"),
        _row(
            "files uploaded (frames, white, manifest rewrites)",
            float((status or {}).get("files_uploaded", 0)),
            "n",
        ),  # fmt: skip
    ]


def run(
    archives: int = 50,
    distinct: int = 5,
    workers: int = 2,
    steps: int = 20,
    width: int = 3000,
    height: int = 1000,
) -> list[dict[str, Any]]:
    """Rows: name, value, unit, target (None = informative), ok (None = no target)."""
    return recalibration_rows(archives, distinct, workers) + overhead_rows(steps, width, height)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--archives", type=int, default=50)
    parser.add_argument("--distinct", type=int, default=5)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--only", choices=["recalibrate", "overhead"], default=None)
    args = parser.parse_args(argv)
    from bench.__main__ import print_table

    rows: list[dict[str, Any]] = []
    if args.only in (None, "recalibrate"):
        rows += recalibration_rows(args.archives, args.distinct, args.workers)
    if args.only in (None, "overhead"):
        rows += overhead_rows(args.steps, 3000, 1000)
    print_table(rows)
    return 0 if all(r["ok"] is not False for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
