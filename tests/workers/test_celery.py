"""Distributed execution with real servers: `celery -A workers.app worker` processes (prefork, one
child) fed by a Redis broker, writing to a PostgreSQL catalog; the jobs table's claims on both
databases. Nothing is mocked: workers are killed with SIGKILL and Redis redelivers their task."""

from __future__ import annotations

import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest
import redis
import spiceypy as sp
from celery import Celery
from celery.result import AsyncResult
from harness import REPO, RESULT_TIMEOUT_S, Worker, celery_worker_command, logs, result_of, wait_for
from sqlalchemy import func, select, update
from sqlalchemy.orm import Session, sessionmaker

from pwm.io.spice_kernels import kernel_pool
from pwm.simulate.windows import window_downlink
from service.conductor import START_MODEL_NAME
from service.db import make_engine, make_sessionmaker, session_scope, upgrade
from service.ingest import COMMIT_EVERY, ingest_directory
from service.jobs import (
    JobBusy,
    JobLost,
    JobState,
    claim_job,
    due_jobs,
    fail_job,
    find_jobs,
    finish_job,
    fuse_key,
    fusions_due,
    heartbeat,
    job_state,
    mark_enqueued,
    refine_key,
    report_progress,
    retry_job,
    submit_job,
)
from service.kernels import accepted_kernels
from service.rows import (
    Base,
    Downlink,
    DownlinkStatus,
    GeometryStatus,
    Image,
    ImageStatus,
    Job,
    JobKind,
    JobStatus,
    Kernel,
    ModelKind,
)
from service.versions import import_model
from workers.app import QUEUES, ProcessState, WorkerSettings, make_app
from workers.tasks import ingest_downlink, ingest_key

# Short limits so that a lost task comes back within seconds: the hard time limit must outlast
# the slowest attempt here (the big downlink's ingest, 6 s alone, on a loaded machine), and
# Redis redelivers after the visibility timeout; a reconciler hands a lost attempt's job over
# once its heartbeat is HEARTBEAT_GRACE_S old.
TIME_LIMIT_S, VISIBILITY_TIMEOUT_S = 20.0, 24.0
HEARTBEAT_S, HEARTBEAT_GRACE_S, RECONCILE_INTERVAL_S, REQUEUE_AFTER_S = 0.5, 3.0, 1.0, 10.0
# A failed attempt is tried again this many times, after this backoff (s).
TASK_RETRIES, RETRY_BACKOFF_S = 2, 0.2
# An ingest plans the refinement of what its images see: one small maplet here, so that the
# refinement and fusion that follow take a moment.
MAPLET_NODES, TILE_RADIUS_KM = 8, 1e-4
REPEATS = 50  # repeat observations of each tiny image: 300 products, over COMMIT_EVERY
WINDOW_PX = 16


@pytest.fixture
def settings(broker_url: str, postgres_url: str, tmp_path: Path) -> WorkerSettings:
    return WorkerSettings(broker_url=broker_url, database_url=postgres_url,
                          data_dir=tmp_path / "data", job_time_limit_s=TIME_LIMIT_S,
                          visibility_timeout_s=VISIBILITY_TIMEOUT_S, task_retries=TASK_RETRIES,
                          retry_backoff_s=RETRY_BACKOFF_S, maplet_nodes=MAPLET_NODES,
                          tile_radius_km=TILE_RADIUS_KM, heartbeat_s=HEARTBEAT_S,
                          heartbeat_grace_s=HEARTBEAT_GRACE_S,
                          reconcile_interval_s=RECONCILE_INTERVAL_S,
                          requeue_after_s=REQUEUE_AFTER_S)


def _send_ingest(client: Celery, directory: Path, key: str) -> AsyncResult:
    return client.send_task(ingest_downlink.name, args=[str(directory)], kwargs={"key": key})


def _job(sessions: sessionmaker[Session], key: str) -> Job:
    with sessions() as session:
        return session.scalars(select(Job).filter_by(key=key)).one()


def _count(sessions: sessionmaker[Session], what: type[Base], *where) -> int:
    with sessions() as session:
        return session.scalar(select(func.count()).select_from(what).where(*where))


