"""Exports of a model version: OBJ, PLY (per-vertex albedo; both with the version, frame and
units in their headers), Gaskell ICQ, SPICE DSK type 2, a LAS point cloud of its vertices (m,
body-fixed, albedo per point), and a site's terrain: a local product (PDS4 heights, albedo,
slope and roughness in the site frame with a Cartography area, and a PNG preview) or the same
layers as a GeoTIFF or an ISIS3 cube in an orthographic projection about the site
(pwm.io.terrain), for GIS and ISIS.

Of a version with levels (pwm.levels), the mesh formats give the whole model (surface `model`,
each place at the finest level that covers it), or the global model alone at the levels of the
whole body (surface `global`: the surface the sites are laid onto, the survey's). The whole
model's DSK has one segment for the body and one per site region, which part it without
overlapping (pwm.io.dsk.write_dsk), so navigation loading it gets the model's own intercepts,
and each segment's index sized to its plates; the global DSK is one segment. A site product is
sampled from the whole model at the spacing of its faces there, the finest level's; its
projection is on the sphere of the body's mean radius, from the constants kernels' radii.

A version whose mesh is stored in tiles (PWM_MESH_TILE_FACES, service.versions.store_mesh) is
too big for one file of a mesh format: its OBJ, PLY and LAS are made a tile at a time (`tile`,
the tiles' keys in its index), each from that tile's file alone, or of the whole decimated; its
DSK has a segment per tile (and per site region within it), each within DSK type 2's limits.

Every export may be decimated to a requested face count first (pwm.decimate: a closed surface
stays closed). A DSK is made only of one closed surface (pwm.evaluate.closure), else refused
saying why; OBJ, PLY and ICQ are made either way, and tell whether their file is closed
(ExportFile.closure, a warning logged when not). An export is made once and kept
in the artifact store's cache (service.artifacts.cached_artifact), keyed by the version's mesh
checksum with the format and the parameters as asked.

An export is planned from the catalog first (plan_export) and made without it (make_export), so
that no database connection is held while a request waits for its turn (the cache's making
lock, which SPICE's kernel pool needs) or while the file is made.
"""

from __future__ import annotations

import dataclasses
import enum
import logging
import math
import zipfile
from collections.abc import Iterable
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np
import spiceypy as sp
from pydantic import BaseModel, ConfigDict, Field
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from pwm.decimate import decimate
from pwm.evaluate.closure import closure
from pwm.io.dsk import write_dsk
from pwm.io.fusion_state import read_composition
from pwm.io.icq import mesh_to_icq, write_icq
from pwm.io.las import body_fixed_wkt, write_las
from pwm.io.mesh_tiles import TileIndex
from pwm.io.meshio import read_shape_model, write_obj, write_ply
from pwm.io.site_product import site_layers, write_site_product
from pwm.io.spice_kernels import kernel_pool
from pwm.io.terrain import TerrainDriver, site_projection, write_terrain
from pwm.mesh import Mesh
from pwm.site import SiteGrid, resample_site
from service.artifacts import (
    artifact_mesh,
    artifact_path,
    artifact_tile,
    cached_artifact,
    digest,
    holds_tiles,
    tile_index,
    tiled_mesh,
)
from service.kernels import accepted_kernels
from service.rows import (
    Image,
    ImageGeometry,
    ImageStatus,
    Instrument,
    KernelKind,
    ModelVersion,
    model_version_downlinks,
)

# Bump when an export's content changes for the same inputs, so that old cache entries are
# not served for new requests.
EXPORT_REVISION = 5
# The site grid has at most (2 * MAX_SITE_HALF_NODES + 1)^2 nodes.
MAX_SITE_HALF_NODES = 500

log = logging.getLogger(__name__)


class ExportFormat(enum.StrEnum):
    OBJ = "obj"
    PLY = "ply"
    ICQ = "icq"
    DSK = "dsk"
    SITE = "site"
    GEOTIFF = "geotiff"
    ISIS = "isis"
    LAS = "las"


