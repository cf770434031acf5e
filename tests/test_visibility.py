"""Occlusion and shadows by Embree, checked against an exact float64 ray-triangle test."""

from __future__ import annotations

import gc
import weakref
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
import trimesh

from pwm.frames import latlon_to_unit, local_frame
from pwm.mesh import Mesh
from pwm.photometry import angles
from pwm.raytrace import RayTracer
from pwm.visibility import node_visibility

M = 1e-3  # km
BOXES = [((-2.0, 1.0), (1.5, 2.0, 2.5)), ((2.5, -1.5), (2.0, 1.0, 1.5)), ((0.5, -3.0), (1.0, 1.0, 3.0))]
"""Box centres (x, y) and extents (x, y, z) in metres on the ground of the scene."""


@pytest.fixture(scope="module")
def scene():
    """A 10 m ground grid with three boxes, placed on the surface of a 250 m body at (30N, 40E)
    so that coordinates have body-centred magnitudes; boxes sink 0.1 m into the ground."""
    n = 21
    axis = np.linspace(-5.0, 5.0, n)
    x, y = np.meshgrid(axis, axis)
    verts = [np.column_stack([x.ravel(), y.ravel(), np.zeros(n * n)])]
    c = np.arange(n * n).reshape(n, n)[:-1, :-1].ravel()
    faces = [np.vstack([np.column_stack([c, c + 1, c + n + 1]), np.column_stack([c, c + n + 1, c + n])])]
    offset = n * n
    for (bx, by), (ex, ey, ez) in BOXES:
        box = trimesh.creation.box(bounds=[[bx - ex / 2, by - ey / 2, -0.1], [bx + ex / 2, by + ey / 2, ez]])
        verts.append(box.vertices)
        faces.append(box.faces + offset)
        offset += len(box.vertices)
    frame = local_frame(0.25 * latlon_to_unit(30.0, 40.0), latlon_to_unit(30.0, 40.0))
    return Mesh(frame.to_body(np.vstack(verts) * M), np.vstack(faces)), frame


