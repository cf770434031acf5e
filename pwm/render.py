"""Image formation by ray tracing: what a camera sees of a mesh lit by the Sun.

Radiance is returned as reflectance (I/F-like, dimensionless): albedo times the McEwen
lunar-Lambert function, zero in shadow and on sky pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pwm.camera import Camera, Pose
from pwm.photometry import angles, lunar_lambert
from pwm.raytrace import RayTracer


@dataclass
class Rendering:
    """A rendered view. All arrays are (height, width), indexed [line, sample].

    reflectance: albedo * G, 0 in shadow and off-body; hit: the pixel sees the body;
    shadow: the pixel sees a shadowed surface; points: body-fixed hit points (km), nan off-body.
    """

    reflectance: np.ndarray
    hit: np.ndarray
    shadow: np.ndarray
    points: np.ndarray


def render(
    tracer: RayTracer,
    *,
    camera: Camera,
    pose: Pose,
    sun_direction: np.ndarray,
    albedo: np.ndarray | None = None,
) -> Rendering:
    """Render the tracer's mesh. sun_direction: unit vector towards the Sun, body-fixed.

    albedo: per-vertex albedo overriding the mesh's own (e.g. to draw markers); 1 if neither.
    Shading uses the interpolated vertex normal; shadows are cast by the true facets.
    """
    mesh = tracer.mesh
    shape = (camera.height, camera.width)
    dirs = pose.to_body_directions(camera.grid_directions())
    origins = np.broadcast_to(pose.position, dirs.shape)
    hits = tracer.intersect(origins, dirs)
    ok = hits.hit
    points = tracer.hit_points(origins, dirs, hits)

    sun = np.asarray(sun_direction, float)
    sun = sun / np.linalg.norm(sun)
    normals = tracer.interpolate(tracer.vertex_normals, hits)[ok]
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    p = points[ok]
    to_cam = -dirs[ok]
    mu0, mu, phase = angles(normals, np.broadcast_to(sun, p.shape), to_cam)

    face_n = tracer.face_normals[hits.face[ok]]
    lift = tracer.offset
    in_shadow = np.ones(len(p), dtype=bool)
    facing = (mu0 > 0) & (np.einsum("ij,j->i", face_n, sun) > -0.2)
    if facing.any():
        start = p[facing] + lift * face_n[facing]
        in_shadow[facing] = tracer.occluded(start, np.broadcast_to(sun, start.shape))

    a = albedo if albedo is not None else mesh.albedo
    alb = tracer.interpolate(a, hits)[ok] if a is not None else np.ones(len(p))
    refl = np.where(in_shadow, 0.0, alb * lunar_lambert(mu0, mu, phase))

    out = np.zeros(camera.height * camera.width)
    out[ok] = refl
    shadow = np.zeros(camera.height * camera.width, dtype=bool)
    shadow[ok] = in_shadow
    return Rendering(
        reflectance=out.reshape(shape),
        hit=ok.reshape(shape),
        shadow=shadow.reshape(shape),
        points=points.reshape(shape + (3,)),
    )
