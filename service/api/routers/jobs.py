"""Background jobs: listing by status and kind, and one job."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, HTTPException, Query, status
from sqlalchemy import func, select

from service.api.deps import Id, PagingDep, SessionDep, TokenGiven
from service.api.schemas import JobOut, Page, Problem
from service.models import Job, JobKind, JobStatus

router = APIRouter(prefix="/jobs", tags=["jobs"])


@router.get("", response_model=Page[JobOut])
def list_jobs(session: SessionDep, paging: PagingDep, token: TokenGiven,
              status_: Annotated[JobStatus | None, Query(alias="status")] = None,
              kind: JobKind | None = None,
              key: Annotated[str | None, Query(max_length=255, pattern=r"^[^\x00-\x1f\x7f]*$",
                                               description="the job with this key")] = None,
              ) -> Page[JobOut]:
    """Jobs, newest first; filtered by status, kind or key. A failed job's traceback is shown
    only with the API token; its error's reason to anyone."""
    query = select(Job)
    if status_ is not None:
        query = query.where(Job.status == status_)
    if kind is not None:
        query = query.where(Job.kind == kind)
    if key is not None:
        query = query.where(Job.key == key)
    total = session.execute(select(func.count()).select_from(query.subquery())).scalar_one()
    rows = session.scalars(query.order_by(Job.created_at.desc(), Job.id.desc())
                           .limit(paging.limit).offset(paging.offset))
    return Page(items=[JobOut.shown(j, with_traceback=token) for j in rows], total=total,
                **paging.model_dump())


@router.get("/{job_id}", response_model=JobOut, responses={404: {"model": Problem}})
def get_job(session: SessionDep, job_id: Id, token: TokenGiven) -> JobOut:
    """One job; its traceback only with the API token."""
    job = session.get(Job, job_id)
    if job is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"no job {job_id}")
    return JobOut.shown(job, with_traceback=token)
