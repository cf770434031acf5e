"""Triangle meshes in the body-fixed frame (km) with optional per-vertex albedo."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Mesh:
    """A triangle mesh.

    vertices: (N, 3) float64, body-fixed frame, km.
    faces: (M, 3) int64 vertex indices, counter-clockwise seen from outside.
    albedo: (N,) float64 normal albedo per vertex, or None.
    """

    vertices: np.ndarray
    faces: np.ndarray
    albedo: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.vertices = np.ascontiguousarray(self.vertices, dtype=np.float64)
        self.faces = np.ascontiguousarray(self.faces, dtype=np.int64)
        if self.albedo is not None:
            self.albedo = np.ascontiguousarray(self.albedo, dtype=np.float64)
            if self.albedo.shape != (len(self.vertices),):
                raise ValueError("albedo must have one value per vertex")

    def require_albedo(self) -> np.ndarray:
        """The per-vertex albedo (N,); ValueError for a mesh that has none."""
        if self.albedo is None:
            raise ValueError("the mesh has no per-vertex albedo")
        return self.albedo

    def face_normals(self) -> np.ndarray:
        """Unit outward normals per face, (M, 3)."""
        v = self.vertices[self.faces]
        n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)

    def vertex_normals(self) -> np.ndarray:
        """Area-weighted unit normals per vertex, (N, 3)."""
        v = self.vertices[self.faces]
        n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        n_vert = len(self.vertices)
        idx = self.faces.ravel()
        # bincount is an order of magnitude faster than np.add.at on millions of faces
        out = np.column_stack([np.bincount(idx, weights=np.repeat(n[:, c], 3), minlength=n_vert) for c in range(3)])
        return out / np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-300)

    def face_areas(self) -> np.ndarray:
        """Area per face, km^2."""
        v = self.vertices[self.faces]
        return 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)

    def mean_edge_length(self) -> float:
        """Mean edge length, km."""
        v = self.vertices[self.faces]
        e = np.linalg.norm(v - np.roll(v, 1, axis=1), axis=2)
        return float(e.mean())


def grid_faces(ny: int, nx: int) -> np.ndarray:
    """(2 (ny - 1)(nx - 1), 3) faces of a grid of ny x nx vertices stored row by row, two
    triangles per cell, counter-clockwise seen from the side the rows and columns make
    right-handed (a height field's outside, +z)."""
    corner = np.arange(ny * nx, dtype=np.int64).reshape(ny, nx)[:-1, :-1]
    faces = np.empty((ny - 1, nx - 1, 2, 3), dtype=np.int64)
    for k, offset in enumerate((0, 1, nx + 1, 0, nx + 1, nx)):
        faces[:, :, k // 3, k % 3] = corner + offset
    return faces.reshape(-1, 3)


def compact(n_vertices: int, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(mask of the n_vertices vertices the faces use, faces renumbered over those vertices)."""
    used = np.zeros(n_vertices, dtype=bool)
    used[faces] = True
    return used, (np.cumsum(used) - 1)[faces]


def surface_points(mesh: Mesh, count: int, rng: np.random.Generator) -> np.ndarray:
    """`count` points (count, 3) drawn uniformly over the mesh's area."""
    areas = mesh.face_areas()
    faces = rng.choice(len(areas), size=count, p=areas / areas.sum())
    u, v = rng.random(count), rng.random(count)
    flip = u + v > 1.0
    u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
    corners = mesh.vertices[mesh.faces[faces]]
    return corners[:, 0] + u[:, None] * (corners[:, 1] - corners[:, 0]) + v[:, None] * (corners[:, 2] - corners[:, 0])


def refine_faces(mesh: Mesh, selected: np.ndarray, *, max_edge_km: float) -> tuple[Mesh, np.ndarray]:
    """The mesh with its selected faces (M,) bool split until none of their edges is longer than
    max_edge_km, and which faces of the result came from selected ones. Conforming (red-green):
    an edge split for a selected face is split for its neighbour too, which takes two or four
    triangles, so a closed, manifold mesh stays closed and manifold. Albedo of a new vertex is
    the mean of its edge's ends."""
    vertices, faces, albedo = mesh.vertices, mesh.faces, mesh.albedo
    selected = np.asarray(selected, dtype=bool)
    while True:
        a, b = faces.ravel(), np.roll(faces, -1, axis=1).ravel()
        n = np.int64(len(vertices))
        keys, inverse = np.unique(np.minimum(a, b) * n + np.maximum(a, b), return_inverse=True)
        edges = np.stack([keys // n, keys % n], axis=1)
        edge_of = inverse.reshape(-1, 3)  # edge k of a face joins its corners k and k + 1
        long = np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=1) > max_edge_km
        split = np.zeros(len(edges), dtype=bool)
        split[edge_of[selected][long[edge_of[selected]]]] = True
        if not split.any():
            return Mesh(vertices, faces, albedo), selected
        # a face with two edges split has its third split too, so each face is halved or quartered
        while True:
            two = split[edge_of].sum(axis=1) == 2
            if not two.any():
                break
            split[edge_of[two]] = True
        index = np.full(len(edges), -1, dtype=np.int64)
        index[split] = len(vertices) + np.arange(split.sum())
        ends = edges[split]
        vertices = np.vstack([vertices, 0.5 * (vertices[ends[:, 0]] + vertices[ends[:, 1]])])
        if albedo is not None:
            albedo = np.concatenate([albedo, 0.5 * (albedo[ends[:, 0]] + albedo[ends[:, 1]])])
        mid = index[edge_of]  # (M, 3) the midpoint of each face's edge k, or -1
        count = split[edge_of].sum(axis=1)
        a, b, c = faces.T
        m0, m1, m2 = mid.T
        quarter = count == 3
        new = [faces[count == 0]]
        new.append(np.concatenate([np.stack([a, m0, m2], 1)[quarter], np.stack([m0, b, m1], 1)[quarter],
                                   np.stack([m2, m1, c], 1)[quarter], np.stack([m0, m1, m2], 1)[quarter]]))
        # halved: from the split edge's midpoint to the opposite corner
        for k, (p, q, r, m) in enumerate(((a, b, c, m0), (b, c, a, m1), (c, a, b, m2))):
            half = (count == 1) & (mid[:, k] >= 0)
            new.append(np.concatenate([np.stack([p, m, r], 1)[half], np.stack([m, q, r], 1)[half]]))
        chosen = [selected[count == 0], np.tile(selected[quarter], 4)]
        for k in range(3):
            half = (count == 1) & (mid[:, k] >= 0)
            chosen.append(np.tile(selected[half], 2))
        faces, selected = np.concatenate(new).astype(np.int64), np.concatenate(chosen)