# The formats of a site's terrain, sampled about a site (Site).
SITE_FORMATS = frozenset({ExportFormat.SITE, ExportFormat.GEOTIFF, ExportFormat.ISIS})
# The formats that name the body and its body-fixed frame, which the plan reads from the catalog.
TARGET_FORMATS = SITE_FORMATS | {ExportFormat.DSK, ExportFormat.LAS}


class ExportSurface(enum.StrEnum):
    """Which surface of a version: all of it (`model`) or the global model beneath the sites."""

    MODEL = "model"
    GLOBAL = "global"


SUFFIXES = {ExportFormat.OBJ: ".obj", ExportFormat.PLY: ".ply", ExportFormat.ICQ: ".icq",
            ExportFormat.DSK: ".bds", ExportFormat.SITE: ".zip", ExportFormat.GEOTIFF: ".tif",
            ExportFormat.ISIS: ".cub", ExportFormat.LAS: ".las"}
MEDIA_TYPES = {ExportFormat.OBJ: "model/obj", ExportFormat.PLY: "application/octet-stream",
               ExportFormat.ICQ: "text/plain", ExportFormat.DSK: "application/octet-stream",
               ExportFormat.SITE: "application/zip",
               ExportFormat.GEOTIFF: "image/tiff; application=geotiff",
               ExportFormat.ISIS: "application/octet-stream", ExportFormat.LAS: "application/vnd.las"}


class ExportError(Exception):
    """The export cannot be made from this version with these parameters."""


# The formats that are one surface: a DSK is refused unless it is closed, these are made and
# their closure told (ExportFile.closure).
CLOSURE_FORMATS = frozenset({ExportFormat.OBJ, ExportFormat.PLY, ExportFormat.ICQ})
# The formats made a tile at a time of a version stored in tiles.
TILE_FORMATS = frozenset({ExportFormat.OBJ, ExportFormat.PLY, ExportFormat.LAS})


class Site(BaseModel):
    """A site: the surface point at planetocentric latitude and east longitude (deg), and the
    half-width (km) of the square grid about it."""

    model_config = ConfigDict(frozen=True)

    lat_deg: float = Field(ge=-90.0, le=90.0)
    lon_deg: float = Field(ge=-360.0, le=360.0)
    radius_km: float = Field(gt=0.0, le=100.0)


@dataclass(frozen=True)
class ExportFile:
    """A made export: its file in the data directory, a name to download it as, its type, and
    for the surface formats (CLOSURE_FORMATS) whether it is one closed surface ("closed", or
    "open: " and why, pwm.evaluate.closure.Closure.describe; None for the other formats)."""

    path: Path
    filename: str
    media_type: str
    sha256: str
    closure: str | None = None


@dataclass(frozen=True)
class Target:
    """The body a model is of: NAIF ID and name, and its body-fixed frame."""

    body_id: int
    name: str
    frame: str


def icq_size(faces: int) -> int:
    """The ICQ grid size q whose mesh (12 q^2 triangles) comes nearest `faces`."""
    return max(1, round(math.sqrt(faces / 12)))


