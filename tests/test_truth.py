"""The truth asteroid: a Bennu radar body with a synthetic site patch, built at tiny sizes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

import pwm
from pwm.frames import latlon_to_unit, unit_to_latlon
from pwm.io.meshio import read_obj
from pwm.raytrace import RayTracer
from pwm.simulate.truth import Truth, build_base, build_truth, load, low_pass, low_pass_heights, sampled, save

BENNU = Path(pwm.__file__).parent / "data" / "shapes" / "bennu_radar_nolan2013_sbgat.obj"
SITE = dict(site_lat_deg=20.0, site_lon_deg=75.0, site_size_km=0.008, resolution_km=5e-5, base_edge_km=0.008,
            n_craters=2, n_boulders=4, steep_boulders=2)
MM = 1e-6


@pytest.fixture(scope="module")
def bennu():
    return read_obj(BENNU)


@pytest.fixture(scope="module")
def truth(bennu) -> Truth:
    return build_truth(base=bennu, seed=7, **SITE)


@pytest.fixture(scope="module")
def boulder_relief(bennu, truth) -> np.ndarray:
    """The boulders alone: the same seed without boulders leaves roughness and craters unchanged."""
    bare = build_truth(base=bennu, seed=7, **{**SITE, "n_boulders": 0, "steep_boulders": 0})
    return truth.height_km - bare.height_km


def grid_height(truth: Truth, height: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Height of the patch triangles (two per cell, split along the (i, j)-(i+1, j+1) diagonal)."""
    fx = (x - truth.x_km[0]) / truth.resolution_km
    fy = (y - truth.y_km[0]) / truth.resolution_km
    j = np.minimum(fx.astype(int), len(truth.x_km) - 2)
    i = np.minimum(fy.astype(int), len(truth.y_km) - 2)
    fx, fy = fx - j, fy - i
    ha, hb, hc, hd = height[i, j], height[i, j + 1], height[i + 1, j + 1], height[i + 1, j]
    return np.where(fx >= fy, ha + fx * (hb - ha) + fy * (hc - hb), ha + fy * (hd - ha) + fx * (hc - hd))


