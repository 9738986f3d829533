"""Jobs keep their subscriber: the callback URIs of the execute request.

- ``jobs.subscriber``: JSON text ``{"successUri": ..., "failedUri": ..., "inProgressUri": ...,
  "base_url": ...}`` (``base_url``: the API's address as the client called it, so the documents
  the worker posts carry absolute links); NULL for a job without callbacks.

Revision ID: 0003
Revises: 0002
Create Date: 2025-01-03
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0003"
down_revision = "0002"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("jobs") as batch:
        batch.add_column(sa.Column("subscriber", sa.Text))


def downgrade() -> None:
    with op.batch_alter_table("jobs") as batch:
        batch.drop_column("subscriber")
