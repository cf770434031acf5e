"""The jobs table: background work known by an idempotency key, claimed one attempt at a time.

A job row is made once per key (`submit_job` when work is requested, or `claim_job` on first
delivery) and every delivery of that key works on the same row:
- done: nothing to do, `claim_job` returns None;
- queued or failed: the delivery takes it (a failed job is tried again);
- running: another attempt holds it while it is alive (JobBusy): the attempt records its worker
  and beats (`heartbeat`) every heartbeat_s while it runs, and an attempt whose latest beat is
  more than grace_s old is lost (JobState.LOST, shown so by the API and `pwm jobs`): the next
  delivery takes it over.

`attempts` counts the attempts taken and fences them: progress, finish and fail only change the
row while it is running for the attempt that calls them (JobLost otherwise), so a worker that was
presumed dead cannot overwrite the outcome of the attempt that took over; they write to the
table and leave the Job object passed as it was claimed. Each function works in the caller's
transaction: commit promptly so that the API sees progress.

The keys' formats live here (ingest_key, refine_key and refine_key_parts, fuse_key): a version's lineage is read
from the refine keys of the revisions it carries (refined_downlinks).

The table, not the broker, is the truth about what must run next: every hand-over to the broker
is recorded (`mark_enqueued`, with its error when the broker could not take it), and
`due_jobs` finds the jobs a reconciler must hand over again: queued or retryable ones whose
message may be gone, lost attempts, and downlinks whose refinements are all done with no fusion
job after them (`fusions_due`; a downlink fuses once per pass).
Handing a job over twice is harmless: the claim makes every delivery after the first a no-op.

`pwm run` does the same stages in one process and records each, once over, as an attempt at
the same job (`record_attempt`): `pwm jobs` and the API show what it did.

Work is handed to whoever runs it through a JobQueue: the workers implement it
(workers.tasks.CeleryQueue) and the command line, which wires the parts together, gives it to
the API and the watcher; nothing else in `service` knows who runs the jobs.
"""

from __future__ import annotations

import enum
import re
from collections.abc import Collection, Iterable
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any, Protocol, cast

from sqlalchemy import ColumnElement, CursorResult, and_, func, or_, select, update
from sqlalchemy.orm import Session, sessionmaker

from service.db import insert_ignoring_conflict
from service.rows import Job, JobKind, JobStatus, Maplet, MapletRevision, utcnow

# An absolute path in a message: a quoted one whole (it may hold spaces), else from a slash at
# the start or after a space, bracket or `=` up to the next space, quote or bracket.
_ABSOLUTE_PATH = re.compile(r"(?<=')/[^']*(?=')|(?<=\")/[^\"]*(?=\")"
                            r"|(?<![^\s(\[=])/[^\s'\"()\[\]]*")
MAX_REASON_CHARS = 500
# Marks the refine and fuse keys of a refinement asked for outside any downlink.
REQUESTED = "requested"


class JobState(enum.StrEnum):
    """A job as shown: its status, with a running job whose heartbeat stopped shown as lost."""

    QUEUED = "queued"
    RUNNING = "running"
    LOST = "lost"
    DONE = "done"
    FAILED = "failed"


def ingest_key(directory: str | Path) -> str:
    """The idempotency key of ingesting `directory`: its absolute path. A directory whose content
    changes after its ingest started is ingested again under the same key (reopen_job)."""
    return f"ingest:{Path(directory).resolve()}"


def refine_key(downlink_id: int | None, maplet_id: int, input_hash: str) -> str:
    """The key of refining a maplet's input (its hash) for a downlink, or on request (None)."""
    return f"refine:{REQUESTED if downlink_id is None else downlink_id}:{maplet_id}:{input_hash}"


def refine_key_parts(key: str) -> tuple[int | None, int, str]:
    """The downlink id (None: on request), maplet id and input hash that refine_key made `key`
    of; ValueError for another key."""
    kind, downlink, maplet_id, input_hash = key.split(":", 3)
    if kind != "refine" or not maplet_id.isdigit() or not (downlink == REQUESTED or downlink.isdigit()):
        raise ValueError(f"not a refine key: {key!r}")
    return None if downlink == REQUESTED else int(downlink), int(maplet_id), input_hash


def fuse_key(downlink_id: int | None, nth: int = 1) -> str:
    """The key of the nth fusion of a downlink's refinements (None: the catalog's) into a new
    version: the first follows its ingest's refinements, each later one a later pass's."""
    return f"fuse:{downlink_id}" if nth == 1 else f"fuse:{downlink_id}:{nth}"


