"""Mesh decimation by quadric edge collapse (fast-simplification), keeping the albedo, and a
closed surface closed."""

from __future__ import annotations

import fast_simplification
import numpy as np
import trimesh
from scipy.spatial import cKDTree

from pwm.evaluate.closure import self_intersections
from pwm.mesh import Mesh, compact, edge_keys, welded

MAX_VOLUME_CHANGE = 0.005
"""The most a decimated closed surface's volume may differ from the input's (relative)."""
MAX_MOVED_VOLUME = 0.05
"""The most a collapse may change the volume by and have it restored by moving the vertices: on
a mesh much denser in places (a site's centimetre faces on a body of metre ones) the library's
default aggressiveness can halve a body while keeping it closed, which no move mends."""
ATTEMPTS = tuple((agg, scale) for agg in (7.0, 4.0, 2.0, 1.0) for scale in (1.0, 1.05, 1.1))
"""The collapses tried, in turn, on a closed surface until one leaves it closed, uncrossed and of
its volume: the library's aggressiveness (its default first; lower collapses more carefully)
and the target's factor. A
collapse that joins two vertices with more than two neighbours in common pinches the surface
(an edge in four faces); which collapses do depends on both."""


def decimate(mesh: Mesh, target_faces: int, *, keep_closed: bool = True) -> Mesh:
    """Reduce `mesh` to about `target_faces` faces (km, same frame) by quadric edge collapse.

    With keep_closed (for what is measured or exported: volumes, DSKs, closed meshes), a
    watertight, consistently wound input comes out so, and free of self-intersections where
    a collapse allows: the collapse sometimes folds two faces back to back (the same corners,
    opposite windings), which are dropped; its vertices then move along their normals by the one
    distance that restores the input's volume (`_with_volume`), unless that makes faces cross;
    where an edge is left in other than two faces, or faces cross, the collapse is made again
    otherwise (ATTEMPTS), as where its volume is off by more than MAX_VOLUME_CHANGE. The first
    closed one within it and without crossings is taken, else the closed one nearest the volume
    (what is wrong with it for the caller's checks to tell), else ValueError. Without it (for
    what is only drawn), the first collapse is taken as it comes, its folds dropped: on a site's
    millions of faces the checks take many minutes that a picture does not need. Each original
    vertex carries its albedo to the nearest kept vertex, which takes the area-weighted mean of
    what it receives (a kept vertex that receives nothing takes its nearest original vertex's
    albedo). Not thread-safe: the library keeps one mesh in a global.
    """
    if not 4 <= target_faces < len(mesh.faces):
        raise ValueError(f"target_faces must be in [4, {len(mesh.faces)}), got {target_faces}")
    closed = keep_closed and _closed(welded(mesh).faces, len(mesh.vertices))
    volume = _volume(mesh) if closed else 0.0
    best: tuple[float, Mesh] | None = None
    for agg, scale in ATTEMPTS:
        target = min(int(target_faces * scale), len(mesh.faces) - 1)
        vertices, faces = fast_simplification.simplify(mesh.vertices, mesh.faces, target_count=target, agg=agg)
        # a collapse may leave two vertices where one is (a pinch the checks would miss, and
        # which the move below would tear): one, as pwm.evaluate.closure takes them
        joined = welded(Mesh(vertices, _without_folds(faces)))
        used, faces = compact(len(vertices), joined.faces)
        made = Mesh(vertices[used], faces)
        if not closed:
            break
        if not _closed(made.faces, len(made.vertices)):
            continue
        lost = abs(_volume(made) / volume - 1.0)
        if best is None or lost < best[0]:
            best = (lost, made)
        # the move restores the volume, but may cross a sliver's faces: then the collapse as made
        options = ([Mesh(_with_volume(made, volume), made.faces)] if lost <= MAX_MOVED_VOLUME else []) + [made]
        clean = next((m for m in options if abs(_volume(m) / volume - 1.0) <= MAX_VOLUME_CHANGE
                      and not self_intersections(m)), None)
        if clean is not None:
            made = clean
            break
    else:
        if best is None:
            raise ValueError(f"no collapse to about {target_faces} faces keeps the closed surface closed")
        made = best[1]
    vertices, faces = made.vertices, made.faces
    if mesh.albedo is None:
        return Mesh(vertices, faces)
    _, receiver = cKDTree(vertices).query(mesh.vertices)
    weight = np.bincount(mesh.faces.ravel(), weights=np.repeat(mesh.face_areas(), 3),
                         minlength=len(mesh.vertices))
    total = np.bincount(receiver, weights=weight, minlength=len(vertices))
    carried = np.bincount(receiver, weights=weight * mesh.albedo, minlength=len(vertices))
    _, nearest = cKDTree(mesh.vertices).query(vertices)
    albedo = np.where(total > 0, carried / np.where(total > 0, total, 1.0), mesh.albedo[nearest])
    return Mesh(vertices, faces, albedo)


def _volume(mesh: Mesh) -> float:
    return float(trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).volume)


def _with_volume(mesh: Mesh, volume_km3: float) -> np.ndarray:
    """The vertices moved along their normals by the one distance that gives the closed `mesh` the
    volume volume_km3 (to first order, the change over the area; twice): the collapse cuts
    corners, which shrinks a body, by more the fewer faces are left."""
    vertices = mesh.vertices
    for _ in range(2):
        moved = Mesh(vertices, mesh.faces)
        offset = (volume_km3 - _volume(moved)) / float(moved.face_areas().sum())
        vertices = vertices + offset * moved.vertex_normals()
    return vertices


def _closed(faces: np.ndarray, n_vertices: int) -> bool:
    """Whether every edge is in two faces, once each way (watertight, consistently wound)."""
    directed = faces * np.int64(n_vertices) + np.roll(faces, -1, axis=1)
    _, uses = np.unique(edge_keys(faces, n_vertices), return_counts=True)
    return bool(len(faces)) and bool((uses == 2).all()) and len(np.unique(directed)) == directed.size


def _without_folds(faces: np.ndarray) -> np.ndarray:
    """The faces less those whose corners another face has too (two faces folded back to back,
    or a face repeated): both go, which leaves the surface as it was around them."""
    _, inverse, counts = np.unique(np.sort(faces, axis=1), axis=0, return_inverse=True, return_counts=True)
    return faces[counts[inverse.reshape(-1)] == 1]
