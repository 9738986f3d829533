"""Heartbeats of running jobs, so a job whose worker is gone is found within a minute.

- ``jobs.heartbeat``: when the worker running the job last said it is alive (UTC text);
- ``jobs.worker_host``: the host of that worker (with ``worker_pid``, whether it still runs);
- ``jobs.requeues``: how often a job of a vanished worker was put back in the queue; a delivery
  sent before the latest re-queue is dropped.

Revision ID: 0005
Revises: 0004
Create Date: 2025-01-03
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0005"
down_revision = "0004"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("jobs") as batch:
        batch.add_column(sa.Column("heartbeat", sa.Text))
        batch.add_column(sa.Column("worker_host", sa.Text))
        batch.add_column(sa.Column("requeues", sa.Integer, nullable=False,
                                   server_default=sa.text("0")))


def downgrade() -> None:
    with op.batch_alter_table("jobs") as batch:
        batch.drop_column("requeues")
        batch.drop_column("worker_host")
        batch.drop_column("heartbeat")
