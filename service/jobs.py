"""The jobs table: background work known by an idempotency key, claimed one attempt at a time.

A job row is made once per key (`submit_job` when work is requested, or `claim_job` on first
delivery) and every delivery of that key works on the same row:
- done: nothing to do, `claim_job` returns None;
- queued or failed: the delivery takes it (a failed job is tried again);
- running: another attempt holds it while its lease lasts (JobBusy). The lease is the attempt's
  start plus `lease_s`, which must exceed the longest an attempt may run (the workers' hard time
  limit): a job still running after that lost its worker, and the next delivery takes it over.

`attempts` counts the attempts taken and fences them: progress, finish and fail only change the
row while it is running for the attempt that calls them (JobLost otherwise), so a worker that was
presumed dead cannot overwrite the outcome of the attempt that took over; they write to the
table and leave the Job object passed as it was claimed. Each function works in the caller's
transaction: commit promptly so that the API sees progress.

Work is handed to whoever runs it through a JobQueue: the workers implement it
(workers.tasks.CeleryQueue) and the command line, which wires the parts together, gives it to
the API and the watcher; nothing else in `service` knows who runs the jobs.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any, Protocol, cast

from sqlalchemy import CursorResult, select, update
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.orm import Session, sessionmaker

from service.models import Job, JobKind, JobStatus, utcnow

_INSERT_IGNORING_CONFLICT: dict[str, Callable[..., postgresql.Insert | sqlite.Insert]] = {
    "postgresql": postgresql.insert, "sqlite": sqlite.insert}
# An absolute path in a message: a quoted one whole (it may hold spaces), else from a slash at
# the start or after a space, bracket or `=` up to the next space, quote or bracket.
_ABSOLUTE_PATH = re.compile(r"(?<=')/[^']*(?=')|(?<=\")/[^\"]*(?=\")"
                            r"|(?<![^\s(\[=])/[^\s'\"()\[\]]*")
MAX_REASON_CHARS = 500


class JobBusy(Exception):
    """Another attempt holds the job; deliver again after `retry_after_s` (s)."""

    def __init__(self, key: str, retry_after_s: float) -> None:
        super().__init__(f"job {key!r} is running in another attempt; its lease ends in "
                         f"{retry_after_s:.1f} s")
        self.key, self.retry_after_s = key, retry_after_s


class JobLost(Exception):
    """The attempt no longer holds its job: it finished, or a later attempt took it over."""


class JobQueue(Protocol):
    """Where jobs are submitted to be run; each call returns the job's idempotency key."""

    def submit_ingest(self, directory: Path, *, sessions: sessionmaker[Session]) -> str:
        """Submit the ingest of the downlink in `directory` (and what follows from it) unless it
        is done."""
        ...

    def submit_refinement(self, session: Session, *, maplet_id: int) -> str:
        """Submit the refinement of a maplet's current input in the caller's transaction, run
        once it commits. Raises LookupError for an unknown maplet, ValueError when there is
        nothing new to refine."""
        ...


def submit_job(session: Session, *, kind: JobKind, key: str, downlink_id: int | None = None,
               maplet_id: int | None = None) -> Job:
    """The job of `key`: made queued if new, else the row as it stands (any status)."""
    _insert_if_missing(session, kind=kind, key=key, downlink_id=downlink_id, maplet_id=maplet_id)
    return _locked(session, kind, key)


def claim_job(session: Session, *, kind: JobKind, key: str, lease_s: float,
              downlink_id: int | None = None, maplet_id: int | None = None,
              now: datetime | None = None) -> Job | None:
    """Start an attempt at the job of `key` (made if missing): running, attempts + 1.

    Returns None when the job is done. Raises JobBusy while another attempt's lease lasts
    (lease_s, s, from the start of that attempt). The row is locked until the transaction ends
    (PostgreSQL; SQLite holds its write lock from the insert), so of two concurrent deliveries
    one claims and the other sees the claim.
    """
    now = now or utcnow()
    _insert_if_missing(session, kind=kind, key=key, downlink_id=downlink_id, maplet_id=maplet_id)
    job = _locked(session, kind, key)
    if job.status is JobStatus.DONE:
        return None
    if job.status is JobStatus.RUNNING and job.started_at is not None:
        remaining = (job.started_at + timedelta(seconds=lease_s) - now).total_seconds()
        if remaining > 0:
            raise JobBusy(key, remaining)
    job.status, job.attempts = JobStatus.RUNNING, job.attempts + 1
    job.started_at, job.finished_at = now, None
    job.progress, job.error = 0.0, None
    session.flush()
    return job