@dataclass(frozen=True)
class ExportPlan:
    """What making an export needs from the catalog, read beforehand: the version (number, kind,
    creation time, its mesh's record (`ModelVersion.mesh_artifact`, or the one tile's asked
    for, `tile` its key) and its composition's, if any), the request (format,
    surface, faces, site, body and frame; frame from the catalog's images unless given), the
    catalog's accepted PCK and FK files with their checksums, and for a site product the time
    span and spacecraft of its images."""

    data_dir: Path
    version: int
    kind: str
    created_at: datetime
    mesh: dict[str, Any]
    fmt: ExportFormat
    faces: int | None
    filename: str
    surface: ExportSurface = ExportSurface.MODEL
    composition: dict[str, Any] | None = None
    site: Site | None = None
    body: str | None = None
    frame: str | None = None
    kernels: tuple[tuple[Path, str], ...] = ()
    time_span: tuple[datetime, datetime] | None = None
    spacecraft_id: int | None = None
    tile: str | None = None

    def key(self) -> str:
        """The cache key: a hex digest of everything the file depends on."""
        return digest({"mesh": self.mesh["sha256"], "version": self.version,
                       "revision": EXPORT_REVISION, "fmt": self.fmt.value, "faces": self.faces,
                       "surface": self.surface.value,
                       "composition": self.composition["sha256"] if self.composition else None,
                       "site": self.site.model_dump() if self.site else None, "body": self.body,
                       "frame": self.frame, "kernels": [sha for _, sha in self.kernels],
                       "time_span": self.time_span, "spacecraft": self.spacecraft_id, "tile": self.tile})


def plan_export(session: Session, *, data_dir: Path, version: ModelVersion, fmt: ExportFormat,
                surface: ExportSurface = ExportSurface.MODEL, faces: int | None = None,
                site: Site | None = None, body: str | None = None, frame: str | None = None,
                tile: str | None = None) -> ExportPlan:
    """Read from the catalog what exporting `version` in format `fmt` needs (make_export makes
    it, without the catalog: end the session's transaction in between).

    surface: the whole model, or the global model beneath the sites (the whole model for a
    version without sites). faces: decimate to about this many faces first (none, or at least
    the surface's count: full resolution); ICQ takes q from it (icq_size). site: needed by, and only by, a site's
    terrain (SITE_FORMATS). body (NAIF name or ID) and frame (body-fixed frame name) override
    what the catalog's images give, for the formats that name them (TARGET_FORMATS; OBJ and
    PLY name the frame when it is known). tile: the key of one tile of a version stored in tiles
    (TILE_FORMATS), which such a version's OBJ, PLY and LAS need unless decimated. Raises
    ExportError when the export cannot be made.
    """
    if (fmt in SITE_FORMATS) != (site is not None):
        raise ExportError(f"a site's terrain ({', '.join(sorted(SITE_FORMATS))}) needs a site, "
                          "and only it takes one")
    if fmt in SITE_FORMATS and surface is ExportSurface.GLOBAL:
        raise ExportError("a site's terrain is sampled from the whole model (the finest level there), "
                          "not from the global one")
    composition = version.artifacts.get("composition")
    below = surface is ExportSurface.GLOBAL and composition is not None
    total = None if below else int(version.statistics.get("faces", 0)) or None
    if faces is not None and faces < 4:
        raise ExportError(f"faces must be at least 4, got {faces}")
    if faces is not None and total is not None and faces >= total:
        faces = None
    mesh = _mesh_record(data_dir, version, fmt=fmt, tile=tile, faces=faces, below=below)
    name = (f"pwm-v{version.version:04d}" + ("-global" if below else "") + (f"-f{faces}" if faces else "")
            + (f"-{tile}" if tile else "") + SUFFIXES[fmt])
    plan = ExportPlan(data_dir=data_dir, version=version.version, kind=str(version.kind),
                      created_at=version.created_at, mesh=mesh, tile=tile,
                      fmt=fmt, faces=faces, filename=name, site=site,
                      surface=ExportSurface.GLOBAL if below else ExportSurface.MODEL,
                      composition=dict(composition) if composition is not None else None)
    if fmt not in TARGET_FORMATS | {ExportFormat.OBJ, ExportFormat.PLY}:
        return plan
    if frame is None:
        frame = _most_common(session, select(ImageGeometry.body_frame))
    if fmt in (ExportFormat.OBJ, ExportFormat.PLY):  # the frame named in the header, if known
        return dataclasses.replace(plan, frame=frame)
    if frame is None:
        raise ExportError("the catalog has no image geometry to take the body-fixed frame "
                          "from: give the frame")
    kernels = tuple((Path(k.path), k.sha256) for k in accepted_kernels(session)
                    if k.kind in (KernelKind.PCK, KernelKind.FK) and Path(k.path).is_file())
    site_context = {}
    if fmt is ExportFormat.SITE:
        site_context = {"time_span": _time_span(session, version),
                        "spacecraft_id": _most_common(session, select(
                            Instrument.spacecraft_id).join(
                                Image, Image.instrument_id == Instrument.id))}
    return dataclasses.replace(plan, body=body, frame=frame, kernels=kernels, **site_context)


