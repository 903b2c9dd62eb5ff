"""Connections of the job store: a bounded pool, and the store's error classes.

:class:`station.store.JobStore` never holds a connection beyond one operation:
it borrows one from a :class:`ConnectionPool` (``with pool.read() as conn`` /
``with pool.write() as conn``, the latter a transaction) and gives it back at
once. A pool owns at most ``size`` connections whatever the number of threads
that come and go (the HTTP server's thread pool, writer threads, analysis
callbacks), so no descriptor can outlive its use; a connection whose
transaction could not be finished is closed instead of being handed on.

:class:`SQLitePool` is the SQLite backend (a WAL database file). A second
backend, :class:`station.db_postgres.PostgresPool` (PostgreSQL through psycopg 3),
implements the same three methods (``read``, ``write``, ``close``) plus
:attr:`ConnectionPool.health`, and maps its driver's errors onto
:class:`StorageFull` / :class:`StoreUnavailable` / :class:`UniqueViolation` as
:func:`sqlite_error` does here. :func:`station.ownership.open_store` picks the
backend from ``[storage] database`` (a file path or a ``postgresql://`` URL).

Errors: a database that cannot be read or written raises
:class:`StoreUnavailable` (the web layer answers 503, code
``store_unavailable``), a full disk :class:`StorageFull` (507,
``storage_full``), both with the database's path and the free space in the
message. The pool remembers the last such error until an operation succeeds
again (:attr:`ConnectionPool.health`), for ``/healthz``.
"""

from __future__ import annotations

import abc
import os
import shutil
import sqlite3
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

# SQLite primary result codes (https://sqlite.org/rescode.html)
_SQLITE_READONLY = 8
_SQLITE_IOERR = 10
_SQLITE_CORRUPT = 11
_SQLITE_FULL = 13
_SQLITE_CANTOPEN = 14
_SQLITE_NOTADB = 26


class StoreError(Exception):
    """Base class of the job store's errors."""


class StoreUnavailable(StoreError):
    """The job database cannot be read or written (I/O error, locked, unreadable file).

    Attributes:
        path: the database.
        cause: the database driver's own message.
    """

    def __init__(self, message: str, *, path: str | os.PathLike[str] = "", cause: str = "") -> None:
        self.path = str(path)
        self.cause = cause
        super().__init__(message)


class UniqueViolation(StoreError):
    """A row whose unique key is already stored (another backend's ``IntegrityError``;
    SQLite's is :class:`sqlite3.IntegrityError`).

    Attributes:
        path: the database.
        cause: the database driver's own message.
    """

    def __init__(self, message: str, *, path: str = "", cause: str = "") -> None:
        self.path = path
        self.cause = cause
        super().__init__(message)


class StorageFull(StoreUnavailable):
    """The disk holding the job database (or the archives) is full.

    Attributes:
        free_bytes: what the file system had available when it was detected.
    """

    def __init__(
        self,
        message: str,
        *,
        path: str | os.PathLike[str] = "",
        cause: str = "",
        free_bytes: int | None = None,
    ) -> None:
        self.free_bytes = free_bytes
        super().__init__(message, path=path, cause=cause)


def free_bytes(path: str | os.PathLike[str]) -> int | None:
    """Free bytes for an unprivileged writer on the file system of ``path`` (or its
    nearest existing parent); None if it cannot be read."""
    probe = Path(path)
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    try:
        return int(shutil.disk_usage(probe).free)
    except OSError:
        return None


def sqlite_error(exc: sqlite3.Error, path: Path, doing: str) -> StoreError:
    """The store error for a SQLite error met while ``doing`` (``"write"``, ``"read"``)."""
    code = getattr(exc, "sqlite_errorcode", None)
    primary = None if code is None else int(code) & 0xFF
    text = str(exc)
    if primary == _SQLITE_FULL or "database or disk is full" in text:
        free = free_bytes(path)
        shown = "unknown" if free is None else f"{free}"
        return StorageFull(
            f"the disk holding the job database {path} is full ({shown} bytes free): "
            f"cannot {doing} it ({text}); free space on that disk",
            path=path,
            cause=text,
            free_bytes=free,
        )
    hint = {
        _SQLITE_READONLY: "check the permissions of the file and its directory",
        _SQLITE_IOERR: "check the disk (dmesg) and the free space",
        _SQLITE_CORRUPT: "the file is damaged: restore it from a backup",
        _SQLITE_NOTADB: "the file is not a SQLite database",
        _SQLITE_CANTOPEN: "check that the directory exists and is writable",
    }.get(primary or -1, "see the station log")
    done = {"write": "written"}.get(doing, doing)
    return StoreUnavailable(
        f"the job database {path} cannot be {done}: {text}; {hint}", path=path, cause=text
    )


