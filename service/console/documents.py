"""What the browser console (service/console/static, served by service/api/routers/console.py)
reads beyond the API's JSON: a version's mesh for WebGL, a site's maps, and the coverage of
every maplet at once. Each map carries what a reader needs to read it: the colour map and
its range (the 3D view), the direction of north in the site frame and where the version holds
refined (maplet) data over a site, and each maplet's true outline on the coverage map.

Big arrays travel as one binary document (`pack`): the 4 bytes b"PWMC", a little-endian uint32
header length, a UTF-8 JSON header padded with spaces to a multiple of 4 bytes, then the arrays,
little-endian and C-ordered, at the offsets (from the end of the header) the header lists as
{"name", "dtype", "shape", "offset"}. JavaScript reads them as typed arrays without a copy.
The mesh and site documents are made once and kept in the artifact store's cache
(service.artifacts.cached_artifact, with the exports and diff maps: same bound on bytes kept,
same making lock), keyed by the version's mesh; a version's mesh document is made after its
publication (`make_mesh_document`), so that the console's first 3D view of it is read at once.
"""

from __future__ import annotations

import json
import logging
import math
import struct
from collections.abc import Callable
from dataclasses import asdict, dataclass
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib import colormaps
from pydantic import BaseModel, ConfigDict
from scipy.spatial import cKDTree
from sqlalchemy import case, distinct, func, select, true
from sqlalchemy.orm import Session, sessionmaker

from pwm.compare import height_change
from pwm.decimate import decimate
from pwm.frames import LocalFrame, stored_frame, unit_to_latlon
from pwm.mesh import Mesh
from pwm.site import BASELINE_M, HazardThresholds, hazard, relief_m, roughness_m, slope_deg
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
from service.exports import ExportError, Site, site_grid
from service.queries import list_maplets
from service.rows import (
    Coverage,
    CoverageRole,
    Maplet,
    MapletRevision,
    ModelVersion,
    model_version_maplet_revisions,
)
from service.versions import get_version

log = logging.getLogger(__name__)

MAGIC = b"PWMC"
# What a browser draws smoothly: meshes above this many faces are decimated for the 3D view
# (at 300k the document is about 8 MB; bench/console.py times its first draw).
MESH_FACES = 300_000
# Bump when a document's content changes for the same inputs.
REVISION = 6
FIELD_UNITS = {"albedo": "", "height": "m", "slope": "deg", "change": "m", "sigma": "m"}
UNKNOWN_GREY = 115
# Farthest (km) a version's surface may have moved from its parent's and still be compared.
CHANGE_REACH_KM = 0.01
# Colour-map samples the browser draws its colour bars from, so that a bar shows the very map
# the server coloured with.
COLOUR_BAR_STOPS = 9
# Below this length the body's spin axis projects to no direction in a site's map (a pole).
NORTH_MIN = 1e-6


def pack(header: dict[str, Any], arrays: list[tuple[str, np.ndarray]]) -> bytes:
    """The binary document of `header` (JSON-able; "arrays" is added) and the named arrays
    (float32, uint32, uint8 or int8)."""
    listed, offset, blobs = [], 0, []
    for name, array in arrays:
        data = np.ascontiguousarray(array)
        if data.dtype not in (np.float32, np.uint32, np.uint8, np.int8):
            raise TypeError(f"array {name} is {data.dtype}; float32, uint32, uint8 or int8 "
                            f"travel")
        listed.append({"name": name, "dtype": data.dtype.name, "shape": list(data.shape),
                       "offset": offset})
        blob = data.astype(data.dtype.newbyteorder("<"), copy=False).tobytes()
        blobs.append(blob + b"\0" * (-len(blob) % 4))  # each array starts 4-byte aligned
        offset += len(blobs[-1])
    text = json.dumps({**header, "arrays": listed}, allow_nan=False).encode()
    text += b" " * (-len(text) % 4)
    return MAGIC + struct.pack("<I", len(text)) + text + b"".join(blobs)


def unpack(document: bytes) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """The header and arrays of a `pack`ed document."""
    if document[:4] != MAGIC:
        raise ValueError("not a console document: no PWMC magic")
    (length,) = struct.unpack("<I", document[4:8])
    header = json.loads(document[8:8 + length])
    start = 8 + length
    arrays = {}
    for entry in header["arrays"]:
        dtype = np.dtype(entry["dtype"]).newbyteorder("<")
        count = int(np.prod(entry["shape"]))
        arrays[entry["name"]] = np.frombuffer(document, dtype=dtype, count=count,
                                              offset=start + entry["offset"]).reshape(entry["shape"])
    return header, arrays


