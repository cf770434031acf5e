"""Tiling a shape into overlapping maplets: frames, heights on the surface, coverage, names."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

import pwm
from pwm.frames import LocalFrame, latlon_to_unit, local_frame
from pwm.io.meshio import read_obj
from pwm.maplets import MapletGrid
from pwm.mesh import Mesh
from pwm.raytrace import RayTracer
from pwm.tiling import level_of, sample_heights, sample_surface, tile

BENNU = Path(pwm.__file__).parent / "data" / "shapes" / "bennu_radar_nolan2013_sbgat.obj"
R = 0.25


@pytest.fixture(scope="module")
def sphere() -> Mesh:
    s = trimesh.creation.icosphere(subdivisions=5, radius=R)
    return Mesh(s.vertices, s.faces, 0.04 + 0.01 * s.vertices[:, 0] / R)


@pytest.fixture(scope="module")
def bennu() -> Mesh:
    return read_obj(BENNU)


def sag(mesh: Mesh) -> float:
    """Largest gap (km) between a facet of the icosphere and its sphere."""
    edge = mesh.mean_edge_length() * 1.2
    return edge**2 / (8 * R) + edge**2 / (6 * R)


def covered(maplets: list[MapletGrid], points: np.ndarray) -> np.ndarray:
    """Points over some maplet's square, within its half-size of its plane."""
    out = np.zeros(len(points), dtype=bool)
    for m in maplets:
        half = m.axis_km[-1]
        out |= np.all(np.abs(m.frame.to_local(points)) <= half, axis=1)
    return out


def test_region_tiles_are_on_the_surface_in_local_frames(sphere):
    maplets = tile(sphere, spacing_km=0.001, nodes=11, centre_lat_deg=30.0, centre_lon_deg=45.0, radius_km=0.02)
    assert 9 <= len(maplets) < 60
    for m in maplets:
        x, y, z = m.frame.rotation
        assert abs(x[2]) < 1e-12 and x @ np.cross([0, 0, 1.0], m.frame.origin) > 0  # x along the equator, east
        assert np.allclose(m.frame.rotation @ m.frame.rotation.T, np.eye(3)) and np.linalg.det(m.frame.rotation) > 0
        radial = m.frame.origin / np.linalg.norm(m.frame.origin)
        # the regional normal of a faceted sphere: radial within the angle a facet spans
        assert np.arccos(min(1.0, z @ radial)) < sphere.mean_edge_length() / R
        # origin and every node on the faceted sphere
        assert abs(np.linalg.norm(m.frame.origin) - R) < sag(sphere)
        assert np.abs(np.linalg.norm(m.nodes_body(), axis=2) - R).max() < sag(sphere)
        assert m.meta["filled_nodes"] == 0 and m.heights.shape == (11, 11)
        assert np.allclose(m.albedo, 0.04 + 0.01 * m.nodes_body()[..., 0] / R, atol=2e-5)
        assert all(np.array_equal(m.node_body(i, j), m.nodes_body()[i, j]) for i, j in ((0, 0), (5, 5), (2, 9)))
    # neighbours one step of (1 - overlap) * size apart
    origins = np.array([m.frame.origin for m in maplets])
    d = np.linalg.norm(origins[:, None] - origins[None], axis=2)
    np.fill_diagonal(d, np.inf)
    assert np.median(d.min(axis=1)) == pytest.approx(0.75 * 0.01, rel=0.02)
    # every point of the disc is covered
    rng = np.random.default_rng(0)
    dirs = latlon_to_unit(30.0 + rng.uniform(-6, 6, 4000), 45.0 + rng.uniform(-8, 8, 4000))
    centre = latlon_to_unit(30.0, 45.0)
    points = R * dirs[np.arccos(np.clip(dirs @ centre, -1, 1)) * R <= 0.02]
    assert len(points) > 1000 and covered(maplets, points).all()


def test_retiling_is_deterministic_and_names_are_unique(sphere):
    kwargs = dict(spacing_km=0.001, nodes=11, centre_lat_deg=-20.0, centre_lon_deg=300.0, radius_km=0.015)
    a, b = tile(sphere, **kwargs), tile(sphere, **kwargs)
    assert [m.name for m in a] == [m.name for m in b]
    assert len({m.name for m in a}) == len(a)
    assert all(np.array_equal(p.heights, q.heights) and np.array_equal(p.frame.rotation, q.frame.rotation)
               for p, q in zip(a, b, strict=True))
    lat = float(a[0].name[1:9])
    assert lat < -15.0 and a[0].name[9] == "E"
    # the level closes the name: 1 m is level 0, and the same place at 25 cm is another maplet
    assert a[0].name.endswith("L+0")
    quarter = tile(sphere, **(kwargs | {"spacing_km": 0.00025, "nodes": 41}))
    assert quarter[0].name.endswith("L-2") and not {m.name for m in quarter} & {m.name for m in a}


