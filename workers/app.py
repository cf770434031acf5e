"""The Celery app: Redis broker and result backend, one queue per job kind, at-least-once delivery.

Run a worker with `pwm worker` (or `celery -A workers.app worker --pool=prefork -Q
ingest,refine,fuse`). A task is acknowledged after it ran (acks_late) and given back when its
worker process dies (task_reject_on_worker_lost); a worker that vanishes altogether leaves its
task unacknowledged, and Redis hands it out again once visibility_timeout_s has passed.
visibility_timeout_s must exceed job_time_limit_s, the hard limit on one attempt, so that Redis
does not hand a running task to a second worker. A running attempt beats every heartbeat_s;
one silent for heartbeat_grace_s is lost (service.jobs), and the reconciler
(workers.tasks.Reconciler, in every worker's main process) hands its job over again, so a dead
worker's job is taken over after about the grace rather than the visibility timeout.
Tasks make deliveries idempotent through the jobs table (workers.tasks).

spiceypy keeps one kernel pool per process and is not thread-safe: workers run the prefork pool
(one task per child process at a time) or solo, never threads or green threads. The solo pool
enforces no time limits, so production workers use prefork. Each process keeps its catalog
engine and its loaded kernels between tasks (ProcessState).
"""

from __future__ import annotations

import math
import os
from functools import lru_cache
from pathlib import Path
from typing import Any

import spiceypy as sp
from celery import Celery, signals
from celery.concurrency import get_implementation
from celery.concurrency.prefork import TaskPool as PreforkPool
from celery.concurrency.solo import TaskPool as SoloPool
from kombu import Exchange, Queue
from pydantic import Field, model_validator
from sqlalchemy.orm import Session

from pwm.io.spice_kernels import KernelError
from pwm.parallel import share_cores
from service.db import make_engine, make_sessionmaker
from service.kernels import accepted_kernels
from service.rows import JobKind
from service.settings import Settings, from_environment

QUEUES = tuple(kind.value for kind in JobKind)
# Tasks are routed by name: workers.tasks.<kind>_<what> goes to the queue of that kind.
TASK_ROUTES = {f"workers.tasks.{queue}_*": {"queue": queue} for queue in QUEUES}
# The soft time limit comes this share of the hard limit (at most SOFT_LIMIT_GRACE_S, s) before
# it, so that SoftTimeLimitExceeded lets a task record its failure before it is killed.
SOFT_LIMIT_GRACE_FRACTION, SOFT_LIMIT_GRACE_S = 0.1, 60.0


class WorkerSettings(Settings):
    """The service settings plus the workers' limits (s).

    job_time_limit_s: PWM_JOB_TIME_LIMIT_S, the hard limit on one attempt at a job.
    visibility_timeout_s: PWM_VISIBILITY_TIMEOUT_S, how long Redis waits for a delivered task to
        be acknowledged before it delivers it again; above job_time_limit_s.
    task_retries: PWM_TASK_RETRIES, how many times a failed job is tried again.
    retry_backoff_s: PWM_RETRY_BACKOFF_S, the wait before the first retry, doubled for each
        further one.
    reconcile_interval_s: PWM_RECONCILE_INTERVAL_S, how often each worker and the watcher look
        for work the broker lost (workers.tasks.reconcile).
    requeue_after_s: PWM_REQUEUE_AFTER_S, how long a queued job may wait with no attempt (its
        queue empty) before it is handed to the broker again; short recovers a lost message
        sooner, long sends fewer needless duplicates (each a no-op).
    """

    job_time_limit_s: float = Field(6600.0, gt=0)
    visibility_timeout_s: float = Field(7200.0, gt=0)
    task_retries: int = Field(3, ge=0)
    retry_backoff_s: float = Field(30.0, ge=0)
    reconcile_interval_s: float = Field(30.0, gt=0)
    requeue_after_s: float = Field(120.0, gt=0)

    @model_validator(mode="after")
    def _check_limits(self) -> WorkerSettings:
        if self.visibility_timeout_s <= self.job_time_limit_s:
            raise ValueError(
                f"PWM_VISIBILITY_TIMEOUT_S ({self.visibility_timeout_s:g} s) must exceed "
                f"PWM_JOB_TIME_LIMIT_S ({self.job_time_limit_s:g} s), or Redis hands running "
                "tasks to a second worker")
        return self