class JobBusy(Exception):
    """Another attempt holds the job; deliver again after `retry_after_s` (s)."""

    def __init__(self, key: str, retry_after_s: float, worker: str | None = None) -> None:
        super().__init__(f"job {key!r} is running in another attempt (worker {worker}); it is "
                         f"lost unless it beats again within {retry_after_s:.1f} s")
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


def claim_job(session: Session, *, kind: JobKind, key: str, grace_s: float,
              worker: str | None = None, downlink_id: int | None = None,
              maplet_id: int | None = None, now: datetime | None = None) -> Job | None:
    """Start an attempt at the job of `key` (made if missing) by `worker`: running,
    attempts + 1, its heartbeat now.

    Returns None when the job is done. Raises JobBusy while another attempt is alive: its latest
    heartbeat (or its start) less than grace_s (s) ago. The row is locked until the transaction
    ends (PostgreSQL; SQLite holds its write lock from the insert), so of two concurrent
    deliveries one claims and the other sees the claim.
    """
    now = now or utcnow()
    _insert_if_missing(session, kind=kind, key=key, downlink_id=downlink_id, maplet_id=maplet_id)
    job = _locked(session, kind, key)
    if job.status is JobStatus.DONE:
        return None
    if job.status is JobStatus.RUNNING and (alive := _last_sign_of_life(job)) is not None:
        remaining = (alive + timedelta(seconds=grace_s) - now).total_seconds()
        if remaining > 0:
            raise JobBusy(key, remaining, job.worker)
    _start_attempt(session, job, worker=worker, now=now)
    return job


def record_attempt(session: Session, *, kind: JobKind, key: str, worker: str, started_at: datetime,
                   message: str | None = None, error: str | None = None, downlink_id: int | None = None,
                   maplet_id: int | None = None) -> Job | None:
    """Record work that ran in this process (`pwm run`, service.run) as an attempt at the job of
    `key`, as a worker's attempt is recorded: started at started_at by `worker`, then done with
    `message`, or failed with `error` (a traceback) when one is given. Recorded once the work is
    over, in one transaction: an attempt that never beats is never seen running, so no
    reconciler takes it for lost. A done job gets a new attempt (the work ran again); a job that
    another attempt is running is left to it (None)."""
    _insert_if_missing(session, kind=kind, key=key, downlink_id=downlink_id, maplet_id=maplet_id)
    job = _locked(session, kind, key)
    if job.status is JobStatus.RUNNING:
        return None
    _start_attempt(session, job, worker=worker, now=started_at)
    if error is None:
        finish_job(session, job, message=message, downlink_id=downlink_id, maplet_id=maplet_id)
    else:
        fail_job(session, job, error=error)
    return job


def _start_attempt(session: Session, job: Job, *, worker: str | None, now: datetime) -> None:
    job.status, job.attempts = JobStatus.RUNNING, job.attempts + 1
    job.started_at, job.heartbeat_at, job.finished_at = now, now, None
    job.worker, job.progress, job.error = worker, 0.0, None
    session.flush()


def heartbeat(session: Session, job: Job, *, now: datetime | None = None) -> None:
    """Record that the attempt `job` (as claimed) is alive."""
    _update_running(session, job, {"heartbeat_at": now or utcnow()})


def job_state(job: Job, *, grace_s: float, now: datetime | None = None) -> JobState:
    """The job as shown: lost when it is running with no heartbeat in the last grace_s (s)."""
    if job.status is JobStatus.RUNNING:
        alive = _last_sign_of_life(job)
        if alive is not None and (now or utcnow()) - alive > timedelta(seconds=grace_s):
            return JobState.LOST
    return JobState(job.status.value)


def state_filter(state: JobState, *, grace_s: float, now: datetime | None = None
                 ) -> ColumnElement[bool]:
    """The SQL condition for the jobs shown in `state` (job_state)."""
    cutoff = (now or utcnow()) - timedelta(seconds=grace_s)
    stale = func.coalesce(Job.heartbeat_at, Job.started_at) < cutoff
    if state is JobState.LOST:
        return and_(Job.status == JobStatus.RUNNING, stale)
    if state is JobState.RUNNING:
        return and_(Job.status == JobStatus.RUNNING, or_(stale.is_(None), ~stale))
    return Job.status == JobStatus(state.value)


