"""Triangle meshes in the body-fixed frame (km) with optional per-vertex albedo."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree


@dataclass
class Mesh:
    """A triangle mesh.

    vertices: (N, 3) float64, body-fixed frame, km.
    faces: (M, 3) int64 vertex indices, counter-clockwise seen from outside.
    albedo: (N,) float64 normal albedo per vertex, or None.
    sigma: (N,) float64 1-sigma height per vertex, km (NaN where nothing says), or None
    (pwm.uncertainty).
    """

    vertices: np.ndarray
    faces: np.ndarray
    albedo: np.ndarray | None = None
    sigma: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.vertices = np.ascontiguousarray(self.vertices, dtype=np.float64)
        self.faces = np.ascontiguousarray(self.faces, dtype=np.int64)
        if self.albedo is not None:
            self.albedo = np.ascontiguousarray(self.albedo, dtype=np.float64)
            if self.albedo.shape != (len(self.vertices),):
                raise ValueError("albedo must have one value per vertex")
        if self.sigma is not None:
            self.sigma = np.ascontiguousarray(self.sigma, dtype=np.float64)
            if self.sigma.shape != (len(self.vertices),):
                raise ValueError("sigma must have one value per vertex")

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


def pieces(n_vertices: int, faces: np.ndarray) -> np.ndarray:
    """(M,) the edge-connected piece of each face, numbered 0, 1, ... (as many as there are)."""
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n_vertices, n_vertices))
    _, labels = connected_components(graph, directed=False)
    return np.unique(labels[faces[:, 0]], return_inverse=True)[1].reshape(-1)


def uncollapsed(faces: np.ndarray) -> np.ndarray:
    """The faces (M, 3) whose three corners are three vertices: a weld can leave a face with two
    corners one vertex, and no area."""
    return faces[~(faces == np.roll(faces, 1, axis=1)).any(axis=1)]


def welded(mesh: Mesh, *, tolerance: float = 1e-9) -> Mesh:
    """`mesh` with the vertices that coincide, within `tolerance` of its extent, made one (the
    first of each), faces renumbered, and the faces so left with two corners one vertex (no
    area) dropped: a plate model's pole is often one vertex per plate. The vertices no face uses
    then are kept, so that albedo and numbering stay as they were."""
    if not len(mesh.vertices):
        return mesh
    extent = float(np.ptp(mesh.vertices, axis=0).max())
    pairs = cKDTree(mesh.vertices).query_pairs(tolerance * extent, output_type="ndarray")
    if not len(pairs):
        return mesh
    n = len(mesh.vertices)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    _, first = np.unique(labels, return_index=True)
    return Mesh(mesh.vertices, uncollapsed(first[labels][mesh.faces]), mesh.albedo)


def largest_piece(n_vertices: int, faces: np.ndarray) -> np.ndarray:
    """Mask of the faces of the largest edge-connected piece (by faces)."""
    face_piece = pieces(n_vertices, faces)
    return face_piece == np.bincount(face_piece).argmax()


def surface_points(mesh: Mesh, count: int, rng: np.random.Generator) -> np.ndarray:
    """`count` points (count, 3) drawn uniformly over the mesh's area."""
    areas = mesh.face_areas()
    faces = rng.choice(len(areas), size=count, p=areas / areas.sum())
    u, v = rng.random(count), rng.random(count)
    flip = u + v > 1.0
    u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
    corners = mesh.vertices[mesh.faces[faces]]
    return corners[:, 0] + u[:, None] * (corners[:, 1] - corners[:, 0]) + v[:, None] * (corners[:, 2] - corners[:, 0])



def face_keys(mesh: Mesh) -> np.ndarray:
    """(M,) one opaque key per face, its corners' coordinates in order: a face of one mesh is
    found, exactly, in another by its key (np.isin), whatever the numbering."""
    return np.ascontiguousarray(mesh.vertices[mesh.faces].reshape(-1, 9)).view("V72").ravel()


