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
in `<data_dir>/exports/`: the file `<key><suffix>` and its record `<key>.json`, where the key
hashes the version's mesh checksum with the format and the parameters as asked (so that a
request already served needs neither SPICE nor a lock). The mesh formats at full resolution are
the version's own artifacts. What is kept is bounded: once the kept files pass the configured
bytes, the least recently served ones are removed (they are made again when asked for).

An export is planned from the catalog first (plan_export) and made without it (make_export), so
that no database connection is held while a request waits for its turn or while the file is
made. spiceypy's kernel pool and fast-simplification keep process-global state: making is
serialised by one lock, and only MAX_QUEUED_EXPORTS requests of a process may wait for it or
hold it; the others are refused at once (ExportBusy), so that exports never take all the API's
worker threads.
"""

from __future__ import annotations

import dataclasses
import enum
import hashlib
import json
import math
import os
import tempfile
import threading
import zipfile
from collections.abc import Callable, Iterable, Iterator
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
from pwm.io.fusion_state import read_composition
from pwm.io.icq import mesh_to_icq, write_icq
from pwm.io.meshio import write_obj, write_ply
from pwm.io.pds4 import file_sha256
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
from service.versions import ArtifactError, artifact_mesh, artifact_path

EXPORTS_DIRNAME = "exports"
# Bump when an export's content changes for the same inputs, so that old cache entries are
# not served for new requests.
EXPORT_REVISION = 4
# The site grid has at most (2 * MAX_SITE_HALF_NODES + 1)^2 nodes.
MAX_SITE_HALF_NODES = 500
# Requests of one process that may wait for the making lock or hold it; one more is refused.
MAX_QUEUED_EXPORTS = 4
# The longest a queued request waits for the making lock (s) before it is refused.
EXPORT_WAIT_S = 60.0
# What a refused request is told to wait before it asks again (s).
RETRY_AFTER_S = 5
_PROCESS_GLOBAL = threading.Lock()
_QUEUE = threading.BoundedSemaphore(MAX_QUEUED_EXPORTS)


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


class ExportBusy(Exception):
    """Too many exports are being made: ask again after `retry_after_s` (s)."""

    def __init__(self, retry_after_s: int = RETRY_AFTER_S) -> None:
        super().__init__(f"too many exports are being made; try again in {retry_after_s} s")
        self.retry_after_s = retry_after_s


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
    of exports the data directory keeps; see cached_artifact).

    Raises ExportError when the export cannot be made, ArtifactError when the version's files
    are damaged, ExportBusy when too many exports are being made.
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


def cached_artifact(data_dir: Path, key: str, *, suffix: str, make: Callable[[Path], None],
                    cache_bytes: int | None) -> dict[str, Any]:
    """The record ({"path", "sha256", "bytes"}) of the file kept for `key` (a hex digest), made
    by `make(path)` (which writes the file `path`) the first time, or again when it went missing.

    Making holds the process's making lock (so `make` may use SPICE and fast-simplification);
    of requests that must make their file, MAX_QUEUED_EXPORTS wait for it at most EXPORT_WAIT_S,
    and the others are refused with ExportBusy. Once made, the least recently served files are
    removed until the kept ones total at most `cache_bytes` (the new one always stays); None
    (a process without the service's settings, such as a publication) leaves that to the next
    request that makes a file.
    """
    record = _kept(data_dir, key)
    if record is not None:
        return record
    if not _QUEUE.acquire(blocking=False):
        raise ExportBusy()
    try:
        if not _PROCESS_GLOBAL.acquire(timeout=EXPORT_WAIT_S):
            raise ExportBusy()
        try:
            # made meanwhile by the request this one waited for
            record = _kept(data_dir, key)
            if record is None:
                record = _make_and_keep(data_dir, key, suffix=suffix, make=make)
                if cache_bytes is not None:
                    _evict(data_dir, cache_bytes=cache_bytes, keep=key)
        finally:
            _PROCESS_GLOBAL.release()
    finally:
        _QUEUE.release()
    return record


def _kept(data_dir: Path, key: str) -> dict[str, Any] | None:
    """The record kept for `key` if its file is there, marked as just served."""
    index = data_dir / EXPORTS_DIRNAME / f"{key}.json"
    try:
        record = json.loads(index.read_text())
        artifact_path(data_dir, record)
        os.utime(index)  # the eviction order: least recently served first
    except (OSError, ValueError, KeyError, TypeError, ArtifactError):
        return None  # missing, being replaced, or damaged: made again
    return record


def _make_and_keep(data_dir: Path, key: str, *, suffix: str,
                   make: Callable[[Path], None]) -> dict[str, Any]:
    directory = data_dir / EXPORTS_DIRNAME
    with _workspace(data_dir) as scratch:
        path = scratch / f"export{suffix}"
        make(path)
        relative = Path(EXPORTS_DIRNAME) / f"{key}{suffix}"
        record = {"path": relative.as_posix(), "sha256": file_sha256(path),
                  "bytes": path.stat().st_size}
        os.replace(path, data_dir / relative)  # same filesystem: atomic
        staged = scratch / "index.json"
        staged.write_text(json.dumps(record))
        os.replace(staged, directory / f"{key}.json")  # a concurrent reader sees old or new
    return record


def _evict(data_dir: Path, *, cache_bytes: int, keep: str) -> None:
    """Remove the least recently served kept files, other than `keep`'s, until the kept files
    total at most cache_bytes. Only files inside the exports folder are removed."""
    directory = data_dir / EXPORTS_DIRNAME
    entries = []
    for index in directory.glob("*.json"):
        try:
            record = json.loads(index.read_text())
            entries.append((index.stat().st_mtime, index, record, int(record["bytes"])))
        except (OSError, ValueError, KeyError, TypeError):
            continue  # removed meanwhile by another process, or not a record of ours
    total = sum(size for *_, size in entries)
    for _, index, record, size in sorted(entries, key=lambda entry: entry[0]):
        if total <= cache_bytes:
            break
        if index.stem == keep:
            continue
        index.unlink(missing_ok=True)
        file = data_dir / str(record.get("path", ""))
        if file.parent.resolve() == directory.resolve():
            file.unlink(missing_ok=True)
        total -= size


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
    return sample_grid(mesh, frame, axis, axis)


def sample_grid(mesh: Mesh, frame: LocalFrame, x_km: np.ndarray, y_km: np.ndarray) -> SiteGrid:
    """The heights and albedo of `mesh` at the nodes x_km, y_km of `frame`: where a ray down the
    frame's z axis first meets the surface (NaN where it misses)."""
    tracer = RayTracer(mesh)
    # Rays start above everything within the grid's horizontal reach, so the first hit is the top.
    local = frame.to_local(mesh.vertices)
    reach = 1.5 * max(np.abs(x_km).max(), np.abs(y_km).max())
    beside = np.hypot(local[:, 0], local[:, 1]) <= reach
    if not beside.any():
        raise ExportError("the grid lies beside the surface")
    top = float(local[beside, 2].max()) + 1e-3 * reach
    xx, yy = np.meshgrid(x_km, y_km)
    starts = frame.to_body(np.stack([xx, yy, np.full_like(xx, top)], axis=-1).reshape(-1, 3))
    downward = np.broadcast_to(-frame.normal, starts.shape)
    hits = tracer.intersect(starts, downward)
    height = frame.to_local(tracer.hit_points(starts, downward, hits))[:, 2]
    albedo = (np.where(hits.hit, tracer.interpolate(mesh.albedo, hits), np.nan)
              if mesh.albedo is not None else np.full(len(starts), np.nan))
    return SiteGrid(frame=frame, x_km=np.asarray(x_km), y_km=np.asarray(y_km),
                    height_km=height.reshape(xx.shape), albedo=albedo.reshape(xx.shape))


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
    grid = resample_site(mesh, plan.site)
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


@contextmanager
def _workspace(data_dir: Path) -> Iterator[Path]:
    """A scratch directory inside the data directory (one filesystem: stored files are renamed,
    not copied), removed afterwards."""
    root = data_dir / EXPORTS_DIRNAME / "tmp"
    root.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=root) as scratch:
        yield Path(scratch)


def digest(value: Any) -> str:
    """A hex SHA-256 of `value` as canonical JSON: a cache key of parameters."""
    return hashlib.sha256(json.dumps(value, sort_keys=True, default=str).encode()).hexdigest()
