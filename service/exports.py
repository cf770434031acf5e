"""Exports of a model version: OBJ, PLY (per-vertex albedo), Gaskell ICQ, SPICE DSK type 2, and
a local terrain product of a site (PDS4 heights and albedo in the site frame, with a PNG preview).

Of a version with levels (pwm.levels), the mesh formats give the whole model (surface `model`,
each place at the finest level that covers it), or the global model alone at the levels of the
whole body (surface `global`: the surface the sites are laid onto, the survey's). The whole
model's DSK has one segment for the body and one per site region, which part it without
overlapping (pwm.io.dsk.write_dsk), so navigation loading it gets the model's own intercepts,
and each segment's index sized to its plates; the global DSK is one segment. A site product is
sampled from the whole model at the spacing of its faces there, the finest level's.

Every export may be decimated to a requested face count first. An export is made once and kept
in the artifact store's cache (service.artifacts.cached_artifact), keyed by the version's mesh
checksum with the format and the parameters as asked; the mesh formats at full resolution are
the version's own artifacts.

An export is planned from the catalog first (plan_export) and made without it (make_export), so
that no database connection is held while a request waits for its turn (the cache's making
lock, which SPICE's kernel pool needs) or while the file is made.
"""

from __future__ import annotations

import dataclasses
import enum
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
from pwm.io.dsk import write_dsk
from pwm.io.fusion_state import read_composition
from pwm.io.icq import mesh_to_icq, write_icq
from pwm.io.meshio import write_obj, write_ply
from pwm.io.site_product import write_site_product
from pwm.io.spice_kernels import kernel_pool
from pwm.mesh import Mesh
from pwm.site import SiteGrid, resample_site
from service.artifacts import artifact_mesh, artifact_path, cached_artifact, digest
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
EXPORT_REVISION = 4
# The site grid has at most (2 * MAX_SITE_HALF_NODES + 1)^2 nodes.
MAX_SITE_HALF_NODES = 500


class ExportFormat(enum.StrEnum):
    OBJ = "obj"
    PLY = "ply"
    ICQ = "icq"
    DSK = "dsk"
    SITE = "site"


class ExportSurface(enum.StrEnum):
    """Which surface of a version: all of it (`model`) or the global model beneath the sites."""

    MODEL = "model"
    GLOBAL = "global"


SUFFIXES = {ExportFormat.OBJ: ".obj", ExportFormat.PLY: ".ply", ExportFormat.ICQ: ".icq",
            ExportFormat.DSK: ".bds", ExportFormat.SITE: ".zip"}
MEDIA_TYPES = {ExportFormat.OBJ: "model/obj", ExportFormat.PLY: "application/octet-stream",
               ExportFormat.ICQ: "text/plain", ExportFormat.DSK: "application/octet-stream",
               ExportFormat.SITE: "application/zip"}


class ExportError(Exception):
    """The export cannot be made from this version with these parameters."""


class Site(BaseModel):
    """A site: the surface point at planetocentric latitude and east longitude (deg), and the
    half-width (km) of the square grid about it."""

    model_config = ConfigDict(frozen=True)

    lat_deg: float = Field(ge=-90.0, le=90.0)
    lon_deg: float = Field(ge=-360.0, le=360.0)
    radius_km: float = Field(gt=0.0, le=100.0)


