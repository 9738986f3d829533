"""Alembic migrations of the job store; :func:`lidar_outliers.jobs.database.upgrade` runs them."""
