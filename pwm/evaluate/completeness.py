"""How much of the true surface a model has: the fraction of the truth's area within a
tolerance of the model's surface (body-fixed frame, km). Model-to-truth distances cannot see a
hole or a missing part; this can (issue 15's coverage of a global model)."""

from __future__ import annotations

import numpy as np

from pwm.evaluate.distance import ClosestPoint
from pwm.mesh import Mesh, surface_points

COMPLETENESS_GSD = 2.0
"""The tolerance, in GSD, within which a true surface point counts as modelled."""
SAMPLES = 50_000
"""Points drawn uniformly over the truth's area: the fraction is good to about 0.5%."""


def truth_gaps(truth: Mesh, model: Mesh, *, samples: int = SAMPLES, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Points (samples, 3) drawn uniformly over the truth's area, and each one's distance (km) to
    the model's surface."""
    points = surface_points(truth, samples, np.random.default_rng(seed))
    distance, _, _ = ClosestPoint(model).query(points)
    return points, distance


def completeness(truth: Mesh, model: Mesh, *, tolerance_km: float, samples: int = SAMPLES, seed: int = 0) -> float:
    """The fraction of the truth's area that lies within tolerance_km of the model's surface."""
    if not tolerance_km > 0:
        raise ValueError(f"tolerance_km must be > 0, got {tolerance_km}")
    return float(np.mean(truth_gaps(truth, model, samples=samples, seed=seed)[1] <= tolerance_km))
