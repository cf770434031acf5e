"""Laser altimetry: a version's lidar residuals (overall, per track, the longitude/latitude map)
and the catalog's tracks (span, shots, strip correction and 1 sigma, residuals)."""

from __future__ import annotations

import math

from fastapi import APIRouter, HTTPException, status
from sqlalchemy import func, select

from service.api.deps import PagingDep, SessionDep, VersionRef, resolve_version
from service.api.schemas import (
    LidarCorrectionOut,
    LidarResidualsOut,
    LidarTrackOut,
    Page,
    Problem,
)
from service.rows import Acceptance, LidarProduct, LidarTrack

router = APIRouter(tags=["lidar"])


@router.get("/versions/{ref}/lidar", response_model=LidarResidualsOut, responses={404: {"model": Problem}})
def version_lidar(session: SessionDep, ref: VersionRef) -> LidarResidualsOut:
    """How far the catalog's lidar spots lie from the version (km): overall, per track and as a
    map over longitude and latitude."""
    version = resolve_version(session, ref)
    figures = version.statistics.get("lidar")
    if figures is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"version {version.version} was not checked against "
                            "the lidar: the catalog had no usable shot when it was published")
    return LidarResidualsOut.model_validate({**figures, "version": version.version})


@router.get("/lidar/tracks", response_model=Page[LidarTrackOut])
def list_tracks(session: SessionDep, paging: PagingDep) -> Page[LidarTrackOut]:
    """The tracks of the accepted lidar products, in the order they were catalogued."""
    query = select(LidarTrack, LidarProduct.lidvid).join(LidarProduct).where(
        LidarProduct.status == Acceptance.ACCEPTED)
    total = session.execute(select(func.count()).select_from(query.subquery())).scalar_one()
    rows = session.execute(query.order_by(LidarTrack.id).limit(paging.limit).offset(paging.offset))
    return Page(items=[_track(row, lidvid) for row, lidvid in rows], total=total, **paging.model_dump())


def _track(row: LidarTrack, lidvid: str) -> LidarTrackOut:
    correction = None
    if row.adjusted_at is not None:
        correction = LidarCorrectionOut(
            rotation_rad=_vector(row.rotation_x_rad, row.rotation_y_rad, row.rotation_z_rad),
            translation_km=_vector(row.translation_x_km, row.translation_y_km, row.translation_z_km),
            about_km=_vector(row.about_x_km, row.about_y_km, row.about_z_km),
            sigma=row.correction_sigma or [None] * 6, adjusted_at=row.adjusted_at)
    return LidarTrackOut(id=row.id, product=lidvid, track=row.track, start_et=row.start_et, stop_et=row.stop_et,
                         shots=row.shots, axis_lat_deg=row.axis_lat_deg, axis_lon_deg=row.axis_lon_deg,
                         cone_half_angle_deg=math.degrees(row.cone_half_angle_rad), correction=correction,
                         residual_version=row.residual_version, residual_mean_km=row.residual_mean_km,
                         residual_rms_km=row.residual_rms_km, residual_p95_km=row.residual_p95_km,
                         crossovers=row.crossovers, crossover_rms_km=row.crossover_rms_km)


def _vector(*values: float | None) -> list[float]:
    """A stored correction's vector; a part missing from an adjusted track is a broken catalog."""
    if any(v is None for v in values):
        raise ValueError("an adjusted lidar track misses a part of its correction")
    return [float(v) for v in values if v is not None]
