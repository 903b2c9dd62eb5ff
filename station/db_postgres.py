"""The PostgreSQL backend of the job store: a bounded pool of psycopg 3 connections.

:class:`PostgresPool` implements :class:`station.db.ConnectionPool` (``read``,
``write``, ``close``, ``health``) like :class:`station.db.SQLitePool`, so
:class:`station.store.JobStore` runs the same SQL on both: the lent connection
is a thin adapter whose ``execute`` takes the store's ``?`` placeholders (the
DB-API ``qmark`` style of :mod:`sqlite3`) and hands psycopg its ``%s`` ones;
rows are dictionaries (``row["id"]``, ``row.keys()``) as :class:`sqlite3.Row`
offers. The store's SQL is plain SQL that both engines accept (``RETURNING``,
``COUNT(*)``, ``IS NOT NULL``); the schema itself is created and upgraded by
the alembic migrations (:mod:`station.schema`), not by the store.

Errors map onto the store's classes: a server that cannot be reached or a
connection that broke becomes :class:`station.db.StoreUnavailable` (503) with
the database's address (never its password) and what to check; a full disk on
the server (SQLSTATE 53100 ``disk_full``) :class:`station.db.StorageFull`
(507); a unique-key violation :class:`station.db.UniqueViolation`. A
connection whose transaction failed is closed, not lent again.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from typing import Any
from urllib.parse import urlsplit, urlunsplit

import psycopg
from psycopg import errors as pg_errors
from psycopg.rows import dict_row

from station.db import BoundedPool, StorageFull, StoreError, StoreUnavailable, UniqueViolation

POSTGRES_SCHEMES = ("postgresql", "postgres", "postgresql+psycopg")
"""URL schemes of ``[storage] database`` that select this backend."""


def is_postgres_url(database: object) -> bool:
    """``database`` is a ``postgresql://`` URL (else a SQLite file path)."""
    text = str(database)
    return "://" in text and text.split("://", 1)[0].lower() in POSTGRES_SCHEMES


def libpq_url(url: str) -> str:
    """The URL as libpq takes it (``postgresql+psycopg://`` -> ``postgresql://``)."""
    scheme, rest = url.split("://", 1)
    return ("postgresql" if scheme.lower() in POSTGRES_SCHEMES else scheme) + "://" + rest


def shown_url(url: str) -> str:
    """The URL without its password, for messages and logs."""
    parts = urlsplit(libpq_url(url))
    netloc = parts.netloc
    if "@" in netloc:
        userinfo, host = netloc.rsplit("@", 1)
        user = userinfo.split(":", 1)[0]
        netloc = f"{user}@{host}" if user else host
    return urlunsplit((parts.scheme, netloc, parts.path, parts.query, ""))


def postgres_error(exc: BaseException, url: str, doing: str) -> StoreError:
    """The store error for a psycopg error met while ``doing`` (``"write"``, ``"read"``)."""
    where = shown_url(url)
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    if isinstance(exc, pg_errors.UniqueViolation):
        return UniqueViolation(f"the job database {where}: {text}", path=where, cause=text)
    if isinstance(exc, pg_errors.DiskFull | pg_errors.OutOfMemory):
        return StorageFull(
            f"the disk of the job database {where} is full: cannot {doing} it ({text}); "
            "free space on the database server",
            path=where,
            cause=text,
        )
    if isinstance(exc, pg_errors.InsufficientPrivilege | pg_errors.ReadOnlySqlTransaction):
        return StoreUnavailable(
            f"the job database {where} cannot be {'written' if doing == 'write' else doing}: "
            f"{text}; check the role's privileges and that the server is not read-only",
            path=where,
            cause=text,
        )
    if isinstance(exc, psycopg.OperationalError | psycopg.InterfaceError):
        return StoreUnavailable(
            f"the job database {where} is unreachable: {text}; check that the PostgreSQL "
            "server runs and accepts connections from this host (address, port, user, password)",
            path=where,
            cause=text,
        )
    return StoreUnavailable(
        f"the job database {where} cannot be {'written' if doing == 'write' else doing}: {text}",
        path=where,
        cause=text,
    )