def edge_keys(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """(M, 3) undirected edge ids, edge k of a face joining its corners k and k + 1."""
    a, b = faces, np.roll(faces, -1, axis=1)
    return np.minimum(a, b) * np.int64(n_vertices) + np.maximum(a, b)


def border_edges(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """Sorted keys (`edge_keys` over n_vertices) of the edges used by one face only."""
    uniq, counts = np.unique(edge_keys(faces, n_vertices), return_counts=True)
    return uniq[counts == 1]


def split_edges(mesh: Mesh, split: np.ndarray) -> tuple[Mesh, np.ndarray]:
    """One red-green refinement step: the face edges marked in `split` (M, 3; edge k joins corners
    k and k + 1) split at their midpoints, in every face that has them; a face left with two or
    three split edges has all three split and goes 1-to-4 (red), one with one goes 1-to-2 (green).
    Midpoints lie on the old facets, so the surface is unchanged and stays conforming (no
    T-junctions); albedo of a midpoint is the mean of its edge's ends. Also returns each new
    face's parent face (untouched faces first, then red children, then green ones)."""
    n = len(mesh.vertices)
    keys = edge_keys(mesh.faces, n)
    uniq, inv = np.unique(keys, return_inverse=True)
    inv = inv.reshape(keys.shape)
    split_edge = np.zeros(len(uniq), dtype=bool)
    split_edge[inv[np.asarray(split, dtype=bool)]] = True
    while True:
        count = split_edge[inv].sum(axis=1)
        two = count == 2
        if not two.any():
            break
        split_edge[inv[two]] = True
    red, green = count == 3, count == 1
    ends = np.stack([uniq // n, uniq % n], axis=1)[split_edge]
    mid_id = np.full(len(uniq), -1, dtype=np.int64)
    mid_id[split_edge] = n + np.arange(split_edge.sum())
    vertices = np.vstack([mesh.vertices, 0.5 * (mesh.vertices[ends[:, 0]] + mesh.vertices[ends[:, 1]])])
    albedo = None
    if mesh.albedo is not None:
        albedo = np.concatenate([mesh.albedo, 0.5 * (mesh.albedo[ends[:, 0]] + mesh.albedo[ends[:, 1]])])
    f, m = mesh.faces[red], mid_id[inv[red]]
    a, b, c = f.T
    ab, bc, ca = m.T
    children = [np.stack(t, axis=1) for t in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))]
    f, m = mesh.faces[green], mid_id[inv[green]]
    k = np.argmax(m >= 0, axis=1)
    rows = np.arange(len(f))
    p, q, o, mid = f[rows, k], f[rows, (k + 1) % 3], f[rows, (k + 2) % 3], m[rows, k]
    children += [np.stack([p, mid, o], axis=1), np.stack([mid, q, o], axis=1)]
    untouched = count == 0
    faces = np.vstack([mesh.faces[untouched]] + children)
    parent = np.concatenate([np.flatnonzero(untouched), np.tile(np.flatnonzero(red), 4),
                             np.tile(np.flatnonzero(green), 2)])
    return Mesh(vertices, faces, albedo), parent


def refine_faces(mesh: Mesh, selected: np.ndarray, *, max_edge_km: float) -> tuple[Mesh, np.ndarray]:
    """The mesh with its selected faces (M,) bool split (`split_edges`, conforming) until none of
    their edges is longer than max_edge_km, and each face's face of `mesh` (its vertices keep
    their indices): a closed, manifold mesh stays closed and manifold."""
    origin = np.arange(len(mesh.faces))
    selected = np.asarray(selected, dtype=bool)
    while True:
        chosen = selected[origin]
        tri = mesh.vertices[mesh.faces]
        long = chosen[:, None] & (np.linalg.norm(np.roll(tri, -1, axis=1) - tri, axis=2) > max_edge_km)
        if not long.any():
            return mesh, origin
        mesh, parent = split_edges(mesh, long)
        origin = origin[parent]
