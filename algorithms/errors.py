"""The exception root of lidar-outliers and the errors the numerical code raises.

Each message is one line that says what to fix. The library (``lidar_outliers.errors``) derives
its file and job errors from the same root, so one ``except LidarOutliersError`` catches every
error a user can cause.
"""


class LidarOutliersError(Exception):
    """Root of the errors this project raises on purpose."""


class ParameterError(LidarOutliersError, ValueError):
    """A parameter is out of range or inconsistent (e.g. k too small for alpha).

    Also a ValueError, the exception numpy-style callers expect for a bad argument.
    """


class MissingDimensionError(LidarOutliersError):
    """A detector needs a dimension the data does not have (e.g. temporal without gps_time)."""


class NotTimeOrderedError(ParameterError):
    """A stream of points along time got a point earlier than one before it in its group."""
