"""SPICE DSK type 2 (plate model) files: write a mesh as one segment or as several that part it,
read segments back.

Vertices in km in the body-fixed frame; SPICE numbers vertices from 1, Mesh from 0. The frame
must be known to SPICE when writing (built in, or from a loaded FK).
"""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np
import spiceypy as sp

from pwm.mesh import Mesh, compact
from pwm.raytrace import RayTracer

LATITUDINAL = 1  # SPICE_DSK_LATSYS
GENERAL_CLASS = 2  # SPICE_DSK_GENCLS: no claim that the surface is single-valued in lat/lon
PLATE_MODEL = 2  # DSK data type 2
MAX_COARSE_VOXELS = 100_000  # SPICE_DSK02_MAXCGR
INDEX_FIXED_INTS = MAX_COARSE_VOXELS + 7  # SPICE_DSK02_IXIFIX
# The spatial index's integers (voxel pointers and plate lists) allowed per plate: uniform meshes
# need 20-60 at dskmi2's documented fine scale, which is then kept.
INDEX_INTS_PER_PLATE = 64
_FINE_SCALE_STEP = 1.25
_VOXEL_TOLERANCE = 0.01  # > dskmi2's plate-box padding (1e-3 voxel) in voxel units
_COMMENT_WIDTH = 80  # NAIF's line length for kernel comments


def write_dsk(path: str | Path, mesh: Mesh, *, body: int, frame: str, surface: int | None = None,
              comment: str, parts: np.ndarray | None = None) -> None:
    """Write `mesh` (km, body-fixed `frame`) as a DSK type 2 file, overwriting `path`: one
    segment, or one per value of `parts` (M,) (a label per face) in the order of the values.

    Segments part the mesh: they meet along shared edges and never overlap, so SPICE's
    unprioritized intercepts over them all (dskxv, sincpt's DSK/UNPRIORITIZED) are the mesh's
    own, and each segment's spatial index is sized to its own plates (a site's centimetre
    plates apart from the body's metre ones).
    body: NAIF ID of the body (each segment's centre); surface: surface ID (default: body).
    Coverage is latitudinal, each segment's longitude/latitude range (rad) and radius range
    (km), valid for +-50 Julian years about J2000. comment goes to the comment area.
    """
    path = Path(path)
    labels = np.zeros(len(mesh.faces), dtype=np.int64) if parts is None else np.asarray(parts)
    if labels.shape != (len(mesh.faces),):
        raise ValueError("parts must give one label per face")
    lines = [wrapped for line in comment.splitlines()
             for wrapped in (textwrap.wrap(line, _COMMENT_WIDTH) or [" "])]
    path.unlink(missing_ok=True)
    handle = sp.dskopn(str(path), path.name[:60], sum(len(s) + 1 for s in lines))
    try:
        if lines:
            sp.dasac(handle, lines)
        for label in np.unique(labels):
            used, faces = compact(len(mesh.vertices), mesh.faces[labels == label])
            _write_segment(handle, np.ascontiguousarray(mesh.vertices[used], dtype=np.float64), faces,
                           body=body, surface=body if surface is None else surface, frame=frame)
    except Exception:
        sp.dskcls(handle, False)
        path.unlink(missing_ok=True)
        raise
    sp.dskcls(handle, True)


def _write_segment(handle: int, vertices: np.ndarray, faces: np.ndarray, *, body: int, surface: int,
                   frame: str) -> None:
    plates = np.ascontiguousarray(faces + 1, dtype=np.int32)
    finscl, corscl, sizes = _index_parameters(vertices, faces)
    spaixd, spaixi = sp.dskmi2(vertices, plates, finscl, corscl, *sizes)
    corpar = np.zeros(10)  # SPICE_DSK_NSYPAR; unused by latitudinal coordinates
    radius_min, radius_max = sp.dskrb2(vertices, plates, LATITUDINAL, corpar)
    lon_min, lon_max, lat_min, lat_max = _coverage(vertices, faces)
    sp.dskw02(handle, body, surface, GENERAL_CLASS, frame, LATITUDINAL, corpar, lon_min, lon_max, lat_min,
              lat_max, radius_min, radius_max, -50 * sp.jyear(), 50 * sp.jyear(), vertices, plates, spaixd, spaixi)


