"""How much of the true surface a model has: the fraction of the truth's area within a
tolerance of the model's surface (body-fixed frame, km). Model-to-truth distances cannot see a
hole or a missing part; this can (issue 15's coverage of a global model)."""

from __future__ import annotations

import numpy as np

from pwm.evaluate.distance import ClosestPoint
from pwm.mesh import Mesh

COMPLETENESS_GSD = 2.0
"""The tolerance, in GSD, within which a true surface point counts as modelled."""
SAMPLES = 50_000
"""Points drawn uniformly over the truth's area: the fraction is good to about 0.5%."""


def surface_points(mesh: Mesh, count: int, rng: np.random.Generator) -> np.ndarray:
    """`count` points (count, 3) drawn uniformly over the mesh's area."""
    areas = mesh.face_areas()
    faces = rng.choice(len(areas), size=count, p=areas / areas.sum())
    u, v = rng.random(count), rng.random(count)
    flip = u + v > 1.0
    u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
    corners = mesh.vertices[mesh.faces[faces]]
    return corners[:, 0] + u[:, None] * (corners[:, 1] - corners[:, 0]) + v[:, None] * (corners[:, 2] - corners[:, 0])


def completeness(truth: Mesh, model: Mesh, *, tolerance_km: float, samples: int = SAMPLES, seed: int = 0) -> float:
    """The fraction of the truth's area that lies within tolerance_km of the model's surface."""
    if not tolerance_km > 0:
        raise ValueError(f"tolerance_km must be > 0, got {tolerance_km}")
    points = surface_points(truth, samples, np.random.default_rng(seed))
    distance, _, _ = ClosestPoint(model).query(points)
    return float(np.mean(distance <= tolerance_km))
