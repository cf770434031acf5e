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
