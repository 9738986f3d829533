"""Alembic's environment: migrate on the connection :func:`lidar_outliers.jobs.database.upgrade`
hands over (inside its lock and transaction), or on DATABASE_URL for the ``alembic`` command."""

from __future__ import annotations

import sqlalchemy as sa
from alembic import context

from lidar_outliers.jobs.schema import metadata

config = context.config


def run(connection: sa.Connection) -> None:
    # batch mode: SQLite alters a table by copying it; PostgreSQL runs plain ALTER TABLE
    context.configure(connection=connection, target_metadata=metadata, render_as_batch=True)
    with context.begin_transaction():
        context.run_migrations()


connection = config.attributes.get("connection")
if connection is not None:
    run(connection)
else:  # `alembic -c alembic.ini revision --autogenerate ...` by a developer
    from lidar_outliers.jobs.database import create_engine
    from lidar_outliers.jobs.settings import get_settings

    engine = create_engine(get_settings().database_url)
    with engine.begin() as conn:
        run(conn)
    engine.dispose()
