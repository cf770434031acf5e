"""Downlinks, and starting the ingest of one from the data directory's incoming area."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, HTTPException, Query, Request, status
from sqlalchemy.orm import Session

from service.api.deps import Authorized, Id, JobsDep, PagingDep, SessionDep, SettingsDep
from service.api.schemas import DownlinkOut, IngestRequest, JobSubmitted, Page, Problem
from service.downlinks import downlink_ids, downlink_summaries
from service.rows import DownlinkStatus

router = APIRouter(tags=["downlinks"])

INCOMING_DIRNAME = "incoming"


def incoming_directory(data_dir: Path, requested: str) -> Path:
    """The directory `requested` names, relative to `<data_dir>/incoming`, resolved (symbolic
    links followed). Raises ValueError if it is absolute, climbs with `..`, or resolves outside
    the incoming area; FileNotFoundError if it is no directory."""
    root = (data_dir / INCOMING_DIRNAME).resolve()
    relative = Path(requested)
    if relative.is_absolute() or relative.drive:
        raise ValueError("give the path relative to the incoming area, not absolute")
    if ".." in relative.parts:
        raise ValueError("the path may not climb with '..'")
    resolved = (root / relative).resolve()
    if not resolved.is_relative_to(root):
        raise ValueError("the path resolves outside the incoming area")
    if not resolved.is_dir():
        raise FileNotFoundError(f"no directory {requested!r} in the incoming area")
    return resolved


def _downlinks(session: Session, ids: list[int]) -> list[DownlinkOut]:
    return [DownlinkOut(id=d.id, name=d.name, received_at=d.received_at, status=d.status,
                        outcome=d.outcome, kernels=d.kernels, images=d.images,
                        accepted=d.accepted, rejected=d.rejected, conflict=d.conflict,
                        unused_files=d.unused_files, lidar=d.lidar,
                        lidar_shots=d.lidar_shots, lidar_valid_shots=d.lidar_valid_shots, repeat_count=d.repeat_count,
                        last_seen_at=d.last_seen_at, model_note=d.model_note,
                        pose_adjustment=d.pose_adjustment)
            for d in downlink_summaries(session, ids)]


@router.get("/downlinks", response_model=Page[DownlinkOut])
def list_downlinks(session: SessionDep, paging: PagingDep,
                   status_: Annotated[DownlinkStatus | None, Query(alias="status")] = None
                   ) -> Page[DownlinkOut]:
    """Downlinks, newest first, with their outcome and their kernel, image and lidar counts."""
    ids, total = downlink_ids(session, status=status_, limit=paging.limit, offset=paging.offset)
    return Page(items=_downlinks(session, ids), total=total, **paging.model_dump())


@router.get("/downlinks/{downlink_id}", response_model=DownlinkOut,
            responses={404: {"model": Problem}})
def get_downlink(session: SessionDep, downlink_id: Id) -> DownlinkOut:
    found = _downlinks(session, [downlink_id])
    if not found:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"no downlink {downlink_id}")
    return found[0]


@router.post("/ingests", response_model=JobSubmitted, dependencies=[Authorized],
             status_code=status.HTTP_202_ACCEPTED,
             responses={400: {"model": Problem}, 401: {"model": Problem},
                        403: {"model": Problem}, 404: {"model": Problem},
                        503: {"model": Problem}})
def start_ingest(request: Request, settings: SettingsDep, jobs: JobsDep, body: IngestRequest) -> JobSubmitted:
    """Queue the ingest of a downlink directory in the data directory's incoming area (its job
    key comes back; submitting the same directory again gives the same job)."""
    try:
        directory = incoming_directory(settings.data_dir, body.path)
    except ValueError as exc:
        raise HTTPException(status.HTTP_400_BAD_REQUEST, str(exc)) from None
    except FileNotFoundError as exc:
        raise HTTPException(status.HTTP_404_NOT_FOUND, str(exc)) from None
    except OSError as exc:  # too long a path, a loop of links, ...: the client's path
        raise HTTPException(status.HTTP_400_BAD_REQUEST,
                            f"the path cannot be looked up: {exc.strerror}") from None
    return JobSubmitted(key=jobs.submit_ingest(directory, sessions=request.app.state.sessions))