def read_dsk(path: str | Path) -> Mesh:
    """Read every type 2 segment of a DSK file into one mesh (km, the segments' frame); the
    segments must share body and frame. Where segments meet, a vertex that several give at the
    same place is one, so a closed surface written in parts reads back closed."""
    handle = sp.dasopr(str(path))
    try:
        vertices: list[np.ndarray] = []
        faces: list[np.ndarray] = []
        owners: set[tuple[int, int]] = set()
        found = True
        descriptor = sp.dlabfs(handle)
        while found:
            dsk = sp.dskgd(handle, descriptor)
            if dsk.dtype != PLATE_MODEL:
                raise ValueError(f"{path}: segment of DSK type {dsk.dtype}, only type 2 is read")
            owners.add((dsk.center, dsk.frmcde))
            n_vertices, n_plates = sp.dskz02(handle, descriptor)
            offset = sum(len(v) for v in vertices)
            vertices.append(sp.dskv02(handle, descriptor, 1, n_vertices))
            faces.append(sp.dskp02(handle, descriptor, 1, n_plates).astype(np.int64) - 1 + offset)
            with sp.no_found_check():
                descriptor, found = sp.dlafns(handle, descriptor)
    finally:
        sp.dascls(handle)
    if len(owners) > 1:
        raise ValueError(f"{path}: segments of different bodies or frames {sorted(owners)}")
    if len(vertices) == 1:
        return Mesh(vertices[0], faces[0])
    unique, inverse = np.unique(np.concatenate(vertices), axis=0, return_inverse=True)
    return Mesh(unique, inverse.reshape(-1)[np.concatenate(faces)])


def _index_parameters(vertices: np.ndarray, faces: np.ndarray) -> tuple[float, int, tuple]:
    """Voxel scales and array sizes for dskmi2: (finscl, corscl, (worksz, voxpsz, voxlsz,
    makvtl, spxisz)).

    The fine scale starts at dskmi2's documented value max(1, np^(1/4) / 8) and grows until the
    index fits INDEX_INTS_PER_PLATE per plate: dskmi2 sizes the voxels from the mean plate
    extent, so on a mesh of many small plates and some large ones (a dense site on a coarse
    body) the large plates' bounding boxes would span thousands of voxels each, and the index,
    the file and dskmi2's time would grow with the body's volume in voxels, not with the plates.
    The coarse scale is the smallest that keeps the padded coarse grid within SPICE's limit.
    Sizes are upper bounds counted from each plate's bounding box, as dskmi2 assigns plates to
    voxels.
    """
    n_vertices, n_plates = len(vertices), len(faces)
    extents = np.ptp(vertices[faces], axis=1)
    box = np.ptp(vertices, axis=0)
    mean_extent = extents.mean()
    budget = INDEX_INTS_PER_PLATE * n_plates + MAX_COARSE_VOXELS
    finscl = max(1.0, n_plates ** 0.25 / 8)
    corscl, voxpsz, cells = _index_counts(extents, box, finscl * mean_extent)
    # once a voxel spans the whole box, a plate meets at most 3 per axis: the budget is met
    while voxpsz + 2 * cells > budget and finscl * mean_extent < box.max():
        finscl *= _FINE_SCALE_STEP
        corscl, voxpsz, cells = _index_counts(extents, box, finscl * mean_extent)
    vertex_plate_list = n_vertices + 3 * n_plates
    voxlsz = 2 * cells
    spxisz = INDEX_FIXED_INTS + voxpsz + voxlsz + n_vertices + vertex_plate_list
    # dskmi2 also keeps a pointer per voxel (voxpsz of them) in the work array
    worksz = max(cells, vertex_plate_list, voxpsz)
    return finscl, corscl, (worksz, voxpsz, voxlsz, True, spxisz)


