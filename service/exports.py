"""Exports of a model version: OBJ, PLY (per-vertex albedo), Gaskell ICQ, SPICE DSK type 2, and
a local terrain product of a site (PDS4 heights and albedo in the site frame, with a PNG preview).

Every export may be decimated to a requested face count first. An export is made once and kept
in the data directory's content-addressed store (service.versions.store_artifact); an index
file `<data_dir>/exports/<key>.json` names the artifact made for a key, which hashes the
version's mesh checksum with the format and parameters. The mesh formats at full resolution are
the version's own artifacts.

spiceypy's kernel pool and fast-simplification keep process-global state: their calls are
serialised by one lock, so that the API's worker threads can share them.
"""

from __future__ import annotations

import enum
import hashlib
import json
import math
import os
import tempfile
import threading
import zipfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
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
from pwm.frames import LocalFrame, latlon_to_unit, local_frame
from pwm.io.dsk import write_dsk
from pwm.io.icq import mesh_to_icq, write_icq
from pwm.io.meshio import write_obj, write_ply
from pwm.io.site_product import write_site_product
from pwm.io.spice_kernels import kernel_pool
from pwm.mesh import Mesh
from pwm.raytrace import RayTracer
from service.kernels import accepted_kernels
from service.models import (
    Image,
    ImageGeometry,
    ImageStatus,
    Instrument,
    KernelKind,
    ModelVersion,
    model_version_downlinks,
)
from service.versions import ArtifactError, artifact_path, store_artifact, version_mesh

EXPORTS_DIRNAME = "exports"
# Bump when an export's content changes for the same inputs, so that old cache entries are
# not served for new requests.
EXPORT_REVISION = 1
# The site grid has at most (2 * MAX_SITE_HALF_NODES + 1)^2 nodes.
MAX_SITE_HALF_NODES = 500
_PROCESS_GLOBAL = threading.Lock()


class ExportFormat(enum.StrEnum):
    OBJ = "obj"
    PLY = "ply"
    ICQ = "icq"
    DSK = "dsk"
    SITE = "site"


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


@dataclass(frozen=True)
class SiteGrid:
    """Heights (km, along the frame's z) and albedo on the regular grid x_km, y_km of the site
    frame; arrays (ny, nx), NaN where the surface is not found or has no albedo."""

    frame: LocalFrame
    x_km: np.ndarray
    y_km: np.ndarray
    height_km: np.ndarray
    albedo: np.ndarray


def icq_size(faces: int) -> int:
    """The ICQ grid size q whose mesh (12 q^2 triangles) comes nearest `faces`."""
    return max(1, round(math.sqrt(faces / 12)))


def export_version(session: Session, *, data_dir: Path, version: ModelVersion,
                   fmt: ExportFormat, faces: int | None = None, site: Site | None = None,
                   body: str | None = None, frame: str | None = None) -> ExportFile:
    """The file of `version` in format `fmt`, made and stored on first request.

    faces: decimate to about this many faces first (none, or at least the version's count:
    full resolution); ICQ takes q from it (icq_size). site: needed by, and only by, the site
    product. body (NAIF name or ID) and frame (body-fixed frame name) override what the
    catalog's images give, for DSK and site products. Raises ExportError when the export cannot
    be made, ArtifactError when the version's files are damaged.
    """
    if (fmt is ExportFormat.SITE) != (site is not None):
        raise ExportError("a site product needs a site, and only a site product takes one")
    total = int(version.statistics.get("faces", 0)) or None
    if faces is not None and faces < 4:
        raise ExportError(f"faces must be at least 4, got {faces}")
    if faces is not None and total is not None and faces >= total:
        faces = None
    name = f"pwm-v{version.version:04d}" + (f"-f{faces}" if faces else "") + SUFFIXES[fmt]
    if fmt in (ExportFormat.PLY, ExportFormat.OBJ) and faces is None:
        record = version.artifacts[fmt.value]
        return ExportFile(artifact_path(data_dir, record), name, MEDIA_TYPES[fmt],
                          record["sha256"])
    target = (resolve_target(session, body=body, frame=frame)
              if fmt in (ExportFormat.DSK, ExportFormat.SITE) else None)
    key = _cache_key(version, fmt=fmt, faces=faces, site=site, target=target)

    def make(path: Path) -> None:
        mesh = version_mesh(data_dir, version)
        if faces is not None and faces < len(mesh.faces):
            with _PROCESS_GLOBAL:
                mesh = decimate(mesh, faces)
        if fmt is ExportFormat.ICQ:
            _write_icq(path, mesh, icq_size(faces or len(mesh.faces)))
        elif fmt is ExportFormat.DSK:
            assert target is not None  # resolved above for DSK and site products
            _write_dsk(session, path, mesh, version=version, target=target)
        elif fmt is ExportFormat.SITE:
            assert site is not None and target is not None  # checked and resolved above
            _write_site(session, path, mesh, version=version, site=site, target=target)
        else:
            (write_ply if fmt is ExportFormat.PLY else write_obj)(path, mesh)

    record = cached_artifact(data_dir, key, suffix=SUFFIXES[fmt], make=make)
    return ExportFile(artifact_path(data_dir, record), name, MEDIA_TYPES[fmt], record["sha256"])


