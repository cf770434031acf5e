"""Images with their geometry and status."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Annotated

from fastapi import APIRouter, HTTPException, Query, status
from pydantic import AfterValidator, AwareDatetime
from sqlalchemy import func, select
from sqlalchemy.orm import selectinload

from pwm.spg.uncertainty import determined
from service.api.deps import MAX_ID, Id, PagingDep, SessionDep
from service.api.schemas import (
    GeometryOut,
    ImageDetail,
    ImageOut,
    Page,
    PoseCorrectionOut,
    PoseSigmaOut,
    Problem,
)
from service.queries import maplets_seen_by
from service.rows import GeometryStatus, Image, ImageStatus

router = APIRouter(prefix="/images", tags=["images"])


def _utc(value: datetime) -> datetime:
    try:
        return value.astimezone(UTC)
    except OverflowError:  # an offset that moves the time out of datetime's range
        raise ValueError("the time is out of range in UTC") from None


UTCTime = Annotated[AwareDatetime, AfterValidator(_utc)]


def image_out(image: Image) -> ImageOut:
    g = image.geometry
    geometry = None if g is None else GeometryOut(
        camera_km=[g.camera_x_km, g.camera_y_km, g.camera_z_km],
        sun_direction=[g.sun_x, g.sun_y, g.sun_z], range_km=g.range_km,
        intercept_range_km=g.intercept_range_km, pixel_scale_m=g.pixel_scale_m,
        phase_deg=g.phase_deg, incidence_deg=g.incidence_deg, emission_deg=g.emission_deg,
        intercept_lat_deg=g.intercept_lat_deg, intercept_lon_deg=g.intercept_lon_deg,
        footprint=g.footprint, body_frame=g.body_frame, computed_at=g.computed_at)
    return ImageOut(id=image.id, lidvid=image.lidvid, status=image.status,
                    rejection_code=image.rejection_code, rejection_reason=image.rejection_reason,
                    downlink_id=image.downlink_id,
                    instrument=image.instrument.name if image.instrument else None,
                    target=image.target, start_utc=image.start_utc, stop_utc=image.stop_utc,
                    geometry_status=image.geometry_status, geometry=geometry,
                    pose_corrected=image.pose_corrected_at is not None,
                    pose_correction=_correction(image))


def _correction(image: Image) -> PoseCorrectionOut | None:
    stored = image.pose_correction()
    if stored is None or image.pose_corrected_at is None:
        return None
    out = PoseCorrectionOut(position_m=[v * 1e3 for v in stored.position_km],
                            rotation_urad=[v * 1e6 for v in stored.rotation_rad],
                            corrected_at=image.pose_corrected_at)
    sigmas = image.pose_sigmas()
    if sigmas is not None:
        prior, posterior = sigmas
        out.sigma_prior = PoseSigmaOut(**prior.as_dict())
        out.sigma_posterior = PoseSigmaOut(**posterior.as_dict())
        out.determined = determined(prior, posterior)
    return out


@router.get("", response_model=Page[ImageOut])
def list_images(
    session: SessionDep, paging: PagingDep,
    status_: Annotated[ImageStatus | None, Query(alias="status")] = None,
    geometry_status: GeometryStatus | None = None,
    downlink_id: Annotated[int | None, Query(ge=1, le=MAX_ID)] = None,
    start_after: Annotated[UTCTime | None, Query(description="start time at or after")] = None,
    start_before: Annotated[UTCTime | None, Query(description="start time before")] = None,
) -> Page[ImageOut]:
    """Images by start time; filtered by status, geometry status, downlink and start time."""
    query = select(Image)
    if status_ is not None:
        query = query.where(Image.status == status_)
    if geometry_status is not None:
        query = query.where(Image.geometry_status == geometry_status)
    if downlink_id is not None:
        query = query.where(Image.downlink_id == downlink_id)
    if start_after is not None:
        query = query.where(Image.start_utc >= start_after)
    if start_before is not None:
        query = query.where(Image.start_utc < start_before)
    total = session.execute(select(func.count()).select_from(query.subquery())).scalar_one()
    rows = session.scalars(query.options(selectinload(Image.geometry),
                                         selectinload(Image.instrument))
                           .order_by(Image.start_utc.asc().nulls_last(), Image.id)
                           .limit(paging.limit).offset(paging.offset))
    return Page(items=[image_out(i) for i in rows], total=total, **paging.model_dump())


@router.get("/{image_id}", response_model=ImageDetail, responses={404: {"model": Problem}})
def get_image(session: SessionDep, image_id: Id) -> ImageDetail:
    """An image with its geometry and the maplets it sees."""
    image = session.get(Image, image_id)
    if image is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"no image {image_id}")
    return ImageDetail(**image_out(image).model_dump(),
                       maplets=maplets_seen_by(session, image_id=image_id))