def _index_counts(extents: np.ndarray, box: np.ndarray, voxel: float) -> tuple[int, int, int]:
    """For fine voxels of edge `voxel` (km): the coarse scale, an upper bound on the fine voxel
    pointers (corscl^3 per non-empty coarse voxel) and one on the plate-voxel pairs."""
    corscl = 1
    # the coarse grid is padded by up to 1.5 coarse voxels at each end
    while np.prod(np.ceil(box / (voxel * corscl)) + 3) > MAX_COARSE_VOXELS:
        corscl += 1
    coarse_voxels = int(np.prod(np.ceil(box / (voxel * corscl)) + 3))
    # a box spanning s voxels along an axis meets at most floor(s) + 2 of them
    cells = int(np.prod(np.floor(extents / voxel + _VOXEL_TOLERANCE) + 2, axis=1).sum())
    coarse_cells = int(np.prod(np.floor(extents / (voxel * corscl) + _VOXEL_TOLERANCE) + 2,
                               axis=1).sum())
    return corscl, corscl ** 3 * min(coarse_voxels, coarse_cells), cells


def _coverage(vertices: np.ndarray, faces: np.ndarray) -> tuple[float, float, float, float]:
    """Longitude and latitude bounds (rad) enclosing the plates: the whole sphere when the mesh
    surrounds the body centre, else the vertices' ranges, widened where plates reach past them."""
    if abs(_solid_angle(vertices, faces)) > 2 * np.pi:
        return -np.pi, np.pi, -np.pi / 2, np.pi / 2
    unit = vertices / np.linalg.norm(vertices, axis=1, keepdims=True)
    # an edge bulges towards a pole past its ends by less than the angle it subtends
    ends = faces, np.roll(faces, 1, axis=1)
    margin = float(np.arccos(np.clip(np.sum(unit[ends[0]] * unit[ends[1]], axis=2), -1, 1)).max())
    lat = np.arcsin(np.clip(unit[:, 2], -1.0, 1.0))
    poles = RayTracer(Mesh(vertices, faces)).intersect(
        np.zeros((2, 3)), np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])).hit
    lat_max = np.pi / 2 if poles[0] else min(lat.max() + margin, np.pi / 2)
    lat_min = -np.pi / 2 if poles[1] else max(lat.min() - margin, -np.pi / 2)
    lon = np.arctan2(unit[:, 1], unit[:, 0])
    # an edge that does not cross a pole spans the longitudes between its ends
    span = np.abs(np.angle(np.exp(1j * (lon[ends[0]] - lon[ends[1]])))).max()
    ordered = np.sort(lon)
    gaps = np.diff(np.append(ordered, ordered[0] + 2 * np.pi))
    widest = int(np.argmax(gaps))
    if poles.any() or gaps[widest] <= span + 2 * margin:
        return -np.pi, np.pi, float(lat_min), float(lat_max)
    # coverage starts after the widest empty sector; unless that sector is the one across
    # +-pi, max < min, which dskw02 reads as a range wrapping through +-pi
    lon_min = ordered[(widest + 1) % len(ordered)] - margin
    lon_max = ordered[widest] + margin
    return float(lon_min), float(lon_max), float(lat_min), float(lat_max)


def _solid_angle(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Signed solid angle (sr) the mesh subtends at the origin: 4 pi for a closed, outward
    oriented mesh around it, 0 for one that does not enclose it (Van Oosterom & Strackee 1983)."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    la, lb, lc = (np.linalg.norm(x, axis=1) for x in (a, b, c))
    numerator = np.einsum("ij,ij->i", a, np.cross(b, c))
    denominator = (la * lb * lc + np.einsum("ij,ij->i", a, b) * lc
                   + np.einsum("ij,ij->i", a, c) * lb + np.einsum("ij,ij->i", b, c) * la)
    return float(2 * np.arctan2(numerator, denominator).sum())
