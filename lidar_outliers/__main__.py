"""`python -m lidar_outliers`: the `lidar-outliers` command."""

from lidar_outliers.cli import console_main

console_main()
