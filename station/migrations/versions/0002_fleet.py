"""Schema 0002: many stations on one database, archives in object storage, result versions.

- ``jobs.station_id``: the station that owns (and alone runs) the job; rows of an
  older single-station database get ``''`` and are adopted by the station that opens it.
- ``jobs.camera_serial``: the serial number of the camera that took the frames.
- ``jobs.archive_url``: where the archive is uploaded (``s3://bucket/prefix/...``), or NULL;
  ``jobs.archive_uploaded_at``: Unix time (s) every file of the final archive was
  uploaded and verified, or NULL.
- ``results``: calibration results computed again later (``lfcal recalibrate``), one
  row per (job, version) with the software version and date; the station's own result
  stays in ``jobs.result`` (version 0).

Revision ID: 0002
Revises: 0001
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("jobs") as batch:
        batch.add_column(sa.Column("station_id", sa.Text, nullable=False, server_default=""))
        batch.add_column(sa.Column("camera_serial", sa.Text))
        batch.add_column(sa.Column("archive_url", sa.Text))
        batch.add_column(sa.Column("archive_uploaded_at", sa.Float(precision=53)))
    op.create_index("jobs_station_state", "jobs", ["station_id", "state"])
    op.create_index("jobs_camera_serial", "jobs", ["camera_serial"])
    op.create_table(
        "results",
        sa.Column("job_id", sa.Integer, sa.ForeignKey("jobs.id"), nullable=False),
        sa.Column("version", sa.Integer, nullable=False),
        sa.Column("software_version", sa.Text, nullable=False),
        sa.Column("created_at", sa.Float(precision=53), nullable=False),
        sa.Column("source", sa.Text, nullable=False),
        sa.Column("result", sa.Text, nullable=False),
        sa.PrimaryKeyConstraint("job_id", "version"),
    )
    op.create_index("results_software", "results", ["software_version"])


def downgrade() -> None:
    op.drop_table("results")
    op.drop_index("jobs_camera_serial", "jobs")
    op.drop_index("jobs_station_state", "jobs")
    with op.batch_alter_table("jobs") as batch:
        batch.drop_column("archive_uploaded_at")
        batch.drop_column("archive_url")
        batch.drop_column("camera_serial")
        batch.drop_column("station_id")
