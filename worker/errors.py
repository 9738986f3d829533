"""One exception root for everything a user can get wrong.

Each message is one line that says what to fix.
"""


class LidarOutliersError(Exception):
    """Root of the errors this project raises on purpose."""


class LasFormatError(LidarOutliersError):
    """Not a readable LAS/LAZ file (bad signature, truncated, inconsistent header...)."""


class MissingDimensionError(LidarOutliersError):
    """A detector needs a dimension the file does not have (e.g. temporal without gps_time)."""


class ParameterError(LidarOutliersError, ValueError):
    """A parameter is out of range or inconsistent (e.g. k too small for alpha).

    Also a ValueError, the exception numpy-style callers expect for a bad argument.
    """


class CancelledError(LidarOutliersError):
    """The job was cancelled while it ran."""
