"""Local surface frames and planetocentric coordinates (body-fixed frame, km)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class LocalFrame:
    """A local frame on the surface: origin P0 (body-fixed, km) and rotation whose rows are the
    local x (parallel to the equator, eastward), y (northward) and z (regional normal) axes."""

    origin: np.ndarray
    rotation: np.ndarray

    def to_local(self, points_body: np.ndarray) -> np.ndarray:
        """Body-fixed points (km) to local coordinates Pl = R (P - P0), km."""
        # einsum: a (N, 3) @ (3, 3) product through BLAS is several times slower
        return np.einsum("ij,...j->...i", self.rotation, np.asarray(points_body, float) - self.origin)

    def to_body(self, points_local: np.ndarray) -> np.ndarray:
        """Local coordinates (km) to body-fixed points (km)."""
        return np.einsum("ji,...j->...i", self.rotation, np.asarray(points_local, float)) + self.origin

    @property
    def normal(self) -> np.ndarray:
        return self.rotation[2].copy()


def stored_frame(origin_km: Sequence[float] | np.ndarray, rotation: Sequence[float] | np.ndarray) -> LocalFrame:
    """A frame as a catalog stores it: its origin (km) and its rotation's nine numbers row by row
    (or its 3 x 3 rows)."""
    return LocalFrame(origin=np.array(origin_km, dtype=float), rotation=np.asarray(rotation, float).reshape(3, 3))


def local_frame(origin: np.ndarray, normal: np.ndarray) -> LocalFrame:
    """Frame at `origin` with z = `normal` and x parallel to the equator (east).

    Near a pole, where east is undefined, x falls back to the body +X axis projected on the plane.
    """
    z = np.asarray(normal, float)
    z = z / np.linalg.norm(z)
    x = np.cross([0.0, 0.0, 1.0], z)
    if np.linalg.norm(x) < 1e-6:
        x = np.array([1.0, 0.0, 0.0]) - z[0] * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return LocalFrame(origin=np.asarray(origin, float).copy(), rotation=np.vstack([x, y, z]))


def latlon_to_unit(lat_deg: float | np.ndarray, lon_deg: float | np.ndarray) -> np.ndarray:
    """Planetocentric latitude/longitude (degrees, east-positive) to unit vectors, (..., 3)."""
    lat = np.radians(lat_deg)
    lon = np.radians(lon_deg)
    return np.stack([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)], axis=-1)


def unit_to_latlon(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Body-fixed vectors to planetocentric latitude and east longitude in degrees [0, 360)."""
    v = np.asarray(v, float)
    r = np.linalg.norm(v, axis=-1)
    return np.degrees(np.arcsin(v[..., 2] / r)), np.degrees(np.arctan2(v[..., 1], v[..., 0])) % 360.0


def local_sun(sun_body: np.ndarray, frame: LocalFrame) -> tuple[np.ndarray, np.ndarray]:
    """Incidence and Sun azimuth (degrees; azimuth from local north, east positive) at the frame's origin."""
    s = np.asarray(sun_body, float) @ frame.rotation.T
    incidence = np.degrees(np.arccos(np.clip(s[..., 2], -1.0, 1.0)))
    azimuth = np.degrees(np.arctan2(s[..., 0], s[..., 1])) % 360.0
    return incidence, azimuth
