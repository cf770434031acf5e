"""Celery tasks: each runs one job of the jobs table (service.jobs), known by its key.

Every delivery claims the job first, so deliveries are idempotent: a job already done is not
done again, a job another live attempt holds is retried once that attempt could be lost, and a
job whose attempt stopped beating (its worker died) is taken over by the next delivery. While it
runs, an attempt records its heartbeat every heartbeat_s from a thread of its own. The outcome
(done with a summary, or failed with the traceback) is recorded in the job row, then returned
or raised to Celery; a failed attempt is tried again after a backoff, up to task_retries times
(workers.app.WorkerSettings).

The flow of a downlink, in the conductor's order (service.conductor), each task followed by the
conductor's rule for what comes next: ingest_downlink runs the stages up to the plan (catalogue,
adjust the poses, weigh, plan: service.conductor.ingest_and_plan) and submits one refine job per
maplet whose input changed; refine_revision makes the maplet's revision of that input
(service.refinement); fusion fans in through the jobs table rather than a chord: after every
delivery of a refine task, once the conductor's fan-in (service.conductor.fusion_due) says the
downlink's fusion is due, its fuse job is submitted and fuse_downlink publishes the new version
(service.publish) and feeds back (service.conductor.feed_back). The check runs after the refine
job's outcome is committed, so of refinements finishing together the last to commit sees all
done; fan-ins that both see it submit the same fuse key, and the claim makes the second delivery a no-op.
A fusion then submits, as refine jobs of the same downlink, the maplets whose revisions it fused
that the conductor's pass rule says are due (service.conductor.due_after_fusion), and their
fan-in the downlink's next fusion: one version per pass, as `pwm run` publishes them.

The broker may lose what it was given (an outage, a restart without persistence) or refuse it:
every hand-over goes through `_enqueue`, which records it in the job row (service.jobs
.mark_enqueued), and `reconcile`, run periodically by every worker (the Reconciler step, which
workers.app adds to each by name) and by `pwm watch`, hands over again what the jobs table says
is due (service.jobs.due_jobs) and submits the fusion of any downlink whose refinements are all
done without one.

Task names decide the queue (workers.app.TASK_ROUTES): ingest_* tasks go to `ingest`, refine_*
to `refine`, fuse_* to `fuse`.
"""

from __future__ import annotations

import logging
import os
import threading
import traceback
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from celery import Task, bootsteps
from sqlalchemy import event
from sqlalchemy.orm import Session, sessionmaker

from pwm.config import RefinementConfig
from service.conductor import adjust_lidar, due_after_fusion, feed_back, fusion_due, ingest_and_plan
from service.console.documents import make_mesh_document
from service.db import session_scope
from service.jobs import (
    JobBusy,
    JobLost,
    claim_job,
    due_jobs,
    error_reason,
    fail_job,
    finish_job,
    fuse_key,
    fusions_due,
    heartbeat,
    ingest_key,
    made_current,
    mark_enqueued,
    refine_key,
    refine_key_parts,
    reopen_job,
    report_progress,
    retry_job,
    submit_job,
)
from service.publish import first_version_with, fuse_and_publish
from service.refinement import MapletWork, refine_catalog_maplet, stale_maplets
from service.rows import Job, JobKind, JobStatus, Maplet
from service.spg import fed_back
from service.watch import last_change
from workers.app import QUEUES, ProcessState, app, get_worker_settings, process_state

log = logging.getLogger(__name__)

# A delivery that found its job busy comes again this long after the holder could be lost (s).
BUSY_SLACK_S = 1.0


@dataclass(frozen=True)
class Outcome:
    """What a job's work produced: a one-line summary and the catalog rows it concerns."""

    message: str
    downlink_id: int | None = None
    maplet_id: int | None = None


class CeleryQueue:
    """The service's job queue (service.jobs.JobQueue) run by these tasks: on the workers with
    a broker, else in the calling process."""

    def submit_ingest(self, directory: Path, *, sessions: sessionmaker[Session]) -> str:
        return submit_ingest(directory, sessions=sessions)

    def submit_refinement(self, session: Session, *, maplet_id: int) -> str:
        return submit_refinement(session, maplet_id=maplet_id)


