"""Fusion across levels of maplets (METHOD.md 6): the sums of each level of node spacing
(pwm.tiling.level_of) kept apart, each at its own voxel size, and composed from the coarsest
level to the finest, so that each place takes the finest level that covers it.

The coarsest level is fused over the base: one closed surface of the body where its lattice is
affordable, else a region stitched into the base (pwm.volume.grid_for chooses). A finer level is
kept as points (pwm.fusion.VoxelGrid) and laid onto the surface made so far (`displace`): that
surface's faces about the level's region are split until they are as fine as its voxels
(pwm.mesh.refine_faces, conforming) and each vertex there is moved along its normal to the
level's own surface, fully inside the region and fading to nothing over BLEND_VOXELS inside its
border. So a site's centimetre maplets sit in the survey's closed surface without a step, and
the result stays closed, manifold and consistently wound. (A level made while it was the
coarsest, and later under a coarser one, may be a DistanceGrid: its closed surface is then made
over the surface below, which fills where its maplets do not reach.) A maplet's revision is
subtracted from its own level's sums exactly as it was added. Lengths in km.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from pwm.fusion import VoxelGrid, border_vertices
from pwm.maplets import MapletGrid
from pwm.mesh import Mesh, refine_faces
from pwm.raytrace import Hits, RayTracer
from pwm.tiling import level_of
from pwm.volume import DistanceGrid, grid_for
from pwm.weights import raised_cosine

Grid = VoxelGrid | DistanceGrid
BATCH = 64
"""Maplets of one level held at a time while they are added."""
BLEND_VOXELS = 12.0
"""Width, in a finer level's voxels, of the band inside its border over which it fades into the
surface below it."""
MAX_EDGE_VOXELS = float(np.sqrt(2.0))
"""Longest edge, in a finer level's voxels, of the faces laid onto it: about as many vertices as
the level has lattice points over the same ground."""
REACH_VOXELS = 4.0
"""How far, in the next coarser level's voxels, a finer level's surface is looked for along the
normals of the surface below it: about how far the coarser level may be off."""


@dataclass
class LevelGrids:
    """The fusion sums of each level, by level. taper_fraction: the maplets' overlap."""

    taper_fraction: float
    grids: dict[int, Grid] = field(default_factory=dict)

    def add_all(self, maplets: Iterable[MapletGrid], *, base: Mesh) -> None:
        """Add the maplets to their levels' sums, a batch of each level at a time, so that they
        need not be held together. A level's first maplet sets its voxel size, and `base` (the
        body) whether the level is one closed surface or a stitched region."""
        pending: dict[int, list[MapletGrid]] = {}
        for maplet in maplets:
            level = int(level_of(maplet.spacing_km))
            if level not in self.grids:
                coarsest = level > max(self.grids, default=level - 1)
                self.grids[level] = (grid_for(base, voxel_km=maplet.spacing_km, taper_fraction=self.taper_fraction)
                                     if coarsest else VoxelGrid(maplet.spacing_km, taper_fraction=self.taper_fraction))
            pending.setdefault(level, []).append(maplet)
            if len(pending[level]) >= BATCH:
                self.grids[level].add_all(pending.pop(level))
        for level, batch in pending.items():
            self.grids[level].add_all(batch)

    def subtract(self, maplet: MapletGrid) -> None:
        """Take a maplet's contribution out of its level's sums, exactly as it was added."""
        level = int(level_of(maplet.spacing_km))
        if level not in self.grids:
            raise ValueError(f"maplet {maplet.name} is of level {level}, which these sums do not hold")
        self.grids[level].subtract(maplet)

    def mesh(self, base: Mesh) -> Mesh:
        """The fused surface: `base` with each level fused over it, coarsest first (see the
        module docstring)."""
        surface, below = base, None
        for level in sorted(self.grids, reverse=True):
            grid = self.grids[level]
            if not len(grid.keys):
                continue
            if below is None or isinstance(grid, DistanceGrid):
                surface = grid.mesh(surface)
            else:
                surface = displace(surface, grid, reach_km=REACH_VOXELS * below)
            below = grid.voxel_km
        return surface

    @property
    def voxels(self) -> int:
        """The lattice points of all levels."""
        return sum(len(grid.keys) for grid in self.grids.values())

    def describe(self) -> dict[str, dict]:
        """Per level (as text), coarsest first: how it makes the surface ("closed"; "stitched" into
        the base; "laid" onto the levels below), its voxel size (m) and lattice points."""
        out: dict[str, dict] = {}
        for level, grid in sorted(self.grids.items(), reverse=True):
            # as `mesh` does: an empty level makes nothing, the first level with sums is stitched
            below = any(d["voxels"] for d in out.values())
            surface = "closed" if isinstance(grid, DistanceGrid) else "laid" if below else "stitched"
            out[str(level)] = {"surface": surface, "voxel_m": grid.voxel_km * 1e3, "voxels": len(grid.keys)}
        return out


def displace(surface: Mesh, grid: VoxelGrid, *, reach_km: float) -> Mesh:
    """`surface` with the finer level of `grid` laid onto it (see the module docstring): the
    faces with a vertex that finds the level's surface along its normal within reach_km either
    way split to MAX_EDGE_VOXELS; the vertices that find it moved to it, in full at BLEND_VOXELS
    and more inside its border, fading to nothing at it; albedo likewise. A face of `surface`
    across the level's border with no vertex over the level stays whole, and the level is laid
    only up to it: its edges shared with split faces are split too, so it ramps from them to its
    own corners, without a step."""
    level = grid.mesh()
    tracer = RayTracer(level)
    over = _crossing(tracer, surface.vertices, surface.vertex_normals(), reach_km)[0]
    refined, chosen = refine_faces(surface, over[surface.faces].any(axis=1),
                                   max_edge_km=MAX_EDGE_VOXELS * grid.voxel_km)
    moved = np.unique(refined.faces[chosen])
    normals = refined.vertex_normals()[moved]
    found, shift, hits = _crossing(tracer, refined.vertices[moved], normals, reach_km)
    at = refined.vertices[moved[found]] + shift[found, None] * normals[found]
    edge = level.vertices[border_vertices(level.faces)]
    inside = cKDTree(edge).query(at)[0] if len(edge) else np.full(len(at), np.inf)
    share = raised_cosine(inside / (BLEND_VOXELS * grid.voxel_km))
    vertices = refined.vertices.copy()
    index = moved[found]
    vertices[index] += (share * shift[found])[:, None] * normals[found]
    albedo = refined.albedo
    if albedo is not None and level.albedo is not None:
        albedo = albedo.copy()
        albedo[index] += share * (tracer.interpolate(level.albedo, hits)[found] - albedo[index])
    return Mesh(vertices, refined.faces, albedo)


def _crossing(tracer: RayTracer, points: np.ndarray, normals: np.ndarray,
              reach_km: float) -> tuple[np.ndarray, np.ndarray, Hits]:
    """Where the tracer's surface crosses each point's normal line within reach_km either way
    (the first crossing from below): whether it does, the signed shift along the normal (km),
    and the hits."""
    hits = tracer.intersect(points - reach_km * normals, normals)
    return hits.hit & (hits.t <= 2.0 * reach_km), hits.t - reach_km, hits