def version_tiles(data_dir: Path, version: ModelVersion) -> TileIndex | None:
    """The index of a version's tiles, or None for a version stored whole."""
    return tile_index(data_dir, version.artifacts["tiles"]) if "tiles" in version.artifacts else None


def _mesh_record(data_dir: Path, version: ModelVersion, *, fmt: ExportFormat, tile: str | None,
                 faces: int | None, below: bool) -> dict[str, Any]:
    """The record of the file the export reads its mesh from: the version's, or the tile's."""
    tiles = version_tiles(data_dir, version)
    if tile is None:
        if tiles is not None and fmt in TILE_FORMATS and faces is None and not below:
            raise ExportError(
                f"version {version.version}'s mesh has {tiles.faces} faces, stored in {len(tiles.tiles)} tiles: "
                f"export its {fmt.value.upper()} a tile at a time (tile=KEY; the keys: GET "
                f"/versions/{version.version}/tiles, or `pwm export --tile all`), or decimated (faces=N)")
        return version.mesh_artifact
    if tiles is None:
        raise ExportError(f"version {version.version} is stored whole, not in tiles: export it without a tile")
    if fmt not in TILE_FORMATS or faces is not None or below:
        raise ExportError(f"a tile is exported whole, as {' | '.join(sorted(TILE_FORMATS))}, of the model's "
                          "surface: no faces and no global surface with it")
    try:
        return dict(tiles.entry(tile).file)
    except KeyError:
        raise ExportError(f"version {version.version} has no tile {tile!r}; it has "
                          f"{tiles.tiles[0].key} to {tiles.tiles[-1].key}") from None