def submit_ingest(directory: Path, *, sessions: sessionmaker[Session] | None = None) -> str:
    """Submit the ingest of the downlink in `directory` and enqueue it unless it is done and
    the directory unchanged since its ingest started; its job key. Idempotent: the key is
    ingest_key(directory). sessions: the catalog (default this process's,
    workers.app.process_state)."""
    path = Path(directory).resolve()
    key = ingest_key(path)
    changed = last_change(path)
    with session_scope(sessions or process_state().sessions) as session:
        job = submit_job(session, kind=JobKind.INGEST, key=key)
        done = job.status is JobStatus.DONE and not (changed is not None and reopen_job(
            session, job, changed_at=datetime.fromtimestamp(changed, UTC)))
    if not done:
        _enqueue(sessions or process_state().sessions, key,
                 lambda: ingest_downlink.apply_async(args=[str(path)], kwargs={"key": key}))
    return key


def submit_refinement(session: Session, *, maplet_id: int) -> str:
    """Submit the refinement of a maplet's current input (at the pass due), in the caller's
    transaction, and enqueue it (with its fusion, and its later passes, to follow) once that
    transaction commits; its job key.

    Raises LookupError for an unknown maplet, ValueError when its current revision is already
    of its current input or it has fewer than the configured minimum of usable images. A
    revision made with another configuration is not of its current input: the request is the
    operator asking for this maplet (service.refinement.stale_maplets, refine_on_config_change)."""
    if session.get(Maplet, maplet_id) is None:
        raise LookupError(f"no maplet {maplet_id}")
    config = get_worker_settings().refinement()
    stale = stale_maplets(session, config=config, maplet_ids=[maplet_id], refine_on_config_change=True)
    if not stale:
        raise ValueError(f"maplet {maplet_id} has nothing new to refine: its current revision is "
                         f"of its current input, or it has fewer than {config.min_images} images")
    if _submit_refine(session, None, stale[0]) is not None:
        sessions = sessionmaker(bind=session.get_bind())
        event.listen(session, "after_commit",
                     lambda _: _enqueue_refine(sessions, None, stale[0]), once=True)
    return refine_key(None, maplet_id, stale[0].input_hash)


@app.task(bind=True, max_retries=None)
def ingest_downlink(self: Task, directory: str, key: str | None = None) -> dict[str, Any]:
    """Catalogue the downlink in `directory` against the current model as the ingest job `key`
    (default ingest_key(directory)), then submit and enqueue the refinement of each maplet whose
    input changed."""
    path = Path(directory).resolve()

    def work(state: ProcessState, job: Job) -> Outcome:
        settings = get_worker_settings()
        with session_scope(state.sessions) as session:
            report_progress(session, job, 0.0, f"ingesting {path}")
        plan = ingest_and_plan(state.sessions, path, data_dir=settings.data_dir,
                               config=settings.refinement(),
                               refine_on_config_change=settings.refine_on_config_change)
        with session_scope(state.sessions) as session:
            pending = [w for w in plan.work if _submit_refine(session, plan.downlink_id, w)]
        # nothing to refine, so no fusion follows: the lidar it brought is adjusted here
        lidar = None if plan.work else adjust_lidar(state.sessions, data_dir=settings.data_dir,
                                                     downlink_id=plan.downlink_id, published=None,
                                                     current=plan.base_version)
        # Enqueued once their jobs are committed, so that the fan-in sees every sibling.
        for work_item in pending:
            _enqueue_refine(state.sessions, plan.downlink_id, work_item)
        then = (f"{len(plan.work)} maplets to refine from version {plan.base_version}"
                if plan.base_version is not None else
                "no model to refine yet (the downlink's model note says why)")
        said = "" if lidar is None else f"; {lidar.summary()}"
        return Outcome(f"{plan.ingest.summary()}; {then}{said}", downlink_id=plan.downlink_id)

    return _run_job(self, kind=JobKind.INGEST, key=key or ingest_key(path), work=work)


@app.task(bind=True, max_retries=None)
def refine_revision(self: Task, maplet_id: int, input_hash: str,
                  downlink_id: int | None = None) -> dict[str, Any]:
    """Refine the maplet's input `input_hash` (service.refinement.refine_catalog_maplet) as the
    job refine_key(downlink_id, maplet_id, input_hash), then fan in: submit and enqueue the
    fusion if this was the downlink's last refinement (or a requested one)."""
    key = refine_key(downlink_id, maplet_id, input_hash)

    def work(state: ProcessState, job: Job) -> Outcome:
        settings = get_worker_settings()

        def progress(fraction: float, message: str) -> None:
            with session_scope(state.sessions) as session:
                report_progress(session, job, fraction, message)

        revision = refine_catalog_maplet(state.sessions, data_dir=settings.data_dir,
                                         maplet_id=maplet_id, input_hash=input_hash,
                                         config=settings.refinement(), progress=progress)
        return Outcome(f"maplet {maplet_id}: revision {revision}", downlink_id=downlink_id,
                       maplet_id=maplet_id)

    result = _run_job(self, kind=JobKind.REFINE, key=key, work=work)
    # Also on a delivery that found the job done: its worker may have died before the fan-in.
    result["fuse"] = _fan_in(process_state().sessions, downlink_id=downlink_id, after=key)
    return result


