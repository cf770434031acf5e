"""How the surface moved between two model versions: figures (JSON) and a map (PNG)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, HTTPException, Query, status
from fastapi.responses import FileResponse

from service.api.deps import SessionDep, SettingsDep, VersionRef, resolve_version
from service.api.schemas import Problem
from service.artifacts import ArtifactError, artifact_path
from service.diff import THRESHOLD_M, VersionDiff, change_map, diff_versions

router = APIRouter(prefix="/diffs", tags=["versions"])

Threshold = Annotated[float, Query(gt=0, le=1000, description="height change above which a "
                                   "vertex counts as changed, m")]
Reach = Annotated[float, Query(gt=0, le=1, description="farthest a surface may have moved "
                               "and still be compared, km")]


@router.get("/{old}/{new}", response_model=VersionDiff,
            responses={404: {"model": Problem}, 410: {"model": Problem}})
def diff(session: SessionDep, settings: SettingsDep, old: VersionRef, new: VersionRef,
         threshold_m: Threshold = THRESHOLD_M, max_distance_km: Reach = 0.01) -> VersionDiff:
    """Signed height change of `new` against `old` along the new model's normals (m)."""
    versions = [resolve_version(session, ref).version for ref in (old, new)]
    try:
        return diff_versions(session, data_dir=settings.data_dir, old=versions[0],
                             new=versions[1], threshold_m=threshold_m,
                             max_distance_km=max_distance_km)
    except ArtifactError as exc:
        raise HTTPException(status.HTTP_410_GONE, str(exc)) from None


@router.get("/{old}/{new}/map.png", response_class=FileResponse,
            responses={200: {"content": {"image/png": {}}}, 404: {"model": Problem},
                       410: {"model": Problem}, 503: {"model": Problem}})
def diff_map(session: SessionDep, settings: SettingsDep, old: VersionRef, new: VersionRef,
             threshold_m: Threshold = THRESHOLD_M, max_distance_km: Reach = 0.01
             ) -> FileResponse:
    """The height change of `new` against `old` over latitude and longitude (PNG), made once."""
    versions = [resolve_version(session, ref) for ref in (old, new)]
    try:
        record = change_map(session, data_dir=settings.data_dir, old=versions[0], new=versions[1],
                            cache_bytes=settings.export_cache_bytes, threshold_m=threshold_m,
                            max_distance_km=max_distance_km)
        path = artifact_path(settings.data_dir, record)
    except ArtifactError as exc:
        raise HTTPException(status.HTTP_410_GONE, str(exc)) from None
    name = f"pwm-diff-v{versions[0].version:04d}-v{versions[1].version:04d}.png"
    return FileResponse(path, media_type="image/png",
                        filename=name, headers={"ETag": f'"{record["sha256"]}"'})
