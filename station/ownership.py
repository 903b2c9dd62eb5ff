"""Which station runs which jobs: one process per station, each station its own jobs.

**SQLite** (one station per database file): :class:`FileLock` takes an exclusive
``flock`` on ``DATABASE.lock`` (the holder's pid written in it); a second process
on the same file gets :class:`StationBusy`. The lock dies with the process.

**PostgreSQL** (several stations on one database): every job carries the
``station_id`` of the station that created it, and a station lists, recovers and
runs only its own jobs. :class:`PostgresOwnership` holds a session-level advisory
lock (``pg_try_advisory_lock(OWNERSHIP_KEY, hashtext(station_id))``) on a connection
of its own for the life of the station process: a second process with the same
``station_id`` gets :class:`StationBusy` (the message names the holder's host and
pid from ``pg_stat_activity``); other stations are not affected. When the holder
dies (even ``kill -9``), the server ends its session and the lock is free at once,
so the station restarted on any machine recovers its own jobs (``running`` ->
``interrupted``, frames verified) and nobody else touches them. A watchdog checks
the connection every few seconds and takes the lock again after a database
restart; :attr:`PostgresOwnership.problem` says when it could not.

:func:`open_store` opens the configured job store (schema migrated, station id
and archive URL set).
"""

from __future__ import annotations

import fcntl
import os
import socket
import threading
from pathlib import Path
from typing import Any, Protocol

from station.config import StationConfig
from station.store import InvalidTransition, JobState, JobStore, default_station_id

OWNERSHIP_KEY = 0x6C666373  # "lfcs": first key of the stations' advisory locks
WATCHDOG_INTERVAL_S = 5.0


class StationBusy(RuntimeError):
    """Another process of this station holds the database (one process per station)."""


class ForeignJob(InvalidTransition):
    """A job of another station sharing the database: visible here, never run,
    paused, resumed or cancelled here (the web layer answers 409)."""

    def __init__(self, job_id: int, owner: str, here: str, state: JobState) -> None:
        super().__init__(job_id, state, state, "act")
        self.owner = owner
        self.here = here
        self.args = (
            f"job {job_id} belongs to station {owner!r}, not to this station ({here!r}): "
            f"only station {owner!r} can pause, resume or cancel it",
        )

    def __str__(self) -> str:
        return str(self.args[0])


class Ownership(Protocol):
    """What a started station holds until it closes."""

    def release(self) -> None: ...


def station_id_of(config: StationConfig) -> str:
    """The configured station id, else ``$LFCAL_STATION_ID`` or the host name."""
    return config.storage.station_id or default_station_id()


def open_store(config: StationConfig) -> JobStore:
    """The configured job store (SQLite file or PostgreSQL), schema at head."""
    return JobStore(
        config.storage.database,
        station_id=station_id_of(config),
        archive_url=config.storage.archive_url,
    )


class FileLock:
    """The SQLite station's exclusive lock on ``DATABASE.lock`` (see the module docstring)."""

    def __init__(self, database: Path) -> None:
        self.database = database
        path = database.with_name(database.name + ".lock")
        path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            try:
                holder = os.pread(fd, 64, 0).decode(errors="replace").strip()
            except OSError:
                holder = "?"
            os.close(fd)
            raise StationBusy(
                f"another station process (pid {holder or '?'}) is using the job database "
                f"{database}; stop it, or use another [storage] database"
            ) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        self._fd: int | None = fd

    def release(self) -> None:
        fd, self._fd = self._fd, None
        if fd is not None:
            try:
                fcntl.flock(fd, fcntl.LOCK_UN)
            finally:
                os.close(fd)


