"""A mesh too big for one file, cut into tiles of at most so many faces, and joined back.

The faces are parted by recursive bisection of their centroids, each part cut across its widest
side at its median face until it holds at most `max_faces`: tiles of nearly equal size that
follow the surface whatever the body's shape. A tile keeps the indices its faces and vertices
have in the whole, so joining the tiles gives back the very mesh that was cut (`join`); a
vertex on a border between tiles is in each of them, at the same place.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from pwm.mesh import Mesh


@dataclass(frozen=True)
class MeshTile:
    """One tile: its faces' and vertices' indices in the whole mesh (ascending) and its own
    mesh over those vertices (km, body-fixed; albedo and sigma where the whole has them)."""

    faces: np.ndarray
    vertices: np.ndarray
    mesh: Mesh

    def box_km(self) -> tuple[list[float], list[float]]:
        """The tile's bounding box: its lowest and highest x, y, z (km)."""
        return self.mesh.vertices.min(axis=0).tolist(), self.mesh.vertices.max(axis=0).tolist()


def face_parts(mesh: Mesh, *, max_faces: int) -> list[np.ndarray]:
    """The faces of `mesh` parted into groups of at most `max_faces` (each ascending), by
    recursive bisection of their centroids at the median across the widest side."""
    if max_faces < 1:
        raise ValueError(f"a tile holds at least one face, not {max_faces}")
    centroids = mesh.vertices[mesh.faces].mean(axis=1)
    parts, pending = [], [np.arange(len(mesh.faces))]
    while pending:
        faces = pending.pop()
        if len(faces) <= max_faces:
            parts.append(np.sort(faces))
            continue
        points = centroids[faces]
        axis = int(np.argmax(np.ptp(points, axis=0)))
        half = len(faces) // 2
        order = np.argpartition(points[:, axis], half)
        # the second half first onto the stack, so that the tiles come in the bisection's order
        pending += [faces[order[half:]], faces[order[:half]]]
    return parts


def split(mesh: Mesh, *, max_faces: int) -> list[MeshTile]:
    """`mesh` cut into tiles of at most `max_faces` faces (`face_parts`); vertices of no face
    go with the first tile."""
    tiles = []
    alone = np.flatnonzero(np.bincount(mesh.faces.ravel(), minlength=len(mesh.vertices)) == 0)
    for number, faces in enumerate(face_parts(mesh, max_faces=max_faces)):
        used = np.unique(mesh.faces[faces])
        if number == 0:
            used = np.union1d(used, alone)
        tiles.append(MeshTile(faces=faces, vertices=used, mesh=Mesh(
            vertices=mesh.vertices[used], faces=np.searchsorted(used, mesh.faces[faces]),
            albedo=None if mesh.albedo is None else mesh.albedo[used],
            sigma=None if mesh.sigma is None else mesh.sigma[used])))
    return tiles


def join(tiles: Iterable[MeshTile], *, vertices: int, faces: int) -> Mesh:
    """The whole mesh of `vertices` vertices and `faces` faces that `tiles` were cut from
    (`split`). ValueError where the tiles leave a face or a vertex out."""
    points = np.full((vertices, 3), np.nan)
    triangles = np.full((faces, 3), -1, dtype=np.int64)
    albedo: np.ndarray | None = None
    sigma: np.ndarray | None = None
    for tile in tiles:
        points[tile.vertices] = tile.mesh.vertices
        triangles[tile.faces] = tile.vertices[tile.mesh.faces]
        if tile.mesh.albedo is not None:
            albedo = np.full(vertices, np.nan) if albedo is None else albedo
            albedo[tile.vertices] = tile.mesh.albedo
        if tile.mesh.sigma is not None:
            sigma = np.full(vertices, np.nan) if sigma is None else sigma
            sigma[tile.vertices] = tile.mesh.sigma
    if (triangles < 0).any() or np.isnan(points).any():
        raise ValueError("the tiles do not hold every face and vertex of the mesh")
    return Mesh(vertices=points, faces=triangles, albedo=albedo, sigma=sigma)


def face_labels(tiles: Iterable[MeshTile], *, faces: int) -> np.ndarray:
    """Each face's tile, by the tiles' order (faces, int64)."""
    labels = np.full(faces, -1, dtype=np.int64)
    for number, tile in enumerate(tiles):
        labels[tile.faces] = number
    return labels
