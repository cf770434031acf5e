"""Volumetric fusion of maplets into one closed surface of the whole body (METHOD.md 6).

Each maplet adds, at the lattice points (multiples of voxel_km along the body axes) within
TRUNCATION_VOXELS of its surface, the signed distance to that surface (positive outside: along the
maplet's z), weighted by w_PWM times the edge taper of pwm.fusion (so that overlapping maplets
cross-fade), and its albedo. The sums are pwm.voxels.SparseSums: a maplet's revision is
subtracted exactly as it was added, and its new one added, without re-fusing the rest.

The surface is the zero set of the weighted mean distance, extracted by marching cubes block by
block, so no dense volume of the body is ever held. A base mesh fills the places no maplet
reaches: its signed distances, bent to meet the maplets at their borders, are added with
BASE_WEIGHT at the lattice points that no maplet touched, so the surface closes over what the
images did not see with the base's shape. Of what
marching cubes makes, the largest connected piece is the body; smaller pieces (bubbles inside,
specks outside, where maplets disagree by more than the truncation) are dropped.

Unlike the height fields of pwm.fusion, nothing here is parameterised over a plane or over the
directions from the centre: overhangs, and bodies that rays from their centre cross several
times (a contact binary's neck), keep their shape. A maplet itself is a height field over its
plane; what it cannot hold, its neighbours at other orientations do.

Limits: parts thinner than about two truncations are thinned by the distances from their two
sides; where the base and the maplets disagree, the base is bent over FADE_VOXELS, which is a
slope on the scale of the disagreement. Lengths in km.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree
from skimage.measure import marching_cubes

from pwm.fusion import VoxelGrid, edge_taper, fill_gaps
from pwm.maplets import MapletGrid
from pwm.mesh import Mesh, compact, largest_piece, uncollapsed
from pwm.raytrace import RayTracer
from pwm.voxels import SparseSums, corners, find, pack, sum_by_key, unpack
from pwm.weights import raised_cosine

TRUNCATION_VOXELS = 4.0
"""Half-width of the band of lattice points about a surface that takes its signed distance."""
BASE_WEIGHT = 1e-3
"""Weight of the base's distances, against w_PWM in (0, 1] times a taper of at most 1."""
FADE_VOXELS = 16.0
"""Distance beyond the maplets' band over which the base's bend towards them fades out."""
BLOCK = 32
"""Side, in lattice steps, of the blocks marching cubes works on."""
MAX_SURFACE_CELLS = 4_000_000
"""The most lattice cells of a base's surface (its area over voxel_km squared) fused as one
closed surface; beyond, maplets are fused as points laid onto the base (pwm.fusion, pwm.levels.displace)."""

_BEND_NEIGHBOURS = 8
_RING_BATCH = 250_000
_INSIDE_RAY = np.array([0.4472, 0.7746, 0.4472]) / np.linalg.norm([0.4472, 0.7746, 0.4472])
_W, _WD, _WA, _A = 0, 1, 2, 3
_COLUMNS = 4
_CORNERS = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=np.int64)
_NEIGHBOURS = np.array([[i, j, k] for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)], dtype=np.int64)


