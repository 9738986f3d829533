"""Every error a user can cause, under one root (``LidarOutliersError``).

The numerical package defines the root and the parameter errors; the library adds the errors of
files and jobs. Each message is one line that says what to fix.
"""

from algorithms.errors import LidarOutliersError, MissingDimensionError, ParameterError

__all__ = [
    "CancelledError",
    "LasFormatError",
    "LidarOutliersError",
    "MissingDimensionError",
    "ParameterError",
]


class LasFormatError(LidarOutliersError):
    """Not a readable LAS/LAZ file (bad signature, truncated, inconsistent header...)."""


class CancelledError(LidarOutliersError):
    """The job was cancelled while it ran."""