@pytest.fixture(scope="module")
def big_downlink(tiny_sim: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The tiny downlink's kernels and REPEATS repeat observations of each of its images:
    distinct products (LIDs of their own, a WINDOW_PX window of the same exposure each)."""
    source = tiny_sim / "downlink"
    root = tmp_path_factory.mktemp("big") / "downlink"
    window_downlink(source, root, size_px=WINDOW_PX, first_px=(0, 0),
                    count=REPEATS * len(list((source / "images").glob("*.xml"))), tag="r")
    return root


def test_tasks_are_routed_to_the_queue_of_their_kind(tmp_path: Path) -> None:
    client = make_app(WorkerSettings(broker_url="redis://127.0.0.1:1/0", data_dir=tmp_path,
                                     job_time_limit_s=60.0, visibility_timeout_s=90.0))
    route = client.amqp.router.route({}, ingest_downlink.name)
    assert route["queue"].name == JobKind.INGEST.value
    assert set(QUEUES) == {kind.value for kind in JobKind}
    options = client.conf.broker_transport_options
    assert options["visibility_timeout"] > client.conf.task_time_limit
    assert client.conf.task_acks_late and client.conf.task_reject_on_worker_lost


def test_a_worker_refuses_the_thread_pool(worker_env: dict[str, str]) -> None:
    result = subprocess.run(celery_worker_command("pwm-test-threads", "threads"), cwd=REPO,
                            env=worker_env, capture_output=True, text=True, timeout=60)
    assert result.returncode != 0
    assert "not thread-safe" in result.stderr and " ready." not in result.stderr


def test_ingest_through_the_broker_records_progress_and_errors(
        tiny_sim: Path, catalog: sessionmaker[Session], client: Celery,
        start_worker: Callable[[], Worker]) -> None:
    worker = start_worker()
    downlink = tiny_sim / "downlink"
    key = ingest_key(downlink)
    with session_scope(catalog) as session:
        queued = submit_job(session, kind=JobKind.INGEST, key=key)
    assert (queued.status, queued.attempts, queued.started_at) == (JobStatus.QUEUED, 0, None)

    result = result_of(_send_ingest(client, downlink, key), [worker])

    job = _job(catalog, key)
    labels = sorted((downlink / "images").glob("*.xml"))
    assert result["ran"] and result["attempt"] == 1
    assert (job.id, job.status, job.attempts, job.progress) == (queued.id, JobStatus.DONE, 1, 1.0)
    assert queued.created_at <= job.started_at <= job.finished_at
    assert job.error is None and f"images {len(labels)} accepted" in job.message
    with catalog() as session:
        row = session.get(Downlink, job.downlink_id)
        assert (Path(row.path), row.status) == (downlink.resolve(), DownlinkStatus.INGESTED)
        images = session.scalars(select(Image)).all()
    assert sorted(Path(i.label_path).name for i in images) == [p.name for p in labels]
    assert all(i.status is ImageStatus.ACCEPTED for i in images)
    assert all(i.geometry_status is GeometryStatus.COMPUTED for i in images)

    missing = tiny_sim / "not-delivered"
    with pytest.raises(NotADirectoryError):
        _send_ingest(client, missing, ingest_key(missing)).get(timeout=RESULT_TIMEOUT_S)
    failed = _job(catalog, ingest_key(missing))
    # Tried again a bounded number of times, each failure recorded.
    assert (failed.status, failed.attempts) == (JobStatus.FAILED, TASK_RETRIES + 1)
    assert "NotADirectoryError" in failed.error and failed.finished_at >= failed.started_at
    assert worker.process.poll() is None
    print(f"\nworker ready in {worker.startup_s:.2f} s")


def test_a_repeated_delivery_does_no_new_work(tiny_sim: Path, catalog: sessionmaker[Session],
                                              client: Celery,
                                              start_worker: Callable[[], Worker]) -> None:
    worker = start_worker()
    downlink = tiny_sim / "downlink"
    key = ingest_key(downlink)
    first, second = (_send_ingest(client, downlink, key) for _ in range(2))
    first_result = result_of(first, [worker])
    job = _job(catalog, key)
    counted = [(Image,), (Kernel,), (Downlink,), (Job, Job.kind == JobKind.INGEST)]
    counts = [_count(catalog, *what) for what in counted]

    second_result = result_of(second, [worker])
    third_result = result_of(_send_ingest(client, downlink, key), [worker])

    assert first_result["ran"] and first_result["attempt"] == 1
    assert not second_result["ran"] and not third_result["ran"]
    again = _job(catalog, key)
    assert (again.id, again.attempts, again.status) == (job.id, 1, JobStatus.DONE)
    assert (again.started_at, again.finished_at) == (job.started_at, job.finished_at)
    assert [_count(catalog, *what) for what in counted] == counts
    assert counts[0] == len(list((downlink / "images").glob("*.xml"))) and counts[3] == 1


def test_a_task_lost_with_its_worker_is_redelivered_and_done_once(
        big_downlink: Path, catalog: sessionmaker[Session], client: Celery, broker_url: str,
        start_worker: Callable[[], Worker], tiny_sim: Path, settings: WorkerSettings) -> None:
    with session_scope(catalog) as session:
        import_model(session, data_dir=settings.data_dir, kind=ModelKind.START,
                     path=tiny_sim / "downlink" / START_MODEL_NAME)
    first_worker = start_worker()
    key = ingest_key(big_downlink)
    labels = list((big_downlink / "images").glob("*.xml"))
    pending = _send_ingest(client, big_downlink, key)

    assert len(labels) > COMMIT_EVERY
    wait_for(lambda: _count(catalog, Image) >= COMMIT_EVERY, "the image pass's first commit",
             [first_worker])
    first_worker.kill()
    killed_at = datetime.now(UTC)
    job = _job(catalog, key)
    with catalog() as session:
        interrupted = session.scalars(select(Downlink)).one()
    assert (job.status, job.attempts, job.message) == (
        JobStatus.RUNNING, 1, f"ingesting {big_downlink.resolve()}")
    assert interrupted.status is DownlinkStatus.INGESTING
    assert COMMIT_EVERY <= _count(catalog, Image) < len(labels)

    second_worker = start_worker()
    # The second worker's reconciler hands the lost job over again once its heartbeat is the
    # grace old, long before Redis hands the unacknowledged message out again (after the
    # visibility timeout, at kombu's next restore of unacknowledged messages: its cadence
    # differs between kombu versions, so the test does not wait for it).
    wait_for(lambda: _job(catalog, key).status is JobStatus.DONE, "the job done",
             [first_worker, second_worker], timeout=VISIBILITY_TIMEOUT_S + RESULT_TIMEOUT_S)

    done = _job(catalog, key)
    assert (done.status, done.attempts, done.progress) == (JobStatus.DONE, 2, 1.0), logs(
        [first_worker, second_worker])
    # Taken over only once the first attempt's heartbeat was the grace old.
    assert done.started_at - job.heartbeat_at >= timedelta(seconds=HEARTBEAT_GRACE_S)
    with catalog() as session:
        lidvids = session.scalars(select(Image.lidvid)).all()
        downlink = session.scalars(select(Downlink)).one()
    assert len(lidvids) == len(set(lidvids)) == len(labels)
    assert downlink.status is DownlinkStatus.INGESTED and downlink.id == interrupted.id
    assert _count(catalog, Job, Job.kind == JobKind.INGEST) == 1
    # The original message: still unacknowledged in Redis (handed out again later), or already
    # handed out again, when it found the job done and did nothing. (Beside it may be the
    # refinements the ingest planned, and the hand-over's own message until it returns.)
    broker = redis.Redis.from_url(broker_url)
    original = [m for m in broker.hvals("unacked") if pending.id.encode() in m]
    assert pending.ready() or len(original) == 1
    broker.close()
    if pending.ready():
        assert not pending.get(timeout=RESULT_TIMEOUT_S)["ran"]
    assert _job(catalog, key).attempts == 2
    print(f"\nworkers ready in {first_worker.startup_s:.2f} s and {second_worker.startup_s:.2f} s;"
          f" redelivered {(done.started_at - killed_at).total_seconds():.2f} s after the kill, "
          f"{(done.started_at - job.started_at).total_seconds():.2f} s after the first attempt"
          f" (visibility timeout {VISIBILITY_TIMEOUT_S:g} s); second attempt "
          f"{(done.finished_at - done.started_at).total_seconds():.2f} s")


@pytest.fixture(params=["sqlite", "postgres"])
def jobs_db(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[sessionmaker[Session]]:
    url = (f"sqlite:///{tmp_path / 'catalog.sqlite'}" if request.param == "sqlite"
           else request.getfixturevalue("postgres_url"))
    upgrade(url)
    engine = make_engine(url)
    yield make_sessionmaker(engine)
    engine.dispose()


def test_claims_follow_the_heartbeat_and_fence_stale_attempts(
        jobs_db: sessionmaker[Session]) -> None:
    kind, key, grace_s = JobKind.REFINE, "refine:test", 60.0
    t0 = datetime(2030, 1, 1, tzinfo=UTC)
    with session_scope(jobs_db) as session:
        first = claim_job(session, kind=kind, key=key, grace_s=grace_s, worker="a@host:1", now=t0)
    assert (first.status, first.attempts, first.started_at, first.heartbeat_at, first.worker) == (
        JobStatus.RUNNING, 1, t0, t0, "a@host:1")
    with session_scope(jobs_db) as session, pytest.raises(JobBusy, match="a@host:1") as busy:
        claim_job(session, kind=kind, key=key, grace_s=grace_s, now=t0 + timedelta(seconds=45))
    assert busy.value.retry_after_s == pytest.approx(15.0)
    # A heartbeat keeps the attempt alive past the grace counted from its start.
    with session_scope(jobs_db) as session:
        report_progress(session, first, 0.25, "a quarter")
        heartbeat(session, first, now=t0 + timedelta(seconds=50))
    assert (_job(jobs_db, key).progress, _job(jobs_db, key).message) == (0.25, "a quarter")
    assert job_state(_job(jobs_db, key), grace_s=grace_s,
                     now=t0 + timedelta(seconds=100)) is JobState.RUNNING
    with session_scope(jobs_db) as session, pytest.raises(JobBusy) as busy:
        claim_job(session, kind=kind, key=key, grace_s=grace_s, now=t0 + timedelta(seconds=100))
    assert busy.value.retry_after_s == pytest.approx(10.0)
    # Silent for longer than the grace: lost, and the next delivery takes it over.
    lost_at = t0 + timedelta(seconds=111)
    assert job_state(_job(jobs_db, key), grace_s=grace_s, now=lost_at) is JobState.LOST
    with jobs_db() as session:
        for state, count in ((JobState.LOST, 1), (JobState.RUNNING, 0)):
            assert find_jobs(session, grace_s=grace_s, state=state, now=lost_at)[0] == count
    with session_scope(jobs_db) as session:
        second = claim_job(session, kind=kind, key=key, grace_s=grace_s, worker="b@host:2",
                           now=lost_at)
    assert (second.id, second.attempts, second.progress, second.worker) == (
        first.id, 2, 0.0, "b@host:2")
    # The first attempt's worker was presumed dead: it may no longer write.
    for stale in (lambda s: report_progress(s, first, 0.5),
                  lambda s: heartbeat(s, first),
                  lambda s: finish_job(s, first, message="stale"),
                  lambda s: fail_job(s, first, error="stale")):
        with pytest.raises(JobLost), session_scope(jobs_db) as session:
            stale(session)
    with session_scope(jobs_db) as session:
        fail_job(session, second, error="Traceback: boom")
    assert (_job(jobs_db, key).status, _job(jobs_db, key).error) == (
        JobStatus.FAILED, "Traceback: boom")
    with session_scope(jobs_db) as session:
        third = claim_job(session, kind=kind, key=key, grace_s=grace_s,
                          now=t0 + timedelta(seconds=112))
        assert third.error is None
    with session_scope(jobs_db) as session:
        finish_job(session, third, message="solved")
    with session_scope(jobs_db) as session:
        assert claim_job(session, kind=kind, key=key, grace_s=grace_s) is None
        assert submit_job(session, kind=kind, key=key).status is JobStatus.DONE
        with pytest.raises(ValueError, match="refine job"):
            claim_job(session, kind=JobKind.FUSE, key=key, grace_s=grace_s)
    row = _job(jobs_db, key)
    assert (row.status, row.attempts, row.progress, row.message) == (
        JobStatus.DONE, 3, 1.0, "solved")
    assert _count(jobs_db, Job) == 1


def test_the_reconciler_finds_what_the_table_says_is_due(
        jobs_db: sessionmaker[Session]) -> None:
    grace_s, requeue_s, retries, backoff_s = 60.0, 100.0, 1, 10.0

    def due(after_s: float, waiting: tuple[JobKind, ...] = ()) -> dict[str, str]:
        with session_scope(jobs_db) as session:
            return {job.key: why for job, why in due_jobs(
                session, grace_s=grace_s, requeue_after_s=requeue_s, retries=retries,
                backoff_s=backoff_s, waiting_kinds=waiting,
                now=t0 + timedelta(seconds=after_s))}

    with session_scope(jobs_db) as session:
        session.add_all([Downlink(name=f"dl-{k}", path=f"/x/dl-{k}") for k in (1, 2)])
    with jobs_db() as session:
        dl1, dl2 = session.scalars(select(Downlink.id).order_by(Downlink.id)).all()
    with session_scope(jobs_db) as session:
        queued = submit_job(session, kind=JobKind.INGEST, key="ingest:/x/dl-1")
        t0 = queued.created_at
        running = claim_job(session, kind=JobKind.REFINE, key=refine_key(dl1, 1, "a"),
                            grace_s=grace_s, downlink_id=dl1, worker="w@h:1",
                            now=t0)
        failed = claim_job(session, kind=JobKind.REFINE, key=refine_key(dl2, 1, "b"),
                           grace_s=grace_s, downlink_id=dl2, now=t0)
        fail_job(session, failed, error="Traceback: boom")
    with session_scope(jobs_db) as session:  # failed at t0 + its wall time: about t0
        session.execute(update(Job).where(Job.id == failed.id).values(finished_at=t0))
    assert due(50) == {}
    # The running attempt, silent since t0: lost after the grace, handed over (whatever the
    # queues hold), then not again until requeue_after_s later.
    assert due(70, waiting=(JobKind.INGEST,)) == {
        refine_key(dl1, 1, "a"): "attempt 1 on w@h:1 lost: no heartbeat for 70 s"}
    # Queued past requeue_after_s: handed over once its queue holds no message, then not again
    # until requeue_after_s after that.
    assert due(101, waiting=(JobKind.INGEST,)) == {}
    assert due(105) == {"ingest:/x/dl-1": "queued with no attempt for 105 s"}
    # Failed with a retry left and none came: due after its backoff and requeue_after_s.
    assert due(111) == {refine_key(dl2, 1, "b"): "attempt 1 failed, with no retry since for 111 s"}
    # A heartbeat: alive again.
    with session_scope(jobs_db) as session:
        heartbeat(session, running, now=t0 + timedelta(seconds=200))
    assert refine_key(dl1, 1, "a") not in due(230)
    # A failed hand-over: due at the next pass.
    with session_scope(jobs_db) as session:
        mark_enqueued(session, key="ingest:/x/dl-1", error="OperationalError: refused")
    assert due(231) == {"ingest:/x/dl-1": "its hand-over failed: OperationalError: refused"}
    # A lost job can be retried by hand; a live one cannot.
    with session_scope(jobs_db) as session:
        with pytest.raises(ValueError, match="running"):
            retry_job(session, running.id, grace_s=grace_s, now=t0 + timedelta(seconds=201))
        assert retry_job(session, running.id, grace_s=grace_s,
                         now=t0 + timedelta(seconds=300)).status is JobStatus.QUEUED
    # Downlink 2's refinements are all done once its failed one is; with no fusion job, its
    # fusion is due; downlink 1's refinement still runs.
    with session_scope(jobs_db) as session:
        assert fusions_due(session) == {}
        retried = retry_job(session, failed.id, grace_s=grace_s)
        assert (retried.status, retried.attempts) == (JobStatus.QUEUED, 1)
        again = claim_job(session, kind=JobKind.REFINE, key=retried.key, grace_s=grace_s)
        finish_job(session, again, message="done")
        assert fusions_due(session) == {dl2: fuse_key(dl2)}
        submit_job(session, kind=JobKind.FUSE, key=fuse_key(dl2), downlink_id=dl2)
        assert fusions_due(session) == {}
        with pytest.raises(ValueError, match="only failed or lost"):
            retry_job(session, again.id, grace_s=grace_s)
        with pytest.raises(LookupError):
            retry_job(session, 999999, grace_s=grace_s)


def test_concurrent_first_deliveries_claim_once(postgres_url: str) -> None:
    upgrade(postgres_url)
    engine = make_engine(postgres_url)
    sessions = make_sessionmaker(engine)
    barrier = threading.Barrier(4)
    outcomes: list[str] = []

    def deliver() -> None:
        barrier.wait()
        try:
            with session_scope(sessions) as session:
                claim_job(session, kind=JobKind.FUSE, key="fuse:race", grace_s=60.0)
                time.sleep(0.2)  # hold the row lock while the others queue up on it
            outcomes.append("claimed")
        except JobBusy:
            outcomes.append("busy")

    threads = [threading.Thread(target=deliver) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    engine.dispose()
    assert sorted(outcomes) == ["busy"] * 3 + ["claimed"]
    assert _job(sessions, "fuse:race").attempts == 1


def test_process_state_loads_kernels_once_until_the_pool_changes(
        tiny_sim: Path, tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'catalog.sqlite'}"
    upgrade(url)
    state = ProcessState(url)
    ingest_directory(state.sessions, tiny_sim / "downlink")
    with state.sessions() as session:
        assert state.load_kernels(session)
        loaded = sp.ktotal("ALL")
        assert loaded == len(accepted_kernels(session)) > 0
        assert not state.load_kernels(session)
        with kernel_pool([]):  # as an ingest leaves it: cleared
            pass
        assert state.load_kernels(session)
        assert sp.ktotal("ALL") == loaded
    sp.kclear()
    state.engine.dispose()
