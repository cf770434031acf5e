"""Processes side by side share the cores: each one's BLAS gets its share of the threads."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

CHILD = """
import sys
import numpy  # noqa: F401  (loads OpenBLAS)
from threadpoolctl import threadpool_info
from pwm.parallel import share_cores
given = share_cores(int(sys.argv[1]))
print(given, *sorted({pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas"}))
"""


@pytest.mark.parametrize("processes", [1, 2, 64])
def test_each_process_gets_its_share_of_the_cores(processes):
    cores = len(os.sched_getaffinity(0))
    done = subprocess.run([sys.executable, "-c", CHILD, str(processes)], capture_output=True, text=True, check=True)
    given, *blas = (int(x) for x in done.stdout.split())
    assert given == max(1, cores // processes)
    assert blas == [given]


_STATE: dict = {}


def _remember(value: int) -> None:
    _STATE["value"] = value


def _work(item: int) -> tuple[int, int]:
    return item * _STATE["value"], os.getpid()


@pytest.mark.parametrize("workers", [1, 2])
def test_map_processes_keeps_item_order_and_runs_the_initializer_in_each_process(workers):
    from pwm.parallel import map_processes

    out = list(map_processes(_work, range(7), workers=workers, initializer=_remember, initargs=(3,)))
    assert [value for value, _ in out] == [3 * k for k in range(7)]
    pids = {pid for _, pid in out}
    if workers == 1:
        assert pids == {os.getpid()}
    else:
        assert os.getpid() not in pids and 1 <= len(pids) <= 2
