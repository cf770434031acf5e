"""The visual hull from the outlines (pwm.spg.hull): a bilobed body with a neck, seen all round
under a Sun near its equator, is held by its hull closely, the ellipsoid of its extents not at
all; no pixel of the body, lit or in shadow, is ever taken for space."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from pwm.camera import Camera, look_at
from pwm.evaluate.distance import ClosestPoint
from pwm.geometry import Ellipsoid
from pwm.mesh import Mesh
from pwm.raytrace import RayTracer
from pwm.render import render
from pwm.spg.config import SPG_DEFAULTS
from pwm.spg.hull import Outline, visual_hull
from pwm.views import View

CAMERA = Camera(width=256, height=256, fx=2000.0, fy=2000.0, cx=127.5, cy=127.5)
RANGE_KM = 25.0
PIXEL_KM = RANGE_KM / CAMERA.fx
CONFIG = SPG_DEFAULTS.hull


def _bilobed() -> Mesh:
    """Two lobes 2 km end to end joined by a neck a third as thick (km)."""
    sphere = Ellipsoid(np.ones(3)).mesh(subdivisions=5)
    v = sphere.vertices.copy()
    v[:, 1:] *= 0.6 * (0.35 + 0.65 * np.abs(v[:, 0:1]) ** 0.7)
    return Mesh(v, sphere.faces)


def _volume(mesh: Mesh) -> float:
    a, b, c = (mesh.vertices[mesh.faces[:, k]] for k in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


@pytest.fixture(scope="module")
def survey() -> tuple[Mesh, list[View]]:
    body = _bilobed()
    tracer = RayTracer(body)
    rng = np.random.default_rng(1)
    views = []
    for k in range(24):
        lon, lat = np.radians(15.0 * k + 3.0), np.radians([-40.0, -15.0, 10.0, 35.0][k % 4])
        direction = np.array([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)])
        pose = look_at(RANGE_KM * direction, np.zeros(3), np.array([0.0, 0.0, 1.0]))
        # the Sun near the equator, 30-60 degrees of phase to either side
        sun_lon, sun_lat = lon + np.radians(rng.uniform(30.0, 60.0)) * (1 if k % 2 else -1), np.radians(5.0)
        sun = np.array([np.cos(sun_lat) * np.cos(sun_lon), np.cos(sun_lat) * np.sin(sun_lon), np.sin(sun_lat)])
        image = render(tracer, camera=CAMERA, pose=pose, sun_direction=sun).reflectance
        views.append(View(name=f"v{k}", image=image + 0.002 * rng.standard_normal(image.shape), camera=CAMERA,
                          pose=pose, sun=sun, et=0.0))
    return body, views


def test_no_pixel_of_the_body_is_taken_for_space(survey):
    body, views = survey
    tracer = RayTracer(body)
    shadowed = 0
    for view in views:
        seen = render(tracer, camera=CAMERA, pose=view.pose, sun_direction=view.sun)
        space = Outline(view, config=CONFIG).space(CONFIG.margin_px)
        assert not (space & seen.hit).any(), view.name
        assert space[~seen.hit].mean() > 0.5  # and most of the sky is
        shadowed += int((seen.hit & (seen.reflectance == 0)).sum())
    assert shadowed > 1000  # the night sides and shadows were in view, dark as the sky


def test_the_hull_holds_a_bilobed_body_and_the_ellipsoid_does_not(survey):
    body, views = survey
    hull = visual_hull(views, bound_km=1.5, config=CONFIG)
    assert hull is not None and hull.closed and hull.carving_views == len(views)
    assert hull.cell_km == pytest.approx(3.0 / 256)
    # it holds the body: a little larger, by the margins, never smaller
    assert _volume(body) < hull.volume_km3 < 1.2 * _volume(body)
    to_body = ClosestPoint(body).query(hull.mesh.vertices)[0]
    to_hull = ClosestPoint(hull.mesh).query(body.vertices)[0]
    assert np.sqrt(np.mean(to_body**2)) < 2.5 * PIXEL_KM and np.sqrt(np.mean(to_hull**2)) < 2.5 * PIXEL_KM
    extents = Ellipsoid(np.abs(body.vertices).max(axis=0)).mesh(subdivisions=5)
    misfit = ClosestPoint(extents).query(body.vertices)[0]
    print(f"hull {np.sqrt(np.mean(to_hull**2)) * 1e3:.1f} m RMS, {to_hull.max() * 1e3:.1f} m at most; "
          f"ellipsoid {np.sqrt(np.mean(misfit**2)) * 1e3:.1f} m RMS, {misfit.max() * 1e3:.1f} m at most")
    assert np.sqrt(np.mean(misfit**2)) > 2.5 * np.sqrt(np.mean(to_hull**2))


def test_views_that_see_no_outline_make_no_hull(survey):
    _, views = survey
    dark = [replace(v, image=np.zeros_like(v.image)) for v in views[:6]]
    assert visual_hull(dark, bound_km=1.5, config=CONFIG) is None
