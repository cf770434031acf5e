"""How processes that run side by side share the machine's cores."""

from __future__ import annotations

import os

from threadpoolctl import threadpool_limits


def share_cores(processes: int) -> int:
    """Limit this process's numerical libraries (BLAS, OpenMP) to its share of the cores it may
    run on when `processes` such processes run at once; returns the threads each gets.

    OpenBLAS's idle threads spin while they wait for work, so processes that each keep a thread
    per core slow one another down (two refining processes on two cores ran 1.6 times slower
    each)."""
    threads = max(1, len(os.sched_getaffinity(0)) // max(processes, 1))
    threadpool_limits(limits=threads)
    return threads