def make_export(plan: ExportPlan, *, cache_bytes: int) -> ExportFile:
    """The file of an export plan, made and kept on first request (cache_bytes: how many bytes
    of derived files the data directory keeps; service.artifacts.cached_artifact).

    Raises ExportError when the export cannot be made, service.artifacts.ArtifactError when the
    version's files are damaged, service.artifacts.CacheBusy when too many files are being made.
    """
    fmt, faces = plan.fmt, plan.faces

    def make(path: Path) -> dict[str, Any] | None:
        composition = (read_composition(artifact_path(plan.data_dir, plan.composition, verify=True))
                       if plan.composition is not None else None)
        tiles = None
        if plan.surface is ExportSurface.GLOBAL and composition is not None:
            mesh = composition.below
        elif plan.tile is not None:
            mesh = artifact_tile(plan.data_dir, plan.mesh).mesh
        elif holds_tiles(plan.mesh) and fmt is ExportFormat.DSK:
            _, mesh, tiles = tiled_mesh(plan.data_dir, plan.mesh)
        else:
            mesh = artifact_mesh(plan.data_dir, plan.mesh)
        # a DSK of the whole model at full resolution: a segment per site region, one for the rest
        parts = composition.face_region() if plan.surface is ExportSurface.MODEL and composition else None
        if tiles is not None:  # and within each tile
            parts = tiles if parts is None else np.unique(np.stack([tiles, parts]), axis=1,
                                                          return_inverse=True)[1].ravel()
        if faces is not None and faces < len(mesh.faces):
            mesh, parts, tiles = _decimated(mesh, faces), None, None
        if fmt is ExportFormat.DSK and not (checks := closure(mesh)).closed:
            raise ExportError(f"no DSK of version {plan.version}: a DSK must be one closed surface, and this "
                              f"one is {checks.describe()}")
        if fmt is ExportFormat.ICQ:
            _write_icq(path, mesh, icq_size(faces or len(mesh.faces)))
        elif fmt is ExportFormat.DSK:
            _write_dsk(path, mesh, plan=plan, parts=parts, tiled=tiles is not None)
        elif fmt is ExportFormat.SITE:
            _write_site(path, mesh, plan=plan)
        elif fmt in (ExportFormat.GEOTIFF, ExportFormat.ISIS):
            _write_terrain(path, mesh, plan=plan)
        elif fmt is ExportFormat.LAS:
            _write_las(path, mesh, plan=plan)
        else:
            frame = plan.frame or "body-fixed (frame not named by the catalog)"
            (write_ply if fmt is ExportFormat.PLY else write_obj)(path, mesh, comments=[
                f"pwm shape model version {plan.version} ({plan.kind}), made "
                f"{plan.created_at:%Y-%m-%dT%H:%M:%SZ}", f"frame {frame}", "units km",
                *([f"tile {plan.tile}: the version's tiles meet vertex on vertex"] if plan.tile else [])])
        # read back from the file as written, and kept in its record
        # (self-intersections are counted for a DSK only: they cost tens of seconds a million faces)
        return ({"closure": closure(read_shape_model(path), count_intersections=False).describe()}
                if fmt in CLOSURE_FORMATS else None)

    record = cached_artifact(plan.data_dir, plan.key(), suffix=SUFFIXES[fmt], make=make,
                             cache_bytes=cache_bytes)
    path = artifact_path(plan.data_dir, record)
    verdict = "closed" if fmt is ExportFormat.DSK else record.get("closure")
    if verdict not in (None, "closed"):
        log.warning("%s of version %d is not one closed surface (%s): mass properties and polyhedral "
                    "gravity need one", plan.filename, plan.version, verdict)
    return ExportFile(path, plan.filename, MEDIA_TYPES[fmt], record["sha256"], verdict)


def _decimated(mesh: Mesh, faces: int) -> Mesh:
    try:
        return decimate(mesh, faces)
    except ValueError as exc:  # a closed surface that the collapse would leave open
        raise ExportError(f"no export at {faces} faces: {exc}") from exc


def resolve_target(kernels: Iterable[Path], *, body: str | None, frame: str) -> Target:
    """The body-fixed `frame` and the body at its centre (or `body`: NAIF name or ID), known to
    SPICE from its built-in names and the given frame and constants kernels. Raises ExportError
    when unknown. The caller holds the making lock."""
    with kernel_pool(kernels), sp.no_found_check():
        frame_code = sp.namfrm(frame)
        if frame_code == 0:
            raise ExportError(f"SPICE knows no frame {frame!r}")
        if body is None:
            code, found = int(sp.frinfo(frame_code)[0]), True
        elif body.lstrip("+-").isdigit():
            code, found = int(body), True
        else:
            code, found = sp.bodn2c(body)
        if not found:
            raise ExportError(f"SPICE knows no body {body!r}")
        name, named = sp.bodc2n(code)
    return Target(body_id=int(code), name=name if named else str(code), frame=frame)


def site_grid(mesh: Mesh, site: Site) -> SiteGrid:
    """`mesh` resampled about the site (pwm.site.resample_site, at most
    2 MAX_SITE_HALF_NODES + 1 nodes a side), as the site product and the console's site maps
    take it. Raises ExportError where the site meets no surface."""
    try:
        return resample_site(mesh, lat_deg=site.lat_deg, lon_deg=site.lon_deg, radius_km=site.radius_km,
                             max_half_nodes=MAX_SITE_HALF_NODES)
    except ValueError as exc:
        raise ExportError(str(exc)) from exc