def qmark_to_pyformat(sql: str) -> str:
    """The store's ``?`` placeholders as psycopg's ``%s`` (the store's SQL has no
    literal ``?`` or ``%``; a ``%`` is refused rather than silently misread)."""
    if "%" in sql:
        raise ValueError(f"SQL for the job store must not contain '%': {sql!r}")
    return sql.replace("?", "%s")


class PgConnection:
    """A psycopg connection as the store uses it (``execute`` / ``executemany`` with
    ``?`` placeholders, rows as dictionaries)."""

    def __init__(self, conn: psycopg.Connection[Any], url: str = "") -> None:
        self.raw = conn
        self.url = url

    def execute(self, sql: str, params: Sequence[Any] = ()) -> psycopg.Cursor[Any]:
        try:
            return self.raw.execute(qmark_to_pyformat(sql), list(params))
        except pg_errors.UniqueViolation as exc:  # as sqlite3.IntegrityError: at the statement
            raise postgres_error(exc, self.url, "write") from exc

    def executemany(self, sql: str, rows: Sequence[Sequence[Any]]) -> psycopg.Cursor[Any]:
        cur = self.raw.cursor()
        cur.executemany(qmark_to_pyformat(sql), [list(r) for r in rows])
        return cur


class PostgresPool(BoundedPool):
    """At most ``size`` connections to one PostgreSQL database (see the module docstring).

    Args:
        url: ``postgresql://user:password@host:port/dbname`` (libpq's URL; libpq's
            environment variables such as ``PGPASSWORD`` fill in what it leaves out).
        size: most connections open at once; a borrower waits up to
            ``busy_timeout_s`` when all are lent.
        connect_timeout_s: how long a connection attempt may take (s).
        busy_timeout_s: how long a borrower waits for a free connection, and a
            statement for a lock (s).
    """

    _driver_error = psycopg.Error

    def __init__(
        self,
        url: str,
        *,
        size: int = 8,
        connect_timeout_s: float = 5.0,
        busy_timeout_s: float = 10.0,
    ) -> None:
        super().__init__(shown_url(url), size=size, busy_timeout_s=busy_timeout_s)
        self.url = libpq_url(url)
        self.path = shown_url(url)
        self._connect_s = max(1, int(round(connect_timeout_s)))

    # ------------------------------------------------------------------ lending

    def connect(self) -> psycopg.Connection[Any]:
        """A new autocommit connection (not part of the pool; the caller closes it)."""
        return psycopg.connect(
            self.url,
            autocommit=True,
            row_factory=dict_row,
            connect_timeout=self._connect_s,
            application_name="lfcal-station",
            options=f"-c lock_timeout={int(self._busy_s * 1000)}",
        )

    def _new(self) -> psycopg.Connection[Any]:
        return self.connect()

    def _translate(self, exc: BaseException, doing: str) -> StoreError:
        return postgres_error(exc, self.url, doing)

    def _release(self, conn: Any, *, broken: bool) -> None:
        broken = broken or conn.closed or conn.info.transaction_status != 0  # 0: IDLE
        super()._release(conn, broken=broken)

    @contextmanager
    def _lend(self, doing: str) -> Iterator[psycopg.Connection[Any]]:
        try:
            conn = self._acquire()
        except psycopg.Error as exc:
            raise self._failed(exc, doing) from exc
        broken = False
        try:
            yield conn
        except psycopg.Error as exc:
            broken = not isinstance(exc, pg_errors.UniqueViolation)
            raise self._failed(exc, doing) from exc
        finally:  # another exception: the transaction was rolled back, the connection is fine
            self._release(conn, broken=broken)

    @contextmanager
    def read(self) -> Iterator[PgConnection]:
        """A connection for reads (autocommit: each statement sees committed data)."""
        with self._lend("read") as conn:
            yield PgConnection(conn, self.url)
        self._succeeded()

    @contextmanager
    def write(self) -> Iterator[PgConnection]:
        """A connection inside ``BEGIN`` ... ``COMMIT`` (rolled back on an error)."""
        with self._lend("write") as conn, conn.transaction():
            yield PgConnection(conn, self.url)
        self._succeeded()


__all__ = [
    "POSTGRES_SCHEMES",
    "PgConnection",
    "PostgresPool",
    "is_postgres_url",
    "libpq_url",
    "postgres_error",
    "qmark_to_pyformat",
    "shown_url",
]