@dataclass
class DistanceGrid(SparseSums):
    """Weighted sums of signed distances at lattice points of spacing voxel_km (pwm.voxels).

    sums columns: weight, weighted distance (km), albedo weight, weighted albedo; count: the
    maplets' contributions per point. taper_fraction: the maplets' overlap (pwm.fusion.edge_taper).
    """

    taper_fraction: float = 0.25

    def __post_init__(self) -> None:
        if not len(self.keys):
            self.sums = np.empty((0, _COLUMNS))

    @property
    def truncation_km(self) -> float:
        return TRUNCATION_VOXELS * self.voxel_km

    def _contribution(self, maplet: MapletGrid,
                      within: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """within: the lattice box (lowest, highest index) whose points are wanted (None: all);
        each point's value is made on its own, so those in it are the whole contribution's."""
        nodes = maplet.nodes_body().reshape(-1, 3)
        normals = maplet.normals_body().reshape(-1, 3)
        if within is not None:
            # a node's band reaches its truncation's whole steps and a cell's corners beyond
            pad = np.ceil(self.truncation_km / self.voxel_km) + 2
            at = nodes / self.voxel_km
            near = in_box(at, within[0] - pad, within[1] + 1 + pad)
            nodes, normals = nodes[near], normals[near]
        index = unpack(self._band(nodes, normals))
        if within is not None:
            index = index[in_box(index, *within)]
        local = maplet.frame.to_local(index * self.voxel_km)
        c = 0.5 * (maplet.n - 1)
        grid = np.stack([local[:, 1] / maplet.spacing_km + c, local[:, 0] / maplet.spacing_km + c])
        inside = ((grid >= 0) & (grid <= maplet.n - 1)).all(axis=0)
        index, local, grid = index[inside], local[inside], grid[:, inside]
        dz_dy, dz_dx = np.gradient(maplet.heights, maplet.spacing_km)
        h, gx, gy, taper = (ndimage.map_coordinates(a, grid, order=1, mode="nearest") for a in
                            (maplet.heights, dz_dx, dz_dy,
                             edge_taper(maplet.n, maplet.spacing_km, self.taper_fraction)))
        distance = (local[:, 2] - h) / np.sqrt(1.0 + gx ** 2 + gy ** 2)
        near = np.abs(distance) <= self.truncation_km
        w = maplet.weight * taper[near]
        cols = np.zeros((int(near.sum()), _COLUMNS))
        cols[:, _W] = w
        cols[:, _WD] = w * distance[near]
        if maplet.albedo is not None:
            cols[:, _WA] = w
            cols[:, _A] = w * ndimage.map_coordinates(maplet.albedo, grid[:, near], order=1, mode="nearest")
        return sum_by_key(pack(index[near]), cols)

    def _band(self, points: np.ndarray, normals: np.ndarray, reach_km: np.ndarray | float | None = None) -> np.ndarray:
        """Sorted unique keys of the lattice points about the surface through `points` with unit
        `normals`, out to reach_km on both sides (per point, or this grid's truncation): the
        corners of the cells that the points stepped along their normals fall in."""
        reach = np.broadcast_to(self.truncation_km if reach_km is None else reach_km, (len(points),))
        keys = []
        # steps at whole lattice steps from the surface, so that a point's band is the same
        # whatever the others' reach
        steps = int(np.ceil(reach.max(initial=0.0) / self.voxel_km))
        for t in self.voxel_km * np.arange(-steps, steps + 1):
            out_to = reach > abs(t) - self.voxel_km
            cell = np.floor((points[out_to] + t * normals[out_to]) / self.voxel_km).astype(np.int64)
            keys.append(np.unique(pack(cell)))
        return corners(np.unique(np.concatenate(keys)))

    def _base_sums(self, base: Mesh, faces: np.ndarray | None = None, clip_km: float | None = None,
                   within: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The base's signed distances, bent to meet the maplets, at the lattice points about it
        that no maplet touched; faces: a mask of the base's faces to sample (all by default: a
        block of pwm.blocks takes those about it), the sign comes from the whole base; clip_km:
        the largest distance kept (by default the widest band's reach, `base_reach`); within: the
        lattice box (lowest, highest index) whose points are wanted (all by default). Each point's
        value is made on its own but for the rings below, which spread at most FADE_VOXELS steps:
        the points more than that beyond the box are left out, and those in it get the values
        the whole lattice would give them.

        Distances to the base come from the nearest of samples at most a lattice step apart on
        its faces. Where the base and the maplets disagree (by delta at a maplet's point near its
        surface), the base's distances take delta off, fully within the truncation of the
        maplets' points and fading to none over FADE_VOXELS: so the base meets the maplets at
        their borders (no tear, no step) and crosses zero under them nowhere else (no second
        layer). Its band is widened by the largest delta so that it reaches the maplets' band,
        and left out where the base runs within a lattice step of the maplets' surface.
        """
        points, normals, albedo = _surface_samples(base, self.voxel_km, faces)
        distance_to_base = _MeshDistance(base, points, normals, self.voxel_km)
        maplet_sums = self.sums[:, _W] > 0
        maplet_distance = self.sums[maplet_sums, _WD] / self.sums[maplet_sums, _W]
        at, delta, local_reach = self._disagreement(points, distance_to_base)
        fade = FADE_VOXELS * self.voxel_km
        reach = float(local_reach.max(initial=self.truncation_km)) if clip_km is None else clip_km
        maplet_surface = cKDTree(at) if len(at) else None
        # where the base runs within a lattice step of the maplets' surface, and is not near
        # where it does not (a border), the maplets hold the surface alone
        bare = np.ones(len(points), dtype=bool) if maplet_surface is None else (
            maplet_surface.query(points, distance_upper_bound=self.voxel_km)[0] > self.voxel_km)
        if bare.any() and not bare.all():
            margin = local_reach + 2.0 * self.voxel_km
            bare = cKDTree(points[bare]).query(points, distance_upper_bound=margin.max())[0] <= margin
        if within is not None:
            # what reaches the box: the samples whose band can, and the points the rings can
            pad = int(FADE_VOXELS) + 1
            lo, hi = within[0] - pad, within[1] + pad
            cell = np.floor(points / self.voxel_km)
            beyond = int(np.ceil(float(local_reach.max(initial=0.0)) / self.voxel_km)) + 2
            bare &= in_box(cell, lo - beyond, hi + beyond)

        def wanted(keys: np.ndarray) -> np.ndarray:
            if within is None:
                return keys
            return keys[in_box(unpack(keys), lo, hi)]

        keys = (wanted(self._band(points[bare], normals[bare], local_reach[bare])) if bare.any()
                else np.empty(0, dtype=np.int64))
        keys = keys[~np.isin(keys, self.keys, assume_unique=True)]

        def bent(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            x = unpack(keys) * self.voxel_km
            distance, nearest = distance_to_base(x)
            if maplet_surface is not None and len(x):
                # the mean disagreement of the nearest maplet points, so that one maplet's
                # outlier does not bend the base alone; none beyond the fade (a bound that also
                # keeps the tree's search on a regular lattice fast)
                gap, which = maplet_surface.query(x, k=min(_BEND_NEIGHBOURS, len(at)),
                                                  distance_upper_bound=fade + self.truncation_km)
                gap, which = gap.reshape(len(x), -1), which.reshape(len(x), -1)
                found = np.isfinite(gap)
                mean = (np.append(delta, 0.0)[which] * found).sum(axis=1) / np.maximum(found.sum(axis=1), 1)
                distance -= mean * raised_cosine((fade + self.truncation_km - gap[:, 0]) / fade)
            return distance, nearest

        distance, nearest = bent(keys)
        # The corners of the cells that samples a lattice step apart fall in can miss points
        # where the base's coarse faces meet at an angle, and the maplets' bands end at their
        # edges: a cell that the surface crosses there would lack a corner, and marching cubes
        # leave a hole. Every lattice point next to one within a cell diagonal of the surface
        # gets the base's distance too, ring after ring while the points added are themselves
        # that near (where the bend carries the surface out of the base's band).
        diagonal = np.sqrt(3.0) * self.voxel_km

        def missing_about(held: np.ndarray) -> np.ndarray:
            # _RING_BATCH points at a time: the points next to a whole body's surface at once
            # would be 26 times its band
            found = [np.empty(0, dtype=np.int64)]
            for start in range(0, len(held), _RING_BATCH):
                around = unpack(held[start:start + _RING_BATCH])[:, None, :] + _NEIGHBOURS[None]
                around = wanted(np.unique(pack(around.reshape(-1, 3))))
                found.append(around[(find(self.keys, around) < 0) & (find(keys, around) < 0)])
            return np.unique(np.concatenate(found))

        held = np.concatenate([self.keys[maplet_sums][np.abs(maplet_distance) <= diagonal],
                               keys[np.abs(distance) <= diagonal]])
        for _ in range(int(FADE_VOXELS)):
            missing = missing_about(held)
            if not len(missing):
                break
            more = bent(missing)
            keys = np.concatenate([keys, missing])
            distance, nearest = np.concatenate([distance, more[0]]), np.concatenate([nearest, more[1]])
            order = np.argsort(keys)
            keys, distance, nearest = keys[order], distance[order], nearest[order]
            held = missing[np.abs(more[0]) <= diagonal]
        cols = np.zeros((len(keys), _COLUMNS))
        cols[:, _W] = BASE_WEIGHT
        cols[:, _WD] = BASE_WEIGHT * np.clip(distance, -reach, reach)
        if albedo is not None:
            cols[:, _WA] = BASE_WEIGHT
            cols[:, _A] = BASE_WEIGHT * albedo[nearest]
        return keys, cols, np.ones(len(keys), dtype=np.int64)

    def mesh(self, base: Mesh | None = None) -> Mesh:
        """The zero set of the fused distances as one closed, outward-wound mesh with per-vertex
        albedo (where any contribution had one); with `base`, the places no maplet reached are
        the base's (see the module docstring). Without one, the maplets must enclose the body."""
        if not len(self.keys):
            raise ValueError("nothing fused")
        return body_surface(*extract(self.closed(base)), voxel_km=self.voxel_km)

    def _disagreement(self, points: np.ndarray,
                      distance_to_base: _MeshDistance) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The maplets' points near their surface (km), the base's distance there less theirs
        (delta), and how far each base sample at `points` reaches: the truncation widened by
        the largest delta about it."""
        maplet_sums = self.sums[:, _W] > 0
        maplet_distance = self.sums[maplet_sums, _WD] / self.sums[maplet_sums, _W]
        surface = np.abs(maplet_distance) <= 0.5 * self.truncation_km
        at = unpack(self.keys[maplet_sums][surface]) * self.voxel_km
        delta = distance_to_base(at)[0] - maplet_distance[surface]
        # each base sample's band is widened by the disagreement of the maplets about it, not the
        # body's largest: one far-off maplet would otherwise widen the band everywhere
        fade = FADE_VOXELS * self.voxel_km
        return at, delta, self.truncation_km + _largest_near(points, at, np.abs(delta), fade + self.truncation_km)

    def base_reach(self, base: Mesh, faces: np.ndarray | None = None,
                   within: tuple[np.ndarray, np.ndarray] | None = None) -> float:
        """How far (km) the base's widest band reaches: what `_base_sums` clips its distances at.
        faces: as there; within: the lattice box (lowest, highest index) whose samples count."""
        points, normals, _ = _surface_samples(base, self.voxel_km, faces)
        if not len(points):
            return self.truncation_km
        distance_to_base = _MeshDistance(base, points, normals, self.voxel_km)
        if within is not None:
            cell = np.floor(points / self.voxel_km)
            points = points[in_box(cell, *within)]
        return float(self._disagreement(points, distance_to_base)[2].max(initial=self.truncation_km))

    def closed(self, base: Mesh | None, faces: np.ndarray | None = None, clip_km: float | None = None,
               within: tuple[np.ndarray, np.ndarray] | None = None) -> SparseSums:
        """A copy of the sums with the base's (see `_base_sums`, and its `within`) where no
        maplet reached; without a base, the sums alone."""
        sums = SparseSums(self.voxel_km, self.keys.copy(), self.sums.copy(), self.count.copy())
        if base is not None:
            sums.merge(*self._base_sums(base, faces, clip_km, within), sign=+1, name="the base")
        return sums


def body_surface(vertices: np.ndarray, faces: np.ndarray, albedo: np.ndarray, *, voxel_km: float) -> Mesh:
    """The largest piece of what marching cubes made (vertices in lattice steps, faces, albedo
    per vertex, nan without) as a mesh in km, each vertex without albedo given its nearest's."""
    if not len(faces):
        raise ValueError("the fused distances have no zero crossing")
    return surface_mesh(vertices, faces[largest_piece(len(vertices), faces)], albedo, voxel_km=voxel_km)


def surface_mesh(vertices: np.ndarray, faces: np.ndarray, albedo: np.ndarray, *, voxel_km: float) -> Mesh:
    """The faces of a fused surface (vertices in lattice steps, albedo per vertex, nan without)
    as a mesh in km of the vertices they use, each vertex without albedo given its nearest's."""
    used, faces = compact(len(vertices), faces)
    vertices, albedo = vertices[used], albedo[used]
    return Mesh(vertices * voxel_km, faces, None if np.isnan(albedo).all() else fill_gaps(albedo, vertices))


def grid_for(base: Mesh, *, voxel_km: float, taper_fraction: float) -> VoxelGrid | DistanceGrid:
    """The fusion for maplets of spacing voxel_km over `base`: one closed surface of the whole
    body (DistanceGrid) where its lattice is affordable (MAX_SURFACE_CELLS), else points laid onto
    the base (pwm.fusion.VoxelGrid, pwm.levels.displace), as a site's centimetre maplets on a whole
    asteroid are."""
    if base.face_areas().sum() / voxel_km ** 2 <= MAX_SURFACE_CELLS:
        return DistanceGrid(voxel_km=voxel_km, taper_fraction=taper_fraction)
    return VoxelGrid(voxel_km=voxel_km, taper_fraction=taper_fraction)


class _MeshDistance:
    """Signed distance (km, positive outside) from points to a closed mesh: its size from the
    nearest of dense samples on the faces (to that sample's face plane when the point lies over
    it), its sign from the facing of the first face met along a fixed direction, which does not
    err at concave creases as a face plane's side does."""

    def __init__(self, mesh: Mesh, points: np.ndarray, normals: np.ndarray, spacing_km: float) -> None:
        self.tracer = RayTracer(mesh)
        self.samples = cKDTree(points)
        self.points, self.normals, self.spacing_km = points, normals, spacing_km

    def __call__(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Signed distances (N,) and the index of each point's nearest sample."""
        euclid, nearest = self.samples.query(x)
        plane = np.abs(np.einsum("ij,ij->i", x - self.points[nearest], self.normals[nearest]))
        size = np.where(euclid ** 2 - plane ** 2 <= self.spacing_km ** 2, plane, euclid)
        direction = np.broadcast_to(_INSIDE_RAY, x.shape)
        hits = self.tracer.intersect(x, direction)
        inside = hits.hit & (self.tracer.face_normals[np.where(hits.hit, hits.face, 0)] @ _INSIDE_RAY > 0)
        return np.where(inside, -size, size), nearest


def in_box(index: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Mask of the (N, 3) lattice indices (or positions in lattice steps) within lo..hi, both included."""
    return np.asarray(((index >= lo) & (index <= hi)).all(axis=1))


def _largest_near(points: np.ndarray, at: np.ndarray, values: np.ndarray, radius_km: float) -> np.ndarray:
    """For each of `points`, the largest of `values` (0 without any) at the points `at` within
    about radius_km: binned in cubes of radius_km, each point takes the largest over its cube and
    the 26 about it (so at least everything within radius_km, and nothing beyond 2 sqrt(3) of it)."""
    if not len(at):
        return np.zeros(len(points))
    cells, slot = np.unique(pack(np.floor(at / radius_km).astype(np.int64)), return_inverse=True)
    largest = np.zeros(len(cells))
    np.maximum.at(largest, slot.ravel(), values)
    own = np.floor(points / radius_km).astype(np.int64)
    found = np.zeros(len(points))
    for step in _NEIGHBOURS:
        key = pack(own + step)
        where = np.clip(np.searchsorted(cells, key), 0, len(cells) - 1)
        found = np.maximum(found, np.where(cells[where] == key, largest[where], 0.0))
    return found


def _surface_samples(mesh: Mesh, spacing_km: float,
                     chosen: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Points on every face of `mesh` (of the `chosen` mask's, if given) at most spacing_km apart
    (a barycentric grid per face), their face's unit normal, and the mesh's albedo interpolated
    there (None without one)."""
    tri = mesh.vertices[mesh.faces]
    normals = mesh.face_normals()
    if chosen is not None:
        tri, normals, mesh = tri[chosen], normals[chosen], Mesh(mesh.vertices, mesh.faces[chosen], mesh.albedo)
    longest = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max(axis=1)
    splits = np.maximum(1, np.ceil(longest / spacing_km)).astype(np.int64)
    points, point_normals, albedo = [], [], []
    for k in np.unique(splits):
        faces = np.flatnonzero(splits == k)
        i, j = np.meshgrid(np.arange(k + 1), np.arange(k + 1), indexing="ij")
        keep = i + j <= k
        bary = np.column_stack([i[keep], j[keep], k - i[keep] - j[keep]]) / k
        points.append(np.einsum("bk,fkc->fbc", bary, tri[faces]).reshape(-1, 3))
        point_normals.append(np.repeat(normals[faces], len(bary), axis=0))
        if mesh.albedo is not None:
            albedo.append((mesh.albedo[mesh.faces[faces]] @ bary.T).ravel())
    return (np.vstack(points), np.vstack(point_normals),
            np.concatenate(albedo) if mesh.albedo is not None else None)


def extract(sums: SparseSums) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Marching cubes over the lattice points with weight, block by block: vertices (in lattice
    steps) merged across blocks, faces wound outwards, albedo per vertex (nan without)."""
    index = unpack(sums.keys)
    weight = sums.sums[:, _W]
    valid = weight > 0
    index, s = index[valid], sums.sums[valid]
    distance = s[:, _WD] / s[:, _W]
    # a distance of exactly zero at a lattice point makes degenerate triangles meeting there
    distance[distance == 0.0] = 1e-9
    with np.errstate(invalid="ignore", divide="ignore"):
        albedo = np.where(s[:, _WA] > 1e-9 * s[:, _W], s[:, _A] / s[:, _WA], np.nan)
    block = index // BLOCK
    order = np.lexsort(block.T[::-1])
    index, distance, albedo, block = index[order], distance[order], albedo[order], block[order]
    starts = np.flatnonzero(np.r_[True, (np.diff(block, axis=0) != 0).any(axis=1)])
    lookup = {tuple(b): (a, z) for b, a, z in zip(block[starts], starts, np.r_[starts[1:], len(block)], strict=True)}
    all_vertices, all_faces, all_albedo, n = [], [], [], 0
    for b in lookup:
        origin = np.array(b) * BLOCK
        # the block's points and those of its upper neighbours' first layer, which close its cells
        volume = np.full((BLOCK + 1,) * 3, np.nan)
        shade = np.full((BLOCK + 1,) * 3, np.nan)
        for offset in _CORNERS:
            span = lookup.get(tuple(np.array(b) + offset))
            if span is None:
                continue
            rel = index[span[0]:span[1]] - origin
            fits = (rel <= BLOCK).all(axis=1)
            volume[tuple(rel[fits].T)] = distance[span[0]:span[1]][fits]
            shade[tuple(rel[fits].T)] = albedo[span[0]:span[1]][fits]
        mask = _cube_mask(np.isfinite(volume))
        if not mask.any() or np.nanmin(volume) > 0 or np.nanmax(volume) < 0:
            continue
        filled = np.where(np.isfinite(volume), volume, 1.0)
        try:
            vertices, faces, _, _ = marching_cubes(filled, level=0.0, mask=mask, gradient_direction="descent",
                                                   allow_degenerate=False)
        except RuntimeError:  # no crossing within the cells whose corners all have a distance
            continue
        if not len(faces):
            continue
        all_vertices.append(vertices + origin)
        all_faces.append(faces + n)
        all_albedo.append(_interpolate(shade, vertices))
        n += len(vertices)
    if not all_faces:
        return np.empty((0, 3)), np.empty((0, 3), dtype=np.int64), np.empty(0)
    vertices, faces, albedo = np.vstack(all_vertices), np.vstack(all_faces), np.concatenate(all_albedo)
    # a vertex on a face shared by two blocks was made by both, from the same two values
    _, first, inverse = np.unique(np.round(vertices * 2 ** 20), axis=0, return_index=True, return_inverse=True)
    return vertices[first], uncollapsed(inverse.ravel()[faces]), albedo[first]


def _cube_mask(valid: np.ndarray) -> np.ndarray:
    """The mask marching_cubes takes for the cells whose eight corners are all `valid`: it looks at
    one entry per cell, the cell's upper corner (index + 1 on every axis)."""
    cells = np.ones(tuple(n - 1 for n in valid.shape), dtype=bool)
    for a, b, c in _CORNERS:
        cells &= valid[a:a + cells.shape[0], b:b + cells.shape[1], c:c + cells.shape[2]]
    mask = np.zeros_like(valid)
    mask[1:, 1:, 1:] = cells
    return mask


def _interpolate(values: np.ndarray, at: np.ndarray) -> np.ndarray:
    """values (a 3-D array, nan where missing) linearly interpolated at fractional indices `at`,
    from the finite ones of the two lattice points of the edge each vertex lies on."""
    lo = np.floor(at).astype(np.int64)
    frac = at - lo
    hi = np.minimum(lo + (frac > 0), np.array(values.shape) - 1)
    a, b = values[tuple(lo.T)], values[tuple(hi.T)]
    t = frac.max(axis=1)
    out = np.where(np.isnan(a), b, np.where(np.isnan(b), a, (1 - t) * a + t * b))
    return out
