"""Batched ray casting against a triangle mesh with Embree (single precision).

Coordinates stay body-centred (km) so float32 keeps ~10 micrometre resolution on a
kilometre-sized body. Callers offset ray origins off the surface (see `surface_offset`).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from embreex import rtcore_scene
from embreex.mesh_construction import TriangleMesh

from pwm.mesh import Mesh

CHUNK = 2_000_000


@dataclass
class Hits:
    """First hits of a ray batch. t: distance along the unit direction (km, inf on miss);
    face: triangle index (-1 on miss); u, v: barycentric weights of the face's vertices 1 and 2."""

    t: np.ndarray
    face: np.ndarray
    u: np.ndarray
    v: np.ndarray

    @property
    def hit(self) -> np.ndarray:
        return self.face >= 0


class RayTracer:
    """An Embree scene over one mesh; thread-compatible but not shared across processes.

    The mesh must not change while the tracer lives: its normals and surface offset are cached.
    """

    def __init__(self, mesh: Mesh) -> None:
        self.mesh = mesh
        self._scene = rtcore_scene.EmbreeScene()
        TriangleMesh(
            self._scene,
            np.ascontiguousarray(mesh.vertices, dtype=np.float32),
            np.ascontiguousarray(mesh.faces, dtype=np.int32),
        )

    def intersect(self, origins: np.ndarray, directions: np.ndarray) -> Hits:
        """First hit for each ray. directions need not be unit; t is in units of |direction|."""
        n = len(origins)
        t = np.full(n, np.inf)
        face = np.full(n, -1, dtype=np.int64)
        u = np.zeros(n)
        v = np.zeros(n)
        for s in range(0, n, CHUNK):
            e = min(n, s + CHUNK)
            out = self._scene.run(
                np.ascontiguousarray(origins[s:e], dtype=np.float32),
                np.ascontiguousarray(directions[s:e], dtype=np.float32),
                output=1,
            )
            prim = out["primID"].astype(np.int64)
            ok = prim >= 0
            face[s:e] = np.where(ok, prim, -1)
            t[s:e] = np.where(ok, out["tfar"], np.inf)
            u[s:e] = out["u"]
            v[s:e] = out["v"]
        return Hits(t=t, face=face, u=u, v=v)

    def occluded(self, origins: np.ndarray, directions: np.ndarray, max_t: np.ndarray | float = np.inf) -> np.ndarray:
        """True where a ray hits the mesh before distance `max_t` (units of |direction|)."""
        n = len(origins)
        tmax = np.broadcast_to(np.asarray(max_t, dtype=np.float64), (n,))
        result = np.zeros(n, dtype=bool)
        for s in range(0, n, CHUNK):
            e = min(n, s + CHUNK)
            d = np.minimum(tmax[s:e], np.finfo(np.float32).max).astype(np.float32)
            out = self._scene.run(
                np.ascontiguousarray(origins[s:e], dtype=np.float32),
                np.ascontiguousarray(directions[s:e], dtype=np.float32),
                dists=np.ascontiguousarray(d),
                query="OCCLUDED",
            )
            result[s:e] = out >= 0
        return result

    @cached_property
    def face_normals(self) -> np.ndarray:
        return self.mesh.face_normals()

    @cached_property
    def vertex_normals(self) -> np.ndarray:
        return self.mesh.vertex_normals()

    @cached_property
    def offset(self) -> float:
        """Distance (km) to lift ray origins off this mesh's surface (see `surface_offset`)."""
        return surface_offset(self.mesh)

    def hit_points(self, origins: np.ndarray, directions: np.ndarray, hits: Hits) -> np.ndarray:
        """Hit positions recomputed in float64 from the face and barycentrics (km), nan on miss."""
        f = np.where(hits.hit, hits.face, 0)
        tri = self.mesh.vertices[self.mesh.faces[f]]
        w0 = 1.0 - hits.u - hits.v
        p = w0[:, None] * tri[:, 0] + hits.u[:, None] * tri[:, 1] + hits.v[:, None] * tri[:, 2]
        p[~hits.hit] = np.nan
        return p

    def interpolate(self, values: np.ndarray, hits: Hits) -> np.ndarray:
        """Interpolate per-vertex values (N,) or (N, k) at the hits with the barycentrics."""
        f = np.where(hits.hit, hits.face, 0)
        idx = self.mesh.faces[f]
        w0 = 1.0 - hits.u - hits.v
        vals = np.asarray(values)
        if vals.ndim == 1:
            return w0 * vals[idx[:, 0]] + hits.u * vals[idx[:, 1]] + hits.v * vals[idx[:, 2]]
        return w0[:, None] * vals[idx[:, 0]] + hits.u[:, None] * vals[idx[:, 1]] + hits.v[:, None] * vals[idx[:, 2]]


def surface_offset(mesh: Mesh) -> float:
    """Distance (km) to lift ray origins off the surface: above float32 noise, far below the facets."""
    scale = float(np.abs(mesh.vertices).max())
    noise = float(64 * np.finfo(np.float32).eps * scale)  # computed in float32, as always
    return max(1e-3 * mesh.mean_edge_length(), noise)
