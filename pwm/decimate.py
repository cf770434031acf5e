"""Mesh decimation by quadric edge collapse (fast-simplification), keeping the albedo."""

from __future__ import annotations

import fast_simplification
import numpy as np
from scipy.spatial import cKDTree

from pwm.mesh import Mesh


def decimate(mesh: Mesh, target_faces: int) -> Mesh:
    """Reduce `mesh` to about `target_faces` faces (km, same frame) by quadric edge collapse.

    Each original vertex carries its albedo to the nearest kept vertex, which takes the
    area-weighted mean of what it receives (a kept vertex that receives nothing takes its
    nearest original vertex's albedo). Not thread-safe: the library keeps one mesh in a global.
    """
    if not 4 <= target_faces < len(mesh.faces):
        raise ValueError(f"target_faces must be in [4, {len(mesh.faces)}), got {target_faces}")
    vertices, faces = fast_simplification.simplify(mesh.vertices, mesh.faces,
                                                   target_count=int(target_faces))
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
