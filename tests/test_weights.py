"""Image, pixel and region weights: the rules one by one, then on real visibility."""

from __future__ import annotations

import numpy as np
import pytest

from pwm.frames import LocalFrame, latlon_to_unit, local_frame, unit_to_latlon
from pwm.maplets import MapletGrid
from pwm.mesh import Mesh, grid_faces
from pwm.raytrace import RayTracer
from pwm.visibility import Visibility, node_visibility
from pwm.weights import (
    RULES,
    MapletGeometry,
    Rules,
    azimuth_spread_deg,
    dark_nodes,
    five_views,
    image_weights,
    maplet_geometry,
    node_factors,
    region_weight,
    select_images,
    shade,
    slope_spread_deg,
    weigh_maplet,
)


def geometry(**columns) -> MapletGeometry:
    """K images of good geometry, with the given columns replaced."""
    k = len(next(iter(columns.values())))
    base = dict(incidence_deg=45.0, emission_deg=10.0, phase_deg=50.0, camera_azimuth_deg=0.0,
                sun_azimuth_deg=90.0, resolution_ratio=1.0, visible_fraction=1.0, shadow_fraction=0.0)
    return MapletGeometry(**{key: np.asarray(columns.get(key, np.full(k, v)), float) for key, v in base.items()})


def directions(frame: LocalFrame, angles_deg: list[tuple[float, float]]) -> np.ndarray:
    """Body-fixed unit vectors at (angle from the frame's z, azimuth from north towards east)."""
    a, b = np.radians(np.array(angles_deg, float)).T
    return frame.to_body(np.column_stack([np.sin(a) * np.sin(b), np.sin(a) * np.cos(b), np.cos(a)])) - frame.origin


def test_each_drop_rule_fires_and_says_why():
    geom = geometry(visible_fraction=[0.9, 0.1, 0.9, 0.9, 0.9, 0.9], shadow_fraction=[0.0, 0.0, 0.7, 0.0, 0.0, 0.0],
                    emission_deg=[10.0, 10.0, 10.0, 45.0, 10.0, 10.0],
                    resolution_ratio=[1.0, 1.0, 1.0, 1.0, 2.5, 0.05])
    keep, reasons = select_images(geom)
    assert keep.tolist() == [True, False, False, False, False, False]
    assert reasons[0] == []
    for k, word in enumerate(["visible", "shadowed", "emission", "pixel scale", "pixel scale"], start=1):
        assert len(reasons[k]) == 1 and reasons[k][0].startswith(word)
    assert "finer levels" in reasons[5][0]
    keep, _ = select_images(geom, Rules(max_emission_deg=50.0, max_resolution_ratio=3.0, min_resolution_ratio=0.01))
    assert keep.tolist() == [True, False, False, True, True, True]


def test_image_weight_favours_moderate_incidence_low_emission_and_fine_pixels():
    w = image_weights(geometry(incidence_deg=[5.0, 20.0, 30.0, 45.0, 75.0, 82.0, 90.0]))
    assert w[2] == w[3] == w[4] == 1.0
    assert RULES.incidence_floor < w[0] < w[1] < 1.0 and 0.0 < w[5] < 1.0 and w[6] == 0.0
    w = image_weights(geometry(emission_deg=[0.0, 30.0, 40.0, 55.0, 70.0]))
    assert w[0] == w[1] == 1.0 and 1.0 > w[2] > w[3] > w[4] == 0.0
    w = image_weights(geometry(resolution_ratio=[0.5, 1.0, 1.6]))
    assert w.tolist() == pytest.approx([1.0, 1.0, 1 / 1.6])
    w = image_weights(geometry(visible_fraction=[1.0, 0.5], shadow_fraction=[0.0, 0.1]))
    assert w.tolist() == pytest.approx([1.0, 0.45])


