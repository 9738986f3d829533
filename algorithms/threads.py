"""How many threads one process's kernels use.

The numba kernels run on NUMBA_NUM_THREADS threads (numba's own setting, read when numba is
imported); the k-d tree queries and the numpy kernels that split their work take the same
number, so a single setting divides a machine among the processes that share it (the service
sets it for its workers: the CPUs over the worker processes).
"""

from __future__ import annotations

import os


def worker_threads() -> int:
    """NUMBA_NUM_THREADS when set, else the CPUs this process may run on."""
    env = os.environ.get("NUMBA_NUM_THREADS", "")
    if env.isdigit() and int(env) > 0:
        return int(env)
    return available_cpus()


def available_cpus() -> int:
    """The CPUs this process may run on (its affinity where the system tells it)."""
    affinity = getattr(os, "sched_getaffinity", None)
    return len(affinity(0)) if affinity else (os.cpu_count() or 1)
