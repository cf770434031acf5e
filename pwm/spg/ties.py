"""Ties of the photogrammetric points to a surface another instrument measured absolutely (the
lidar's spots, placed by range from the spacecraft): each point near enough spots is held to
the plane they make under it, to that plane's own uncertainty.

Images alone fix their points against each other, never where the block of points and cameras
lies: a shift, turn or scaling of the whole block, or a turn of the camera common to every
image, leaves every image as it is. A point tied to a measured surface cannot slide with the
block, so ties spread over relief in several directions fix the block's place and the camera's
alignment (pwm.spg.adjustment takes them as observations of the points). Lengths in km,
body-fixed frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from pwm.spg.config import SPG_DEFAULTS, SpgConfig


@dataclass(frozen=True)
class SurfaceTies:
    """Point `point[k]` (an index into the adjustment's points) lies on the plane through
    `at[k]` (km) with unit normal `normal[k]`, to `sigma_km[k]` (1 sigma, along the normal).

    frame_km, frame_rad: the 1 sigma per axis of a shift and a turn (about the body's origin)
    common to every plane: how well the other instrument's own frame is placed. Its
    measurements' errors shared by all of them (the spacecraft's trajectory and attitude errors
    its spots were placed with) do not average out over the ties, so the adjustment takes that
    motion as unknowns under this prior rather than the planes as exact; zero: exact.
    """

    point: np.ndarray
    at: np.ndarray
    normal: np.ndarray
    sigma_km: np.ndarray
    frame_km: float = 0.0
    frame_rad: float = 0.0

    def __len__(self) -> int:
        return len(self.point)

    def frame_motion(self) -> np.ndarray:
        """(n, k): how far each plane moves along its normal (km) per unit (1 sigma) of the
        frame's unknowns: its shift's three, then its turn's three, those of no sigma left out."""
        columns = [self.normal * self.frame_km] if self.frame_km > 0 else []
        if self.frame_rad > 0:
            columns.append(np.cross(self.at, self.normal) * self.frame_rad)  # n . (w x a) = w . (a x n)
        return np.hstack(columns) if columns else np.zeros((len(self), 0))

    def distances_km(self, points_km: np.ndarray) -> np.ndarray:
        """Each tie's signed distance of its point from its plane (km)."""
        return np.einsum("ij,ij->i", points_km[self.point] - self.at, self.normal)


SPAN_SAMPLE = 20000  # spots enough for a median span, however many there are

@dataclass(frozen=True)
class MeasuredSurface:
    """Spots of the surface another instrument measured (km, body-fixed), and the 1 sigma per
    axis of the shift (km) and turn (rad) of their frame (`SurfaceTies`)."""

    spots_km: np.ndarray
    frame_km: float = 0.0
    frame_rad: float = 0.0


NO_TIES = SurfaceTies(point=np.zeros(0, np.int64), at=np.zeros((0, 3)), normal=np.zeros((0, 3)),
                      sigma_km=np.zeros(0))


def surface_ties(points_km: np.ndarray, surface: MeasuredSurface, *, config: SpgConfig = SPG_DEFAULTS) -> SurfaceTies:
    """Tie each point to the plane of its config.tie_spots nearest spots where all lie within
    config.tie_reach times the distance at which a spot has as many neighbours (the median over
    the spots): a point among the spots, not beside them. The plane is the spots' least-squares
    plane; its sigma is the spots' scatter about it (the ground's relief at the spots' scale,
    their noise, and how far neighbouring tracks disagree), at least config.tie_floor_km.
    The ties' frame is the surface's."""
    points_km = np.asarray(points_km, float).reshape(-1, 3)
    spots_km = np.asarray(surface.spots_km, float).reshape(-1, 3)
    k = config.tie_spots
    if len(points_km) == 0 or len(spots_km) <= k:
        return NO_TIES
    tree = cKDTree(spots_km)
    sample = spots_km[:: max(1, len(spots_km) // SPAN_SAMPLE)]
    span = float(np.median(tree.query(sample, k=k + 1)[0][:, k]))  # each spot is its own nearest
    distance, nearest = tree.query(points_km, k=k, distance_upper_bound=config.tie_reach * span)
    among = np.isfinite(distance).all(axis=1)
    if not among.any():
        return NO_TIES
    near = spots_km[nearest[among]]  # (m, k, 3)
    centre = near.mean(axis=1)
    spread = near - centre[:, None, :]
    values, vectors = np.linalg.eigh(np.einsum("mki,mkj->mij", spread, spread))
    normal = vectors[:, :, 0]  # least scatter: across the plane
    # k spots fit a plane with three unknowns: their scatter about it, per degree of freedom
    scatter = np.sqrt(np.maximum(values[:, 0], 0.0) / (k - 3))
    return SurfaceTies(point=np.flatnonzero(among).astype(np.int64), at=centre, normal=normal,
                       sigma_km=np.maximum(scatter, config.tie_floor_km), frame_km=surface.frame_km,
                       frame_rad=surface.frame_rad)