def test_maplet_geometry_in_the_maplet_frame():
    frame = local_frame(0.25 * latlon_to_unit(20.0, 100.0), latlon_to_unit(20.0, 100.0))
    views = [(0.0, 0.0), (30.0, 90.0), (40.0, 200.0)]
    cams = frame.origin + 2.0 * directions(frame, views)
    sun = 3.0 * directions(frame, [(45.0, 300.0)] * 3)
    n = 10
    visible = np.zeros((3, n), dtype=bool)
    visible[0, :8] = visible[1, :4] = visible[2] = True
    lit = np.ones((3, n), dtype=bool)
    lit[:, :2] = False
    vis = Visibility(visible=visible, lit=lit, mu0=np.ones((3, n)), mu=np.ones((3, n)), phase=np.zeros((3, n)))
    in_frame = np.ones((3, n), dtype=bool)
    in_frame[2, 5:] = False
    geom = maplet_geometry(frame, vis, camera_positions=cams, sun_directions=sun,
                           pixel_scale_km=np.array([1e-4, 2e-4, 4e-4]), spacing_km=2e-4, in_frame=in_frame)
    assert geom.emission_deg == pytest.approx([0.0, 30.0, 40.0], abs=1e-9)
    assert geom.camera_azimuth_deg[1:] == pytest.approx([90.0, 200.0])
    assert geom.incidence_deg == pytest.approx([45.0] * 3) and geom.sun_azimuth_deg == pytest.approx([300.0] * 3)
    assert geom.resolution_ratio.tolist() == pytest.approx([0.5, 1.0, 2.0])
    assert geom.visible_fraction.tolist() == pytest.approx([0.8, 0.4, 0.5])
    assert geom.shadow_fraction.tolist() == pytest.approx([2 / 8, 2 / 4, 2 / 5])
    # the east view is seen from the east: the camera's longitude is larger than the maplet's
    assert unit_to_latlon(cams[1])[1] > 100.0
    # phase: angle between the directions to the camera and to the Sun
    to_cam = (cams[2] - frame.origin) / np.linalg.norm(cams[2] - frame.origin)
    assert geom.phase_deg[2] == pytest.approx(np.degrees(np.arccos(to_cam @ (sun[2] / 3.0))))


def test_five_views_and_region_weight():
    # 0, 1 near nadir (1 has the lower phase); 2-5 east, west, north, south; 6 a weaker east view
    geom = geometry(emission_deg=[3.0, 8.0, 25.0, 25.0, 25.0, 25.0, 30.0],
                    phase_deg=[40.0, 30.0, 50.0, 50.0, 50.0, 50.0, 50.0],
                    camera_azimuth_deg=[0.0, 0.0, 80.0, 275.0, 350.0, 185.0, 100.0],
                    sun_azimuth_deg=[60.0, 90.0, 120.0, 150.0, 100.0, 70.0, 130.0],
                    incidence_deg=[45.0, 45.0, 45.0, 45.0, 45.0, 45.0, 80.0])
    keep, _ = select_images(geom)
    weight = image_weights(geom)
    views = five_views(geom, weight, keep)
    assert (views.nadir, views.east, views.west, views.north, views.south) == (1, 2, 3, 4, 5)
    assert azimuth_spread_deg(geom.sun_azimuth_deg) == pytest.approx(90.0)
    assert azimuth_spread_deg(np.array([350.0, 10.0, 30.0])) == pytest.approx(40.0)
    full, factors = region_weight(geom, weight, keep, views)
    assert full == pytest.approx(1.0) and factors["sun"] == 1.0

    # without the west and south views, with one Sun azimuth, or with nothing usable: lower
    partial = keep.copy()
    partial[[3, 5]] = False
    w_partial, _ = region_weight(geom, weight, partial, five_views(geom, weight, partial))
    # 3 of 5 views, 5 images, Sun azimuths of the kept images over 70 deg
    assert w_partial == pytest.approx(0.6 * (RULES.sun_floor + (1 - RULES.sun_floor) * 70 / 90))
    one_sun = geometry(**{**{f: getattr(geom, f) for f in ("emission_deg", "phase_deg", "camera_azimuth_deg",
                                                            "incidence_deg")}, "sun_azimuth_deg": np.full(7, 90.0)})
    w_one_sun, _ = region_weight(one_sun, weight, keep, five_views(one_sun, weight, keep))
    assert w_one_sun == pytest.approx(RULES.sun_floor)
    none = np.zeros(7, dtype=bool)
    assert region_weight(geom, weight, none, five_views(geom, weight, none))[0] == RULES.min_region_weight
    assert 0 < RULES.min_region_weight < w_one_sun < full


