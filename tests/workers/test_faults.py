"""Faults with real servers, as issue 22 found them: `pwm worker` processes (prefork) on a Redis
broker of the test's own, which it stops and restarts empty (no persistence, as a crashed broker
comes back), and a PostgreSQL catalog. A fusion due while Redis is down is published once it is
back, with its own downlink in its lineage; workers started together on an empty database all
come up; a worker killed in the middle of a refinement shows its job lost within seconds and
the job is done once, by another worker, long before Redis would have handed it out again."""

from __future__ import annotations

import json
import subprocess
import time
from collections.abc import Callable
from datetime import timedelta
from pathlib import Path

import pytest
from celery import Celery
from harness import (
    HEARTBEAT_GRACE_S,
    PWM,
    REPO,
    WORKER_START_TIMEOUT_S,
    Worker,
    end_to_end_settings,
    logs,
    pwm_worker_command,
    wait_for,
)
from sqlalchemy import create_engine, func, select, text
from sqlalchemy.orm import Session, selectinload, sessionmaker

from service.db import normalize_url
from service.rows import Job, JobKind, JobStatus, MapletRevision, ModelVersion, utcnow
from workers.app import WorkerSettings
from workers.tasks import fuse_key, ingest_downlink, ingest_key

DOWNLINK_TIMEOUT_S = 150.0
# Longer than any test here: a task lost with its worker comes back only through a reconciler,
# not through Redis's own redelivery of unacknowledged tasks.
VISIBILITY_TIMEOUT_S = 600.0
WORKERS_TOGETHER = 3  # without the migration lock, two of them often collide


@pytest.fixture
def broker_url(redis_server) -> str:
    return redis_server.url(1)


@pytest.fixture
def settings(broker_url: str, postgres_url: str, tmp_path: Path) -> WorkerSettings:
    return end_to_end_settings(broker_url=broker_url, database_url=postgres_url,
                               data_dir=tmp_path / "data",
                               visibility_timeout_s=VISIBILITY_TIMEOUT_S)


def _jobs(sessions: sessionmaker[Session], kind: JobKind, *where) -> list[Job]:
    with sessions() as session:
        return list(session.scalars(select(Job).where(Job.kind == kind, *where)
                                    .order_by(Job.id)))


def _versions(sessions: sessionmaker[Session]) -> list[ModelVersion]:
    with sessions() as session:
        return list(session.scalars(select(ModelVersion).order_by(ModelVersion.version).options(
            selectinload(ModelVersion.maplet_revisions), selectinload(ModelVersion.downlinks))))


def _ingest(client: Celery, downlink: Path) -> None:
    client.send_task(ingest_downlink.name, args=[str(downlink)],
                     kwargs={"key": ingest_key(downlink)})


def _revisions_by_maplet(sessions: sessionmaker[Session]) -> dict[int, int]:
    with sessions() as session:
        return {maplet_id: count for maplet_id, count in session.execute(
            select(MapletRevision.maplet_id, func.count()).group_by(MapletRevision.maplet_id))}


def test_a_fusion_due_during_a_broker_outage_is_published_once_the_broker_is_back(
        tiny_sim: Path, catalog: sessionmaker[Session], client: Celery, redis_server,
        start_worker: Callable[..., Worker]) -> None:
    worker = start_worker(lambda name: pwm_worker_command(name, 2))
    downlink = tiny_sim / "downlink"
    _ingest(client, downlink)

    def last_refinements_running() -> bool:
        ingest = _jobs(catalog, JobKind.INGEST)
        left = [j for j in _jobs(catalog, JobKind.REFINE) if j.status is not JobStatus.DONE]
        return (bool(ingest) and ingest[0].status is JobStatus.DONE and 0 < len(left) <= 2
                and all(j.status is JobStatus.RUNNING for j in left))

    wait_for(last_refinements_running, "the downlink's last refinements under way", [worker],
             timeout=DOWNLINK_TIMEOUT_S)
    redis_server.stop(kill=True)
    wait_for(lambda: all(j.status is JobStatus.DONE for j in _jobs(catalog, JobKind.REFINE)),
             "the last refinements done during the outage", [worker])
    refines = _jobs(catalog, JobKind.REFINE)
    downlink_id = refines[0].downlink_id
    # The fan-in could not hand the fusion to the broker: recorded, not lost.
    wait_for(lambda: any(j.enqueue_error for j in _jobs(catalog, JobKind.FUSE)),
             "the failed hand-over of the fusion recorded", [worker])
    [fuse] = _jobs(catalog, JobKind.FUSE)
    assert (fuse.key, fuse.status, fuse.attempts) == (fuse_key(downlink_id), JobStatus.QUEUED, 0)
    assert _versions(catalog)[-1].version == 1

    redis_server.start()  # empty: what it held is gone
    restarted = utcnow()
    wait_for(lambda: len(_versions(catalog)) == 2, "the version published after the outage",
             [worker], timeout=60.0)
    # the fusion goes on after its publication, making the console's 3D document
    wait_for(lambda: all(j.status is JobStatus.DONE for j in _jobs(catalog, JobKind.FUSE)),
             "the fusion's job done", [worker])
    published = _versions(catalog)[-1]
    [fuse] = _jobs(catalog, JobKind.FUSE)
    assert published.created_at - restarted < timedelta(seconds=60)
    assert [d.id for d in published.downlinks] == [downlink_id]
    assert len(published.maplet_revisions) == len(refines) > 1
    assert (fuse.status, fuse.attempts, fuse.enqueue_error) == (JobStatus.DONE, 1, None)
    assert fuse.message == f"published version {published.version}"
    assert all((j.status, j.attempts) == (JobStatus.DONE, 1) for j in _jobs(catalog, JobKind.REFINE))
    assert set(_revisions_by_maplet(catalog).values()) == {1}
    assert f"could not hand job {fuse.key} to the broker" in worker.output()
    print(f"\nversion {published.version} published "
          f"{(published.created_at - restarted).total_seconds():.1f} s after Redis came back")


