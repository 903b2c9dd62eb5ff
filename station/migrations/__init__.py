"""Versioned schema migrations of the job database (alembic; see :mod:`station.schema`)."""