def find_jobs(session: Session, *, grace_s: float, state: JobState | None = None,
              kind: JobKind | None = None, key: str | None = None, limit: int | None = None,
              offset: int = 0, now: datetime | None = None) -> tuple[int, list[Job]]:
    """The jobs in `state` (job_state, lost after grace_s), of `kind`, with `key`, newest
    first: how many match, and `limit` of them from `offset` (the API's /jobs and `pwm jobs`)."""
    query = select(Job)
    if state is not None:
        query = query.where(state_filter(state, grace_s=grace_s, now=now))
    if kind is not None:
        query = query.where(Job.kind == kind)
    if key is not None:
        query = query.where(Job.key == key)
    total = session.execute(select(func.count()).select_from(query.subquery())).scalar_one()
    rows = session.scalars(query.order_by(Job.created_at.desc(), Job.id.desc())
                           .limit(limit).offset(offset))
    return total, list(rows)


def mark_enqueued(session: Session, *, key: str, error: str | None = None,
                  now: datetime | None = None) -> None:
    """Record that the job `key` was handed to the broker now, or that it could not be (error):
    a job whose hand-over failed is due again at the reconciler's next pass (due_jobs)."""
    session.execute(update(Job).where(Job.key == key).values(
        enqueued_at=None if error else (now or utcnow()), enqueue_error=error)
        .execution_options(synchronize_session=False))


def due_jobs(session: Session, *, grace_s: float, requeue_after_s: float, retries: int,
             backoff_s: float, waiting_kinds: Collection[JobKind] = (),
             now: datetime | None = None) -> list[tuple[Job, str]]:
    """The jobs that must be handed to the broker again, with why, each taken for this caller
    (its enqueued_at set to now, in the caller's transaction; rows another caller holds are
    skipped) so that reconcilers running together hand each over once:
    - a job whose last hand-over failed (mark_enqueued with an error);
    - queued, with no attempt requeue_after_s (s) after it was made or last handed over (its
      message may have gone with the broker), unless its kind is in waiting_kinds (its queue
      holds messages, which may be its own);
    - lost (no heartbeat for grace_s), grace_s after its last beat, then every requeue_after_s;
    - failed with retries left (attempts <= retries), once the retry's backoff
      (backoff_s * 2**(attempts - 1)) and requeue_after_s have passed with no new attempt.
    """
    now = now or utcnow()
    candidates = session.scalars(
        select(Job).where(or_(Job.status.in_([JobStatus.QUEUED, JobStatus.RUNNING]),
                              and_(Job.status == JobStatus.FAILED, Job.attempts <= retries)))
        .order_by(Job.id).with_for_update(skip_locked=True)
        .execution_options(populate_existing=True)).all()
    due = []
    for job in candidates:
        if job.enqueue_error is not None:
            due.append((job, f"its hand-over failed: {job.enqueue_error}"))
            continue
        if job.status is JobStatus.QUEUED:
            if job.kind in waiting_kinds:
                continue
            since, wait, why = job.created_at, requeue_after_s, "queued with no attempt"
        elif job.status is JobStatus.FAILED:
            since = job.finished_at or job.created_at
            wait = backoff_s * 2 ** max(job.attempts - 1, 0) + requeue_after_s
            why = f"attempt {job.attempts} failed, with no retry since"
        elif job_state(job, grace_s=grace_s, now=now) is JobState.LOST:
            since, wait = _last_sign_of_life(job) or job.created_at, grace_s
            why = f"attempt {job.attempts} on {job.worker} lost: no heartbeat"
        else:
            continue
        if job.enqueued_at is not None and job.enqueued_at > since:
            since, wait = job.enqueued_at, max(wait, requeue_after_s)
        idle_s = (now - since).total_seconds()
        if idle_s > wait:
            due.append((job, f"{why} for {idle_s:.0f} s"))
    for job, _ in due:
        job.enqueued_at, job.enqueue_error = now, None
    session.flush()
    return due


