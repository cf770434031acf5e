"""Batched ray casting against a triangle mesh with Embree (single precision).

Coordinates stay body-centred (km) so float32 keeps ~10 micrometre resolution on a
kilometre-sized body. Callers offset ray origins off the surface (see `surface_offset`).

A mesh's scene is built once, by its first tracer, and shared by every tracer of a mesh of the
same vertices and faces arrays (the same Mesh, or one made of its arrays, as with its albedo
dropped) in the process until they are freed: a tracer costs nothing to make again.
"""

from __future__ import annotations

import threading
import weakref
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
from embreex import rtcore_scene
from embreex.mesh_construction import TriangleMesh
from scipy.spatial import cKDTree

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


class _Scene:
    """The Embree scene of a mesh's vertices and faces arrays and what its tracers derive from
    them (normals, surface offset); it holds neither the arrays nor the mesh."""

    def __init__(self, mesh: Mesh) -> None:
        self.embree = rtcore_scene.EmbreeScene()
        TriangleMesh(
            self.embree,
            np.ascontiguousarray(mesh.vertices, dtype=np.float32),
            np.ascontiguousarray(mesh.faces, dtype=np.int32),
        )
        # embreex commits (builds the hierarchy) on a scene's first query: make that query here,
        # under the cache's lock, so that threads sharing the scene never commit it together.
        self.embree.run(np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32), query="OCCLUDED")
        self.derived: dict[str, np.ndarray | float] = {}
        self.finalizers: list[weakref.finalize] = []


_SCENES: dict[tuple[int, int], _Scene] = {}  # by id() of live vertices and faces arrays
_SCENES_LOCK = threading.Lock()


def _scene_of(mesh: Mesh) -> _Scene:
    """The mesh's shared scene, built on first use (one build even when threads ask at once)."""
    key = (id(mesh.vertices), id(mesh.faces))
    with _SCENES_LOCK:
        scene = _SCENES.get(key)
        if scene is None:
            scene = _SCENES[key] = _Scene(mesh)
            # the entry goes as either array is freed, before its id can be another object's
            scene.finalizers = [weakref.finalize(array, _forget, key) for array in (mesh.vertices, mesh.faces)]
        return scene


def _forget(key: tuple[int, int]) -> None:
    # Called by the garbage collector, perhaps while this thread holds the lock: no lock here
    # (dict.pop is atomic), and none needed: with one of its arrays gone, no one asks for the key.
    scene = _SCENES.pop(key, None)
    if scene is not None:
        for finalizer in scene.finalizers:
            finalizer.detach()


class RayTracer:
    """Ray queries on one mesh, through the Embree scene its tracers share (module docstring);
    thread-safe, but not shared across processes.

    Its mesh's vertices and faces arrays must not be changed in place once traced: their scene
    would go stale. A changed mesh is made of new arrays (or given them: `mesh.vertices = ...`),
    which get a scene of their own. (They are not made read-only: compiled libraries such as
    fast_simplification refuse read-only arrays.)
    """

    def __init__(self, mesh: Mesh) -> None:
        self.mesh = mesh
        self._scene = _scene_of(mesh)

    @cached_property
    def vertex_tree(self) -> cKDTree:
        """A KD-tree of the mesh's vertices, made on first use: the vertices about a place."""
        return cKDTree(self.mesh.vertices)

    def intersect(self, origins: np.ndarray, directions: np.ndarray) -> Hits:
        """First hit for each ray. directions need not be unit; t is in units of |direction|."""
        n = len(origins)
        t = np.full(n, np.inf)
        face = np.full(n, -1, dtype=np.int64)
        u = np.zeros(n)
        v = np.zeros(n)
        for s in range(0, n, CHUNK):
            e = min(n, s + CHUNK)
            out = self._scene.embree.run(
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
            out = self._scene.embree.run(
                np.ascontiguousarray(origins[s:e], dtype=np.float32),
                np.ascontiguousarray(directions[s:e], dtype=np.float32),
                dists=np.ascontiguousarray(d),
                query="OCCLUDED",
            )
            result[s:e] = out >= 0
        return result

    @property
    def face_normals(self) -> np.ndarray:
        return self._derived("face_normals", self.mesh.face_normals)

    @property
    def vertex_normals(self) -> np.ndarray:
        return self._derived("vertex_normals", self.mesh.vertex_normals)

    @property
    def offset(self) -> float:
        """Distance (km) to lift ray origins off this mesh's surface (see `surface_offset`)."""
        return self._derived("offset", lambda: surface_offset(self.mesh))

    def _derived(self, name: str, compute: Callable[[], Any]) -> Any:
        """`compute()` once per mesh, kept with its scene; arrays read-only, as they are shared."""
        derived = self._scene.derived
        if name not in derived:
            value = compute()
            if isinstance(value, np.ndarray):
                value.flags.writeable = False
            derived.setdefault(name, value)
        return derived[name]

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
