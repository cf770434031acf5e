"""Background jobs: listing by status and kind, and one job."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, HTTPException, Query, status

from service.api.deps import Id, PagingDep, SessionDep, SettingsDep, TokenGiven
from service.api.schemas import JobOut, Page, Problem
from service.jobs import JobState, find_jobs
from service.rows import Job, JobKind

router = APIRouter(prefix="/jobs", tags=["jobs"])


@router.get("", response_model=Page[JobOut])
def list_jobs(session: SessionDep, settings: SettingsDep, paging: PagingDep, token: TokenGiven,
              status_: Annotated[JobState | None, Query(
                  alias="status", description="`lost`: running with no heartbeat for "
                  "PWM_HEARTBEAT_GRACE_S")] = None,
              kind: JobKind | None = None,
              key: Annotated[str | None, Query(max_length=255, pattern=r"^[^\x00-\x1f\x7f]*$",
                                               description="the job with this key")] = None,
              ) -> Page[JobOut]:
    """Jobs, newest first; filtered by status (as shown: `lost` for a running job whose
    heartbeat stopped), kind or key. A failed job's traceback is shown only with the API token;
    its error's reason to anyone."""
    total, rows = find_jobs(session, grace_s=settings.heartbeat_grace_s, state=status_,
                            kind=kind, key=key, limit=paging.limit, offset=paging.offset)
    return Page(items=[JobOut.shown(j, with_traceback=token, grace_s=settings.heartbeat_grace_s)
                       for j in rows], total=total, **paging.model_dump())


@router.get("/{job_id}", response_model=JobOut, responses={404: {"model": Problem}})
def get_job(session: SessionDep, settings: SettingsDep, job_id: Id, token: TokenGiven) -> JobOut:
    """One job; its traceback only with the API token."""
    job = session.get(Job, job_id)
    if job is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"no job {job_id}")
    return JobOut.shown(job, with_traceback=token, grace_s=settings.heartbeat_grace_s)
