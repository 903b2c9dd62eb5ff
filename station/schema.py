"""Versioned schema of the job database: alembic migrations applied at start-up.

The schema is defined once, in the migration scripts of ``station/migrations/versions``
(``0001`` the single-station store, ``0002`` stations, cameras, object storage and
result versions), for both backends (SQLite and PostgreSQL). :func:`ensure_schema`
runs when a :class:`station.store.JobStore` opens its database:

- the version is read through the store's own pool (``alembic_version``); at
  :data:`HEAD` nothing else happens (no alembic import, a few milliseconds);
- an older version is upgraded to :data:`HEAD` by alembic, in one transaction on
  PostgreSQL (transactional DDL), under a PostgreSQL advisory lock so that two
  stations starting together do not both migrate (the second waits, then finds
  :data:`HEAD`); SQLite is serialised by its write lock and the station's file lock;
- a SQLite file of the time before migrations (tables, no ``alembic_version``) is
  stamped ``0001`` first;
- a version this software does not know (a newer station migrated the database)
  raises :class:`SchemaTooNew`: the database is left untouched, and ``lfcal serve`` /
  ``lfcal sweep`` / ``lfcal jobs`` exit 2 with that one line.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from station.db import ConnectionPool, StoreError, StoreUnavailable, sqlite_error

HEAD = "0002"
"""The schema version this software writes."""

KNOWN_REVISIONS = ("0001", "0002")
"""Every schema version this software can read or upgrade, oldest first."""

MIGRATION_LOCK_KEY = 0x6C666361  # "lfca": pg_advisory_lock key of the migrations
MIGRATIONS_DIR = Path(__file__).with_name("migrations")


class SchemaTooNew(StoreError):
    """The database's schema is newer than this software (it is not changed)."""

    def __init__(self, where: str, revision: str) -> None:
        self.where = where
        self.revision = revision
        super().__init__(
            f"the job database {where} has schema version {revision}, newer than this "
            f"lfcal-station knows (it knows up to {HEAD}): upgrade lfcal-station on this "
            "machine; the database was not changed"
        )


def _is_postgres(pool: ConnectionPool) -> bool:
    return hasattr(pool, "url")


def current_revision(pool: ConnectionPool) -> str | None:
    """The database's schema version; ``"legacy"`` for a SQLite store made before
    migrations; None for an empty database."""
    with pool.read() as conn:
        if _is_postgres(pool):
            has_version = conn.execute(
                "SELECT to_regclass('alembic_version') IS NOT NULL AS present"
            ).fetchone()["present"]
            has_jobs = conn.execute("SELECT to_regclass('jobs') IS NOT NULL AS present").fetchone()[
                "present"
            ]
        else:
            names = {
                r["name"]
                for r in conn.execute(
                    "SELECT name FROM sqlite_master WHERE type = 'table'"
                ).fetchall()
            }
            has_version, has_jobs = "alembic_version" in names, "jobs" in names
        if has_version:
            row = conn.execute("SELECT version_num FROM alembic_version").fetchone()
            if row is not None:
                return str(row["version_num"])
    return "legacy" if has_jobs else None


def _sqlalchemy_url(pool: ConnectionPool) -> str:
    if _is_postgres(pool):
        url = str(pool.url)  # type: ignore[attr-defined]
        return "postgresql+psycopg://" + url.split("://", 1)[1]
    return f"sqlite:///{Path(pool.path).resolve()}"  # type: ignore[attr-defined]


def _upgrade(pool: ConnectionPool, start: str | None) -> None:
    import sqlalchemy as sa
    from alembic import command
    from alembic.config import Config
    from sqlalchemy.pool import NullPool

    cfg = Config()
    cfg.set_main_option("script_location", str(MIGRATIONS_DIR))
    engine = sa.create_engine(_sqlalchemy_url(pool), poolclass=NullPool)
    try:
        with engine.connect() as conn:
            postgres = _is_postgres(pool)
            if postgres:
                conn.execute(sa.text(f"SELECT pg_advisory_lock({MIGRATION_LOCK_KEY})"))
                conn.commit()
            try:
                cfg.attributes["connection"] = conn
                if start == "legacy":
                    command.stamp(cfg, "0001")
                command.upgrade(cfg, HEAD)
                conn.commit()
            finally:
                if postgres:
                    conn.execute(sa.text(f"SELECT pg_advisory_unlock({MIGRATION_LOCK_KEY})"))
                    conn.commit()
    except sa.exc.DBAPIError as exc:
        raise _driver_error(pool, exc.orig or exc) from exc
    finally:
        engine.dispose()


def _driver_error(pool: ConnectionPool, exc: BaseException) -> StoreError:
    if _is_postgres(pool):
        from station.db_postgres import postgres_error

        return postgres_error(exc, str(pool.url), "migrate")  # type: ignore[attr-defined]
    import sqlite3

    if isinstance(exc, sqlite3.Error):
        return sqlite_error(exc, Path(pool.path), "write")  # type: ignore[attr-defined]
    return StoreUnavailable(f"the job database cannot be migrated: {exc}")


def ensure_schema(pool: ConnectionPool) -> tuple[str | None, str]:
    """Bring the database to :data:`HEAD` (see the module docstring); returns the
    version found and the version now. Raises :class:`SchemaTooNew` for a version
    this software does not know, :class:`station.db.StoreUnavailable` when the
    database cannot be reached or written."""
    found = current_revision(pool)
    where = str(getattr(pool, "path", "?"))
    if found == HEAD:
        return found, HEAD
    if found is not None and found != "legacy" and found not in KNOWN_REVISIONS:
        raise SchemaTooNew(where, found)
    _upgrade(pool, found)
    now = current_revision(pool)
    if now != HEAD:  # another process migrated it further meanwhile
        if now is not None and now not in KNOWN_REVISIONS:
            raise SchemaTooNew(where, now)
        raise StoreUnavailable(f"the job database {where} is at schema {now}, not {HEAD}")
    return found, HEAD


def schema_report(pool: ConnectionPool) -> dict[str, Any]:
    """The database's schema version against this software's (for ``lfcal jobs``)."""
    found = current_revision(pool)
    return {"schema": found, "software_schema": HEAD, "known": list(KNOWN_REVISIONS)}


__all__ = [
    "HEAD",
    "KNOWN_REVISIONS",
    "SchemaTooNew",
    "current_revision",
    "ensure_schema",
    "schema_report",
]
