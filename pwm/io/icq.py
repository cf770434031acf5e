"""Gaskell's ICQ (implicitly connected quadrilateral) shape format, as SPC's SHAPE.TXT.

The body is a cube of six faces, each a (q+1) x (q+1) grid of vertices (body-fixed, km);
vertices on shared cube edges and corners appear once per face. A grid is indexed
[face, j, i, xyz]; the file has q on the first line, then the vertices face by face, j-major,
i fastest. Face 0 is +Z, faces 1-4 go round the equator (-Y, -X, +Y, +X) and face 5 is -Z.
Seen from outside, i runs to the right and j down, faces 1-4 with +Z up; face 0 has +Y up
(towards face 3) and face 5 has -Y up (towards face 1).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pwm.mesh import Mesh
from pwm.raytrace import RayTracer

# Per face: cube-face centre, then the unit steps of i and of j (cube half-width 1).
_FACES = np.array([
    [[0, 0, 1], [1, 0, 0], [0, -1, 0]],
    [[0, -1, 0], [1, 0, 0], [0, 0, -1]],
    [[-1, 0, 0], [0, -1, 0], [0, 0, -1]],
    [[0, 1, 0], [-1, 0, 0], [0, 0, -1]],
    [[1, 0, 0], [0, 1, 0], [0, 0, -1]],
    [[0, 0, -1], [1, 0, 0], [0, 1, 0]],
])


def cube_points(q: int) -> np.ndarray:
    """Integer cube coordinates of the ICQ vertices, (6, q+1, q+1, 3), on the cube of half-width
    q: shared vertices get identical triples, and direction = triple / |triple|."""
    steps = 2 * np.arange(q + 1) - q
    centre, di, dj = (_FACES[:, k][:, None, None, :] for k in range(3))
    return q * centre + steps[None, None, :, None] * di + steps[None, :, None, None] * dj


def write_icq(path: str | Path, vertices_grid: np.ndarray) -> None:
    """Write an ICQ file from a (6, q+1, q+1, 3) grid (km): q as I12, vertices as 3F12.5
    (a space is kept between values that overflow the 12 columns)."""
    grid = _checked(vertices_grid)
    with open(path, "w", encoding="ascii") as fh:
        fh.write(f"{grid.shape[1] - 1:12d}\n")
        np.savetxt(fh, grid.reshape(-1, 3), fmt=" %11.5f", delimiter="")


def read_icq(path: str | Path) -> np.ndarray:
    """Read an ICQ file into a (6, q+1, q+1, 3) vertex grid (km)."""
    with open(path, encoding="ascii") as fh:
        q = int(fh.readline())
        values = np.array(fh.read().split(), dtype=np.float64)
    if values.size != 6 * (q + 1) ** 2 * 3:
        raise ValueError(f"{path}: q = {q} needs {6 * (q + 1) ** 2} vertices, "
                         f"found {values.size / 3:g}")
    return values.reshape(6, q + 1, q + 1, 3)


def mesh_to_icq(mesh: Mesh, q: int) -> np.ndarray:
    """Resample a closed mesh, star-shaped about the body-fixed origin, onto the ICQ grid of
    size q: each vertex is where the ray from the origin along its cube direction first meets
    the surface (km). Raises ValueError where a ray misses (a mesh not around the origin)."""
    if q < 1:
        raise ValueError(f"q must be at least 1, got {q}")
    points, inverse = np.unique(cube_points(q).reshape(-1, 3), axis=0, return_inverse=True)
    directions = points / np.linalg.norm(points, axis=1, keepdims=True)
    origins = np.zeros_like(directions)
    tracer = RayTracer(mesh)
    hits = tracer.intersect(origins, directions)
    if not hits.hit.all():
        raise ValueError(f"{np.count_nonzero(~hits.hit)} ICQ rays from the origin miss the mesh")
    return tracer.hit_points(origins, directions, hits)[inverse.ravel()].reshape(6, q + 1, q + 1, 3)


def icq_to_mesh(vertices_grid: np.ndarray) -> Mesh:
    """Triangle mesh of an ICQ grid: 6 q^2 + 2 vertices (each shared vertex once, at its first
    copy in file order), each quad split into two triangles along its (j, i)-(j+1, i+1)
    diagonal, counter-clockwise seen from outside."""
    grid = _checked(vertices_grid)
    q = grid.shape[1] - 1
    _, first, inverse = np.unique(cube_points(q).reshape(-1, 3), axis=0, return_index=True,
                                  return_inverse=True)
    index = inverse.reshape(6, q + 1, q + 1)
    corner = index[:, :-1, :-1], index[:, :-1, 1:], index[:, 1:, 1:], index[:, 1:, :-1]
    a, b, c, d = (k.ravel() for k in corner)  # (j, i), (j, i+1), (j+1, i+1), (j+1, i)
    faces = np.concatenate([np.column_stack([a, d, c]), np.column_stack([a, c, b])])
    return Mesh(grid.reshape(-1, 3)[first], faces)


def _checked(vertices_grid: np.ndarray) -> np.ndarray:
    grid = np.asarray(vertices_grid, dtype=np.float64)
    if grid.ndim != 4 or grid.shape[0] != 6 or grid.shape[1] != grid.shape[2] \
            or grid.shape[3] != 3 or grid.shape[1] < 2:
        raise ValueError(f"an ICQ grid is (6, q+1, q+1, 3) with q >= 1, got {grid.shape}")
    return grid