def test_node_factors_exclude_occluded_and_shadow_and_soften_shadow_edges():
    n, spacing = 9, 1e-3
    lit = np.ones((2, n, n), dtype=bool)
    lit[0, 3:6, 3:6] = False
    visible = np.ones((2, n, n), dtype=bool)
    visible[1, :, 5:] = False
    vis = Visibility(visible=visible.reshape(2, -1), lit=lit.reshape(2, -1), mu0=np.ones((2, n * n)),
                     mu=np.ones((2, n * n)), phase=np.zeros((2, n * n)))
    ring = np.zeros((n, n), dtype=bool)
    ring[2:7, 2:7] = True
    ring[3:6, 3:6] = False
    dark_edge = np.zeros((n, n), dtype=bool)
    dark_edge[3:6, 3:6] = True
    dark_edge[4, 4] = False

    flat = np.zeros((n, n))
    assert slope_spread_deg(flat, spacing) < RULES.steep_slope_std_deg
    f = node_factors(vis, flat, spacing)
    assert np.all(f[0][ring] == RULES.shadow_edge_factor) and np.all(f[0][3:6, 3:6] == 0.0)
    assert np.all(f[0][~ring & lit[0]] == 1.0)
    assert np.all(f[1][:, 5:] == 0.0) and np.all(f[1][:, :5] == 1.0)

    # steep terrain: shadowed nodes next to lit ones keep a small weight, the innermost does not
    rough = np.random.default_rng(1).normal(scale=2 * spacing, size=(n, n))
    assert slope_spread_deg(rough, spacing) > RULES.steep_slope_std_deg
    f = node_factors(vis, rough, spacing)
    assert np.all(f[0][dark_edge] == RULES.shadow_keep_weight) and f[0][4, 4] == 0.0
    in_frame = np.ones((2, n * n), dtype=bool)
    in_frame[0, : n * 2] = False
    assert np.all(node_factors(vis, rough, spacing, in_frame=in_frame)[0][:2] == 0.0)


def grid_mesh(maplet: MapletGrid) -> Mesh:
    """The maplet's nodes as a mesh, two triangles per cell, outward along its z."""
    return Mesh(maplet.nodes_body().reshape(-1, 3), grid_faces(maplet.n, maplet.n))


def test_nodes_dark_in_an_image_are_shadows_whatever_the_shape_says():
    rng = np.random.default_rng(3)
    values = rng.uniform(0.8, 1.2, (2, 8, 8)) * np.array([1.0, 0.03])[:, None, None]  # bright and dim images
    values[0, 2:4, 5] = 0.02  # a cast shadow in the bright image: 2% of its median
    values[0, 0, 3] = 0.1     # a dim face turned from the Sun, lit all the same
    values[1, 6, 6] = 0.0006  # a shadow in the dim image, by its own median
    values[0, 7, 0] = np.nan  # no data
    weights = np.ones_like(values)
    weights[1, 0, 0] = 0.0    # not weighed: never dark, and not counted in the median
    values[1, 0, 0] = 0.0
    dark = dark_nodes(values, weights)
    assert sorted(zip(*np.nonzero(dark), strict=True)) == [(0, 2, 5), (0, 3, 5), (1, 6, 6)]