def test_levels_are_the_nearest_powers_of_two():
    spacing_m = np.array([0.05, 0.1, 0.125, 0.17, 0.18, 0.5, 0.7, 0.72, 1.0, 2.0, 2.8])
    assert level_of(spacing_m * 1e-3).tolist() == [-4, -3, -3, -3, -2, -1, -1, 0, 0, 1, 1]
    assert int(level_of(2e-3)) == 1


def test_whole_body_is_covered(bennu):
    maplets = tile(bennu, spacing_km=0.004, nodes=11)
    size = 0.04
    assert 0.6 * bennu.face_areas().sum() / size**2 < len(maplets) < 4 * bennu.face_areas().sum() / size**2
    # random surface points seen from outside, independent of the tiling's own samples
    rng = np.random.default_rng(3)
    d = rng.normal(size=(20000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    tracer = RayTracer(bennu)
    hits = tracer.intersect(d, -d)
    points = tracer.hit_points(d, -d, hits)[hits.hit]
    assert covered(maplets, points).all()
    # nodes lie on the surface: a ray cast down from just above each node meets it at once
    m = maplets[len(maplets) // 2]
    above = m.nodes_body().reshape(-1, 3) + 1e-4 * m.frame.normal
    t = tracer.intersect(above, np.broadcast_to(-m.frame.normal, above.shape)).t
    assert np.allclose(t, 1e-4, atol=1e-6)


def test_sample_heights_fills_misses_and_follows_the_model():
    # an open tilted plane, z = 0.25 + 0.1 x (km), 10 m square; the maplet hangs 2 m over its +x edge
    axis = np.linspace(-0.005, 0.005, 11)
    x, y = np.meshgrid(axis, axis)
    n = len(axis)
    c = np.arange(n * n).reshape(n, n)[:-1, :-1].ravel()
    plane = Mesh(np.column_stack([x.ravel(), y.ravel(), 0.25 + 0.1 * x.ravel()]),
                 np.vstack([np.column_stack([c, c + 1, c + n + 1]), np.column_stack([c, c + n + 1, c + n])]))
    frame = LocalFrame(origin=np.array([0.00325, 0.0, 0.2503]), rotation=np.eye(3))
    maplet = MapletGrid(name="edge", frame=frame, spacing_km=0.0005, heights=np.zeros((17, 17)))
    h = sample_heights(plane, maplet)
    xs = maplet.axis_km + 0.00325
    on = xs < 0.005
    assert 3 <= (~on).sum() <= 5
    expected = 0.25 + 0.1 * np.where(on, xs, xs[on].max()) - 0.2503
    assert np.allclose(h, expected[None, :], atol=3e-8)  # float32 hits
    assert np.array_equal(sample_heights(RayTracer(plane), maplet), h)
    assert sample_surface(plane, maplet)[1] is None
    # a model 1 m higher everywhere gives heights 1 m higher (the plane's normal is tilted by 5.7 deg)
    lifted = Mesh(plane.vertices + [0.0, 0.0, 0.001], plane.faces)
    assert np.allclose(sample_heights(lifted, maplet), h + 0.001, atol=3e-8)


def test_a_node_over_a_pinhole_is_filled_not_dropped_to_the_far_side(sphere):
    # one face of the sphere missing under a maplet: the ray there would meet the far side 0.5 km down
    up = latlon_to_unit(10.0, 40.0)
    face = int(RayTracer(sphere).intersect(2 * R * up[None], -up[None]).face[0])
    holed = Mesh(sphere.vertices, np.delete(sphere.faces, face, axis=0))
    frame = local_frame(R * up, up)
    maplet = MapletGrid(name="hole", frame=frame, spacing_km=0.0005, heights=np.zeros((21, 21)))
    whole, holed_h = sample_heights(sphere, maplet), sample_heights(holed, maplet)
    assert np.abs(holed_h - whole).max() < 0.002  # within the missing face's sag and size, not 0.5 km


def test_a_region_over_a_pinhole_puts_no_maplet_on_the_far_side(sphere):
    # the hole under one maplet's origin of the whole sphere's tiling: that centre's ray would meet
    # the far side 0.5 km down, and a maplet would be tiled there
    kw = dict(spacing_km=0.001, nodes=11, centre_lat_deg=30.0, centre_lon_deg=45.0, radius_km=0.02)
    origins = np.array([m.frame.origin for m in tile(sphere, **kw)])
    up = origins[np.argsort(np.linalg.norm(origins - origins.mean(axis=0), axis=1))[5]]
    up = up / np.linalg.norm(up)
    face = int(RayTracer(sphere).intersect(2 * R * up[None], -up[None]).face[0])
    holed = tile(Mesh(sphere.vertices, np.delete(sphere.faces, face, axis=0)), **kw)
    centre = R * latlon_to_unit(30.0, 45.0)
    assert len(holed) == len(origins)
    assert max(np.linalg.norm(m.frame.origin - centre) for m in holed) < 0.02 + 0.01

def test_bad_arguments_are_refused(sphere):
    with pytest.raises(ValueError):
        tile(sphere, spacing_km=0.001, nodes=11, centre_lat_deg=10.0, radius_km=0.01)
    with pytest.raises(ValueError):
        tile(sphere, spacing_km=0.001, nodes=11, overlap=1.0)