def _write_icq(path: Path, mesh: Mesh, q: int) -> None:
    try:
        grid = mesh_to_icq(mesh, q)
    except ValueError as exc:  # a mesh not star-shaped about the body centre
        raise ExportError(f"no ICQ model of this version: {exc}") from exc
    write_icq(path, grid)


def _write_dsk(path: Path, mesh: Mesh, *, plan: ExportPlan, parts: np.ndarray | None, tiled: bool) -> None:
    target = _target(plan)
    segments = 1 if parts is None else len(np.unique(parts))
    what = ("the global model beneath the sites" if plan.surface is ExportSurface.GLOBAL
            else f"{segments} segments: each tile of the model and each site region within it, parting the "
                 "surface without overlap" if tiled
            else f"{segments} segments: the body and each site region, parting the surface without overlap"
            if segments > 1 else "one segment")
    comment = (f"pwm shape model version {plan.version} ({plan.kind}), made "
               f"{plan.created_at:%Y-%m-%dT%H:%M:%SZ}; plate model in km in {target.frame}; "
               f"{len(mesh.vertices)} vertices, {len(mesh.faces)} plates; {what}.")
    with kernel_pool(_kernel_paths(plan)):
        write_dsk(path, mesh, body=target.body_id, frame=target.frame, comment=comment, parts=parts)


def _site_sample(mesh: Mesh, plan: ExportPlan) -> SiteGrid:
    assert plan.site is not None  # plan_export sets it for the site formats
    grid = site_grid(mesh, plan.site)
    if np.isnan(grid.height_km).all():
        raise ExportError("the site grid meets no surface")
    return grid


def _write_terrain(path: Path, mesh: Mesh, *, plan: ExportPlan) -> None:
    target = _target(plan)
    grid = _site_sample(mesh, plan)
    radii = _radii(plan, target)
    projection = site_projection(grid.frame, body=target.name, radii_km=radii)
    spacing_m = float(grid.x_km[1] - grid.x_km[0]) * 1e3
    driver = TerrainDriver.ISIS3 if plan.fmt is ExportFormat.ISIS else TerrainDriver.GEOTIFF

    def numbers(values: Iterable[float]) -> str:
        return " ".join(f"{v:.12g}" for v in values)

    write_terrain(path, driver=driver, x_km=grid.x_km, y_km=grid.y_km, projection=projection,
                  layers=site_layers(grid.height_km, grid.albedo, spacing_m=spacing_m, sigma_km=grid.sigma_km),
                  metadata={
                      "PWM_VERSION": str(plan.version), "PWM_MODEL_KIND": plan.kind,
                      "BODY": target.name, "BODY_NAIF_ID": str(target.body_id),
                      "BODY_FRAME": target.frame, "BODY_RADII_KM": numbers(radii),
                      "SITE_FRAME_ORIGIN_KM": numbers(grid.frame.origin),
                      "SITE_FRAME_AXES": numbers(grid.frame.rotation.ravel()),
                      "HEIGHT": "m along the site frame z axis (the projection's centre "
                                "direction) from the site frame origin, not above the sphere",
                      "SITE_FRAME": "rows of SITE_FRAME_AXES: x (east), y (north), z (regional "
                                    f"normal) in {target.frame}; origin and radii in km"})


def _write_las(path: Path, mesh: Mesh, *, plan: ExportPlan) -> None:
    target = _target(plan)
    radius = sum(_radii(plan, target)) / 3.0
    write_las(path, vertices_km=mesh.vertices, albedo=mesh.albedo,
              crs_wkt=body_fixed_wkt(body=target.name, frame=target.frame, radius_km=radius),
              system_identifier=f"pwm v{plan.version} {target.frame}"[:32],
              description=f"pwm shape model version {plan.version} ({plan.kind}) of {target.name}: "
                          f"its {len(mesh.vertices)} vertices in m in {target.frame}"
                          + ("; albedo per point" if mesh.albedo is not None else ""))


