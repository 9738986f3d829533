"""Pure numerical code of lidar-outliers: numpy arrays in, numpy arrays out.

No files, no web, no queue. Each detector is a function ``detect_<name>(xyz, ..., *, params)``
returning a :class:`algorithms.result.DetectorResult`.
"""
