"""Height change between versions: a known bump and a uniform rise are measured along the
local vertical, a boulder with near-vertical walls by its height, with the area changed, and
mapped to a PNG."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from pwm.compare import height_change
from pwm.io.meshio import write_obj
from pwm.mesh import Mesh, grid_faces
from service.db import session_scope
from service.diff import diff_versions
from service.versions import import_model

RADIUS_KM = 0.25


def _sphere(radius_km: float = RADIUS_KM) -> Mesh:
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=radius_km)
    return Mesh(np.asarray(sphere.vertices), np.asarray(sphere.faces))


def test_a_bump_is_measured_where_it_is():
    old = _sphere()
    up = old.vertices / np.linalg.norm(old.vertices, axis=1, keepdims=True)
    angle = np.arccos(np.clip(up @ [0.0, 0.0, 1.0], -1, 1))
    cap = angle < 0.2
    bump_m = np.where(cap, 0.5 * np.cos(angle / 0.2 * np.pi / 2) ** 2, 0.0)  # 0.5 m at the pole
    new = Mesh(old.vertices + up * bump_m[:, None] * 1e-3, old.faces)
    change = height_change(old, new, max_distance_km=0.005)
    assert change.compared.all()
    # Along the new normal the rise is the radial bump foreshortened by the slope (< 1%).
    np.testing.assert_allclose(change.change_m[~cap], 0.0, atol=1e-4)
    np.testing.assert_allclose(change.change_m[cap], bump_m[cap], rtol=0.02, atol=1e-3)
    assert change.max_abs_m() == pytest.approx(0.5, rel=1e-3)
    rising = change.changed(0.01)
    assert rising.any() and not (rising & ~cap).any()


def _plane(heights_m: np.ndarray, spacing_m: float) -> Mesh:
    """A grid of heights (m) on the plane z = 0.3 km (x, y, z in km), two triangles a cell."""
    ny, nx = heights_m.shape
    y, x = np.mgrid[0:ny, 0:nx] * spacing_m * 1e-3
    vertices = np.column_stack([x.ravel(), y.ravel(), 0.3 + heights_m.ravel() * 1e-3])
    return Mesh(vertices, grid_faces(ny, nx))


def test_a_boulder_with_steep_walls_changes_by_its_height():
    spacing_m, size = 0.1, 201
    flat = np.zeros((size, size))
    boulder = flat.copy()
    boulder[90:111, 90:111] = 1.0  # 2 m across, 1 m tall, walls of 84 deg between nodes
    old, new = _plane(flat, spacing_m), _plane(boulder, spacing_m)
    change = height_change(old, new, max_distance_km=0.005)
    # along each vertex's own normal a wall vertex would look metres away from the old plane
    own = new.vertex_normals()
    tilt = np.degrees(np.arccos(own[:, 2]))
    assert tilt.max() > 80
    # along the local vertical every vertex rises by its own height, walls included
    np.testing.assert_allclose(change.change_m[change.compared], boulder.ravel()[change.compared], atol=1e-4)
    # all but the grid's border, where a ray down may pass beside the old plane's edge
    inner = np.zeros((size, size), dtype=bool)
    inner[1:-1, 1:-1] = True
    assert change.compared[inner.ravel()].all() and change.max_abs_m() == pytest.approx(1.0, abs=1e-4)
    assert np.count_nonzero(change.changed(0.01)) == np.count_nonzero(boulder)


def test_diff_of_two_versions(catalog, tmp_path):
    write_obj(tmp_path / "old.obj", _sphere())
    write_obj(tmp_path / "new.obj", _sphere(RADIUS_KM + 1e-4))  # 0.1 m higher everywhere
    data = tmp_path / "data"
    with session_scope(catalog) as session:
        for name in ("old", "new"):
            import_model(session, data_dir=data, path=tmp_path / f"{name}.obj")
    png = tmp_path / "diff.png"
    with catalog() as session:
        diff = diff_versions(session, data_dir=data, old=1, new="latest", png=png)
        back = diff_versions(session, data_dir=data, old=2, new=1)
    assert (diff.old, diff.new) == (1, 2)
    assert diff.vertices_compared == diff.vertices_total == diff.vertices_changed
    assert diff.mean_m == pytest.approx(0.1, rel=1e-3) and diff.rms_m == pytest.approx(0.1, rel=1e-3)
    assert back.mean_m == pytest.approx(-0.1, rel=1e-3)
    assert diff.area_changed_m2 == pytest.approx(4 * np.pi * (RADIUS_KM * 1e3 + 0.1) ** 2, rel=0.01)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and diff.png == str(png)