@dataclass(frozen=True)
class StoreHealth:
    """What the pool knows about its database.

    Attributes:
        ok: the last operation succeeded (or none failed yet).
        error: the message of the error that made it not ok.
        since: Unix time (s) of that error.
        storage_full: the error was a full disk.
        open_connections: connections currently open (idle or in use).
    """

    ok: bool
    error: str | None
    since: float | None
    storage_full: bool
    open_connections: int


class ConnectionPool(Protocol):
    """What the job store needs from a database backend (see the module docstring)."""

    def read(self) -> Any:
        """A context manager lending a connection for reads."""

    def write(self) -> Any:
        """A context manager lending a connection inside a write transaction
        (committed on a normal exit, rolled back on an exception)."""

    def close(self) -> None:
        """Close every connection; the pool cannot be used afterwards."""

    @property
    def health(self) -> StoreHealth:
        """The last error, if the database has not worked since."""


class BoundedPool(abc.ABC):
    """The lending machinery both backends share: at most ``size`` connections.

    A borrower takes an idle connection, opens a new one while fewer than
    ``size`` are open, or waits up to ``busy_timeout_s`` for one to come back;
    a broken connection (or any, once the pool is closed) is closed when given
    back. The last store error is remembered until an operation succeeds
    (:attr:`health`). Subclasses open connections (:meth:`_new`), translate
    their driver's errors (:meth:`_translate`) and name the driver's error class
    (``_driver_error``, ignored when closing a connection).

    Args:
        shown: the database as messages show it (a path, a URL without password).
        size: most connections open at once.
        busy_timeout_s: how long a borrower waits for a free connection (s).
    """

    _driver_error: type[BaseException] = Exception

    def __init__(self, shown: str | os.PathLike[str], *, size: int, busy_timeout_s: float) -> None:
        if size < 1:
            raise ValueError(f"pool size must be at least 1, got {size}")
        self.size = size
        self._shown = shown
        self._busy_s = float(busy_timeout_s)
        self._idle: list[Any] = []
        self._open = 0
        self._cond = threading.Condition()
        self._closed = False
        self._error: tuple[str, float, bool] | None = None

    @abc.abstractmethod
    def _new(self) -> Any:
        """A new connection (the subclass's driver)."""

    @abc.abstractmethod
    def _translate(self, exc: BaseException, doing: str) -> StoreError:
        """The store error for a driver error while ``doing`` (``read``/``write``)."""

    def _close_quietly(self, conn: Any) -> None:
        try:
            conn.close()
        except self._driver_error:
            pass

    def _acquire(self) -> Any:
        deadline = time.monotonic() + self._busy_s
        with self._cond:
            while True:
                if self._closed:
                    raise StoreError(f"job store {self._shown} is closed")
                if self._idle:
                    return self._idle.pop()
                if self._open < self.size:
                    self._open += 1
                    break
                left = deadline - time.monotonic()
                if left <= 0:
                    raise StoreUnavailable(
                        f"the job database {self._shown} is busy: all {self.size} connections "
                        f"were in use for {self._busy_s:g} s",
                        path=self._shown,
                    )
                self._cond.wait(left)
        try:
            return self._new()
        except BaseException:
            with self._cond:
                self._open -= 1
                self._cond.notify()
            raise

    def _release(self, conn: Any, *, broken: bool) -> None:
        with self._cond:
            discard = broken or self._closed
            if discard:
                self._open -= 1
            else:
                self._idle.append(conn)
            self._cond.notify()
        if discard:
            self._close_quietly(conn)

    def _failed(self, exc: BaseException, doing: str) -> StoreError:
        """Translate ``exc`` and remember it for :attr:`health` (a unique-key
        violation is the caller's conflict, not the database's health)."""
        error = self._translate(exc, doing)
        if not isinstance(error, UniqueViolation):
            with self._cond:
                self._error = (str(error), time.time(), isinstance(error, StorageFull))
        return error

    def _succeeded(self) -> None:
        if self._error is not None:
            with self._cond:
                self._error = None

    def close(self) -> None:
        """Close every idle connection; lent ones are closed when given back."""
        with self._cond:
            self._closed = True
            idle, self._idle = self._idle, []
            self._open -= len(idle)
            self._cond.notify_all()
        for conn in idle:
            self._close_quietly(conn)

    @property
    def health(self) -> StoreHealth:
        """The last error, if no operation succeeded since (see :class:`StoreHealth`)."""
        with self._cond:
            err, opened = self._error, self._open
        if err is None:
            return StoreHealth(True, None, None, False, opened)
        return StoreHealth(False, err[0], err[1], err[2], opened)