def surface_points(mesh: Mesh, rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """n random points on the faces (area-weighted) with their face normals; those on the ground
    inside a box see nothing."""
    area = mesh.face_areas()
    face = rng.choice(len(mesh.faces), size=n, p=area / area.sum())
    r1, r2 = rng.random((2, n))
    s = np.sqrt(r1)
    tri = mesh.vertices[mesh.faces[face]]
    p = (1 - s)[:, None] * tri[:, 0] + (s * (1 - r2))[:, None] * tri[:, 1] + (s * r2)[:, None] * tri[:, 2]
    return p, mesh.face_normals()[face]


def directions(frame, angles_deg: list[tuple[float, float]]) -> np.ndarray:
    """Body-fixed unit vectors at (angle from the frame's z, azimuth from y towards x), degrees."""
    a, b = np.radians(np.array(angles_deg, float)).T
    local = np.column_stack([np.sin(a) * np.sin(b), np.sin(a) * np.cos(b), np.cos(a)])
    return frame.to_body(local) - frame.origin


def brute_force(tri: np.ndarray, origins: np.ndarray, dirs: np.ndarray, t_max: np.ndarray,
                tol_bary: float = 1e-4, tol_t: float = 2e-7) -> tuple[np.ndarray, np.ndarray]:
    """Moller-Trumbore in float64 over all triangles: (blocked, ambiguous) per ray, where ambiguous
    rays pass within tol_bary (barycentric) of an edge or meet a triangle within tol_t (km) of
    their ends, so that single precision may decide either way."""
    v0, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    blocked = np.zeros(len(origins), dtype=bool)
    ambiguous = np.zeros(len(origins), dtype=bool)
    for s in range(0, len(origins), 256):
        o, d, tm = origins[s:s + 256, None], dirs[s:s + 256, None], t_max[s:s + 256, None]
        pvec = np.cross(d, e2)
        det = np.einsum("rtk,tk->rt", pvec, e1)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / det
            tvec = o - v0
            u = np.einsum("rtk,rtk->rt", tvec, pvec) * inv
            qvec = np.cross(tvec, e1)
            v = np.einsum("rtk,rtk->rt", d, qvec) * inv
            t = np.einsum("tk,rtk->rt", e2, qvec) * inv
        edge = np.minimum(np.minimum(u, v), 1 - u - v)
        ok = np.isfinite(t)
        blocked[s:s + 256] = (ok & (edge >= 0) & (t > 0) & (t < tm)).any(axis=1)
        near_edge = ok & (np.abs(edge) <= tol_bary) & (t > -tol_t) & (t < tm + tol_t)
        near_end = ok & (edge >= -tol_bary) & ((np.abs(t) <= tol_t) | (np.abs(t - tm) <= tol_t))
        ambiguous[s:s + 256] = (near_edge | near_end).any(axis=1)
    return blocked, ambiguous


def test_occlusion_and_shadows_match_exact_ray_tests(scene):
    mesh, frame = scene
    tracer = RayTracer(mesh)
    rng = np.random.default_rng(5)
    points, normals = surface_points(mesh, rng, 900)
    cams = frame.origin + 1.5 * directions(frame, [(0, 0), (30, 20), (50, 110), (60, 200), (45, 300)])
    sun = directions(frame, [(20, 0), (45, 80), (60, 160), (70, 250), (80, 330)])
    vis = node_visibility(tracer, points, normals, camera_positions=cams, sun_directions=sun)

    origins = points + tracer.offset * normals
    tri = mesh.vertices[mesh.faces]
    to_cam = cams[:, None] - origins[None]
    dist = np.linalg.norm(to_cam, axis=2)
    blocked, amb_v = brute_force(tri, np.tile(origins, (len(cams), 1)), (to_cam / dist[..., None]).reshape(-1, 3),
                                 dist.ravel())
    view_ref = (vis.mu > 0) & ~blocked.reshape(dist.shape)
    in_shadow, amb_s = brute_force(tri, np.tile(origins, (len(sun), 1)), np.repeat(sun, len(points), axis=0),
                                   np.full(len(sun) * len(points), np.inf))
    lit_ref = (vis.mu0 > 0) & ~in_shadow.reshape(dist.shape)
    amb_v, amb_s = amb_v.reshape(dist.shape), amb_s.reshape(dist.shape)

    # the test has teeth: many rays are blocked by the boxes, many are clear
    facing_cam, facing_sun = vis.mu > 0, vis.mu0 > 0
    assert (facing_cam & ~view_ref).sum() > 100 and view_ref.sum() > 500
    assert (facing_sun & ~lit_ref).sum() > 100 and lit_ref.sum() > 500
    assert amb_v.mean() < 0.03 and amb_s.mean() < 0.03
    assert np.array_equal(vis.visible[~amb_v], view_ref[~amb_v])
    assert np.array_equal(vis.lit[~amb_s], lit_ref[~amb_s])
    # points facing away from the camera or the Sun are neither visible nor lit
    assert not vis.visible[~facing_cam].any() and not vis.lit[~facing_sun].any()


def test_angles_are_those_of_the_given_normals(scene):
    mesh, frame = scene
    tracer = RayTracer(mesh)
    points, normals = surface_points(mesh, np.random.default_rng(2), 150)
    cams = frame.origin + np.array([[0.3, 0.2, 1.0], [-0.5, 0.4, 0.8]])
    sun = np.array([[1.0, 0.5, 0.7], [0.1, -0.4, 2.0]])
    vis = node_visibility(tracer, points, normals, camera_positions=cams, sun_directions=sun)
    origins = points + tracer.offset * normals
    for k in range(2):
        to_cam = cams[k] - origins
        mu0, mu, phase = angles(normals, np.broadcast_to(sun[k] / np.linalg.norm(sun[k]), points.shape),
                                to_cam / np.linalg.norm(to_cam, axis=1, keepdims=True))
        assert np.allclose(vis.mu[k], mu) and np.allclose(vis.mu0[k], mu0) and np.allclose(vis.phase[k], phase)
    assert vis.visible.shape == vis.lit.shape == (2, len(points))


def test_tracers_of_one_mesh_share_its_scene_until_the_mesh_is_freed(scene):
    mesh, frame = scene
    first, again = RayTracer(mesh), RayTracer(mesh)
    assert again._scene is first._scene and again.vertex_normals is first.vertex_normals
    assert RayTracer(Mesh(mesh.vertices, mesh.faces))._scene is first._scene  # the same arrays
    other = Mesh(mesh.vertices.copy(), mesh.faces.copy())
    assert RayTracer(other)._scene is not first._scene
    down = np.broadcast_to(-frame.normal, (50, 3))
    starts = frame.to_body(np.column_stack([np.linspace(-4, 4, 50) * M, np.zeros(50), np.full(50, 5 * M)]))
    hits = [RayTracer(m).intersect(starts, down) for m in (mesh, mesh, other)]
    assert hits[0].hit.all() and all(np.array_equal(h.t, hits[0].t) for h in hits[1:])
    # the cache holds a scene for as long as its mesh lives, and no longer
    built = weakref.ref(RayTracer(other)._scene)
    gc.collect()
    assert built() is not None
    del other
    gc.collect()
    assert built() is None


def test_a_scene_is_built_once_for_threads_and_again_for_new_arrays(scene):
    mesh, _ = scene
    fresh = Mesh(mesh.vertices.copy(), mesh.faces.copy())
    with ThreadPoolExecutor(8) as pool:
        scenes = list(pool.map(lambda _: RayTracer(fresh)._scene, range(32)))
    assert all(s is scenes[0] for s in scenes)
    fresh.vertices = fresh.vertices + 1.0
    assert RayTracer(fresh)._scene is not scenes[0]