@app.task(bind=True, max_retries=None)
def fuse_downlink(self: Task, downlink_id: int | None, key: str | None = None
                  ) -> dict[str, Any]:
    """Fuse the maplets' current revisions into a new version (service.publish) as the job `key`
    (default fuse_key(downlink_id)), with the downlink in its lineage; then submit and enqueue
    the next pass of the maplets whose current revision the downlink's (or the requested)
    refinements made. Also when nothing was published: an attempt may have died after
    publishing and before submitting."""
    key = key or fuse_key(downlink_id)

    def work(state: ProcessState, job: Job) -> Outcome:
        with session_scope(state.sessions) as session:
            report_progress(session, job, 0.0, "fusing")
        settings = get_worker_settings()
        config = settings.refinement()
        version = fuse_and_publish(state.sessions, data_dir=settings.data_dir,
                                   downlink_ids=[] if downlink_id is None else [downlink_id],
                                   config=config)
        if version is not None:
            make_mesh_document(state.sessions, data_dir=settings.data_dir, version=version)
        if version is not None and downlink_id is not None:
            feed_back(state.sessions, data_dir=settings.data_dir, downlink_id=downlink_id,
                      version=version, config=config)
        with session_scope(state.sessions) as session:
            # from the catalog, not from this attempt: one that died after the feedback left it there
            fed = downlink_id is not None and fed_back(session, downlink_id)
            later = [w for w in _next_passes(session, downlink_id=downlink_id, key=key, config=config, fed=fed,
                                             refine_on_config_change=settings.refine_on_config_change)
                     if _submit_refine(session, downlink_id, w)]
        for work_item in later:
            _enqueue_refine(state.sessions, downlink_id, work_item)
        # the downlink's last pass published: its tracks (all the catalog's) adjusted to the version
        lidar = (adjust_lidar(state.sessions, data_dir=settings.data_dir, downlink_id=downlink_id,
                              published=version, current=None)
                 if version is not None and downlink_id is not None and not later else None)
        then = f"; {len(later)} maplets due for another pass" if later else ""
        then += "" if lidar is None else f"; {lidar.summary()}"
        if version is not None:
            message = f"published version {version}"
        else:
            with state.sessions() as session:
                earlier = (None if downlink_id is None
                           else first_version_with(session, downlink_id=downlink_id))
            # Its refinements fused into a version by another downlink's fusion (which names
            # this downlink in its lineage): nothing left to publish.
            message = ("no maplet changed: no new version" if earlier is None else
                       f"its refinements were already published in version {earlier}")
        return Outcome(message + then, downlink_id=downlink_id)

    return _run_job(self, kind=JobKind.FUSE, key=key, work=work)


def _next_passes(session: Session, *, downlink_id: int | None, key: str, config: RefinementConfig,
                 fed: bool = False, refine_on_config_change: bool = False) -> list[MapletWork]:
    """The maplets due after the fusion (service.conductor.due_after_fusion, fed and
    refine_on_config_change as there)
    whose current revision the downlink's refine jobs made, or (downlink None) the requested
    refinement that the fuse job `key` follows made."""
    if downlink_id is None:
        try:
            _, maplet_id, _ = refine_key_parts(key.removeprefix("fuse:"))
        except ValueError:  # the catalog's own fusion follows no refinement
            return []
        made = made_current(session, downlink_id=None, maplet_ids=[maplet_id])
    else:
        made = made_current(session, downlink_id=downlink_id)
    return due_after_fusion(session, config=config, fed=fed, maplet_ids=made,
                            refine_on_config_change=refine_on_config_change)


def _submit_refine(session: Session, downlink_id: int | None, work: MapletWork) -> str | None:
    """Submit the refine job of `work`; its key, or None when that job is done already."""
    key = refine_key(downlink_id, work.maplet_id, work.input_hash)
    job = submit_job(session, kind=JobKind.REFINE, key=key, downlink_id=downlink_id,
                     maplet_id=work.maplet_id)
    return None if job.status is JobStatus.DONE else key


def _enqueue_refine(sessions: sessionmaker[Session], downlink_id: int | None,
                    work: MapletWork) -> None:
    _enqueue(sessions, refine_key(downlink_id, work.maplet_id, work.input_hash),
             _refine_sender(downlink_id, work.maplet_id, work.input_hash))


