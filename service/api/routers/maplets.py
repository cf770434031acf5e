"""Maplets: near a surface point, one with its image set, weights and revision history, and
re-queueing one for refinement."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, HTTPException, Query, status

from service.api.deps import Authorized, Id, JobsDep, PagingDep, SessionDep
from service.api.schemas import JobSubmitted, MapletDetail, Page, Problem
from service.queries import MapletInfo, count_maplets, list_maplets, maplet_coverage, maplet_images, maplet_revisions
from service.rows import Maplet

router = APIRouter(prefix="/maplets", tags=["maplets"])


@router.get("", response_model=Page[MapletInfo])
def list_maplets_near(
    session: SessionDep, paging: PagingDep,
    lat: Annotated[float | None, Query(ge=-90, le=90, description="planetocentric latitude, "
                                       "deg")] = None,
    lon: Annotated[float | None, Query(ge=-360, le=360, description="east longitude, deg")]
    = None,
    radius_km: Annotated[float, Query(ge=0, le=100, description="also maplets within this "
                                      "distance of the point, km")] = 0.0,
    level: Annotated[int | None, Query(ge=-64, le=64, description="only maplets of this level: node "
                                       "spacings within a factor sqrt(2) of 2^level m")] = None,
) -> Page[MapletInfo]:
    """Maplets by name; or, with lat and lon, those holding that surface point or within
    radius_km of it, nearest first; of one level if given."""
    if (lat is None) != (lon is None):
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, "give lat and lon together")
    items = list_maplets(session, lat_deg=lat, lon_deg=lon, radius_km=radius_km, level=level,
                         **paging.model_dump())
    total = count_maplets(session, lat_deg=lat, lon_deg=lon, radius_km=radius_km, level=level)
    return Page(items=items, total=total, **paging.model_dump())


@router.get("/{maplet_id}", response_model=MapletDetail, responses={404: {"model": Problem}})
def get_maplet(session: SessionDep, maplet_id: Id) -> MapletDetail:
    """A maplet: its frame, coverage summary, image set with weights, and revisions with their
    statistics (residuals)."""
    maplet = session.get(Maplet, maplet_id)
    if maplet is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"no maplet {maplet_id}")
    images = maplet_images(session, maplet_id=maplet_id)
    revisions = maplet_revisions(session, maplet_id=maplet_id)
    current = next((r.revision for r in revisions if r.current), None)
    info = MapletInfo(id=maplet.id, name=maplet.name, center_lat_deg=maplet.center_lat_deg,
                      center_lon_deg=maplet.center_lon_deg, size_km=maplet.size_km,
                      gsd_m=maplet.gsd_m, level=maplet.level, nodes_per_side=maplet.nodes_per_side,
                      region_weight=maplet.region_weight, current_revision=current,
                      image_count=len(images), distance_km=None)
    return MapletDetail(maplet=info,
                        origin_km=[maplet.origin_x_km, maplet.origin_y_km, maplet.origin_z_km],
                        rotation=maplet.rotation,
                        coverage=maplet_coverage(session, maplet_id=maplet_id),
                        images=images, revisions=revisions)


@router.post("/{maplet_id}/requeue", response_model=JobSubmitted, dependencies=[Authorized],
             status_code=status.HTTP_202_ACCEPTED,
             responses={401: {"model": Problem}, 403: {"model": Problem},
                        404: {"model": Problem}, 409: {"model": Problem},
                        503: {"model": Problem}})
def requeue(session: SessionDep, jobs: JobsDep, maplet_id: Id) -> JobSubmitted:
    """Queue the refinement of a maplet's current input (its job key comes back), also of one
    whose current revision was made with another configuration; 409 when its current revision
    is of that input already, or too few images see it."""
    try:
        with session.begin():
            key = jobs.submit_refinement(session, maplet_id=maplet_id)
    except LookupError as exc:
        raise HTTPException(status.HTTP_404_NOT_FOUND, str(exc)) from None
    except ValueError as exc:
        raise HTTPException(status.HTTP_409_CONFLICT, str(exc)) from None
    return JobSubmitted(key=key)
