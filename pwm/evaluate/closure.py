"""Whether a mesh is one closed surface: watertight, consistently wound outwards, one piece, and
free of self-intersections (what a DSK needs, and what navigation's intercepts and a polyhedral
gravity model assume); and the mass properties such a surface encloses.

Watertightness, winding and mass properties are trimesh's. Self-intersections are counted here: two faces
that share no vertex intersect when an edge of one crosses the other (Moller-Trumbore on the
pairs of faces near enough to touch); faces that share a vertex are not tested. Lengths in km.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from pwm.mesh import Mesh, edge_keys, pieces, welded

_CHUNK = 200_000
# faces whose near pairs are found at once: a bound on the pairs held (a million: about 0.6 GiB)
_SLAB_FACES = 1_000_000


@dataclass(frozen=True)
class Closure:
    """watertight: every edge in exactly two faces; winding_consistent: each such edge used once
    each way; outward: positive signed volume; self_intersections: pairs of faces sharing no
    vertex that cross, counted only on a watertight mesh (None otherwise: open whatever they
    are, and a torn surface's layers make the count the costliest check); volume_km3: the signed
    volume; boundary_edges: edges in one face only; nonmanifold_edges: edges in more than two
    faces; components: edge-connected pieces; intersections_counted: whether self_intersections
    was counted (it is the costliest check: tens of seconds for a million faces; a closed surface
    whose self-intersections were not counted is closed in every other respect)."""

    watertight: bool
    winding_consistent: bool
    outward: bool
    self_intersections: int | None
    volume_km3: float
    boundary_edges: int
    nonmanifold_edges: int
    components: int
    intersections_counted: bool = True

    @property
    def closed(self) -> bool:
        crossing = self.self_intersections != 0 if self.intersections_counted else not self.watertight
        return self.watertight and self.winding_consistent and self.outward and not crossing and self.components == 1

    def describe(self) -> str:
        """"closed", or "open: " and what makes it not closed (one line, for messages and headers)."""
        if self.closed:
            return "closed"
        flaws = [f"{n} {what}" for n, what in (
            (self.boundary_edges, "boundary edges"), (self.nonmanifold_edges, "non-manifold edges"),
            (self.self_intersections, "self-intersections")) if n]
        if self.components != 1:
            flaws.append(f"{self.components} components")
        if not self.winding_consistent:
            flaws.append("inconsistent winding")
        if not self.outward:
            flaws.append("wound inwards")
        return "open: " + ", ".join(flaws)


@dataclass(frozen=True)
class MassProperties:
    """What a closed surface encloses, for a uniform density: volume_km3; centre_km: the centre of
    figure (3,) in the mesh's body-fixed frame; inertia_km5: the inertia tensor (3, 3) about the
    centre of figure, axes those of the frame, per unit density (times a density in kg/km^3:
    kg km^2); area_km2: the surface's area."""

    volume_km3: float
    centre_km: np.ndarray
    inertia_km5: np.ndarray
    area_km2: float


def closure(mesh: Mesh, *, count_intersections: bool = True) -> Closure:
    """The closed-surface checks of `mesh`, its coincident vertices taken as one (pwm.mesh.welded);
    without count_intersections, all but the self-intersections (Closure.intersections_counted)."""
    mesh = welded(mesh)
    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    volume = float(tm.volume)
    _, uses = np.unique(edge_keys(mesh.faces, len(mesh.vertices)), return_counts=True)
    watertight = bool(tm.is_watertight)
    return Closure(watertight=watertight, winding_consistent=bool(tm.is_winding_consistent),
                   outward=volume > 0,
                   self_intersections=self_intersections(mesh) if watertight and count_intersections else None,
                   intersections_counted=watertight and count_intersections, volume_km3=volume,
                   boundary_edges=int((uses == 1).sum()), nonmanifold_edges=int((uses > 2).sum()),
                   components=int(pieces(len(mesh.vertices), mesh.faces).max(initial=-1)) + 1)


def mass_properties(mesh: Mesh) -> MassProperties:
    """The mass properties of the closed surface `mesh` (km, body-fixed; see MassProperties).
    ValueError for a mesh that is not watertight or wound inwards: what it encloses is undefined."""
    mesh = welded(mesh)
    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    if not (tm.is_watertight and tm.is_winding_consistent) or tm.volume <= 0:
        raise ValueError("the mesh encloses no volume: it is not watertight and wound outwards")
    properties = tm.mass_properties
    return MassProperties(volume_km3=float(properties.volume), centre_km=np.asarray(properties.center_mass),
                          inertia_km5=np.asarray(properties.inertia), area_km2=float(tm.area))


def self_intersections(mesh: Mesh, *, owned: np.ndarray | None = None) -> int:
    """Number of pairs of faces that share no vertex and cross; with `owned` (a mask of the
    faces), only the pairs with an owned face (a part of a surface with the faces about it:
    pwm.blocks.block_crossings). The faces are taken in slabs of _SLAB_FACES along the axis
    they spread most on, each with the faces near enough to cross its own, so that the near
    pairs held at a time stay bounded whatever the mesh's size; a pair is counted by the slab
    of its first face in that order."""
    tri = mesh.vertices[mesh.faces]
    centroids = tri.mean(axis=1)
    radius = np.linalg.norm(tri - centroids[:, None], axis=2).max(axis=1)
    axis = int(np.argmax(np.ptp(centroids, axis=0))) if len(centroids) else 0
    order = np.argsort(centroids[:, axis], kind="stable")
    along = centroids[order, axis]
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    halo = 2.0 * float(radius.max(initial=0.0))  # two faces cross only within their radii's sum
    crossing = 0
    for start in range(0, len(order), _SLAB_FACES):
        end = min(start + _SLAB_FACES, len(order))
        first = int(np.searchsorted(along, along[start] - halo, side="left"))
        last = int(np.searchsorted(along, along[end - 1] + halo, side="right"))
        members = order[first:last]
        pairs = members[_near_pairs(centroids[members], radius[members])]
        owner = np.minimum(rank[pairs[:, 0]], rank[pairs[:, 1]])
        pairs = pairs[(owner >= start) & (owner < end)]
        if owned is not None:
            pairs = pairs[owned[pairs[:, 0]] | owned[pairs[:, 1]]]
        shared = (mesh.faces[pairs[:, 0], :, None] == mesh.faces[pairs[:, 1], None, :]).any(axis=(1, 2))
        pairs = pairs[~shared]
        for chunk in range(0, len(pairs), _CHUNK):
            a, b = pairs[chunk:chunk + _CHUNK].T
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