def _refine_sender(downlink_id: int | None, maplet_id: int, input_hash: str
                   ) -> Callable[[], object]:
    return lambda: refine_revision.apply_async(kwargs={
        "maplet_id": maplet_id, "input_hash": input_hash, "downlink_id": downlink_id})


def _fuse_sender(downlink_id: int | None, key: str) -> Callable[[], object]:
    return lambda: fuse_downlink.apply_async(kwargs={"downlink_id": downlink_id, "key": key})


def _sender(job: Job) -> Callable[[], object]:
    """What hands the job over to the broker, from its key (the key functions' formats)."""
    rest = job.key.split(":", 1)[1]
    if job.kind is JobKind.INGEST:
        return lambda: ingest_downlink.apply_async(args=[rest], kwargs={"key": job.key})
    if job.kind is JobKind.REFINE:
        return _refine_sender(*refine_key_parts(job.key))
    # fuse:<downlink id>[:<nth>], fuse:None (the catalog's), or fuse:<requested refine key>
    downlink = rest.split(":", 1)[0]
    return _fuse_sender(int(downlink) if downlink.isdigit() else None, job.key)


def _enqueue(sessions: sessionmaker[Session], key: str, send: Callable[[], object]) -> None:
    """Hand the job `key` to the broker with `send` and record it in the job row; a broker that
    refuses it is recorded too (the reconciler hands it over again), not raised. In eager mode
    (no broker) `send` runs the job here, and its errors are raised."""
    if app.conf.task_always_eager:
        send()
        return
    try:
        send()
    except Exception as exc:  # the broker is unreachable or refused it: record, retry later
        error = f"{type(exc).__name__}: {exc}"
        log.warning("could not hand job %s to the broker, left to the reconciler: %s", key,
                    error)
        with session_scope(sessions) as session:
            mark_enqueued(session, key=key, error=error)
        return
    with session_scope(sessions) as session:
        mark_enqueued(session, key=key)


def reconcile(sessions: sessionmaker[Session] | None = None) -> list[str]:
    """Hand over again the jobs the jobs table says are due (service.jobs.due_jobs) and submit
    the fusion of each downlink whose refinements are all done without one; the keys handed
    over. Queued jobs of a kind whose queue still holds messages are left: theirs may be among
    them. Raises when the broker cannot be reached (nothing is changed then)."""
    settings = get_worker_settings()
    sessions = sessions or process_state().sessions
    waiting = _waiting_kinds()
    with session_scope(sessions) as session:
        sends: list[tuple[str, str, Callable[[], object]]] = []
        for downlink_id, key in fusions_due(session).items():
            submit_job(session, kind=JobKind.FUSE, key=key, downlink_id=downlink_id)
            sends.append((key, "its downlink's refinements are all done, with no fusion",
                          _fuse_sender(downlink_id, key)))
        for job, reason in due_jobs(session, grace_s=settings.heartbeat_grace_s,
                                    requeue_after_s=settings.requeue_after_s,
                                    retries=settings.task_retries,
                                    backoff_s=settings.retry_backoff_s, waiting_kinds=waiting):
            sends.append((job.key, reason, _sender(job)))
    for key, reason, send in sends:
        log.warning("reconciler: handing job %s to the broker again: %s", key, reason)
        _enqueue(sessions, key, send)
    return [key for key, _, _ in sends]


def reconcile_pass() -> None:
    """reconcile, with a broker or database that cannot be reached logged, not raised: the next
    pass tries again (the workers' Reconciler and `pwm watch` run it periodically)."""
    try:
        reconcile()
    except Exception as exc:
        log.warning("reconciler: pass skipped: %s: %s", type(exc).__name__, exc)


class Reconciler(bootsteps.StartStopStep):
    """Runs `reconcile_pass` every reconcile_interval_s on the consumer's timer, in the worker's
    main process (not a thread: the pool forks from it).

    A step of the consumer, not of the worker: when the broker connection drops, the consumer
    clears its timer (celery's Consumer.on_close) and restarts its steps once it is connected
    again, so that a step of the worker would never run again after a broker outage, the moment
    it is needed most."""

    requires = {"celery.worker.consumer.tasks:Tasks"}

    def __init__(self, consumer: Any, **kwargs: Any) -> None:
        super().__init__(consumer, **kwargs)
        self.timer_ref: Any = None

    def start(self, consumer: Any) -> None:
        self.timer_ref = consumer.timer.call_repeatedly(
            get_worker_settings().reconcile_interval_s, self.run)

    def stop(self, consumer: Any) -> None:
        if self.timer_ref is not None:
            self.timer_ref.cancel()
            self.timer_ref = None

    shutdown = stop

    def run(self) -> None:
        reconcile_pass()


