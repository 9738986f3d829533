"""Resumable uploads (tus): the uploads still arriving, their announced size reserved against
the user's quota until they complete (then they become rows of ``uploads``) or expire.

Revision ID: 0004
Revises: 0003
Create Date: 2025-01-03
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0004"
down_revision = "0003"
branch_labels = None
depends_on = None

Bytes = sa.BigInteger().with_variant(sa.Integer(), "sqlite")


def upgrade() -> None:
    op.create_table(
        "resumable_uploads",
        sa.Column("id", sa.Text, primary_key=True),
        sa.Column("user_id", sa.Integer, sa.ForeignKey("users.id"), nullable=False),
        sa.Column("name", sa.Text, nullable=False),
        sa.Column("kind", sa.Text, nullable=False),
        sa.Column("length", Bytes, nullable=False),
        sa.Column("offset", Bytes, nullable=False, server_default=sa.text("0")),
        sa.Column("created", sa.Text, nullable=False),
        sa.Column("expires", sa.Text, nullable=False),
        sa.Column("host", sa.Text, nullable=False),
    )
    op.create_index("resumable_uploads_by_expiry", "resumable_uploads", ["expires"])


def downgrade() -> None:
    op.drop_index("resumable_uploads_by_expiry", table_name="resumable_uploads")
    op.drop_table("resumable_uploads")
