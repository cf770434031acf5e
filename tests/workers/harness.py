"""What the workers' tests share besides fixtures: worker processes and their commands, and
waiting on them with their logs at hand."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest
from celery.result import AsyncResult

from workers.app import QUEUES, WorkerSettings

REPO = Path(__file__).resolve().parents[2]
PWM = Path(sys.executable).parent / "pwm"
WORKER_START_TIMEOUT_S = 60.0
RESULT_TIMEOUT_S = 60.0

# The end-to-end tests' settings (test_operations, test_faults). The hard limit on one attempt
# outlasts the slowest attempt on a loaded machine (an ingest that imports the start model, or a
# refinement), and Redis hands an unacknowledged task out again after the visibility timeout.
TIME_LIMIT_S, VISIBILITY_TIMEOUT_S = 25.0, 30.0
# Short liveness and reconciliation: a lost attempt is taken over, and work the broker lost is
# handed over again, within seconds.
HEARTBEAT_S, HEARTBEAT_GRACE_S, RECONCILE_INTERVAL_S, REQUEUE_AFTER_S = 1.0, 5.0, 1.0, 10.0
# Small maplets over the middle of the tiny site: 9 of them, a second or two each to refine.
MAPLET_NODES, TILE_RADIUS_KM = 40, 0.002
# One refinement pass: the fault and flow tests are about the jobs, which a later pass runs
# again the same way; test_operations' passes test runs the default two.
REFINE_PASSES = 1


def end_to_end_settings(*, broker_url: str, database_url: str, data_dir: Path,
                        **overrides: object) -> WorkerSettings:
    """The settings of the end-to-end tests' processes, on their broker and catalog, with any
    of them overridden."""
    values: dict[str, object] = dict(
        job_time_limit_s=TIME_LIMIT_S, visibility_timeout_s=VISIBILITY_TIMEOUT_S, task_retries=1,
        retry_backoff_s=1.0, maplet_nodes=MAPLET_NODES, tile_radius_km=TILE_RADIUS_KM,
        refine_passes=REFINE_PASSES, heartbeat_s=HEARTBEAT_S, heartbeat_grace_s=HEARTBEAT_GRACE_S,
        reconcile_interval_s=RECONCILE_INTERVAL_S, requeue_after_s=REQUEUE_AFTER_S)
    return WorkerSettings(broker_url=broker_url, database_url=database_url, data_dir=data_dir,
                          **(values | overrides))


@dataclass
class Worker:
    """A worker process group, its log, and how long it took to be ready (s)."""

    process: subprocess.Popen
    log: Path
    startup_s: float = 0.0

    def output(self) -> str:
        return self.log.read_text(errors="replace") if self.log.exists() else ""

    def children(self) -> list[int]:
        """The pids of the main process's children: its pool processes."""
        pid = self.process.pid
        return [int(p) for p in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]

    def kill(self) -> None:
        """SIGKILL the main process and its pool children, as a lost machine would."""
        if self.process.poll() is None:
            os.killpg(self.process.pid, signal.SIGKILL)
            self.process.wait()


def celery_worker_command(name: str, pool: str) -> list[str]:
    """`celery -A workers.app worker` with one pool process on all queues."""
    return [sys.executable, "-m", "celery", "-A", "workers.app", "worker", f"--pool={pool}",
            "--concurrency=1", "-Q", ",".join(QUEUES), "--loglevel=INFO", "-n", f"{name}@%h",
            "--without-gossip", "--without-mingle", "--without-heartbeat"]


def pwm_worker_command(name: str, concurrency: int) -> list[str]:
    """`pwm worker` with `concurrency` pool processes on all queues."""
    return [str(PWM), "worker", f"--concurrency={concurrency}", "--name", f"{name}@%h"]


def logs(workers: list[Worker]) -> str:
    return "\n".join(f"--- {w.log.name}\n{w.output()}" for w in workers)


def result_of(async_result: AsyncResult, workers: list[Worker],
              timeout: float = RESULT_TIMEOUT_S) -> dict:
    """The task's result, or the test fails with the workers' logs."""
    try:
        return async_result.get(timeout=timeout)
    except Exception as exc:
        pytest.fail(f"task {async_result.id} gave no result ({exc!r}):\n{logs(workers)}")


def wait_for(condition: Callable[[], bool], what: str, workers: list[Worker],
             timeout: float = RESULT_TIMEOUT_S) -> None:
    """Poll until `condition` holds, or fail with the workers' logs."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            pytest.fail(f"{what} not seen in {timeout} s:\n{logs(workers)}")
        time.sleep(0.05)