@lru_cache(maxsize=1)
def get_worker_settings() -> WorkerSettings:
    """The process-wide worker settings, read from the environment once (BadEnvironment if they
    cannot be)."""
    return from_environment(WorkerSettings)


def make_app(settings: WorkerSettings) -> Celery:
    """A Celery app for `settings`; with no (or an empty) broker URL, tasks run in the calling
    process."""
    app = Celery("pwm", include=["workers.tasks"])
    hard = settings.job_time_limit_s
    # The sweep for abandoned tasks bounds how late after visibility_timeout_s they come back.
    sweep_s = math.ceil(min(60.0, max(1.0, settings.visibility_timeout_s / 10)))
    app.conf.update(
        task_routes=TASK_ROUTES,
        task_queues=[Queue(queue, Exchange(queue), routing_key=queue) for queue in QUEUES],
        task_acks_late=True,
        task_reject_on_worker_lost=True,
        worker_prefetch_multiplier=1,
        task_time_limit=hard,
        task_soft_time_limit=hard - min(SOFT_LIMIT_GRACE_S, SOFT_LIMIT_GRACE_FRACTION * hard),
        worker_pool="prefork",
        broker_connection_retry_on_startup=True,
    )
    if not settings.broker_url:
        app.conf.update(task_always_eager=True, task_eager_propagates=True)
        return app
    app.conf.update(
        broker_url=settings.broker_url,
        result_backend=settings.broker_url,
        broker_transport_options={
            "visibility_timeout": settings.visibility_timeout_s,
            "unacked_restore_interval": sweep_s,
            "unacked_restore_throttle": 1,
            # A worker killed inside a sweep leaves the sweep lock behind until it expires.
            "unacked_mutex_expire": sweep_s,
        },
    )
    return app


class ProcessState:
    """What one worker process keeps between tasks: its catalog sessions and the SPICE kernels
    in its kernel pool."""

    def __init__(self, database_url: str) -> None:
        self.pid = os.getpid()
        self.engine = make_engine(database_url)
        self.sessions = make_sessionmaker(self.engine)
        self._loaded: list[tuple[int, str]] = []
        sp.kclear()

    def load_kernels(self, session: Session) -> bool:
        """Have the catalog's accepted kernels (service.kernels.accepted_kernels) in this
        process's kernel pool. They are loaded again only when the catalog's set changed or the
        pool was cleared (an ingest clears it); returns True when it loaded them."""
        kernels = accepted_kernels(session)
        wanted = [(k.id, k.sha256) for k in kernels]
        if wanted == self._loaded and sp.ktotal("ALL") == len(wanted):
            return False
        missing = [Path(k.path) for k in kernels if not Path(k.path).is_file()]
        if missing:
            raise KernelError(f"{len(missing)} catalogued kernels are missing on disk: "
                              + ", ".join(map(str, missing)), missing)
        sp.kclear()
        self._loaded = []
        for kernel in kernels:
            sp.furnsh(kernel.path)
        self._loaded = wanted
        return True


_state: ProcessState | None = None


def process_state() -> ProcessState:
    """This process's ProcessState, made on first use in each process."""
    global _state
    if _state is not None and _state.pid != os.getpid():
        # Inherited through fork: the parent's connections must stay open for the parent.
        _state.engine.dispose(close=False)
        _state = None
    if _state is None:
        _state = ProcessState(get_worker_settings().database_url)
    return _state


_controller: Any = None
"""This worker's WorkController: its pool processes, forked from it, read its concurrency."""


@signals.worker_init.connect
def _check_pool(sender: Any, **_: Any) -> None:
    global _controller
    pool = get_implementation(sender.pool_cls)
    if not issubclass(pool, (PreforkPool, SoloPool)):
        # Handlers' exceptions are only logged by Celery; SystemExit stops the worker.
        raise SystemExit(f"pwm workers run the prefork or solo pool, not {pool.__module__}: "
                         "SPICE's kernel pool is per process and not thread-safe")
    _controller = sender  # "auto" concurrency is resolved only after this signal


@signals.worker_process_init.connect
def _prepare_process(**_: Any) -> None:
    # worker_process_init comes in prefork's pool processes alone
    share_cores(int(_controller.concurrency) if _controller is not None else 1)
    process_state()


app = make_app(get_worker_settings())
# By name, so that this module imports no task: workers.tasks imports it.
app.steps["consumer"].add("workers.tasks:Reconciler")