def _radii(plan: ExportPlan, target: Target) -> tuple[float, float, float]:
    """The body's radii (km) from the plan's constants kernels. The caller holds the making
    lock."""
    with kernel_pool(_kernel_paths(plan)):
        if not sp.bodfnd(target.body_id, "RADII"):
            raise ExportError(f"the catalog's constants kernels give no radii of {target.name}: "
                              f"accept a PCK with BODY{target.body_id}_RADII")
        _, radii = sp.bodvcd(target.body_id, "RADII", 3)
    if not (np.isfinite(radii).all() and np.min(radii) > 0):
        raise ExportError(f"the constants kernels' radii of {target.name} are not positive: {list(radii)}")
    return (float(radii[0]), float(radii[1]), float(radii[2]))


def _write_site(path: Path, mesh: Mesh, *, plan: ExportPlan) -> None:
    assert plan.site is not None and plan.time_span is not None  # plan_export sets them
    target = _target(plan)
    grid = _site_sample(mesh, plan)
    start, stop = plan.time_span
    host = _spacecraft(plan.spacecraft_id)
    name = f"pwm_site_v{plan.version:04d}_{digest(plan.site.model_dump())[:10]}"
    scratch = path.parent / "site"
    scratch.mkdir()
    projection = site_projection(grid.frame, body=target.name, radii_km=_radii(plan, target))
    files = write_site_product(
        scratch, name=name, frame=grid.frame, x_km=grid.x_km, y_km=grid.y_km,
        height_km=grid.height_km, albedo=grid.albedo, sigma_km=grid.sigma_km, projection=projection,
        lid=f"urn:nasa:pds:pwm:data_site:{name}", version="1.0",
        model_version=str(plan.version),
        source_lidvid=f"urn:nasa:pds:pwm:shape_model:v{plan.version:04d}::1.0",
        body_frame=target.frame,
        target_name=target.name, mission=host, host_name=host,
        start_utc=start.isoformat(), stop_utc=stop.isoformat())
    # Stored, not deflated: binary doubles compress little.
    with zipfile.ZipFile(path, "x", compression=zipfile.ZIP_STORED) as archive:
        for file in files:
            archive.write(file, arcname=file.name)


def _kernel_paths(plan: ExportPlan) -> list[Path]:
    return [path for path, _ in plan.kernels]


def _target(plan: ExportPlan) -> Target:
    assert plan.frame is not None  # plan_export sets it for DSK and site products
    return resolve_target(_kernel_paths(plan), body=plan.body, frame=plan.frame)


def _time_span(session: Session, version: ModelVersion) -> tuple[datetime, datetime]:
    """First start and last stop (UTC) of the accepted images of the version's downlinks (all
    accepted images when it names none); its creation time when there are none."""
    query = select(func.min(Image.start_utc), func.max(func.coalesce(Image.stop_utc,
                                                                     Image.start_utc)))
    query = query.where(Image.status == ImageStatus.ACCEPTED)
    if version.downlinks:
        query = query.join(model_version_downlinks,
                           model_version_downlinks.c.downlink_id == Image.downlink_id).where(
            model_version_downlinks.c.model_version_id == version.id)
    start, stop = session.execute(query).one()
    return (start or version.created_at, stop or version.created_at)


def _spacecraft(code: int | None) -> str:
    """The name of the spacecraft of NAIF ID `code` (SPICE's built-in names), or 'unknown'.
    The caller holds the making lock."""
    if code is None:
        return "unknown"
    with sp.no_found_check():
        name, found = sp.bodc2n(code)
    return name if found else str(code)


def _most_common(session: Session, query: Any) -> Any:
    column = query.subquery().c[0]
    row = session.execute(select(column, func.count()).group_by(column)
                          .order_by(func.count().desc(), column).limit(1)).first()
    return None if row is None else row[0]
