"""Voxel fusion of maplets: weighted averages, exact incremental updates, hole-free meshes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from trimesh.remesh import subdivide_loop

import pwm
from pwm.frames import LocalFrame, latlon_to_unit
from pwm.fusion import VoxelGrid, edge_taper
from pwm.io.meshio import read_obj
from pwm.maplets import MapletGrid
from pwm.mesh import Mesh
from pwm.raytrace import RayTracer
from pwm.tiling import tile

BENNU = Path(pwm.__file__).parent / "data" / "shapes" / "bennu_radar_nolan2013_sbgat.obj"
S = 1e-3  # voxel and node spacing, km
Z0 = 0.2503  # plane of the flat maplets, km


@pytest.fixture(scope="module")
def bennu() -> Mesh:
    """The radar shape refined to ~6 m facets, with a uniform albedo."""
    b = read_obj(BENNU)
    v, f = subdivide_loop(b.vertices, b.faces, iterations=2)
    return Mesh(v, f, np.full(len(v), 0.044))


def flat(name: str, x0: float, height: float, albedo: float, weight: float, n: int = 21) -> MapletGrid:
    """A maplet on the plane z = Z0 + height, axes along the body axes, its nodes at voxel centres."""
    frame = LocalFrame(origin=np.array([x0 + S / 2, S / 2, Z0]), rotation=np.eye(3))
    return MapletGrid(name=name, frame=frame, spacing_km=S, heights=np.full((n, n), height),
                      albedo=np.full((n, n), albedo), weight=weight)


def test_taper_cross_fades_maplets_that_overlap_by_the_fraction():
    n, fraction = 21, 0.25
    t = edge_taper(n, S, fraction)
    assert t[10, 10] == 1.0 and np.allclose(t, t.T) and np.allclose(t, t[::-1])
    assert 0.0 < t[10, 0] < 0.05 and np.all(np.diff(t[10, :11]) >= 0)
    # neighbours 15 spacings apart (a quarter of the 20-spacing side shared): weights sum to 1
    assert np.allclose(t[10, 15:] + t[10, :6], 1.0)


def test_overlap_is_the_weighted_average_and_each_maplet_rules_alone():
    a = flat("A", 0.0, 0.0, 0.04, 1.0)
    b = flat("B", 15 * S, 0.4 * S, 0.06, 0.5)
    grid = VoxelGrid(S)
    grid.add(a)
    grid.add(b)
    fused = grid.points()
    # every voxel holds one node of A, of B, or of each
    x = (fused.points[:, 0] - S / 2) / S
    assert len(fused.points) == 21 * 36 and np.allclose(x, np.round(x))
    j = np.round(x).astype(int) + 10
    i = np.round((fused.points[:, 1] - S / 2) / S).astype(int) + 10
    ta, tb = edge_taper(21, S, 0.25), 0.5 * edge_taper(21, S, 0.25)
    wa = np.where(j <= 20, ta[i, np.minimum(j, 20)], 0.0)
    wb = np.where(j >= 15, tb[i, np.maximum(j - 15, 0)], 0.0)
    assert np.allclose(fused.points[:, 2], Z0 + 0.4 * S * wb / (wa + wb), rtol=0, atol=1e-15)
    assert np.allclose(fused.albedo, (0.04 * wa + 0.06 * wb) / (wa + wb), rtol=1e-12)
    assert np.all(fused.points[j < 15, 2] == Z0) and np.allclose(fused.points[j > 20, 2], Z0 + 0.4 * S, atol=1e-15)
    overlap = (j >= 15) & (j <= 20)
    assert np.all((fused.points[overlap, 2] > Z0) & (fused.points[overlap, 2] < Z0 + 0.4 * S))

    # the mesh over the plane: the same heights and albedo at its vertices, and no holes
    mesh = grid.mesh(frame=LocalFrame(origin=np.zeros(3), rotation=np.eye(3)))
    order = np.lexsort((fused.points[:, 1], fused.points[:, 0]))
    again = np.lexsort((mesh.vertices[:, 1], mesh.vertices[:, 0]))
    assert np.allclose(mesh.vertices[again], fused.points[order], atol=1e-15)
    assert np.allclose(mesh.albedo[again], fused.albedo[order])
    rng = np.random.default_rng(0)
    xy = np.column_stack([rng.uniform(-10 * S, 25 * S, 5000), rng.uniform(-10 * S, 10 * S, 5000)]) + S / 2
    origins = np.column_stack([xy, np.full(len(xy), 1.0)])
    hits = RayTracer(mesh).intersect(origins, np.broadcast_to([0.0, 0.0, -1.0], origins.shape))
    assert hits.hit.all()
    assert np.all((1.0 - hits.t >= Z0 - 1e-7) & (1.0 - hits.t <= Z0 + 0.4 * S + 1e-7))  # float32 hits


def test_replacing_a_maplet_equals_fusing_afresh():
    a = flat("A", 0.0, 0.0, 0.04, 1.0)
    b = flat("B", 15 * S, 0.4 * S, 0.06, 0.5)
    b_new = flat("B", 15 * S, 0.2 * S, 0.05, 0.8)
    b_new.heights[5:9, 3:12] += 1.5 * S  # a boulder: voxels B never had
    incremental = VoxelGrid(S)
    for m in (a, b):
        incremental.add(m)
    incremental.subtract(b)
    incremental.add(b_new)
    fresh = VoxelGrid(S)
    for m in (a, b_new):
        fresh.add(m)
    assert np.array_equal(incremental.keys, fresh.keys) and np.array_equal(incremental.count, fresh.count)
    assert np.allclose(incremental.sums, fresh.sums, rtol=1e-12, atol=1e-15)
    assert np.allclose(incremental.points().points, fresh.points().points, rtol=0, atol=1e-12)
    with pytest.raises(ValueError):
        incremental.subtract(b)  # that revision is gone


def test_site_fusion_has_no_holes_and_carries_albedo(bennu):
    maplets = tile(bennu, spacing_km=5e-4, nodes=31, centre_lat_deg=12.0, centre_lon_deg=60.0, radius_km=0.02)
    rng = np.random.default_rng(4)
    for k, m in enumerate(maplets):
        m.albedo = np.full_like(m.heights, 0.03 + 0.002 * (k % 10))
        m.heights = m.heights + 2e-5 * rng.standard_normal(m.heights.shape)  # refinements disagree by 2 cm
        m.weight = 0.5 + 0.5 * rng.random()
    grid = VoxelGrid(5e-4)
    for m in maplets:
        grid.add(m)
    fused = grid.mesh(bennu)
    assert fused.albedo is not None and len(fused.albedo) == len(fused.vertices)
    assert np.all(fused.face_areas() > 0) and fused.faces.max() < len(fused.vertices)
    tracer = RayTracer(fused)

    # rays down onto the site, inside and across the border of the fused region, all hit ...
    centre = latlon_to_unit(12.0, 60.0)
    frame = maplets[len(maplets) // 2].frame
    xy = rng.uniform(-0.05, 0.05, (30000, 2))
    origins = frame.to_body(np.column_stack([xy, np.full(len(xy), 0.05)]))
    down = np.broadcast_to(-frame.normal, origins.shape)
    hits = tracer.intersect(origins, down)
    assert hits.hit.all()
    # ... on the fused surface, which follows the maplets (the base within mm of them)
    base_t = RayTracer(bennu).intersect(origins, down).t
    assert np.abs(hits.t - base_t).max() < 2e-4
    site = np.hypot(*xy.T) < 0.015
    albedo = tracer.interpolate(fused.albedo, hits)
    assert np.all((albedo[site] >= 0.03 - 1e-9) & (albedo[site] <= 0.048 + 1e-9))
    assert np.allclose(albedo[np.hypot(*xy.T) > 0.045], 0.044)  # the base beyond the maplets
    # and so do rays from everywhere around the body: the stitch leaves no gap
    d = rng.normal(size=(50000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d = np.vstack([d, centre + 0.15 * rng.normal(size=(20000, 3))])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    assert tracer.intersect(d, -d).hit.all()


def test_whole_body_fusion_is_a_closed_surface():
    bennu = read_obj(BENNU)
    maplets = tile(bennu, spacing_km=0.006, nodes=11)
    grid = VoxelGrid(0.006)
    for m in maplets:
        grid.add(m)
    mesh = grid.mesh()
    assert mesh.albedo is None
    # closed and oriented: every edge in two faces, once each way; genus 0
    edges = np.stack([mesh.faces, np.roll(mesh.faces, -1, axis=1)], axis=2).reshape(-1, 2)
    assert len(np.unique(edges, axis=0)) == len(edges)
    assert len(np.unique(np.sort(edges, axis=1), axis=0)) * 2 == len(edges)
    assert len(mesh.vertices) - len(edges) // 2 + len(mesh.faces) == 2
    # outward: positive volume, close to the body's
    tri = mesh.vertices[mesh.faces]
    volume = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6
    tri = bennu.vertices[bennu.faces]
    assert volume == pytest.approx(np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6, rel=0.02)