def retry(job_id: int, *, sessions: sessionmaker[Session] | None = None) -> str:
    """Queue the failed or lost job `job_id` again (service.jobs.retry_job) and hand it to the
    broker (or run it here without one); its key. Raises LookupError or ValueError as
    retry_job does."""
    sessions = sessions or process_state().sessions
    with session_scope(sessions) as session:
        job = retry_job(session, job_id, grace_s=get_worker_settings().heartbeat_grace_s)
        send = _sender(job)
    _enqueue(sessions, job.key, send)
    return job.key


def _waiting_kinds() -> set[JobKind]:
    """The job kinds whose queue holds messages not yet delivered."""
    with app.connection_for_write() as connection:
        connection.ensure_connection(max_retries=1)  # a broker away fails the pass at once
        channel = connection.default_channel
        return {JobKind(queue) for queue in QUEUES
                if channel.queue_declare(queue=queue, durable=True, auto_delete=False
                                         ).message_count}


def _fan_in(sessions: sessionmaker[Session], *, downlink_id: int | None, after: str
            ) -> str | None:
    """Submit and enqueue the fusion that follows the refine job `after` when the conductor's
    fan-in says it is due (service.conductor.fusion_due). Its key, or None when not due."""
    with session_scope(sessions) as session:
        key = fusion_due(session, downlink_id=downlink_id, after=after)
        if key is None:
            return None
        done = submit_job(session, kind=JobKind.FUSE, key=key,
                          downlink_id=downlink_id).status is JobStatus.DONE
    if not done:
        _enqueue(sessions, key, _fuse_sender(downlink_id, key))
    return key


def _run_job(task: Task, *, kind: JobKind, key: str,
             work: Callable[[ProcessState, Job], Outcome]) -> dict[str, Any]:
    """Claim the job `key`, run `work` as one attempt at it, beating while it runs, and record
    the outcome; a failed attempt is retried after retry_backoff_s * 2**(attempt - 1) while
    attempts <= task_retries."""
    state = process_state()
    settings = get_worker_settings()
    worker = f"{task.request.hostname or 'local'}:{os.getpid()}"
    try:
        with session_scope(state.sessions) as session:
            job = claim_job(session, kind=kind, key=key, grace_s=settings.heartbeat_grace_s,
                            worker=worker)
    except JobBusy as busy:
        log.info("job %s: %s; delivered again then", key, busy)
        raise task.retry(exc=busy, countdown=busy.retry_after_s + BUSY_SLACK_S) from busy
    if job is None:
        return {"key": key, "status": "done", "ran": False}
    try:
        with _beating(state.sessions, job, interval_s=settings.heartbeat_s):
            outcome = work(state, job)
    except Exception as exc:
        error = traceback.format_exc()
        with session_scope(state.sessions) as session:
            fail_job(session, job, error=error)
        reason = error_reason(error)
        if job.attempts <= settings.task_retries:
            countdown = settings.retry_backoff_s * 2 ** (job.attempts - 1)
            log.warning("job %s: attempt %d failed (%s); retried in %.1f s (%d of %d)", key,
                        job.attempts, reason, countdown, job.attempts, settings.task_retries)
            raise task.retry(exc=exc, countdown=countdown) from exc
        log.error("job %s: attempt %d failed (%s); no retries left: `pwm jobs retry %d` runs "
                  "it again", key, job.attempts, reason, job.id)
        raise
    with session_scope(state.sessions) as session:
        finish_job(session, job, message=outcome.message, downlink_id=outcome.downlink_id,
                   maplet_id=outcome.maplet_id)
    return {"key": key, "status": "done", "ran": True, "attempt": job.attempts,
            "message": outcome.message}


@contextmanager
def _beating(sessions: sessionmaker[Session], job: Job, *, interval_s: float) -> Iterator[None]:
    """Record the attempt's heartbeat every interval_s from a thread while the block runs. The
    thread only writes the job row: SPICE, which is not thread-safe, stays with the task."""
    stop = threading.Event()

    def beat() -> None:
        while not stop.wait(interval_s):
            try:
                with session_scope(sessions) as session:
                    heartbeat(session, job)
            except JobLost:
                return  # taken over: the attempt's outcome will be refused too
            except Exception as exc:  # the database briefly away: the next beat may pass
                log.warning("job %s: heartbeat not recorded: %s", job.key, exc)

    thread = threading.Thread(target=beat, name=f"heartbeat {job.key}", daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()
