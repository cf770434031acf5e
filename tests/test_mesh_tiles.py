"""A mesh cut into tiles and joined back: every face in one tile, tiles of at most the size
asked for, vertices shared across the cuts at the same place, the very mesh back; stored and read
back exactly."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from pwm.io.mesh_tiles import read_tile, write_tile
from pwm.mesh import Mesh
from pwm.mesh_tiles import face_labels, face_parts, join, split


def _dumbbell() -> Mesh:
    """Two lobes joined by a neck, far from any ellipsoid, with albedo and a sigma unknown (NaN)
    over part of it, and one vertex of no face."""
    a = trimesh.creation.icosphere(subdivisions=4, radius=0.3)
    b = trimesh.creation.icosphere(subdivisions=4, radius=0.2)
    b.apply_translation([0.55, 0.0, 0.0])
    body = trimesh.util.concatenate([a, b])
    vertices = np.vstack([body.vertices, [[9.0, 9.0, 9.0]]])
    sigma = np.where(vertices[:, 0] > 0.1, 1e-5, np.nan)
    return Mesh(vertices, body.faces, albedo=0.05 + 0.01 * vertices[:, 1], sigma=sigma)


def test_the_tiles_part_the_faces_and_join_back_to_the_mesh():
    mesh = _dumbbell()
    tiles = split(mesh, max_faces=700)
    sizes = [len(t.faces) for t in tiles]
    assert max(sizes) <= 700
    # each face in exactly one tile
    labels = face_labels(tiles, faces=len(mesh.faces))
    assert (labels >= 0).all()
    assert sum(sizes) == len(mesh.faces)
    # bisection at the median: the tiles are nearly equal
    assert min(sizes) >= max(sizes) // 2
    # a vertex on a cut is in both tiles, at the same place
    for tile in tiles:
        np.testing.assert_array_equal(tile.mesh.vertices, mesh.vertices[tile.vertices])
        np.testing.assert_array_equal(tile.vertices[tile.mesh.faces], mesh.faces[tile.faces])
    shared = np.bincount(np.concatenate([t.vertices for t in tiles]), minlength=len(mesh.vertices))
    assert (shared >= 2).sum() > 0
    back = join(tiles, vertices=len(mesh.vertices), faces=len(mesh.faces))
    np.testing.assert_array_equal(back.vertices, mesh.vertices)
    np.testing.assert_array_equal(back.faces, mesh.faces)
    np.testing.assert_array_equal(back.albedo, mesh.albedo)
    np.testing.assert_array_equal(back.sigma, mesh.sigma)  # NaN where unknown, as given


def test_the_first_cut_is_across_the_widest_side():
    mesh = _dumbbell()
    centroids = mesh.vertices[mesh.faces].mean(axis=1)
    parts = face_parts(mesh, max_faces=len(mesh.faces) // 2)
    assert len(parts) == 2
    highest = [centroids[p, 0].max() for p in parts]
    lowest = [centroids[p, 0].min() for p in parts]
    assert min(highest) <= max(lowest)  # the two halves do not overlap along x


def test_a_tile_is_stored_exactly(tmp_path):
    mesh = _dumbbell()
    tile = split(mesh, max_faces=1000)[1]
    write_tile(tmp_path / "t.npz", tile)
    back = read_tile(tmp_path / "t.npz")
    for name in ("faces", "vertices"):
        np.testing.assert_array_equal(getattr(back, name), getattr(tile, name))
    np.testing.assert_array_equal(back.mesh.vertices, tile.mesh.vertices)
    np.testing.assert_array_equal(back.mesh.faces, tile.mesh.faces)
    np.testing.assert_array_equal(back.mesh.sigma, tile.mesh.sigma)


def test_tiles_that_leave_a_face_out_do_not_join():
    mesh = _dumbbell()
    tiles = split(mesh, max_faces=1000)
    with pytest.raises(ValueError, match="every face"):
        join(tiles[1:], vertices=len(mesh.vertices), faces=len(mesh.faces))
    with pytest.raises(ValueError, match="at least one face"):
        split(mesh, max_faces=0)
