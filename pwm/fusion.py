"""Fusion of refined maplets into one surface (PWM paper section 3.5; METHOD.md 6).

Maplets go back into the body frame by their rigid local-to-body transforms (no re-alignment).
Every node adds, to the voxel of side voxel_km that holds it, its weight w = w_PWM * taper and
its weighted position, regional normal and albedo; the taper is 1 in the maplet's centre and falls
as a raised cosine to nearly 0 at its edges over the overlap with its neighbours, so adjacent
maplets cross-fade. The voxel sums are kept: a maplet's old revision is subtracted exactly as it
was added, and its new one added, without re-fusing the rest.

Remeshing (`VoxelGrid.mesh`) parameterises the fused surface as a height field: over the plane
of a region frame (given, or the fused region's mean plane when all its normals lie within 60 deg
of their mean), or over the sphere of directions from the body centre (the whole body). Voxels
are merged into columns of the same size in that parameterisation (sums add, so a column holds
the weighted average of everything above or below it), the column points are triangulated in the
parameter domain (Delaunay in the plane, convex hull of the directions on the sphere) and
triangles with an edge longer than MAX_EDGE_VOXELS voxels are dropped, which leaves the gaps
between separate fused regions open. Stitching into a base model removes the base faces under the
fused region except within a margin of its border, where base faces overlap the fused surface
(as for the proving-ground patch, pwm.simulate.truth): no gap, but a thin doubly covered band.

Limits: overhangs and surfaces steeper than the parameterisation allows (beyond 90 deg from the
region normal, or not star-shaped from the body centre) are averaged into one layer (a whole
body whose lattice is affordable is fused by pwm.volume instead, which keeps them); the base
facets near the region must be smaller than the region, else none is removed and the fused
surface only overlays the base. Lengths in km.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull, Delaunay, cKDTree

from pwm.frames import LocalFrame, local_frame
from pwm.maplets import MapletGrid
from pwm.mesh import Mesh, border_edges, compact
from pwm.voxels import SparseSums, pack, sum_by_key
from pwm.weights import raised_cosine

MAX_EDGE_VOXELS = 4.0
"""Longest triangle edge of the fused surface, in voxels (in the parameter domain)."""
PLANE_MAX_TILT_DEG = 60.0
"""A fused region whose voxel normals all lie within this of their mean is meshed over a plane."""

_W, _P, _N, _WA, _A = 0, slice(1, 4), slice(4, 7), 7, 8
_COLUMNS = 9


def edge_taper(n: int, spacing_km: float, fraction: float) -> np.ndarray:
    """(n, n) node weights: 1 in the centre, a raised cosine falling towards the edges over a band
    of `fraction` of the side plus one spacing, so that maplets overlapping by that fraction sum
    to 1 across their overlap; edge nodes keep a small positive weight."""
    half = 0.5 * (n - 1) * spacing_km
    axis = np.abs((np.arange(n) - (n - 1) / 2) * spacing_km)
    depth = half + 0.5 * spacing_km - np.maximum(axis[:, None], axis[None, :])
    return raised_cosine(depth / (fraction * 2.0 * half + spacing_km))


@dataclass
class FusedPoints:
    """The voxel averages: points (M, 3) km, unit regional normals (M, 3), albedo (M,) (nan where no
    maplet gave one) and total weight (M,)."""

    points: np.ndarray
    normals: np.ndarray
    albedo: np.ndarray
    weight: np.ndarray


@dataclass
class VoxelGrid(SparseSums):
    """Sparse weighted sums of the maplets' nodes per voxel of side voxel_km (pwm.voxels).

    sums columns: weight, weighted position (3), weighted normal (3), albedo weight, weighted
    albedo; count: number of nodes per voxel. taper_fraction: the overlap fraction of the maplets
    (see `edge_taper`).
    """

    taper_fraction: float = 0.25

    def _contribution(self, maplet: MapletGrid) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Voxel keys (sorted, unique), sums and node counts of one maplet."""
        p = maplet.nodes_body().reshape(-1, 3)
        w = maplet.weight * edge_taper(maplet.n, maplet.spacing_km, self.taper_fraction).ravel()
        cols = np.zeros((len(p), _COLUMNS))
        cols[:, _W] = w
        cols[:, _P] = w[:, None] * p
        cols[:, _N] = w[:, None] * maplet.frame.normal
        if maplet.albedo is not None:
            cols[:, _WA] = w
            cols[:, _A] = w * maplet.albedo.ravel()
        return sum_by_key(pack(np.floor(p / self.voxel_km)), cols)

    def points(self) -> FusedPoints:
        """The weighted average of each voxel."""
        return _averages(self.sums)

    def mesh(self, base: Mesh | None = None, *, frame: LocalFrame | None = None) -> Mesh:
        """The fused surface as a mesh with per-vertex albedo, stitched into `base` if given (see the
        module docstring). frame: mesh over this frame's x-y plane (z outwards); by default the
        region's mean plane, or the sphere of directions for a region that curves too far."""
        if not len(self.keys):
            raise ValueError("nothing fused")
        voxels = self.points()
        param = _Plane(frame) if frame is not None else _parameterisation(voxels, self.sums[:, _W])
        q = param.coords(voxels.points)
        cell = np.floor(q / self.voxel_km).astype(np.int64)
        cell -= cell.min(axis=0)
        _, col = np.unique(np.ravel_multi_index(cell.T, cell.max(axis=0) + 1), return_inverse=True)
        sums = np.column_stack([np.bincount(col, weights=self.sums[:, c]) for c in range(_COLUMNS)])
        fused = _averages(sums)
        q = param.coords(fused.points)
        faces = param.triangulate(q)
        edges = np.linalg.norm(q[faces] - q[np.roll(faces, 1, axis=1)], axis=2)
        faces = faces[(edges <= MAX_EDGE_VOXELS * self.voxel_km).all(axis=1)]
        if not len(faces):
            raise ValueError("the fused points are too sparse to mesh at this voxel size")
        used, faces = compact(len(q), faces)
        points, q, albedo = fused.points[used], q[used], fused.albedo[used]
        if not np.isnan(albedo).all():
            albedo = fill_gaps(albedo, q)
        if base is None:
            return Mesh(points, faces, None if np.isnan(albedo).all() else albedo)
        return _stitch(base, points, faces, albedo, param, q, self.voxel_km)

    def vertical(self, points: np.ndarray) -> np.ndarray:
        """Unit directions (N, 3) at the points along which `mesh`'s surface is a height field:
        the region's mean normal, or radial for a region that curves too far (its
        parameterisation)."""
        return _parameterisation(self.points(), self.sums[:, _W]).up(points)


