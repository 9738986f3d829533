"""Uploads named by their object-storage key, with their facts; jobs numbered per user.

- ``uploads.path`` (an absolute path under DATA_DIR) becomes ``uploads.key``, the key under the
  storage root (``uploads/<user>/<file>``), so the same record works with local and S3 storage;
- ``uploads.facts``: the upload's header facts, so a job made from it needs no second read;
- ``jobs.seq``: the user's n-th job, assigned in the transaction that creates it; lists are in
  submission order even when API hosts' clocks disagree. Existing jobs are numbered in the order
  they were created.

Revision ID: 0002
Revises: 0001
Create Date: 2025-01-02
"""

from __future__ import annotations

import posixpath

import sqlalchemy as sa
from alembic import op

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("uploads") as batch:
        batch.alter_column("path", new_column_name="key", existing_type=sa.Text,
                           existing_nullable=False)
        batch.add_column(sa.Column("facts", sa.Text))
    bind = op.get_bind()
    uploads = sa.table("uploads", sa.column("id", sa.Text), sa.column("key", sa.Text))
    for upload_id, key in bind.execute(sa.select(uploads.c.id, uploads.c.key)).all():
        if posixpath.isabs(key):  # DATA_DIR/uploads/<user>/<file> -> uploads/<user>/<file>
            relative = "/".join(["uploads", *key.rstrip("/").split("/")[-2:]])
            bind.execute(sa.update(uploads).where(uploads.c.id == upload_id)
                         .values(key=relative))

    with op.batch_alter_table("jobs") as batch:
        batch.add_column(sa.Column("seq", sa.Integer, nullable=False, server_default=sa.text("0")))
    jobs = sa.table("jobs", sa.column("id", sa.Text), sa.column("user_id", sa.Integer),
                    sa.column("created", sa.Text), sa.column("seq", sa.Integer))
    order = (jobs.c.user_id, jobs.c.created)
    if bind.dialect.name == "sqlite":  # ties in time: the order of insertion
        order = (*order, sa.literal_column("rowid"))
    else:
        order = (*order, jobs.c.id)
    numbered: dict[int, int] = {}
    for job_id, user_id in bind.execute(sa.select(jobs.c.id, jobs.c.user_id).order_by(*order)):
        numbered[user_id] = numbered.get(user_id, 0) + 1
        bind.execute(sa.update(jobs).where(jobs.c.id == job_id).values(seq=numbered[user_id]))
    op.drop_index("jobs_by_user", table_name="jobs")
    op.create_index("jobs_by_user_seq", "jobs", ["user_id", "seq"], unique=True)
    op.create_index("jobs_by_user_status", "jobs", ["user_id", "status"])


def downgrade() -> None:
    op.drop_index("jobs_by_user_status", table_name="jobs")
    op.drop_index("jobs_by_user_seq", table_name="jobs")
    op.create_index("jobs_by_user", "jobs", ["user_id", "created"])
    with op.batch_alter_table("jobs") as batch:
        batch.drop_column("seq")
    with op.batch_alter_table("uploads") as batch:
        batch.drop_column("facts")
        batch.alter_column("key", new_column_name="path", existing_type=sa.Text,
                           existing_nullable=False)
