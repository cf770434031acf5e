"""Image formation by ray tracing: what a camera sees of a mesh lit by the Sun.

Radiance is returned as reflectance (I/F-like, dimensionless): albedo times a photometric
function (McEwen's lunar-Lambert, the solver's, unless another is given), zero in shadow and on
sky pixels. One ray per pixel centre, or the mean of factor x factor rays spread over each pixel
(`render_supersampled`), as a detector integrates its pixel's area.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pwm.camera import Camera, Pose
from pwm.photometry import MCEWEN, Photometry, angles
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
    photometry: Photometry = MCEWEN,
) -> Rendering:
    """Render the tracer's mesh. sun_direction: unit vector towards the Sun, body-fixed.

    albedo: per-vertex albedo overriding the mesh's own (e.g. to draw markers); 1 if neither.
    photometry: the reflectance law G(mu0, mu, phase). Shading uses the interpolated vertex
    normal; shadows are cast by the true facets.
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
    refl = np.where(in_shadow, 0.0, alb * photometry(mu0, mu, phase))

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


def render_supersampled(
    tracer: RayTracer,
    *,
    camera: Camera,
    pose: Pose,
    sun_direction: np.ndarray,
    factor: int,
    photometry: Photometry = MCEWEN,
) -> Rendering:
    """`render` with factor x factor rays per pixel, evenly spread over it: reflectance is their
    mean; a pixel is a hit or in shadow when most of its rays are, and its point is the mean of
    its rays' hits (nan when none hit). factor 1 is `render`."""
    if factor < 1:
        raise ValueError(f"supersampling factor must be at least 1, not {factor}")
    if factor == 1:
        return render(tracer, camera=camera, pose=pose, sun_direction=sun_direction, photometry=photometry)
    # Sub-pixel k of pixel u sits at u + (k + 1/2)/factor - 1/2: a camera `factor` times finer
    # whose pixel centres are those positions.
    fine = Camera(width=camera.width * factor, height=camera.height * factor, fx=camera.fx * factor,
                  fy=camera.fy * factor, cx=camera.cx * factor + (factor - 1) / 2,
                  cy=camera.cy * factor + (factor - 1) / 2)
    view = render(tracer, camera=fine, pose=pose, sun_direction=sun_direction, photometry=photometry)

    def blocks(a: np.ndarray) -> np.ndarray:
        return a.reshape(camera.height, factor, camera.width, factor, *a.shape[2:]).swapaxes(1, 2).reshape(
            camera.height, camera.width, factor * factor, *a.shape[2:])

    hits = blocks(view.hit)
    count = hits.sum(axis=2)[..., None]
    total = np.where(hits[..., None], blocks(view.points), 0.0).sum(axis=2)
    points = np.where(count > 0, total / np.maximum(count, 1), np.nan)
    return Rendering(reflectance=blocks(view.reflectance).mean(axis=2), hit=hits.mean(axis=2) > 0.5,
                     shadow=blocks(view.shadow).mean(axis=2) > 0.5, points=points)
