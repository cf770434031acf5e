"""Volumetric fusion into one closed surface (pwm.volume) on a body that is not star-shaped."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import trimesh
from skimage.measure import marching_cubes

import pwm.evaluate.closure as closure_module
from pwm.evaluate.closure import closure, self_intersections
from pwm.frames import local_frame
from pwm.fusion import VoxelGrid
from pwm.maplets import MapletGrid
from pwm.mesh import Mesh, refine_faces
from pwm.raytrace import RayTracer
from pwm.tiling import sample_surface, tile
from pwm.volume import FADE_VOXELS, TRUNCATION_VOXELS, DistanceGrid, grid_for
from pwm.voxels import unpack

# Two lobes of radius 0.1 km, 0.4 km apart, joined by a neck of radius 0.045 km: rays from the
# centre at 23-29 degrees from the long axis leave the neck, enter a lobe and leave it.
LOBE, CENTRE, NECK = 0.1, 0.2, 0.045
SPACING, NODES = 0.004, 11


def dumbbell_distance(p: np.ndarray, grow: float = 0.0) -> np.ndarray:
    a = np.linalg.norm(p - [CENTRE, 0, 0], axis=-1) - LOBE
    b = np.linalg.norm(p + [CENTRE, 0, 0], axis=-1) - LOBE
    neck = np.maximum(np.hypot(p[..., 1], p[..., 2]) - NECK, np.abs(p[..., 0]) - CENTRE)
    return np.minimum(np.minimum(a, b), neck) - grow


def dumbbell(step: float, grow: float = 0.0) -> Mesh:
    x = np.arange(-0.33, 0.33 + step, step)
    yz = np.arange(-0.13, 0.13 + step, step)
    grid = np.stack(np.meshgrid(x, yz, yz, indexing="ij"), axis=-1)
    v, f, _, _ = marching_cubes(dumbbell_distance(grid, grow), 0.0, spacing=(step,) * 3,
                                gradient_direction="descent", allow_degenerate=False)
    return Mesh(v + [x[0], yz[0], yz[0]], f)


@pytest.fixture(scope="module")
def truth() -> Mesh:
    return dumbbell(0.0025)


@pytest.fixture(scope="module")
def maplets(truth: Mesh) -> list[MapletGrid]:
    """Maplets every third of a side over the whole truth, each a height field sampled from above,
    with albedo varying along the body."""
    tracer = RayTracer(truth)
    half = 0.5 * (NODES - 1) * SPACING
    cell = np.floor(truth.vertices / (half / 1.5)).astype(np.int64)
    _, first = np.unique(cell, axis=0, return_index=True)
    normals = truth.vertex_normals()
    out = []
    for k in first:
        m = MapletGrid(name=f"m{k}", frame=local_frame(truth.vertices[k], normals[k]), spacing_km=SPACING,
                       heights=np.zeros((NODES, NODES)))
        m.heights, _ = sample_surface(tracer, m)
        m.albedo = np.full_like(m.heights, 0.04 + 0.1 * truth.vertices[k, 0])
        out.append(m)
    return out


def crossings(mesh: Mesh, origin: np.ndarray, direction: np.ndarray) -> int:
    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    return len(tm.ray.intersects_location(origin[None], direction[None], multiple_hits=True)[0])


def neck_radius(mesh: Mesh) -> np.ndarray:
    angle = np.linspace(0.0, 2 * np.pi, 48, endpoint=False)
    out = np.column_stack([np.zeros_like(angle), np.cos(angle), np.sin(angle)])
    hits = RayTracer(mesh).intersect(np.zeros_like(out), out)
    return np.where(hits.hit, hits.t, np.inf)


def test_a_body_that_is_not_star_shaped_keeps_its_shape_and_closes(truth, maplets):
    ray = np.array([np.cos(np.radians(26)), np.sin(np.radians(26)), 0.0])
    assert crossings(truth, np.zeros(3), ray) == 3  # the test body is what it says
    grid = DistanceGrid(SPACING)
    grid.add_all(maplets)
    fused = grid.mesh()
    checks = closure(fused)
    assert checks.closed, checks
    assert checks.volume_km3 == pytest.approx(closure(truth).volume_km3, rel=0.01)
    assert np.abs(neck_radius(fused) - NECK).max() <= 2 * SPACING
    assert crossings(fused, np.zeros(3), ray) == 3
    # albedo follows the maplets: 0.04 + 0.1 x at the lobes' far ends
    ends = np.abs(fused.vertices[:, 0]) > 0.29
    assert fused.albedo is not None
    np.testing.assert_allclose(fused.albedo[ends], 0.04 + 0.1 * fused.vertices[ends, 0], atol=0.003)
    # the height fields over the sphere of directions lose the neck and do not close
    height_field = VoxelGrid(SPACING)
    height_field.add_all(maplets)
    flattened = height_field.mesh()
    assert not np.isfinite(neck_radius(flattened)).any() or not closure(flattened).closed


def test_places_no_maplet_reaches_keep_the_base_and_the_surface_closes(truth, maplets):
    base = dumbbell(0.006, grow=SPACING)  # a coarser, fatter earlier model
    lobe = [m for m in maplets if m.frame.origin[0] > 0.2]  # only the +x lobe's far half was seen
    grid = DistanceGrid(SPACING)
    grid.add_all(lobe)
    fused = grid.mesh(base)
    assert closure(fused).closed
    # on the seen lobe's axis the surface is the maplets' (the truth), on the other the base's
    hits = RayTracer(fused).intersect(np.array([[0.0, 0, 0], [0.0, 0, 0]]), np.array([[1.0, 0, 0], [-1.0, 0, 0]]))
    assert hits.t[0] == pytest.approx(CENTRE + LOBE, abs=0.25 * SPACING)
    assert hits.t[1] == pytest.approx(CENTRE + LOBE + SPACING, abs=0.5 * SPACING)


def test_one_far_off_maplet_widens_the_base_only_about_itself(truth, maplets):
    # a maplet 20 spacings off the base (a misplaced one) bends the base towards it over a band
    # that wide about itself (once everywhere, which took a global survey's fusion from 20 s to
    # 160 s); the base's lattice away from it is as it was
    base = dumbbell(0.006, grow=SPACING)
    lobe = [m for m in maplets if m.frame.origin[0] > 0.2]
    grid = DistanceGrid(SPACING)
    grid.add_all(lobe)
    plain = grid._base_sums(base)[0]
    far = dataclasses.replace(lobe[0], name="far", heights=lobe[0].heights + 20 * SPACING)
    grid.add(far)
    bent = grid._base_sums(base)[0]
    reach = 5 * (FADE_VOXELS + TRUNCATION_VOXELS) * SPACING  # the bins about it, and a band as wide

    def away(keys: np.ndarray) -> np.ndarray:
        return keys[np.linalg.norm(unpack(keys) * SPACING - far.frame.origin, axis=1) > reach]

    assert len(away(plain)) > 0.3 * len(plain) and np.array_equal(away(bent), away(plain))
    assert len(bent) > 1.2 * len(plain)  # and about it, the band is wider
    assert closure(grid.mesh(base)).closed


def test_maplets_misplaced_by_many_voxels_still_close(truth, maplets):
    # maplets raised or lowered by up to 25 voxels (a placement gone wrong) bend the base far out
    # of its band, where cells the surface crosses once lacked corners (open with seed 0 before)
    rng = np.random.default_rng(0)
    lobe = [dataclasses.replace(m, heights=m.heights + rng.choice([0, 0, 0, 8, 15, 25, -10]) * SPACING)
            for m in maplets if m.frame.origin[0] > 0.2]
    grid = DistanceGrid(SPACING)
    grid.add_all(lobe)
    assert closure(grid.mesh(dumbbell(0.006, grow=SPACING))).closed


def test_a_rough_low_poly_base_still_closes():
    # a start model's coarse faces meeting at sharp angles (radial noise of 10% on 1280 faces),
    # under five maplets: lattice points between the base's samples once went without a
    # distance, and cells the surface crossed there without a corner (not watertight with
    # seeds 0-3 before)
    rng = np.random.default_rng(0)
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.25)
    base = Mesh(np.asarray(sphere.vertices) * (1 + 0.1 * rng.uniform(-1, 1, (len(sphere.vertices), 1))),
                np.asarray(sphere.faces))
    grid = DistanceGrid(voxel_km=0.004, taper_fraction=0.25)
    grid.add_all(tile(base, spacing_km=0.004, nodes=60, centre_lat_deg=0.0, centre_lon_deg=0.0, radius_km=0.1))
    assert closure(grid.mesh(base)).closed


def test_a_revision_is_replaced_exactly_and_the_choice_of_fusion_follows_the_lattice(truth, maplets):
    maplets = [m for m in maplets if m.frame.origin[0] > 0.25]
    fresh, incremental = DistanceGrid(SPACING), DistanceGrid(SPACING)
    incremental.add_all(maplets)
    old = maplets[7]
    new = MapletGrid(name=old.name, frame=old.frame, spacing_km=SPACING, heights=old.heights + 0.001,
                     albedo=old.albedo, weight=0.5)
    incremental.subtract(old)
    incremental.add(new)
    fresh.add_all(maplets[:7] + [new] + maplets[8:])
    np.testing.assert_array_equal(incremental.keys, fresh.keys)
    np.testing.assert_array_equal(incremental.count, fresh.count)
    np.testing.assert_allclose(incremental.sums, fresh.sums, rtol=1e-9, atol=1e-12)
    with pytest.raises(ValueError, match="not added"):
        DistanceGrid(SPACING).subtract(old)
    # a whole body at its own maplets' spacing is one closed surface; centimetre maplets on the
    # same body are a region stitched into it
    assert isinstance(grid_for(truth, voxel_km=SPACING, taper_fraction=0.25), DistanceGrid)
    assert isinstance(grid_for(truth, voxel_km=SPACING / 100, taper_fraction=0.25), VoxelGrid)


def test_the_closure_checks_see_what_they_check():
    sphere = trimesh.creation.icosphere(3, 1.0)
    other = sphere.copy()
    other.apply_translation([1.0, 0.013, 0.0071])
    both = trimesh.util.concatenate([sphere, other])
    crossed = closure(Mesh(np.asarray(both.vertices), np.asarray(both.faces)))
    assert crossed.watertight and crossed.self_intersections > 0 and not crossed.closed
    faces = np.asarray(sphere.faces)
    assert not closure(Mesh(np.asarray(sphere.vertices), faces[1:])).watertight
    inward = closure(Mesh(np.asarray(sphere.vertices), faces[:, ::-1]))
    assert inward.winding_consistent and not inward.outward
    flipped = faces.copy()
    flipped[0] = flipped[0, ::-1]
    assert not closure(Mesh(np.asarray(sphere.vertices), flipped)).winding_consistent


def test_self_intersections_counted_in_slabs_are_those_counted_at_once(monkeypatch):
    # two spheres through each other: every crossing pair counted once, whatever the slabs
    a, b = trimesh.creation.icosphere(3, 1.0), trimesh.creation.icosphere(3, 0.8)
    b.apply_translation([0.9, 0.1, 0.05])
    both = Mesh(np.vstack([a.vertices, b.vertices]), np.vstack([a.faces, np.asarray(b.faces) + len(a.vertices)]))
    whole = self_intersections(both)
    assert whole > 100
    monkeypatch.setattr(closure_module, "_SLAB_FACES", 97)
    assert self_intersections(both) == whole


def test_the_self_intersection_check_holds_a_dense_site_on_a_coarse_body():
    # a site's centimetre faces on a body of metre ones (as levels make): counted pair by pair,
    # not every small face against every other within a large face's size
    sphere = trimesh.creation.icosphere(2, 1.0)
    body = Mesh(np.asarray(sphere.vertices), np.asarray(sphere.faces))
    site = body.vertices[body.faces].mean(axis=1)[:, 2] > 0.95
    dense, _ = refine_faces(body, site, max_edge_km=0.004)
    assert len(dense.faces) > 50_000
    assert closure(dense).closed
    pebble = trimesh.creation.icosphere(2, 0.01)
    pebble.apply_translation(dense.vertices[dense.faces[-1]].mean(axis=0) + [0.0013, 0.0007, 0.0])
    crossed = Mesh(np.vstack([dense.vertices, pebble.vertices]),
                   np.vstack([dense.faces, np.asarray(pebble.faces) + len(dense.vertices)]))
    assert closure(crossed).self_intersections > 0
