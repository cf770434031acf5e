"""Running work in processes side by side: the one way maplets are refined in parallel outside
Celery (`pwm refine` and `pwm run`), how such processes share the machine's cores, and how a
long loop tells its caller how far it has come (`Progress`)."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from typing import Any, TypeVar

from threadpoolctl import threadpool_limits

T = TypeVar("T")
R = TypeVar("R")

Progress = Callable[[str, int, int], None]
"""Told (stage, done, total) as a long loop starts (done 0) and after each of its items: the
science only counts; whoever runs it (the command line's progress bar) shows it."""


def share_cores(processes: int) -> int:
    """Limit this process's numerical libraries (BLAS, OpenMP) to its share of the cores it may
    run on when `processes` such processes run at once; returns the threads each gets.

    OpenBLAS's idle threads spin while they wait for work, so processes that each keep a thread
    per core slow one another down."""
    threads = max(1, len(os.sched_getaffinity(0)) // max(processes, 1))
    threadpool_limits(limits=threads)
    return threads


def map_processes(function: Callable[[T], R], items: Iterable[T], *, workers: int,
                  initializer: Callable[..., None] | None = None, initargs: tuple[Any, ...] = ()) -> Iterator[R]:
    """function(item) for each item, in item order, in `workers` processes (each with its share of
    the cores) or, with one worker or one item, in this process (its thread limits left as they are).

    initializer(*initargs) runs once in each process first, to build what the items share (a ray
    tracer, a catalog engine). The processes are spawned, not forked: nothing they use is
    inherited, since an Embree scene, a database connection or a SPICE kernel pool of the parent
    must not be used from another process. function, initializer and their arguments must
    therefore pickle (module-level functions)."""
    items = list(items)
    if workers <= 1 or len(items) <= 1:
        if initializer is not None:
            initializer(*initargs)
        yield from map(function, items)
        return
    processes = min(workers, len(items))
    with ProcessPoolExecutor(processes, mp_context=get_context("spawn"), initializer=_start_process,
                             initargs=(processes, initializer, initargs)) as pool:
        yield from pool.map(function, items)


def _start_process(processes: int, initializer: Callable[..., None] | None, initargs: tuple[Any, ...]) -> None:
    share_cores(processes)
    if initializer is not None:
        initializer(*initargs)