@dataclass(frozen=True)
class MeshRequest:
    """A version's mesh record (`ModelVersion.mesh_artifact`: of a mesh stored in tiles, their
    index) and its parent's, for the change colour."""

    version: int
    mesh: dict[str, Any]
    parent: int | None
    parent_mesh: dict[str, Any] | None

    @classmethod
    def of(cls, version: ModelVersion) -> MeshRequest:
        parent = version.parent
        return cls(version=version.version, mesh=version.mesh_artifact,
                   parent=parent.version if parent else None,
                   parent_mesh=parent.mesh_artifact if parent else None)


def mesh_document(data_dir: Path, request: MeshRequest, *, cache_bytes: int | None,
                  faces: int = MESH_FACES) -> Path:
    """The file of the 3D view's document of a version, made once: the mesh decimated to at
    most `faces` faces, vertices (float32, km, body-fixed), faces (uint32), unit normals
    (int8, x 127), and per vertex an RGB colour (uint8) of each of albedo, height (m above the
    mean radius), slope (deg between the vertex normal and the radial direction), change (m
    along the normal since the parent version, pwm.compare; unknown without a parent) and the
    1-sigma height (m, pwm.uncertainty; unknown where the version has none), with
    the range each colour map spans in the header. The browser does no per-vertex work.
    Of a version stored in tiles, the header lists the tiles (key, faces, bounding box) and
    "face_tile" (uint32) gives each face's tile (of a decimated mesh, that of the full face whose
    centre is nearest its centre), so that the view can draw a tile at full resolution in its place (`tile_document`).
    cache_bytes: as for service.artifacts.cached_artifact."""
    key = digest({"console": "mesh", "revision": REVISION, "mesh": request.mesh["sha256"],
                  "parent": request.parent_mesh["sha256"] if request.parent_mesh else None,
                  "faces": faces})

    def make(path: Path) -> None:
        tiled = holds_tiles(request.mesh)
        if tiled:
            index, full, labels = tiled_mesh(data_dir, request.mesh)
        else:
            full = artifact_mesh(data_dir, request.mesh)
        mesh = decimate(full, faces, keep_closed=False) if len(full.faces) > faces else full
        header, arrays = _mesh_fields(request, mesh, full=full, change=_change(data_dir, request, full))
        if tiled:
            if mesh is not full:  # each decimated face in the tile of the full face nearest it
                nearest = cKDTree(full.vertices[full.faces].mean(axis=1)).query(
                    mesh.vertices[mesh.faces].mean(axis=1))[1]
                labels = labels[nearest]
            header["tiles"] = [{"key": entry.key, "faces": entry.faces, "box_km": list(entry.box_km)}
                               for entry in index.tiles]
            arrays.append(("face_tile", labels.astype(np.uint32)))
        path.write_bytes(pack(header, arrays))

    record = cached_artifact(data_dir, key, suffix=".pwmc", make=make, cache_bytes=cache_bytes)
    return artifact_path(data_dir, record)


def tile_document(data_dir: Path, request: MeshRequest, tile: str, *, cache_bytes: int | None) -> Path:
    """The file of the 3D view's document of one tile of a version stored in tiles, at full
    resolution, made once: laid out as `mesh_document`'s, coloured on the whole version's
    colour ranges and mean radius (its document's header), so that it takes the decimated
    surface's place seamlessly; the change since the parent is not coloured (unknown: it would
    read the parent's whole mesh). KeyError for a tile the version does not have; ValueError
    for a version stored whole."""
    if not holds_tiles(request.mesh):
        raise ValueError(f"version {request.version} is stored whole, not in tiles")
    entry = tile_index(data_dir, request.mesh).entry(tile)
    key = digest({"console": "tile", "revision": REVISION, "mesh": request.mesh["sha256"], "tile": tile,
                  "parent": request.parent_mesh["sha256"] if request.parent_mesh else None})

    def make(path: Path) -> None:
        whole, _ = unpack(mesh_document(data_dir, request, cache_bytes=cache_bytes).read_bytes())
        mesh = artifact_tile(data_dir, entry.file).mesh
        header, arrays = _mesh_fields(request, mesh, full=mesh, change=None, whole=whole)
        path.write_bytes(pack({**header, "tile": tile}, arrays))

    record = cached_artifact(data_dir, key, suffix=".pwmc", make=make, cache_bytes=cache_bytes)
    return artifact_path(data_dir, record)