@dataclass(frozen=True)
class ExportFile:
    """A made export: its file in the data directory, a name to download it as, its type."""

    path: Path
    filename: str
    media_type: str
    sha256: str


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
    creation time, PLY artifact record and its composition's, if any; its own record of the file
    asked for, for the mesh formats at full resolution), the request (format, surface, faces,
    site, body and frame; frame from the catalog's images unless given), the catalog's accepted
    PCK and FK files with their checksums, and for a site product the time span and spacecraft
    of its images."""

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
    own: dict[str, Any] | None = None

    def key(self) -> str:
        """The cache key: a hex digest of everything the file depends on."""
        return digest({"mesh": self.mesh["sha256"], "version": self.version,
                       "revision": EXPORT_REVISION, "fmt": self.fmt.value, "faces": self.faces,
                       "surface": self.surface.value,
                       "composition": self.composition["sha256"] if self.composition else None,
                       "site": self.site.model_dump() if self.site else None, "body": self.body,
                       "frame": self.frame, "kernels": [sha for _, sha in self.kernels],
                       "time_span": self.time_span, "spacecraft": self.spacecraft_id})


def plan_export(session: Session, *, data_dir: Path, version: ModelVersion, fmt: ExportFormat,
                surface: ExportSurface = ExportSurface.MODEL, faces: int | None = None,
                site: Site | None = None, body: str | None = None, frame: str | None = None) -> ExportPlan:
    """Read from the catalog what exporting `version` in format `fmt` needs (make_export makes
    it, without the catalog: end the session's transaction in between).

    surface: the whole model, or the global model beneath the sites (the whole model for a
    version without sites). faces: decimate to about this many faces first (none, or at least
    the surface's count: full resolution); ICQ takes q from it (icq_size). site: needed by, and only by, the site
    product. body (NAIF name or ID) and frame (body-fixed frame name) override what the
    catalog's images give, for DSK and site products. Raises ExportError when the export cannot
    be made.
    """
    if (fmt is ExportFormat.SITE) != (site is not None):
        raise ExportError("a site product needs a site, and only a site product takes one")
    if fmt is ExportFormat.SITE and surface is ExportSurface.GLOBAL:
        raise ExportError("a site product is sampled from the whole model (the finest level there), "
                          "not from the global one")
    composition = version.artifacts.get("composition")
    below = surface is ExportSurface.GLOBAL and composition is not None
    total = None if below else int(version.statistics.get("faces", 0)) or None
    if faces is not None and faces < 4:
        raise ExportError(f"faces must be at least 4, got {faces}")
    if faces is not None and total is not None and faces >= total:
        faces = None
    name = (f"pwm-v{version.version:04d}" + ("-global" if below else "") + (f"-f{faces}" if faces else "")
            + SUFFIXES[fmt])
    plan = ExportPlan(data_dir=data_dir, version=version.version, kind=str(version.kind),
                      created_at=version.created_at, mesh=dict(version.artifacts["ply"]),
                      fmt=fmt, faces=faces, filename=name, site=site,
                      surface=ExportSurface.GLOBAL if below else ExportSurface.MODEL,
                      composition=dict(composition) if composition is not None else None)
    if fmt in (ExportFormat.PLY, ExportFormat.OBJ) and faces is None and not below:
        return dataclasses.replace(plan, own=dict(version.artifacts[fmt.value]))
    if fmt not in (ExportFormat.DSK, ExportFormat.SITE):
        return plan
    if frame is None:
        frame = _most_common(session, select(ImageGeometry.body_frame))
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


def make_export(plan: ExportPlan, *, cache_bytes: int) -> ExportFile:
    """The file of an export plan, made and kept on first request (cache_bytes: how many bytes
    of derived files the data directory keeps; service.artifacts.cached_artifact).

    Raises ExportError when the export cannot be made, service.artifacts.ArtifactError when the
    version's files are damaged, service.artifacts.CacheBusy when too many files are being made.
    """
    fmt, faces = plan.fmt, plan.faces
    if plan.own is not None:
        return ExportFile(artifact_path(plan.data_dir, plan.own), plan.filename,
                          MEDIA_TYPES[fmt], plan.own["sha256"])

    def make(path: Path) -> None:
        composition = (read_composition(artifact_path(plan.data_dir, plan.composition, verify=True))
                       if plan.composition is not None else None)
        if plan.surface is ExportSurface.GLOBAL and composition is not None:
            mesh = composition.below
        else:
            mesh = artifact_mesh(plan.data_dir, plan.mesh)
        # a DSK of the whole model at full resolution: a segment per site region, one for the rest
        parts = composition.face_region() if plan.surface is ExportSurface.MODEL and composition else None
        if faces is not None and faces < len(mesh.faces):
            mesh, parts = decimate(mesh, faces), None
        if fmt is ExportFormat.ICQ:
            _write_icq(path, mesh, icq_size(faces or len(mesh.faces)))
        elif fmt is ExportFormat.DSK:
            _write_dsk(path, mesh, plan=plan, parts=parts)
        elif fmt is ExportFormat.SITE:
            _write_site(path, mesh, plan=plan)
        else:
            (write_ply if fmt is ExportFormat.PLY else write_obj)(path, mesh)

    record = cached_artifact(plan.data_dir, plan.key(), suffix=SUFFIXES[fmt], make=make,
                             cache_bytes=cache_bytes)
    return ExportFile(artifact_path(plan.data_dir, record), plan.filename, MEDIA_TYPES[fmt],
                      record["sha256"])


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


def _write_dsk(path: Path, mesh: Mesh, *, plan: ExportPlan, parts: np.ndarray | None) -> None:
    target = _target(plan)
    segments = 1 if parts is None else len(np.unique(parts))
    what = ("the global model beneath the sites" if plan.surface is ExportSurface.GLOBAL
            else f"{segments} segments: the body and each site region, parting the surface without overlap"
            if segments > 1 else "one segment")
    comment = (f"pwm shape model version {plan.version} ({plan.kind}), made "
               f"{plan.created_at:%Y-%m-%dT%H:%M:%SZ}; plate model in km in {target.frame}; "
               f"{len(mesh.vertices)} vertices, {len(mesh.faces)} plates; {what}.")
    with kernel_pool(_kernel_paths(plan)):
        write_dsk(path, mesh, body=target.body_id, frame=target.frame, comment=comment, parts=parts)


def _write_site(path: Path, mesh: Mesh, *, plan: ExportPlan) -> None:
    assert plan.site is not None and plan.time_span is not None  # plan_export sets them
    target = _target(plan)
    grid = site_grid(mesh, plan.site)
    if np.isnan(grid.height_km).all():
        raise ExportError("the site grid meets no surface")
    start, stop = plan.time_span
    host = _spacecraft(plan.spacecraft_id)
    name = f"pwm_site_v{plan.version:04d}_{digest(plan.site.model_dump())[:10]}"
    scratch = path.parent / "site"
    scratch.mkdir()
    files = write_site_product(
        scratch, name=name, frame=grid.frame, x_km=grid.x_km, y_km=grid.y_km,
        height_km=grid.height_km, albedo=grid.albedo,
        lid=f"urn:nasa:pds:pwm:data_site:{name}", version="1.0",
        model_version=str(plan.version), body_frame=target.frame,
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
