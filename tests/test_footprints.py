"""Where the images see well enough to refine, and how finely (pwm.footprints), and the tiling of
such places (pwm.tiling.tile(where=...))."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from pwm import footprints
from pwm.camera import Camera, look_at, project
from pwm.footprints import footprint_samples, judge_samples, places, seen_samples
from pwm.frames import latlon_to_unit, unit_to_latlon
from pwm.mesh import Mesh
from pwm.raytrace import RayTracer
from pwm.tiling import tile
from pwm.views import Cones, View
from pwm.weights import RULES

R = 0.25
CAMERA = Camera(width=200, height=200, fx=2000.0, fy=2000.0, cx=99.5, cy=99.5)  # 5.7 deg field


@pytest.fixture(scope="module")
def tracer() -> RayTracer:
    s = trimesh.creation.icosphere(subdivisions=5, radius=R)
    return RayTracer(Mesh(np.asarray(s.vertices), np.asarray(s.faces)))


def views_of(lat: float, lon: float, range_km: float, tilts: list[tuple[float, float]], name: str) -> list[View]:
    """Images of the point (lat, lon) from range_km, each from a direction tilted by (dlat, dlon) deg,
    with the Sun overhead."""
    target = R * latlon_to_unit(lat, lon)
    out = []
    for k, (dlat, dlon) in enumerate(tilts):
        position = target + range_km * latlon_to_unit(lat + dlat, lon + dlon)
        out.append(View(name=f"{name}{k}", image=np.zeros((CAMERA.height, CAMERA.width)), camera=CAMERA,
                        pose=look_at(position, target, np.array([0.0, 0.0, 1.0])),
                        sun=latlon_to_unit(lat, lon), et=0.0))
    return out


TILTS = [(0.0, 0.0), (15.0, 0.0), (-15.0, 0.0), (0.0, 15.0), (0.0, -15.0)]


def test_two_sites_seen_at_two_scales_are_two_places(tracer):
    # site A from 1 km (0.5 m pixels), site B from 0.25 km (12.5 cm pixels), a lone image elsewhere
    a = views_of(10.0, 40.0, 1.0, TILTS, "a")
    b = views_of(-30.0, 200.0, 0.25, TILTS, "b")
    lone = views_of(60.0, 300.0, 1.0, TILTS[:1], "lone")
    seen = seen_samples(tracer, a + b + lone, rules=RULES, min_images=3)
    lat, lon = unit_to_latlon(seen.points)
    at_a = np.hypot(lat - 10.0, (lon - 40.0) * np.cos(np.radians(10.0))) < 30.0
    at_b = np.hypot(lat + 30.0, (lon - 200.0) * np.cos(np.radians(30.0))) < 30.0
    assert at_a.any() and at_b.any() and (at_a | at_b).all()  # the lone image's ground is not seen enough
    # each sample's pixel scale is its images' range over focal length
    assert np.allclose(seen.pixel_km[at_a], 1.0 / 2000.0, rtol=0.05)
    assert np.allclose(seen.pixel_km[at_b], 0.25 / 2000.0, rtol=0.05)
    found = places(seen, nodes=20, spacing_gsd=1.0)
    assert len(found) == 2
    by_site = sorted(found, key=lambda p: -p.spacing_km)
    assert by_site[0].spacing_km == pytest.approx(5e-4, rel=0.05)
    assert by_site[1].spacing_km == pytest.approx(1.25e-4, rel=0.05)
    # with fewer images required, the lone image's ground is a third place
    assert len(places(seen_samples(tracer, a + b + lone, rules=RULES, min_images=1), nodes=20, spacing_gsd=1.0)) == 3


def test_where_close_and_far_images_look_the_close_ones_set_the_scale(tracer):
    # a site from 1 km (0.5 m pixels) and again from 0.25 km (12.5 cm): five of each
    far = views_of(10.0, 40.0, 1.0, TILTS, "far")
    close = views_of(10.0, 40.0, 0.25, [(dlat / 4, dlon / 4) for dlat, dlon in TILTS], "close")
    seen = seen_samples(tracer, far + close, rules=RULES, min_images=3)
    target = R * latlon_to_unit(10.0, 40.0)
    under_close = np.linalg.norm(seen.points - target, axis=1) < 0.004  # inside every close footprint
    outside = np.linalg.norm(seen.points - target, axis=1) > 0.02  # beyond all of them
    assert under_close.sum() > 20 and outside.sum() > 20
    # not the median of all ten (between the two), but the close images'
    assert np.allclose(seen.pixel_km[under_close], 0.25 / 2000.0, rtol=0.05)
    assert np.allclose(seen.pixel_km[outside], 1.0 / 2000.0, rtol=0.05)
    found = places(seen, nodes=20, spacing_gsd=1.0)
    assert sorted(p.level for p in found) == [-3, -1]  # 12.5 cm and 50 cm
    fine = next(p for p in found if p.level == -3)
    assert np.linalg.norm(fine.points - target, axis=1).max() < 0.02


def test_a_place_is_tiled_over_what_is_seen_and_no_farther(tracer):
    views = views_of(10.0, 40.0, 1.0, TILTS, "a")
    place = places(seen_samples(tracer, views, rules=RULES, min_images=3), nodes=20, spacing_gsd=1.0)[0]
    maplets = tile(tracer.mesh, spacing_km=place.spacing_km, nodes=20, overlap=0.25, where=place.points)
    half = maplets[0].axis_km[-1]
    inside = np.zeros(len(place.points), dtype=bool)
    for m in maplets:
        inside |= np.all(np.abs(m.frame.to_local(place.points)) <= half, axis=1)
        # every maplet reaches a seen sample (none tiled where no image looks)
        assert np.linalg.norm(place.points - m.frame.origin, axis=1).min() <= 2 * half
    assert inside.all()
    with pytest.raises(ValueError, match="not both"):
        tile(tracer.mesh, spacing_km=place.spacing_km, nodes=20, where=place.points, centre_lat_deg=0.0,
             centre_lon_deg=0.0, radius_km=0.01)


def test_a_survey_is_one_place_round_the_body(tracer):
    # twelve images round the equator and four over the poles, from 2 km with a wide field
    wide = Camera(width=200, height=200, fx=150.0, fy=150.0, cx=99.5, cy=99.5)
    views = []
    for k, (lat, lon) in enumerate([(0.0, 30.0 * j) for j in range(12)] + [(70.0, 0.0), (70.0, 180.0),
                                                                            (-70.0, 0.0), (-70.0, 180.0)]):
        position = 2.0 * latlon_to_unit(lat, lon)
        views.append(View(name=f"s{k}", image=np.zeros((200, 200)), camera=wide,
                          pose=look_at(position, np.zeros(3), np.array([0.0, 0.0, 1.0])),
                          sun=latlon_to_unit(0.0, 30.0 * k), et=0.0))
    seen = seen_samples(tracer, views, rules=RULES, min_images=2)
    found = places(seen, nodes=20, spacing_gsd=1.0)
    assert len(found) == 1
    lat, lon = unit_to_latlon(found[0].points)
    assert np.ptp(lon) > 300.0 and lat.min() < -45.0 and lat.max() > 45.0


def test_a_cone_holds_all_that_its_view_sees_and_little_else():
    camera = Camera(width=320, height=200, fx=1000.0, fy=1000.0, cx=200.0, cy=90.0)  # off-centre window
    pose = look_at(np.array([1.0, 0.5, 0.3]), np.zeros(3), up=np.array([0.0, 0.0, 1.0]))
    view = View(name="a", image=np.empty((0, 0)), camera=camera, pose=pose, sun=np.array([1.0, 0, 0]), et=0.0)
    cones = Cones.of([view])
    rng = np.random.default_rng(1)
    points = rng.uniform(-0.6, 0.6, (20000, 3))
    ahead = pose.to_camera(points)[:, 2] > 0
    px = np.full((len(points), 2), -1e9)
    px[ahead] = project(points[ahead], camera, pose)
    framed = ahead & (px[:, 0] >= -0.5) & (px[:, 0] <= 319.5) & (px[:, 1] >= -0.5) & (px[:, 1] <= 199.5)
    inside = cones.seeing(points, 0.0)[0]
    assert framed.sum() > 100 and inside[framed].all()
    # the cone is the frame's circumscribed one, plus a small margin: it holds few points beyond
    assert inside.sum() < 3 * framed.sum()
    assert not inside[~ahead].any()
    # a ball reaching into the cone counts; an unknown cone holds everything
    off = points[~inside][0]
    assert cones.seeing(off[None], np.linalg.norm(off - pose.position))[0, 0]
    unknown = Cones(apex=cones.apex, axis=cones.axis, half_angle=np.array([np.nan]))
    assert unknown.seeing(points, 0.0).all()


def test_judging_by_cells_changes_nothing_but_the_work(tracer, monkeypatch):
    """Each judge looks only at the cells its cone meets: the same samples are seen as when every
    judge looks at every sample (one cell holding them all)."""
    site = views_of(10.0, 40.0, 1.0, [(0, 0), (5, 0), (0, 5), (-5, 0), (0, -5)], "site")
    elsewhere = views_of(-30.0, 200.0, 1.0, [(0, 0), (5, 0), (0, 5)], "far")
    survey = views_of(0.0, 100.0, 3.0, [(0, 0), (20, 0), (0, 20), (-20, 0)], "wide")
    judges = site + elsewhere + survey
    samples = footprint_samples(tracer, site + survey)
    judged = judge_samples(tracer, samples, judges, rules=RULES, min_images=2)
    monkeypatch.setattr(footprints, "CELLS_PER_SIDE", 1)
    assert len(samples.cells()[0]) == 1
    everything = judge_samples(tracer, samples, judges, rules=RULES, min_images=2)
    assert len(judged.points) > 100
    np.testing.assert_array_equal(judged.points, everything.points)
    np.testing.assert_array_equal(judged.pixel_km, everything.pixel_km)
