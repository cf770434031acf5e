"""Celery tasks: each runs one job of the jobs table (service.jobs), known by its key.

Every delivery claims the job first, so deliveries are idempotent: a job already done is not
done again, a job another attempt holds is retried once that attempt's lease ends, and a job
whose worker died is taken over by the redelivery. The outcome (done with a summary, or failed
with the traceback) is recorded in the job row, then returned or raised to Celery; a failed
attempt is tried again after a backoff, up to task_retries times (workers.app.WorkerSettings).

The flow of a downlink: ingest_downlink catalogues it against the current model
(service.run.ingest_and_plan) and submits one refine job per maplet whose input changed;
refine_revision makes the maplet's revision of that input (service.refinement); fusion fans in
through the jobs table rather than a chord: after every delivery of a refine task, once no
refine job of its downlink is left unfinished, the downlink's fuse job is submitted and
fuse_downlink publishes the new version (service.publish). The check runs after the refine
job's outcome is committed, so of refinements finishing together the last to commit sees all
done; fan-ins that both see it submit the same fuse key, and the claim makes the second delivery a no-op.

Task names decide the queue (workers.app.TASK_ROUTES): ingest_* tasks go to `ingest`, refine_*
to `refine`, fuse_* to `fuse`.
"""

from __future__ import annotations

import traceback
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from celery import Task
from sqlalchemy import event, func, select
from sqlalchemy.orm import Session, sessionmaker

from service.db import session_scope
from service.jobs import JobBusy, claim_job, fail_job, finish_job, report_progress, submit_job
from service.models import Job, JobKind, JobStatus, Maplet
from service.publish import fuse_and_publish
from service.refinement import MapletWork, refine_catalog_maplet, stale_maplets
from service.run import ingest_and_plan
from workers.app import ProcessState, app, get_worker_settings, process_state

# A retried delivery waits this long past the end of the lease that made it wait (s).
LEASE_SLACK_S = 1.0
# Marks the refine and fuse keys of a refinement asked for outside any downlink.
REQUESTED = "requested"


@dataclass(frozen=True)
class Outcome:
    """What a job's work produced: a one-line summary and the catalog rows it concerns."""

    message: str
    downlink_id: int | None = None
    maplet_id: int | None = None


def ingest_key(directory: str | Path) -> str:
    """The idempotency key of ingesting `directory`: its absolute path. A directory whose
    content changes after it was ingested needs a key of its own to be ingested again."""
    return f"ingest:{Path(directory).resolve()}"


def refine_key(downlink_id: int | None, maplet_id: int, input_hash: str) -> str:
    """The key of refining a maplet's input (its hash) for a downlink, or on request (None)."""
    return f"refine:{REQUESTED if downlink_id is None else downlink_id}:{maplet_id}:{input_hash}"


def fuse_key(downlink_id: int | None) -> str:
    """The key of fusing a downlink's refinements (None: the catalog's) into a new version."""
    return f"fuse:{downlink_id}"


class CeleryQueue:
    """The service's job queue (service.jobs.JobQueue) run by these tasks: on the workers with
    a broker, else in the calling process."""

    def submit_ingest(self, directory: Path, *, sessions: sessionmaker[Session]) -> str:
        return submit_ingest(directory, sessions=sessions)

    def submit_refinement(self, session: Session, *, maplet_id: int) -> str:
        return submit_refinement(session, maplet_id=maplet_id)


def submit_ingest(directory: Path, *, sessions: sessionmaker[Session] | None = None) -> str:
    """Submit the ingest of the downlink in `directory` and enqueue it unless it is done; its
    job key. Idempotent: the key is ingest_key(directory). sessions: the catalog (default this
    process's, workers.app.process_state)."""
    path = Path(directory).resolve()
    key = ingest_key(path)
    with session_scope(sessions or process_state().sessions) as session:
        done = submit_job(session, kind=JobKind.INGEST, key=key).status is JobStatus.DONE
    if not done:
        ingest_downlink.apply_async(args=[str(path)], kwargs={"key": key})
    return key


