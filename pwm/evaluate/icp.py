"""Rigid registration of points to a surface: point-to-plane ICP (Chen & Medioni 1992).

Each iteration pairs every point with its exact closest point on the target triangles and solves
the linearised least squares for a small rotation and translation that move the points onto the
tangent planes there. Body-fixed frame, km.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from pwm.evaluate.distance import ClosestPoint
from pwm.mesh import Mesh


@dataclass(frozen=True)
class RigidTransform:
    """x -> rotation @ x + translation; rotation (3, 3), translation (3,) km."""

    rotation: np.ndarray
    translation: np.ndarray

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Transform (N, 3) points, km."""
        return np.asarray(points, float) @ self.rotation.T + self.translation


def register(
    source_points: np.ndarray,
    target: Mesh | ClosestPoint,
    *,
    max_iterations: int = 50,
    tolerance_km: float = 1e-9,
    max_distance_km: float | None = None,
) -> RigidTransform:
    """The rigid transform that moves source_points (N, 3, km) onto the target surface.

    target: the surface as a Mesh, or a ClosestPoint already built on it (reused, not rebuilt).
    Pairs farther apart than max_distance_km are left out of each step (None keeps all).
    Iterates until the step moves no point more than tolerance_km, or max_iterations.
    Directions the surface does not constrain (e.g. sliding along a plane) are left unchanged.
    """
    surface = target if isinstance(target, ClosestPoint) else ClosestPoint(target)
    source = np.asarray(source_points, float).reshape(-1, 3)
    rotation, translation = np.eye(3), np.zeros(3)
    for _ in range(max_iterations):
        moved = source @ rotation.T + translation
        distance, closest, face = surface.query(moved)
        keep = np.ones(len(moved), bool) if max_distance_km is None else distance <= max_distance_km
        if keep.sum() < 6:
            raise ValueError("fewer than 6 point pairs within max_distance_km")
        step_rotation, step_translation, step_size = _point_to_plane_step(
            moved[keep], closest[keep], surface.face_normals[face[keep]]
        )
        rotation = step_rotation @ rotation
        translation = step_rotation @ translation + step_translation
        if step_size <= tolerance_km:
            break
    return RigidTransform(rotation=rotation, translation=translation)


def _point_to_plane_step(
    points: np.ndarray, closest: np.ndarray, normals: np.ndarray
) -> tuple[np.ndarray, np.ndarray, float]:
    """Rotation, translation (km) and largest point displacement (km) of one linearised step.

    The rotation is taken about the points' centroid, scaled by their extent, so that the six
    unknowns are comparably conditioned; the minimum-norm solution leaves unconstrained
    directions alone.
    """
    centre = points.mean(axis=0)
    arm = points - centre
    extent = max(float(np.sqrt((arm**2).sum(axis=1).max())), 1e-12)
    # n . (p + w x r + t - c) = 0 with n . (w x r) = w . (r x n)
    design = np.hstack([np.cross(arm, normals) / extent, normals])
    residual = np.einsum("ij,ij->i", normals, closest - points)
    solution = np.linalg.lstsq(design, residual, rcond=1e-10)[0]
    omega, shift = solution[:3] / extent, solution[3:]
    rotation = Rotation.from_rotvec(omega).as_matrix()
    translation = centre - rotation @ centre + shift
    step = float(np.linalg.norm(shift) + np.linalg.norm(omega) * extent)
    return rotation, translation, step