def drop_rays(tracer: RayTracer, truth: Truth, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Height along the site normal of the first surface under local (x, y), nan on a miss."""
    top = truth.height_km.max() + 0.01
    frame = truth.site_frame
    origins = frame.to_body(np.column_stack([x, y, np.full(len(x), top)]))
    hits = tracer.intersect(origins, np.broadcast_to(-frame.normal, origins.shape))
    return np.where(hits.hit, top - hits.t, np.nan)


def test_same_seed_same_truth_other_seed_other_terrain(bennu, truth):
    again = build_truth(base=bennu, seed=7, **SITE)
    assert np.array_equal(again.mesh.vertices, truth.mesh.vertices)
    assert np.array_equal(again.mesh.faces, truth.mesh.faces)
    assert np.array_equal(again.mesh.albedo, truth.mesh.albedo)
    assert again.boulders == truth.boulders and again.craters == truth.craters
    other = build_truth(base=bennu, seed=8, **SITE)
    assert other.boulders != truth.boulders
    assert np.abs(other.height_km - truth.height_km).max() > 0.1e-3


def test_site_frame_is_east_north_up_at_the_requested_site(truth):
    frame = truth.site_frame
    x, y, z = frame.rotation
    assert abs(x[2]) < 1e-12
    east = np.cross([0.0, 0.0, 1.0], latlon_to_unit(SITE["site_lat_deg"], SITE["site_lon_deg"]))
    assert x @ east / np.linalg.norm(east) > 0.9
    lat, lon = unit_to_latlon(frame.origin)
    assert lat == pytest.approx(SITE["site_lat_deg"], abs=1e-6)
    assert lon == pytest.approx(SITE["site_lon_deg"], abs=1e-6)
    # z is the regional normal: the ground of the site, seen in its frame, is level on average
    ground = truth.height_km
    xx, yy = np.meshgrid(truth.x_km, truth.y_km)
    inside = np.hypot(xx, yy) <= truth.eval_radius_km
    design = np.column_stack([xx[inside], yy[inside], np.ones(inside.sum())])
    slope_x, slope_y, _ = np.linalg.lstsq(design, ground[inside], rcond=None)[0]
    assert np.degrees(np.arctan(np.hypot(slope_x, slope_y))) < 3.0  # the radial direction is 7 deg off here


def test_patch_has_no_holes_overhangs_or_seams(truth):
    rng = np.random.default_rng(0)
    half = truth.x_km[-1]
    x, y = rng.uniform(-half, half, (2, 20000))
    tracer = RayTracer(truth.mesh)
    hit = drop_rays(tracer, truth, x, y)
    assert np.isfinite(hit).all()
    error = np.abs(hit - grid_height(truth, truth.height_km, x, y))
    band = np.maximum(np.abs(x), np.abs(y)) > half - truth.zero_band_km
    assert error[~band].max() < 0.1 * MM  # Embree's single precision
    # where base and patch overlap at the border, both lie on the patch surface within the error
    # of sampling the base facets' creases at the grid spacing
    assert error[band].max() < 2 * MM

    # oblique views from 40 degrees off the normal, four azimuths, all see the surface
    frame = truth.site_frame
    targets = frame.to_body(np.column_stack([x[:4000], y[:4000],
                                             grid_height(truth, truth.height_km, x[:4000], y[:4000])]))
    for az in np.radians([0.0, 90.0, 180.0, 270.0]):
        look = np.array([np.sin(0.7) * np.cos(az), np.sin(0.7) * np.sin(az), np.cos(0.7)]) @ frame.rotation
        eye = targets.mean(axis=0) + 0.2 * look
        assert tracer.intersect(np.broadcast_to(eye, targets.shape), targets - eye).hit.all()

    # the base is closed but for the hole under the patch: refining it left no cracks
    base = truth.mesh.faces[: truth.n_base_faces]
    edges = np.sort(np.concatenate([base[:, [0, 1]], base[:, [1, 2]], base[:, [2, 0]]]), axis=1)
    edges, count = np.unique(edges, axis=0, return_counts=True)
    assert count.max() == 2
    rim = frame.to_local(truth.mesh.vertices[np.unique(edges[count == 1])])
    assert len(rim) > 0 and np.abs(rim[:, :2]).max() <= half

    patch = truth.mesh.faces[truth.n_base_faces :]
    assert patch.min() == truth.n_base_vertices
    assert (truth.mesh.face_normals()[truth.n_base_faces :] @ frame.normal > 0).all()
    edges = np.sort(np.concatenate([patch[:, [0, 1]], patch[:, [1, 2]], patch[:, [2, 0]]]), axis=1)
    _, count = np.unique(edges, axis=0, return_counts=True)
    ny, nx = truth.height_km.shape
    border_edges = 2 * (nx - 1) + 2 * (ny - 1)
    assert (count == 1).sum() == border_edges and (count == 2).sum() == len(count) - border_edges


def test_boulders_reach_their_heights(truth, boulder_relief):
    assert sum(b.steep for b in truth.boulders) == SITE["steep_boulders"]
    xx, yy = np.meshgrid(truth.x_km, truth.y_km)
    footprint = np.zeros(xx.shape, dtype=bool)
    for b in truth.boulders:
        assert 0.5e-3 <= b.height_km <= 3e-3 and 1e-3 <= b.diameter_km <= 6e-3
        assert max(abs(b.x_km), abs(b.y_km)) + b.diameter_km / 2 <= truth.site_size_km / 2
        i, j = np.argmin(np.abs(truth.y_km - b.y_km)), np.argmin(np.abs(truth.x_km - b.x_km))
        assert boulder_relief[i, j] > 0.97 * b.height_km
        disc = np.hypot(xx - b.x_km, yy - b.y_km) < b.diameter_km / 2
        assert boulder_relief[disc].max() <= b.height_km * (1 + 1e-9)
        footprint |= disc
    assert np.abs(boulder_relief[~footprint]).max() < 1e-12


def side_slope_deg(truth: Truth, relief: np.ndarray, boulder, azimuth: float) -> float:
    """Mean slope between 80 % and 20 % of the boulder's height along a ray from its centre."""
    r = np.arange(0.0, 0.7 * boulder.diameter_km, truth.resolution_km / 8)
    x = boulder.x_km + r * np.cos(azimuth)
    y = boulder.y_km + r * np.sin(azimuth)
    rows = (y - truth.y_km[0]) / truth.resolution_km
    cols = (x - truth.x_km[0]) / truth.resolution_km
    z = ndimage.map_coordinates(relief, [rows, cols], order=1) / boulder.height_km
    r80 = r[np.argmax(z < 0.8)]
    r20 = r[np.argmax(z < 0.2)]
    return float(np.degrees(np.arctan(0.6 * boulder.height_km / max(r20 - r80, 1e-12))))


def test_steep_boulders_have_sides_above_60_degrees_and_rounded_ones_below(truth, boulder_relief):
    for b in truth.boulders:
        slopes = [side_slope_deg(truth, boulder_relief, b, az) for az in np.radians(np.arange(0, 360, 45))]
        if b.steep:
            assert min(slopes) > 60.0
        else:
            assert max(slopes) < 60.0


def test_low_pass_is_a_smooth_valid_model_away_from_the_truth(truth):
    rng = np.random.default_rng(1)
    half = truth.x_km[-1]
    x, y = rng.uniform(-half, half, (2, 20000))
    truth_h = grid_height(truth, truth.height_km, x, y)
    site = np.hypot(x, y) <= truth.eval_radius_km
    amplitude = max(b.height_km for b in truth.boulders) + max(c.depth_km for c in truth.craters)
    rms = {}
    for wavelength in (0.5e-3, 2e-3):
        model = low_pass(truth, wavelength_km=wavelength)
        assert model.albedo is None and model.faces.max() < len(model.vertices)
        tracer = RayTracer(model)
        h = drop_rays(tracer, truth, x, y)
        assert np.isfinite(h).all()
        d = h - truth_h
        rms[wavelength] = np.sqrt(np.mean(d[site] ** 2))
        assert np.abs(d).max() < amplitude
    assert rms[0.5e-3] > 0.01e-3
    assert rms[2e-3] > 2 * rms[0.5e-3]
    # the coarse nodes (every 1 m, on fine nodes here) carry the low-passed heights
    smooth = low_pass_heights(truth, wavelength_km=2e-3)
    step = round(1e-3 / truth.resolution_km)
    xx, yy = np.meshgrid(truth.x_km[::step], truth.y_km[::step])
    assert np.abs(drop_rays(tracer, truth, xx.ravel(), yy.ravel()) - smooth[::step, ::step].ravel()).max() < 0.1 * MM
    # and the low-passed heights are the truth's in the border band, where they meet the base
    band = truth.blend_weight() == 0
    assert np.array_equal(smooth[band], truth.height_km[band])


def test_sampled_truth_holds_the_cell_averages_at_its_nodes(truth):
    same = sampled(truth, spacing_km=truth.resolution_km, average_km=truth.resolution_km)
    assert np.array_equal(same.vertices, truth.mesh.vertices) and np.array_equal(same.faces, truth.mesh.faces)
    assert np.array_equal(same.albedo, truth.mesh.albedo)

    step = 3
    coarse = sampled(truth, spacing_km=step * truth.resolution_km, average_km=step * truth.resolution_km)
    xx, yy = np.meshgrid(truth.x_km[::step], truth.y_km[::step])
    assert len(coarse.vertices) == truth.n_base_vertices + xx.size
    average = ndimage.uniform_filter(truth.height_km, step, mode="nearest")[::step, ::step]
    site = np.hypot(xx, yy) <= truth.eval_radius_km  # the border band lies on the base faces
    # rays just beside the nodes: exactly on a vertex, single precision lets some slip through
    nudge = 1e-4 * truth.resolution_km
    h = drop_rays(RayTracer(coarse), truth, xx[site] + 1.3 * nudge, yy[site] + 0.7 * nudge)
    assert np.abs(h - average[site]).max() < 0.1 * MM
    patch = coarse.albedo[truth.n_base_vertices:].reshape(xx.shape)
    assert patch[1, 1] == pytest.approx(truth.albedo_grid[2:5, 2:5].mean(), rel=1e-12)
    assert np.array_equal(coarse.albedo[:truth.n_base_vertices], truth.mesh.albedo[:truth.n_base_vertices])


def test_save_and_load_round_trip(truth, tmp_path):
    save(truth, tmp_path / "truth")
    back = load(tmp_path / "truth")
    assert np.array_equal(back.mesh.vertices, truth.mesh.vertices)
    assert np.array_equal(back.mesh.faces, truth.mesh.faces)
    np.testing.assert_allclose(back.mesh.albedo, truth.mesh.albedo, rtol=1e-6)
    np.testing.assert_array_equal(back.height_km, truth.height_km)
    np.testing.assert_array_equal(back.site_frame.rotation, truth.site_frame.rotation)
    np.testing.assert_array_equal(back.site_frame.origin, truth.site_frame.origin)
    assert back.boulders == truth.boulders and back.craters == truth.craters
    assert (back.site_size_km, back.eval_radius_km, back.zero_band_km) == (
        truth.site_size_km, truth.eval_radius_km, truth.zero_band_km)
    assert back.params == truth.params
    np.testing.assert_allclose(back.albedo_grid, truth.albedo_grid, rtol=1e-6)


def test_global_roughness_has_the_requested_rms_and_low_passes_on_the_same_body(bennu):
    smooth = build_base(bennu, base_edge_km=0.008, seed=3)
    rough = build_base(bennu, base_edge_km=0.008, seed=3, global_roughness_km=2e-3)
    start = build_base(bennu, base_edge_km=0.008, seed=3, global_roughness_km=2e-3, low_pass_km=0.1)
    assert np.array_equal(rough.faces, smooth.faces) and np.array_equal(rough.albedo, smooth.albedo)
    radial = smooth.vertices / np.linalg.norm(smooth.vertices, axis=1, keepdims=True)
    bump = np.einsum("ij,ij->i", rough.vertices - smooth.vertices, radial)
    bump_start = np.einsum("ij,ij->i", start.vertices - smooth.vertices, radial)
    assert 1e-3 < np.sqrt(np.mean(bump**2)) < 3e-3
    assert 0.0 < np.sqrt(np.mean((bump - bump_start) ** 2)) < np.sqrt(np.mean(bump**2))
    assert np.abs(np.mean(smooth.albedo) / 0.044 - 1) < 0.1
    assert 0.05 < np.std(np.log(smooth.albedo)) < 0.25


def test_large_boulders_are_the_largest_about_them_and_leave_the_others_as_they_were():
    from pwm.simulate.terrain import (
        LARGE_BOULDER_DIAMETER_KM,
        LARGE_BOULDER_HEIGHT_KM,
        add_large_boulders,
        sample_boulders,
    )

    site = dict(site_size_km=0.05, resolution_km=2.5e-5)
    others = sample_boulders(np.random.default_rng(1), n=100, n_steep=25, **site)
    placed = add_large_boulders(np.random.default_rng(2), others, n=4, clearance_km=0.01, **site)
    assert placed == add_large_boulders(np.random.default_rng(2), others, n=4, clearance_km=0.01, **site)
    assert add_large_boulders(np.random.default_rng(2), others, n=0, clearance_km=0.01, **site) == others
    large, kept = placed[:4], placed[4:]
    assert set(kept) < set(others) and len(kept) >= 80  # only the boulders in their way are dropped
    for big in large:
        assert LARGE_BOULDER_DIAMETER_KM[0] <= big.diameter_km <= LARGE_BOULDER_DIAMETER_KM[1]
        assert LARGE_BOULDER_HEIGHT_KM[0] <= big.height_km <= LARGE_BOULDER_HEIGHT_KM[1]
        assert max(abs(big.x_km), abs(big.y_km)) <= 0.0125  # well inside the site and its evaluation disc
        for b in placed:
            gap = np.hypot(b.x_km - big.x_km, b.y_km - big.y_km)
            if b is not big:
                assert gap > (b.diameter_km + big.diameter_km) / 2  # no overlap
                assert gap >= 0.01 or b.diameter_km < big.diameter_km  # the largest within a maplet's side
    with pytest.raises(ValueError, match="cannot place"):
        add_large_boulders(np.random.default_rng(2), [], n=4, clearance_km=0.03, **site)
