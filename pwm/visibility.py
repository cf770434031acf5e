"""Occlusion and shadowing of surface points in a set of images (PWM paper section 3.3.2).

A point is occluded in an image when the ray from it towards the camera meets the surface first,
and shadowed when the ray towards the Sun does. Rays are traced with Embree (single precision)
against the current shape, all images in one batch; their origins are lifted off the surface
along the normal so that a point does not occlude itself. Whether a point falls inside an
image's frame is the caller's test.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pwm.photometry import angles
from pwm.raytrace import RayTracer


@dataclass
class Visibility:
    """Per image k and point n, all (K, N). visible: the point faces the camera (mu > 0) and its
    line of sight is clear; lit: it faces the Sun (mu0 > 0) and its ray to the Sun is clear;
    mu0, mu: cosines of incidence and emission on the given normals; phase: phase angle, rad."""

    visible: np.ndarray
    lit: np.ndarray
    mu0: np.ndarray
    mu: np.ndarray
    phase: np.ndarray


def node_visibility(
    tracer: RayTracer, points: np.ndarray, normals: np.ndarray, *, camera_positions: np.ndarray,
    sun_directions: np.ndarray, offset_km: float | None = None,
) -> Visibility:
    """Visibility of N points (body-fixed km, unit normals (N, 3)) in K images with camera centres
    camera_positions (K, 3) km and directions towards the Sun sun_directions (K, 3), body-fixed.

    offset_km: lift of the ray origins along the normal (default tracer.offset); raise it when
    the points may lie below the tracer's surface by more than that, e.g. a refined maplet
    against an older shape. Only rays from points facing the camera (Sun) are traced.
    """
    points = np.asarray(points, float)
    normals = np.asarray(normals, float)
    cams = np.asarray(camera_positions, float)
    sun = np.asarray(sun_directions, float)
    sun = sun / np.linalg.norm(sun, axis=1, keepdims=True)
    origins = points + (tracer.offset if offset_km is None else offset_km) * normals
    to_cam = cams[:, None, :] - origins[None]
    distance = np.linalg.norm(to_cam, axis=2)
    to_cam /= distance[..., None]
    mu0, mu, phase = angles(normals[None], sun[:, None, :], to_cam)
    view = mu > 0
    lamp = mu0 > 0
    _, n_view = np.nonzero(view)
    k_sun, n_sun = np.nonzero(lamp)
    blocked = tracer.occluded(
        np.concatenate([origins[n_view], origins[n_sun]]),
        np.concatenate([to_cam[view], sun[k_sun]]),
        np.concatenate([distance[view], np.full(len(n_sun), np.inf)]),
    )
    visible = np.zeros(mu.shape, dtype=bool)
    lit = np.zeros(mu.shape, dtype=bool)
    visible[view] = ~blocked[: len(n_view)]
    lit[lamp] = ~blocked[len(n_view) :]
    return Visibility(visible=visible, lit=lit, mu0=mu0, mu=mu, phase=phase)
