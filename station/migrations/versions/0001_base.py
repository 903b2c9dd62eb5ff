"""Schema 0001: the single-station job store (jobs, transitions, steps).

The schema that ``station/store.py`` created with ``CREATE TABLE IF NOT EXISTS``
before migrations existed; a SQLite database of that time (``PRAGMA user_version = 1``,
no ``alembic_version`` table) is stamped ``0001`` and then upgraded.

Revision ID: 0001
Revises: -
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0001"
down_revision = None
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "jobs",
        sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
        sa.Column("state", sa.Text, nullable=False),
        sa.Column("request", sa.Text, nullable=False),
        sa.Column("created_at", sa.Float(precision=53), nullable=False),
        sa.Column("updated_at", sa.Float(precision=53), nullable=False),
        sa.Column("result", sa.Text),
        sa.Column("last_error", sa.Text),
        sa.Column("archive_dir", sa.Text, nullable=False),
        sa.Column("frames_total", sa.Integer, nullable=False),
        sa.Column("idempotency_key", sa.Text, unique=True),
        sqlite_autoincrement=True,
    )
    op.create_index("jobs_state", "jobs", ["state"])
    op.create_table(
        "transitions",
        sa.Column("seq", sa.Integer, primary_key=True, autoincrement=True),
        sa.Column("job_id", sa.Integer, sa.ForeignKey("jobs.id"), nullable=False),
        sa.Column("from_state", sa.Text),
        sa.Column("to_state", sa.Text, nullable=False),
        sa.Column("at", sa.Float(precision=53), nullable=False),
        sa.Column("reason", sa.Text, nullable=False),
        sqlite_autoincrement=True,
    )
    op.create_index("transitions_job", "transitions", ["job_id", "seq"])
    op.create_table(
        "steps",
        sa.Column("job_id", sa.Integer, sa.ForeignKey("jobs.id"), nullable=False),
        sa.Column("idx", sa.Integer, nullable=False),
        sa.Column("commanded_mm", sa.Float(precision=53), nullable=False),
        sa.Column("actual_mm", sa.Float(precision=53), nullable=False),
        sa.Column("file", sa.Text, nullable=False),
        sa.Column("sha256", sa.Text, nullable=False),
        sa.Column("started_at", sa.Float(precision=53), nullable=False),
        sa.Column("captured_at", sa.Float(precision=53), nullable=False),
        sa.Column("written_at", sa.Float(precision=53), nullable=False),
        sa.Column("summary", sa.Text),
        sa.PrimaryKeyConstraint("job_id", "idx"),
    )


def downgrade() -> None:
    op.drop_table("steps")
    op.drop_table("transitions")
    op.drop_table("jobs")