def cached_artifact(data_dir: Path, key: str, *, suffix: str,
                    make: Callable[[Path], None]) -> dict[str, Any]:
    """The artifact record stored for `key` (a hex digest), made by `make(path)` (which writes
    the file `path`) and stored the first time, or again when its file went missing."""
    index = data_dir / EXPORTS_DIRNAME / f"{key}.json"
    if index.is_file():
        record = json.loads(index.read_text())
        try:
            artifact_path(data_dir, record)
            return record
        except ArtifactError:
            pass
    with _workspace(data_dir) as scratch:
        path = scratch / f"export{suffix}"
        make(path)
        record = store_artifact(data_dir, path)
        staged = scratch / "index.json"
        staged.write_text(json.dumps(record))
        os.replace(staged, index)  # atomic: a concurrent reader sees the old index or the new
    return record


def resolve_target(session: Session, *, body: str | None = None,
                   frame: str | None = None) -> Target:
    """The body-fixed frame of the catalogued image geometry (the most frequent) and the body at
    its centre, each overridable (body: NAIF name or ID); known to SPICE from its built-in names
    and the catalog's accepted frame and constants kernels. Raises ExportError when unknown."""
    if frame is None:
        frame = _most_common(session, select(ImageGeometry.body_frame))
    if frame is None:
        raise ExportError("the catalog has no image geometry to take the body-fixed frame "
                          "from: give the frame")
    with _spice(session), sp.no_found_check():
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


def resample_site(mesh: Mesh, site: Site) -> SiteGrid:
    """Resample `mesh` (km, body-fixed) on a square grid about a site.

    The site frame's origin is the outermost surface point along the site's radial line; its
    z axis the area-weighted mean normal of the faces within radius_km of it (x east, y north,
    pwm.frames.local_frame); the grid spacing the mean edge of those faces, at most
    2 MAX_SITE_HALF_NODES + 1 nodes a side, spanning +-radius_km. Each node is where a ray down
    the frame's z axis first meets the surface. Raises ExportError if the radial line misses.
    """
    tracer = RayTracer(mesh)
    reach = 2.0 * float(np.linalg.norm(mesh.vertices, axis=1).max())
    direction = latlon_to_unit(site.lat_deg, site.lon_deg)
    down = tracer.intersect((reach * direction)[None], -direction[None])
    if not down.hit[0]:
        raise ExportError(f"no surface along latitude {site.lat_deg}, longitude {site.lon_deg}")
    origin = tracer.hit_points((reach * direction)[None], -direction[None], down)[0]
    corners = mesh.vertices[mesh.faces]
    near = np.linalg.norm(corners.mean(axis=1) - origin, axis=1) <= site.radius_km
    near[down.face[0]] = True
    normals = np.cross(corners[near, 1] - corners[near, 0], corners[near, 2] - corners[near, 0])
    frame = local_frame(origin, normals.sum(axis=0))
    edge = float(np.linalg.norm(corners[near] - np.roll(corners[near], 1, axis=1), axis=2).mean())
    half = min(MAX_SITE_HALF_NODES, max(1, math.ceil(site.radius_km / edge)))
    axis = np.linspace(-site.radius_km, site.radius_km, 2 * half + 1)
    # Rays start above everything within the site's horizontal reach, so the first hit is the top.
    local = frame.to_local(mesh.vertices)
    beside = np.hypot(local[:, 0], local[:, 1]) <= 1.5 * site.radius_km
    top = float(local[beside, 2].max()) + edge
    xx, yy = np.meshgrid(axis, axis)
    starts = frame.to_body(np.stack([xx, yy, np.full_like(xx, top)], axis=-1).reshape(-1, 3))
    downward = np.broadcast_to(-frame.normal, starts.shape)
    hits = tracer.intersect(starts, downward)
    height = frame.to_local(tracer.hit_points(starts, downward, hits))[:, 2]
    albedo = (np.where(hits.hit, tracer.interpolate(mesh.albedo, hits), np.nan)
              if mesh.albedo is not None else np.full(len(starts), np.nan))
    return SiteGrid(frame=frame, x_km=axis, y_km=axis, height_km=height.reshape(xx.shape),
                    albedo=albedo.reshape(xx.shape))


