"""Sub-commands of `lidar-outliers`: each module here defines ``register(subparsers)``."""
