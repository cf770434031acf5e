"""Pinhole camera: intrinsics in pixels and pose in the body-fixed frame.

Pixel convention (shared by the renderer, the PDS4 writer and ingest): an image array is indexed
[line, sample]; pixel centres sit at integer coordinates, zero-based, so the centre of the first
pixel is (sample 0, line 0). In the camera frame +Z is the boresight, +X points along increasing
sample and +Y along increasing line.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation


@dataclass(frozen=True)
class Camera:
    """Pinhole intrinsics. fx, fy: focal length in pixels; cx, cy: principal point (sample, line)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    def pixel_directions(self, samples: np.ndarray, lines: np.ndarray) -> np.ndarray:
        """Unit ray directions in the camera frame for pixel coordinates, shape (..., 3)."""
        d = np.stack(
            [(np.asarray(samples, float) - self.cx) / self.fx,
             (np.asarray(lines, float) - self.cy) / self.fy,
             np.ones(np.broadcast(samples, lines).shape)],
            axis=-1,
        )
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def grid_directions(self) -> np.ndarray:
        """Unit directions for every pixel centre, (height * width, 3), row-major [line, sample]."""
        lines, samples = np.mgrid[0 : self.height, 0 : self.width]
        return self.pixel_directions(samples.ravel(), lines.ravel())

    def project_camera(self, points_cam: np.ndarray) -> np.ndarray:
        """Project camera-frame points to (sample, line), shape (..., 2). Points must have z > 0."""
        p = np.asarray(points_cam, float)
        return np.stack(
            [self.fx * p[..., 0] / p[..., 2] + self.cx, self.fy * p[..., 1] / p[..., 2] + self.cy],
            axis=-1,
        )

    def subframe(self, *, first_sample: int, first_line: int, samples: int, lines: int) -> Camera:
        """The camera of a detector window starting at zero-based (first_sample, first_line)."""
        if (first_sample < 0 or first_line < 0 or first_sample + samples > self.width
                or first_line + lines > self.height):
            raise ValueError(f"subframe {samples}x{lines}+{first_sample}+{first_line} exceeds the "
                             f"{self.width}x{self.height} detector")
        return Camera(width=samples, height=lines, fx=self.fx, fy=self.fy, cx=self.cx - first_sample,
                      cy=self.cy - first_line)

    def scaled(self, factor: float) -> Camera:
        """The same optics on a detector binned by `factor` (pixel-centre convention kept)."""
        return Camera(
            width=int(round(self.width / factor)),
            height=int(round(self.height / factor)),
            fx=self.fx / factor,
            fy=self.fy / factor,
            cx=(self.cx + 0.5) / factor - 0.5,
            cy=(self.cy + 0.5) / factor - 0.5,
        )


@dataclass(frozen=True)
class Pose:
    """Camera pose. position: camera centre, body-fixed, km. rotation: 3x3 body-fixed -> camera."""

    position: np.ndarray
    rotation: np.ndarray

    def to_camera(self, points_body: np.ndarray) -> np.ndarray:
        """Body-fixed points (km) to camera-frame coordinates (km)."""
        return (np.asarray(points_body, float) - self.position) @ self.rotation.T

    def to_body_directions(self, dirs_cam: np.ndarray) -> np.ndarray:
        """Camera-frame directions to body-fixed directions."""
        return np.asarray(dirs_cam, float) @ self.rotation

    @property
    def boresight(self) -> np.ndarray:
        """Boresight (+Z camera) as a body-fixed unit vector."""
        return self.rotation[2].copy()


@dataclass(frozen=True)
class PoseCorrection:
    """A correction to a camera pose, as a bundle adjustment estimates it: position_km (dx, dy, dz)
    added to the camera centre and rotation_rad, a rotation vector turning the camera axes, both
    body-fixed (see `corrected_pose`)."""

    position_km: tuple[float, float, float]
    rotation_rad: tuple[float, float, float]

    def apply(self, pose: Pose) -> Pose:
        """`pose` corrected."""
        return corrected_pose(pose, np.asarray(self.position_km), np.asarray(self.rotation_rad))


def corrected_pose(pose: Pose, dp_km: np.ndarray, omega_rad: np.ndarray) -> Pose:
    """`pose` with a position correction (km, body-fixed) and a rotation vector (rad, body-fixed)
    applied to its axes: rotation @ R(omega)^T."""
    return Pose(position=pose.position + dp_km, rotation=pose.rotation @ Rotation.from_rotvec(omega_rad).as_matrix().T)


def project(points_body: np.ndarray, camera: Camera, pose: Pose) -> np.ndarray:
    """Body-fixed points (km) to pixel coordinates (sample, line), (..., 2)."""
    return camera.project_camera(pose.to_camera(points_body))


def look_at(position: np.ndarray, target: np.ndarray, up: np.ndarray) -> Pose:
    """Pose of a camera at `position` looking at `target` with image -Y (line decreasing) towards `up`."""
    z = np.asarray(target, float) - np.asarray(position, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, -np.asarray(up, float))
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, [1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.cross(z, [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return Pose(position=np.asarray(position, float).copy(), rotation=np.vstack([x, y, z]))