def test_workers_started_together_on_an_empty_database_all_come_up(
        postgres_url: str, worker_env: dict[str, str], tmp_path: Path) -> None:
    workers = []
    try:
        for k in range(WORKERS_TOGETHER):
            log = tmp_path / f"worker-{k}.log"
            with open(log, "wb") as out:
                workers.append(Worker(subprocess.Popen(
                    pwm_worker_command(f"together-{k}", 1), cwd=REPO, env=worker_env,
                    stdout=out, stderr=subprocess.STDOUT, start_new_session=True), log))
        deadline = time.monotonic() + 2 * WORKER_START_TIMEOUT_S
        while not all(" ready." in w.output() for w in workers):
            if any(w.process.poll() is not None for w in workers) or time.monotonic() > deadline:
                pytest.fail(f"not all workers came up:\n{logs(workers)}")
            time.sleep(0.1)
        engine = create_engine(normalize_url(postgres_url))
        with engine.connect() as connection:
            heads = connection.execute(text("SELECT version_num FROM alembic_version")).all()
        engine.dispose()
        assert len(heads) == 1
    finally:
        for worker in workers:
            worker.kill()


def _lost_jobs(env: dict[str, str]) -> list[dict]:
    """`pwm jobs list --status lost --json`: the lost jobs, as an operator sees them."""
    run = subprocess.run([str(PWM), "jobs", "list", "--status", "lost", "--json"], cwd=REPO,
                         env=env, capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stderr
    return json.loads(run.stdout)["items"]


def test_a_worker_killed_in_a_refinement_shows_its_job_lost_and_another_does_it_once(
        tiny_sim: Path, catalog: sessionmaker[Session], client: Celery,
        worker_env: dict[str, str], start_worker: Callable[..., Worker]) -> None:
    victim = start_worker(lambda name: pwm_worker_command(name, 1))
    _ingest(client, tiny_sim / "downlink")

    def refining() -> list[Job]:
        return _jobs(catalog, JobKind.REFINE, Job.status == JobStatus.RUNNING,
                     Job.progress >= 0.2)

    wait_for(lambda: bool(refining()), "a refinement under way", [victim])
    [job] = refining()
    assert job.worker.startswith(f"{victim.log.stem}@")
    victim.kill()  # the whole worker, as a lost machine: its task stays unacknowledged
    killed = time.monotonic()

    # No worker is left to take it over: it stays lost, and shows so.
    wait_for(lambda: [(j["id"], j["worker"]) for j in _lost_jobs(worker_env)] == [
        (job.id, job.worker)], "the job shown lost", [victim], timeout=60.0)
    lost_after_s = time.monotonic() - killed
    survivor = start_worker(lambda name: pwm_worker_command(name, 1))
    wait_for(lambda: _jobs(catalog, JobKind.REFINE, Job.id == job.id)[0].status is JobStatus.DONE,
             "the lost job done", [survivor], timeout=300.0)
    done_after_s = time.monotonic() - killed
    wait_for(lambda: len(_versions(catalog)) == 2, "the downlink's version", [survivor],
             timeout=DOWNLINK_TIMEOUT_S)
    [again] = _jobs(catalog, JobKind.REFINE, Job.id == job.id)
    assert (again.status, again.attempts) == (JobStatus.DONE, 2)
    assert again.worker.startswith(f"{survivor.log.stem}@")
    # Handed over by the survivor's reconciler (Redis would hand the task out only after its
    # visibility timeout), and its log says why.
    assert (f"reconciler: handing job {job.key} to the broker again: attempt 1 on {job.worker} "
            "lost: no heartbeat") in survivor.output()
    assert _revisions_by_maplet(catalog)[job.maplet_id] == 1
    refines = _jobs(catalog, JobKind.REFINE)
    assert all(j.status is JobStatus.DONE for j in refines)
    assert set(_revisions_by_maplet(catalog).values()) == {1}
    assert len(_versions(catalog)[-1].maplet_revisions) == len(refines)
    print(f"\nkilled worker's job shown lost after {lost_after_s:.1f} s (grace "
          f"{HEARTBEAT_GRACE_S:g} s); done {done_after_s:.1f} s after the kill by a worker started "
          "then")
