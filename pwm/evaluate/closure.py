"""Whether a mesh is one closed surface: watertight, consistently wound outwards, and free of
self-intersections (what a DSK needs, and what navigation's intercepts assume).

Watertightness and winding are trimesh's tests. Self-intersections are counted here: two faces
that share no vertex intersect when an edge of one crosses the other (Moller-Trumbore on the
pairs of faces near enough to touch); faces that share a vertex are not tested. Lengths in km.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from pwm.mesh import Mesh

_CHUNK = 200_000


@dataclass(frozen=True)
class Closure:
    """watertight: every edge in exactly two faces; winding_consistent: each such edge used once
    each way; outward: positive signed volume; self_intersections: pairs of faces sharing no
    vertex that cross; volume_km3: the signed volume."""

    watertight: bool
    winding_consistent: bool
    outward: bool
    self_intersections: int
    volume_km3: float

    @property
    def closed(self) -> bool:
        return self.watertight and self.winding_consistent and self.outward and not self.self_intersections


def closure(mesh: Mesh) -> Closure:
    """The closed-surface checks of `mesh`."""
    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    volume = float(tm.volume)
    return Closure(watertight=bool(tm.is_watertight), winding_consistent=bool(tm.is_winding_consistent),
                   outward=volume > 0, self_intersections=self_intersections(mesh), volume_km3=volume)


def self_intersections(mesh: Mesh) -> int:
    """Number of pairs of faces that share no vertex and cross."""
    tri = mesh.vertices[mesh.faces]
    centroids = tri.mean(axis=1)
    radius = np.linalg.norm(tri - centroids[:, None], axis=2).max(axis=1)
    pairs = _near_pairs(centroids, radius)
    shared = (mesh.faces[pairs[:, 0], :, None] == mesh.faces[pairs[:, 1], None, :]).any(axis=(1, 2))
    pairs = pairs[~shared]
    crossing = 0
    for start in range(0, len(pairs), _CHUNK):
        a, b = pairs[start:start + _CHUNK].T
        hit = _edges_cross(tri[a], tri[b]) | _edges_cross(tri[b], tri[a])
        crossing += int(hit.sum())
    return crossing


def _near_pairs(centres: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """(P, 2) pairs i < j of balls (centres, radius) that overlap. Balls are sorted into octaves
    of radius first, each pair of octaves searched within their largest radii: one search within
    the largest radius of all would pair every small face of a dense site with every other within
    a coarse face's size of it."""
    octave = np.floor(np.log2(np.maximum(radius, 1e-300))).astype(np.int64)
    groups = [np.flatnonzero(octave == k) for k in np.unique(octave)]
    trees = [cKDTree(centres[g]) for g in groups]
    reach = [float(radius[g].max()) for g in groups]
    found = []
    for i, (gi, ti) in enumerate(zip(groups, trees, strict=True)):
        for j in range(i, len(groups)):
            if i == j:
                local = ti.query_pairs(2.0 * reach[i], output_type="ndarray")
                pairs = gi[local]
            else:
                near = ti.sparse_distance_matrix(trees[j], reach[i] + reach[j], output_type="ndarray")
                pairs = np.column_stack([gi[near["i"]], groups[j][near["j"]]])
            found.append(pairs.reshape(-1, 2))
    pairs = np.sort(np.vstack(found), axis=1) if found else np.empty((0, 2), dtype=np.int64)
    a, b = pairs.T
    return pairs[np.linalg.norm(centres[a] - centres[b], axis=1) <= radius[a] + radius[b]]


def _edges_cross(edges_of: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(P,) whether any edge of the first triangles crosses the second's interior (Moller-Trumbore,
    strictly inside the segment and the triangle)."""
    eps = 1e-9
    v0, e1, e2 = triangles[:, 0], triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0]
    out = np.zeros(len(triangles), dtype=bool)
    for k in range(3):
        origin = edges_of[:, k]
        direction = edges_of[:, (k + 1) % 3] - origin
        p = np.cross(direction, e2)
        det = np.einsum("ij,ij->i", e1, p)
        ok = np.abs(det) > eps * np.linalg.norm(e1, axis=1) * np.linalg.norm(direction, axis=1) ** 2
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        s = origin - v0
        u = np.einsum("ij,ij->i", s, p) * inv
        q = np.cross(s, e1)
        v = np.einsum("ij,ij->i", direction, q) * inv
        t = np.einsum("ij,ij->i", e2, q) * inv
        out |= ok & (u > eps) & (v > eps) & (u + v < 1 - eps) & (t > eps) & (t < 1 - eps)
    return out
