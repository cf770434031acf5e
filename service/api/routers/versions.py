"""Model versions: listing, detail with lineage and statistics, downloads and exports, release."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, HTTPException, Path, Query, status
from fastapi.responses import FileResponse
from sqlalchemy import func, select

from pwm.io.mesh_tiles import TILE_KEY_PATTERN
from service.api.deps import Authorized, PagingDep, SessionDep, SettingsDep, VersionRef, resolve_version
from service.api.schemas import (
    ArtifactOut,
    DownlinkRef,
    Lineage,
    Page,
    Problem,
    ReleaseRequest,
    TileOut,
    VersionDetail,
    VersionSummary,
    VersionTiles,
)
from service.artifacts import ArtifactError, artifact_path
from service.exports import (
    SITE_FORMATS,
    ExportError,
    ExportFormat,
    ExportSurface,
    Site,
    make_export,
    plan_export,
    version_tiles,
)
from service.releases import ReleaseConflict, release_version
from service.rows import ModelKind, ModelVersion

router = APIRouter(prefix="/versions", tags=["versions"])

# SPICE names: letters, digits, underscores, spaces, signs.
SPICE_NAME = r"^[A-Za-z0-9_ +-]{1,32}$"
ARTIFACT_ROLE = r"^[a-z]{1,16}$"
IMMUTABLE = "public, max-age=31536000, immutable"  # a version's files never change


def summary(version: ModelVersion) -> VersionSummary:
    stats = version.statistics
    return VersionSummary(version=version.version, kind=version.kind,
                          parent=version.parent.version if version.parent else None,
                          created_at=version.created_at, released=version.released,
                          release_tag=version.release_tag, vertices=stats.get("vertices"),
                          faces=stats.get("faces"))


def detail(version: ModelVersion) -> VersionDetail:
    ancestors, parent = [], version.parent
    while parent is not None:
        ancestors.append(parent.version)
        parent = parent.parent
    lineage = Lineage(ancestors=ancestors,
                      children=sorted(child.version for child in version.children),
                      downlinks=[DownlinkRef.model_validate(d) for d in version.downlinks],
                      maplet_revisions=len(version.maplet_revisions))
    return VersionDetail(**summary(version).model_dump(), statistics=version.statistics,
                         artifacts={role: ArtifactOut(sha256=a["sha256"], bytes=a["bytes"])
                                    for role, a in version.artifacts.items()},
                         lineage=lineage)


@router.get("", response_model=Page[VersionSummary])
def list_versions(session: SessionDep, paging: PagingDep,
                  kind: ModelKind | None = None, released: bool | None = None
                  ) -> Page[VersionSummary]:
    """Model versions, newest first; optionally of one kind, or only (un)released ones."""
    query = select(ModelVersion)
    if kind is not None:
        query = query.where(ModelVersion.kind == kind)
    if released is not None:
        query = query.where(ModelVersion.released.is_(released))
    total = session.execute(select(func.count()).select_from(query.subquery())).scalar_one()
    rows = session.scalars(query.order_by(ModelVersion.version.desc())
                           .limit(paging.limit).offset(paging.offset))
    return Page(items=[summary(v) for v in rows], total=total, **paging.model_dump())


@router.get("/{ref}", response_model=VersionDetail, responses={404: {"model": Problem}})
def get_version_detail(session: SessionDep, ref: VersionRef) -> VersionDetail:
    """One version with its statistics, artifacts and lineage."""
    return detail(resolve_version(session, ref))


@router.get("/{ref}/artifacts/{role}", response_class=FileResponse,
            responses={200: {"content": {"application/octet-stream": {}}},
                       404: {"model": Problem}})
def download_artifact(session: SessionDep, settings: SettingsDep, ref: VersionRef,
                      role: Annotated[str, Path(pattern=ARTIFACT_ROLE)]) -> FileResponse:
    """A file the version was published with (`ply`, `obj`, `grid`, ...), as stored."""
    version = resolve_version(session, ref)
    record = version.artifacts.get(role)
    if record is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND,
                            f"version {version.version} has no artifact {role!r}; it has "
                            f"{sorted(version.artifacts)}")
    try:
        path = artifact_path(settings.data_dir, record)
    except ArtifactError as exc:
        raise HTTPException(status.HTTP_410_GONE, str(exc)) from None
    return FileResponse(path, media_type="application/octet-stream",
                        filename=f"pwm-v{version.version:04d}-{role}{path.suffix}",
                        headers={"Cache-Control": IMMUTABLE})


@router.get("/{ref}/tiles", response_model=VersionTiles, responses={404: {"model": Problem},
                                                                    410: {"model": Problem}})
def list_tiles(session: SessionDep, settings: SettingsDep, ref: VersionRef) -> VersionTiles:
    """The tiles of a version whose mesh is too big for one file (more faces than
    PWM_MESH_TILE_FACES): each one's key, size and bounding box; export one with
    `export?format=ply&tile=KEY` (or obj, las). 404 for a version stored whole."""
    version = resolve_version(session, ref)
    try:
        index = version_tiles(settings.data_dir, version)
    except ArtifactError as exc:
        raise HTTPException(status.HTTP_410_GONE, str(exc)) from None
    if index is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"version {version.version} is stored whole, "
                            f"not in tiles ({version.statistics.get('faces')} faces)")
    return VersionTiles(version=version.version, vertices=index.vertices, faces=index.faces,
                        tiles=[TileOut(key=t.key, faces=t.faces, vertices=t.vertices, box_min_km=t.box_km[0],
                                       box_max_km=t.box_km[1], sha256=t.file["sha256"], bytes=t.file["bytes"])
                               for t in index.tiles])


@router.get("/{ref}/export", response_class=FileResponse,
            responses={200: {"content": {"application/octet-stream": {}}},
                       404: {"model": Problem}, 503: {"model": Problem}})
def export(session: SessionDep, settings: SettingsDep, ref: VersionRef,
           format: ExportFormat,
           surface: Annotated[ExportSurface, Query(description="model: every level; global: the whole "
                                                   "body's levels, beneath the sites")] = ExportSurface.MODEL,
           faces: Annotated[int | None, Query(ge=4, le=100_000_000,
                                              description="decimate to about this many faces")]
           = None,
           lat: Annotated[float | None, Query(ge=-90, le=90, description="site latitude, deg")]
           = None,
           lon: Annotated[float | None, Query(ge=-360, le=360,
                                              description="site east longitude, deg")] = None,
           radius_km: Annotated[float | None, Query(gt=0, le=100,
                                                    description="site half-width, km")] = None,
           body: Annotated[str | None, Query(pattern=SPICE_NAME,
                                             description="NAIF body name or ID")] = None,
           frame: Annotated[str | None, Query(pattern=SPICE_NAME,
                                              description="body-fixed frame name")] = None,
           tile: Annotated[str | None, Query(pattern=TILE_KEY_PATTERN, description="one tile of a version "
                                             "stored in tiles (obj, ply, las)")] = None,
           ) -> FileResponse:
    """The version as OBJ, PLY (albedo per vertex), ICQ, SPICE DSK type 2 (km, body-fixed; of
    the whole model, a segment for the body and one per site), LAS (its vertices, m, body-fixed,
    albedo per point), or the terrain of a site (lat, lon and radius_km): format `site`, a zip
    of the PDS4 label, its data file and a PNG preview; `geotiff` or `isis`, the same layers as
    a GeoTIFF or an ISIS3 cube in an orthographic projection about the site. surface `global`:
    the global model alone, beneath the sites. Body and frame default to the catalog's. A
    version too big for one file (`GET /versions/{ref}/tiles`) gives its OBJ, PLY and LAS a
    tile at a time (`tile`) or decimated (`faces`), its DSK a segment per tile. While
    too many exports are being made, one not made yet is refused with 503 and Retry-After."""
    version = resolve_version(session, ref)
    site_args = (lat, lon, radius_km)
    if format in SITE_FORMATS and None in site_args:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT,
                            f"format={format} needs lat, lon and radius_km")
    if format not in SITE_FORMATS and any(a is not None for a in site_args):
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT,
                            f"lat, lon and radius_km go with format={' | '.join(sorted(SITE_FORMATS))} only")
    site = (Site(lat_deg=lat, lon_deg=lon, radius_km=radius_km)
            if lat is not None and lon is not None and radius_km is not None else None)  # site format only
    try:
        plan = plan_export(session, data_dir=settings.data_dir, version=version, fmt=format,
                           surface=surface, faces=faces, site=site, body=body, frame=frame, tile=tile)
        # The connection goes back to the pool before the export waits for its turn.
        session.close()
        made = make_export(plan, cache_bytes=settings.export_cache_bytes)
    except ExportError as exc:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, str(exc)) from None
    except ArtifactError as exc:
        raise HTTPException(status.HTTP_410_GONE, str(exc)) from None
    return FileResponse(made.path, media_type=made.media_type, filename=made.filename,
                        headers={"Cache-Control": IMMUTABLE, "ETag": f'"{made.sha256}"',
                                 **({"X-PWM-Closure": made.closure} if made.closure else {})})


@router.post("/{ref}/release", response_model=VersionDetail, dependencies=[Authorized],
             responses={401: {"model": Problem}, 403: {"model": Problem},
                        404: {"model": Problem}, 409: {"model": Problem}})
def release(session: SessionDep, ref: VersionRef, body: ReleaseRequest) -> VersionDetail:
    """Mark a version released under a tag. The tag is set once: a released version cannot be
    changed or unreleased (409), and a tag names one version."""
    try:
        with session.begin():
            version = release_version(session, ref, tag=body.tag)
    except LookupError as exc:
        raise HTTPException(status.HTTP_404_NOT_FOUND, str(exc)) from None
    except ReleaseConflict as exc:
        raise HTTPException(status.HTTP_409_CONFLICT, str(exc)) from None
    return detail(version)
