"""Rendering with the truth's photometry and several rays per pixel (pwm.render)."""

from __future__ import annotations

import numpy as np
import pytest

from pwm.camera import Camera, Pose
from pwm.mesh import Mesh
from pwm.photometry import Hapke, lunar_lambert
from pwm.raytrace import RayTracer
from pwm.render import render, render_supersampled

# Looking straight down from 1 km at the plane z = 0: camera +Z is body -Z.
DOWN = Pose(position=np.array([0.0, 0.0, 1.0]), rotation=np.diag([1.0, -1.0, -1.0]))
SUN = np.array([np.sin(np.radians(40)), 0.0, np.cos(np.radians(40))])


def plane(half_km: float, *, x_max_km: float | None = None) -> RayTracer:
    """A square of the plane z = 0, optionally cut at x = x_max_km, with albedo 0.05."""
    right = half_km if x_max_km is None else x_max_km
    vertices = np.array([[-half_km, -half_km, 0], [right, -half_km, 0], [right, half_km, 0], [-half_km, half_km, 0.0]])
    return RayTracer(Mesh(vertices, np.array([[0, 1, 2], [0, 2, 3]]), albedo=np.full(4, 0.05)))


CAMERA = Camera(width=8, height=6, fx=400.0, fy=400.0, cx=3.5, cy=2.5)


def test_a_law_other_than_the_solvers_changes_the_brightness_as_it_says():
    tracer = plane(1.0)
    law = Hapke()
    mcewen = render(tracer, camera=CAMERA, pose=DOWN, sun_direction=SUN)
    hapke = render(tracer, camera=CAMERA, pose=DOWN, sun_direction=SUN, photometry=law)
    centre = (2, 3)
    to_camera = DOWN.position - mcewen.points[centre]
    to_camera /= np.linalg.norm(to_camera)
    mu0, mu, phase = SUN[2], to_camera[2], np.arccos(SUN @ to_camera)
    assert mcewen.reflectance[centre] == pytest.approx(0.05 * lunar_lambert(mu0, mu, phase), rel=1e-5)
    assert hapke.reflectance[centre] == pytest.approx(0.05 * law(mu0, mu, phase), rel=1e-5)
    assert abs(hapke.reflectance[centre] / mcewen.reflectance[centre] - 1) > 0.02


def test_one_ray_per_pixel_is_render_and_more_keep_a_uniform_surface_uniform():
    tracer = plane(1.0)
    single = render(tracer, camera=CAMERA, pose=DOWN, sun_direction=SUN)
    once = render_supersampled(tracer, camera=CAMERA, pose=DOWN, sun_direction=SUN, factor=1)
    np.testing.assert_array_equal(once.reflectance, single.reflectance)
    fine = render_supersampled(tracer, camera=CAMERA, pose=DOWN, sun_direction=SUN, factor=3)
    assert fine.reflectance.shape == (6, 8) and fine.hit.all() and not fine.shadow.any()
    np.testing.assert_allclose(fine.reflectance, single.reflectance, rtol=1e-4)
    # a pixel's point is the mean of its rays' hits: the pixel centre's (to Embree's single precision)
    np.testing.assert_allclose(fine.points, single.points, atol=1e-6)
    with pytest.raises(ValueError, match="at least 1"):
        render_supersampled(tracer, camera=CAMERA, pose=DOWN, sun_direction=SUN, factor=0)


def test_sub_pixel_rays_average_over_an_edge_inside_a_pixel():
    """The plane ends a quarter of the way into the pixels of column 4: with 4x4 rays a quarter
    of their rays hit (reflectance a quarter of the lit value, not a hit), with one none do."""
    column_4_left_km = (4 - 0.5 - CAMERA.cx) / CAMERA.fx  # at range 1 km
    edge = column_4_left_km + 0.25 / CAMERA.fx
    tracer = plane(1.0, x_max_km=edge)
    lit = render(tracer, camera=CAMERA, pose=DOWN, sun_direction=SUN).reflectance[2, 3]
    fine = render_supersampled(tracer, camera=CAMERA, pose=DOWN, sun_direction=SUN, factor=4)
    assert fine.reflectance[2, 4] == pytest.approx(lit / 4, rel=1e-3)
    assert fine.reflectance[2, 3] == pytest.approx(lit, rel=1e-3) and fine.reflectance[2, 5] == 0
    assert not fine.hit[2, 4] and fine.hit[2, 3] and np.isnan(fine.points[2, 5]).all()
