"""A closed surface and what it encloses (pwm.evaluate.closure), kept closed by decimation
(pwm.decimate): the checks that exports and version statistics carry."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from pwm.decimate import decimate
from pwm.evaluate.closure import closure, mass_properties
from pwm.mesh import Mesh

RADII_KM = np.array([0.283, 0.271, 0.250])
CENTRE_KM = np.array([0.012, -0.007, 0.003])


def _ellipsoid(subdivisions: int = 5) -> Mesh:
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    return Mesh(np.asarray(sphere.vertices) * RADII_KM + CENTRE_KM, np.asarray(sphere.faces))


def _bumpy(subdivisions: int = 5) -> Mesh:
    """A closed body with relief on every scale down to its faces, and albedo."""
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    unit = np.asarray(sphere.vertices)
    rng = np.random.default_rng(0)
    radius = 0.25 * (1 + 0.05 * np.sin(7 * unit[:, 0]) * np.cos(5 * unit[:, 1]) + 0.002 * rng.normal(size=len(unit)))
    return Mesh(unit * radius[:, None], np.asarray(sphere.faces), 0.04 + 0.01 * unit[:, 2])


def test_mass_properties_are_the_enclosed_bodys():
    mesh = _ellipsoid()
    mass = mass_properties(mesh)
    a, b, c = RADII_KM
    volume = 4 / 3 * np.pi * a * b * c
    # the polyhedron is inscribed: a little smaller than the ellipsoid, and trimesh's own figures
    assert mass.volume_km3 == pytest.approx(volume, rel=5e-3) and mass.volume_km3 < volume
    np.testing.assert_allclose(mass.centre_km, CENTRE_KM, atol=1e-6)
    expected = volume / 5 * np.diag([b * b + c * c, a * a + c * c, a * a + b * b])
    np.testing.assert_allclose(mass.inertia_km5, expected, rtol=1e-2, atol=1e-3 * expected.max())
    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    assert mass.volume_km3 == pytest.approx(tm.volume, rel=5e-3)
    assert mass.area_km2 == pytest.approx(tm.area, rel=5e-3)
    np.testing.assert_allclose(mass.inertia_km5, tm.moment_inertia, rtol=5e-3, atol=1e-9)
    # an open surface encloses nothing
    with pytest.raises(ValueError, match="encloses no volume"):
        mass_properties(Mesh(mesh.vertices, mesh.faces[1:]))


def test_the_closure_checks_say_what_is_open():
    mesh = _ellipsoid(3)
    assert closure(mesh).closed and closure(mesh).describe() == "closed"
    holed = closure(Mesh(mesh.vertices, mesh.faces[1:]))
    assert (holed.boundary_edges, holed.components) == (3, 1)
    assert holed.describe() == "open: 3 boundary edges"
    island = trimesh.creation.icosphere(subdivisions=1, radius=0.01)
    apart = Mesh(np.vstack([mesh.vertices, np.asarray(island.vertices) + 1.0]),
                 np.vstack([mesh.faces, np.asarray(island.faces) + len(mesh.vertices)]))
    checks = closure(apart)
    assert checks.watertight and checks.components == 2 and not checks.closed
    assert checks.describe() == "open: 2 components"


@pytest.mark.parametrize("target", [5000, 600])
def test_decimation_keeps_a_closed_surface_closed_and_its_volume(target):
    mesh = _bumpy()
    before = mass_properties(mesh)
    decimated = decimate(mesh, target)
    checks = closure(decimated)
    assert checks.closed, checks
    assert abs(len(decimated.faces) - target) <= 0.1 * target
    after = mass_properties(decimated)
    # the collapse shrinks the body by 0.7% at 600 faces; the vertices moved out restore it
    assert after.volume_km3 == pytest.approx(before.volume_km3, rel=1e-3)
    np.testing.assert_allclose(after.centre_km, before.centre_km, atol=1e-3)
    assert decimated.albedo is not None and decimated.albedo.min() >= 0.03 and decimated.albedo.max() <= 0.05