def fusions_due(session: Session, *, downlink_id: int | None = None) -> dict[int, str]:
    """The key of each downlink's next fusion (of `downlink_id` alone, if given) that is due and
    was never made: the downlink has refine jobs, all done, and no fusion job made after the
    last of them; the key counts the fusions made before (fuse_key). The fan-in asks for its
    downlink's; the reconciler for all, whose fan-in never happened (the worker died between
    the two, or the fusion job was never made)."""
    mine = Job.downlink_id.is_not(None) if downlink_id is None else Job.downlink_id == downlink_id
    refines = (select(Job.downlink_id, func.max(Job.id).label("last"))
               .where(Job.kind == JobKind.REFINE, mine)
               .group_by(Job.downlink_id)
               .having(func.count().filter(Job.status != JobStatus.DONE) == 0).subquery())
    fused = (select(Job.downlink_id, func.count().label("made"), func.max(Job.id).label("latest"))
             .where(Job.kind == JobKind.FUSE, mine)
             .group_by(Job.downlink_id).subquery())
    rows = session.execute(
        select(refines.c.downlink_id, fused.c.made)
        .outerjoin(fused, fused.c.downlink_id == refines.c.downlink_id)
        .where(or_(fused.c.latest.is_(None), fused.c.latest < refines.c.last))
        .order_by(refines.c.downlink_id))
    return {d: fuse_key(d, (made or 0) + 1) for d, made in rows}


def made_current(session: Session, *, downlink_id: int | None,
                 maplet_ids: Collection[int] | None = None) -> set[int]:
    """The maplets (of maplet_ids, or all) whose current revision a done refine job of the
    downlink (None: a requested one) made."""
    query = (select(Job.key, Job.maplet_id, MapletRevision.input_hash)
             .join(Maplet, Maplet.id == Job.maplet_id)
             .join(MapletRevision, MapletRevision.id == Maplet.current_revision_id)
             .where(Job.kind == JobKind.REFINE, Job.status == JobStatus.DONE,
                    Job.downlink_id.is_(None) if downlink_id is None
                    else Job.downlink_id == downlink_id))
    if maplet_ids is not None:
        query = query.where(Job.maplet_id.in_(list(maplet_ids)))
    return {m for key, m, h in session.execute(query)
            if m is not None and key == refine_key(downlink_id, m, h)}


def refined_downlinks(session: Session, revisions: Iterable[MapletRevision]) -> set[int]:
    """The downlinks whose refine jobs made these revisions (by maplet and input)."""
    wanted = {(r.maplet_id, r.input_hash) for r in revisions}
    if not wanted:
        return set()
    rows = session.execute(select(Job.key, Job.downlink_id).where(
        Job.kind == JobKind.REFINE, Job.status == JobStatus.DONE, Job.downlink_id.is_not(None),
        Job.maplet_id.in_({m for m, _ in wanted})))
    return {downlink_id for key, downlink_id in rows if downlink_id is not None
            and any(key == refine_key(downlink_id, m, h) for m, h in wanted)}


def retry_job(session: Session, job_id: int, *, grace_s: float,
              now: datetime | None = None) -> Job:
    """Make a failed or lost job queued again, to be handed to the broker (the caller's queue,
    or the reconciler); its attempts are kept. Raises LookupError for an unknown job and
    ValueError for one that is done, queued or alive."""
    job = session.scalars(select(Job).where(Job.id == job_id).with_for_update()
                          .execution_options(populate_existing=True)).one_or_none()
    if job is None:
        raise LookupError(f"no job {job_id}")
    state = job_state(job, grace_s=grace_s, now=now)
    if state not in (JobState.FAILED, JobState.LOST):
        raise ValueError(f"job {job_id} is {state}: only failed or lost jobs are retried")
    job.status, job.worker, job.enqueued_at, job.enqueue_error = (
        JobStatus.QUEUED, None, None, None)
    session.flush()
    return job


def reopen_job(session: Session, job: Job, *, changed_at: datetime) -> bool:
    """Make a done job queued again when its input changed after its last attempt started (a
    downlink's directory written to during or after its ingest: a product whose data arrived
    late, a re-transfer); True when it was reopened, to be handed to the broker. Its attempts
    are kept."""
    if job.status is not JobStatus.DONE or job.started_at is None or job.started_at >= changed_at:
        return False
    job.status, job.worker, job.enqueued_at, job.enqueue_error = (
        JobStatus.QUEUED, None, None, None)
    job.progress, job.message = 0.0, f"queued again: its input changed at {changed_at.isoformat()}"
    session.flush()
    return True


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
    session.execute(insert_ignoring_conflict(session, Job, unique=[Job.key], kind=kind, key=key,
                                             downlink_id=downlink_id, maplet_id=maplet_id))


def _last_sign_of_life(job: Job) -> datetime | None:
    return job.heartbeat_at or job.started_at


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