def make_mesh_document(sessions: sessionmaker[Session], *, data_dir: Path, version: int) -> None:
    """Make the 3D view's document of a version now, once it is published: so that the console's
    first view of it is read, not decimated while the user waits (a minute for two million
    faces). A failure here loses nothing (the first request makes it)."""
    with sessions() as session:
        request = MeshRequest.of(get_version(session, version))
    try:
        mesh_document(data_dir, request, cache_bytes=None)
    except Exception:
        log.exception("the console's mesh of version %d was not made now", version)


def _mesh_fields(request: MeshRequest, mesh: Mesh, *, full: Mesh, change: np.ndarray | None,
                 whole: dict[str, Any] | None = None) -> tuple[dict[str, Any], list[tuple[str, np.ndarray]]]:
    """The header and arrays of the document of `mesh` (`full` decimated, or `full` itself;
    `change`: per vertex of `full`, or None), coloured on their own ranges, or on those of the
    header `whole` of the document of the whole version that `mesh` is a tile of."""
    radius = np.linalg.norm(mesh.vertices, axis=1)
    radial = mesh.vertices / radius[:, None]
    normals = mesh.vertex_normals()
    slope = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", normals, radial), -1.0, 1.0)))
    carried = _carrier(mesh, full=full)
    mean_radius_km = float(radius.mean()) if whole is None else float(whole["mean_radius_km"])
    fields = {"albedo": (mesh.albedo if mesh.albedo is not None
                         else np.full(len(mesh.vertices), np.nan)),
              "height": (radius - mean_radius_km) * 1e3, "slope": slope,
              "change": carried(change),
              "sigma": carried(None if full.sigma is None else full.sigma * 1e3)}
    colours = {name: _colour(values, signed=name == "change",
                             span=None if whole is None else whole["colours"][name])
               for name, values in fields.items()}
    header = {"kind": "mesh", "version": request.version, "parent": request.parent,
              "faces_full": len(full.faces), "faces": len(mesh.faces),
              "vertices": len(mesh.vertices), "mean_radius_km": mean_radius_km,
              "colours": {name: {"unit": FIELD_UNITS[name], **scale}
                          for name, (_, scale) in colours.items()},
              "extent_km": _extent_km(mesh)}
    return header, [("vertices", mesh.vertices.astype(np.float32)),
                    ("faces", mesh.faces.astype(np.uint32)),
                    ("normals", np.round(normals * 127).astype(np.int8)),
                    *((f"colour_{name}", rgb) for name, (rgb, _) in colours.items())]


def _carrier(mesh: Mesh, *, full: Mesh) -> Callable[[np.ndarray | None], np.ndarray]:
    """Values per vertex of the full mesh (None: unknown) at the vertices of `mesh`, each from its
    nearest full one (decimation carries none of them); NaN where unknown. The nearest vertices
    are found once, and only when a field needs them."""
    @cache
    def nearest() -> np.ndarray:
        return cKDTree(full.vertices).query(mesh.vertices)[1]

    def carried(values: np.ndarray | None) -> np.ndarray:
        if values is None:
            return np.full(len(mesh.vertices), np.nan)
        return values if mesh is full else values[nearest()]

    return carried


def _change(data_dir: Path, request: MeshRequest, full: Mesh) -> np.ndarray | None:
    """Height change (m) since the parent at the vertices of the full mesh (decimation moves the
    surface, which is no change of the model); None without a parent."""
    if request.parent_mesh is None:
        return None
    return height_change(artifact_mesh(data_dir, request.parent_mesh), full,
                         max_distance_km=CHANGE_REACH_KM).change_m


def _extent_km(mesh: Mesh) -> dict[str, Any]:
    """The body's size for the 3D view's scale: its bounding box's sides (km, body-fixed x, y,
    z) and its largest distance from the centre."""
    sides = np.ptp(mesh.vertices, axis=0)
    return {"sides": [float(v) for v in sides],
            "max_radius": float(np.linalg.norm(mesh.vertices, axis=1).max())}