class SQLitePool(BoundedPool):
    """At most ``size`` SQLite connections to one database file (see the module docstring).

    Args:
        path: the database file (its directory is created if missing).
        size: most connections open at once; a borrower waits (up to
            ``busy_timeout_s``) when all are lent.
        busy_timeout_s: how long a writer waits for another writer's lock, and a
            borrower for a free connection (s).
        connect: opens a raw connection (``sqlite3.connect``-like; for tests that
            inject faults at the connection).
    """

    _driver_error = sqlite3.Error

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        size: int = 8,
        busy_timeout_s: float = 10.0,
        connect: Callable[..., Any] | None = None,
    ) -> None:
        super().__init__(Path(path), size=size, busy_timeout_s=busy_timeout_s)
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._connect = connect or sqlite3.connect

    # ------------------------------------------------------------------ lending

    def _new(self) -> Any:
        conn = self._connect(
            self.path, timeout=self._busy_s, isolation_level=None, check_same_thread=False
        )
        try:
            conn.execute(f"PRAGMA busy_timeout = {int(self._busy_s * 1000)}")
            conn.execute("PRAGMA journal_mode = WAL")
            conn.execute("PRAGMA synchronous = FULL")
            conn.execute("PRAGMA foreign_keys = ON")
            conn.row_factory = sqlite3.Row
        except BaseException:
            conn.close()
            raise
        return conn

    def _translate(self, exc: BaseException, doing: str) -> StoreError:
        assert isinstance(exc, sqlite3.Error)
        return sqlite_error(exc, self.path, doing)

    @contextmanager
    def read(self) -> Iterator[Any]:
        """A connection for reads (given back afterwards)."""
        try:
            conn = self._acquire()
        except sqlite3.Error as exc:  # cannot open the file
            raise self._failed(exc, "read") from exc
        broken = False
        try:
            yield conn
        except sqlite3.IntegrityError:
            raise
        except (sqlite3.OperationalError, sqlite3.DatabaseError) as exc:
            broken = True
            raise self._failed(exc, "read") from exc
        except BaseException:
            broken = conn.in_transaction
            raise
        finally:
            self._release(conn, broken=broken or conn.in_transaction)

    @contextmanager
    def write(self) -> Iterator[Any]:
        """A connection inside ``BEGIN IMMEDIATE`` ... ``COMMIT`` (rolled back on an error)."""
        try:
            conn = self._acquire()
        except sqlite3.Error as exc:
            raise self._failed(exc, "write") from exc
        broken = False
        try:
            conn.execute("BEGIN IMMEDIATE")
            yield conn
            conn.execute("COMMIT")
        except BaseException as exc:
            try:
                if conn.in_transaction:
                    conn.execute("ROLLBACK")
            except sqlite3.Error:
                broken = True
            if isinstance(exc, sqlite3.IntegrityError) or not isinstance(
                exc, sqlite3.OperationalError | sqlite3.DatabaseError
            ):
                raise
            broken = True
            raise self._failed(exc, "write") from exc
        else:
            self._succeeded()
        finally:
            self._release(conn, broken=broken or conn.in_transaction)


__all__ = [
    "BoundedPool",
    "ConnectionPool",
    "SQLitePool",
    "StorageFull",
    "StoreError",
    "StoreHealth",
    "StoreUnavailable",
    "UniqueViolation",
    "free_bytes",
    "sqlite_error",
]