def report_progress(session: Session, job: Job, fraction: float, message: str | None = None
                    ) -> None:
    """Record how far the attempt `job` (as claimed) has come: fraction in [0, 1]."""
    if not 0.0 <= fraction <= 1.0:
        raise ValueError(f"progress {fraction} is outside [0, 1]")
    values: dict[str, Any] = {"progress": fraction}
    if message is not None:
        values["message"] = message
    _update_running(session, job, values)


def finish_job(session: Session, job: Job, *, message: str | None = None,
               downlink_id: int | None = None, maplet_id: int | None = None) -> None:
    """Mark the attempt `job` done (progress 1), with a summary and the rows it concerns."""
    values: dict[str, Any] = {"status": JobStatus.DONE, "progress": 1.0,
                              "finished_at": utcnow(), "message": message}
    if downlink_id is not None:
        values["downlink_id"] = downlink_id
    if maplet_id is not None:
        values["maplet_id"] = maplet_id
    _update_running(session, job, values)


def fail_job(session: Session, job: Job, *, error: str) -> None:
    """Mark the attempt `job` failed with `error` (a traceback or a message)."""
    _update_running(session, job, {"status": JobStatus.FAILED, "finished_at": utcnow(),
                                   "error": error})


def error_reason(error: str | None) -> str | None:
    """The reason a job failed, fit to show to anyone: the last line of its error (a
    traceback's is the exception and its message), with absolute paths reduced to their file
    names, at most MAX_REASON_CHARS characters."""
    if error is None:
        return None
    lines = [line.strip() for line in error.splitlines() if line.strip()]
    if not lines:
        return None
    reason = _ABSOLUTE_PATH.sub(lambda m: m.group().rstrip("/").rsplit("/", 1)[-1] or "/",
                                lines[-1])
    return reason[:MAX_REASON_CHARS]


def _insert_if_missing(session: Session, *, kind: JobKind, key: str, downlink_id: int | None,
                       maplet_id: int | None) -> None:
    # INSERT .. ON CONFLICT DO NOTHING rather than select-then-insert: concurrent first
    # deliveries never fail on the unique key, and on SQLite the write lock is taken before
    # the row is read.
    dialect = session.get_bind().dialect.name
    insert = _INSERT_IGNORING_CONFLICT.get(dialect)
    if insert is None:
        raise NotImplementedError(f"jobs need PostgreSQL or SQLite, not {dialect}")
    session.execute(insert(Job).values(kind=kind, key=key, downlink_id=downlink_id,
                                       maplet_id=maplet_id)
                    .on_conflict_do_nothing(index_elements=[Job.key]))


def _locked(session: Session, kind: JobKind, key: str) -> Job:
    job = session.scalars(select(Job).filter_by(key=key).with_for_update()
                          .execution_options(populate_existing=True)).one()
    if job.kind != kind:
        raise ValueError(f"job key {key!r} belongs to a {job.kind} job, not {kind}")
    return job


def _update_running(session: Session, job: Job, values: dict[str, Any]) -> None:
    # an UPDATE's result is a CursorResult, which counts the rows matched
    result = cast(CursorResult[Any], session.execute(
        update(Job).where(Job.id == job.id, Job.attempts == job.attempts,
                          Job.status == JobStatus.RUNNING).values(**values)
        .execution_options(synchronize_session=False)))
    if result.rowcount != 1:
        raise JobLost(f"attempt {job.attempts} of job {job.key!r} no longer holds it")
