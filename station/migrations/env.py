"""alembic environment: runs the migrations on the connection :mod:`station.schema` passes.

Never run from the command line with an ``alembic.ini``: :func:`station.schema.migrate`
configures alembic in code and hands over an open SQLAlchemy connection
(``config.attributes["connection"]``), already holding the migration lock.
"""

from __future__ import annotations

from alembic import context

connection = context.config.attributes["connection"]
context.configure(connection=connection, target_metadata=None, render_as_batch=True)
with context.begin_transaction():
    context.run_migrations()