def _averages(sums: np.ndarray) -> FusedPoints:
    w = sums[:, _W]
    n = sums[:, _N]
    with np.errstate(invalid="ignore", divide="ignore"):
        # a relative threshold: subtracting a maplet's albedo may leave rounding residue
        albedo = np.where(sums[:, _WA] > 1e-9 * w, sums[:, _A] / sums[:, _WA], np.nan)
    return FusedPoints(points=sums[:, _P] / w[:, None], normals=n / np.linalg.norm(n, axis=1, keepdims=True),
                       albedo=albedo, weight=w)


def _fill_nearest(values: np.ndarray, at: np.ndarray, donors: np.ndarray, donor_values: np.ndarray) -> np.ndarray:
    """values with each nan replaced by the value of the nearest donor point."""
    out = values.copy()
    missing = np.isnan(out)
    out[missing] = donor_values[cKDTree(donors).query(at[missing])[1]]
    return out


def fill_gaps(values: np.ndarray, at: np.ndarray) -> np.ndarray:
    """Per-point values (some finite) with each nan replaced by the nearest finite one's, points
    `at` (N, k)."""
    known = ~np.isnan(values)
    return values if known.all() else _fill_nearest(values, at, at[known], values[known])


@dataclass
class _Plane:
    """Height field over a frame's x-y plane: coordinates (x, y)."""

    frame: LocalFrame

    def coords(self, points: np.ndarray) -> np.ndarray:
        return self.frame.to_local(points)[:, :2]

    def up(self, points: np.ndarray) -> np.ndarray:
        return np.broadcast_to(self.frame.normal, points.shape)

    def triangulate(self, q: np.ndarray) -> np.ndarray:
        faces = Delaunay(q).simplices.astype(np.int64)
        a, b, c = q[faces[:, 0]], q[faces[:, 1]], q[faces[:, 2]]
        cw = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0]) < 0
        faces[cw] = faces[cw][:, ::-1]
        return faces

    def near(self, points: np.ndarray, fused: np.ndarray, pad: float) -> np.ndarray:
        """Points within pad of the fused surface's height range (not on the far side)."""
        z = self.frame.to_local(points)[:, 2]
        zf = self.frame.to_local(fused)[:, 2]
        return (z >= zf.min() - pad) & (z <= zf.max() + pad)


