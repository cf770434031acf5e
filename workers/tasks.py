"""Celery tasks: each runs one job of the jobs table (service.jobs), known by its key.

Every delivery claims the job first, so deliveries are idempotent: a job already done is not
done again, a job another attempt holds is retried once that attempt's lease ends, and a job
whose worker died is taken over by the redelivery. The outcome (done with a summary, or failed
with the traceback) is recorded in the job row, then returned or raised to Celery.

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
from sqlalchemy import select

from service.db import session_scope
from service.ingest import ingest_directory
from service.jobs import JobBusy, claim_job, fail_job, finish_job, report_progress
from service.models import Downlink, Job, JobKind
from workers.app import ProcessState, app, get_worker_settings, process_state

# A retried delivery waits this long past the end of the lease that made it wait (s).
LEASE_SLACK_S = 1.0


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


@app.task(bind=True)
def ingest_downlink(self: Task, directory: str, key: str | None = None) -> dict[str, Any]:
    """Catalogue the downlink in `directory` (service.ingest) as the ingest job `key` (default
    ingest_key(directory))."""
    path = Path(directory).resolve()

    def work(state: ProcessState, job: Job) -> Outcome:
        with session_scope(state.sessions) as session:
            report_progress(session, job, 0.0, f"ingesting {path}")
        report = ingest_directory(state.sessions, path)
        with state.sessions() as session:
            downlink_id = session.scalar(select(Downlink.id).filter_by(name=report.downlink))
        return Outcome(report.summary(), downlink_id=downlink_id)

    return _run_job(self, kind=JobKind.INGEST, key=key or ingest_key(path), work=work)


# Refinement (refine_* tasks, queue `refine`) and fusion (fuse_* tasks, queue `fuse`) go here:
# bound tasks that run their work through _run_job with JobKind.REFINE or JobKind.FUSE and a
# key naming their inputs, loading SPICE kernels with ProcessState.load_kernels if they need them.


def _run_job(task: Task, *, kind: JobKind, key: str,
             work: Callable[[ProcessState, Job], Outcome]) -> dict[str, Any]:
    """Claim the job `key`, run `work` as one attempt at it and record the outcome."""
    state = process_state()
    try:
        with session_scope(state.sessions) as session:
            job = claim_job(session, kind=kind, key=key,
                            lease_s=get_worker_settings().job_time_limit_s)
    except JobBusy as busy:
        raise task.retry(countdown=busy.retry_after_s + LEASE_SLACK_S) from busy
    if job is None:
        return {"key": key, "status": "done", "ran": False}
    try:
        outcome = work(state, job)
    except Exception:
        with session_scope(state.sessions) as session:
            fail_job(session, job, error=traceback.format_exc())
        raise
    with session_scope(state.sessions) as session:
        finish_job(session, job, message=outcome.message, downlink_id=outcome.downlink_id,
                   maplet_id=outcome.maplet_id)
    return {"key": key, "status": "done", "ran": True, "attempt": job.attempts,
            "message": outcome.message}