def _colour(values: np.ndarray, *, signed: bool,
            span: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
    """RGB (uint8, per vertex) of `values` on viridis from their 2nd to 98th percentile, or for
    a signed field on RdBu_r symmetric about 0 (grey where unknown), or over the range `span`
    ("min" and "max", another document's) where given; and that range with the
    colour map's name and COLOUR_BAR_STOPS samples of it (RGB 0-255, low to high)."""
    known = np.isfinite(values)
    rgb = np.full((len(values), 3), UNKNOWN_GREY, dtype=np.uint8)
    name = "RdBu_r" if signed else "viridis"
    cmap = colormaps[name]
    stops = [[int(c) for c in np.round(np.asarray(cmap(t))[:3] * 255)]
             for t in np.linspace(0.0, 1.0, COLOUR_BAR_STOPS)]
    if span is not None and span["min"] is not None:
        low, high = float(span["min"]), float(span["max"])
    elif not known.any() or span is not None:
        return rgb, {"min": None, "max": None, "colormap": name, "stops": stops}
    else:
        low, high = (float(v) for v in np.percentile(values[known], [2.0, 98.0]))
    if signed:
        high = max(abs(low), abs(high), 1e-9)
        low = -high
    width = high - low if high > low else 1.0
    rgb[known] = np.round(cmap(np.clip((values[known] - low) / width, 0.0, 1.0))[:, :3] * 255)
    return rgb, {"min": low, "max": high, "colormap": name, "stops": stops}


@dataclass(frozen=True)
class MapletSquare:
    """A refined maplet's square (side size_km about its frame's origin, in the frame's x-y
    plane; origin km, body-fixed; rotation body-fixed -> local, row-major) and its level
    (pwm.tiling.level_of: lower is finer) and node spacing (m)."""

    name: str
    origin_km: tuple[float, float, float]
    rotation: tuple[float, ...]
    size_km: float
    level: int
    gsd_m: float

    def frame(self) -> LocalFrame:
        return stored_frame(self.origin_km, self.rotation)


def site_maplets(session: Session, *, version: ModelVersion, site: Site) -> tuple[MapletSquare, ...]:
    """The maplets whose revisions `version` was fused from (its refined data) that reach the
    site's square (within its half-diagonal of the site's centre), by name."""
    near = {m.id for m in list_maplets(session, lat_deg=site.lat_deg, lon_deg=site.lon_deg,
                                       radius_km=site.radius_km * math.sqrt(2.0),
                                       limit=2**31 - 1)}
    if not near:
        return ()
    rows = session.scalars(
        select(Maplet).join(MapletRevision, MapletRevision.maplet_id == Maplet.id)
        .join(model_version_maplet_revisions,
              model_version_maplet_revisions.c.maplet_revision_id == MapletRevision.id)
        .where(model_version_maplet_revisions.c.model_version_id == version.id,
               Maplet.id.in_(near))
        .order_by(Maplet.name))
    return tuple(MapletSquare(name=m.name, origin_km=(m.origin_x_km, m.origin_y_km, m.origin_z_km),
                              rotation=tuple(float(v) for v in np.ravel(m.rotation)),
                              size_km=m.size_km, level=m.level, gsd_m=m.gsd_m) for m in rows)


@dataclass(frozen=True)
class SiteRequest:
    """A site of a version's mesh, the roughness baseline (m), the hazard thresholds and the
    version's refined maplets about the site (`site_maplets`)."""

    version: int
    mesh: dict[str, Any]
    site: Site
    baseline_m: float = BASELINE_M
    thresholds: HazardThresholds = HazardThresholds()
    maplets: tuple[MapletSquare, ...] = ()


def site_document(data_dir: Path, request: SiteRequest, *, cache_bytes: int) -> Path:
    """The file of a site's maps, made once: the version's surface resampled on the site
    frame's grid (service.exports.site_grid, as the site product is), with height (m),
    albedo, slope (deg), roughness (m), relief (m above the plane over the baseline), the 1-sigma
    height (m; NaN where the version has none), the hazard mask (uint8, pwm.site) and the
    fine-data mask (uint8, `_fine`) as [line = y, sample = x] arrays; the header holds the grid
    (x0_m, y0_m, spacing_m, the site frame), the direction of north in it (`_north`), where the
    fine data lies (`_fine`) and each map's minimum, mean and maximum. Raises ExportError when
    the site meets no surface."""
    key = digest({"console": "site", "revision": REVISION, "mesh": request.mesh["sha256"],
                  "site": request.site.model_dump(), "baseline_m": request.baseline_m,
                  "thresholds": [request.thresholds.max_slope_deg,
                                 request.thresholds.max_relief_m],
                  "maplets": [asdict(m) for m in request.maplets]})

    def make(path: Path) -> None:
        grid = site_grid(artifact_mesh(data_dir, request.mesh), request.site)
        height = grid.height_km * 1e3
        if np.isnan(height).all():
            raise ExportError("the site grid meets no surface")
        spacing_m = float(grid.x_km[1] - grid.x_km[0]) * 1e3
        maps = {"height": height, "albedo": grid.albedo,
                "slope": slope_deg(height, spacing_m=spacing_m, baseline_m=request.baseline_m),
                "roughness": roughness_m(height, spacing_m=spacing_m,
                                         baseline_m=request.baseline_m),
                "relief": relief_m(height, spacing_m=spacing_m, baseline_m=request.baseline_m),
                "sigma": (np.full_like(height, np.nan) if grid.sigma_km is None else grid.sigma_km * 1e3)}
        hazardous = hazard(maps["slope"], maps["relief"], request.thresholds)
        fine, fine_header = _fine(grid.frame, grid.x_km, grid.y_km, request.maplets)
        header = {"kind": "site", "version": request.version, "site": request.site.model_dump(),
                  "nx": len(grid.x_km), "ny": len(grid.y_km), "x0_m": float(grid.x_km[0]) * 1e3,
                  "y0_m": float(grid.y_km[0]) * 1e3, "spacing_m": spacing_m,
                  "baseline_m": request.baseline_m,
                  "thresholds": {"max_slope_deg": request.thresholds.max_slope_deg,
                                 "max_relief_m": request.thresholds.max_relief_m},
                  "frame": {"origin_km": grid.frame.origin.tolist(),
                            "rotation": grid.frame.rotation.tolist()},
                  "north": _north(grid.frame), "fine": fine_header,
                  "statistics": {name: _extent(values) for name, values in maps.items()},
                  "hazard_fraction": float(hazardous.mean())}
        path.write_bytes(pack(header, [*((name, values.astype(np.float32))
                                         for name, values in maps.items()),
                                       ("hazard", hazardous.astype(np.uint8)),
                                       ("fine", fine)]))

    record = cached_artifact(data_dir, key, suffix=".pwmc", make=make, cache_bytes=cache_bytes)
    return artifact_path(data_dir, record)


def _north(frame: LocalFrame) -> list[float] | None:
    """North in a site's map: the body's +Z (spin) axis projected on the frame's x-y plane, as
    a unit [x, y]; None at a pole, where it projects to nothing."""
    x, y = frame.rotation[0, 2], frame.rotation[1, 2]
    length = float(np.hypot(x, y))
    return None if length < NORTH_MIN else [float(x) / length, float(y) / length]


def _fine(frame: LocalFrame, x_km: np.ndarray, y_km: np.ndarray,
          maplets: tuple[MapletSquare, ...]) -> tuple[np.ndarray, dict[str, Any]]:
    """Where the site's grid lies within a refined maplet of the finest level that reaches it:
    a uint8 mask (ny, nx), and that level, its maplets, node spacing (m) and share of the grid
    (level None and share 0 where no refined maplet reaches the site). A node's place is taken
    on the frame's plane: a maplet's square holds its footprint, whatever the height."""
    xx, yy = np.meshgrid(x_km, y_km)
    nodes = frame.to_body(np.stack([xx, yy, np.zeros_like(xx)], axis=-1))
    inside = {}
    for maplet in maplets:
        local = maplet.frame().to_local(nodes)
        held = (np.abs(local[..., 0]) <= maplet.size_km / 2) & (np.abs(local[..., 1]) <= maplet.size_km / 2)
        if held.any():
            inside[maplet] = held
    mask = np.zeros(xx.shape, dtype=np.uint8)
    if not inside:
        return mask, {"level": None, "maplets": [], "gsd_m": None, "fraction": 0.0}
    level = min(m.level for m in inside)
    finest = [m for m in inside if m.level == level]
    for maplet in finest:
        mask |= inside[maplet]
    return mask, {"level": level, "maplets": [m.name for m in finest],
                  "gsd_m": min(m.gsd_m for m in finest), "fraction": float(mask.mean())}


def _extent(values: np.ndarray) -> dict[str, float | None]:
    finite = values[np.isfinite(values)]
    if not finite.size:
        return {"min": None, "mean": None, "max": None}
    return {"min": float(finite.min()), "mean": float(finite.mean()), "max": float(finite.max())}


class MapletCoverageRow(BaseModel):
    """One maplet on the coverage map: where it is, its region weight w_PWM, the images that see
    it (visible fraction above 0) and those of them with a weight above 0 ("used"), the range of
    the used images' incidence angles (deg; None without any), and whether the five views
    (nadir, east, west, north, south) are all filled. outline: its square's corners as
    [latitude, east longitude] (deg), for the map to draw its true extent; radius_km: its
    origin's distance from the body's centre, for the map's scale."""

    model_config = ConfigDict(frozen=True)

    id: int
    name: str
    center_lat_deg: float
    center_lon_deg: float
    size_km: float
    radius_km: float
    outline: list[tuple[float, float]]
    region_weight: float
    current_revision: int | None
    image_count: int
    used_count: int
    incidence_min_deg: float | None
    incidence_max_deg: float | None
    roles_filled: int
    five_views: bool


def coverage_map(session: Session, *, near: tuple[float, float, float] | None = None
                 ) -> list[MapletCoverageRow]:
    """Every maplet with its coverage figures (as service.queries.maplet_coverage counts them),
    by name; near = (lat_deg, lon_deg, radius_km): only the maplets within radius_km of that
    surface point (service.queries.list_maplets), for the map of a site."""
    ids = None
    if near is not None:
        lat_deg, lon_deg, radius_km = near
        ids = [m.id for m in list_maplets(session, lat_deg=lat_deg, lon_deg=lon_deg,
                                          radius_km=radius_km, limit=2**31 - 1)]
    used = Coverage.weight > 0
    figures = {row.maplet_id: row for row in session.execute(
        select(Coverage.maplet_id, func.count().label("images"),
               func.sum(case((used, 1), else_=0)).label("used"),
               func.min(case((used, Coverage.incidence_deg))).label("inc_min"),
               func.max(case((used, Coverage.incidence_deg))).label("inc_max"),
               func.count(distinct(Coverage.role)).label("roles"))
        .where(Coverage.visible_fraction > 0,
               Coverage.maplet_id.in_(ids) if ids is not None else true())
        .group_by(Coverage.maplet_id))}
    rows = session.execute(
        select(Maplet.id, Maplet.name, Maplet.center_lat_deg, Maplet.center_lon_deg,
               Maplet.size_km, Maplet.origin_x_km, Maplet.origin_y_km, Maplet.origin_z_km,
               Maplet.rotation, Maplet.region_weight, MapletRevision.revision)
        .outerjoin(MapletRevision, MapletRevision.id == Maplet.current_revision_id)
        .where(Maplet.id.in_(ids) if ids is not None else true())
        .order_by(Maplet.name))
    out = []
    for row in rows:
        seen = figures.get(row.id)
        roles = int(seen.roles) if seen else 0
        frame = Maplet.frame_of(row)
        half = row.size_km / 2
        lat, lon = unit_to_latlon(frame.to_body(np.array(
            [[-half, -half, 0.0], [half, -half, 0.0], [half, half, 0.0], [-half, half, 0.0]])))
        out.append(MapletCoverageRow(
            id=row.id, name=row.name, center_lat_deg=row.center_lat_deg,
            center_lon_deg=row.center_lon_deg, size_km=row.size_km,
            radius_km=float(np.linalg.norm(frame.origin)),
            outline=[(float(a), float(o)) for a, o in zip(lat, lon, strict=True)],
            region_weight=row.region_weight, current_revision=row.revision,
            image_count=int(seen.images) if seen else 0, used_count=int(seen.used or 0) if seen else 0,
            incidence_min_deg=seen.inc_min if seen else None,
            incidence_max_deg=seen.inc_max if seen else None,
            roles_filled=roles, five_views=roles == len(CoverageRole)))
    return out