def _write_icq(path: Path, mesh: Mesh, q: int) -> None:
    try:
        grid = mesh_to_icq(mesh, q)
    except ValueError as exc:  # a mesh not star-shaped about the body centre
        raise ExportError(f"no ICQ model of this version: {exc}") from exc
    write_icq(path, grid)


def _write_dsk(session: Session, path: Path, mesh: Mesh, *, version: ModelVersion,
               target: Target) -> None:
    comment = (f"pwm shape model version {version.version} ({version.kind}), made "
               f"{version.created_at:%Y-%m-%dT%H:%M:%SZ}; plate model in km in {target.frame}; "
               f"{len(mesh.vertices)} vertices, {len(mesh.faces)} plates.")
    with _spice(session):
        write_dsk(path, mesh, body=target.body_id, frame=target.frame, comment=comment)


def _write_site(session: Session, path: Path, mesh: Mesh, *, version: ModelVersion, site: Site,
                target: Target) -> None:
    grid = resample_site(mesh, site)
    if np.isnan(grid.height_km).all():
        raise ExportError("the site grid meets no surface")
    start, stop = _time_span(session, version)
    host = _spacecraft(session)
    name = f"pwm_site_v{version.version:04d}_{digest(site.model_dump())[:10]}"
    scratch = path.parent / "site"
    scratch.mkdir()
    files = write_site_product(
        scratch, name=name, frame=grid.frame, x_km=grid.x_km, y_km=grid.y_km,
        height_km=grid.height_km, albedo=grid.albedo,
        lid=f"urn:nasa:pds:pwm:data_site:{name}", version="1.0",
        model_version=str(version.version), body_frame=target.frame,
        target_name=target.name, mission=host, host_name=host,
        start_utc=start.isoformat(), stop_utc=stop.isoformat())
    # Stored, not deflated: binary doubles compress little.
    with zipfile.ZipFile(path, "x", compression=zipfile.ZIP_STORED) as archive:
        for file in files:
            archive.write(file, arcname=file.name)


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


def _spacecraft(session: Session) -> str:
    """The name of the spacecraft that took most of the catalogued images, or 'unknown'."""
    code = _most_common(session, select(Instrument.spacecraft_id).join(
        Image, Image.instrument_id == Instrument.id))
    if code is None:
        return "unknown"
    with _PROCESS_GLOBAL, sp.no_found_check():
        name, found = sp.bodc2n(code)
    return name if found else str(code)


def _most_common(session: Session, query: Any) -> Any:
    column = query.subquery().c[0]
    row = session.execute(select(column, func.count()).group_by(column)
                          .order_by(func.count().desc(), column).limit(1)).first()
    return None if row is None else row[0]


@contextmanager
def _spice(session: Session) -> Iterator[None]:
    """SPICE with the catalog's accepted constants and frame kernels loaded, one thread at a
    time (the pool is per process)."""
    paths = [Path(k.path) for k in accepted_kernels(session)
             if k.kind in (KernelKind.PCK, KernelKind.FK) and Path(k.path).is_file()]
    with _PROCESS_GLOBAL, kernel_pool(paths):
        yield


@contextmanager
def _workspace(data_dir: Path) -> Iterator[Path]:
    """A scratch directory inside the data directory (one filesystem: stored files are renamed,
    not copied), removed afterwards."""
    root = data_dir / EXPORTS_DIRNAME / "tmp"
    root.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=root) as scratch:
        yield Path(scratch)


def _cache_key(version: ModelVersion, **parameters: Any) -> str:
    values = {name: (value.model_dump() if isinstance(value, BaseModel) else
                     value.__dict__ if isinstance(value, Target) else value)
              for name, value in parameters.items()}
    return digest({"mesh": version.artifacts["ply"]["sha256"], "revision": EXPORT_REVISION,
                    **values})


def digest(value: Any) -> str:
    """A hex SHA-256 of `value` as canonical JSON: a cache key of parameters."""
    return hashlib.sha256(json.dumps(value, sort_keys=True, default=str).encode()).hexdigest()
