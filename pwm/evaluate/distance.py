"""Exact point-to-surface distances against a triangle mesh (body-fixed frame, km).

Candidate triangles are the one-rings of a point's nearest vertices (a kd-tree), nearest first.
The answer is certified exact: a triangle that fits in a ball of radius rho and whose vertices all
lie at least D from the point is at least sqrt(D^2 - rho^2) away (|x - p|^2 - |x - centre|^2 is
affine in x, so over the triangle it is smallest at a vertex). Vertex rings are therefore visited
while D^2 < best^2 + rho^2, fetching more neighbours where needed. Faces are grouped by size into
levels, each with its own tree and rho, so that a few large faces (steep flanks on a height field,
a coarse part of a mixed mesh) do not make every query search wide.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.spatial import cKDTree

from pwm.mesh import Mesh, edge_keys

# Region codes of the closest point on a triangle (a, b, c): vertices, then edges ab, bc, ca
# (edge j joins corners j and j+1), then the interior.
_VERTEX_A, _VERTEX_B, _VERTEX_C, _EDGE_AB, _EDGE_BC, _EDGE_CA, _INTERIOR = range(7)


def _dot(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Dot products of (3, N) component arrays."""
    return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]


def _closest_on_triangles(
    p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Closest point on each triangle (a, b, c) to each point p (Ericson 2005, Real-Time
    Collision Detection, 5.1.5). All inputs are (3, N) component arrays (km) because per-component
    rows vectorise faster than (N, 3). Returns the (3, N) closest points and region codes."""
    ab, ac = b - a, c - a
    ap, bp, cp = p - a, p - b, p - c
    d1, d2 = _dot(ab, ap), _dot(ac, ap)
    d3, d4 = _dot(ab, bp), _dot(ac, bp)
    d5, d6 = _dot(ab, cp), _dot(ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    conditions = [
        (d1 <= 0) & (d2 <= 0),
        (d3 >= 0) & (d4 <= d3),
        (vc <= 0) & (d1 >= 0) & (d3 <= 0),
        (d6 >= 0) & (d5 <= d6),
        (vb <= 0) & (d2 >= 0) & (d6 <= 0),
        (va <= 0) & (d4 >= d3) & (d5 >= d6),
    ]
    region = np.select(
        conditions, [_VERTEX_A, _VERTEX_B, _EDGE_AB, _VERTEX_C, _EDGE_CA, _EDGE_BC], _INTERIOR
    )
    # Zero denominators only occur in branches that np.select does not pick, or on degenerate
    # triangles, where a zero parameter still gives a point of the triangle.
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ab = np.nan_to_num(d1 / (d1 - d3))
        t_ca = np.nan_to_num(d2 / (d2 - d6))
        t_bc = np.nan_to_num((d4 - d3) / ((d4 - d3) + (d5 - d6)))
        t_b = np.nan_to_num(vb / (va + vb + vc))
        t_c = np.nan_to_num(vc / (va + vb + vc))
    zero, one = np.zeros_like(d1), np.ones_like(d1)
    v = np.select(conditions, [zero, one, t_ab, zero, zero, 1 - t_bc], t_b)
    w = np.select(conditions, [zero, zero, zero, one, t_ca, t_bc], t_c)
    return a + v * ab + w * ac, region


@dataclass(frozen=True)
class _Level:
    """Faces of similar size: a kd-tree over their vertices, the faces around each tree vertex
    (ring_face[ring_start[i]:ring_start[i + 1]]), the largest squared bounding radius of each
    vertex's faces (km^2) and of all of them."""

    tree: cKDTree
    ring_start: np.ndarray
    ring_face: np.ndarray
    ring_rho2: np.ndarray
    rho2: float


class ClosestPoint:
    """Closest points on a mesh, built once and queried many times.

    k: nearest vertices fetched per point at first (more where the certificate needs them);
    chunk: points per batch, small enough for the per-triangle arrays to stay in the CPU cache.
    """

    def __init__(self, mesh: Mesh, *, k: int = 8, chunk: int = 8192) -> None:
        self.mesh = mesh
        self.k = k
        self.chunk = chunk
        self._vertices_t = np.ascontiguousarray(mesh.vertices.T)
        rho = _bounding_radii(mesh)
        typical = np.median(rho)
        with np.errstate(divide="ignore"):
            size_class = np.floor(np.log2(rho / typical)) if typical > 0 else np.zeros_like(rho)
        size_class = np.maximum(size_class, 0).astype(np.int64)
        self._levels = [
            _build_level(mesh, np.flatnonzero(size_class == c), rho)
            for c in np.unique(size_class)
        ]
        # Points are processed in spatial order so that neighbouring queries touch the same
        # parts of the mesh and tree (a large speed-up on big meshes).
        self._sort_cell = 16.0 * max(float(typical), 1e-12)

    def query(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Unsigned distance (km), closest surface point (body-fixed, km) and face index for each
        of the (N, 3) points."""
        distance, closest, face, _ = self._query(points)
        return distance, closest, face

    def signed_distance(self, points: np.ndarray) -> np.ndarray:
        """Distance (km) to the surface, positive on the side the outward normals point to.

        The sign uses angle-weighted pseudonormals at vertices and edges (Baerentzen & Aanaes
        2005), so it is right also where the closest point is on an edge or vertex, provided the
        mesh is a consistently oriented manifold there.
        """
        points = np.asarray(points, float).reshape(-1, 3)
        distance, closest, face, region = self._query(points)
        normal = self.face_normals[face]
        at_vertex = region <= _VERTEX_C
        vertex = self.mesh.faces[face[at_vertex], region[at_vertex]]
        normal[at_vertex] = self._vertex_pseudonormals[vertex]
        at_edge = (region >= _EDGE_AB) & (region <= _EDGE_CA)
        neighbour = self._edge_neighbours[face[at_edge], region[at_edge] - _EDGE_AB]
        normal[at_edge] += np.where(neighbour[:, None] >= 0, self.face_normals[neighbour], 0.0)
        outside = np.einsum("ij,ij->i", points - closest, normal) >= 0
        return np.where(outside, distance, -distance)

    @cached_property
    def face_normals(self) -> np.ndarray:
        """Unit outward normals of all faces, (M, 3)."""
        return self.mesh.face_normals()

    @cached_property
    def _vertex_pseudonormals(self) -> np.ndarray:
        """Sum of the normals of the faces around each vertex weighted by their angle there."""
        faces = self.mesh.faces
        corners = [np.take(self._vertices_t, faces[:, j], axis=1) for j in range(3)]
        out = np.zeros((3, len(self.mesh.vertices)))
        for j in range(3):
            e1 = corners[(j + 1) % 3] - corners[j]
            e2 = corners[(j + 2) % 3] - corners[j]
            cosine = _dot(e1, e2) / np.sqrt(_dot(e1, e1) * _dot(e2, e2))
            angle = np.arccos(np.clip(np.nan_to_num(cosine), -1.0, 1.0))
            for axis in range(3):
                out[axis] += np.bincount(
                    faces[:, j], weights=angle * self.face_normals[:, axis], minlength=out.shape[1]
                )
        return out.T

    @cached_property
    def _edge_neighbours(self) -> np.ndarray:
        """Face across edge j (corners j, j+1) of each face, -1 on a boundary, (M, 3)."""
        faces = self.mesh.faces
        key = edge_keys(faces, len(self.mesh.vertices)).ravel()
        order = np.argsort(key)
        pair = np.flatnonzero(key[order][1:] == key[order][:-1])
        out = np.full(len(key), -1)
        out[order[pair]] = order[pair + 1] // 3
        out[order[pair + 1]] = order[pair] // 3
        return out.reshape(-1, 3)

    def _query(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        points = np.asarray(points, float).reshape(-1, 3)
        n = len(points)
        order = np.lexsort(np.floor(points / self._sort_cell).T[::-1])
        p = points[order]
        d2 = np.full(n, np.inf)
        closest = np.empty((3, n))
        face = np.empty(n, dtype=np.int64)
        region = np.empty(n, dtype=np.int64)
        for s in range(0, n, self.chunk):
            sl = slice(s, s + self.chunk)
            best = (d2[sl], closest[:, sl], face[sl], region[sl])
            for level in self._levels:
                self._search(level, p[sl], best)
        unsort = np.empty(n, dtype=np.int64)
        unsort[order] = np.arange(n)
        return np.sqrt(d2[unsort]), closest.T[unsort], face[unsort], region[unsort]

    def _search(self, level: _Level, p: np.ndarray, best: tuple[np.ndarray, ...]) -> None:
        """Improve `best` (views: squared distance, closest point, face, region) for points p
        with the faces of one level.

        Where no face has been seen yet, the nearest vertex's ring gives a first bound. Vertex
        j's ring can then hold a closer face only if |v_j - p|^2 < best^2 + rho_j^2, rho_j the
        largest radius in that ring (a face all of whose vertices fail is farther than best).
        A point is finished once its k-th vertex fails with the level's largest radius;
        otherwise more vertices are fetched. Vertices beyond every point's reach are not fetched.
        """
        n_tree = level.tree.n
        reach = float(np.sqrt(np.max(best[0] + level.rho2)))
        active = np.arange(len(p))
        done_k, k = 0, min(self.k, n_tree)
        while active.size:
            vertex_d, nearest = level.tree.query(p[active], k=k, distance_upper_bound=reach)
            vertex_d = vertex_d.reshape(len(active), k) ** 2
            # Neighbours beyond reach come back as index n_tree at infinite distance.
            nearest = np.minimum(nearest.reshape(len(active), k), n_tree - 1)
            if done_k == 0:
                fresh = np.isinf(best[0][active])
                self._test_rings(level, p, active[fresh], nearest[fresh, 0], best)
            bound = best[0][active, None] + level.ring_rho2[nearest[:, done_k:]]
            needed = vertex_d[:, done_k:] < bound
            if done_k == 0:
                needed[fresh, 0] = False
            # Row-major nonzero keeps each point's rings together, as _test_rings needs.
            rows, cols = np.nonzero(needed)
            self._test_rings(level, p, active[rows], nearest[rows, done_k + cols], best)
            if k == n_tree:
                break
            active = active[vertex_d[:, -1] < best[0][active] + level.rho2]
            done_k, k = k, min(4 * k, n_tree)

    def _test_rings(
        self,
        level: _Level,
        p: np.ndarray,
        point: np.ndarray,
        vertex: np.ndarray,
        best: tuple[np.ndarray, ...],
    ) -> None:
        """Test the faces around tree vertex[i] against p[point[i]] (point non-decreasing) and
        keep improvements."""
        if len(point) == 0:
            return
        start = level.ring_start[vertex]
        count = level.ring_start[vertex + 1] - start
        total = np.cumsum(count)
        offset = np.arange(total[-1]) - np.repeat(total - count, count)
        candidate = level.ring_face[np.repeat(start, count) + offset]
        owner = np.repeat(point, count)
        corners = np.take(self.mesh.faces, candidate, axis=0)
        a, b, c = (np.take(self._vertices_t, corners[:, i], axis=1) for i in range(3))
        q = np.take(p, owner, axis=0).T
        x, region = _closest_on_triangles(q, a, b, c)
        d2 = _dot(q - x, q - x)

        first = np.flatnonzero(np.r_[True, owner[1:] != owner[:-1]])
        point = owner[first]
        group_best = np.minimum.reduceat(d2, first)
        # Any of several equally close candidates will do.
        pick = np.empty(len(first), dtype=np.int64)
        winner = np.flatnonzero(d2 == np.repeat(group_best, np.diff(np.r_[first, len(d2)])))
        pick[np.searchsorted(first, winner, side="right") - 1] = winner
        better = group_best < best[0][point]
        pick, target = pick[better], point[better]
        best[0][target] = group_best[better]
        best[1][:, target] = x[:, pick]
        best[2][target] = candidate[pick]
        best[3][target] = region[pick]


def _build_level(mesh: Mesh, face_ids: np.ndarray, rho: np.ndarray) -> _Level:
    corner_vertex = mesh.faces[face_ids].ravel()
    counts = np.bincount(corner_vertex, minlength=len(mesh.vertices))
    tree_vertex = np.flatnonzero(counts)
    ring_start = np.concatenate([[0], np.cumsum(counts[tree_vertex])])
    ring_face = face_ids[np.argsort(corner_vertex, kind="stable") // 3]
    ring_rho2 = np.maximum.reduceat(rho[ring_face] ** 2, ring_start[:-1])
    return _Level(
        tree=cKDTree(mesh.vertices[tree_vertex]),
        ring_start=ring_start,
        ring_face=ring_face,
        ring_rho2=ring_rho2,
        rho2=float(ring_rho2.max()),
    )


def _bounding_radii(mesh: Mesh) -> np.ndarray:
    """Radius of the smallest ball around each face, km: half the longest edge for right or
    obtuse triangles, the circumradius otherwise."""
    corners = [mesh.vertices[mesh.faces[:, j]] for j in range(3)]
    edge2 = np.sort(
        np.stack([np.sum((corners[(j + 1) % 3] - corners[j]) ** 2, axis=1) for j in range(3)]),
        axis=0,
    )
    area2 = np.sum(np.cross(corners[1] - corners[0], corners[2] - corners[0]) ** 2, axis=1)
    obtuse = edge2[2] >= edge2[0] + edge2[1]
    with np.errstate(divide="ignore", invalid="ignore"):
        # R = abc / (4 area), and |cross| = 2 area.
        circum = np.sqrt(edge2[0] * edge2[1] * edge2[2] / (4.0 * area2))
    return np.where(obtuse, 0.5 * np.sqrt(edge2[2]), circum)