def test_shade_marks_shadows_and_plain_light_but_not_the_nodes_beside_a_shadows_edge():
    values = np.full((1, 9, 9), 1.0)
    values[0, 2:7, 2:7] = 0.01    # a shadow 5 nodes across
    values[0, 0, 8] = 0.2         # dim: neither shadow nor plainly lit
    visible = np.ones(values.shape, bool)
    visible[0, 8, 0] = False      # hidden: neither, whatever its value
    marks = shade(values, np.ones_like(values), visible)[0]
    dark, lit = marks < 0, marks > 0
    # the shadow's core (its outer ring borders light), the light away from the shadow's edge
    assert np.array_equal(np.argwhere(dark), np.argwhere(np.pad(np.ones((3, 3), bool), 3)))
    assert not lit[1:8, 1:8].any() and lit[0, 0] and lit[8, 8]
    assert marks[0, 8] == 0 and marks[8, 0] == 0


def test_weigh_maplet_on_real_shadows_and_occlusion():
    """A 20 m maplet with a 4 m boulder, seen from nadir and the four sides, lit from the east."""
    frame = local_frame(0.25 * latlon_to_unit(10.0, 30.0), latlon_to_unit(10.0, 30.0))
    n, spacing = 41, 5e-4
    axis = (np.arange(n) - 20) * spacing
    r2 = axis[None, :] ** 2 + axis[:, None] ** 2
    heights = 4e-3 * np.exp(-r2 / (2 * 1e-3**2))
    maplet = MapletGrid(name="boulder", frame=frame, spacing_km=spacing, heights=heights)
    tracer = RayTracer(grid_mesh(maplet))
    gy, gx = np.gradient(heights, spacing)
    normals = frame.to_body(np.column_stack([-gx.ravel(), -gy.ravel(), np.ones(n * n)])) - frame.origin
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    views = [(0.0, 0.0), (35.0, 90.0), (35.0, 270.0), (35.0, 0.0), (35.0, 180.0), (60.0, 45.0)]
    cams = frame.origin + 1.0 * directions(frame, views)
    sun = directions(frame, [(50.0, 70.0), (55.0, 100.0), (45.0, 130.0), (50.0, 160.0), (60.0, 80.0), (40.0, 90.0)])
    vis = node_visibility(tracer, maplet.nodes_body().reshape(-1, 3), normals, camera_positions=cams,
                          sun_directions=sun)
    geom = maplet_geometry(frame, vis, camera_positions=cams, sun_directions=sun,
                           pixel_scale_km=np.full(6, 4e-4), spacing_km=spacing)
    w = weigh_maplet(maplet, vis, geom)

    assert (~vis.visible[1:5]).sum() > 20 and (~vis.lit).sum() > 100  # the boulder hides and shadows
    assert w.keep.tolist() == [True] * 5 + [False]  # the last view is too oblique
    assert w.reasons[5][0].startswith("emission")
    assert (w.views.nadir, w.views.east, w.views.west, w.views.north, w.views.south) == (0, 1, 2, 3, 4)
    assert np.all(w.pixel[5] == 0.0)
    pixel = w.pixel.reshape(6, -1)
    assert np.all(pixel[~vis.visible] == 0.0)
    assert np.all(pixel[:5][vis.visible[:5] & vis.lit[:5]] > 0.0)
    assert np.all(pixel <= w.image[:, None] + 1e-15)
    assert 0.5 < w.region <= 1.0 and w.sun_spread_deg == pytest.approx(90.0, abs=1.0)
    # seen shadowed nodes get nothing in this moderate relief; the rim of the shadow keeps a small
    # weight when the relief counts as steep
    dark = (vis.visible & ~vis.lit)[:5]
    assert dark.sum() > 100 and np.all(pixel[:5][dark] == 0.0)
    steep = weigh_maplet(maplet, vis, geom, rules=Rules(steep_slope_std_deg=5.0))
    ratio = (steep.pixel.reshape(6, -1) / np.maximum(steep.image, 1e-300)[:, None])[:5][dark]
    assert set(np.round(ratio, 12)) == {0.0, RULES.shadow_keep_weight}