@dataclass
class _Sphere:
    """Radial height field over the sphere of directions: coordinates radius_km * unit direction."""

    radius_km: float

    def coords(self, points: np.ndarray) -> np.ndarray:
        return self.radius_km * points / np.linalg.norm(points, axis=1, keepdims=True)

    def up(self, points: np.ndarray) -> np.ndarray:
        return points / np.linalg.norm(points, axis=1, keepdims=True)

    def triangulate(self, q: np.ndarray) -> np.ndarray:
        faces = ConvexHull(q).simplices.astype(np.int64)
        tri = q[faces]
        inward = np.einsum("ij,ij->i", np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), tri.sum(axis=1)) < 0
        faces[inward] = faces[inward][:, ::-1]
        return faces

    def near(self, points: np.ndarray, fused: np.ndarray, pad: float) -> np.ndarray:
        return np.ones(len(points), dtype=bool)


def _parameterisation(voxels: FusedPoints, weight: np.ndarray) -> _Plane | _Sphere:
    """The region's mean plane if every voxel normal lies within PLANE_MAX_TILT_DEG of the mean
    normal, else the sphere of directions with the mean radius."""
    mean = (weight[:, None] * voxels.normals).sum(axis=0)
    mean /= np.linalg.norm(mean)
    if (voxels.normals @ mean).min() >= np.cos(np.radians(PLANE_MAX_TILT_DEG)):
        centre = (weight[:, None] * voxels.points).sum(axis=0) / weight.sum()
        return _Plane(local_frame(centre, mean))
    return _Sphere(float((weight * np.linalg.norm(voxels.points, axis=1)).sum() / weight.sum()))


def _stitch(base: Mesh, points: np.ndarray, faces: np.ndarray, albedo: np.ndarray, param: _Plane | _Sphere,
            q: np.ndarray, voxel: float) -> Mesh:
    """Fused surface + the base without its faces under the fused region's interior: base vertices
    within 2 voxels of a fused point (in the parameter domain), on the near side, and farther than
    the longest base edge around there plus 3 voxels from the fused surface's border."""
    qb = param.coords(base.vertices)
    inside = np.zeros(len(base.vertices), dtype=bool)
    near = param.near(base.vertices, points, MAX_EDGE_VOXELS * voxel)
    inside[near] = cKDTree(q).query(qb[near], distance_upper_bound=2 * voxel)[0] <= 2 * voxel
    touching = inside[base.faces].any(axis=1)
    tri = qb[base.faces[touching]]
    margin = float(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max(initial=0.0)) + 3 * voxel
    border = border_vertices(faces)
    interior = inside.copy()
    if len(border) and inside.any():
        interior[inside] = cKDTree(q[border]).query(qb[inside])[0] >= margin
    used, kept = compact(len(base.vertices), base.faces[~interior[base.faces].all(axis=1)])
    n_base = int(used.sum())
    vertices = np.vstack([base.vertices[used], points])
    faces = np.vstack([kept, faces + n_base])
    fused_has = not np.isnan(albedo).all()
    if base.albedo is None and not fused_has:
        return Mesh(vertices, faces)
    base_albedo = base.albedo[used] if base.albedo is not None else np.full(n_base, np.nanmean(albedo))
    if not fused_has and base.albedo is not None:  # without either, returned above
        albedo = _fill_nearest(albedo, points, base.vertices, base.albedo)
    return Mesh(vertices, faces, np.concatenate([base_albedo, albedo]))


def border_vertices(faces: np.ndarray) -> np.ndarray:
    """Vertices on edges used by one face only."""
    n = int(faces.max()) + 1
    once = border_edges(faces, n)
    return np.unique(np.concatenate([once // n, once % n]))
