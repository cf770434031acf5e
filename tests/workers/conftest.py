"""The workers' test harness: a Redis database per test, a PostgreSQL catalog, and real worker
processes started on them with the PWM_* environment of the test module's `settings` fixture
(each module defines its own, with the limits its tests need)."""

from __future__ import annotations

import itertools
import os
import subprocess
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import redis
from celery import Celery
from harness import REPO, WORKER_START_TIMEOUT_S, Worker, celery_worker_command
from sqlalchemy.orm import Session, sessionmaker

from workers.app import WorkerSettings, make_app

_redis_databases = itertools.count()


@pytest.fixture
def broker_url(redis_url: str) -> Iterator[str]:
    """A Redis database of its own for one test (empty queues), flushed afterwards."""
    url = redis_url.rsplit("/", 1)[0] + f"/{next(_redis_databases) % 15 + 1}"
    client = redis.Redis.from_url(url)
    client.flushdb()
    yield url
    client.flushdb()
    client.close()


@pytest.fixture
def catalog(postgres_url: str, open_catalog_at) -> sessionmaker[Session]:
    return open_catalog_at(postgres_url)


@pytest.fixture
def client(settings: WorkerSettings, catalog: sessionmaker[Session]) -> Iterator[Celery]:
    """The submitting side: an app on the test broker (tasks are sent by name)."""
    app = make_app(settings)
    yield app
    app.close()


@pytest.fixture
def worker_env(settings: WorkerSettings) -> dict[str, str]:
    """The environment of a process on the test broker and catalog: every setting as PWM_*."""
    values = {f"PWM_{name.upper()}": str(value)
              for name, value in settings.model_dump().items() if value is not None}
    return os.environ | values | {"PYTHONUNBUFFERED": "1"}


@pytest.fixture
def start_worker(worker_env: dict[str, str], catalog: sessionmaker[Session], tmp_path: Path
                 ) -> Iterator[Callable[..., Worker]]:
    """Start worker processes on the test broker and catalog (default: `celery worker`, prefork,
    one pool process; or command(name)); all are killed at teardown."""
    workers: list[Worker] = []

    def start(command: Callable[[str], list[str]] | None = None) -> Worker:
        name = f"pwm-test-{uuid.uuid4().hex[:8]}"
        log = tmp_path / f"{name}.log"
        clock = time.monotonic()
        argv = command(name) if command else celery_worker_command(name, "prefork")
        with open(log, "wb") as out:
            process = subprocess.Popen(argv, cwd=REPO, env=worker_env, stdout=out,
                                       stderr=subprocess.STDOUT, start_new_session=True)
        worker = Worker(process, log)
        workers.append(worker)
        while " ready." not in worker.output():
            if process.poll() is not None:
                pytest.fail(f"worker exited ({process.returncode}):\n{worker.output()}")
            if time.monotonic() - clock > WORKER_START_TIMEOUT_S:
                pytest.fail(f"worker not ready in {WORKER_START_TIMEOUT_S} s:\n{worker.output()}")
            time.sleep(0.05)
        worker.startup_s = time.monotonic() - clock
        return worker

    yield start
    for worker in workers:
        worker.kill()  # a shutdown takes seconds, and the test's broker and catalog go anyway