class PostgresOwnership:
    """This process owns ``station_id`` on a PostgreSQL job database (module docstring).

    Raises :class:`StationBusy` when another live process owns it,
    :class:`station.db.StoreUnavailable` when the database cannot be reached.
    """

    def __init__(self, url: str, station_id: str, *, connect_timeout_s: float = 5.0) -> None:
        from station.db_postgres import libpq_url, shown_url

        self.url = libpq_url(url)
        self.shown = shown_url(url)
        self.station_id = station_id
        self._connect_s = max(1, int(round(connect_timeout_s)))
        self.label = (f"lfcal-station {station_id} pid {os.getpid()} on {socket.gethostname()}")[
            :63
        ]
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.problem: str | None = None
        self._conn: Any = None
        self._conn = self._take()
        self._watchdog = threading.Thread(
            target=self._watch, name=f"ownership-{station_id}", daemon=True
        )
        self._watchdog.start()

    def _take(self) -> Any:
        import psycopg

        from station.db_postgres import postgres_error

        try:
            conn = psycopg.connect(
                self.url,
                autocommit=True,
                connect_timeout=self._connect_s,
                application_name=self.label,
                keepalives=1,
                keepalives_idle=30,
                keepalives_interval=10,
                keepalives_count=3,
            )
        except psycopg.Error as exc:
            raise postgres_error(exc, self.url, "reach") from exc
        try:
            row = conn.execute(
                "SELECT pg_try_advisory_lock(%s, hashtext(%s))", (OWNERSHIP_KEY, self.station_id)
            ).fetchone()
            got = bool(row and row[0])
            if not got:
                holder = conn.execute(
                    "SELECT a.application_name, a.client_addr::text FROM pg_locks l "
                    "JOIN pg_stat_activity a ON a.pid = l.pid WHERE l.locktype = 'advisory' "
                    "AND l.classid = %s AND l.objid = hashtext(%s)::oid AND l.objsubid = 2",
                    (OWNERSHIP_KEY, self.station_id),
                ).fetchone()
                who = "another process" if holder is None else f"{holder[0]} ({holder[1]})"
                raise StationBusy(
                    f"station {self.station_id!r} is already running on the job database "
                    f"{self.shown}: {who}; stop it, or give this station another "
                    "[storage] station_id"
                )
        except BaseException:
            conn.close()
            raise
        return conn

    def _watch(self) -> None:
        import psycopg

        while not self._stop.wait(WATCHDOG_INTERVAL_S):
            with self._lock:
                conn = self._conn
                try:
                    if conn is None or conn.closed:
                        raise psycopg.OperationalError("connection closed")
                    conn.execute("SELECT 1")
                    continue
                except psycopg.Error:
                    pass
                try:
                    if conn is not None:
                        conn.close()
                    self._conn = self._take()
                    self.problem = None
                except (StationBusy, Exception) as exc:  # noqa: BLE001 - reported, retried
                    self._conn = None
                    self.problem = f"the ownership of station {self.station_id!r} is lost: {exc}"

    def release(self) -> None:
        self._stop.set()
        with self._lock:
            conn, self._conn = self._conn, None
        if conn is None:
            return
        try:
            # unlocked before the return: closing alone ends the session, but the server
            # drops its locks only when that backend has exited, a moment later, and a
            # station started again at once would find itself still running
            conn.execute(
                "SELECT pg_advisory_unlock(%s, hashtext(%s))", (OWNERSHIP_KEY, self.station_id)
            )
        except Exception:  # noqa: BLE001 - the server may be gone: closing ends it anyway
            pass
        try:
            conn.close()  # ends the session: any lock left goes with it
        except Exception:  # noqa: BLE001 - closing is best effort
            pass


def station_alive(store: JobStore, station_id: str, live: set[str] | None) -> bool | None:
    """Whether the process of the station that owns a job is running: True for this
    store's own station, else whether ``station_id`` is in ``live`` (from
    :func:`live_stations`); None when that cannot be known (``live`` is None)."""
    if store.own_station is None or station_id == store.own_station:
        return True
    return None if live is None else station_id in live


def live_stations(store: JobStore) -> set[str] | None:
    """The stations sharing ``store``'s PostgreSQL database whose process is running:
    those whose ownership lock (:class:`PostgresOwnership`) some session holds. A
    station killed even with ``kill -9`` drops out as soon as the server ends its
    session. None on SQLite (one station per file: the one in this process)."""
    if not store.postgres:
        return None
    return store.stations_holding_advisory_lock(OWNERSHIP_KEY)


def claim_station(config: StationConfig) -> Ownership:
    """Make this process the one that runs the configured station's jobs."""
    path = config.storage.database_path
    if path is None:
        return PostgresOwnership(str(config.storage.database), station_id_of(config))
    return FileLock(path)


__all__ = [
    "OWNERSHIP_KEY",
    "FileLock",
    "ForeignJob",
    "Ownership",
    "PostgresOwnership",
    "StationBusy",
    "claim_station",
    "live_stations",
    "station_alive",
    "open_store",
    "station_id_of",
]
