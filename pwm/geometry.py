"""Viewing geometry of one image: camera pose and Sun direction in the body-fixed frame (km),
and where the boresight and the four image corners meet the surface, which is the target's
triaxial ellipsoid or a shape model.

Pure: the pose and the Sun come from the SPICE kernel pool by pwm.io.resolve.pose_and_sun, the
target's radii by pwm.io.spice_geometry.ellipsoid_of.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from pwm.camera import Camera, Pose
from pwm.frames import unit_to_latlon
from pwm.mesh import Mesh
from pwm.raytrace import RayTracer


class Surface(Protocol):
    """Something rays can hit, in the body-fixed frame (km)."""

    def intersect(self, origins: np.ndarray, directions: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
        """First hits of rays (n, 3) from `origins` along unit `directions`: points (n, 3) km
        and unit outward normals (n, 3), NaN where a ray misses."""
        ...


@dataclass(frozen=True)
class Ellipsoid:
    """A triaxial ellipsoid centred on the body origin, semi-axes `radii` (km) along x, y, z."""

    radii: np.ndarray

    def intersect(self, origins: np.ndarray, directions: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
        radii = np.asarray(self.radii, dtype=float)
        # In coordinates scaled by the radii the ellipsoid is the unit sphere.
        o, d = origins / radii, directions / radii
        a, b, c = (d * d).sum(1), 2 * (o * d).sum(1), (o * o).sum(1) - 1
        disc = b * b - 4 * a * c
        t = (-b - np.sqrt(np.where(disc >= 0, disc, np.nan))) / (2 * a)
        t[~(t > 0)] = np.nan  # behind the origin, or the origin inside the body
        points = origins + t[:, None] * directions
        normals = points / radii**2
        return points, normals / np.linalg.norm(normals, axis=1, keepdims=True)

    def mesh(self, *, subdivisions: int = 5) -> Mesh:
        """The ellipsoid as a closed triangle mesh (km): an icosphere of `subdivisions` (20 * 4**n
        faces) scaled by the radii."""
        import trimesh

        sphere = trimesh.creation.icosphere(subdivisions=subdivisions)
        return Mesh(np.asarray(sphere.vertices) * np.asarray(self.radii, dtype=float),
                    np.asarray(sphere.faces, dtype=np.int64))


class MeshSurface:
    """A shape model, ray traced with Embree; normals are those of the facets hit."""

    def __init__(self, mesh: Mesh) -> None:
        self._tracer = RayTracer(mesh)

    def intersect(self, origins: np.ndarray, directions: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
        hits = self._tracer.intersect(origins, directions)
        normals = self._tracer.face_normals[np.where(hits.hit, hits.face, 0)]
        normals[~hits.hit] = np.nan
        return self._tracer.hit_points(origins, directions, hits), normals


@dataclass(frozen=True)
class ViewGeometry:
    """Geometry of one image. position_km: camera, body-fixed; rotation: body-fixed ->
    instrument frame; sun: unit vector to the Sun, body-fixed. Boresight quantities (intercept
    range km, pixel scale m/px, angles deg, planetocentric lat and east lon in [0, 360) deg) are
    None when the boresight misses; footprint holds (lat, lon) of the four image corners in the
    order of image_corners, None for a corner off the body."""

    position_km: np.ndarray
    rotation: np.ndarray
    sun: np.ndarray
    range_km: float
    intercept_range_km: float | None
    pixel_scale_m: float | None
    phase_deg: float | None
    incidence_deg: float | None
    emission_deg: float | None
    intercept_lat_deg: float | None
    intercept_lon_deg: float | None
    footprint: list[tuple[float, float] | None]
    cone_axis: np.ndarray
    cone_half_angle_rad: float


def view_cone(camera: Camera, pose: Pose) -> tuple[np.ndarray, float]:
    """The cone that holds every ray of the array, apex at the camera: its body-fixed unit axis
    through the array's centre, and the half-angle (rad) to the farthest outer corner."""
    centre = camera.pixel_directions(np.array((camera.width - 1) / 2), np.array((camera.height - 1) / 2))
    corners = image_corners(camera)
    rays = camera.pixel_directions(corners[:, 0], corners[:, 1])
    half = float(np.max(np.arccos(np.clip(rays @ centre, -1.0, 1.0))))
    return pose.to_body_directions(centre), half


def image_corners(camera: Camera) -> np.ndarray:
    """(sample, line) px of the outer corners of the first and last pixels: first line first
    sample, first line last sample, last line last sample, last line first sample."""
    s0, s1, l0, l1 = -0.5, camera.width - 0.5, -0.5, camera.height - 0.5
    return np.array([[s0, l0], [s1, l0], [s1, l1], [s0, l1]])


def _angles_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angles between row vectors, accurate near 0 and pi (unlike arccos of the dot product)."""
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), (a * b).sum(-1)))


def view_geometry(*, pose: Pose, sun: np.ndarray, camera: Camera, surface: Surface) -> ViewGeometry:
    """Range, boresight intercept quantities and corner footprint of a view.

    pose: in pwm.camera's image frame (as camera_pose returns it). Pixel scale is the intercept
    range over the mean focal length: metres per pixel across the line of sight.
    """
    corners = image_corners(camera)
    offsets = np.column_stack([(corners[:, 0] - camera.cx) / camera.fx,
                               (corners[:, 1] - camera.cy) / camera.fy, np.ones(len(corners))])
    rays = np.vstack([[0.0, 0.0, 1.0], offsets])  # image frame
    directions = rays @ pose.rotation  # image -> body-fixed: rotation transposed
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    points, normals = surface.intersect(np.tile(pose.position, (len(rays), 1)), directions)
    lat, lon = unit_to_latlon(points)
    latlon = np.column_stack([lat, lon]).tolist()
    missed = np.isnan(points).any(axis=1)
    footprint = [None if m else (lat, lon) for m, (lat, lon) in zip(missed[1:], latlon[1:], strict=True)]
    axis, half = view_cone(camera, pose)
    base: dict[str, Any] = dict(position_km=np.asarray(pose.position, float), rotation=np.asarray(pose.rotation),
                                sun=np.asarray(sun, float), range_km=float(np.linalg.norm(pose.position)),
                                footprint=footprint, cone_axis=axis, cone_half_angle_rad=half)
    if missed[0]:
        return ViewGeometry(**base, intercept_range_km=None, pixel_scale_m=None, phase_deg=None,
                            incidence_deg=None, emission_deg=None, intercept_lat_deg=None,
                            intercept_lon_deg=None)
    to_camera = pose.position - points[0]
    distance = float(np.linalg.norm(to_camera))
    phase, incidence, emission = _angles_deg(np.array([to_camera, normals[0], normals[0]]),
                                             np.array([sun, sun, to_camera])).tolist()
    return ViewGeometry(
        **base, intercept_range_km=distance,
        pixel_scale_m=distance * 1e3 / ((camera.fx + camera.fy) / 2), phase_deg=phase,
        incidence_deg=incidence, emission_deg=emission, intercept_lat_deg=latlon[0][0],
        intercept_lon_deg=latlon[0][1])
