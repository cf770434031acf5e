"""The browser console: its pages at / and /console/ (static files, no token needed to read),
and the documents it reads beyond the API's JSON (service.console.documents): a version's mesh
for the 3D view, a site's maps, every maplet's coverage. The console's changing controls (release,
re-queue) call the API's own changing routes, with the token the user gives."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

from fastapi import APIRouter, HTTPException, Path as FastPath, Query, status
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles

from pwm.io.mesh_tiles import TILE_KEY_PATTERN
from pwm.site import BASELINE_M, HazardThresholds
from service.api.deps import SessionDep, SettingsDep, VersionRef, resolve_version
from service.api.schemas import Problem
from service.artifacts import ArtifactError
from service.console.documents import (
    MapletCoverageRow,
    MeshRequest,
    SiteRequest,
    coverage_map,
    mesh_document,
    site_document,
    site_maplets,
    tile_document,
)
from service.exports import ExportError, Site

STATIC_DIR = Path(__file__).resolve().parents[2] / "console" / "static"
MEDIA_TYPE = "application/vnd.pwm.console"
# The documents of a version never change; `latest` and tags may name another version later.
IMMUTABLE = "public, max-age=31536000, immutable"
REVALIDATE = "no-cache"

router = APIRouter(tags=["console"])
BINARY: dict[int | str, dict[str, Any]] = {
    200: {"content": {MEDIA_TYPE: {}}}, 404: {"model": Problem}, 410: {"model": Problem},
    503: {"model": Problem}}


def static_files() -> StaticFiles:
    """The console's pages, scripts and styles (three.js vendored in vendor/), for /console."""
    return StaticFiles(directory=STATIC_DIR, html=True)


@router.get("/", include_in_schema=False)
def index() -> FileResponse:
    """The console's first page: the versions."""
    return FileResponse(STATIC_DIR / "index.html", media_type="text/html")


@router.get("/console/api/versions/{ref}/mesh", response_class=FileResponse, responses=BINARY)
def version_mesh(session: SessionDep, settings: SettingsDep, ref: VersionRef) -> FileResponse:
    """The 3D view's document of a version (service.console.documents.mesh_document): the mesh
    decimated to at most MESH_FACES faces, with albedo, height, slope and change since the
    parent per vertex, in the console's binary layout."""
    request = MeshRequest.of(resolve_version(session, ref))
    session.close()  # no connection held while the document waits for the making lock
    try:
        path = mesh_document(settings.data_dir, request, cache_bytes=settings.export_cache_bytes)
    except ArtifactError as exc:
        raise HTTPException(status.HTTP_410_GONE, str(exc)) from None
    return _document(path, ref)


@router.get("/console/api/versions/{ref}/tiles/{key}/mesh", response_class=FileResponse, responses=BINARY)
def version_tile(session: SessionDep, settings: SettingsDep, ref: VersionRef,
                 key: Annotated[str, FastPath(pattern=TILE_KEY_PATTERN)]) -> FileResponse:
    """The 3D view's document of one tile of a version stored in tiles
    (service.console.documents.tile_document): the tile at full resolution, coloured on the
    whole version's ranges; 404 for a version stored whole or a tile it does not have."""
    request = MeshRequest.of(resolve_version(session, ref))
    session.close()
    try:
        path = tile_document(settings.data_dir, request, key, cache_bytes=settings.export_cache_bytes)
    except (KeyError, ValueError) as exc:
        raise HTTPException(status.HTTP_404_NOT_FOUND,
                            f"version {request.version} has no tile {key!r}" if isinstance(exc, KeyError)
                            else str(exc)) from None
    except ArtifactError as exc:
        raise HTTPException(status.HTTP_410_GONE, str(exc)) from None
    return _document(path, ref)


@router.get("/console/api/versions/{ref}/site", response_class=FileResponse,
            responses={**BINARY, 422: {"model": Problem}})
def version_site(
    session: SessionDep, settings: SettingsDep, ref: VersionRef,
    lat: Annotated[float, Query(ge=-90, le=90, description="site latitude, deg")],
    lon: Annotated[float, Query(ge=-360, le=360, description="site east longitude, deg")],
    radius_km: Annotated[float, Query(gt=0, le=1, description="site half-width, km")],
    baseline_m: Annotated[float, Query(gt=0, le=100, description="slope, roughness and relief "
                                       "baseline, m")] = BASELINE_M,
    max_slope_deg: Annotated[float, Query(gt=0, lt=90, description="hazard above this slope, "
                                          "deg")] = HazardThresholds().max_slope_deg,
    max_relief_m: Annotated[float, Query(gt=0, le=100, description="hazard above this height "
                                         "over the local plane, m")] = HazardThresholds().max_relief_m,
) -> FileResponse:
    """A site's maps (service.console.documents.site_document): height, albedo, slope,
    roughness, relief and hazard on the site frame's grid, north in it, and where the version's
    refined maplets cover it, in the console's binary layout."""
    version = resolve_version(session, ref)
    site = Site(lat_deg=lat, lon_deg=lon, radius_km=radius_km)
    request = SiteRequest(version=version.version, mesh=version.mesh_artifact,
                          site=site, baseline_m=baseline_m,
                          thresholds=HazardThresholds(max_slope_deg=max_slope_deg,
                                                      max_relief_m=max_relief_m),
                          maplets=site_maplets(session, version=version, site=site))
    session.close()
    try:
        path = site_document(settings.data_dir, request, cache_bytes=settings.export_cache_bytes)
    except ExportError as exc:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, str(exc)) from None
    except ArtifactError as exc:
        raise HTTPException(status.HTTP_410_GONE, str(exc)) from None
    return _document(path, ref)


class _Document(FileResponse):
    # Documents run to tens of MB: read and sent in 4 MiB chunks, not Starlette's 64 KiB,
    # which cost a thread hop each.
    chunk_size = 4 * 1024 * 1024


def _document(path: Path, ref: str) -> FileResponse:
    return _Document(path, media_type=MEDIA_TYPE,
                     headers={"Cache-Control": IMMUTABLE if ref.isdigit() else REVALIDATE})


@router.get("/console/api/coverage", response_model=list[MapletCoverageRow],
            responses={422: {"model": Problem}})
def coverage(
    session: SessionDep,
    lat: Annotated[float | None, Query(ge=-90, le=90, description="site latitude, deg")] = None,
    lon: Annotated[float | None, Query(ge=-360, le=360, description="site east longitude, "
                                       "deg")] = None,
    radius_km: Annotated[float, Query(ge=0, le=100, description="maplets within this distance "
                                      "of the site, km")] = 0.0,
) -> list[MapletCoverageRow]:
    """Every maplet's coverage for the map (with lat and lon, those of a site): images that see
    it and those used, w_PWM, the used images' incidence range and whether the five views are
    filled."""
    if (lat is None) != (lon is None):
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, "give lat and lon together")
    near = (lat, lon, radius_km) if lat is not None and lon is not None else None
    return coverage_map(session, near=near)