def submit_refinement(session: Session, *, maplet_id: int) -> str:
    """Submit the refinement of a maplet's current input, in the caller's transaction, and
    enqueue it (with its fusion to follow) once that transaction commits; its job key.

    Raises LookupError for an unknown maplet, ValueError when its current revision is already
    of its current input or it has fewer than the configured minimum of usable images."""
    if session.get(Maplet, maplet_id) is None:
        raise LookupError(f"no maplet {maplet_id}")
    config = get_worker_settings().refinement()
    stale = stale_maplets(session, config=config, maplet_ids=[maplet_id])
    if not stale:
        raise ValueError(f"maplet {maplet_id} has nothing new to refine: its current revision is "
                         f"of its current input, or it has fewer than {config.min_images} images")
    if _submit_refine(session, None, stale[0]) is not None:
        event.listen(session, "after_commit", lambda _: _enqueue_refine(None, stale[0]),
                     once=True)
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
                               config=settings.refinement())
        with session_scope(state.sessions) as session:
            pending = [w for w in plan.work if _submit_refine(session, plan.downlink_id, w)]
        # Enqueued once their jobs are committed, so that the fan-in sees every sibling.
        for work_item in pending:
            _enqueue_refine(plan.downlink_id, work_item)
        return Outcome(f"{plan.ingest.summary()}; {len(plan.work)} maplets to refine "
                       f"from version {plan.base_version}", downlink_id=plan.downlink_id)

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
    (default fuse_key(downlink_id)), with the downlink in its lineage."""

    def work(state: ProcessState, job: Job) -> Outcome:
        with session_scope(state.sessions) as session:
            report_progress(session, job, 0.0, "fusing")
        settings = get_worker_settings()
        version = fuse_and_publish(state.sessions, data_dir=settings.data_dir,
                                   downlink_ids=[] if downlink_id is None else [downlink_id],
                                   config=settings.refinement())
        message = ("no maplet changed: no new version" if version is None
                   else f"published version {version}")
        return Outcome(message, downlink_id=downlink_id)

    return _run_job(self, kind=JobKind.FUSE, key=key or fuse_key(downlink_id), work=work)


def _submit_refine(session: Session, downlink_id: int | None, work: MapletWork) -> str | None:
    """Submit the refine job of `work`; its key, or None when that job is done already."""
    key = refine_key(downlink_id, work.maplet_id, work.input_hash)
    job = submit_job(session, kind=JobKind.REFINE, key=key, downlink_id=downlink_id,
                     maplet_id=work.maplet_id)
    return None if job.status is JobStatus.DONE else key


def _enqueue_refine(downlink_id: int | None, work: MapletWork) -> None:
    refine_revision.apply_async(kwargs={"maplet_id": work.maplet_id,
                                      "input_hash": work.input_hash,
                                      "downlink_id": downlink_id})


def _fan_in(sessions: sessionmaker[Session], *, downlink_id: int | None, after: str
            ) -> str | None:
    """Submit and enqueue the fusion that follows the refine job `after` when it is due: a
    downlink's once none of its refine jobs is unfinished (failed ones count as unfinished),
    a requested refinement's at once. Its key, or None when not due."""
    with session_scope(sessions) as session:
        if downlink_id is None:
            key = f"fuse:{after}"
        else:
            unfinished = session.scalar(select(func.count()).select_from(Job).where(
                Job.kind == JobKind.REFINE, Job.downlink_id == downlink_id,
                Job.status != JobStatus.DONE))
            if unfinished:
                return None
            key = fuse_key(downlink_id)
        done = submit_job(session, kind=JobKind.FUSE, key=key,
                          downlink_id=downlink_id).status is JobStatus.DONE
    if not done:
        fuse_downlink.apply_async(kwargs={"downlink_id": downlink_id, "key": key})
    return key


def _run_job(task: Task, *, kind: JobKind, key: str,
             work: Callable[[ProcessState, Job], Outcome]) -> dict[str, Any]:
    """Claim the job `key`, run `work` as one attempt at it and record the outcome; a failed
    attempt is retried after retry_backoff_s * 2**(attempt - 1) while attempts <= task_retries."""
    state = process_state()
    settings = get_worker_settings()
    try:
        with session_scope(state.sessions) as session:
            job = claim_job(session, kind=kind, key=key, lease_s=settings.job_time_limit_s)
    except JobBusy as busy:
        raise task.retry(countdown=busy.retry_after_s + LEASE_SLACK_S) from busy
    if job is None:
        return {"key": key, "status": "done", "ran": False}
    try:
        outcome = work(state, job)
    except Exception as exc:
        with session_scope(state.sessions) as session:
            fail_job(session, job, error=traceback.format_exc())
        if job.attempts <= settings.task_retries:
            raise task.retry(exc=exc, countdown=settings.retry_backoff_s
                             * 2 ** (job.attempts - 1)) from exc
        raise
    with session_scope(state.sessions) as session:
        finish_job(session, job, message=outcome.message, downlink_id=outcome.downlink_id,
                   maplet_id=outcome.maplet_id)
    return {"key": key, "status": "done", "ran": True, "attempt": job.attempts,
            "message": outcome.message}
